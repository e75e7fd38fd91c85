"""Forward+backward time of the CPU rasterizers: the fused kernels (backend 'cpu') against the
torch-op rasterizer (backend 'torch') on the same scene, and both against gsplat's pure-torch
reference pipeline (the test oracle in tests/test_rasterize.py).

    python bench/bench_rasterize.py [--gaussians 100000 --width 832 --height 480] [--threads 2]

``full.speedup`` is torch-op time / fused time at full size, measured in the same process, each
on --threads as the stages run it (``deterministic_torch``: the fused kernels on the threads and
torch's own operations on one; the torch-op rasterizer on all of them). The
reference builds its tile lists in a Python loop per Gaussian and expands every tile-Gaussian
pair to all tile pixels, so it is measured on the first --ref-gaussians of the same scene
(default: min(--gaussians, 20000)), with both backends at that size too. Prints one JSON object.
"""

from __future__ import annotations

import argparse
import functools
import importlib.util
import json
import math
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from paradrive.gs.model import deterministic_torch  # noqa: E402
from paradrive.gs.rasterize import rasterize  # noqa: E402


def make_scene(n: int, width: int, height: int, seed: int = 0):
    """n Gaussians spread over the view frustum at 4..40 m, each a few to tens of pixels wide."""
    g = torch.Generator().manual_seed(seed)
    f = 0.8 * width
    z = 4.0 + 36.0 * torch.rand(n, generator=g) ** 1.5
    u = torch.rand(n, generator=g) * width
    v = torch.rand(n, generator=g) * height
    means = torch.stack([(u - width / 2) * z / f, (v - height / 2) * z / f, z], -1)
    sigma_px = torch.exp(torch.empty(n, 3).uniform_(math.log(0.4), math.log(3.0), generator=g))
    scales = sigma_px * z[:, None] / f
    quats = torch.randn(n, 4, generator=g)
    opacities = torch.rand(n, generator=g) * 0.9 + 0.05
    sh = torch.randn(n, 16, 3, generator=g) * 0.2
    viewmats = torch.eye(4)[None]
    Ks = torch.tensor([[[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]]])
    # SH coefficients in the two parts a fit keeps them in (sh0, shN)
    return (dict(means=means, quats=quats, scales=scales, opacities=opacities, sh0=sh[:, :1].clone(),
                 shN=sh[:, 1:].clone()), viewmats, Ks)


def _args(leaves: dict) -> tuple:
    return (leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"],
            (leaves["sh0"], leaves["shN"]))


def load_reference():
    spec = importlib.util.spec_from_file_location("_raster_ref", ROOT / "tests" / "test_rasterize.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    mod.install_cpu_stand_ins()

    def reference(means, quats, scales, opacities, colors, *args, **kw):
        return mod.reference_rasterize(means, quats, scales, opacities, torch.cat(colors, 1), *args,
                                       **kw)

    return reference


def time_once(fn, scene, viewmats, Ks, width, height) -> tuple[float, float]:
    """(forward, backward) seconds of one call on fresh leaves."""
    leaves = {k: v.clone().requires_grad_(True) for k, v in scene.items()}
    t0 = time.perf_counter()
    renders, alphas, _ = fn(*_args(leaves), viewmats, Ks, width, height, sh_degree=3)
    t1 = time.perf_counter()
    (renders.sum() + alphas.sum()).backward()
    return t1 - t0, time.perf_counter() - t1


def median_run(runs: list[tuple[float, float]]) -> dict:
    """The run of median total (the faster middle one for an even count)."""
    total = [f + b for f, b in runs]
    i = total.index(statistics.median(total)) if len(total) % 2 else total.index(min(total))
    f, b = runs[i]
    return {"forward_s": round(f, 4), "backward_s": round(b, 4), "total_s": round(f + b, 4)}


def time_fwd_bwd(fn, scene, viewmats, Ks, width, height, repeats):
    return median_run([time_once(fn, scene, viewmats, Ks, width, height) for _ in range(repeats)])


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--gaussians", type=int, default=100_000)
    p.add_argument("--width", type=int, default=832)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--ref-gaussians", type=int, default=None)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--no-reference", action="store_true")
    a = p.parse_args(argv)
    if a.threads:
        torch.set_num_threads(a.threads)
    n_ref = a.ref_gaussians or min(a.gaussians, 20_000)
    W, H = a.width, a.height

    backends = {name: functools.partial(rasterize, backend=name) for name in ("cpu", "torch")}
    scene, viewmats, Ks = make_scene(a.gaussians, W, H)
    threads = torch.get_num_threads()
    infos = {}
    for name, fn in backends.items():  # warm-up (and the native library's first load)
        with deterministic_torch(threads, name):
            infos[name] = fn(*_args(scene), viewmats, Ks, W, H, sh_degree=3)[2]
    info = infos["cpu"]  # the fused kernels' lists (the torch-op rasterizer's tiles differ)

    def timed(scene_: dict) -> dict:
        """Both backends on threads as the stages set them (deterministic_torch), their runs
        interleaved so that a busy spell on a shared machine slows both."""
        runs: dict[str, list] = {name: [] for name in backends}
        for _ in range(a.repeats):
            for name, fn in backends.items():
                with deterministic_torch(threads, name):
                    runs[name].append(time_once(fn, scene_, viewmats, Ks, W, H))
        return {name: median_run(r) for name, r in runs.items()}

    full = timed(scene)
    result = {
        "device": "cpu", "torch": torch.__version__, "threads": threads,
        "machine": platform.processor() or platform.machine(),
        "load_average": [round(x, 2) for x in os.getloadavg()],
        "width": W, "height": H, "cameras": 1, "sh_degree": 3,
        "full": {"gaussians": a.gaussians, "visible": int((info["radii"] > 0).sum()),
                 "tile_isects": info["n_isects"], **full,
                 "speedup": round(full["torch"]["total_s"] / full["cpu"]["total_s"], 2)},
    }
    if not a.no_reference:
        small = {k: v[:n_ref] for k, v in scene.items()}
        times = timed(small)
        ref_small = time_fwd_bwd(load_reference(), small, viewmats, Ks, W, H, 1)
        result["compared"] = {
            "gaussians": n_ref, **times, "reference": ref_small,
            "speedup_vs_reference": {name: round(ref_small["total_s"] / t["total_s"], 2)
                                     for name, t in times.items()},
        }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
