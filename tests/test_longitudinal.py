"""Longitudinal pairs (``render.transform: longitudinal``): sources moved along the recorded
path by arc length, windows kept on the path, stream names tagged, rel_pose from the actual
poses, the transform in index.json and inspect, and eval scoring them against the truth."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from typer.testing import CliRunner

from paradrive import geometry
from paradrive.cli import app
from paradrive.contracts.records import IndexRecord
from paradrive.evaluation import evaluate_scene
from paradrive.pairs import read_index, read_pairs
from paradrive.pipeline import StageRegistry, run_build
from paradrive.scene import load_scene
from paradrive.streams import (plan_streams, source_clip_windows, source_stream, stream_transform)

SCENE = "synthetic:demo?seed=7"
SID = "synthetic-demo-s7"
LONG = {"transform": "longitudinal"}


def camera_path(n: int, step: float, curvature: float = 0.0) -> np.ndarray:
    """Cameras (n, 4, 4) every ``step`` m along a circle arc (a line at curvature 0) in the ground
    plane, 1.5 m up, looking along it (OpenCV: x right, y down, z forward)."""
    s = step * np.arange(n)
    heading = curvature * s
    if curvature:
        xy = np.stack([np.sin(heading), 1 - np.cos(heading)], -1) / curvature
    else:
        xy = np.stack([s, np.zeros(n)], -1)
    forward = np.stack([np.cos(heading), np.sin(heading), np.zeros(n)], -1)
    right = np.stack([np.sin(heading), -np.cos(heading), np.zeros(n)], -1)
    down = np.broadcast_to([0.0, 0.0, -1.0], (n, 3))
    return geometry.make_pose(np.stack([right, down, forward], -1), np.concatenate([xy, np.full((n, 1), 1.5)], -1))


def test_a_longitudinal_source_lies_on_the_path_at_the_arc_length_ahead():
    path = camera_path(30, 0.7, curvature=0.02)
    arc = geometry.arc_length(path)
    ahead = 2.5 * arc[1]   # two and a half steps (chords of the arc)
    shifted, on_path = geometry.longitudinal_shift(path, ahead)
    want = arc + ahead
    assert np.array_equal(on_path, want <= arc[-1] + 1e-9)
    for axis in range(3):   # centres on the polyline, interpolated by arc length
        expected = np.interp(want[on_path], arc, path[:, axis, 3])
        assert np.abs(shifted[on_path, axis, 3] - expected).max() < 1e-9
    # halfway between two recorded rotations
    i = 3
    half = geometry.relative_pose(path[i + 2], path[i + 3])[:3, :3]
    between = geometry.relative_pose(path[i + 2], shifted[i])[:3, :3]
    angle = np.arccos(np.clip((np.trace(half) - 1) / 2, -1, 1))
    assert np.arccos(np.clip((np.trace(between) - 1) / 2, -1, 1)) == pytest.approx(angle / 2, abs=1e-9)
    assert geometry.is_rigid(shifted).all()
    behind, on = geometry.longitudinal_shift(path, -2.0)
    assert not on[:2].any() and on[3:].all()
    assert np.array_equal(behind[~on], path[~on])


def test_source_streams_are_tagged_with_the_transform():
    assert source_stream(4.0, "longitudinal") == "source+long+4m"
    assert source_stream(-1.5, "longitudinal") == "source+long-1.5m"
    assert source_stream(4.0) == "source+4m"
    assert stream_transform("source+long+4m") == "longitudinal" and stream_transform("source+4m") == "lateral"
    names = [s.name for s in plan_streams([25], 300, [1.0, -1.0], "longitudinal")]
    assert names == ["target", "cond@000025", "source+long+1m", "source+long-1m"]


def test_clip_windows_move_inwards_so_no_source_runs_off_the_path():
    path = camera_path(30, 1.0)
    windows, skipped = source_clip_windows(path, 8, ["front", "middle", "rear"], [3.0, -2.0], "longitudinal")
    assert not skipped
    # frames 2..26 keep 2 m behind and 3 m ahead on the path
    assert [(w.name, w.start, w.stop) for w in windows] == [("front", 2, 10), ("middle", 10, 18),
                                                            ("rear", 19, 27)]
    lateral, _ = source_clip_windows(path, 8, ["front", "rear"], [3.0, -2.0], "lateral")
    assert [(w.start, w.stop) for w in lateral] == [(0, 8), (22, 30)]
    none, why = source_clip_windows(path, 28, ["front"], [3.0, -2.0], "longitudinal")
    assert none == [] and "on the recorded path (29.0 m) for 25 of its 30 frames (2..26), a clip needs 28" \
        in why[0]["reason"]


@pytest.fixture(scope="module")
def long_build(tmp_path_factory, request):
    """The smoke scene's fit, rendered, clipped and published with longitudinal sources."""
    smoke = request.getfixturevalue("smoke_scene")
    root = tmp_path_factory.mktemp("longitudinal")
    shutil.copytree(smoke["data_dir"], root / "data", symlinks=True)
    config = StageRegistry().resolve("smoke", {"render": LONG})
    report = run_build(config, [SCENE], root / "data", manifests_dir=root / "m", build="long")
    assert not report.failures(), [r.error for r in report.failures()]
    statuses = {r.stage: r.status for r in report.results}
    assert statuses["fit"] == "skipped"   # the same fit makes both kinds of pairs
    return {"config": config, "data": root / "data", "build": root / "m" / "long"}


