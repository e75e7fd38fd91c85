"""Fault injection at scale: kill a real build N times at random points of every stage.

Each kill is a fresh ``paradrive build`` of the tiny synthetic scene in a folder of its own,
SIGKILLed at a point drawn from the seed (see ``tests/test_faults.py`` for the points: the k-th
file of the stage's temporary folder, the k-th fit checkpoint, a named step of publishing),
followed by a plain re-run. Every kill must end healed: exit code 0, ``inspect --verify``
clean, no temporary left, nothing outside ``data/`` and ``m/``, and every output with the bytes
of one uninterrupted build (files recording times excepted). The test suite runs one kill per
stage; this runs ``--n`` per stage.

    .venv/bin/python bench/bench_faults.py --n 10 --seed 1 [--stages fit,clip] [--json out.json]
    .venv/bin/python bench/bench_faults.py --n 0 --shard-flip 4
    .venv/bin/python bench/bench_faults.py --n 0 --full-disk 2

Prints one line per kill and a table per stage; exits 1 when any kill did not heal.

``--republish N`` (with ``--n 0`` for this alone): readers run while a build is republished
N times, every other time SIGKILLed at a publishing step and re-run. A reader process iterates the
build pass after pass through ``PairIterableDataset`` (refreshing at each epoch boundary) and a
``PairDataset`` opened once, counting samples, complete passes and errors; any error fails the
bench. Other loops can run beside it: ``BACKGROUND`` maps a name to the script of a process that
works on the build until its stop file appears and then prints one JSON summary line.

``--missing N``: ``plan`` and ``build`` of N scene inputs whose files do not exist, against
``paradrive --version`` in the same run: both must refuse (exit 2) in about the time of starting
the command.

``--shard-flip N``: N times, one bit of a published pair shard flipped at a place drawn from the
seed, its size and modification time set back (so only its bytes tell). A reader process must
then refuse the build with the one shard-checksum error naming that shard (and says what reading
without the check gives: wrong rows, the same rows, or a Parquet error); a plain re-run of the
build must heal it
(exit 0, ``inspect --verify`` clean, every output with the bytes of the uninterrupted build), and
the reader must read every sample again, with the rows it read before the flip.

``--full-disk N``: N publishes (a first publish and a republish in turn) on a real full disk: a
small tmpfs under ``--manifests``, filled until the ledger's writes fit and the pairs' media do
not. Each must exit 1 with the version before it (if any) still published, its ``--retry-failed``
still on the full disk must exit 1 again, and once the filling file is deleted the retry must
exit 0 with the pairs of a build published in one go. Needs root (to mount); skipped otherwise.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))

import test_faults as faults  # noqa: E402  (the kill points and checks of the test suite)


# A reader: argv = build folder, stop file. Epoch after epoch until the stop file appears; one
# JSON line at the end. It never stops on an error: it counts it and starts the next pass.
READER = """
import json, sys
from pathlib import Path
from paradrive.data import PairDataset, PairIterableDataset

build, stop = sys.argv[1], Path(sys.argv[2])
ds = PairIterableDataset(build, seed=0, dtype="uint8", num_frames=2, output_size=(48, 64))
once = PairDataset(build, dtype="uint8", num_frames=2, output_size=(48, 64))
passes = complete = samples = 0
errors, versions = [], []
while not stop.exists():
    ds.set_epoch(passes, refresh=True)
    versions.append(ds.version)
    seen = 0
    try:
        for _ in ds:
            seen += 1
        for i in range(len(once)):
            once[i]
            seen += 1
    except Exception as exc:
        errors.append(f"pass {passes}: {type(exc).__name__}: {exc}"[:300])
    passes += 1
    samples += seen
    complete += seen == len(ds) + len(once)
print(json.dumps({"passes": passes, "complete": complete, "samples": samples, "errors": errors,
                  "versions": sorted(set(versions)), "once": once.version}))
