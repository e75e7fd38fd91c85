"""Forward+backward time of the CPU rasterizers: the fused kernels (backend 'cpu') against the
torch-op rasterizer (backend 'torch') on the same scene, and both against gsplat's pure-torch
reference pipeline (the test oracle in tests/test_rasterize.py).

    python bench/bench_rasterize.py [--gaussians 100000 --width 832 --height 480] [--threads 2]

``full.speedup`` is torch-op time / fused time at full size, measured in the same process. The
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
    return dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=sh), viewmats, Ks


def load_reference():
    spec = importlib.util.spec_from_file_location("_raster_ref", ROOT / "tests" / "test_rasterize.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    mod.install_cpu_stand_ins()
    return mod.reference_rasterize


def time_fwd_bwd(fn, scene, viewmats, Ks, width, height, repeats):
    fwd, bwd = [], []
    for _ in range(repeats):
        leaves = {k: v.clone().requires_grad_(True) for k, v in scene.items()}
        t0 = time.perf_counter()
        renders, alphas, _ = fn(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"],
                                leaves["colors"], viewmats, Ks, width, height, sh_degree=3)
        t1 = time.perf_counter()
        (renders.sum() + alphas.sum()).backward()
        t2 = time.perf_counter()
        fwd.append(t1 - t0)
        bwd.append(t2 - t1)
    total = [a + b for a, b in zip(fwd, bwd)]
    i = total.index(statistics.median(total)) if len(total) % 2 else total.index(min(total))
    return {"forward_s": round(fwd[i], 4), "backward_s": round(bwd[i], 4), "total_s": round(total[i], 4)}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--gaussians", type=int, default=100_000)
    p.add_argument("--width", type=int, default=832)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--ref-gaussians", type=int, default=None)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--no-reference", action="store_true")
    a = p.parse_args(argv)
    if a.threads:
        torch.set_num_threads(a.threads)
    n_ref = a.ref_gaussians or min(a.gaussians, 20_000)
    W, H = a.width, a.height

    backends = {name: functools.partial(rasterize, backend=name) for name in ("cpu", "torch")}
    scene, viewmats, Ks = make_scene(a.gaussians, W, H)
    for fn in backends.values():  # warm-up (and Numba's first load)
        _, _, info = fn(*scene.values(), viewmats, Ks, W, H, sh_degree=3)
    full = {name: time_fwd_bwd(fn, scene, viewmats, Ks, W, H, a.repeats)
            for name, fn in backends.items()}
    result = {
        "device": "cpu", "torch": torch.__version__, "threads": torch.get_num_threads(),
        "machine": platform.processor() or platform.machine(),
        "load_average": [round(x, 2) for x in os.getloadavg()],
        "width": W, "height": H, "cameras": 1, "sh_degree": 3,
        "full": {"gaussians": a.gaussians, "visible": int((info["radii"] > 0).sum()),
                 "tile_isects": info["n_isects"], **full,
                 "speedup": round(full["torch"]["total_s"] / full["cpu"]["total_s"], 2)},
    }
    if not a.no_reference:
        small = {k: v[:n_ref] for k, v in scene.items()}
        times = {name: time_fwd_bwd(fn, small, viewmats, Ks, W, H, a.repeats)
                 for name, fn in backends.items()}
        ref_small = time_fwd_bwd(load_reference(), small, viewmats, Ks, W, H, 1)
        result["compared"] = {
            "gaussians": n_ref, **times, "reference": ref_small,
            "speedup_vs_reference": {name: round(ref_small["total_s"] / t["total_s"], 2)
                                     for name, t in times.items()},
        }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
