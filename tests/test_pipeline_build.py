"""Builds of many scenes: scene lists and folders, partial builds, retrying failures, killing and resuming.

The pipeline here is the stand-in one of ``pipeline_stages`` (same stage names, milliseconds of
work), so these tests show the build machinery, not the image processing; the real stages are
exercised end to end in test_ray_executor.py.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from paradrive.errors import ConfigError
from paradrive.pipeline import StageRegistry, run_build
from paradrive.pipeline.build import EXIT_FAILED, EXIT_OK, EXIT_PARTIAL
from paradrive.pipeline.ledger import Ledger
from paradrive.pipeline.scenes import expand_scene_inputs

import pipeline_stages

ROOT = Path(__file__).resolve().parents[1]
SCENES = [f"synthetic:street?seed={s}" for s in (1, 2, 3)]
IDS = [f"synthetic-street-s{s}" for s in (1, 2, 3)]


# -- scene lists and folders of logs ------------------------------------------------------------

def test_list_file_with_comments_blank_lines_and_relative_paths(tmp_path):
    (tmp_path / "logs").mkdir()
    (tmp_path / "logs" / "segment-1_with_camera_labels.tfrecord").write_bytes(b"")
    listing = tmp_path / "scenes.txt"
    listing.write_text("# my scenes\n\nsynthetic:demo?seed=7   # the demo\n"
                       "nuscenes:/data/nuscenes?version=v1.0-mini#scene-0061\n"
                       "logs/segment-1_with_camera_labels.tfrecord\n")
    assert expand_scene_inputs([str(listing)]) == [
        "synthetic:demo?seed=7",
        "nuscenes:/data/nuscenes?version=v1.0-mini#scene-0061",  # a glued '#' is the fragment
        f"waymo:{tmp_path / 'logs' / 'segment-1_with_camera_labels.tfrecord'}"]


def test_folder_of_tfrecords_gives_one_waymo_scene_each(tmp_path):
    for name in ("b.tfrecord", "a.tfrecord", "sub/c.tfrecord", "notes.txt"):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_bytes(b"")
    assert expand_scene_inputs([str(tmp_path)]) == [
        f"waymo:{tmp_path / 'a.tfrecord'}", f"waymo:{tmp_path / 'b.tfrecord'}",
        f"waymo:{tmp_path / 'sub' / 'c.tfrecord'}"]


def test_nuscenes_dataroot_gives_one_scene_per_scene_record(tmp_path):
    (tmp_path / "v1.0-mini").mkdir()
    (tmp_path / "v1.0-mini" / "scene.json").write_text(json.dumps(
        [{"token": "t1", "name": "scene-0061"}, {"token": "t2", "name": "scene-0103"}]))
    (tmp_path / "samples").mkdir()
    uris = expand_scene_inputs([str(tmp_path)])
    assert uris == [f"nuscenes:{tmp_path}?version=v1.0-mini#scene-0061",
                    f"nuscenes:{tmp_path}?version=v1.0-mini#scene-0103"]
    from paradrive.uri import parse_uri
    assert parse_uri(uris[1]).scene_id == "nuscenes-scene-0103"


def test_drivestudio_processed_folders(tmp_path):
    for scene, poses in (("023", "ego_pose"), ("031", "extrinsics")):
        (tmp_path / scene / "images").mkdir(parents=True)
        (tmp_path / scene / poses).mkdir()
    (tmp_path / "README").mkdir()  # not a scene
    assert expand_scene_inputs([str(tmp_path)]) == [f"drivestudio:{tmp_path / '023'}",
                                                    f"drivestudio:{tmp_path / '031'}"]
    assert expand_scene_inputs([str(tmp_path / "031")]) == [f"drivestudio:{tmp_path / '031'}"]


def test_uris_pass_through_and_one_given_twice_is_refused():
    assert expand_scene_inputs(["synthetic:a", "waymo:/x/s.tfrecord"]) == [
        "synthetic:a", "waymo:/x/s.tfrecord"]
    with pytest.raises(ConfigError, match="--scenes synthetic:a and --scenes synthetic:a are the "
                                          "same log"):
        expand_scene_inputs(["synthetic:a", "waymo:/x/s.tfrecord", "synthetic:a"])


def test_nothing_found_says_what_was_expected(tmp_path):
    with pytest.raises(ConfigError, match="no scenes found; expected \\*.tfrecord"):
        expand_scene_inputs([str(tmp_path)])
    with pytest.raises(ConfigError, match="not a scene URI"):
        expand_scene_inputs([str(tmp_path / "missing.txt")])
    bad = tmp_path / "list.txt"
    bad.write_text("synthetic:ok\nno-such-file\n")
    with pytest.raises(ConfigError, match="list.txt:2: --scenes 'no-such-file'"):
        expand_scene_inputs([str(bad)])


# -- the build command ----------------------------------------------------------------------------

@pytest.fixture
def stand_in(tmp_path, monkeypatch):
    """The stand-in pipeline as the CLI's stage folder; a scene list; where things go."""
    folder = pipeline_stages.write_stages(tmp_path / "stages")
    monkeypatch.setenv("PARADRIVE_STAGES", str(folder))
    listing = tmp_path / "scenes.txt"
    listing.write_text("\n".join(SCENES) + "\n")
    return {"stages": folder, "list": listing, "data": tmp_path / "data",
            "manifests": tmp_path / "manifests"}


