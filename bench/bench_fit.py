"""Fit throughput: iterations per second at smoke and demo sizes; prints JSON.

    .venv/bin/python bench/bench_fit.py [--sizes smoke,demo] [--iterations 60]

Each size ingests the synthetic street with that profile's ingest parameters, then times a fit
with that profile's fit parameters shortened to ``--iterations`` (the first iterations, before
densification, dominate neither way: the count is reported next to the rate). Wall and process
CPU seconds are both reported; on a shared machine trust the CPU figure.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def bench(profile: str, iterations: int, root: Path) -> dict:
    import torch

    from paradrive.gs.fit import fit_scene
    from paradrive.pipeline import StageRegistry, run_build

    config = StageRegistry().resolve(profile)
    report = run_build(config, ["synthetic:demo?seed=7"], root / "data", stages=["ingest"],
                       manifests_dir=root / "manifests", build=profile)
    if report.failures():
        raise RuntimeError([r.error for r in report.failures()])
    (scene_dir,) = (root / "data" / "scenes").iterdir()
    params = dict(config.params["fit"])
    params["checkpoints"] = [iterations]
    params["keep_state"] = False
    t0, c0 = time.perf_counter(), time.process_time()
    doc = fit_scene(scene_dir, params)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    last = doc["checkpoints"][-1]
    scene = json.loads((scene_dir / "scene.json").read_text())
    cam = next(iter(scene["cameras"].values()))
    return {"profile": profile, "iterations": iterations, "frames": len(scene["frames"]),
            "train_resolution": doc["resolution"], "image_resolution": [cam["width"], cam["height"]],
            "gaussians": last["num_gaussians"], "init": doc["init"]["method"],
            "fit_seconds": round(last["seconds"], 2), "wall_seconds_with_setup": round(wall, 2),
            "cpu_seconds": round(cpu, 2),
            "iterations_per_second": round(iterations / last["seconds"], 3),
            "psnr": round(last["psnr"], 2), "peak_rss_mb": last["peak_rss_mb"],
            "torch_threads": params["threads"], "device": doc["device"],
            "torch": torch.__version__}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="smoke,demo")
    ap.add_argument("--iterations", type=int, default=60)
    args = ap.parse_args()
    results = []
    for size in args.sizes.split(","):
        with tempfile.TemporaryDirectory() as tmp:
            results.append(bench(size.strip(), args.iterations, Path(tmp)))
    print(json.dumps({"bench": "fit", "machine": platform.machine(), "results": results}, indent=2))


if __name__ == "__main__":
    main()