def test_longitudinal_pairs_have_rel_pose_along_the_path(long_build):
    offsets = long_build["config"].params["render"]["longitudinal_offsets_m"]
    cols = read_pairs(long_build["build"], ["offset_m", "source_stream", "rel_pose", "target_c2w",
                                            "frame_start", "num_frames"]).to_pydict()
    assert sorted(set(cols["offset_m"])) == sorted(offsets)
    assert {stream_transform(s) for s in cols["source_stream"]} == {"longitudinal"}
    path = load_scene(long_build["data"] / "scenes" / SID).c2w("front")
    arc = geometry.arc_length(path)
    for i, d in enumerate(cols["offset_m"]):
        assert cols["source_stream"][i] == source_stream(d, "longitudinal")
        frames = range(cols["frame_start"][i], cols["frame_start"][i] + cols["num_frames"][i])
        target = np.asarray(cols["target_c2w"][i]).reshape(-1, 4, 4)
        assert np.abs(target - path[list(frames)]).max() < 1e-9
        want = arc[list(frames)] + d
        assert (want >= 0).all() and (want <= arc[-1]).all()   # every source on the recorded path
        centres = np.stack([np.interp(want, arc, path[:, a, 3]) for a in range(3)], -1)
        expected = np.einsum("nji,nj->ni", target[:, :3, :3], centres - target[:, :3, 3])
        rel = np.asarray(cols["rel_pose"][i], dtype=np.float64).reshape(-1, 4, 4)
        assert np.abs(rel[:, :3, 3] - expected).max() < 1e-4
        # the street is straight: the move is the camera's own forward direction, |d| long
        assert np.abs(rel[:, 0, 3]).max() < 1e-4
        assert np.abs(np.linalg.norm(rel[:, :3, 3], axis=-1) - abs(d)).max() < 1e-4
        assert (np.sign(rel[:, 2, 3]) == np.sign(d)).all()


def test_the_transform_is_in_index_json_and_inspect(long_build):
    index = IndexRecord.model_validate(json.loads((long_build["build"] / "index.json").read_text()))
    assert [s.transform for s in index.scenes] == ["longitudinal"]
    result = CliRunner().invoke(app, ["inspect", str(long_build["build"])])
    assert result.exit_code == 0, result.output
    assert "longitudinal sources" in " ".join(result.output.split())


def test_eval_scores_longitudinal_sources_against_the_truth_per_offset(long_build, tmp_path):
    config = long_build["config"]
    doc = evaluate_scene(long_build["data"] / "scenes" / SID, config.typed("render"), max_frames=4,
                         out_dir=tmp_path)
    rows = doc["cameras"]["front"]["shifted"]
    assert [r["offset_m"] for r in rows] == config.params["render"]["longitudinal_offsets_m"]
    assert {r["stream"] for r in rows} == {source_stream(r["offset_m"], "longitudinal") for r in rows}
    assert all(r["transform"] == "longitudinal" for r in rows)
    psnr = {r["offset_m"]: r["psnr"] for r in rows}
    # a step along the road sees what the fit saw from a neighbouring recorded frame
    assert min(psnr.values()) > 18.0, psnr
    assert json.loads((tmp_path / "eval.json").read_text())["cameras"]["front"]["shifted"] == rows


def test_the_plan_counts_the_longitudinal_pairs_the_build_made(long_build):
    """Sources kept on the path: the plan lays the windows as render does, for an ingested scene
    and for its URI alone, and counts fewer pairs than the lateral plan where the path is short."""
    from paradrive.pipeline.budget import plan_build

    rows = read_index(long_build["build"]).totals.rows
    config = long_build["config"]
    assert plan_build(config, [SCENE], long_build["data"]).pairs == rows
    assert plan_build(config, [SCENE], None).pairs == rows
    short = "synthetic:demo?seed=7&frames=16"   # 12 m: +-4 m keeps frames 5..10 on the path
    lateral = plan_build(StageRegistry().resolve("smoke"), [short], None)
    moved = plan_build(StageRegistry().resolve("smoke", {"render": LONG}), [short], None)
    assert lateral.pairs > 0 and moved.pairs < lateral.pairs and not lateral.unfit
    assert list(moved.unfit) == ["synthetic-demo-s7-frames16"]
    assert "for 6 of its 16 frames (5..10), a clip needs 9" in moved.unfit["synthetic-demo-s7-frames16"]


def test_a_scene_too_short_for_its_longitudinal_windows_fails_before_its_fit(tmp_path):
    # 10 frames at 0.8 m: ±4 m keeps only frames 5..4 on the path, so no 9-frame clip
    result = CliRunner().invoke(app, [
        "build", "--profile", "smoke", "--scene", SCENE, "--set", "ingest.synthetic_frames=10",
        "--set", "ingest.synthetic_width=48", "--set", "ingest.synthetic_height=32",
        "--set", "render.transform=longitudinal", "--stages", "ingest,fit",
        "--data", str(tmp_path / "data"), "--manifests", str(tmp_path / "m")])
    assert result.exit_code != 0, result.output
    text = " ".join(result.output.split())
    assert "camera front: its longitudinal sources stay on the recorded path (7.2 m) for 0 of its 10 " \
        "frames, a clip needs 9" in text
    assert "smaller render.longitudinal_offsets_m" in text
    (scene_dir,) = (tmp_path / "data" / "scenes").iterdir()
    assert not (scene_dir / "gs").exists()
