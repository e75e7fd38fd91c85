"""Fit throughput: iterations per second at smoke and demo sizes, fused CPU kernels against the
torch-op rasterizer; prints JSON.

    .venv/bin/python bench/bench_fit.py [--sizes smoke,demo] [--iterations 60] [--threads 2]
                                        [--backends cpu,torch]

Each size ingests the synthetic street with that profile's ingest parameters, then times a fit
per backend with that profile's fit parameters shortened to ``--iterations`` (the first
iterations, before densification, dominate neither way: the count is reported next to the rate).
Both fits start from the same scene and the same initial Gaussians; ``speedup`` is the ratio of
their rates, measured in the same process, the first backend's rate the mean of a run before and
a run after the second's (a shared machine's speed drifts within minutes; the bracket cancels a
steady drift). Wall and process CPU seconds are both reported; on a
shared machine trust the ratio.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def ingest(profile: str, root: Path) -> tuple[Path, dict]:
    """The synthetic street ingested with the profile's parameters: (scene dir, fit params)."""
    from paradrive.pipeline import StageRegistry, run_build

    config = StageRegistry().resolve(profile)
    report = run_build(config, ["synthetic:demo?seed=7"], root / "data", stages=["ingest"],
                       manifests_dir=root / "manifests", build=profile)
    if report.failures():
        raise RuntimeError([r.error for r in report.failures()])
    (scene_dir,) = (root / "data" / "scenes").iterdir()
    return scene_dir, dict(config.params["fit"])


def time_fit(scene_dir: Path, params: dict, backend: str, *, label: str | None = None,
             moving_threshold_m: float | None = None) -> dict:
    """One fit of the scene with ``backend``, from scratch (its gs/ folder removed first)."""
    from paradrive.stages.fit import fit_scene
    from paradrive.stages.fit import Params

    shutil.rmtree(scene_dir / "gs", ignore_errors=True)
    typed = Params.of("fit", {**params, "backend": backend})
    t0, c0 = time.perf_counter(), time.process_time()
    record = fit_scene(scene_dir, typed, moving_threshold_m=moving_threshold_m)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    last = record.checkpoints[-1]
    return {"run": label or backend, "backend": backend, "gaussians": last.num_gaussians,
            "actor_nodes": len(record.actors),
            "fit_seconds": round(last.seconds, 2), "wall_seconds_with_setup": round(wall, 2),
            "cpu_seconds": round(cpu, 2),
            "iterations_per_second": round(typed.iterations / last.seconds, 3),
            "psnr": round(last.psnr, 2), "peak_rss_mb": last.peak_rss_mb,
            "resolution": record.resolution, "init": record.init.method}


def first_call_seconds(backend: str) -> float:
    """A tiny forward+backward: the one-off cost (importing the kernels, torch's first calls) that
    the fit would otherwise count as its own."""
    import torch

    from paradrive.gs.rasterize import rasterize

    leaves = [torch.rand(4, 3).add_(torch.tensor([0.0, 0.0, 2.0])), torch.rand(4, 4),
              torch.full((4, 3), 0.1), torch.rand(4), torch.rand(4, 16, 3)]
    leaves = [t.requires_grad_(True) for t in leaves]
    K = torch.tensor([[[20.0, 0, 16], [0, 20.0, 16], [0, 0, 1]]])
    t0 = time.perf_counter()
    out, alphas, _ = rasterize(*leaves, torch.eye(4)[None], K, 32, 32, sh_degree=3,
                               render_mode="RGB+ED", backend=backend)
    (out.sum() + alphas.sum()).backward()
    return round(time.perf_counter() - t0, 2)


def bench(profile: str, iterations: int, threads: int | None, backends: list[str],
          root: Path) -> dict:
    import torch

    from paradrive import kernels

    first = {b: first_call_seconds(b) for b in backends}
    scene_dir, params = ingest(profile, root)
    params.update(checkpoints=[iterations], keep_state=False)
    if threads is not None:
        params["threads"] = threads
    runs = [time_fit(scene_dir, params, b) for b in backends]
    if len(backends) > 1:  # the first backend again after the others: the machine's drift
        runs.append(time_fit(scene_dir, params, backends[0], label=f"{backends[0]} (again)"))
    scene = json.loads((scene_dir / "scene.json").read_text())
    cam = next(iter(scene["cameras"].values()))
    out = {"profile": profile, "iterations": iterations, "frames": len(scene["frames"]),
           "image_resolution": [cam["width"], cam["height"]], "threads": params["threads"],
           "torch": torch.__version__, "load_average": [round(x, 2) for x in os.getloadavg()],
           "kernels": getattr(kernels.load(), "__name__", None),
           "first_call_seconds": first, "runs": runs}
    if len(runs) > 1:
        rate = (runs[0]["iterations_per_second"] + runs[-1]["iterations_per_second"]) / 2
        out["speedup"] = round(rate / runs[1]["iterations_per_second"], 2)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="smoke,demo")
    ap.add_argument("--iterations", type=int, default=60)
    ap.add_argument("--threads", type=int, default=None, help="override the profile's fit threads")
    ap.add_argument("--backends", default="cpu,torch", help="the first is compared to the second")
    args = ap.parse_args()
    backends = [b.strip() for b in args.backends.split(",")]
    results = []
    for size in args.sizes.split(","):
        with tempfile.TemporaryDirectory() as tmp:
            results.append(bench(size.strip(), args.iterations, args.threads, backends, Path(tmp)))
    print(json.dumps({"bench": "fit", "machine": platform.machine(), "results": results}, indent=2))


if __name__ == "__main__":
    main()
