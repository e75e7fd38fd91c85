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
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

import test_faults as faults
from test_faults import BUILD, SCENE_DIR, SID, build_command, healed, outputs

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


# -- a full disk in every stage that writes, named with the room there and the room needed --------

def remount_size(target: Path, size: int | str) -> None:
    """The tmpfs at ``target`` resized (a tmpfs is never made smaller than what it holds)."""
    subprocess.run(["mount", "-o", f"remount,size={size}", str(target)], check=True)


def used_bytes(target: Path) -> int:
    usage = os.statvfs(target)
    return (usage.f_blocks - usage.f_bfree) * usage.f_frsize


def reported(text: str, needle: str) -> str:
    """The message from ``needle`` on of the build's one line that holds it (the summary table's
    row repeats it, cut to the table's width)."""
    (line,) = [x for x in text.splitlines() if needle in x and "│" not in x]
    return line[line.index(needle):]


def disk_full_line(text: str, who: str, folder: Path, elsewhere: str) -> str:
    """The one line naming a full disk for ``who``: the folder, the room there and the room the
    write needed, the fix; no traceback, no raw OSError."""
    assert "Traceback" not in text and "requested and" not in text and "crashed" not in text, text[-3000:]
    line = reported(text, f"{who}: disk full writing in {folder}: ")
    assert re.search(r": [\d,]+ bytes? (\([\d.]+ [MG]B\) )?free there and it needs (at least [\d,]+ "
                     r"bytes? more than that|more than that)", line), line
    assert line.endswith(f"; free space there (or {elsewhere}) and re-run (nothing half-written was kept)"), line
    assert ".tmp-" not in line, line   # the folder where the output lands, never a temporary
    return line


@pytest.mark.parametrize("size", ["200k", "1m"])  # an image's write; a LiDAR sweep's (numpy's short write)
def test_a_full_disk_at_ingest_names_the_scene_the_folder_and_the_room_needed(size, env, tmp_path):
    from paradrive.pipeline.ledger import Ledger

    folder = tmp_path / "work"
    with mounted(folder / "data", "-o", f"size={size}") as data:
        run = faults.build(folder, env)
        assert run.returncode == 1, run.stdout[-3000:] + run.stderr[-3000:]
        line = disk_full_line(run.stdout + run.stderr, f"scene {SID}: ingest", data / "scenes" / SID,
                              "pass another --data")
        assert "it needs at least" in line   # what the write still had to put down is known
        assert faults.temporaries(folder) == [] and not (data / "scenes" / SID).exists()
        task = Ledger(folder / "m" / BUILD / "ledger.sqlite", BUILD).task(SID, "ingest")
        assert task["state"] == "failed" and f"scene {SID}: ingest: disk full writing in" in task["error"]


def test_a_full_disk_at_clip_names_the_scene_folder_and_a_rerun_with_room_heals(reference, env, tmp_path):
    folder = copy_build(reference, tmp_path / "work")
    kept = tmp_path / "kept-data"
    os.replace(folder / "data", kept)
    with mounted(folder / "data", "-o", "size=64m") as data:
        subprocess.run(["cp", "-a", f"{kept}/.", str(data)], check=True)
        scene = data / "scenes" / SID
        subprocess.run(["rm", "-rf", str(scene / "clips"), str(scene / ".paradrive" / "clip.json")], check=True)
        remount_size(data, used_bytes(data) + 16 * 1024)   # room for less than the clips
        run = faults.build(folder, env)
        assert run.returncode == 1, run.stdout[-3000:] + run.stderr[-3000:]
        disk_full_line(run.stdout + run.stderr, f"scene {SID}: clip", scene, "pass another --data")
        assert faults.temporaries(folder) == [] and not (scene / "clips").exists()
        remount_size(data, "64m")
        assert healed(folder, env, outputs(reference)) == []


@pytest.mark.parametrize("size", ["8k", "40k"])  # a Parquet shard's write; a clip's copy into the build
def test_a_full_disk_at_the_publish_names_the_build_folder_and_leaves_nothing(size, reference, tmp_path):
    import pipeline_stages
    from paradrive.pipeline import StageRegistry, run_build

    folder = copy_build(reference, tmp_path / "work")
    config = StageRegistry().resolve("smoke", pipeline_stages.TINY_REAL)
    with mounted(tmp_path / "manifests", "-o", f"size={size}") as full:
        report = run_build(config, [faults.SCENE], folder / "data", manifests_dir=full, build=BUILD)
        (failure,) = report.failures()
        assert failure.stage == "manifest" and report.exit_code == 1
        disk_full_line(failure.error, f"build {BUILD}: manifest", full / BUILD, "pass another --manifests")
        assert failure.seconds > 0 and failure.peak_rss_mb > 0   # recorded as a finished stage's
        assert faults.temporaries(full) == [] and not (full / BUILD / "index.json").exists()
        remount_size(full, "64m")
        again = run_build(config, [faults.SCENE], folder / "data", manifests_dir=full, build=BUILD)
        assert again.exit_code == 0 and (full / BUILD / "index.json").is_file()


