"""Outputs that cannot be written: a command refuses a path it cannot write before any work (one
line, exit 2), and a write that fails at the end (the disk full, the file size limit) is one line
with the fix, a non-zero exit and nothing half-written; a YAML tag in --set is refused, never run.

The file size limit is the real one (RLIMIT_FSIZE in the child, SIGXFSZ ignored so the write
fails with EFBIG instead of killing it). The children write no bytecode: a ``.pyc`` written under
the limit would be cut short and break every later import of its module."""

from __future__ import annotations

import os
import resource
import signal
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import stage_params
from paradrive.errors import EXIT_FAILED, EXIT_USAGE, ConfigError, FileSizeLimitError, ParaDriveError
from paradrive.io import check_output, write_bytes
from paradrive.stages.manifest import build_manifest
from test_manifest import scenes_entry, write_clip_scene

REPO = Path(__file__).resolve().parents[1]
LIMIT = 15_000   # bytes a child may write to one file
TINY = ["--profile", "smoke", "--set", "ingest.synthetic_frames=10", "--set", "ingest.synthetic_width=64",
        "--set", "ingest.synthetic_height=48"]


def _limited() -> None:
    """In the child: no file grows past LIMIT bytes (EFBIG, not a signal)."""
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (LIMIT, LIMIT))


def paradrive(*args: str, limited: bool = False) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO), "COLUMNS": "80", "PYTHONDONTWRITEBYTECODE": "1"}
    return subprocess.run([sys.executable, "-m", "paradrive.cli", *args], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=300, preexec_fn=_limited if limited else None)


def in_process(*args: str) -> tuple[int, str]:
    """The command run by typer's runner in this process: its exit code and its output."""
    from typer.testing import CliRunner

    from paradrive.cli import app

    result = CliRunner().invoke(app, list(args), env={"COLUMNS": "80"})
    return result.exit_code, result.output


def error_line(done: subprocess.CompletedProcess | str) -> str:
    """The command's one line of error (its output holds nothing else)."""
    text = done if isinstance(done, str) else done.stderr
    lines = [line for line in text.splitlines() if line.strip()]
    assert len(lines) == 1, text[-3000:]
    assert lines[0].startswith("error: ")
    return lines[0]


@pytest.fixture(scope="module")
def build(tmp_path_factory):
    """One pair of 4 frames of 64x48: its recording is about 0.1 MB, past LIMIT."""
    data = tmp_path_factory.mktemp("outputs")
    scene = write_clip_scene(data / "data", "synthetic-a", clips=("front",), offsets=(2.0,),
                             conditions=(100,), num_frames=4)
    build_manifest(data / "b", [scenes_entry(scene)], stage_params("manifest", {}))
    return data / "b"


def a_device(folder: Path) -> Path:
    """A character device like /dev/full (1, 7) where this user may make one, else a named pipe:
    neither a file nor a folder, and never /dev/full itself, which a broken check would replace."""
    path = folder / "full"
    try:
        os.mknod(path, 0o666 | stat.S_IFCHR, os.makedev(1, 7))
    except PermissionError:
        os.mkfifo(path)
    return path


def unchanged(path: Path) -> bool:
    mode = path.lstat().st_mode
    return stat.S_ISCHR(mode) or stat.S_ISFIFO(mode)


# --------------------------------------------------------------------------- refused before any work

def test_view_save_to_a_place_it_cannot_write_is_refused_before_any_work(build, tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("x")
    device = a_device(tmp_path)
    cases = {afile / "x.rrd": f"{afile} is a file, not a folder",
             tmp_path: "is a folder, not a file",
             device: "is a device, pipe or socket, not a file",
             Path("/proc/x.rrd"): "cannot write in /proc"}
    for target, reason in cases.items():
        code, output = in_process("view", str(build), "--save", str(target))
        assert code == EXIT_USAGE, output
        line = error_line(output)
        assert line.startswith(f"error: --save {target}: ") and reason in line
    assert unchanged(device) and afile.read_text() == "x"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "full"]


