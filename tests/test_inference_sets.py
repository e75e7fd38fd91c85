"""Inference sets: the recording as source, the final checkpoint's shifted render as condition,
the true novel view as target (synthetic scenes), null where no truth is known."""

from __future__ import annotations

import json
import shutil
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from conftest import assert_a_drawing, picture, stage_params

from paradrive import geometry
from paradrive.data import PairDataset
from paradrive.video import decode_frames
from paradrive.manifest import publish, scene_rows
from paradrive.pairs import read_index, read_pairs
from paradrive.pipeline import StageRegistry, run_build

SCENE = "synthetic-demo-s7"


@pytest.fixture(scope="module")
def inference_build(smoke_build, tmp_path_factory):
    """The smoke scenes' inference set, from their existing fits, renders and clips (a copy of
    the data folder: a build writes its ledger and logs there)."""
    root = tmp_path_factory.mktemp("inference")
    data_dir = Path(shutil.copytree(smoke_build["data_dir"], root / "data", symlinks=True))
    config = StageRegistry().resolve("smoke", {"manifest": {"kind": "inference"}})
    report = run_build(config, smoke_build["scene_uris"], data_dir,
                       stages=["manifest"], manifests_dir=root / "manifests", build="infer")
    assert not report.failures(), [r.error for r in report.failures()]
    return {"dir": root / "manifests" / "infer", "config": config, "data_dir": data_dir,
            "training": smoke_build["build_dir"]}


def test_a_scene_without_a_fit_is_a_failed_scene_not_a_silent_omission(smoke_build, copy_tree, tmp_path):
    config = StageRegistry().resolve("smoke", {"manifest": {"kind": "inference"}})
    unfitted = "synthetic:demo?seed=5"   # never built in this data root
    report = run_build(config, smoke_build["scene_uris"] + [unfitted], copy_tree(smoke_build["data_dir"]),
                       stages=["manifest"], manifests_dir=tmp_path, build="infer")
    (failure,) = report.failures()
    assert failure.scene_id == "synthetic-demo-s5" and failure.stage == "manifest"
    assert "has not finished clip" in failure.error and "plain re-run" in failure.error
    assert report.exit_code == 3   # partial: the other scenes' rows are published
    assert {r["scene_id"] for r in read_pairs(tmp_path / "infer").to_pylist()} == {
        "synthetic-demo-s7", "synthetic-demo-s11"}


def test_one_row_per_camera_clip_and_offset(inference_build):
    render = inference_build["config"].params["render"]
    rows = read_pairs(inference_build["dir"]).to_pylist()
    per_camera = Counter((r["scene_id"], r["camera"]) for r in rows)
    expected = len(render["clips"]) * len(render["offsets_m"])
    assert expected == 24
    assert set(per_camera.values()) == {expected} and len(per_camera) == 2
    assert read_index(inference_build["dir"]).kind == "inference"
    final = render["source_checkpoint"]
    assert {r["condition_iteration"] for r in rows} == {final}
    assert {r["source_iteration"] for r in rows} == {None}


def test_source_is_the_recording_and_condition_the_final_shifted_render(inference_build):
    training = {r["pair_id"]: r for r in read_pairs(inference_build["training"]).to_pylist()}
    for row in read_pairs(inference_build["dir"]).to_pylist():
        # any training pair of the same clip and offset shares the videos, roles swapped
        twin = next(t for t in training.values() if t["scene_id"] == row["scene_id"] and
                    t["camera"] == row["camera"] and t["clip"] == row["clip"] and
                    t["offset_m"] == row["offset_m"])
        assert row["source_sha256"] == twin["target_sha256"]
        assert row["condition_sha256"] == twin["source_sha256"]


