"""A scene's lease on an object store is never held by two builds at once.

The store is moto's local S3 server. A lease expires ``LEASE_SECONDS`` after it is written
(never counted from before a wait) and is renewed every third of that; a build whose lease was
taken stops its stage before it writes anything more, and a plain re-run builds the scene; a
holder killed on another machine is taken over once its lease expires. The lease is made short
here, so that waiting builds wait longer than a lease lives."""

from __future__ import annotations

import json
import logging
import queue
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import pytest

from paradrive.pipeline import locks
from paradrive.pipeline.locks import Holder, LockOptions, scene_lock
from paradrive.pipeline.runner import run_scene_stage
from paradrive.storage import DataRoot

import pipeline_stages

ROOT = Path(__file__).resolve().parents[1]
SCENE, SID = "synthetic:street?seed=1", "synthetic-street-s1"
RENEWALS_HELD = 4   # each holder keeps the scene this many renewals: longer than a lease lives


@pytest.fixture
def store(s3_bucket, tmp_path):
    url = f"s3://builds/{uuid.uuid4().hex[:8]}"
    root = DataRoot.of(url, storage_options=s3_bucket, cache_dir=str(tmp_path / "cache"))
    fs, base = root.filesystem()
    return {"root": root, "fs": fs, "lease": f"{base}/locks/{SID}.json", "url": url,
            "options": s3_bucket}


@pytest.fixture
def renewals(monkeypatch):
    """token -> a queue that gets each renewal of that lease."""
    monkeypatch.setattr(locks, "LEASE_SECONDS", 1.5)   # renewed every 0.5 s
    seen: dict[str, queue.Queue] = {}
    renew = locks._Lease.renew

    def reported(self, holder):
        renewed = renew(self, holder)
        if renewed is not None:
            seen.setdefault(holder.token, queue.Queue()).put(renewed)
        return renewed

    monkeypatch.setattr(locks._Lease, "renew", reported)
    return seen


def test_three_builds_on_one_scene_never_hold_it_together(store, renewals):
    intervals: list[tuple[float, float, str]] = []
    failures: list[BaseException] = []
    start = threading.Barrier(3)

    def build(name: str) -> None:
        try:
            start.wait(60)
            with scene_lock(store["root"], SID, LockOptions(name, timeout=120)) as held:
                began = time.monotonic()
                assert json.loads(store["fs"].cat_file(store["lease"]))["token"] == held.holder.token
                mine = renewals.setdefault(held.holder.token, queue.Queue())
                got = 0
                for _ in range(20 * RENEWALS_HELD):   # each wait ends with a renewal or a lease
                    if got == RENEWALS_HELD or held.lost:
                        break
                    try:
                        got += bool(mine.get(timeout=locks.LEASE_SECONDS))
                    except queue.Empty:
                        continue
                intervals.append((began, time.monotonic(), name))
                assert not held.lost, f"{name}: {held.lost}"
                assert got == RENEWALS_HELD
        except BaseException as exc:   # reported below, on the test's thread
            failures.append(exc)

    threads = [threading.Thread(target=build, args=(f"b{k}",)) for k in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(300)
    assert not failures, failures
    assert sorted(name for *_, name in intervals) == ["b0", "b1", "b2"]
    ordered = sorted(intervals)
    for (_, ended, first), (began, _, second) in zip(ordered, ordered[1:]):
        assert began >= ended, f"{first} and {second} held the scene together"
    assert not store["fs"].exists(store["lease"])


# a build on another machine that takes the lease, says so and waits to be killed
HOLDER = """
import json, socket, sys
socket.gethostname = lambda: "elsewhere"   # its death cannot be seen from here: only its expiry
from paradrive.pipeline import locks
from paradrive.storage import DataRoot
locks.LEASE_SECONDS = float(sys.argv[4])
root = DataRoot.of(sys.argv[1], storage_options=json.loads(sys.argv[2]), cache_dir=sys.argv[3])
with locks.scene_lock(root, sys.argv[5], locks.LockOptions("doomed")):
    print("held", flush=True)
    sys.stdin.readline()
"""


def test_a_holder_killed_elsewhere_is_taken_over_once_its_lease_expires(store, renewals, tmp_path):
    proc = subprocess.Popen([sys.executable, "-c", HOLDER, store["url"], json.dumps(store["options"]),
                             str(tmp_path / "other-cache"), str(locks.LEASE_SECONDS), SID], cwd=ROOT,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "held"
    finally:
        proc.kill()
        proc.wait()
    left = Holder.parse(store["fs"].cat_file(store["lease"]))
    assert left is not None and left.build == "doomed" and left.host == "elsewhere"
    with scene_lock(store["root"], SID, LockOptions("next", timeout=120)) as held:
        assert time.time() > left.expires_at   # not before the dead holder's lease ran out
        assert held.took_over.startswith("build doomed (host elsewhere, pid ")
        assert held.took_over.endswith("(lease expired)")
    assert not store["fs"].exists(store["lease"])


class _Said(logging.Handler):
    def __init__(self, words: str, event: threading.Event):
        super().__init__()
        self.words, self.event = words, event

    def emit(self, record: logging.LogRecord) -> None:
        if self.words in record.getMessage():
            self.event.set()


def test_a_stage_whose_lease_was_taken_stops_before_writing_and_a_rerun_builds_it(
        store, renewals, monkeypatch, tmp_path, stage_config):
    config = stage_config()
    root, fs = store["root"], store["fs"]
    assert run_scene_stage(config, "ingest", SCENE, root, locks=LockOptions("b1", 0)).status == "done"
    started, taken, lost = threading.Event(), threading.Event(), threading.Event()
    fit = pipeline_stages.run_fit

    def fit_that_reports(ctx):
        started.set()
        assert taken.wait(60)
        assert lost.wait(60)       # the keep-alive found the lease another build's
        ctx.progress(1, 2)         # the stage's next report: it stops here
        return fit(ctx)

    monkeypatch.setattr(pipeline_stages, "run_fit", fit_that_reports)
    said = _Said("stopping the stage", lost)
    monkeypatch.setattr(logging.getLogger("paradrive.locks"), "handlers", [said])
    result: list = []
    runner = threading.Thread(target=lambda: result.append(
        run_scene_stage(config, "fit", SCENE, root, locks=LockOptions("b1", 0))))
    runner.start()
    assert started.wait(60)
    other = Holder(build="b2", host="elsewhere", pid=1, started_at=time.time(),
                   expires_at=time.time() + 600, token="theirs")
    fs.pipe_file(store["lease"], other.dumps().encode())   # another build took the scene
    taken.set()
    runner.join(120)
    (stopped,) = result
    assert stopped.status == "failed"
    assert stopped.error == (f"scene {SID}: its lease was taken by {other.describe()}; the stage "
                             f"stopped before writing more; re-run the build (a plain re-run "
                             f"builds the scene, or finds it done)")
    base = store["lease"].rsplit("/locks/", 1)[0]
    assert not fs.exists(f"{base}/scenes/{SID}/.paradrive/fit.json")
    assert not fs.exists(f"{base}/scenes/{SID}/gs")                       # nothing uploaded
    assert json.loads(fs.cat_file(store["lease"]))["token"] == "theirs"  # and theirs left alone

    fs.rm_file(store["lease"])                                          # that build finished
    monkeypatch.setattr(pipeline_stages, "run_fit", fit)
    again = run_scene_stage(config, "fit", SCENE, root, locks=LockOptions("b1", 0))
    assert again.status == "done", again.error
    assert fs.exists(f"{base}/scenes/{SID}/.paradrive/fit.json")
