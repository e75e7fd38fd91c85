"""The status ledger: per (scene, stage) state in SQLite, safe for concurrent writers; `paradrive status`."""

from __future__ import annotations

import json
import multiprocessing
import pickle
import sqlite3

import pytest
from typer.testing import CliRunner

from paradrive.errors import ConfigError
from paradrive.pipeline.ledger import Ledger, LedgerError
from paradrive.pipeline.runner import StageResult

A, B, C = "synthetic:a?seed=1", "synthetic:b?seed=2", "synthetic:c?seed=3"
AID, BID, CID = "synthetic-a-s1", "synthetic-b-s2", "synthetic-c-s3"
STAGES = ["ingest", "fit", "render"]


@pytest.fixture
def ledger(tmp_path):
    return Ledger.for_build(tmp_path / "manifests", "b1")


def run_scene(ledger, uri, sid, outcome="done", seconds=2.0, error=""):
    """Feed the ledger what an executor would for one scene: start + result per stage."""
    for stage in STAGES:
        ledger.start(uri, stage)
        status = outcome if stage == "fit" else ("done" if outcome != "failed" or stage == "ingest"
                                                 else "blocked")
        if status == "blocked":
            ledger.record(StageResult(sid, stage, "blocked", error="not run: fit failed"))
            continue
        ledger.record(StageResult(sid, stage, status, seconds=seconds if status == "done" else 0.0,
                                  error=error if status == "failed" else "", peak_rss_mb=100.0))


def test_ledger_lives_in_the_build_folder_in_wal_mode(ledger, tmp_path):
    path = tmp_path / "manifests" / "b1" / "ledger.sqlite"
    assert ledger.path == path and path.is_file()
    conn = sqlite3.connect(path)
    assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert ledger.meta()["schema_version"] == "1" and ledger.meta()["build"] == "b1"


def test_register_makes_every_scene_stage_pending(ledger):
    ledger.register([A, B], STAGES, ["manifest"])
    rows = ledger.tasks()
    assert [(r["scene_id"], r["stage"]) for r in rows] == (
        [(AID, s) for s in STAGES] + [(BID, s) for s in STAGES] + [("build:b1", "manifest")])
    assert {r["state"] for r in rows} == {"pending"}
    assert rows[0]["scene_uri"] == A
    assert ledger.scene_states() == {AID: "pending", BID: "pending"}


def test_start_and_record_track_state_attempts_time_and_memory(ledger):
    ledger.register([A], STAGES)
    ledger.start(A, "ingest")  # executors hand the URI
    row = ledger.task(AID, "ingest")
    assert row["state"] == "running" and row["attempts"] == 1 and row["started_at"]
    ledger.record(StageResult(AID, "ingest", "done", seconds=3.5, peak_rss_mb=250.0,
                              fingerprint="abc"))
    row = ledger.task(AID, "ingest")
    assert row["state"] == "done" and row["seconds"] == 3.5 and row["peak_rss_mb"] == 250.0
    assert row["fingerprint"] == "abc" and row["finished_at"] >= row["started_at"]
    assert [e["state"] for e in ledger.events(AID)] == ["running", "done"]


def test_a_skip_is_no_attempt_and_keeps_the_time_of_the_run_that_made_the_outputs(ledger):
    ledger.register([A], STAGES)
    ledger.start(A, "fit")
    ledger.record(StageResult(AID, "fit", "done", seconds=40.0))
    ledger.register([A], STAGES)  # the next run
    ledger.start(A, "fit")
    ledger.record(StageResult(AID, "fit", "skipped", fingerprint="f"))
    row = ledger.task(AID, "fit")
    assert row["state"] == "skipped" and row["attempts"] == 1 and row["seconds"] == 40.0


