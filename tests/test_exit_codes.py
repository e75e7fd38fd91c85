"""A build's exit code is the README's: 0 every scene landed, 1 no scene landed, 2 a usage or
configuration error, 3 some scenes landed and some failed, 130 interrupted (Ctrl-C) and 143
terminated (SIGTERM), each with a line that says what was stopped and that a plain re-run
resumes."""

from __future__ import annotations

import os
import resource
import signal
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest

from paradrive.errors import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK, EXIT_PARTIAL, EXIT_TERMINATED
from paradrive.pipeline.build import BuildReport
from paradrive.pipeline.runner import StageResult

REPO = Path(__file__).resolve().parents[1]
TINY = ["--profile", "smoke", "--set", "ingest.synthetic_frames=10", "--set", "ingest.synthetic_width=64",
        "--set", "ingest.synthetic_height=48"]


def _command(root: Path, *args: str) -> list[str]:
    return [sys.executable, "-m", "paradrive.cli", "build", "--data", str(root / "data"),
            "--manifests", str(root / "m"), "--build", "K", *TINY, *args]


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": str(REPO), "COLUMNS": "250"}


def _run(root: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(_command(root, *args), cwd=REPO, env=_env(), capture_output=True, text=True,
                          timeout=600)


@pytest.mark.slow
def test_scenes_that_all_failed_after_their_ingest_exit_1(tmp_path):
    # the ingest of both scenes lands, then every fit fails: no scene was built
    res = _run(tmp_path, "--scene", "synthetic:p1?seed=3", "--scene", "synthetic:p1?seed=4",
               "--stages", "ingest,fit", "--set", "fit.init=lidar", "--set", "ingest.lidar=false")
    assert res.returncode == EXIT_FAILED, res.stdout + res.stderr
    assert res.stderr.count("done ingest") == 2 and res.stderr.count("failed fit") == 2
    assert "0 of 2 scenes done; exit code 1 (no scene built)" in res.stdout
    assert list((tmp_path / "data" / "scenes").iterdir())   # the ingests are kept for a re-run


def _small_disk() -> None:
    """In the child: files stop growing past 500 kB (EFBIG, not a signal)."""
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (500_000, 500_000))


@pytest.mark.slow
def test_every_scene_failing_at_the_file_size_limit_exits_1_naming_the_folder_and_the_fix(tmp_path):
    # no bytecode: a .pyc written under the limit would be cut short and break its module's imports
    res = subprocess.run(_command(tmp_path, "--scene", "synthetic:p1?seed=3", "--stages", "ingest,fit"),
                         cwd=REPO, env={**_env(), "PYTHONDONTWRITEBYTECODE": "1"}, capture_output=True,
                         text=True, timeout=600, preexec_fn=_small_disk)
    assert res.returncode == EXIT_FAILED, res.stdout + res.stderr
    scene = tmp_path / "data" / "scenes" / "synthetic-p1-s3"
    # EFBIG is the file size limit (ulimit -f), not free space
    ckpt = scene / "gs" / "ckpt_000025.ply"
    assert (f"failed fit      synthetic-p1-s3 — scene synthetic-p1-s3: fit: "
            f"file size limit (ulimit -f: 500,000 bytes) reached writing in {ckpt.parent}, not "
            f"a full disk: raise it (ulimit -f unlimited) and re-run (while writing {ckpt}; nothing "
            f"half-written was kept)") in [line.strip() for line in res.stderr.splitlines()]
    assert not ckpt.exists() and not list(ckpt.parent.glob(".*tmp-*"))


def _mount_namespaces() -> bool:
    """Whether this user may mount in a namespace of its own (``unshare -rm``)."""
    try:
        return subprocess.run(["unshare", "-rm", "true"], capture_output=True).returncode == 0
    except FileNotFoundError:
        return False


@pytest.mark.skipif(not _mount_namespaces(), reason="needs unshare -rm (a mount namespace)")
def test_a_read_only_data_folder_fails_every_scene_with_exit_1(tmp_path):
    (tmp_path / "data").mkdir()
    command = " ".join(f"'{arg}'" for arg in _command(tmp_path, "--scene", "synthetic:p1?seed=3",
                                                        "--scene", "synthetic:p1?seed=4", "--stages", "ingest"))
    # --data is an empty read-only file system, seen by this build only
    res = subprocess.run(["unshare", "-rm", "sh", "-c",
                          f"mount -t tmpfs -o size=1m,ro tmpfs '{tmp_path / 'data'}' && exec {command}"],
                         cwd=REPO, env=_env(), capture_output=True, text=True, timeout=600)
    assert res.returncode == EXIT_FAILED, res.stdout + res.stderr
    assert res.stderr.count("Read-only file system") == 2 and "0 of 2 scenes done" in res.stdout


