"""Ground-truth eval on the synthetic street: shifted renders degrade with the offset,
conditions improve with the iteration, and the CLI prints the table."""

from __future__ import annotations

import json

import numpy as np
import pytest

from conftest import assert_a_drawing, stage_params

from paradrive.contracts.records import FitRecord
from paradrive.evaluation import depth_abs_rel, depth_signed_rel, evaluate_scene, image_quality

from test_render import SCENE, SID, smoke_params


@pytest.fixture(scope="module")
def evaluated(request, tmp_path_factory):
    config = smoke_params(offsets_m=[1.0, -1.0, 4.0, -4.0])
    smoke = request.getfixturevalue("smoke_scene")
    scene_dir = smoke["data_dir"] / "scenes" / SID
    out = tmp_path_factory.mktemp("eval")
    doc = evaluate_scene(scene_dir, config.typed("render"), max_frames=4, out_dir=out)
    return {"doc": doc, "out": out, "config": config, "data_dir": smoke["data_dir"]}


def test_metrics_on_known_images():
    a = np.full((2, 8, 8, 3), 100, np.uint8)
    b = a.copy()
    b[..., 0] += 10
    q = image_quality(a, b)
    assert q["psnr"] == pytest.approx(10 * np.log10(1 / ((10 / 255) ** 2 / 3)), rel=1e-4)
    assert image_quality(a, a)["ssim"] == pytest.approx(1.0)
    truth = np.array([[10.0, np.inf], [20.0, 40.0]])
    assert depth_abs_rel(np.array([[11.0, 5.0], [20.0, 44.0]]), truth) == pytest.approx(0.1)
    assert depth_abs_rel(truth, np.full((2, 2), np.inf)) is None


def test_shifted_renders_get_worse_as_the_offset_grows(evaluated):
    cam = evaluated["doc"]["cameras"]["front"]
    psnr = {r["offset_m"]: r["psnr"] for r in cam["shifted"]}
    near = np.mean([psnr[1.0], psnr[-1.0]])
    far = np.mean([psnr[4.0], psnr[-4.0]])
    assert near > far + 0.5, cam["shifted"]
    by_abs = cam["shifted_by_abs_offset"]
    assert by_abs["1"]["psnr"] == pytest.approx(near) and by_abs["4"]["psnr"] == pytest.approx(far)
    assert by_abs["1"]["ssim"] > by_abs["4"]["ssim"]
    # the recorded trajectory (offset 0) is the best the final checkpoint does
    assert cam["recorded"]["psnr_vs_truth"] > near


def test_conditions_improve_with_the_iteration(evaluated):
    cam = evaluated["doc"]["cameras"]["front"]
    its = [r["iteration"] for r in cam["conditions"]]
    assert its == evaluated["config"].params["render"]["condition_checkpoints"]
    psnr = [r["psnr"] for r in cam["conditions"]]
    assert all(b > a for a, b in zip(psnr, psnr[1:])), psnr
    assert cam["recorded"]["psnr"] > psnr[-1]


def test_a_shift_to_the_left_renders_what_the_ray_caster_sees_from_the_left(evaluated):
    """Independent of the shift function that eval and render share: the truth here comes from
    a pose moved by hand. The world frame is the first ego pose (x forward, y left), so at
    frame 0 a parallel lane 2 m to the left is the recorded camera moved by +2 m along world y."""
    from paradrive import geometry
    from paradrive.ingest.synthetic import street_from_uri
    from paradrive.gs.views import render_views
    from test_render import fitted_model
    from paradrive.scene import load_scene
    from paradrive.uri import parse_uri

    scene_dir = evaluated["data_dir"] / "scenes" / SID
    scene = load_scene(scene_dir)
    rp, ingest = evaluated["config"].params["render"], evaluated["config"].typed("ingest")
    np.testing.assert_allclose(scene.ego2world()[0], np.eye(4), atol=1e-12)
    c2w = scene.c2w("front")[0]
    by_hand = {d: c2w.copy() for d in (2.0, -2.0)}
    for d, pose in by_hand.items():
        pose[1, 3] += d
    street = street_from_uri(parse_uri(SCENE), ingest)
    w, h = 160, 96
    cam = scene.cameras["front"]
    K = np.array([[cam.fx * w / cam.width, 0, cam.cx * w / cam.width],
                  [0, cam.fy * h / cam.height, cam.cy * h / cam.height], [0, 0, 1]])
    truth = {d: street.render(pose[None], K, w, h)["rgb"] for d, pose in by_hand.items()}
    model = fitted_model(scene_dir, rp["source_checkpoint"])
    shifted = geometry.lateral_shift(c2w[None], scene.ego2world()[:1], 2.0)   # what render uses
    render = next(render_views(model, shifted, K, w, h, frames=[0]))["rgb"]
    left, right = (image_quality(render, truth[d])["psnr"] for d in (2.0, -2.0))
    assert left > right + 1.0, (left, right)
    assert left > 15.0, left


def test_eval_writes_json_and_plot(evaluated):
    doc = json.loads((evaluated["out"] / "eval.json").read_text())
    assert doc == json.loads(json.dumps(evaluated["doc"]))
    assert doc["scene_id"] == SID and len(doc["cameras"]["front"]["frames"]) == 4
    assert_a_drawing(evaluated["out"] / "eval.png", 301, 201)   # the curves drawn, not a blank canvas