"""
# what runs beside the republishes and kills: name -> script (argv: build folder, stop file)
BACKGROUND = {"reader": READER}
PUBLISH_STOPS = ("publish:first-media", "publish:before-switch", "publish:after-switch")


def republish_under_readers(work: Path, env: dict[str, str], times: int, rng: random.Random,
                            during: tuple[str, ...] = ("reader",)) -> dict:
    """Republish a tiny build ``times`` times (other shard settings each time; every other time
    SIGKILLed at a publishing step, then re-run) while the ``during`` loops work on it."""
    folder = work / "readers"
    faults.reference_build(folder, env)
    build_dir, stop = folder / "m" / faults.BUILD, folder / "stop"
    loops = {name: subprocess.Popen([sys.executable, "-c", BACKGROUND[name], str(build_dir), str(stop)],
                                    env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for name in during}
    kills, failed, t0 = 0, [], time.time()
    try:
        for i in range(times):
            extra = ["--stages", "manifest", "--set", f"manifest.shard_rows={rng.randint(1, 30)}",
                     "--set", f"manifest.row_group_rows={rng.randint(1, 16)}"]
            if i % 2:
                kills += _killed_publish(folder, env, extra, rng.choice(PUBLISH_STOPS))
            done = faults.build(folder, env, *extra)
            if done.returncode != 0:
                failed.append(f"republish {i}: exit {done.returncode}: {done.stdout[-500:]}")
    finally:
        stop.touch()
    summaries = {name: json.loads(proc.communicate(timeout=600)[0].strip().splitlines()[-1])
                 for name, proc in loops.items()}
    return {"republishes": times, "killed": kills, "seconds": round(time.time() - t0, 1),
            "failed": failed, "loops": summaries}


def _killed_publish(folder: Path, env: dict[str, str], extra: list[str], step: str) -> bool:
    proc = subprocess.Popen(faults.build_command(*extra), cwd=folder,
                            env={**env, "PARADRIVE_STOP_AT": step}, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    _, status = os.waitpid(proc.pid, os.WUNTRACED)
    stopped = os.WIFSTOPPED(status)
    if stopped:
        os.killpg(proc.pid, signal.SIGKILL)
        os.waitpid(proc.pid, 0)
    proc.returncode = 0   # reaped here
    return stopped


# A reader of a build whose shard may be flipped: argv = build folder. One JSON line: the samples
# read with the shards checked (or the error), and a digest of every row read without the check
# (or the error that reading them raised).
FLIP_READER = """
import hashlib, json, sys
from paradrive.data import PairDataset
from paradrive.pairs import ShardChecksumError

build, out = sys.argv[1], {}
try:
    ds = PairDataset(build, dtype="uint8", num_frames=2, output_size=(48, 64))
    out["samples"] = sum(1 for i in range(len(ds)) if ds[i]["pair_id"])
except ShardChecksumError as exc:
    out["error"] = str(exc)
try:
    raw, digest = PairDataset(build, verify_shards=False), hashlib.sha256()
    for i in range(len(raw)):
        for name, value in sorted(raw.row(i).items()):
            digest.update(name.encode() + (value.tobytes() if hasattr(value, "tobytes") else repr(value).encode()))
    out["rows_digest"] = digest.hexdigest()
except Exception as exc:
    out["unverified_error"] = f"{type(exc).__name__}: {exc}"[:300]
