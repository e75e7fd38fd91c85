"""An encode that meets trouble, run for real on copies of the smoke build with the tiny random
VAE: a second encode of the same build while one runs is refused naming it (one writer per latent
cache), a killed encode's lock goes with it, an index never lists a shard that is not there, and
a text encoder cut short or a read-only build folder is one line with the fix, no traceback."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("diffusers")
pytest.importorskip("transformers")

from paradrive.errors import EXIT_FAILED, EXIT_OK, EXIT_USAGE  # noqa: E402
from paradrive import latents as cache  # noqa: E402
from test_exit_codes import _mount_namespaces  # noqa: E402
from test_wan_latents import CLI_SETS, ROOT  # noqa: E402

# another setting than CLI_SETS's 24x40: a cache of another shape, whose shards have other names
OTHER_SIZE = ["--set", "encode.size=[16,24]"]


def _env(**extra: str) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "PARADRIVE_STOP_AT"}
    return {**env, "PYTHONPATH": str(ROOT), "COLUMNS": "500", **extra}


def _command(build: Path, wan: Path, *sets: str) -> list[str]:
    """The test's encode: one frame at 24x40 (CLI_SETS), two shards of the smoke build's 144 pairs."""
    return [sys.executable, "-m", "paradrive.cli", "encode", str(build), "--vae", str(wan), *CLI_SETS,
            "--set", "encode.shard_pairs=72", *sets]


def _encode(build: Path, wan: Path, *sets: str) -> subprocess.CompletedProcess:
    return subprocess.run(_command(build, wan, *sets), env=_env(), capture_output=True, text=True, timeout=600)


@contextlib.contextmanager
def stopped_encode(build: Path, wan: Path, at: str):
    """An encode of ``build`` stopped by itself at step ``at`` (it holds the cache's lock there);
    yields its process, which the caller continues or kills; killed at the end in any case."""
    proc = subprocess.Popen(_command(build, wan), env=_env(PARADRIVE_STOP_AT=at), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        _, status = os.waitpid(proc.pid, os.WUNTRACED)
        assert os.WIFSTOPPED(status), "the encode ended before " + at
        yield proc
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        with contextlib.suppress(ChildProcessError):
            proc.wait()


def error_lines(done: subprocess.CompletedProcess) -> list[str]:
    """The command's error lines (its log lines, INFO ..., left out): exactly one, no traceback."""
    lines = [line for line in done.stderr.splitlines() if line.startswith("error: ") or "Traceback" in line]
    assert len(lines) == 1 and "Traceback" not in done.stderr, done.stderr[-3000:]
    return lines


def consistent(build: Path) -> dict:
    """The published latent index, after checking that every file it lists is there with its
    bytes and that no shard it does not list is left."""
    doc = cache.read_latents_index(build)
    assert cache.verify_latents(build)["problems"] == []
    listed = {e["file"] for e in doc["shards"]}
    assert {f"shards/{p.name}" for p in (build / "latents" / "shards").iterdir()} == listed
    return doc


def test_a_second_encode_of_a_build_is_refused_naming_the_first_and_a_kill_lets_go(
        smoke_build, wan_folder, copy_tree):
    build = copy_tree(smoke_build["build_dir"], "smoke")
    with stopped_encode(build, wan_folder, "encode:shard-0") as first:
        second = _encode(build, wan_folder, *OTHER_SIZE)   # runs while the first holds the cache
        assert second.returncode == EXIT_USAGE, second.stderr[-3000:]
        (line,) = error_lines(second)
        assert line.startswith(f"error: {build / 'latents'} is being written by another encode (host ")
        assert f"pid {first.pid}, " in line and "1 frames of 24x40, bfloat16); wait for it" in line
        assert not cache.has_latents(build)
        os.killpg(first.pid, signal.SIGKILL)   # killed holding the lock: the kernel lets it go
        first.wait()
    again = _encode(build, wan_folder, *OTHER_SIZE)
    assert again.returncode == EXIT_OK, again.stderr[-3000:]
    doc = consistent(build)
    assert doc["size"] == [16, 24] and doc["totals"]["pairs"] == len(json.loads(
        (build / "index.json").read_text())["scenes"]) * 72


def test_an_index_never_lists_a_shard_that_is_gone(smoke_build, wan_folder, copy_tree):
    build = copy_tree(smoke_build["build_dir"], "smoke")
    with stopped_encode(build, wan_folder, "encode:shard-0") as encode:
        written = sorted((build / "latents" / "shards").iterdir())
        assert len(written) == 1
        written[0].unlink()   # removed behind the encode's back (an older encoder's clean-up)
        os.kill(encode.pid, signal.SIGCONT)
        _, err = encode.communicate(timeout=600)
    assert encode.returncode == EXIT_FAILED, err[-3000:]
    assert f"error: {written[0]} is missing after this encode wrote it" in err
    assert not cache.has_latents(build)   # no index was published
    again = _encode(build, wan_folder)
    assert again.returncode == EXIT_OK, again.stderr[-3000:]
    consistent(build)


def test_a_text_encoder_cut_short_is_one_line_with_the_fix(smoke_build, wan_folder, copy_tree):
    build = copy_tree(smoke_build["build_dir"], "smoke")
    wan = copy_tree(wan_folder, "wan")
    weights = wan / "text_encoder" / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[: weights.stat().st_size // 2])
    from typer.testing import CliRunner

    from paradrive.cli import app

    done = CliRunner().invoke(app, _command(build, wan)[3:], env={"COLUMNS": "500"})
    assert done.exit_code == EXIT_USAGE, done.output[-3000:]
    (line,) = [line for line in done.output.splitlines() if line.startswith("error: ")]
    assert "Traceback" not in done.output
    assert line.startswith(f"error: text encoder folder {wan} could not be loaded (Error while "
                           f"deserializing header")
    assert "must be fetched again" in line and not cache.has_latents(build)


@pytest.mark.skipif(not _mount_namespaces(), reason="needs unshare -rm (a mount namespace)")
def test_a_read_only_build_folder_is_one_line_before_any_work(smoke_build, wan_folder, copy_tree):
    build = copy_tree(smoke_build["build_dir"], "smoke")
    command = " ".join(f"'{arg}'" for arg in _command(build, wan_folder))
    # the build folder is read-only for this encode alone (a bind mount in its own namespace)
    done = subprocess.run(["unshare", "-rm", "sh", "-c",
                           f"mount --bind '{build}' '{build}' && mount -o remount,bind,ro '{build}' "
                           f"&& exec {command}"], env=_env(), capture_output=True, text=True, timeout=600)
    assert done.returncode == EXIT_USAGE, done.stderr[-3000:]
    (line,) = error_lines(done)
    assert line == (f"error: {build / 'latents'}: the latent cache cannot be written there (Read-only "
                    f"file system); make the build folder writable, or encode a writable copy of it")
    assert not (build / "latents").exists()
