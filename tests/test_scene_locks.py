"""Many builds, one data root: a scene is locked while a stage of it runs.

Builds run as real ``paradrive build`` processes (the stand-in stages of ``pipeline_stages``
where only the locking matters, the real stages where the outputs must verify) over a folder
and over a URL root (moto's local S3 server; ``memory://`` within this process).
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
import uuid
from collections import Counter
from pathlib import Path

import pytest
from typer.testing import CliRunner

from paradrive.cli import app
from paradrive.inspection import verify_build
from paradrive.pairs import read_pairs
from paradrive.pipeline import StageRegistry, run_scene_stage
from paradrive.pipeline.ledger import Ledger
from paradrive.pipeline.locks import LockOptions, held_locks, scene_lock
from paradrive.storage import DataRoot

import pipeline_stages

ROOT = Path(__file__).resolve().parents[1]
SCENES = [f"synthetic:street?seed={s}" for s in (1, 2, 3, 4)]
IDS = [f"synthetic-street-s{s}" for s in (1, 2, 3, 4)]


def environment(stages: Path | None) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "PARADRIVE_STAGES"}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(ROOT / "tests")])
    if stages is not None:
        env["PARADRIVE_STAGES"] = str(stages)
    return env


def command(scenes: list[str], build: str, where: list[str], manifests: Path, *extra) -> list[str]:
    return [sys.executable, "-m", "paradrive.cli", "build",
            *[a for uri in scenes for a in ("--scene", uri)], *where,
            "--manifests", str(manifests), "--build", build, *extra]


def storage_flags(options: dict) -> list[str]:
    return [a for k, v in options.items() for a in ("--storage-option", f"{k}={json.dumps(v)}")]


@pytest.fixture
def stand_in(tmp_path):
    return pipeline_stages.write_stages(tmp_path / "stages")


@pytest.fixture(params=["folder", "s3"])
def data_root(request, tmp_path):
    """Where the builds write: a folder, or a fresh prefix of the local S3 bucket (both builds of
    a test share one cache folder, as two builds on one machine would)."""
    if request.param == "folder":
        return {"root": DataRoot.of(tmp_path / "data"), "flags": ["--data", str(tmp_path / "data")],
                "status_flags": []}
    options = request.getfixturevalue("s3_bucket")
    url = f"s3://builds/{uuid.uuid4().hex[:8]}"
    cache = tmp_path / "cache"
    return {"root": DataRoot.of(url, storage_options=options, cache_dir=str(cache)),
            "flags": ["--data", url, *storage_flags(options), "--cache", str(cache)],
            "status_flags": storage_flags(options)}


# -- waiting, giving up, status ------------------------------------------------------------------

@pytest.fixture(params=["folder", "memory"])
def any_root(request, tmp_path):
    if request.param == "folder":
        yield DataRoot.of(tmp_path / "data")
        return
    url = f"memory://locks-{uuid.uuid4().hex[:8]}/data"
    yield DataRoot.of(url, cache_dir=str(tmp_path / "cache"))
    fs, base = DataRoot.of(url).filesystem()
    fs.rm(base.rsplit("/", 1)[0], recursive=True)


def test_a_held_scene_is_waited_for_then_left_naming_the_build_that_holds_it(any_root, stage_config):
    config = stage_config()
    with scene_lock(any_root, IDS[0], LockOptions("b1")):
        assert {sid: h.build for sid, h in held_locks(any_root).items()} == {IDS[0]: "b1"}
        result = run_scene_stage(config, "ingest", SCENES[0], any_root,
                                 locks=LockOptions("b2", timeout=0.5))
        other = run_scene_stage(config, "ingest", SCENES[1], any_root, locks=LockOptions("b2", 0))
    assert result.status == "failed"
    assert (f"scene {IDS[0]}: locked by build b1 (host {socket.gethostname()}, pid {os.getpid()}"
            in result.error and "re-run once that build finished it" in result.error)
    assert other.status == "done"  # other scenes are free
    assert held_locks(any_root) == {}
    assert run_scene_stage(config, "ingest", SCENES[0], any_root, locks=LockOptions("b2", 0)).status == "done"


def test_status_shows_the_locked_scenes_and_who_holds_them(tmp_path, stand_in, monkeypatch):
    monkeypatch.setenv("PARADRIVE_STAGES", str(stand_in))
    data, manifests = tmp_path / "data", tmp_path / "manifests"
    res = CliRunner().invoke(app, ["build", "--scene", SCENES[0], "--scene", SCENES[1], "--data",
                                   str(data), "--manifests", str(manifests), "--build", "b2"])
    assert res.exit_code == 0, res.output
    with scene_lock(DataRoot.of(data), IDS[1], LockOptions("b1")):
        res = CliRunner().invoke(app, ["status", "b2", "--manifests", str(manifests)],
                                 env={"COLUMNS": "250"})
        doc = json.loads(CliRunner().invoke(app, ["status", "b2", "--manifests", str(manifests),
                                                  "--json"]).output)
    assert res.exit_code == 0, res.output
    assert "locked scenes" in res.output and f"{IDS[1]}" in res.output
    assert f"build b1 (host {socket.gethostname()}, pid {os.getpid()}" in res.output
    assert [(lock["scene_id"], lock["build"], lock["pid"]) for lock in doc["locks"]] == [
        (IDS[1], "b1", os.getpid())]
    after = json.loads(CliRunner().invoke(app, ["status", "b2", "--manifests", str(manifests),
                                                "--json"]).output)
    assert after["locks"] == []


def test_status_without_object_store_credentials_shows_the_ledger_and_says_why_no_locks(
        tmp_path, stand_in, s3_bucket):
    """A real `paradrive status` against the test S3 store with no credentials anywhere (no
    AWS_* variables, no credentials or config file): the ledger, and one line naming the error."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("AWS_")}
    env.update(PARADRIVE_STAGES=str(stand_in), AWS_SHARED_CREDENTIALS_FILE=str(tmp_path / "none"),
               AWS_CONFIG_FILE=str(tmp_path / "none"), AWS_EC2_METADATA_DISABLED="true",
               COLUMNS="250")
    manifests = tmp_path / "manifests"
    res = CliRunner().invoke(app, ["build", "--scene", SCENES[0], "--data", str(tmp_path / "data"),
                                   "--manifests", str(manifests), "--build", "b3"], env=env)
    assert res.exit_code == 0, res.output
    command = [sys.executable, "-m", "paradrive.cli", "status", "b3", "--manifests", str(manifests),
               "--data", "s3://builds/no-credentials", "--storage-option",
               f"endpoint_url={s3_bucket['endpoint_url']}"]
    done = subprocess.run(command, env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stdout + done.stderr
    assert IDS[0] in done.stdout and "locks not shown:" in done.stdout
    assert "NoCredentialsError" in done.stdout and "s3://builds/no-credentials" in done.stdout
    doc = json.loads(subprocess.run(command + ["--json"], env=env, capture_output=True, text=True,
                                    check=True).stdout)
    assert doc["locks"] == [] and "NoCredentialsError" in doc["locks_error"]


def test_an_expired_lease_is_taken_over_and_a_live_one_is_not(tmp_path, stand_in, monkeypatch):
    monkeypatch.setenv("PARADRIVE_STAGES", str(stand_in))
    url = f"memory://lease-{uuid.uuid4().hex[:8]}/data"
    fs, base = DataRoot.of(url).filesystem()
    now = time.time()
    lease = {"build": "old", "host": "elsewhere", "pid": 1, "started_at": now - 600, "token": "t"}
    fs.pipe_file(f"{base}/locks/{IDS[0]}.json", json.dumps({**lease, "expires_at": now - 5}).encode())
    fs.pipe_file(f"{base}/locks/{IDS[1]}.json", json.dumps({**lease, "expires_at": now + 600}).encode())
    args = ["build", "--scene", SCENES[0], "--scene", SCENES[1], "--data", url, "--cache",
            str(tmp_path / "cache"), "--manifests", str(tmp_path / "m"), "--build", "new",
            "--lock-timeout", "0", "--stages", "ingest"]
    try:
        res = CliRunner().invoke(app, args, env={"COLUMNS": "250"})
        assert res.exit_code == 3, res.output
        ledger = Ledger.for_build(tmp_path / "m", "new")
        assert ledger.task(IDS[0], "ingest")["state"] == "done"
        assert "locked by build old (host elsewhere, pid 1" in ledger.task(IDS[1], "ingest")["error"]
        takeovers = ledger.takeovers()
        assert [(t["scene_id"], t["stage"]) for t in takeovers] == [(IDS[0], "ingest")]
        assert "build old (host elsewhere, pid 1" in takeovers[0]["error"]
        assert "lease expired" in takeovers[0]["error"]
        assert not fs.exists(f"{base}/locks/{IDS[0]}.json")  # released after the stage
    finally:
        fs.rm(base.rsplit("/", 1)[0], recursive=True)


def test_a_lease_is_renewed_while_its_holder_works(monkeypatch, tmp_path):
    import queue

    from paradrive.pipeline import locks

    monkeypatch.setattr(locks, "LEASE_SECONDS", 1.5)  # renewed every 0.5 s
    renewals: queue.Queue = queue.Queue()
    renew = locks._Lease.renew

    def reported_renew(self, holder):
        renewed = renew(self, holder)
        renewals.put(renewed)
        return renewed

    monkeypatch.setattr(locks._Lease, "renew", reported_renew)
    root = DataRoot.of(f"memory://renew-{uuid.uuid4().hex[:8]}/data", cache_dir=str(tmp_path))
    fs, base = root.filesystem()
    lease = f"{base}/locks/{IDS[0]}.json"
    try:
        with scene_lock(root, IDS[0], LockOptions("b1")):
            first = json.loads(fs.cat_file(lease))["expires_at"]
            # wait for the renewals up to one made after the first expiry: only they keep it now
            while (renewed := renewals.get()) is not None and \
                    renewed.expires_at - locks.LEASE_SECONDS <= first:
                pass
            assert renewed is not None, "the lease was lost"
            later = json.loads(fs.cat_file(lease))["expires_at"]
            assert later > first
            with pytest.raises(locks.SceneLocked, match="locked by build b1"):
                with scene_lock(root, IDS[0], LockOptions("b2", timeout=0)):
                    pass
        assert not fs.exists(lease)
    finally:
        with contextlib.suppress(FileNotFoundError):
            fs.rm(base.rsplit("/", 1)[0], recursive=True)


# -- a holder killed with SIGKILL -----------------------------------------------------------------

def test_a_build_killed_holding_a_lock_is_taken_over_at_once(data_root, stand_in, tmp_path):
    root, where = data_root["root"], data_root["flags"]
    env = environment(stand_in)
    first = subprocess.Popen(command(SCENES[:1], "b1", where, tmp_path / "m"),
                             env={**env, "PARADRIVE_STOP_AT": "stand-in:fit"},
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        _, stopped = os.waitpid(first.pid, os.WUNTRACED)   # it stops itself inside fit
        assert os.WIFSTOPPED(stopped), "b1 ended before it reached fit"
        assert ("start", "fit", IDS[0]) in pipeline_stages.calls(root.local)
        status = CliRunner().invoke(app, ["status", "b1", "--manifests", str(tmp_path / "m"), "--json",
                                          *data_root["status_flags"]])
        assert status.exit_code == 0, status.output
        assert [(lock["scene_id"], lock["build"], lock["pid"])
                for lock in json.loads(status.output)["locks"]] == [(IDS[0], "b1", first.pid)]
        first.send_signal(signal.SIGKILL)
        # dead, not reaped (a zombie until this test waits for it): gone all the same
        os.waitid(os.P_PID, first.pid, os.WEXITED | os.WNOWAIT)
        # --lock-timeout 0: the build succeeds only if it takes the dead build's lock at once
        second = subprocess.run(command(SCENES[:1], "b2", where, tmp_path / "m", "--lock-timeout",
                                        "0"), env=env, capture_output=True, text=True, timeout=300)
    finally:
        first.kill()
        first.wait(30)
    assert second.returncode == 0, second.stdout[-3000:] + second.stderr[-3000:]
    ledger = Ledger.for_build(tmp_path / "m", "b2")
    assert ledger.task(IDS[0], "ingest")["state"] == "skipped"  # b1 had finished it
    assert ledger.task(IDS[0], "fit")["state"] == "done"
    takeovers = ledger.takeovers()  # noted where b2 first took the scene's lock
    assert [(t["scene_id"], t["stage"]) for t in takeovers] == [(IDS[0], "ingest")]
    assert f"build b1 (host {socket.gethostname()}, pid {first.pid}," in takeovers[0]["error"]
    assert held_locks(root) == {}


# -- two builds at once ----------------------------------------------------------------------------

def test_two_builds_started_together_share_the_scenes_and_run_each_stage_once(data_root, stand_in,
                                                                            tmp_path):
    """Overlapping scene lists in opposite orders, so that they meet on every shared scene."""
    root, where = data_root["root"], data_root["flags"]
    env = environment(stand_in)
    lists = {"b1": SCENES[:3], "b2": [SCENES[2], SCENES[1], SCENES[3]]}
    procs = {b: subprocess.Popen(command(s, b, where, tmp_path / "m", "--set", "fit.sleep_s=0.5"),
                                 env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
             for b, s in lists.items()}
    outputs = {b: p.communicate(timeout=300)[0] for b, p in procs.items()}
    for b, p in procs.items():
        assert p.returncode == 0, outputs[b][-3000:]
    ran = Counter(pipeline_stages.finished(root.local))
    assert {k: v for k, v in ran.items() if k[1] != "build"} == {
        (stage, sid): 1 for sid in IDS for stage in ("ingest", "fit", "render", "clip")}
    # the same bytes as one build of the four scenes alone
    from paradrive.pipeline import run_build

    alone = DataRoot.of(tmp_path / "alone")
    report = run_build(StageRegistry(stand_in).resolve(), SCENES, alone, manifests_dir=tmp_path / "am",
                       build="b")
    assert report.exit_code == 0
    assert pipeline_stages.scenes_digest(root) == pipeline_stages.scenes_digest(alone)
    rows = {b: {json.loads(line)["pair_id"]: line for line in
                (tmp_path / "m" / b / "pairs.jsonl").read_text().splitlines()} for b in lists}
    shared = [f"{IDS[i]}/{o}" for i in (1, 2) for o in ("+1.0", "-1.0")]
    assert all(rows["b1"][p] == rows["b2"][p] for p in shared)


@pytest.mark.slow
def test_two_real_builds_overlapping_on_shared_scenes_both_verify(tmp_path):
    """The reported case: builds b1 and b2 of the real stages over one folder and shared scenes."""
    env = environment(None)
    scenes = ["synthetic:demo?seed=7", "synthetic:demo?seed=8"]
    where = ["--data", str(tmp_path / "data"), "--profile", "smoke", *pipeline_stages.tiny_real_sets()]
    # b1 stops itself at its first rendered frame; b2 starts then, and b1 goes on beside it
    procs = {"b1": subprocess.Popen(command(scenes, "b1", where, tmp_path / "m"),
                                    env={**env, "PARADRIVE_STOP_AT": "render:frame-1"},
                                    stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)}
    _, stopped = os.waitpid(procs["b1"].pid, os.WUNTRACED)
    assert os.WIFSTOPPED(stopped), "b1 ended before its first rendered frame"
    procs["b2"] = subprocess.Popen(command(scenes[::-1], "b2", where, tmp_path / "m"), env=env,
                                   stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    os.kill(procs["b1"].pid, signal.SIGCONT)
    outputs = {b: p.communicate(timeout=600)[0] for b, p in procs.items()}
    for b, p in procs.items():
        assert p.returncode == 0, outputs[b][-3000:]
    states = {b: {(r["scene_id"], r["stage"]): r["state"] for r in Ledger.for_build(tmp_path / "m", b).tasks()
                  if not r["scene_id"].startswith("build:")} for b in procs}
    assert states["b1"].keys() == states["b2"].keys() and len(states["b1"]) == 8
    for key in states["b1"]:  # one build ran it, the other found it done
        assert sorted([states["b1"][key], states["b2"][key]]) == ["done", "skipped"], key
    for b in procs:
        check = verify_build(tmp_path / "m" / b)
        assert check["ok"], check["problems"]
    columns = ["pair_id"] + [f"{r}_sha256" for r in ("source", "condition", "target")]
    tables = [read_pairs(tmp_path / "m" / b).select(columns).sort_by("pair_id") for b in procs]
    assert tables[0].num_rows == 2 * 6 and tables[0].equals(tables[1])


def test_a_fresh_local_url_root_without_auto_mkdir_makes_the_folders_it_needs(tmp_path,
                                                                           stage_config):
    root = DataRoot.of(f"local://{tmp_path / 'fresh' / 'data'}", cache_dir=str(tmp_path / "cache"))
    assert "auto_mkdir" not in root.storage_options
    result = run_scene_stage(stage_config(), "ingest", SCENES[0], root, locks=LockOptions("b1", 0))
    assert result.status == "done", result.error
    assert (tmp_path / "fresh" / "data" / "scenes" / IDS[0] / ".paradrive" / "ingest.json").is_file()
    assert held_locks(root) == {}  # the lease is gone again, its folder stays