print(json.dumps(out))
"""


def shard_flips(work: Path, env: dict[str, str], times: int, rng: random.Random) -> list[dict]:
    """Flip a bit of a published shard ``times`` times (see the module's docstring): each must be
    refused by the reader, healed by a plain re-run, and read again with the rows of before."""
    folder = work / "shard-flip"
    faults.reference_build(folder, env)
    expected, build_dir = faults.outputs(folder), folder / "m" / faults.BUILD
    before = _read_flipped(build_dir, env)
    rows = []
    for i in range(times):
        rel, offset, bit = _flip(build_dir, rng)
        damaged = _read_flipped(build_dir, env)
        t0 = time.time()
        problems = faults.healed(folder, env, expected)
        after = _read_flipped(build_dir, env)
        error = damaged.get("error", "")
        refused = (not damaged.get("samples") and "\n" not in error and
                   error.startswith(f"build {build_dir}: shard {rel} does not match") and
                   "run paradrive build" in error)
        reads_again = after == before
        unchecked = ("unreadable" if "rows_digest" not in damaged else
                     "same rows" if damaged["rows_digest"] == before["rows_digest"] else "wrong rows")
        rows.append({"flip": i, "shard": rel, "offset": offset, "bit": bit, "refused": refused,
                     "error": error, "without_check": unchecked, "problems": problems,
                     "reads_again": reads_again, "heal_seconds": round(time.time() - t0, 1)})
        print(f"flip {i}: {rel} byte {offset} bit {bit}: {'refused' if refused else 'NOT refused'}"
              f" (without the check: {unchecked}); "
              f"{'healed' if not problems else '; '.join(problems[:3])}; "
              f"{'reads again' if reads_again else 'does NOT read as before'}", flush=True)
    return rows


def _flip(build_dir: Path, rng: random.Random) -> tuple[str, int, int]:
    """One bit of one of the published shards flipped in place, its size and mtime set back."""
    index = json.loads((build_dir / "index.json").read_text())
    rel = f"{index['version']}/{rng.choice(index['shards'])['file']}"
    shard = build_dir / rel
    stat = shard.stat()
    offset, bit = rng.randrange(stat.st_size), rng.randrange(8)
    with open(shard, "r+b") as f:
        f.seek(offset)
        byte = f.read(1)[0] ^ (1 << bit)
        f.seek(offset)
        f.write(bytes([byte]))
    os.utime(shard, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    return rel, offset, bit


def _read_flipped(build_dir: Path, env: dict[str, str]) -> dict:
    done = subprocess.run([sys.executable, "-c", FLIP_READER, str(build_dir)], env=env,
                          capture_output=True, text=True)
    if done.returncode != 0:
        return {"reader_failed": done.stderr.strip().splitlines()[-1:]}
    return json.loads(done.stdout.strip().splitlines()[-1])


def missing_inputs(work: Path, env: dict[str, str], count: int) -> dict:
    """CPU and wall seconds of ``plan`` and ``build`` refusing ``count`` inputs that are not
    there, and of ``paradrive --version`` (the command's start) in the same run."""
    listing = work / "missing.txt"
    listing.write_text("".join(f"waymo:{work}/nowhere/segment-{k}_with_camera_labels.tfrecord\n"
                               for k in range(count)))
    base = [sys.executable, "-m", "paradrive.cli"]
    runs = {"version": base + ["--version"],
            "plan": base + ["plan", "--scenes", str(listing), "--data", str(work / "d")],
            "build": base + ["build", "--scenes", str(listing), "--profile", "smoke", "--data",
                             str(work / "d"), "--manifests", str(work / "m")]}
    out = {}
    for name, command in runs.items():
        before, t0 = resource.getrusage(resource.RUSAGE_CHILDREN), time.time()
        done = subprocess.run(command, env=env, capture_output=True, text=True)
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        out[name] = {"exit": done.returncode, "wall_s": round(time.time() - t0, 2),
                     "cpu_s": round(after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime, 2),
                     "line": done.stderr.strip().splitlines()[-1][:160] if done.stderr.strip() else ""}
    out["left_behind"] = sorted(p.name for p in work.iterdir() if p.name in ("d", "m"))
    return out


def publish_on_full_disk(work: Path, env: dict[str, str], times: int) -> list[dict]:
    """``--full-disk``: each publish on a full disk fails, its retry publishes once space is
    freed (see the module's docstring)."""
    from test_publish_retry import ROOM_FOR_THE_LEDGER, fill

    if os.geteuid() != 0:
        print("full disk: skipped (mounting a tmpfs needs root)", flush=True)
        return []
    folder = work / "full-disk"
    folder.mkdir(parents=True)
    options = ["--profile", "smoke", "--data", "data", "--build", "F"]

    def build(manifests: Path, *extra: str) -> subprocess.CompletedProcess:
        """The build of the scene, or its retry (which takes its scenes from the ledger)."""
        scene = [] if "--retry-failed" in extra else ["--scene", "synthetic:demo?seed=7"]
        return subprocess.run([sys.executable, "-m", "paradrive.cli", "build", *scene, *options,
                               "--manifests", str(manifests), *extra], cwd=folder, env=env,
                              capture_output=True, text=True)

    assert build(folder / "reference").returncode == 0
    shards = [s["sha256"] for s in json.loads((folder / "reference/F/index.json").read_text())["shards"]]
    rows = []
    for i in range(times):
        disk = folder / f"m{i}"
        disk.mkdir()
        subprocess.run(["mount", "-t", "tmpfs", "-o", "size=16m", "tmpfs", str(disk)], check=True)
        try:
            rows.append(_full_disk_publish(disk, build, shards, republish=i % 2 == 1, fill=fill,
                                           room=ROOM_FOR_THE_LEDGER))
        finally:
            subprocess.run(["umount", "-l", str(disk)], check=True)
        print(f"full disk {'republish' if i % 2 else 'first publish'}: "
              f"{'; '.join(rows[-1]['problems']) or 'failed, retried, published'}", flush=True)
    return rows


def _full_disk_publish(disk: Path, build, shards: list[str], *, republish: bool, fill, room: int) -> dict:
    index = disk / "F" / "index.json"
    change = ("--set", "manifest.row_group_rows=32") if republish else ()
    problems = []
    if republish and build(disk).returncode != 0:
        problems.append("the first publish failed on an empty disk")
    before = index.read_text() if index.exists() else None
    filler = fill(disk, room)
    failed = build(disk, *change)
    if failed.returncode != 1:
        problems.append(f"the publish on a full disk exited {failed.returncode}, not 1")
    if (index.read_text() if index.exists() else None) != before:
        problems.append("the published version changed on a full disk")
    if build(disk, "--retry-failed", *change).returncode != 1:
        problems.append("the retry on a still full disk did not exit 1")
    filler.unlink()
    retried = build(disk, "--retry-failed", *change)
    if retried.returncode != 0:
        problems.append(f"the retry with space exited {retried.returncode}: {retried.stdout[-300:]}")
    elif not republish and [s["sha256"] for s in json.loads(index.read_text())["shards"]] != shards:
        problems.append("the retried publish has other shards than a publish in one go")
    return {"republish": republish, "exit_full": failed.returncode, "exit_retry": retried.returncode,
            "problems": problems}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=5, help="kills per stage")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--stages", default=",".join(faults.STAGES))
    ap.add_argument("--republish", type=int, default=0, help="republishes under running readers")
    ap.add_argument("--missing", type=int, default=0, help="plan and build of this many missing inputs")
    ap.add_argument("--shard-flip", type=int, default=0,
                    help="bits flipped in a published shard, each refused, healed and read again")
    ap.add_argument("--full-disk", type=int, default=0,
                    help="publishes on a full disk under --manifests, each failed, retried and published")
    ap.add_argument("--json", type=Path, default=None, help="write every kill's result here")
    args = ap.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="bench_faults-"))
    rows: list[dict] = []
    extra: dict = {}
    try:
        env = faults.environment(work / "cache")
        rng = random.Random(args.seed)
        if args.missing:
            extra["missing"] = missing_inputs(work, env, args.missing)
            print(json.dumps(extra["missing"], indent=2), flush=True)
        if args.republish:
            extra["readers"] = republish_under_readers(work, env, args.republish, rng)
            print(json.dumps(extra["readers"], indent=2), flush=True)
        if args.shard_flip:
            extra["shard_flips"] = shard_flips(work, env, args.shard_flip, rng)
        if args.full_disk:
            extra["full_disk"] = publish_on_full_disk(work, env, args.full_disk)
        if args.n:
            rows = _kills(work, env, args, rng)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    if args.json:
        args.json.write_text(json.dumps({"kills": rows, **extra}, indent=2))
    return 0 if all(not r["problems"] for r in rows) and _extra_ok(extra) else 1