def test_rel_pose_maps_the_recorded_camera_into_the_novel_one(inference_build):
    clips = json.loads((inference_build["data_dir"] / "scenes" / SCENE / "clips" /
                        "clips.json").read_text())
    recorded = {(c["camera"], c["clip"]): geometry.as_pose(c["c2w"]) for c in clips["clips"]}
    rows = [r for r in read_pairs(inference_build["dir"]).to_pylist() if r["scene_id"] == SCENE]
    for row in rows:
        n = row["num_frames"]
        novel = np.asarray(row["target_c2w"]).reshape(n, 4, 4)
        rec = recorded[row["camera"], row["clip"]]
        rel = np.asarray(row["rel_pose"]).reshape(n, 4, 4)
        np.testing.assert_allclose(rel, np.linalg.inv(novel) @ rec, atol=1e-5)
        # a pure lateral shift: no rotation, a translation of |offset|
        np.testing.assert_allclose(rel[:, :3, :3], np.broadcast_to(np.eye(3), (n, 3, 3)), atol=1e-5)
        np.testing.assert_allclose(np.linalg.norm(rel[:, :3, 3], axis=1), abs(row["offset_m"]),
                                   atol=1e-4)


def test_targets_are_the_ray_casters_shifted_views(inference_build):
    from paradrive.ingest.synthetic import street_from_uri
    from paradrive.scene import load_scene
    from paradrive.uri import parse_uri

    config = inference_build["config"]
    scene = load_scene(inference_build["data_dir"] / "scenes" / SCENE)
    street = street_from_uri(parse_uri(scene.source), config.typed("ingest"))
    ego = scene.ego2world()
    rows = [r for r in read_pairs(inference_build["dir"]).to_pylist() if r["scene_id"] == SCENE]
    for row in rows[::5]:  # a spread of clips and offsets
        frames = row["frame_indices"]
        shifted = geometry.lateral_shift(scene.c2w(row["camera"])[frames], ego[frames],
                                         row["offset_m"])
        fx, fy, cx, cy = row["intrinsics"]
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        truth = street.render(shifted, K, row["width"], row["height"], frames=frames)["rgb"]
        video = decode_frames(inference_build["dir"] / read_index(inference_build["dir"]).version
                              / row["target_uri"])
        assert np.array_equal(video, truth), row["pair_id"]
        assert row["condition_psnr"] is not None and row["condition_psnr"] > 10


def test_the_adapter_reads_rows_with_and_without_a_target(inference_build, tmp_path):
    sample = PairDataset(inference_build["dir"])[0]
    assert {"source", "condition", "target"} <= set(sample)
    # a real log's inference rows: the same scene published with no truth known
    rows, media, summary = scene_rows(inference_build["data_dir"] / "scenes" / SCENE,
                                      truth=lambda clip, offset, c2w: None)
    publish(tmp_path / "real", rows, media, scenes=[summary], skipped=[],
            params=stage_params("manifest", {"kind": "inference"}))
    table = read_pairs(tmp_path / "real").to_pylist()
    assert len(table) == 24 and {r["target_uri"] for r in table} == {None}
    sample = PairDataset(tmp_path / "real")[3]
    assert "target" not in sample and sample["source"].shape == sample["condition"].shape
    from paradrive.inspection import contact_sheet, verify_build

    assert verify_build(tmp_path / "real")["ok"]
    contact_sheet(tmp_path / "real", tmp_path / "sheet.png", pairs=1, frames=3, thumb_width=208)
    # the sheet shows the video frames: its first thumbnail (below the title and the pair's
    # header) is the decoded source frame, not the blank page
    first = table[0]
    th = int(round(208 * first["height"] / first["width"])) // 2 * 2
    sheet = picture(tmp_path / "sheet.png")
    assert sheet.shape[1] == 190 + 3 * (208 + 6) + 6
    thumb = sheet[6 + 18 + 26:6 + 18 + 26 + th, 190:190 + 208].astype(float)
    assert thumb.std() > 10.0 and len(np.unique(thumb.reshape(-1, 3), axis=0)) > 500