def test_some_scenes_failed_and_some_landed_exits_3(tmp_path):
    res = _run(tmp_path, "--scene", "synthetic:demo?seed=4&colour=red", "--scene", "synthetic:demo?seed=5",
               "--stages", "ingest")
    assert res.returncode == EXIT_PARTIAL, res.stdout + res.stderr
    assert "1 of 2 scenes done; exit code 3 (partial build)" in res.stdout


def test_the_exit_code_counts_scenes_not_stages():
    def results(*rows):
        return BuildReport(results=[StageResult(sid, stage, status) for sid, stage, status in rows])

    assert results(("a", "ingest", "done"), ("a", "fit", "failed"),
                   ("b", "ingest", "skipped"), ("b", "fit", "failed")).exit_code == EXIT_FAILED
    assert results(("a", "ingest", "done"), ("a", "fit", "failed"),
                   ("b", "ingest", "done"), ("b", "fit", "done")).exit_code == EXIT_PARTIAL
    assert results(("build:K", "manifest", "failed")).exit_code == EXIT_FAILED
    assert results(("a", "ingest", "done"), ("build:K", "manifest", "done")).exit_code == EXIT_OK


def _running(ledger: Path) -> list[tuple[str, str]]:
    with sqlite3.connect(f"file:{ledger}?mode=ro", uri=True) as db:
        return db.execute("SELECT scene_id, stage FROM tasks WHERE state = 'running'").fetchall()


def _stopped_in_the_fit_then(tmp_path: Path, signum: int) -> subprocess.CompletedProcess:
    """A build of one scene that stopped itself inside its fit, after its first checkpoint
    (however loaded the machine: the signal then lands in the fit for certain), then sent
    ``signum``. It starts with Ctrl-C's own handler: a suite launched in the background by a
    non-interactive shell ignores SIGINT, and a process inherits that (Python then installs no
    KeyboardInterrupt handler)."""
    env = {**_env(), "PARADRIVE_STOP_AT": "fit:checkpoint-25"}
    code = ("import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
            "sys.argv = ['paradrive', *sys.argv[1:]]; from paradrive.cli import main; main()")
    command = [sys.executable, "-c", code, *_command(tmp_path, *FIT_ARGS)[3:]]
    proc = subprocess.Popen(command, cwd=REPO, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        _, status = os.waitpid(proc.pid, os.WUNTRACED)
        assert os.WIFSTOPPED(status), "the build ended before the fit's first checkpoint"
        assert ("synthetic-p1-s3", "fit") in _running(tmp_path / "m" / "K" / "ledger.sqlite")
        proc.send_signal(signum)
        proc.send_signal(signal.SIGCONT)
        out, err = proc.communicate(timeout=300)
    finally:
        proc.kill()
        proc.wait()
    return subprocess.CompletedProcess(command, proc.returncode, out, err)


FIT_ARGS = ("--scene", "synthetic:p1?seed=3", "--stages", "ingest,fit")


def _said_and_resumes(tmp_path: Path, stopped: subprocess.CompletedProcess, code: int, how: str) -> None:
    assert stopped.returncode == code, stopped.stdout + stopped.stderr
    assert (f"{how}: stopped fit of synthetic-p1-s3; finished stages are kept: run the same "
            "command again to resume (a fit goes on from its last saved state)") in stopped.stderr.splitlines()
    with sqlite3.connect(f"file:{tmp_path / 'm' / 'K' / 'ledger.sqlite'}?mode=ro", uri=True) as db:
        (recorded,) = db.execute("SELECT exit_code FROM runs ORDER BY run_id DESC LIMIT 1").fetchone()
    assert recorded == code
    assert not [p for p in tmp_path.rglob("*") if ".tmp-" in p.name]   # nothing half-written
    again = _run(tmp_path, *FIT_ARGS)
    assert again.returncode == EXIT_OK, again.stdout + again.stderr
    assert "skipped ingest" in again.stderr and "done fit" in again.stderr


@pytest.mark.slow
def test_ctrl_c_says_what_it_stopped_and_a_plain_rerun_finishes(tmp_path):
    _said_and_resumes(tmp_path, _stopped_in_the_fit_then(tmp_path, signal.SIGINT), EXIT_INTERRUPTED,
                      "interrupted")


@pytest.mark.slow
def test_sigterm_says_what_it_stopped_exits_143_and_a_plain_rerun_finishes(tmp_path):
    _said_and_resumes(tmp_path, _stopped_in_the_fit_then(tmp_path, signal.SIGTERM), EXIT_TERMINATED,
                      "terminated (SIGTERM)")
