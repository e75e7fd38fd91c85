"""``paradrive inspect``: counts, quality, --verify, --json and the pictures."""

from __future__ import annotations

import json
import os
import shutil

import numpy as np
import pytest

from conftest import stage_params
import typer
from typer.testing import CliRunner

from paradrive.commands.inspect import register
from paradrive.inspection import sheet_labels, summarize, verify_build
from paradrive.stages.manifest import build_manifest
from paradrive.pairs import read_index
from test_manifest import scenes_entry, write_clip_scene


@pytest.fixture(scope="module")
def build(tmp_path_factory):
    data = tmp_path_factory.mktemp("data")
    scenes = [write_clip_scene(data, "synthetic-a"),
              write_clip_scene(data, "synthetic-b", clips=("middle",))]
    lidar = scenes[0] / "lidar"
    lidar.mkdir()
    rng = np.random.default_rng(0)
    np.save(lidar / "000000.npy", (rng.uniform([-5, -12, -1], [30, 12, 3], (4000, 3))).astype(np.float32))
    build_dir = tmp_path_factory.mktemp("manifests") / "b"
    build_manifest(build_dir, [scenes_entry(s) for s in scenes], stage_params("manifest", {"media": "copy"}))
    return build_dir


def invoke(*args):
    # The command on an app of its own, as paradrive.cli registers it.
    app = typer.Typer()
    app.callback()(lambda: None)
    register(app)
    return CliRunner().invoke(app, ["inspect", *map(str, args)], env={"COLUMNS": "400"})


def test_summary_counts_by_every_key(build):
    s = summarize(build)
    assert s["rows"] == 72 + 24
    c = s["counts"]
    assert c["scene"] == {"synthetic-a": 72, "synthetic-b": 24}
    assert c["dataset"] == {"synthetic": 96} and c["camera"] == {"front": 96}
    assert c["clip"] == {"front": 24, "middle": 48, "rear": 24}
    assert c["offset"] == {k: 12 for k in ("-4m", "-3m", "-2m", "-1m", "+1m", "+2m", "+3m", "+4m")}
    assert c["checkpoint"] == {"000100": 32, "000500": 32, "001000": 32}
    q = s["quality"]["scenes"]["synthetic-a"]
    assert q["fit_train_psnr"] == pytest.approx(31.2)
    assert q["condition"]["000500"]["psnr"] == pytest.approx(20.0)


def test_cli_prints_tables(build):
    result = invoke(build)
    assert result.exit_code == 0, result.output
    for text in ("pairs by offset", "synthetic-b", "+4m", "001000", "fit PSNR"):
        assert text in result.output


def test_cli_json_is_machine_readable(build):
    result = invoke(build, "--json", "--verify")
    assert result.exit_code == 0, result.output
    doc = json.loads(result.stdout)
    assert doc["rows"] == 96 and doc["verify"]["ok"]
    assert doc["verify"]["checked_files"] == 1 + 12 * 3 + 12  # shard + videos


def test_verify_names_each_missing_or_corrupt_file(build, tmp_path):
    copy = tmp_path / "b"
    shutil.copytree(build, copy)
    corrupt = copy / read_index(copy).version / "media/synthetic-a/clips/front/rear/cond@000500.mp4"
    data = bytearray(corrupt.read_bytes())
    data[100] ^= 0x55
    corrupt.write_bytes(bytes(data))
    missing = copy / read_index(copy).version / "media/synthetic-b/clips/front/middle/source-3m.mp4"
    missing.unlink()
    result = invoke(copy, "--verify")
    assert result.exit_code == 1
    out = result.output.replace("\n", "")
    assert "cond@000500.mp4" in out and "source-3m.mp4" in out
    problems = verify_build(copy)["problems"]
    assert len(problems) == 2
    assert any(p.startswith("corrupt:") and str(corrupt) in p for p in problems)
    assert any(p.startswith("missing:") and str(missing) in p for p in problems)


def test_verify_checks_shards_against_the_index(build, tmp_path):
    copy = tmp_path / "b"
    shutil.copytree(build, copy)
    shard = copy / read_index(copy).version / read_index(copy).shards[0].file
    with open(shard, "r+b") as f:
        f.seek(20)
        f.write(b"\0\0\0\0")
    problems = verify_build(copy)["problems"]
    assert len(problems) == 1 and "pairs-00000.parquet" in problems[0] and "shard" in problems[0]


def test_not_a_build_is_a_usage_error(tmp_path):
    result = invoke(tmp_path)
    # rich wraps a long path at any space: compare without whitespace
    assert result.exit_code == 2 and "index.jsonismissing" in "".join(result.output.split())


def _rgb(path):
    from PIL import Image

    return np.asarray(Image.open(path).convert("RGB")).astype(int)


def test_sheet_and_trajectory_pictures(build, tmp_path):
    out = tmp_path / "sheet.png"
    result = invoke(build, "--sheet", out, "--pairs", "3")
    assert result.exit_code == 0, result.output
    sheet = _rgb(out)
    assert sheet.shape[0] > 3 * 3 * 40 and sheet.shape[1] > 3 * 150
    assert sheet.std() > 20  # thumbnails, not a blank page
    picture = _rgb(tmp_path / "sheet_trajectories.png")
    # The shifted paths are drawn in colour (blue left, red right), the recorded one in black.
    assert (np.abs(picture[..., 0] - picture[..., 2]) > 80).sum() > 500
    assert (tmp_path / "sheet_rig.png").is_file() and "sheet_rig.png" in result.output
    assert not [p for p in os.listdir(tmp_path) if ".tmp-" in p]


