"""``paradrive plan``: a build's pairs, bytes and hours projected before anything runs."""

from __future__ import annotations

import json

import yaml
from typer.testing import CliRunner

from paradrive.cli import app
from paradrive.pipeline import StageRegistry
from paradrive.pipeline.budget import plan_build, scene_footprint
from paradrive.pipeline.runner import read_marker

WAYMO = [f"waymo:/logs/segment-{n}_with_camera_labels.tfrecord" for n in ("1", "2")]
PAIRS_PER_SCENE = 72   # docs/scene-layout.md: 3 clips x 8 offsets x 3 under-fitted checkpoints, one camera


def rates() -> dict:
    return yaml.safe_load((StageRegistry().dir / "budget" / "rates.yaml").read_text())


def test_paper_logs_take_the_documented_rates_and_the_papers_gpu_budget():
    config = StageRegistry().resolve(None)
    plan = plan_build(config, WAYMO, None)
    assert plan.scenes == 2 and plan.pairs == 2 * PAIRS_PER_SCENE
    assert plan.shapes == {"typical waymo log": 2}
    # the paper: 8,240 GPU-hours for ~1.6K scenes, about 5.15 a scene
    assert abs(plan.hours("gpu") - 2 * 5.15) < 0.01
    assert plan.rates["compute:fit"].source == rates()["compute"]["fit"]["source"]
    one = plan_build(config, WAYMO[:1], None)
    for key in ("media_bytes", "intermediate_bytes"):   # two scenes of one shape: twice one
        assert one.as_json()[key] > 0 and abs(plan.as_json()[key] - 2 * one.as_json()[key]) <= 1


def _scene_alone(data_dir, tmp_path):
    """A data root holding only seed 7's scene folder, copied from ``data_dir``."""
    import shutil

    data = tmp_path / "data"
    shutil.copytree(data_dir / "scenes" / "synthetic-demo-s7", data / "scenes" / "synthetic-demo-s7")
    return data, data / "scenes" / "synthetic-demo-s7"


def test_a_finished_scene_is_projected_at_what_it_took(smoke_scene, tmp_path):
    """Rates measured on the data root's finished scene (ingested and fitted, never rendered)
    reproduce that scene's own seconds and bytes; render, not yet measured, takes the default."""
    data, scene_dir = _scene_alone(smoke_scene["data_dir"], tmp_path)
    config = StageRegistry().resolve("smoke")
    plan = plan_build(config, ["synthetic:demo?seed=7"], data)
    assert plan.shapes == {"ingested": 1}
    for stage in ("ingest", "fit"):
        assert plan.rates[f"compute:{stage}"].source.startswith("measured")
        assert abs(plan.seconds[stage] - read_marker(scene_dir, stage).seconds) < 1e-6
    footprint = scene_footprint(data, "synthetic-demo-s7")
    for folder in ("images", "lidar", "gs"):
        assert abs(plan.bytes[folder] - footprint[folder]) < 1.0, folder
    assert plan.rates["compute:fit"].device == "cpu"     # fit.json says where the fit ran
    assert read_marker(scene_dir, "render") is None
    assert plan.rates["compute:render"].source == rates()["compute"]["render"]["source"]


def test_a_rendered_scene_is_projected_at_its_render_time(smoke_build, tmp_path):
    data, scene_dir = _scene_alone(smoke_build["data_dir"], tmp_path)
    plan = plan_build(StageRegistry().resolve("smoke"), ["synthetic:demo?seed=7"], data)
    assert plan.rates["compute:render"].source.startswith("measured")
    assert abs(plan.seconds["render"] - read_marker(scene_dir, "render").seconds) < 1e-6


def test_retention_switches_lower_only_what_is_kept():
    uris = WAYMO[:1]
    kept = plan_build(StageRegistry().resolve(None), uris, None)
    let_go = plan_build(StageRegistry().resolve(None, {"render": {"keep_frames": False},
                                                        "ingest": {"keep_lidar": False}}), uris, None)
    assert let_go.bytes == kept.bytes
    assert let_go.kept["renders"] == 0 < kept.kept["renders"]
    assert let_go.kept["lidar"] == 0 < kept.kept["lidar"]
    assert let_go.kept["images"] == kept.kept["images"] and let_go.kept["clips"] == kept.kept["clips"]


def test_a_synthetic_scene_is_sized_by_its_uri_and_a_short_one_gives_no_pairs():
    config = StageRegistry().resolve("demo")   # 121-frame clips at 320x192
    long = plan_build(config, ["synthetic:demo?seed=3&frames=150"], None)
    short = plan_build(config, ["synthetic:demo?seed=3&frames=100"], None)
    assert long.shapes == {"uri": 1} and long.pairs == PAIRS_PER_SCENE
    assert short.pairs == 0 and short.bytes["clips"] == 0 < long.bytes["clips"]
    assert short.bytes["images"] < long.bytes["images"]


def test_cli_plan_prints_the_projection_and_json(tmp_path):
    runner = CliRunner()
    segment = tmp_path / "segment-1_with_camera_labels.tfrecord"
    segment.write_bytes(b"")   # planned by its URI: the file is only looked for
    args = ["plan", "--scene", f"waymo:{segment}", "--data", "/nonexistent-data-root"]
    result = runner.invoke(app, [*args, "--json"])
    assert result.exit_code == 0, result.output
    doc = json.loads(result.output)
    assert doc["pairs"] == PAIRS_PER_SCENE and doc["gpu_hours"] > 0 and doc["media_bytes"] > 0
    text = runner.invoke(app, args)
    assert text.exit_code == 0 and "GPU-hours" in text.output and "pairs" in text.output
    assert runner.invoke(app, ["plan"]).exit_code == 2   # no scenes: a usage error