def cli_build(env, *extra):
    from paradrive.cli import app

    args = ["build", "--data", str(env["data"]), "--manifests", str(env["manifests"]),
            "--build", "b", *extra]
    return CliRunner().invoke(app, args, env={"COLUMNS": "250"})


def pairs(manifests: Path) -> list[dict]:
    return [json.loads(line) for line in (manifests / "b" / "pairs.jsonl").read_text().splitlines()]


def test_build_from_a_scene_list_records_every_stage_in_the_ledger(stand_in):
    res = cli_build(stand_in, "--scenes", str(stand_in["list"]))
    assert res.exit_code == EXIT_OK, res.output
    assert "3 of 3 scenes done" in res.output
    ledger = Ledger.for_build(stand_in["manifests"], "b")
    assert ledger.scene_states() == {sid: "done" for sid in IDS}
    assert ledger.task("build:b", "manifest")["state"] == "done"
    assert {r["attempts"] for r in ledger.tasks()} == {1}
    assert ledger.runs()[-1]["exit_code"] == 0 and ledger.runs()[-1]["executor"] == "local"
    assert {r["scene_id"] for r in pairs(stand_in["manifests"])} == set(IDS)
    for sid in IDS:  # one log file per scene
        assert (stand_in["data"] / "logs" / f"{sid}.log").is_file()


def test_one_bad_scene_among_good_ones_is_a_partial_build(stand_in):
    bad = "synthetic:street?seed=4&fail=fit"
    res = cli_build(stand_in, "--scenes", str(stand_in["list"]), "--scene", bad)
    assert res.exit_code == EXIT_PARTIAL, res.output
    assert "3 of 4 scenes done; exit code 3 (partial build)" in res.output
    assert {r["scene_id"] for r in pairs(stand_in["manifests"])} == set(IDS)  # the good ones landed
    ledger = Ledger.for_build(stand_in["manifests"], "b")
    row = ledger.task("synthetic-street-s4-failfit", "fit")
    assert row["state"] == "failed"
    assert row["error"] == ("scene synthetic-street-s4-failfit: fit cannot read this scene (asked to "
                            f"fail) ({bad}); drop the scene")
    assert ledger.task("synthetic-street-s4-failfit", "render")["state"] == "blocked"
    assert ledger.failed_scene_uris() == [bad]


def test_a_bug_in_a_build_stage_fails_that_stage_and_the_run_still_closes(stand_in):
    spec = stand_in["stages"] / "manifest.yaml"
    spec.write_text(spec.read_text().replace("pipeline_stages:run_manifest",
                                             "pipeline_stages:run_manifest_with_a_bug"))
    res = cli_build(stand_in, "--scenes", str(stand_in["list"]))
    assert res.exception is None or isinstance(res.exception, SystemExit), res.output
    assert res.exit_code == EXIT_FAILED, res.output   # the publish failed: nothing landed
    ledger = Ledger.for_build(stand_in["manifests"], "b")
    row = ledger.task("build:b", "manifest")
    assert row["state"] == "failed" and "KeyError" in row["error"] and "crashed" in row["error"]
    assert ledger.scene_states() == {sid: "done" for sid in IDS}   # the scenes' work stands
    assert ledger.runs()[-1]["exit_code"] == EXIT_FAILED             # the run was closed


def test_every_scene_failing_is_a_failed_build(stand_in):
    res = cli_build(stand_in, "--scene", "synthetic:street?seed=4&fail=ingest")
    assert res.exit_code == EXIT_FAILED, res.output


def test_retry_failed_reruns_only_the_failed_scenes_and_publishes_the_whole_build(stand_in):
    broken = stand_in["data"] / f"broken-{IDS[1]}-render"
    broken.parent.mkdir(parents=True)
    broken.write_text("a fault the test repairs\n")
    assert cli_build(stand_in, "--scenes", str(stand_in["list"])).exit_code == EXIT_PARTIAL
    assert {r["scene_id"] for r in pairs(stand_in["manifests"])} == {IDS[0], IDS[2]}
    n = len(pipeline_stages.finished(stand_in["data"]))

    broken.unlink()
    res = cli_build(stand_in, "--retry-failed")
    assert res.exit_code == EXIT_OK, res.output
    redone = pipeline_stages.finished(stand_in["data"])[n:]
    assert sorted(redone) == [("clip", IDS[1]), ("manifest", "build"), ("render", IDS[1])]
    assert [r["scene_id"] for r in pairs(stand_in["manifests"])] == [i for i in IDS for _ in (0, 1)]
    ledger = Ledger.for_build(stand_in["manifests"], "b")
    assert ledger.scene_states() == {sid: "done" for sid in IDS}
    assert ledger.task(IDS[1], "render")["attempts"] == 2

    res = cli_build(stand_in, "--retry-failed")
    assert res.exit_code == EXIT_OK and "nothing to retry" in res.output


