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
import weakref
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


class SteppedClock(locks.LeaseClock):
    """Lease time that moves only when the test moves it: a renewal cannot be late, however
    little CPU its thread gets, and a lease expires only when the test lets it."""

    def __init__(self) -> None:
        self.t = time.time()
        self.moved = threading.Condition()
        # a holder's keep-alive (its stop event) -> the time its last wait was due
        self.beats: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


    def now(self) -> float:
        with self.moved:
            return self.t

    def advance(self, seconds: float) -> None:
        with self.moved:
            self.t += seconds
            self.moved.notify_all()

    def wait(self, stop: threading.Event, seconds: float) -> bool:
        """Until ``seconds`` after this keep-alive's last wait was due (a beat the test made
        while it was busy renewing still counts), or ``stop``."""
        with self.moved:
            until = self.beats.get(stop, self.t) + seconds
            while self.t < until and not stop.is_set():
                self.moved.wait(0.05)   # and look at ``stop`` again: a holder leaving sets it
            self.beats[stop] = until
            return stop.is_set()


GUARD_S = 600   # a wait this long means a deadlock, not a slow machine


def test_three_builds_on_one_scene_never_hold_it_together(store, monkeypatch):
    """Each build holds the scene for RENEWALS_HELD renewals (longer than a lease lives); the
    test moves the lease clock a renewal's beat at a time, only once the holder has renewed."""
    clock = SteppedClock()
    monkeypatch.setattr(locks, "CLOCK", clock)
    events: queue.Queue = queue.Queue()   # ("acquired", name, token) and ("renewed", token)
    renew = locks._Lease.renew

    def reported(self, holder):
        renewed = renew(self, holder)
        if renewed is not None:
            events.put(("renewed", holder.token))
        return renewed

    monkeypatch.setattr(locks._Lease, "renew", reported)
    holding: list[str] = []
    failures: list[BaseException] = []
    done = {f"b{k}": threading.Event() for k in range(3)}

    def build(name: str) -> None:
        try:
            with scene_lock(store["root"], SID, LockOptions(name, timeout=GUARD_S)) as held:
                assert not holding, f"{name} took the scene while {holding} held it"
                holding.append(name)
                assert json.loads(store["fs"].cat_file(store["lease"]))["token"] == held.holder.token
                events.put(("acquired", name, held.holder.token))
                assert done[name].wait(GUARD_S)
                assert not held.lost, f"{name}: {held.lost}"
                holding.remove(name)
        except BaseException as exc:   # reported below, on the test's thread
            failures.append(exc)
            events.put(("failed", name, repr(exc)))

    threads = [threading.Thread(target=build, args=(name,)) for name in done]
    for t in threads:
        t.start()
    order = []
    for _ in threads:
        kind, name, token = events.get(timeout=GUARD_S)
        assert kind == "acquired", (kind, name, token, failures)
        order.append(name)
        for _beat in range(RENEWALS_HELD):
            clock.advance(locks.LEASE_SECONDS / 3)
            assert events.get(timeout=GUARD_S) == ("renewed", token), failures
        done[name].set()
    for t in threads:
        t.join(GUARD_S)
    assert not failures, failures
    assert sorted(order) == ["b0", "b1", "b2"]
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
