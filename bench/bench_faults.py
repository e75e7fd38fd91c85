"""Fault injection at scale: kill a real build N times at random points of every stage.

Each kill is a fresh ``paradrive build`` of the tiny synthetic scene in a folder of its own,
SIGKILLed at a point drawn from the seed (see ``tests/test_faults.py`` for the points: the k-th
file of the stage's temporary folder, the k-th fit checkpoint, a named step of publishing),
followed by a plain re-run. Every kill must end healed: exit code 0, ``inspect --verify``
clean, no temporary left, nothing outside ``data/`` and ``m/``, and every output with the bytes
of one uninterrupted build (files recording times excepted). The test suite runs one kill per
stage; this runs ``--n`` per stage.

    .venv/bin/python bench/bench_faults.py --n 10 --seed 1 [--stages fit,clip] [--json out.json]

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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=5, help="kills per stage")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--stages", default=",".join(faults.STAGES))
    ap.add_argument("--republish", type=int, default=0, help="republishes under running readers")
    ap.add_argument("--missing", type=int, default=0, help="plan and build of this many missing inputs")
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
    return ((readers is None or (not readers["failed"] and all(
        not loop.get("errors") for loop in readers["loops"].values())))
            and (missing is None or (missing["plan"]["exit"] == missing["build"]["exit"] == 2
                                     and not missing["left_behind"])))


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
