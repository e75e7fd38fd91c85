"""A publish that fails is a failed step of the build: it never exits 0, the ledger records it,
and ``--retry-failed`` runs it again (and only it) once the cause is gone.

Each case is a real full disk: a small tmpfs under ``--manifests`` holding the ledger, filled
with a file (``posix_fallocate``) until the publish no longer fits; deleting that file frees the
space. The scene stages come from a copy of the session's smoke build, so they are skipped and
only the publish runs.
"""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from paradrive.errors import EXIT_FAILED, EXIT_OK
from paradrive.pipeline.ledger import Ledger

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[1]
BUILD = "R"
ROOM_FOR_THE_LEDGER = 600_000   # bytes left free: the ledger's writes fit, the pairs' media do not


@contextlib.contextmanager
def small_disk(target: Path, size: str = "16m") -> Iterator[Path]:
    """A real tmpfs at ``target`` (skipped where this process may not mount)."""
    target.mkdir(parents=True, exist_ok=True)
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(target)],
                          capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip()}")
    try:
        yield target
    finally:
        subprocess.run(["umount", "-l", str(target)], check=True)


def fill(disk: Path, leave: int) -> Path:
    """A file taking all of ``disk``'s free space but ``leave`` bytes."""
    stat = os.statvfs(disk)
    filler = disk / "filler"
    fd = os.open(filler, os.O_CREAT | os.O_WRONLY)
    try:
        os.posix_fallocate(fd, 0, stat.f_bavail * stat.f_frsize - leave)
    finally:
        os.close(fd)
    return filler


def paradrive_build(cwd: Path, manifests: Path, *args: str) -> subprocess.CompletedProcess:
    command = [sys.executable, "-m", "paradrive.cli", "build", "--profile", "smoke", "--data",
               str(cwd / "data"), "--manifests", str(manifests), "--build", BUILD, *args]
    return subprocess.run(command, cwd=cwd, capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(REPO), "COLUMNS": "250"})


def scene_args(smoke_build: dict) -> list[str]:
    return [arg for uri in smoke_build["scene_uris"] for arg in ("--scene", uri)]


def manifest_row(manifests: Path) -> dict:
    (row,) = [r for r in Ledger(manifests / BUILD / "ledger.sqlite", BUILD).tasks()
              if r["scene_id"] == f"build:{BUILD}"]
    return row


def published(manifests: Path) -> dict:
    return json.loads((manifests / BUILD / "index.json").read_text())


@pytest.fixture
def work(smoke_build, copy_tree) -> Path:
    """This test's copy of the smoke build's data root (its scenes done through clip)."""
    folder = copy_tree(smoke_build["data_dir"], "work/data").parent
    return folder


def test_a_first_publish_on_a_full_disk_exits_1_and_a_retry_publishes_it(smoke_build, work):
    with small_disk(work / "m") as disk:
        filler = fill(disk, ROOM_FOR_THE_LEDGER)
        run = paradrive_build(work, disk, *scene_args(smoke_build))
        assert run.returncode == EXIT_FAILED, run.stdout[-3000:] + run.stderr[-3000:]
        assert "2 of 2 scenes done; exit code 1 (manifest failed: nothing of this run was published" in run.stdout
        assert not (disk / BUILD / "index.json").exists()
        row = manifest_row(disk)
        assert row["state"] == "failed" and "manifest" in row["error"]
        # still full: the retry runs the publish again and fails again, never exit 0
        again = paradrive_build(work, disk, "--retry-failed")
        assert again.returncode == EXIT_FAILED, again.stdout[-3000:]
        assert f"retrying manifest of build '{BUILD}' over its 2 scene(s)" in again.stdout
        assert manifest_row(disk)["attempts"] == 2
        filler.unlink()   # space freed
        retry = paradrive_build(work, disk, "--retry-failed")
        assert retry.returncode == EXIT_OK, retry.stdout[-3000:] + retry.stderr[-3000:]
        assert "skipped clip" not in retry.stderr   # only what failed ran: no scene stage
        assert manifest_row(disk)["state"] == "done"
        index = published(disk)
        assert sorted(s["scene_id"] for s in index["scenes"]) == sorted(smoke_build["report"].scenes())
        # the pairs are those of a build published in one go, byte for byte
        assert [s["sha256"] for s in index["shards"]] == [
            s["sha256"] for s in json.loads((smoke_build["build_dir"] / "index.json").read_text())["shards"]]
        nothing = paradrive_build(work, disk, "--retry-failed")
        assert nothing.returncode == EXIT_OK and "nothing to retry" in nothing.stdout


def test_a_republish_on_a_full_disk_keeps_the_old_version_exits_1_and_a_retry_publishes(smoke_build,
                                                                                      work):
    with small_disk(work / "m") as disk:
        first = paradrive_build(work, disk, *scene_args(smoke_build))
        assert first.returncode == EXIT_OK, first.stdout[-3000:]
        before = published(disk)
        filler = fill(disk, ROOM_FOR_THE_LEDGER)
        change = ("--set", "manifest.row_group_rows=32")   # other shards, the same scenes
        run = paradrive_build(work, disk, *scene_args(smoke_build), *change)
        assert run.returncode == EXIT_FAILED, run.stdout[-3000:] + run.stderr[-3000:]
        assert published(disk) == before   # the old version stays for its readers
        assert manifest_row(disk)["state"] == "failed"
        filler.unlink()
        retry = paradrive_build(work, disk, "--retry-failed", *change)
        assert retry.returncode == EXIT_OK, retry.stdout[-3000:] + retry.stderr[-3000:]
        after = published(disk)
        assert after["version"] != before["version"] and after["config_fingerprint"] != before["config_fingerprint"]
        assert manifest_row(disk)["state"] == "done"
