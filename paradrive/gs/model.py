"""The 3D Gaussian model: raw (pre-activation) parameters, their activations, SH colour, rendering.

Parameters are a plain dict of tensors (``torch.nn.Parameter`` while training), the layout of the
3DGS reference and of the PLY files:

====================  ============  =================================================
key                   shape         meaning (activation)
====================  ============  =================================================
``means``             (N, 3)        world position, metres (identity)
``scales``            (N, 3)        log of the standard deviations along the axes (exp)
``quats``             (N, 4)        rotation, w x y z, unnormalised (normalise)
``opacities``         (N,)          opacity logit (sigmoid)
``sh0``               (N, 1, 3)     SH band 0 (colour = SH_C0 * sh0 + 0.5)
``shN``               (N, K-1, 3)   SH bands 1..degree, K = (degree + 1) ** 2
====================  ============  =================================================
"""

from __future__ import annotations

import math
from contextlib import contextmanager
from collections.abc import Mapping
from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    import numpy as np

Params = dict[str, torch.Tensor]
Gaussians = Mapping[str, torch.Tensor]   # what a render reads: plain tensors or fit Parameters

SH_C0 = 0.28209479177387814
PARAM_KEYS = ("means", "scales", "quats", "opacities", "sh0", "shN")


def num_sh_bases(degree: int) -> int:
    """Number of SH coefficients per colour channel for bands 0..degree: (degree + 1) ** 2."""
    return (degree + 1) ** 2


def sh_degree_of(params: Gaussians) -> int:
    """The SH degree the parameters hold (from the shape of ``shN``)."""
    k = 1 + params["shN"].shape[1]
    d = int(round(math.sqrt(k))) - 1
    if num_sh_bases(d) != k:
        raise ValueError(f"shN holds {k - 1} coefficients per channel: not (d+1)^2 - 1 for any d")
    return d


def rgb_to_sh0(rgb: torch.Tensor) -> torch.Tensor:
    """Colour in [0, 1] (..., 3) -> band-0 SH coefficient (..., 3)."""
    return (rgb - 0.5) / SH_C0


def sh0_to_rgb(sh0: torch.Tensor) -> torch.Tensor:
    """Band-0 SH coefficient (..., 3) -> view-independent colour (..., 3), unclamped."""
    return sh0 * SH_C0 + 0.5


def logit(p: torch.Tensor | float) -> torch.Tensor:
    p = torch.as_tensor(p, dtype=torch.float32)
    return torch.log(p / (1.0 - p))


def new_params(means: torch.Tensor, rgb: torch.Tensor, scales: torch.Tensor, *, opacity: float = 0.1,
               sh_degree: int = 3) -> Params:
    """Raw parameters for N Gaussians.

    means: (N, 3) world; rgb: (N, 3) in [0, 1]; scales: (N, 3) standard deviations in metres
    (activated; stored as log). Rotations start at identity, opacities at ``opacity``,
    SH bands above 0 at zero.
    """
    n = means.shape[0]
    quats = torch.zeros(n, 4, dtype=torch.float32)
    quats[:, 0] = 1.0
    return {
        "means": means.float().contiguous(),
        "scales": torch.log(scales.float().clamp_min(1e-7)).contiguous(),
        "quats": quats,
        "opacities": torch.full((n,), float(logit(opacity)), dtype=torch.float32),
        "sh0": rgb_to_sh0(rgb.float().clamp(0.0, 1.0))[:, None, :].contiguous(),
        "shN": torch.zeros(n, num_sh_bases(sh_degree) - 1, 3, dtype=torch.float32),
    }


def cat_params(a: Params, b: Params) -> Params:
    """Concatenate two parameter sets along the Gaussian axis."""
    return {k: torch.cat([a[k], b[k]], 0) for k in PARAM_KEYS}


def activated(params: Gaussians) -> dict:
    """Activated tensors as the rasterizer takes them.

    Returns means (N, 3), quats (N, 4) (unnormalised; the rasterizer normalises),
    scales (N, 3) metres, opacities (N,) in (0, 1), sh: the coefficients in their two parts
    (sh0 (N, 1, 3), shN (N, K - 1, 3)), which the rasterizer takes as they are.
    """
    return {
        "means": params["means"],
        "quats": params["quats"],
        "scales": torch.exp(params["scales"]),
        "opacities": torch.sigmoid(params["opacities"]),
        "sh": (params["sh0"], params["shN"]),
    }


def render_gaussians(params: Gaussians, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int, *,
           sh_degree: int | None = None, render_mode: str = "RGB",
           backgrounds: torch.Tensor | None = None, **kwargs):
    """Render the Gaussians from C cameras.

    viewmats: (C, 4, 4) world-to-camera, OpenCV; Ks: (C, 3, 3) pixels; ``sh_degree``: bands
    to evaluate (default: all the parameters hold). ``render_mode`` "RGB" or "RGB+ED"
    (expected depth as a 4th channel). Returns (renders (C, H, W, 3|4), alphas (C, H, W, 1),
    info) exactly as :func:`paradrive.gs.rasterize.rasterize`.
    """
    from paradrive.gs.rasterize import rasterize

    a = activated(params)
    degree = sh_degree_of(params) if sh_degree is None else int(sh_degree)
    return rasterize(a["means"], a["quats"], a["scales"], a["opacities"], a["sh"],
                     viewmats, Ks, int(width), int(height), sh_degree=degree,
                     backgrounds=backgrounds, render_mode=render_mode, **kwargs)


def scene_scale_of(c2w: torch.Tensor | np.ndarray) -> float:
    """3DGS scene extent: 1.1 x the largest distance of a camera centre from their mean.

    c2w: (F, 4, 4) camera-to-world. Floored at 1 m so a standing camera still gets a scale.
    """
    c = torch.as_tensor(c2w, dtype=torch.float64)[:, :3, 3]
    d = (c - c.mean(0)).norm(dim=1).max().item() if len(c) else 0.0
    return max(1.1 * d, 1.0)


@contextmanager
def deterministic_torch(threads: int, backend: str = "torch"):
    """Fixed thread count and deterministic kernels (fit, render); restored afterwards.

    A fixed count makes torch's floating-point sums, hence the files, identical whichever
    executor runs the stage. With the fused CPU kernels (``backend`` 'cpu', built) the kernels take the
    ``threads`` (their results do not depend on the count) and torch's own operations run on one:
    torch's idle OpenMP workers spin on the cores the kernels need (a demo fit iteration on two
    cores: 45 ms with both on two threads, 37 ms so).
    """
    from paradrive.devices import set_cpu_kernel_threads
    from paradrive import kernels

    old_threads = torch.get_num_threads()
    old_det = torch.are_deterministic_algorithms_enabled()
    old_warn = torch.is_deterministic_algorithms_warn_only_enabled()
    fused = backend == "cpu" and kernels.load() is not None  # else the torch-op stages run
    old_kernels = set_cpu_kernel_threads(threads if fused and threads > 0 else 0)
    if threads > 0:
        torch.set_num_threads(1 if fused else threads)
    torch.use_deterministic_algorithms(True, warn_only=True)
    try:
        yield
    finally:
        torch.set_num_threads(old_threads)
        set_cpu_kernel_threads(old_kernels)
        torch.use_deterministic_algorithms(old_det, warn_only=old_warn)
