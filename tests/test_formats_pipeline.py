"""Every log format, exported from a synthetic street, goes through the whole pipeline."""

import json
from collections import Counter

import pytest
from typer.testing import CliRunner

from paradrive.cli import app
from paradrive.pairs import read_pairs
from paradrive.contracts.layout import SceneLayout
from paradrive.contracts.records import FitRecord
from paradrive.uri import parse_uri

FRONT3 = ["front", "front_left", "front_right"]
SIX = FRONT3 + ["back_left", "back_right", "back"]


@pytest.mark.slow
def test_waymo_nuscenes_and_drivestudio_logs_build_72_pairs_each(tmp_path):
    runner = CliRunner()
    uris = []
    for fmt in ("waymo", "nuscenes", "drivestudio"):
        result = runner.invoke(app, ["export", fmt, str(tmp_path / fmt), "--profile", "smoke"])
        assert result.exit_code == 0, result.output
        uris.append(result.output.strip().splitlines()[-1])
    assert [u.split(":", 1)[0] for u in uris] == ["waymo", "nuscenes", "drivestudio"]

    args = ["build", "--profile", "smoke", "--data", str(tmp_path / "data"),
            "--manifests", str(tmp_path / "manifests"), "--build", "formats"]
    for uri in uris:
        args += ["--scene", uri]
    result = runner.invoke(app, args, env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    rows = read_pairs(tmp_path / "manifests" / "formats").to_pylist()
    assert Counter(r["dataset"] for r in rows) == {"waymo": 72, "nuscenes": 72, "drivestudio": 72}
    # the fit sees the dataset's fit set (ingest.cameras: auto); the pairs come from the front camera
    assert {r["camera"] for r in rows} == {"front"}
    for uri, cameras in zip(uris, (FRONT3, SIX, FRONT3)):
        scene_dir = tmp_path / "data" / "scenes" / parse_uri(uri).scene_id
        assert sorted(json.loads((scene_dir / "scene.json").read_text())["cameras"]) == sorted(cameras)
        assert json.loads((scene_dir / "gs" / "fit.json").read_text())["cameras"] == sorted(cameras)
    # the Waymo log's moving traffic is fitted as a scene graph, without ghosts: on the recorded
    # front views the moving boxes' pixels come out nearly as well as the rest (a static fit
    # of the same log smears them: 7 dB below the rest there, the graph 4)
    waymo_dir = tmp_path / "data" / "scenes" / parse_uri(uris[0]).scene_id
    fit = FitRecord.load(SceneLayout(waymo_dir).fit_json)
    assert fit.dynamic and fit.actors
    inside, outside = moving_pixels_psnr(waymo_dir, fit)
    assert inside > outside - 5.0, (inside, outside)


def moving_pixels_psnr(scene_dir, fit, camera: str = "front") -> tuple[float, float]:
    """PSNR (dB) of the final checkpoint on the recorded ``camera`` views that show moving
    actors, against the images: inside the ingest's dynamic masks, and outside them."""
    import numpy as np

    from paradrive.gs.views import masked_psnr
    from paradrive.gs.graph import load_model
    from paradrive.gs.views import render_views
    from paradrive.scene import load_scene, read_image

    scene, layout = load_scene(scene_dir), SceneLayout(scene_dir)
    model = load_model(layout, fit.iterations, scene, fit)
    masks = [read_image(layout.dynamic_mask(camera, f.index))[..., 0] > 127 for f in scene.frames]
    frames = [i for i, m in enumerate(masks) if m.mean() > 0.01]
    cam = scene.cameras[camera]
    rgb = np.concatenate([r["rgb"] for r in render_views(model, scene.c2w(camera)[frames], cam.K(),
                                                         cam.width, cam.height, frames=frames)])
    truth = np.stack([scene.load_image(i, camera) for i in frames])
    moving = np.stack([masks[i] for i in frames])
    return masked_psnr(rgb, truth, moving), masked_psnr(rgb, truth, ~moving)


def test_export_refuses_a_non_synthetic_scene(tmp_path):
    result = CliRunner().invoke(app, ["export", "waymo", str(tmp_path), "--scene", "waymo:/x.tfrecord"])
    assert result.exit_code == 2
    assert "export writes synthetic scenes only" in result.output