def test_a_full_disk_under_the_latent_cache_names_the_build_and_the_room_needed(reference, wan_folder,
                                                                                 env, tmp_path):
    pytest.importorskip("diffusers")
    from paradrive import latents as cache

    folder = copy_build(reference, tmp_path / "work")
    build = folder / "m" / BUILD
    with mounted(build / "latents", "-o", "size=8k") as latents:
        run = subprocess.run([sys.executable, "-m", "paradrive.cli", "encode", str(build), "--vae",
                              str(wan_folder), "--device", "cpu", "--set", "encode.size=[24,40]",
                              "--set", "encode.num_frames=1"], cwd=folder, env=env, capture_output=True,
                             text=True)
        assert run.returncode == 1, run.stderr[-3000:]
        line = disk_full_line(run.stderr, f"build {BUILD}: encode", latents / "text",
                              "encode a copy of the build on a disk with room")
        assert "it needs at least" in line and one_line(run.stderr, "error: ").startswith("error: build")
        assert not cache.has_latents(build) and faults.temporaries(latents) == []


def test_a_full_disk_under_a_scene_log_drops_its_lines_without_a_traceback(tmp_path, capfd):
    from paradrive.pipeline.runner import scene_logger

    with mounted(tmp_path / "logs", "-o", "size=4k") as logs:
        with scene_logger("s", logs / "s.log") as log:
            for i in range(300):   # ~20 kB of lines into 4 kB
                log.info("line %d of a stage that goes on while the disk is full", i)
        assert 0 < (logs / "s.log").stat().st_size <= 4096
    err = capfd.readouterr().err
    assert "Logging error" not in err and "Traceback" not in err, err[-2000:]


# -- a read-only data root --------------------------------------------------------------------------

def test_a_read_only_data_root_with_every_stage_up_to_date_is_skipped(reference, env, tmp_path):
    from paradrive.pipeline.ledger import Ledger

    folder = copy_build(reference, tmp_path / "work")
    before = outputs(folder)
    with mounted(folder / "data", source=str(folder / "data")) as data:
        with pytest.raises(OSError):
            (data / "probe").touch()  # really read-only, root included
        run = faults.build(folder, env)
        assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
        rows = Ledger(folder / "m" / BUILD / "ledger.sqlite", BUILD).tasks()
        assert {(r["stage"], r["state"]) for r in rows} == {(stage, "skipped") for stage in faults.STAGES}
        # a build that publishes elsewhere reads the scenes and publishes them all the same
        fresh = subprocess.run(build_command(manifests="m2"), cwd=folder, env=env, capture_output=True,
                               text=True)
        assert fresh.returncode == 0, fresh.stdout[-3000:] + fresh.stderr[-3000:]
        assert (folder / "m2" / BUILD / "index.json").is_file()
    assert {k: v for k, v in outputs(folder).items() if not k.startswith("m2/")} == before


def test_a_read_only_data_root_with_a_stage_to_run_says_so_with_the_fix(reference, env, tmp_path):
    folder = copy_build(reference, tmp_path / "work")
    with mounted(folder / "data", source=str(folder / "data")) as data:
        run = faults.build(folder, env, "--set", "render.offsets_m=[1.0, -2.0]")   # render is stale
        assert run.returncode == 1, run.stdout[-3000:] + run.stderr[-3000:]
        text = run.stdout + run.stderr
        line = reported(text, f"scene {SID}: render has to run")
        assert line == (
            f"scene {SID}: render has to run (parameters or inputs changed), but the data root {data} is "
            f"read-only for this build ({data / 'locks' / (SID + '.lock')}: Read-only file system); "
            f"make it writable or pass a --data this user can write, then re-run")
        assert "skipped ingest" in text and "skipped fit" in text and "Traceback" not in text


# -- a failed stage's time and memory -----------------------------------------------------------------

def test_a_failed_stage_keeps_its_seconds_and_peak_memory_in_the_ledger_and_status(reference, env,
                                                                                    tmp_path):
    from paradrive.pipeline.ledger import Ledger

    folder = copy_build(reference, tmp_path / "work")
    image = sorted((folder / SCENE_DIR / "images").rglob("*.jpg"))[-1]
    damaged = bytearray(image.read_bytes())
    damaged[2:40] = bytes(b ^ 0xFF for b in damaged[2:40])  # same size: found when the fit reads it
    image.write_bytes(bytes(damaged))
    run = faults.build(folder, env, "--stages", "fit", "--force")
    assert run.returncode == 1 and f"scene {SID}: image" in run.stdout + run.stderr, run.stdout[-3000:]
    status = subprocess.run([sys.executable, "-m", "paradrive.cli", "status", BUILD, "--manifests", "m",
                             "--json"], cwd=folder, env=env, capture_output=True, text=True)
    assert status.returncode == 0, status.stderr
    doc = json.loads(status.stdout)
    (failure,) = doc["failures"]
    assert failure["stage"] == "fit" and failure["seconds"] > 0 and failure["peak_rss_mb"] > 0
    (fit,) = [s for s in doc["stages"] if s["stage"] == "fit"]
    assert fit["failed"] == 1 and fit["seconds_total"] == failure["seconds"] and fit["peak_rss_mb_max"] > 0
    rows = Ledger(folder / "m" / BUILD / "ledger.sqlite", BUILD).tasks()
    (scene,) = doc["slowest"]   # the scene's time counts its failed fit too
    assert scene["state"] == "failed" and scene["seconds"] == pytest.approx(
        sum(r["seconds"] or 0.0 for r in rows if r["scene_id"] == SID and r["state"] != "blocked"), abs=1e-3)
