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
"""

from __future__ import annotations

import argparse
import json
import random
import shutil
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))

import test_faults as faults  # noqa: E402  (the kill points and checks of the test suite)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=5, help="kills per stage")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--stages", default=",".join(faults.STAGES))
    ap.add_argument("--json", type=Path, default=None, help="write every kill's result here")
    args = ap.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="bench_faults-"))
    rows = []
    try:
        env = faults.environment(work / "cache")
        reference = faults.reference_build(work / "reference", env)
        expected = faults.outputs(reference)
        rng = random.Random(args.seed)
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
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print(f"\n{'stage':<9} {'kills':>5} {'inside':>6} {'healed':>6}")
    for stage in args.stages.split(","):
        mine = [r for r in rows if r["stage"] == stage]
        print(f"{stage:<9} {sum(r['killed'] for r in mine):>5} "
              f"{sum(r['inside_stage'] for r in mine):>6} {sum(not r['problems'] for r in mine):>6}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))
    return 0 if all(not r["problems"] for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