def test_cli_prints_the_table(evaluated, tmp_path):
    from typer.testing import CliRunner

    from paradrive.cli import app

    result = CliRunner().invoke(app, [
        "eval", "--scene", SCENE, "--data", str(evaluated["data_dir"]), "--profile", "smoke",
        "--set", "render.offsets_m=[2.0]", "--frames", "1", "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    rows = [line for line in result.output.splitlines() if "source+2m" in line]
    assert len(rows) == 1 and "truth" in rows[0]
    n_cond = len(evaluated["config"].params["render"]["condition_checkpoints"])
    assert sum("cond@" in line for line in result.output.splitlines()) == n_cond
    assert json.loads((tmp_path / "eval.json").read_text())["scene_id"] == SID
    assert_a_drawing(tmp_path / "eval.png", 301, 201)


def test_eval_with_another_profile_names_the_checkpoints_and_the_profile_flag(evaluated):
    """A scene built with one profile and evaluated with another (``make eval`` after ``make demo``
    without PROFILE=demo) is told which checkpoints it has and how to pass the profile."""
    from typer.testing import CliRunner

    from paradrive.cli import app

    have = [c.iteration for c in FitRecord.load(
        evaluated["data_dir"] / "scenes" / SID / "gs" / "fit.json", SID).checkpoints]
    result = CliRunner().invoke(app, ["eval", "--scene", SCENE, "--data", str(evaluated["data_dir"])])
    text = " ".join(result.output.split())
    assert result.exit_code == 2, result.output
    assert "checkpoint for iteration" in text and "is missing" in text
    assert str(have) in text and "--profile NAME" in text and "PROFILE=NAME" in text


def test_cli_refuses_a_real_log_that_was_never_ingested(tmp_path):
    """A real log is measured on its fit's held-out views (tests/test_heldout.py); one that is
    not in the data folder is an error naming the file and the fix."""
    from typer.testing import CliRunner

    from paradrive.cli import app

    result = CliRunner().invoke(app, ["eval", "--scene", "waymo:/logs/x.tfrecord",
                                      "--data", str(tmp_path)], env={"COLUMNS": "300"})
    assert result.exit_code == 2
    assert "scene.json is missing" in result.output and "ingest" in result.output


def test_signed_depth_error_of_a_scaled_true_depth():
    from paradrive.ingest.synthetic import street_from_uri
    from paradrive.uri import parse_uri

    street = street_from_uri(parse_uri("synthetic:demo?seed=7&frames=2&width=64&height=40"),
                             stage_params("ingest"))
    spec = street.cameras["front"]
    truth = street.render(street.c2w("front"), spec.K(), spec.width, spec.height)["depth"]
    assert np.isinf(truth).any() and np.isfinite(truth).any()   # sky and surfaces
    near = np.where(np.isfinite(truth), 0.9 * truth, np.inf)      # every surface 10 % too near
    assert depth_signed_rel(near, truth) == pytest.approx(-0.1, abs=1e-6)
    assert depth_abs_rel(near, truth) == pytest.approx(0.1, abs=1e-6)
    far = truth * 1.25
    assert depth_signed_rel(far, truth) == pytest.approx(0.25, abs=1e-6)
    # a surface rendered as sky is an error towards +inf, sky rendered as a surface is ignored
    assert depth_signed_rel(np.full_like(truth, np.inf), truth) == np.inf
    assert depth_signed_rel(np.where(np.isfinite(truth), truth, 1.0), truth) == 0.0
    assert depth_signed_rel(truth, np.full_like(truth, np.inf)) is None


def test_every_stream_reports_the_signed_depth_error(evaluated):
    cam = evaluated["doc"]["cameras"]["front"]
    for row in [cam["recorded"]] + cam["shifted"]:
        signed, absolute = row["depth_signed_rel"], row["depth_abs_rel"]
        assert signed is not None and abs(signed) <= absolute + 1e-9, row
    assert "depth_signed_rel" in evaluated["doc"]["metrics"]


def test_static_psnr_leaves_out_the_pixels_of_moving_actors(evaluated):
    from paradrive.gs.views import static_quality

    # the smoke street's moving traffic shows in every eval row, scored apart
    cam = evaluated["doc"]["cameras"]["front"]
    rows = [cam["recorded"]] + cam["shifted"]
    assert all(r["psnr_static"] is not None and 0.0 <= r["dynamic_fraction"] < 0.5 for r in rows)
    assert max(r["dynamic_fraction"] for r in rows) > 0.0
    truth = np.zeros((2, 8, 8, 3), np.uint8)
    pred = truth.copy()
    pred[:, :2, :2] = 255  # a ghost where a moving car was
    dynamic = np.zeros((2, 8, 8), bool)
    dynamic[:, :2, :2] = True
    q = static_quality(pred, truth, dynamic)
    assert q["dynamic_fraction"] == pytest.approx(4 / 64)
    assert q["psnr_static"] == pytest.approx(100.0)  # the rest is exact (error floored at 1e-10)
    everything = static_quality(pred, truth, np.zeros_like(dynamic))["psnr_static"]
    assert everything == pytest.approx(10 * np.log10(64 / 4))
    assert static_quality(pred, truth, np.ones_like(dynamic))["psnr_static"] is None