def videos_folder(build_dir, rows, role, folder):
    """Generated videos stand-ins: each row's ``role`` video linked as ``<pair_id><suffix>``."""
    import os

    version = read_index(build_dir).version   # URIs are relative to the published version
    for row in rows:
        src = build_dir / version / row[f"{role}_uri"]
        dst = folder / f"{row['pair_id']}{src.suffix}"
        dst.parent.mkdir(parents=True, exist_ok=True)
        os.link(src, dst)
    return folder


def test_eval_build_scores_the_targets_themselves_as_perfect(inference_build, tmp_path):
    from typer.testing import CliRunner

    from paradrive.cli import app

    rows = read_pairs(inference_build["dir"]).to_pylist()
    videos = videos_folder(inference_build["dir"], rows, "target", tmp_path / "videos")
    result = CliRunner().invoke(app, ["eval", "--build", str(inference_build["dir"]),
                                      "--videos", str(videos)], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    doc = json.loads((videos / "scores.json").read_text())
    assert len(doc["by_offset"]) == 8 and not doc["missing"]
    assert all(r["videos"] == 6 for r in doc["by_offset"])  # 2 scenes x 3 clips
    assert all(r["psnr"] >= 99.0 and r["ssim"] > 0.9999 for r in doc["by_offset"])
    assert_a_drawing(videos / "scores.png", 600, 300)


def test_eval_build_scores_the_conditions_as_eval_scores_the_final_checkpoint(inference_build,
                                                                             tmp_path):
    from paradrive.evaluation import evaluate_scene
    from paradrive.scoring.run import ScoreSettings, score_videos

    rows = [r for r in read_pairs(inference_build["dir"]).to_pylist() if r["scene_id"] == SCENE]
    videos = videos_folder(inference_build["dir"], rows, "condition", tmp_path / "videos")
    doc = score_videos(inference_build["dir"], videos, ScoreSettings(metrics=("psnr",)))
    assert len(doc["missing"]) == 24  # the other scene's rows
    params = inference_build["config"].params
    truth = evaluate_scene(inference_build["data_dir"] / "scenes" / SCENE,
                           inference_build["config"].typed("render"),
                           ingest_params=params["ingest"], max_frames=None,
                           out_dir=tmp_path / "eval")
    shifted = {r["offset_m"]: r for r in truth["cameras"]["front"]["shifted"]}
    for r in doc["by_offset"]:
        # the same renders and truth; the build's conditions went through H.264 once
        assert r["psnr"] == pytest.approx(shifted[r["offset_m"]]["psnr"], abs=0.5)
        assert r["ssim"] == pytest.approx(shifted[r["offset_m"]]["ssim"], abs=0.02)


def test_train_samples_an_inference_set_that_eval_build_scores(inference_build, smoke_build,
                                                              tmp_path):
    from typer.testing import CliRunner

    from paradrive.cli import app

    samples = tmp_path / "samples"
    result = CliRunner().invoke(app, [
        "train", "--build", str(smoke_build["build_dir"]), "--config", "smoke", "--stage", "1",
        "--out", str(tmp_path / "run"), "--steps", "1", "--sample", str(samples),
        "--sample-set", str(inference_build["dir"]), "--sample-steps", "1"])
    assert result.exit_code == 0, result.output
    ids = read_pairs(inference_build["dir"], ["pair_id"]).column("pair_id").to_pylist()
    assert sorted(p.relative_to(samples).as_posix() for p in samples.rglob("*.mp4")) == \
        sorted(f"{i}.mp4" for i in ids)
    scored = CliRunner().invoke(app, ["eval", "--build", str(inference_build["dir"]),
                                      "--videos", str(samples)], env={"COLUMNS": "200"})
    assert scored.exit_code == 0, scored.output
    doc = json.loads((samples / "scores.json").read_text())
    assert len(doc["rows"]) == len(ids)  # a one-step model: scored, far from perfect
    assert all(r["psnr"] < 40 for r in doc["by_offset"])
