"""Logs that are not there are refused up front: ``plan`` and ``build`` of scene inputs whose
files do not exist exit 2 in one line (how many, the first few, the fix) before any work, and a
scene that never started leaves no lock file behind, whichever way it ended."""

from __future__ import annotations

import logging
import threading

import pytest
from typer.testing import CliRunner

from paradrive.cli import app
from paradrive.pipeline.locks import LockOptions, SceneLocked, scene_lock
from paradrive.storage import DataRoot

COUNT = 1000


@pytest.fixture
def missing_list(tmp_path):
    listing = tmp_path / "scenes.txt"
    listing.write_text("".join(f"waymo:{tmp_path}/nowhere/segment-{k}_with_camera_labels.tfrecord\n"
                               for k in range(COUNT)))
    return listing


def _one_line_about_the_missing(output: str, tmp_path) -> None:
    line = output.strip()
    assert "\n" not in line, output
    assert line.startswith(f"error: {COUNT} of {COUNT} scene input(s) do not exist: waymo:{tmp_path}"
                           f"/nowhere/segment-0_with_camera_labels.tfrecord, "), line
    assert line.endswith(f" and {COUNT - 3} more; fix their paths or leave them out, then re-run")


def test_plan_of_logs_that_are_not_there_exits_2_in_one_line(tmp_path, missing_list):
    res = CliRunner().invoke(app, ["plan", "--scenes", str(missing_list), "--data", str(tmp_path / "d")],
                             env={"COLUMNS": "100"})
    assert res.exit_code == 2
    _one_line_about_the_missing(res.output, tmp_path)


def test_build_of_logs_that_are_not_there_exits_2_before_any_work(tmp_path, missing_list):
    data, manifests = tmp_path / "data", tmp_path / "m"
    res = CliRunner().invoke(app, ["build", "--scenes", str(missing_list), "--profile", "smoke",
                                   "--data", str(data), "--manifests", str(manifests)],
                             env={"COLUMNS": "100"})
    assert res.exit_code == 2
    _one_line_about_the_missing(res.output, tmp_path)
    assert not data.exists() and not manifests.exists()   # no lock, no log, no ledger


def test_a_scene_that_never_started_leaves_no_lock_file(tmp_path):
    bad = tmp_path / "segment-9_with_camera_labels.tfrecord"
    bad.write_bytes(b"not a tfrecord at all")
    res = CliRunner().invoke(app, ["build", "--scene", f"waymo:{bad}", "--scene", "synthetic:demo?seed=7",
                                   "--profile", "smoke", "--stages", "ingest", "--set",
                                   "ingest.synthetic_frames=4", "--data", str(tmp_path / "data"),
                                   "--manifests", str(tmp_path / "m")], env={"COLUMNS": "300"})
    assert res.exit_code == 3, res.output
    assert "failed ingest   waymo-9 — scene waymo-9: corrupt TFRecord" in res.output
    assert sorted(p.name for p in (tmp_path / "data" / "locks").iterdir()) == ["synthetic-demo-s7.lock"]
    assert sorted(p.name for p in (tmp_path / "data" / "scenes").iterdir()) == ["synthetic-demo-s7"]


class _Told(logging.Handler):
    """Sets ``event`` when the lock says it is waiting."""

    def __init__(self, event: threading.Event):
        super().__init__()
        self.event = event

    def emit(self, record: logging.LogRecord) -> None:
        self.event.set()


def test_a_lock_file_its_holder_removed_is_never_held_twice(tmp_path):
    root = DataRoot.of(tmp_path / "data")
    waiting, taken, done = threading.Event(), threading.Event(), threading.Event()
    log = logging.getLogger("paradrive.test.discarded-lock")
    log.addHandler(_Told(waiting))

    def second() -> None:   # opened the file before the first holder removed it
        with scene_lock(root, "s", LockOptions("second", timeout=60), log):
            taken.set()
            done.wait(60)

    with scene_lock(root, "s", LockOptions("first")) as held:
        thread = threading.Thread(target=second)
        thread.start()
        assert waiting.wait(60)
        held.discard = True    # its scene never started: the file goes as it lets go
    try:
        assert taken.wait(60)
        with pytest.raises(SceneLocked, match="locked by build second"):
            with scene_lock(root, "s", LockOptions("third", timeout=0)):
                pass
    finally:
        done.set()
        thread.join(60)
