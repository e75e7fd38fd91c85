"""Masks: the ego mask (what moves with the camera) is found, the pairs carry the share of their
target masked as moving, and manifest.max_dynamic_fraction filters on it at publish."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from paradrive.contracts.layout import SceneLayout
from paradrive.contracts.records import ClipsRecord, RendersRecord
from paradrive.ingest.egomask import ego_mask, grey
from paradrive.pairs import read_pairs
from paradrive.scene import read_image
from paradrive.stages.manifest import build_manifest
from paradrive.synthetic import SyntheticStreet
from conftest import stage_params

REALDATA = Path(__file__).resolve().parents[1].parent / "shared" / "realdata"
LABELS = Path(__file__).resolve().parent / "udacity_freeway_cars.json"


@pytest.fixture(scope="module")
def street_frames() -> np.ndarray:
    street = SyntheticStreet(name="demo", seed=7, frames=12, width=192, height=112)
    spec = street.cameras["front"]
    return street.render(street.c2w("front"), spec.K(), spec.width, spec.height)["rgb"]


def _hood(frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The frames with a textured hood whose edge waves (rows from ~82 % down), and its pixels."""
    n, h, w = frames.shape[:3]
    edge = (0.82 * h + 4 * np.sin(np.arange(w) / 15.0)).astype(int)
    hood = np.arange(h)[:, None] >= edge[None, :]
    texture = np.random.default_rng(3).integers(90, 150, (h, w, 3), dtype=np.uint8)
    out = frames.copy()
    for k in range(n):  # the light on it changes from frame to frame; its texture stays
        out[k][hood] = np.clip(texture[hood] * (0.8 + 0.03 * k), 0, 255).astype(np.uint8)
    return out, hood


def test_the_ego_mask_finds_a_hood_and_nothing_on_a_plain_street(street_frames):
    hooded, hood = _hood(street_frames)
    greys = [grey(f) for f in hooded]
    found = ego_mask(list(zip(greys[:-1], greys[1:])))
    assert found[hood].mean() > 0.97
    # above the hood's edge a band of the slow synthetic road (smooth at this size) and the
    # margin; the rest of the image stays out
    assert found[~hood].mean() < 0.12 and not found[: int(0.6 * len(hood))].any()
    plain = [grey(f) for f in street_frames]
    assert ego_mask(list(zip(plain[:-1], plain[1:]))).mean() < 0.03  # the margin of the bottom rows


def test_a_pair_s_dynamic_fraction_is_its_target_s_share_inside_moving_boxes(smoke_build):
    """The smoke street's moving traffic: each clip's figure is the mean over its frames of the
    cropped box masks' share, and every row of the clip carries it."""
    data = Path(smoke_build["data_dir"])
    scene = SceneLayout(data / "scenes" / "synthetic-demo-s7")
    renders = RendersRecord.load(scene.renders_json)
    clips = ClipsRecord.load(scene.clips_json)
    x0, y0, cw, ch = renders.cameras["front"].crop
    rows = read_pairs(smoke_build["build_dir"]).to_pylist()
    figures = []
    for clip in clips.clips:
        shares = [(read_image(scene.dynamic_mask("front", index))[y0:y0 + ch, x0:x0 + cw, 0] > 127).mean()
                  for index in clip.frame_indices]
        assert clip.dynamic_fraction == pytest.approx(np.mean(shares), abs=1e-6)
        mine = {r["dynamic_fraction"] for r in rows
                if r["scene_id"] == scene.scene_id and r["clip"] == clip.clip}
        assert mine == {clip.dynamic_fraction}
        figures.append(clip.dynamic_fraction)
    assert max(figures) > 0.01  # cars do drive through these clips


def test_max_dynamic_fraction_leaves_out_pairs_and_index_json_says_which(smoke_build, tmp_path):
    data = Path(smoke_build["data_dir"]) / "scenes"
    entries = [{"scene_id": d.name, "scene_uri": f"synthetic:{d.name}", "scene_dir": str(d)}
               for d in sorted(data.iterdir())]
    index = build_manifest(tmp_path / "b", entries,
                           stage_params("manifest", {"max_dynamic_fraction": 0.05}))
    rows = read_pairs(tmp_path / "b").to_pylist()
    assert rows and all(r["dynamic_fraction"] <= 0.05 for r in rows)
    dropped = index.dynamic_filter
    assert dropped is not None and dropped.max_fraction == 0.05 and dropped.dropped_rows > 0
    everything = read_pairs(smoke_build["build_dir"]).to_pylist()
    assert len(rows) + dropped.dropped_rows == len(everything)
    assert {(c.scene_id, c.clip) for c in dropped.dropped_clips} == {
        (r["scene_id"], r["clip"]) for r in everything if r["dynamic_fraction"] > 0.05}
    doc = json.loads((tmp_path / "b" / "index.json").read_text())
    assert doc["params"]["max_dynamic_fraction"] == 0.05


@pytest.mark.slow
@pytest.mark.skipif(not (REALDATA / "udacity-freeway").is_dir(),
                    reason="the real clip lives in ../shared/realdata/udacity-freeway/")
def test_the_real_clip_s_cars_are_masked_and_its_road_is_not(real_clip_scene):
    """Hand-labelled boxes of the two cars ahead (tests/udacity_freeway_cars.json) against the
    moving masks of the real freeway clip (docs/scene-layout.md, "Masks", has the figures)."""
    from paradrive.ingest.videomasks import labelled_scores

    scores = labelled_scores(real_clip_scene, LABELS, REALDATA / "udacity-freeway" / "calibration.json")
    assert len(scores.frames) >= 10
    assert scores.coverage >= 0.5
    assert scores.road_masked <= 0.05


@pytest.fixture(scope="module")
def real_clip_scene(tmp_path_factory) -> Path:
    """The real clip's every second frame, undistorted with its calibration and halved to
    640x360, ingested as a folder of frames with the intrinsics to match."""
    from paradrive.ingest.undistort import undistort_image
    from paradrive.scene import write_image
    from paradrive.stages.ingest import ingest, params_of
    from paradrive.video import decode_frames

    clip = REALDATA / "udacity-freeway"
    cal = json.loads((clip / "calibration.json").read_text())
    K = np.array([[cal["fx"], 0, cal["cx"] + 0.5], [0, cal["fy"], cal["cy"] + 0.5], [0, 0, 1]])
    dist = [cal[k] for k in ("k1", "k2", "p1", "p2", "k3")]
    folder = tmp_path_factory.mktemp("freeway") / "frames"
    for k, rgb in enumerate(decode_frames(clip / cal["file"], list(range(0, 160, 2)))):
        flat = undistort_image(rgb, K, dist)
        write_image(folder / f"{2 * k:03d}.png", flat[::2, ::2] // 2 + flat[1::2, 1::2] // 2)
    uri = (f"video:{folder}?fps=12.5&fx={K[0, 0] / 2}&fy={K[1, 1] / 2}&cx={K[0, 2] / 2}"
           f"&cy={K[1, 2] / 2}&height_m=1.2")
    root = tmp_path_factory.mktemp("scenes") / "freeway"
    ingest(uri, root, params_of({"image_ext": "png"}))
    return root
