"""A scene that can give no clip (too few frames, or no camera render.cameras names) fails right
after its ingest, named with its frames, a clip's frames and the fix, before any fit runs; the
plan shows it too."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from paradrive.cli import app
from paradrive.ingest import export
from paradrive.pipeline import StageRegistry
from paradrive.pipeline.budget import plan_build
from paradrive.pipeline.ledger import Ledger
from paradrive.streams import clip_shortfall
from paradrive.synthetic import SyntheticStreet

CAMS = ("front", "front_left", "front_right")
TINY = ["--set", "ingest.synthetic_frames=10", "--set", "ingest.synthetic_width=48",
        "--set", "ingest.synthetic_height=32"]


def build(tmp_path, *args: str):
    return CliRunner().invoke(app, ["build", "--profile", "smoke", "--data", str(tmp_path / "data"),
                                    "--manifests", str(tmp_path / "m"), "--build", "b", *args])


def test_a_one_frame_waymo_record_fails_after_ingest_naming_its_frames_and_the_fix(tmp_path):
    record = tmp_path / "logs" / "segment-1234_with_camera_labels.tfrecord"
    export.export_waymo(SyntheticStreet("demo", seed=3, frames=1, width=64, height=48, cameras=CAMS),
                        record)
    result = build(tmp_path, "--scene", f"waymo:{record}")
    assert result.exit_code != 0, result.output
    scene_dir = tmp_path / "data" / "scenes" / "waymo-1234"
    message = ("scene waymo-1234: it has 1 frame, and a clip needs 9 (render.clip_frames) "
               f"({scene_dir / 'scene.json'}); set a shorter render.clip_frames (at most 1) "
               "or use another scene")
    assert message in " ".join(result.output.split())
    assert (scene_dir / "scene.json").is_file()                 # the ingest landed ...
    assert not (scene_dir / "gs").exists()                      # ... and no fit began
    ledger = Ledger.for_reading(tmp_path / "m" / "b" / "ledger.sqlite")
    assert ledger.scene_states() == {"waymo-1234": "failed"}
    fit = ledger.task("waymo-1234", "fit")
    assert fit is not None and fit["state"] == "failed" and message in fit["error"]
    assert ledger.task("waymo-1234", "render")["state"] == "blocked"


def test_a_scene_without_the_render_camera_fails_before_its_fit(tmp_path):
    uri = "synthetic:demo?seed=7"
    result = build(tmp_path, "--scene", uri, *TINY, "--set", 'ingest.cameras=["front_left"]',
                   "--stages", "ingest,fit")
    assert result.exit_code != 0, result.output
    text = " ".join(result.output.split())
    assert "it has no camera front, which render.cameras needs for its pairs (it has front_left)" in text
    assert "ingest that camera (ingest.cameras)" in text
    (scene_dir,) = (tmp_path / "data" / "scenes").iterdir()
    assert not (scene_dir / "gs").exists()


def test_a_clip_needs_clip_frames_frames_of_every_render_camera():
    assert clip_shortfall(8, CAMS, ["front"], 8) is None
    short = clip_shortfall(7, CAMS, ["front"], 8)
    assert short is not None and short.what.startswith("it has 7 frames, and a clip needs 8")
    assert "at most 7" in short.fix
    assert clip_shortfall(200, ["back"], ["front"], 8) is not None


def test_the_plan_shows_a_scene_that_can_give_no_clip_and_spends_nothing_past_its_ingest():
    config = StageRegistry().resolve("smoke")
    plan = plan_build(config, ["synthetic:demo?seed=3&frames=5", "synthetic:demo?seed=4&frames=10"], None)
    assert list(plan.unfit) == ["synthetic-demo-s3-frames5"]
    assert "it has 5 frames, and a clip needs 9" in plan.unfit["synthetic-demo-s3-frames5"]
    alone = plan_build(config, ["synthetic:demo?seed=4&frames=10"], None)
    assert plan.seconds["fit"] == alone.seconds["fit"] and plan.pairs == alone.pairs
    assert plan.seconds["ingest"] > alone.seconds["ingest"]
    result = CliRunner().invoke(app, ["plan", "--profile", "smoke", "--scene", "synthetic:demo?seed=3&frames=5",
                                      "--data", "/nonexistent-data-root"])
    assert result.exit_code == 0, result.output
    assert "no clip" in result.output and "synthetic-demo-s3-frames5" in result.output
    doc = json.loads(CliRunner().invoke(app, ["plan", "--profile", "smoke", "--json", "--scene",
                                              "synthetic:demo?seed=3&frames=5"]).output)
    assert "render.clip_frames" in doc["unfit"]["synthetic-demo-s3-frames5"]
