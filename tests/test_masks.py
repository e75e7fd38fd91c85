"""Masks: the ego mask (what moves with the camera: a hood, still overlays anywhere) is found,
the moving masks of a real clip cover its cars and not its road, the pairs carry the share of
their target masked as moving, and manifest.max_dynamic_fraction filters on it at publish. (The
fit and the render's use of the masks are tested in test_gs_fit.py and test_render.py; the real
freeway clip's masks in test_video_real.py, beside the clip's other tests: one worker builds
the clip once for them all.)"""

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


def test_still_overlays_anywhere_join_the_ego_mask_and_the_street_does_not():
    """A logo and a clock burned into a drive (the clock's digits change every frame, inside its
    box): both are found, wherever they are; the street around them is not, nor on the same
    drive without them."""
    from paradrive.ingest.videomasks import scene_ego_mask

    street = SyntheticStreet(name="demo", seed=7, frames=40, width=192, height=112)
    spec = street.cameras["front"]
    frames = street.render(street.c2w("front"), spec.K(), spec.width, spec.height)["rgb"]
    n, h, w = frames.shape[:3]
    rng = np.random.default_rng(5)
    logo = np.zeros((h, w), dtype=bool)
    logo[6:18, 8:44] = True
    clock = np.zeros((h, w), dtype=bool)
    clock[5:17, 130:186] = True
    burned = frames.copy()
    mark = rng.integers(0, 2, (12, 36, 1)) * 200 + 30
    face = rng.integers(0, 2, (12, 56, 1)) * 180 + 40
    for k in range(n):
        burned[k][logo] = mark.repeat(3, -1).reshape(-1, 3)
        face[2:10, 20:36] = rng.integers(0, 2, (8, 16, 1)) * 180 + 40   # the digits tick
        burned[k][clock] = face.repeat(3, -1).reshape(-1, 3)
    hood, overlays = scene_ego_mask(lambda k: burned[k], n, scene_id="drive")
    assert overlays[logo].mean() > 0.97 and overlays[clock].mean() > 0.97
    near = np.zeros((h, w), dtype=bool)
    near[1:22, 3:49] = near[1:21, 125:191] = True   # the overlays and the margin around them
    top = slice(0, h // 3)   # houses and sky: no overlay
    assert (overlays | hood)[top][~near[top]].mean() < 0.01
    plain_hood, plain = scene_ego_mask(lambda k: frames[k], n, scene_id="drive")
    assert not plain[top].any() and plain.mean() < 0.05


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