def _extra_ok(extra: dict) -> bool:
    readers = extra.get("readers")
    missing = extra.get("missing")
    flips = extra.get("shard_flips", [])
    return ((readers is None or (not readers["failed"] and all(
        not loop.get("errors") for loop in readers["loops"].values())))
            and (missing is None or (missing["plan"]["exit"] == missing["build"]["exit"] == 2
                                     and not missing["left_behind"]))
            and all(f["refused"] and not f["problems"] and f["reads_again"] for f in flips)
            and all(not f["problems"] for f in extra.get("full_disk", [])))


def _kills(work: Path, env: dict[str, str], args, rng: random.Random) -> list[dict]:
    rows = []
    reference = faults.reference_build(work / "reference", env)
    expected = faults.outputs(reference)
    for stage in args.stages.split(","):
        for i, point in enumerate(faults.points(stage, rng, reference, args.n)):
            folder = work / f"{stage}-{i}"
            t0 = time.time()
            killed = faults.kill_at(folder, env, point)
            inside = killed and stage in faults.running_stages(folder)
            problems = faults.healed(folder, env, expected)
            rows.append({"stage": stage, "point": point.describe(), "killed": killed,
                         "inside_stage": inside, "problems": problems,
                         "seconds": round(time.time() - t0, 1)})
            print(f"{stage:<9} {point.describe():<60} "
                  f"{'killed' if killed else 'ended first'}{'' if inside else ' (stage done)'}: "
                  f"{'healed' if not problems else '; '.join(problems[:3])}", flush=True)
            shutil.rmtree(folder, ignore_errors=True)
    print(f"\n{'stage':<9} {'kills':>5} {'inside':>6} {'healed':>6}")
    for stage in args.stages.split(","):
        mine = [r for r in rows if r["stage"] == stage]
        print(f"{stage:<9} {sum(r['killed'] for r in mine):>5} "
              f"{sum(r['inside_stage'] for r in mine):>6} {sum(not r['problems'] for r in mine):>6}")
    return rows


if __name__ == "__main__":
    raise SystemExit(main())