def test_export_into_a_file_or_a_device_is_refused_before_any_work(tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("x")
    device = a_device(tmp_path)
    for target, reason in ((afile, "is a file, not a folder"), (device, "is a device, pipe or socket"),
                           (afile / "sub", f"{afile} is a file, not a folder")):
        code, output = in_process("export", "waymo", str(target), *TINY)
        assert code == EXIT_USAGE, output
        line = error_line(output)
        assert line.startswith(f"error: export: OUT {target}: ") and reason in line
    assert unchanged(device) and afile.read_text() == "x"


def test_check_output_makes_nothing_where_it_probes(tmp_path):
    target = tmp_path / "new" / "deeper" / "x.rrd"
    assert check_output(target, "--save") == target
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ConfigError, match=r"^--save .*: is a folder, not a file"):
        check_output(tmp_path, "--save")
    assert check_output(tmp_path, "OUT", folder=True) == tmp_path


def test_a_write_never_replaces_a_device_or_a_pipe(tmp_path):
    device = a_device(tmp_path)
    with pytest.raises(ParaDriveError, match="is not a file or folder .* refusing to replace it"):
        write_bytes(device, b"data")
    assert unchanged(device) and sorted(p.name for p in tmp_path.iterdir()) == ["full"]


# --------------------------------------------------------------------------- a write that fails at the end

def test_a_write_past_the_file_size_limit_says_so_and_leaves_nothing(tmp_path):
    code = ("import sys; from paradrive.io import write_bytes\n"
            "try:\n    write_bytes(sys.argv[1], b'x' * 100_000)\n"
            "except OSError as exc:\n    print(type(exc).__name__, exc.errno, exc.strerror)")
    env = {**os.environ, "PYTHONPATH": str(REPO), "PYTHONDONTWRITEBYTECODE": "1"}
    done = subprocess.run([sys.executable, "-c", code, str(tmp_path / "big.bin")], env=env,
                          capture_output=True, text=True, timeout=120, preexec_fn=_limited)
    assert done.stdout.strip() == (
        f"{FileSizeLimitError.__name__} 27 file size limit (ulimit -f: {LIMIT:,} bytes) reached writing in "
        f"{tmp_path}, not a full disk: raise it (ulimit -f unlimited) and re-run (while writing "
        f"{tmp_path / 'big.bin'}; nothing half-written was kept)"), done.stderr
    assert list(tmp_path.iterdir()) == []


def test_view_past_the_file_size_limit_is_one_line_and_writes_nothing(build, tmp_path):
    done = paradrive("view", str(build), "--save", str(tmp_path / "pairs.rrd"), limited=True)
    assert done.returncode == EXIT_FAILED, done.stderr[-3000:]
    assert f"file size limit (ulimit -f: {LIMIT:,} bytes) reached writing in {tmp_path}" in error_line(done)
    assert list(tmp_path.iterdir()) == []


def test_an_export_past_the_file_size_limit_leaves_the_folder_as_it_was(tmp_path):
    out = tmp_path / "log"
    out.mkdir()
    (out / "kept.txt").write_text("mine")
    done = paradrive("export", "nuscenes", str(out), *TINY, limited=True)
    assert done.returncode == EXIT_FAILED, done.stderr[-3000:]
    assert f"file size limit (ulimit -f: {LIMIT:,} bytes) reached writing in {out}" in error_line(done)
    assert [p.name for p in out.rglob("*")] == ["kept.txt"]
    fresh = tmp_path / "fresh"
    done = paradrive("export", "drivestudio", str(fresh), *TINY, limited=True)
    assert done.returncode == EXIT_FAILED and "file size limit" in error_line(done)
    assert not fresh.exists()


# --------------------------------------------------------------------------- YAML tags in --set

@pytest.mark.parametrize("command", [["train", "--build", "nowhere"], ["stages"]])
def test_a_yaml_tag_in_set_is_one_line_exit_2_and_never_runs(command, tmp_path):
    marker = tmp_path / "ran"
    key = "model.dim" if command[0] == "train" else "fit.iterations"
    code, output = in_process(*command, "--set", f'{key}=!!python/object/apply:os.system ["touch {marker}"]')
    assert code == EXIT_USAGE, output
    line = error_line(output)
    assert f"--set '{key}=!!python/object/apply:os.system" in line
    assert "could not determine a constructor for the tag" in line
    assert not marker.exists()
