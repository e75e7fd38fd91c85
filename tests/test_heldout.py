"""Held-out evaluation: views a fit never sees (``fit.holdout_every``, ``fit.holdout_cameras``),
measured by the fit stage (fit.json ``heldout``), by ``paradrive eval`` on every dataset, and
used by publishing to leave out poorly fitted scenes (``manifest.min_heldout_psnr``)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from PIL import Image
from typer.testing import CliRunner

from paradrive.cli import app
from paradrive.contracts.layout import SceneLayout
from paradrive.contracts.records import FitRecord, HeldoutRecord
from paradrive.errors import ConfigError
from paradrive.pipeline import StageRegistry, run_build
from paradrive.scene import load_scene

from conftest import stage_params

# a few iterations of the smoke profile on a tiny street: enough for measurable renders
TINY_FIT = {"checkpoints": [10, 20], "init_points": 1500, "sky_points": 200,
            "refine_start_iter": 5, "refine_every": 5, "refine_stop_iter": 15, "eval_views": 4}
TINY_RENDER = {"condition_checkpoints": [10], "source_checkpoint": 20, "clip_frames": 8}   # the 8-frame scene
TINY_INGEST = {"synthetic_frames": 8, "synthetic_width": 80, "synthetic_height": 48}
HOLDOUT = {"holdout_every": 3, "holdout_cameras": ["front_left"]}


def _magenta(scene_dir: Path, held) -> int:
    """Paint every image ``held(frame position, camera)`` accepts pure magenta; how many."""
    scene = load_scene(scene_dir)
    n = 0
    for fi, frame in enumerate(scene.frames):
        for cam in frame.cameras:
            if held(fi, cam):
                path = scene.image_path(fi, cam)
                size = Image.open(path).size
                Image.new("RGB", size, (255, 0, 255)).save(path)
                n += 1
    return n


def _fit(scene_dir: Path, overrides: dict) -> dict[str, bytes]:
    from paradrive.stages.fit import fit_scene

    # byte-identical fits are the CPU kernels' promise
    p = stage_params("fit", {**TINY_FIT, "device": "cpu", **overrides}, profile="smoke")
    fit_scene(scene_dir, p, moving_threshold_m=None)
    return {f.name: f.read_bytes() for f in sorted(SceneLayout(scene_dir).gs_dir.glob("*.ply"))}


def test_held_out_images_never_reach_the_loss_densification_or_init(tiny_scene, tmp_path):
    from paradrive.gs.init import Holdout

    holdout = Holdout(every=3, cameras=("front_left",))
    clean, painted, plain = (tmp_path / n for n in ("clean", "painted", "plain"))
    for d in (clean, painted, plain):
        shutil.copytree(tiny_scene, d)
        shutil.rmtree(d / "gs", ignore_errors=True)
    assert _magenta(painted, holdout.held) == _magenta(plain, holdout.held) > 0
    clean_fit = _fit(clean, HOLDOUT)
    assert clean_fit  # the checkpoints were written
    record = FitRecord.load(SceneLayout(clean).fit_json)
    scene = load_scene(clean)
    assert record.n_views == sum(1 for fi, f in enumerate(scene.frames) for c in f.cameras
                                 if not holdout.held(fi, c)) > 0
    assert "front_left" not in record.cameras
    # the same fit of the scene whose held-out images are magenta: the very same bytes
    assert _fit(painted, HOLDOUT) == clean_fit
    # and the magenta images do change a fit that trains on them (the comparison can fail)
    assert _fit(plain, {}) != _fit(clean, {})


def test_a_default_holdout_keeps_the_fit_fingerprint_and_bad_values_are_refused():
    from paradrive.gs.fit import HOLDOUT_KEYS, _fingerprint

    source = stage_params("fit").source
    assert source["holdout_every"] == 0 and source["holdout_cameras"] == []
    without = {k: v for k, v in source.items() if k not in HOLDOUT_KEYS}
    assert _fingerprint(source) == _fingerprint(without)
    assert _fingerprint({**source, "holdout_every": 4}) != _fingerprint(source)
    assert _fingerprint({**source, "holdout_cameras": ["front"]}) != _fingerprint(source)
    with pytest.raises(ConfigError, match="holdout_every"):
        StageRegistry().resolve(None, {"fit": {"holdout_every": -1}})
    with pytest.raises(ConfigError, match="holdout_cameras"):
        StageRegistry().resolve(None, {"fit": {"holdout_cameras": [""]}})


def _scene_uri(fmt: str, tmp_path: Path, config) -> str:
    if fmt == "synthetic":
        return "synthetic:demo?seed=7"
    from paradrive.ingest.export import export_scene

    return export_scene("synthetic:demo?seed=7", fmt, tmp_path / fmt, config.typed("ingest"))


@pytest.mark.parametrize("fmt", ["waymo", "nuscenes", "drivestudio", "synthetic"])
def test_fit_records_and_eval_reports_held_out_quality_on_every_dataset(fmt, tmp_path):
    overrides = {"ingest": TINY_INGEST, "fit": {**TINY_FIT, **HOLDOUT}, "render": TINY_RENDER}
    config = StageRegistry().resolve("smoke", overrides)
    uri = _scene_uri(fmt, tmp_path, config)
    report = run_build(config, [uri], tmp_path / "data", stages=["ingest", "fit"],
                       manifests_dir=tmp_path / "manifests", build="heldout")
    assert not report.failures(), [r.error for r in report.failures()]
    (scene_dir,) = (tmp_path / "data" / "scenes").iterdir()
    fit = FitRecord.load(SceneLayout(scene_dir).fit_json)
    held = fit.heldout
    assert isinstance(held, HeldoutRecord) and held.iteration == 20
    assert held.every == 3 and held.cameras == ["front_left"]
    assert held.per_camera["front_left"].kind == "camera"
    assert held.per_camera["front"].kind == "frames"
    scene = load_scene(scene_dir)
    # frames 2 and 5 of the fitted cameras, every frame of front_left
    assert held.per_camera["front"].views == 2
    assert held.per_camera["front_left"].views == len(scene.frames)
    assert 5.0 < held.psnr < 60.0 and 0.0 < held.ssim <= 1.0

    sets = [f"fit.{k}={json.dumps(v)}" for k, v in TINY_FIT.items()]
    sets += [f"render.{k}={json.dumps(v)}" for k, v in TINY_RENDER.items()]
    sets += [f"ingest.{k}={json.dumps(v)}" for k, v in TINY_INGEST.items()]
    args = ["eval", "--scene", uri, "--data", str(tmp_path / "data"), "--profile", "smoke",
            "--out", str(tmp_path / "eval"), "--frames", "0"]
    for s in sets:
        args += ["--set", s]
    result = CliRunner().invoke(app, args, env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    doc = json.loads((tmp_path / "eval" / "eval.json").read_text())
    heldout = doc["heldout"]
    assert heldout["every"] == 3 and heldout["cameras"] == ["front_left"]
    assert set(heldout["per_camera"]) == set(held.per_camera)
    for cam, c in heldout["per_camera"].items():
        assert [r["iteration"] for r in c["checkpoints"]] == [10, 20]
    # the final checkpoint's figures are the fit stage's, recomputed from the checkpoint
    assert heldout["iteration"] == 20 and heldout["views"] == held.views
    assert heldout["psnr"] == pytest.approx(held.psnr, abs=1e-6)
    assert "heldout" in result.output
    if fmt == "synthetic":
        # beside the recorded images, the street's truth at the same held-out poses
        assert heldout["psnr_vs_truth"] > 5.0
        assert all("psnr_vs_truth" in r for c in heldout["per_camera"].values()
                   for r in c["checkpoints"])
        assert doc["cameras"]   # and the shifted views against the truth, as before
    else:
        assert "psnr_vs_truth" not in heldout and doc["cameras"] == {}


def test_eval_of_a_real_log_without_held_out_views_says_how_to_get_them(tmp_path):
    config = StageRegistry().resolve("smoke", {"ingest": TINY_INGEST, "fit": TINY_FIT, "render": TINY_RENDER})
    uri = _scene_uri("waymo", tmp_path, config)
    report = run_build(config, [uri], tmp_path / "data", stages=["ingest", "fit"],
                       manifests_dir=tmp_path / "manifests", build="plain")
    assert not report.failures(), [r.error for r in report.failures()]
    (scene_dir,) = (tmp_path / "data" / "scenes").iterdir()
    assert FitRecord.load(SceneLayout(scene_dir).fit_json).heldout is None
    assert "heldout" not in json.loads(SceneLayout(scene_dir).fit_json.read_text())
    args = ["eval", "--scene", uri, "--data", str(tmp_path / "data"), "--profile", "smoke"]
    for k, v in {**{f"fit.{k}": v for k, v in TINY_FIT.items()},
                 **{f"render.{k}": v for k, v in TINY_RENDER.items()}}.items():
        args += ["--set", f"{k}={json.dumps(v)}"]
    result = CliRunner().invoke(app, args, env={"COLUMNS": "300"})
    assert result.exit_code == 2, result.output
    assert "held none out" in result.output and "fit.holdout_every" in result.output
    # asking eval for a holdout the fit did not make is refused: those views were trained on
    result = CliRunner().invoke(app, args + ["--set", "fit.holdout_every=2"], env={"COLUMNS": "300"})
    assert result.exit_code == 2, result.output
    assert "did not hold these views out" in result.output


def _with_heldout(scene_dir: Path, psnr: float | None) -> None:
    layout = SceneLayout(scene_dir)
    fit = FitRecord.load(layout.fit_json)
    held = None if psnr is None else HeldoutRecord(every=4, cameras=[], iteration=300, views=6,
                                                   psnr=psnr, ssim=0.5, per_camera={})
    fit.model_copy(update={"heldout": held}).save(layout.fit_json)


def test_publishing_leaves_out_scenes_below_the_held_out_psnr(smoke_build, copy_tree, tmp_path):
    from paradrive.inspection import summarize
    from paradrive.stages.manifest import build_manifest

    data = copy_tree(smoke_build["data_dir"])
    scenes = sorted((data / "scenes").iterdir())
    good, poor = scenes
    _with_heldout(good, 27.5)
    _with_heldout(poor, 14.0)
    entries = [{"scene_id": d.name, "scene_uri": "", "scene_dir": str(d)} for d in scenes]

    params = stage_params("manifest", {"min_heldout_psnr": 20}, profile="smoke")
    index = build_manifest(tmp_path / "filtered", entries, params, build="filtered")
    assert [s.scene_id for s in index.scenes] == [good.name]
    assert index.scenes[0].heldout_psnr == 27.5
    assert index.heldout_filter is not None and index.heldout_filter.min_psnr == 20
    (dropped,) = index.heldout_filter.dropped
    assert dropped.scene_id == poor.name
    assert "held-out PSNR 14.00 dB is below manifest.min_heldout_psnr 20 dB" in dropped.reason
    assert [s.scene_id for s in index.skipped_scenes] == [poor.name]
    summary = summarize(tmp_path / "filtered")
    assert summary["quality"]["scenes"][good.name]["heldout_psnr"] == 27.5
    assert summary["heldout_filter"]["dropped"][0]["scene_id"] == poor.name

    # a scene fitted without a holdout has no held-out PSNR: the filter leaves it out too
    _with_heldout(poor, None)
    index = build_manifest(tmp_path / "unknown", entries, params, build="unknown")
    assert "fit held no views out" in index.heldout_filter.dropped[0].reason

    # no threshold: every scene is published, their held-out PSNR recorded where there is one
    params = stage_params("manifest", {}, profile="smoke")
    index = build_manifest(tmp_path / "all", entries, params, build="all")
    assert len(index.scenes) == 2 and index.heldout_filter is None
    assert json.loads((tmp_path / "all" / "index.json").read_text())["heldout_filter"] is None
    assert [s.heldout_psnr for s in index.scenes] == [27.5, None]


def test_holdout_selects_stride_frames_and_whole_cameras(tiny_scene):
    """Held-out selection: DriveStudio's test_image_stride positions, and whole cameras."""
    from paradrive.gs.init import Holdout

    h = Holdout(every=4, cameras=("back",))
    assert [fi for fi in range(10) if h.frame_held(fi)] == [3, 7]
    assert h.held(0, "back") and not h.held(0, "front") and h.held(3, "front")
    assert not Holdout().active and Holdout(every=2).active and Holdout(cameras=("x",)).active
    with pytest.raises(Exception, match="holdout_cameras"):
        Holdout(cameras=("nope",)).check(load_scene(tiny_scene))