def test_a_scene_folder_argument_and_status_after_the_build(stand_in, tmp_path):
    from paradrive.cli import app

    res = cli_build(stand_in, "--scenes", str(stand_in["list"]), "--stages", "ingest,fit")
    assert res.exit_code == EXIT_OK, res.output
    res = CliRunner().invoke(app, ["status", "b", "--manifests", str(stand_in["manifests"]), "--json"])
    doc = json.loads(res.stdout)
    assert doc["counts"]["done"] == 3
    assert [s["stage"] for s in doc["stages"]] == ["ingest", "fit"]


def test_a_build_keeps_no_scene_log_file_open_once_the_scene_is_through(stand_in):
    """Thousands of scenes in one process must not exhaust its file handles."""
    import logging

    config = StageRegistry(stand_in["stages"]).resolve()
    run_build(config, SCENES, stand_in["data"], manifests_dir=stand_in["manifests"], build="b")
    for sid in IDS:
        handlers = logging.getLogger(f"paradrive.scene.{sid}").handlers
        assert not [h for h in handlers if isinstance(h, logging.FileHandler)]
        assert "clip: done" in (stand_in["data"] / "logs" / f"{sid}.log").read_text()


def test_unknown_scene_input_is_a_usage_error(stand_in):
    res = cli_build(stand_in, "--scenes", "no/such/list.txt")
    assert res.exit_code == 2
    assert "not a scene URI" in " ".join(res.output.split())


# -- killed midway, resumed -------------------------------------------------------------------------

def _env(stages: Path) -> dict:
    env = dict(os.environ)
    env["PARADRIVE_STAGES"] = str(stages)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(ROOT / "tests")])
    env["COLUMNS"] = "200"
    return env


def _build_cmd(root: Path, listing: Path) -> list[str]:
    return [sys.executable, "-m", "paradrive.cli", "build", "--scenes", str(listing),
            "--data", str(root / "data"), "--manifests", str(root / "manifests"), "--build", "b"]


def test_a_build_killed_midway_resumes_with_only_the_missing_work(tmp_path):
    stages = pipeline_stages.write_stages(tmp_path / "stages")
    listing = tmp_path / "scenes.txt"
    listing.write_text("\n".join(SCENES) + "\n")
    env = _env(stages)

    whole = tmp_path / "whole"  # the uninterrupted build, same stages and parameters
    config = StageRegistry(stages).resolve(None)
    assert run_build(config, SCENES, whole / "data", manifests_dir=whole / "manifests",
                     build="b").exit_code == EXIT_OK

    killed = tmp_path / "killed"
    held = pipeline_stages.hold(killed / "data", IDS[1], "fit")
    proc = subprocess.Popen(_build_cmd(killed, listing), env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:  # kill it while the second scene's fit is running (held there)
        assert pipeline_stages.wait_for_hold(held, proc) == "held", "the build ended before the kill"
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()
    held.unlink()
    assert ("fit", IDS[1]) not in pipeline_stages.finished(killed / "data")
    ledger = Ledger.for_build(killed / "manifests", "b")
    assert ledger.task(IDS[1], "fit")["state"] == "running"  # what the dead build left
    assert ledger.runs()[-1]["exit_code"] is None
    before = pipeline_stages.finished(killed / "data")

    resumed = subprocess.run(_build_cmd(killed, listing), env=env, capture_output=True, text=True,
                             timeout=240)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    redone = pipeline_stages.finished(killed / "data")[len(before):]
    # only the missing work ran: every scene stage finished exactly once over both runs
    assert sorted(before + redone) == sorted(
        [(st, sid) for sid in IDS for st in ("ingest", "fit", "render", "clip")] + [("manifest", "build")])
    assert ("fit", IDS[1]) in redone and ("ingest", IDS[1]) not in redone
    # and the result equals the uninterrupted build
    assert pipeline_stages.tree_digest(killed / "data") == pipeline_stages.tree_digest(whole / "data")
    assert pipeline_stages.tree_digest(killed / "manifests") == \
        pipeline_stages.tree_digest(whole / "manifests")
    assert not list((killed / "data").rglob(".*.tmp-*"))
    states = {(r["scene_id"], r["stage"]): r["state"] for r in ledger.tasks()}
    assert states[(IDS[0], "clip")] == "skipped" and states[(IDS[1], "fit")] == "done"
    assert states[(IDS[2], "ingest")] == "done" and ledger.runs()[-1]["exit_code"] == 0


def test_a_folder_of_tfrecords_files_lists_every_segment(tmp_path):
    from paradrive.pipeline.scenes import expand_scene_inputs

    (tmp_path / "a").mkdir()
    for name in ("a/segment-1.tfrecord", "segment-2.tfrecords"):
        (tmp_path / name).write_bytes(b"")
    uris = expand_scene_inputs([str(tmp_path)])
    assert sorted(u.rsplit("/", 1)[-1] for u in uris) == ["segment-1.tfrecord", "segment-2.tfrecords"]