def test_sheet_labels_say_moved_for_a_longitudinal_source_and_shifted_for_a_lateral_one():
    row = {"offset_m": 4.0, "source_iteration": 7500, "condition_iteration": 100,
           "source_stream": "source+long+4m", "condition_stream": "cond@000100"}
    assert sheet_labels(row, "pairs")[0] == ("source", "moved +4m", "ckpt 7500")
    lateral = {**row, "offset_m": -2.0, "source_stream": "source-2m"}
    assert sheet_labels(lateral, "pairs")[0] == ("source", "shifted -2m", "ckpt 7500")
    # an inference set: the condition is the moved render, the target the true moved view
    inference = {**row, "source_stream": "target", "condition_stream": "source+long+4m"}
    assert [line for _, line, _ in sheet_labels(inference, "inference")] == [
        "recorded camera", "moved +4m", "true view, moved +4m"]


def test_the_plan_is_framed_on_the_paths_with_the_legend_outside_and_nothing_cut(build, tmp_path):
    from PIL import Image

    from paradrive.inspection import trajectories_picture

    out = trajectories_picture(build, tmp_path / "plan.png", scene_id="synthetic-a")
    picture = _rgb(out)
    h, w = picture.shape[:2]
    info = Image.open(out).info
    left, top, right, bottom = json.loads(info["plot_box"])
    l2, t2, r2, b2 = json.loads(info["legend_box"])
    # The plot fills most of the picture; the legend lies outside it, inside the picture.
    assert right - left > 0.85 * w and bottom - top > 0.6 * h
    assert t2 >= bottom and 0 <= l2 < r2 <= w and b2 <= h
    # Nothing touches the picture's edge: no label or tick is cut.
    edge = np.concatenate([picture[:2].reshape(-1, 3), picture[-2:].reshape(-1, 3),
                           picture[:, :2].reshape(-1, 3), picture[:, -2:].reshape(-1, 3)])
    assert (edge >= 250).all()
    # The paths (black, blue, red pixels inside the frame of the plot) span most of it both ways.
    plot = picture[top + 3:bottom - 3, left + 3:right - 3]
    black = plot.max(axis=-1) < 40
    blue = plot[..., 2] - plot[..., 0] > 80
    rows, cols = np.nonzero(black | blue | (plot[..., 0] - plot[..., 2] > 80))
    assert np.ptp(cols) > 0.8 * plot.shape[1] and np.ptp(rows) > 0.6 * plot.shape[0]
    # Equal aspect: a metre is as many pixels across (the +1..+4 m paths) as along (the clips
    # of the fixture start 8 m apart: 8 frames at 1 m a frame).
    blue_rows = np.unique(np.nonzero(blue)[0])
    lanes = np.split(blue_rows, np.nonzero(np.diff(blue_rows) > 3)[0] + 1)
    assert len(lanes) == 4
    across = float(np.mean(np.diff([np.mean(lane) for lane in lanes])))
    black_cols = np.unique(np.nonzero(black)[1])
    starts = black_cols[np.r_[0, np.nonzero(np.diff(black_cols) > 3)[0] + 1]]
    assert len(starts) == 3
    along = float(np.mean(np.diff(starts))) / 8.0
    assert across > 20 and along == pytest.approx(across, rel=0.05)


def test_the_rig_picture_shows_left_shifted_cameras_left_of_the_recorded_one(build, tmp_path):
    from paradrive.inspection import rig_picture

    picture = _rgb(rig_picture(build, tmp_path / "rig.png", scene_id="synthetic-a"))
    assert picture.shape[:2] == (700, 1200)
    lower = picture[picture.shape[0] // 3:]   # below the title and the legend
    blue = np.nonzero((lower[..., 2] - lower[..., 0] > 80) & (lower[..., 1] < 200))[1]
    red = np.nonzero((lower[..., 0] - lower[..., 2] > 80) & (lower[..., 1] < 200))[1]
    black = np.nonzero(lower.max(axis=-1) < 40)[1]
    assert len(blue) > 500 and len(red) > 500 and len(black) > 100
    # Seen from behind the rig, a shift to the left (+) lies left of the recorded camera.
    assert blue.mean() < black.mean() < red.mean()


def test_trajectory_picture_draws_actor_tracks_beside_the_camera_paths(build, tmp_path):
    from PIL import Image

    from paradrive.actors import Actor, box_pose
    from paradrive.inspection import trajectories_picture

    data = tmp_path / "data"
    (data / "scenes" / "synthetic-a").mkdir(parents=True)
    poses = np.stack([box_pose([5.0 + 2.0 * i, 3.5, 0.8], 0.0) for i in range(10)])
    car = Actor("t:car", "vehicle", True, np.array([4.5, 1.9, 1.6]), np.arange(10), poses)
    (data / "scenes" / "synthetic-a" / "scene.json").write_text(json.dumps({"actors": [car.to_json()]}))

    def orange_pixels(out, data_dir):
        trajectories_picture(build, out, scene_id="synthetic-a", data_dir=data_dir)
        picture = np.asarray(Image.open(out).convert("RGB")).astype(int)
        return (np.abs(picture - [242, 140, 0]).max(axis=-1) < 40).sum()

    assert orange_pixels(tmp_path / "with.png", data) > 100
    assert orange_pixels(tmp_path / "without.png", tmp_path / "nowhere") == 0