def test_failures_are_kept_with_reason_and_retry_counts_attempts(ledger):
    ledger.register([A, B, C], STAGES)
    run_scene(ledger, A, AID)
    run_scene(ledger, B, BID, "failed", error="scene b: frame 3 is truncated (images/000003.jpg)")
    run_scene(ledger, C, CID)
    assert ledger.scene_states() == {AID: "done", BID: "failed", CID: "done"}
    assert ledger.failed_scene_uris() == [B]
    fit = ledger.task(BID, "fit")
    assert fit["state"] == "failed" and "truncated" in fit["error"]
    assert ledger.task(BID, "render")["state"] == "blocked"
    # --retry-failed: register the subset without retiring the others, run it again
    ledger.register([B], STAGES, replace=False)
    run_scene(ledger, B, BID)
    assert ledger.task(BID, "fit")["attempts"] == 2
    assert ledger.failed_scene_uris() == []
    assert ledger.scene_uris() == [A, B, C]  # the build keeps its scenes and their order


def test_a_run_over_other_scenes_retires_the_old_ones(ledger):
    ledger.register([A, B], STAGES)
    ledger.register([C], STAGES)
    assert ledger.scene_uris() == [C]
    assert ledger.scene_states() == {CID: "pending"}
    assert len(ledger.tasks(active_only=False)) == 9


def test_rows_left_running_by_a_killed_run_become_pending_on_the_next(ledger):
    ledger.register([A], STAGES)
    ledger.start(A, "ingest")  # the process died here
    assert ledger.scene_states() == {AID: "running"}
    ledger.register([A], STAGES)
    assert ledger.task(AID, "ingest")["state"] == "pending"


def test_summary_counts_times_slowest_and_failures(ledger):
    ledger.register([A, B, C], STAGES, ["manifest"])
    ledger.begin_run("local", 3, command="paradrive build")
    run_scene(ledger, A, AID, seconds=1.0)
    run_scene(ledger, B, BID, "failed", error="bad log")
    run_scene(ledger, C, CID, seconds=5.0)
    ledger.start("build:b1", "manifest")
    ledger.record(StageResult("build:b1", "manifest", "done", seconds=0.5))
    ledger.end_run(3)
    s = ledger.summary()
    assert s["scenes"] == 3 and s["counts"] == {"done": 2, "failed": 1, "running": 0, "pending": 0}
    fit = next(st for st in s["stages"] if st["stage"] == "fit")
    assert fit["done"] == 2 and fit["failed"] == 1 and fit["seconds_total"] == 6.0
    assert fit["seconds_max"] == 5.0 and fit["peak_rss_mb_max"] == 100.0
    assert s["slowest"][0]["scene_id"] == CID
    assert s["failures"] == [{"scene_id": BID, "scene_uri": B, "stage": "fit", "attempts": 1,
                              "seconds": 0.0, "peak_rss_mb": 100.0, "error": "bad log"}]
    assert s["build_stages"][0]["state"] == "done"
    assert s["last_run"]["exit_code"] == 3 and s["last_run"]["executor"] == "local"


def test_ledger_pickles_and_reopens_in_another_process(ledger):
    ledger.register([A], STAGES)
    copy = pickle.loads(pickle.dumps(ledger))
    copy.start(A, "ingest")
    assert ledger.task(AID, "ingest")["state"] == "running"


def _writer(path, worker, n):
    ledger = Ledger(path)
    for i in range(n):
        sid = f"synthetic-w{worker}-s{i}"
        ledger.start(sid, "fit")
        ledger.record(StageResult(sid, "fit", "done" if i % 5 else "failed", seconds=0.01,
                                  error="" if i % 5 else "boom"))


