"""Faults outside a kill, each produced for real, and what a plain re-run leaves after each.

- same-size damage: a byte of a clip inverted in place (the build's media share its inode);
- a ledger that is not a database: garbage bytes written over ``ledger.sqlite``;
- a read-only ``--manifests``: a read-only bind mount of the build folder (root ignores
  permission bits; skipped where this process cannot mount);
- a full disk: a small tmpfs under the ledger, and under ``gs/`` while the fit saves its state
  (skipped where this process cannot mount);
- a bad record: a Waymo segment with one byte inverted (its CRC no longer matches).
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

import test_faults as faults
from test_faults import BUILD, SCENE_DIR, build_command, healed, outputs

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def env(tmp_path_factory) -> dict[str, str]:
    return faults.environment(tmp_path_factory.mktemp("cache"))


@pytest.fixture(scope="module")
def reference(tmp_path_factory, env) -> Path:
    return faults.reference_build(tmp_path_factory.mktemp("reference") / "work", env)


# -- damage, the ledger, the disk ----------------------------------------------------------------

def copy_build(reference: Path, folder: Path) -> Path:
    """A copy of the reference build with its hard links (clips and media share an inode)."""
    subprocess.run(["cp", "-a", str(reference), str(folder)], check=True)
    return folder


def one_line(text: str, needle: str) -> str:
    (line,) = [x for x in text.splitlines() if needle in x]
    return line


def test_a_byte_flipped_in_a_clip_is_named_with_the_command_that_heals_it(reference, env, tmp_path):
    from paradrive.inspection import verify_build

    folder = copy_build(reference, tmp_path / "work")
    path = folder / SCENE_DIR / "clips/front/front/target.mp4"
    size = path.stat().st_size
    with open(path, "r+b") as f:
        f.seek(size // 2)
        byte = f.read(1)[0]
        f.seek(size // 2)
        f.write(bytes([byte ^ 0xFF]))
    problems = verify_build(folder / "m" / BUILD)["problems"]
    assert problems and "re-run the build without --stages" in problems[0]
    assert healed(folder, env, outputs(reference)) == []


def test_a_garbage_ledger_is_moved_aside_and_rebuilt_from_the_markers(reference, env, tmp_path):
    from paradrive.pipeline.ledger import Ledger

    folder = copy_build(reference, tmp_path / "work")
    ledger = folder / "m" / BUILD / "ledger.sqlite"
    for extra in ledger.parent.glob("ledger.sqlite-*"):
        extra.unlink()
    ledger.write_bytes(b"not a database at all; " * 200)
    rerun = faults.build(folder, env)
    line = one_line(rerun.stderr, "not a database")
    assert str(Path("m") / BUILD / "ledger.sqlite") in line and "moved aside" in line
    assert len(list(ledger.parent.glob("ledger.sqlite.corrupt-*"))) == 1
    rows = Ledger(ledger, BUILD).tasks()
    assert {(r["stage"], r["state"]) for r in rows} == {  # rebuilt, then this run's skips
        (stage, "skipped") for stage in faults.STAGES}
    assert healed(folder, env, outputs(reference), rerun) == []


@contextlib.contextmanager
def mounted(target: Path, *options: str, source: str = "tmpfs") -> Iterator[Path]:
    """A real mount (a small tmpfs, a read-only bind) where this process may mount; else skip."""
    target.mkdir(parents=True, exist_ok=True)
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs or a read-only bind needs root")
    kind = ["-t", "tmpfs"] if source == "tmpfs" else ["--bind"]
    done = subprocess.run(["mount", *kind, *options, source, str(target)], capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount here: {done.stderr.strip()}")
    try:
        if source != "tmpfs":  # a bind mount is made read-only by remounting it
            subprocess.run(["mount", "-o", "remount,ro,bind", str(target)], check=True)
        yield target
    finally:
        subprocess.run(["umount", "-l", str(target)], check=True)


def test_a_read_only_build_folder_is_named_with_the_fix_and_status_still_reads_it(reference, env,
                                                                                 tmp_path):
    folder = copy_build(reference, tmp_path / "work")
    with mounted(tmp_path / "ro", source=str(folder / "m")) as ro:
        with pytest.raises(OSError):
            (ro / "probe").touch()  # really read-only, root included
        run = subprocess.run(build_command(manifests=str(ro)), cwd=folder, env=env,
                             capture_output=True, text=True)
        assert run.returncode == 2
        line = one_line(run.stderr + run.stdout, "ledger")
        assert f"{ro / BUILD / 'ledger.sqlite'}" in line and "writable" in line
        status = subprocess.run([sys.executable, "-m", "paradrive.cli", "status", BUILD,
                                 "--manifests", str(ro), "--json"], cwd=folder, env=env,
                                capture_output=True, text=True)
        assert status.returncode == 0, status.stderr
        assert json.loads(status.stdout)["counts"]["done"] == 1
    assert outputs(folder) == outputs(reference)  # nothing was changed


def test_a_full_disk_under_the_ledger_is_named_with_the_fix(reference, env, tmp_path):
    folder = copy_build(reference, tmp_path / "work")
    with mounted(tmp_path / "full", "-o", "size=20k") as full:
        run = subprocess.run(build_command(manifests=str(full)), cwd=folder, env=env,
                             capture_output=True, text=True)
        assert run.returncode == 2
        line = one_line(run.stderr + run.stdout, "ledger")
        assert str(full / BUILD / "ledger.sqlite") in line and "disk full" in line
    assert outputs(folder) == outputs(reference)  # nothing was changed


def test_a_full_disk_while_saving_the_fit_state_says_so_and_leaves_nothing(tiny_scene, tmp_path):
    import shutil

    from conftest import stage_params
    from paradrive.stages.fit import fit_scene

    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene, scene)
    params = stage_params("fit", {"checkpoints": [5], "init_points": 2000, "sky_points": 100},
                          profile="smoke")
    with mounted(scene / "gs", "-o", "size=16k") as gs:
        with pytest.raises(OSError) as err:
            fit_scene(scene, params, stop_after=1)  # the only write: gs/state.pt
        assert f"disk full while writing {gs / 'state.pt'}" in str(err.value)
        assert "free space" in str(err.value) and "\n" not in str(err.value)
        assert list(gs.iterdir()) == []


def test_a_bad_record_fails_its_ingest_and_leaves_no_scene_folder(tmp_path):
    from paradrive.ingest import export
    from paradrive.pipeline import StageRegistry, run_build
    from paradrive.synthetic import SyntheticStreet

    segment = tmp_path / "logs" / "segment-77_with_camera_labels.tfrecord"
    export.export_waymo(SyntheticStreet("demo", seed=3, frames=3, width=64, height=48), segment)
    raw = bytearray(segment.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    segment.write_bytes(bytes(raw))
    data = tmp_path / "data"
    config = StageRegistry().resolve("smoke", {"ingest": {"cameras": ["front"]}})
    report = run_build(config, [f"waymo:{segment}"], data,
                       stages=["ingest"], manifests_dir=tmp_path / "m", build="bad")
    (failure,) = report.failures()
    assert "CRC mismatch" in failure.error and str(segment) in failure.error
    assert list((data / "scenes").iterdir()) == []
