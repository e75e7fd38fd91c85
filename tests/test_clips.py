"""Clip windows, stream names and the clip stage (real H.264 / FFV1 files through PyAV)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from conftest import stage_params

from paradrive import geometry
from paradrive.streams import ClipWindow, clip_windows, condition_stream, format_offset, frames_needed, source_stream
from paradrive.stages.clip import write_clips
from paradrive.errors import SceneError
from paradrive.io import sha256_file
from paradrive.pipeline import run_build
from paradrive.scene import load_scene, read_image
from video_probe import probe_video

from paradrive.video import decode_frames

from test_render import SCENE, SID, smoke_params


# --------------------------------------------------------------------------- windows (pure)

def test_paper_windows_for_a_200_frame_segment():
    windows, skipped = clip_windows(200, 121, ["front", "middle", "rear"])
    assert skipped == []
    assert [(w.name, w.start, w.stop) for w in windows] == [
        ("front", 0, 121), ("middle", 39, 160), ("rear", 79, 200)]


@pytest.mark.parametrize("n, f, starts", [(24, 8, [0, 8, 16]), (8, 8, [0, 0, 0]),
                                          (9, 8, [0, 0, 1]), (10, 3, [0, 3, 7])])
def test_window_starts(n, f, starts):
    windows, _ = clip_windows(n, f, ["front", "middle", "rear"])
    assert [w.start for w in windows] == starts
    assert all(w.num_frames == f and w.stop <= n for w in windows)


def test_short_scene_skips_every_clip_with_a_reason():
    windows, skipped = clip_windows(90, 121, ["front", "middle", "rear"])
    assert windows == []
    assert skipped == [{"clip": c, "reason": "scene has 90 frames, a clip needs 121"}
                       for c in ("front", "middle", "rear")]


def test_subset_order_and_bad_names():
    windows, _ = clip_windows(30, 10, ["rear", "front"])
    assert [w.name for w in windows] == ["rear", "front"]
    with pytest.raises(ValueError, match="'centre'"):
        clip_windows(30, 10, ["centre"])
    with pytest.raises(ValueError, match="positive"):
        clip_windows(30, 0, ["front"])


def test_frames_needed_is_the_sorted_union():
    windows, _ = clip_windows(20, 12, ["front", "middle", "rear"])   # overlapping windows
    assert frames_needed(windows) == list(range(20))
    assert frames_needed([ClipWindow("rear", 5, 2), ClipWindow("front", 0, 2)]) == [0, 1, 5, 6]


def test_stream_names():
    assert [format_offset(d) for d in (1, -2.0, 0.5, -0.25, 4.0, 0.0)] == [
        "+1m", "-2m", "+0.5m", "-0.25m", "+4m", "+0m"]
    assert source_stream(-3.0) == "source-3m" and condition_stream(500) == "cond@000500"


# --------------------------------------------------------------------------- the stage

@pytest.fixture(scope="module")
def clipped(request, tmp_path_factory):
    """Smoke scene: front and rear clips of 4 frames, offsets +1 / -4 m, depth copied."""
    config = smoke_params(clips=["front", "rear"], clip_frames=4, offsets_m=[1.0, -4.0],
                          depth=True)
    config.params["clip"]["depth"] = True
    smoke = request.getfixturevalue("smoke_scene")
    root = tmp_path_factory.mktemp("clipped")
    shutil.copytree(smoke["data_dir"], root / "data")
    report = run_build(config, [SCENE], root / "data", stages=["render", "clip"])
    assert not report.failures(), report.failures()[0].error
    scene_dir = root / "data" / "scenes" / SID
    return {"dir": scene_dir, "doc": json.loads((scene_dir / "clips" / "clips.json").read_text()),
            "render": config.params["render"], "clip": config.params["clip"], "config": config}


def _stream_names(render_params) -> list[str]:
    return (["target"] + [condition_stream(i) for i in render_params["condition_checkpoints"]]
            + [source_stream(d) for d in render_params["offsets_m"]])


def test_every_stream_decodes_to_the_clip_frame_count_and_matches_its_checksum(clipped):
    doc = clipped["doc"]
    assert [(c["camera"], c["clip"], c["frame_start"]) for c in doc["clips"]] == [
        ("front", "front", 0), ("front", "rear", 20)]
    for clip in doc["clips"]:
        assert list(clip["streams"]) == _stream_names(clipped["render"])
        for name, s in clip["streams"].items():
            path = clipped["dir"] / s["file"]
            assert s["file"] == f"clips/front/{clip['clip']}/{name}.mp4"
            assert s["bytes"] == path.stat().st_size and s["sha256"] == sha256_file(path)
            info = probe_video(path)
            assert info["frames"] == clip["num_frames"] == 4
            assert (info["codec"], info["pix_fmt"], info["width"], info["height"]) == (
                "h264", "yuv420p", 160, 96)
            assert info["fps"] == pytest.approx(doc["fps"])


def test_decoded_frames_are_the_rendered_frames_in_order(clipped):
    clip = clipped["doc"]["clips"][1]
    for name in ("target", "source-4m"):
        decoded = decode_frames(clipped["dir"] / clip["streams"][name]["file"]).astype(int)
        pngs = np.stack([read_image(clipped["dir"] / "renders/front" / name / f"{i:06d}.png")
                         for i in range(clip["frame_start"], clip["frame_start"] + 4)]).astype(int)
        err = np.abs(decoded[:, None] - pngs[None]).mean(axis=(2, 3, 4))   # decoded x png
        assert np.array_equal(err.argmin(axis=1), np.arange(4)), err
        assert err.diagonal().max() < 6


def test_clips_json_describes_poses_timing_fit_and_quality(clipped):
    doc, scene_dir = clipped["doc"], clipped["dir"]
    scene = load_scene(scene_dir)
    renders = json.loads((scene_dir / "renders" / "renders.json").read_text())
    assert {k: doc[k] for k in ("schema_version", "scene_id", "dataset", "source", "width", "height")} == {
        "schema_version": 1, "scene_id": SID, "dataset": "synthetic", "source": SCENE,
        "width": 160, "height": 96}
    assert doc["fps"] == scene.fps
    assert doc["cameras"]["front"]["intrinsics"] == renders["cameras"]["front"]["intrinsics"]
    fit = json.loads((scene_dir / "gs" / "fit.json").read_text())
    final = [c for c in fit["checkpoints"] if c["iteration"] == clipped["render"]["source_checkpoint"]][0]
    assert doc["fit"] == {"iteration": final["iteration"], "train_psnr": final["psnr"],
                          "train_ssim": final["ssim"]}
    assert doc["skipped"] == []
    clip = doc["clips"][1]
    frames = list(range(20, 24))
    assert clip["frame_indices"] == frames
    assert clip["timestamps_us"] == scene.timestamps_us()[frames].tolist()
    recorded = scene.c2w("front")[frames]
    assert np.allclose(geometry.as_pose(clip["c2w"]), recorded)
    src = clip["streams"]["source-4m"]
    assert (src["kind"], src["offset_m"], src["iteration"]) == (
        "source", -4.0, clipped["render"]["source_checkpoint"])
    assert np.allclose(geometry.as_pose(src["c2w"]),
                       geometry.lateral_shift(recorded, scene.ego2world()[frames], -4.0))
    rel = geometry.relative_pose(geometry.as_pose(clip["c2w"]), geometry.as_pose(src["c2w"]))
    assert np.allclose(np.linalg.norm(rel[:, :3, 3], axis=1), 4.0)
    target = np.stack([read_image(scene_dir / "renders/front/target" / f"{i:06d}.png") for i in frames])
    psnrs = []
    for it in clipped["render"]["condition_checkpoints"]:
        s = clip["streams"][condition_stream(it)]
        assert (s["kind"], s["iteration"]) == ("condition", it)
        q = clip["quality"][condition_stream(it)]
        # the recorded quality is that of the condition's frames against the target's
        cond = np.stack([read_image(scene_dir / "renders/front" / condition_stream(it) / f"{i:06d}.png")
                         for i in frames])
        mse = ((cond.astype(np.float64) - target) / 255.0) ** 2
        assert q["psnr"] == pytest.approx(np.mean(10 * np.log10(1 / mse.mean(axis=(1, 2, 3)))), abs=1e-3)
        assert 0 < q["ssim"] <= 1
        psnrs.append(q["psnr"])
    assert psnrs == sorted(psnrs), psnrs   # a longer-fitted condition is closer to the target
    assert clip["streams"]["target"]["kind"] == "target"


def test_depth_sequences_are_copied_next_to_the_clips(clipped):
    from paradrive.exr import read_depth_exr

    clip = clipped["doc"]["clips"][0]
    folder = clipped["dir"] / "clips/front/front/depth/source+1m"
    assert sorted(p.name for p in folder.glob("*.exr")) == [f"{i:06d}.exr" for i in range(4)]
    assert clip["streams"]["source+1m"]["depth_dir"] == "clips/front/front/depth/source+1m"
    src = clipped["dir"] / "renders/front/source+1m/depth/000002.exr"
    assert np.array_equal(read_depth_exr(folder / "000002.exr"), read_depth_exr(src))
    assert "depth_dir" not in clip["streams"]["target"]


def test_ffv1_clips_are_lossless_mkv(clipped, copy_tree):
    scene_dir = copy_tree(clipped["dir"])
    write_clips(scene_dir, stage_params("clip", {**clipped["clip"], "codec": "ffv1", "depth": False}))
    doc = json.loads((scene_dir / "clips" / "clips.json").read_text())
    clip = doc["clips"][0]
    s = clip["streams"][f"cond@{clipped['render']['condition_checkpoints'][-1]:06d}"]
    assert s["file"].endswith(".mkv") and doc["codec"] == "ffv1"
    decoded = decode_frames(scene_dir / s["file"])
    name = s["file"].rsplit("/", 1)[1][:-4]
    pngs = np.stack([read_image(scene_dir / "renders/front" / name / f"{i:06d}.png") for i in range(4)])
    assert np.array_equal(decoded, pngs)
    assert not (scene_dir / "clips" / "front" / "front" / "depth").exists()   # the old set is replaced


@pytest.mark.parametrize("encoders", [1, 3])
def test_re_encoding_gives_identical_files(clipped, copy_tree, monkeypatch, encoders):
    """The same files, checksums, stream order and scores whether the streams are encoded one
    or several at a time, and the progress counts every stream once."""
    from paradrive.stages import clip as clip_stage

    monkeypatch.setattr(clip_stage, "ENCODERS", encoders)
    scene_dir = copy_tree(clipped["dir"])
    ticks: list[tuple[int, int]] = []
    write_clips(scene_dir, config_clip(clipped), progress=lambda done, total: ticks.append((done, total)))
    again = json.loads((scene_dir / "clips" / "clips.json").read_text())
    assert again == clipped["doc"]
    assert list(again["clips"][0]["streams"]) == list(clipped["doc"]["clips"][0]["streams"])
    total = sum(len(c["streams"]) for c in again["clips"])
    assert ticks == [(i, total) for i in range(1, total + 1)]
    assert not list(scene_dir.glob("**/.*.tmp-*"))


def test_clip_depth_needs_render_depth(clipped, copy_tree):
    scene_dir = copy_tree(clipped["dir"])
    doc = json.loads((scene_dir / "renders" / "renders.json").read_text())
    doc["depth"] = False
    (scene_dir / "renders" / "renders.json").write_text(json.dumps(doc))
    with pytest.raises(SceneError, match="render.depth=true"):
        write_clips(scene_dir, config_clip(clipped))
    assert (scene_dir / "clips" / "clips.json").read_text() == json.dumps(clipped["doc"], indent=2) + "\n"


def test_a_missing_render_names_the_file(clipped, copy_tree):
    scene_dir = copy_tree(clipped["dir"])
    (scene_dir / "renders/front/source+1m/000002.png").unlink()
    with pytest.raises(SceneError, match=r"source\+1m/000002.png"):
        write_clips(scene_dir, config_clip(clipped))
    # raised by an encoder thread: the old clip set stays, nothing half-written beside it
    assert json.loads((scene_dir / "clips" / "clips.json").read_text()) == clipped["doc"]
    assert not list(scene_dir.glob("**/.*.tmp-*"))


def test_short_scene_writes_no_clips_but_records_why(clipped, copy_tree):
    from paradrive.stages.render import render_scene

    scene_dir = copy_tree(clipped["dir"])
    render_scene(scene_dir, stage_params("render", {**clipped["render"], "clip_frames": 121,
                                                    "clips": ["front", "middle", "rear"]}))
    summary = write_clips(scene_dir, config_clip(clipped)).summary()
    doc = json.loads((scene_dir / "clips" / "clips.json").read_text())
    assert summary["clips"] == 0 and doc["clips"] == []
    assert doc["skipped"] == [{"camera": "front", "clip": c, "reason": "scene has 24 frames, a clip needs 121"}
                              for c in ("front", "middle", "rear")]


def config_clip(clipped: dict):
    return stage_params("clip", clipped["clip"])