def test_concurrent_writers_from_many_processes_lose_nothing(ledger):
    ctx = multiprocessing.get_context("fork")
    procs = [ctx.Process(target=_writer, args=(str(ledger.path), w, 40)) for w in range(4)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(120)
    assert [p.exitcode for p in procs] == [0, 0, 0, 0]
    rows = ledger.tasks(active_only=False)
    assert len(rows) == 160
    assert sum(r["state"] == "failed" for r in rows) == 32
    assert len(ledger.events()) == 320


def test_open_existing_names_the_builds_that_have_a_ledger(tmp_path):
    Ledger.for_build(tmp_path, "real")
    with pytest.raises(ConfigError, match="builds with a ledger under .*: real"):
        Ledger.open_existing(tmp_path, "typo")


# -- paradrive status ---------------------------------------------------------------------------

@pytest.fixture
def filled(ledger):
    ledger.register([A, B, C], STAGES, ["manifest"])
    ledger.begin_run("ray", 3)
    run_scene(ledger, A, AID)
    run_scene(ledger, B, BID, "failed", error="scene synthetic-b-s2: waymo record 12 is garbage")
    ledger.start(C, "ingest")
    return ledger


def cli(*args):
    from paradrive.cli import app

    return CliRunner().invoke(app, list(args), env={"COLUMNS": "250"})


def test_status_shows_summary_stages_and_failures(filled, tmp_path):
    res = cli("status", "b1", "--manifests", str(tmp_path / "manifests"))
    assert res.exit_code == 0, res.output
    text = " ".join(res.output.split())
    assert "3 scenes: 1 done, 1 failed, 1 running, 0 pending" in text
    assert "waymo record 12 is garbage" in text
    assert "--retry-failed" in text
    for stage in STAGES:
        assert stage in text


def test_status_json_and_build_folder_argument(filled, tmp_path):
    res = cli("status", str(tmp_path / "manifests" / "b1"), "--json")
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    assert doc["counts"] == {"done": 1, "failed": 1, "running": 1, "pending": 0}
    assert doc["failures"][0]["scene_uri"] == B
    assert {s["stage"] for s in doc["stages"]} == {*STAGES, "manifest"}


def test_status_of_an_unknown_build_is_a_usage_error(tmp_path):
    res = cli("status", "nope", "--manifests", str(tmp_path))
    assert res.exit_code == 2
    assert "no ledger for build 'nope'" in " ".join(res.output.split())


def test_status_lists_every_scene_on_request(filled, tmp_path):
    res = cli("status", "b1", "--manifests", str(tmp_path / "manifests"), "--scenes")
    assert res.exit_code == 0
    assert AID in res.output and CID in res.output


def test_a_ledger_that_is_not_a_database_is_moved_aside_and_rebuilt_from_the_markers(tmp_path):
    build_dir, scene_dir = tmp_path / "manifests" / "b1", tmp_path / "data" / "scenes" / AID
    for folder, stage, extra in ((scene_dir, "ingest", {}),
                                 (scene_dir, "fit", {"upstream_runs": {"ingest": "r1"}}),
                                 (build_dir, "manifest", {})):
        (folder / ".paradrive").mkdir(parents=True, exist_ok=True)
        (folder / ".paradrive" / f"{stage}.json").write_text(json.dumps(
            {"stage": stage, "fingerprint": f"fp-{stage}", "seconds": 4.0, "run": "r1", **extra}))
    (build_dir / "index.json").write_text(json.dumps(
        {"scenes": [{"scene_id": AID, "scene_uri": A, "scene_dir": str(scene_dir)}]}))
    (build_dir / "ledger.sqlite").write_bytes(b"\x00garbage" * 100)
    ledger = Ledger.for_build(tmp_path / "manifests", "b1")
    assert "not a database" in ledger.recovered and "ledger.sqlite.corrupt-" in ledger.recovered
    assert [(r["scene_id"], r["stage"], r["state"], r["seconds"]) for r in ledger.tasks()] == [
        (AID, "ingest", "done", 4.0), (AID, "fit", "done", 4.0), ("build:b1", "manifest", "done", 4.0)]
    (aside,) = build_dir.glob("ledger.sqlite.corrupt-*")
    assert aside.read_bytes() == b"\x00garbage" * 100  # kept for a person to look at


def test_a_ledger_that_cannot_be_made_is_one_line_naming_the_file_and_the_fix(tmp_path):
    (tmp_path / "manifests").write_text("a file where the builds folder should be")
    with pytest.raises(LedgerError) as err:
        Ledger.for_build(tmp_path / "manifests", "b1")
    text = str(err.value)
    assert str(tmp_path / "manifests" / "b1" / "ledger.sqlite") in text and "\n" not in text
    assert "pass a writable --manifests" in text
