"""The stage runner: a scene's stages run in order, skip when up to date, and fail loudly."""

import json
import shutil

import pytest
import yaml
from typer.testing import CliRunner

from paradrive.cli import app
from paradrive.pipeline import StageRegistry, run_build, run_scene_stage
from paradrive.contracts.specs import default_stages_dir
from paradrive.scene import load_scene

URI = "synthetic:demo?seed=7&frames=6&width=64&height=48"


@pytest.fixture
def stages_copy(tmp_path):
    dst = tmp_path / "stages"
    shutil.copytree(default_stages_dir(), dst)
    return dst


def test_ingest_writes_a_valid_scene_and_a_rerun_skips_it(tmp_path):
    config = StageRegistry().resolve("smoke")
    first = run_scene_stage(config, "ingest", URI, tmp_path)
    assert first.status == "done", first.error
    scene = load_scene(tmp_path / "scenes" / first.scene_id)
    assert len(scene.frames) == 6 and scene.cameras["front"].width == 64
    assert scene.load_image(5, "front").shape == (48, 64, 3)
    marker = json.loads((tmp_path / "scenes" / first.scene_id / ".paradrive/ingest.json").read_text())
    assert marker["fingerprint"] == first.fingerprint
    again = run_scene_stage(config, "ingest", URI, tmp_path)
    assert again.status == "skipped"


def test_changed_parameter_reruns_the_stage(tmp_path):
    registry = StageRegistry()
    run_scene_stage(registry.resolve("smoke"), "ingest", URI, tmp_path)
    changed = registry.resolve("smoke", {"ingest": {"image_ext": "png"}})
    result = run_scene_stage(changed, "ingest", URI, tmp_path)
    assert result.status == "done"
    scene = load_scene(tmp_path / "scenes" / result.scene_id)
    assert scene.frames[0].cameras["front"].image.endswith(".png")
    assert not list((tmp_path / "scenes" / result.scene_id / "images/front").glob("*.jpg"))


def test_deleted_output_is_rebuilt_not_skipped(tmp_path):
    config = StageRegistry().resolve("smoke")
    result = run_scene_stage(config, "ingest", URI, tmp_path)
    (tmp_path / "scenes" / result.scene_id / "scene.json").unlink()
    assert run_scene_stage(config, "ingest", URI, tmp_path).status == "done"


def test_stage_without_implementation_fails_loudly(stages_copy, tmp_path):
    doc = yaml.safe_load((stages_copy / "fit.yaml").read_text())
    doc["entry"] = "paradrive.not_landed:run_stage"
    (stages_copy / "fit.yaml").write_text(yaml.safe_dump(doc))
    config = StageRegistry(stages_copy).resolve("smoke")
    report = run_build(config, [URI], tmp_path, stages=["ingest", "fit"])
    by_stage = {r.stage: r for r in report.results}
    assert by_stage["ingest"].status == "done"
    assert by_stage["fit"].status == "failed"
    assert "paradrive.not_landed:run_stage is not available" in by_stage["fit"].error
    assert report.exit_code != 0


def test_stage_needing_an_unfinished_stage_says_what_to_run(tmp_path):
    config = StageRegistry().resolve("smoke")
    result = run_scene_stage(config, "fit", URI, tmp_path)
    assert result.status == "failed"
    assert "needs 'ingest'" in result.error and "--stages" in result.error


def test_bad_scene_fails_and_the_others_go_on(tmp_path):
    config = StageRegistry().resolve("smoke")
    report = run_build(config, ["synthetic:demo?seed=7&frames=5&width=48&height=32&colour=red", URI],
                       tmp_path, stages=["ingest"])
    states = {r.scene_id: r.status for r in report.results}
    assert list(states.values()) == ["failed", "done"]
    assert "unknown synthetic option 'colour'" in report.failures()[0].error
    assert report.exit_code == 3


def test_cli_build_ingest_then_skip(tmp_path):
    runner = CliRunner()
    args = ["build", "--scene", URI, "--profile", "smoke", "--stages", "ingest",
            "--data", str(tmp_path / "data"), "--manifests", str(tmp_path / "m")]
    first = runner.invoke(app, args)
    assert first.exit_code == 0, first.output
    assert (tmp_path / "data/scenes/synthetic-demo-s7-frames6-height48-width64/scene.json").is_file()
    second = runner.invoke(app, args)
    assert second.exit_code == 0 and "skipped" in second.output


def test_cli_stages_lists_params_and_their_origin():
    result = CliRunner().invoke(app, ["stages", "render", "--profile", "smoke"])
    assert result.exit_code == 0, result.output
    assert "offsets_m" in result.output and "profile smoke" in result.output
    assert "paper" in result.output


def test_cli_unknown_stage_is_a_usage_error(tmp_path):
    result = CliRunner().invoke(app, ["build", "--scene", URI, "--stages", "ingest,fitt",
                                      "--data", str(tmp_path)])
    assert result.exit_code == 2
    assert "unknown stage 'fitt'" in result.output


def test_each_stage_appends_to_the_scene_log_and_leaves_no_file_open(tmp_path):
    import logging

    config = StageRegistry().resolve("smoke")
    result = run_scene_stage(config, "ingest", URI, tmp_path)
    run_scene_stage(config, "ingest", URI, tmp_path)
    text = (tmp_path / "logs" / f"{result.scene_id}.log").read_text()
    assert text.count("ingest: started") == 1 and text.count("up to date") == 1
    handlers = logging.getLogger(f"paradrive.scene.{result.scene_id}").handlers
    assert not any(isinstance(h, logging.FileHandler) for h in handlers)
