"""Views of a fitted checkpoint: load a 3DGS PLY, render it from many cameras in batches (RGB,
alpha and depth with the sky dome left out).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from paradrive import geometry
from paradrive.errors import SceneError

if TYPE_CHECKING:
    from paradrive.stages.records import FitInit

__all__ = ["SkyDome", "sky_dome_of", "render_views", "load_checkpoint"]


# --------------------------------------------------------------------------- rendering

def load_checkpoint(path: str | os.PathLike, *, scene_id: str | None = None) -> dict:
    """Gaussian parameters of a 3DGS PLY checkpoint (see :mod:`paradrive.gs.ply`)."""
    from paradrive.gs.ply import load_ply

    path = Path(path)
    try:
        return load_ply(path)
    except (OSError, ValueError, KeyError) as exc:
        raise SceneError(f"checkpoint cannot be read: {type(exc).__name__}: {exc}",
                         scene_id=scene_id, path=path, fix="re-run the fit stage") from exc


@dataclass(frozen=True)
class SkyDome:
    """Where a fit keeps its sky: Gaussians farther than ``radius`` metres from ``centre``."""

    centre: np.ndarray   # (3,) world
    radius: float


def sky_dome_of(scene, init: FitInit | None) -> SkyDome | None:
    """The sky dome of a fit (its record's ``init``), or None when it has none.

    The dome is centred on the mean camera position of the scene; everything beyond half its
    radius counts as sky (street geometry lies within a few hundred metres, the dome at ~1 km).
    """
    if init is None or not init.sky_radius_m or not init.sky_points:
        return None
    centres = np.concatenate([scene.c2w(c)[:, :3, 3] for c in scene.cameras])
    return SkyDome(centre=centres.mean(0), radius=0.5 * init.sky_radius_m)


def render_views(params: dict, c2w: np.ndarray, K: np.ndarray, width: int, height: int, *,
                 depth: bool = False, batch_frames: int = 8, sky: SkyDome | None = None,
                 device: str = "auto", backend: str = "auto") -> Iterator[dict]:
    """Render Gaussians ``params`` from cameras ``c2w`` (N, 4, 4) (camera-to-world, OpenCV),
    ``batch_frames`` cameras per rasterizer call, all with intrinsics ``K`` (3, 3) at
    ``width x height``.

    Yields one dict per batch: ``rgb`` uint8 (B, H, W, 3), ``alpha`` float32 (B, H, W) and, with
    ``depth``, ``depth`` float32 (B, H, W): the expected z-depth in metres of the Gaussians
    outside the ``sky`` dome, +inf where their opacity is below 0.5 (None without ``depth``).
    """
    import torch

    from paradrive.devices import resolve_backend, resolve_device
    from paradrive.gs.model import render_gaussians, sh_degree_of

    dev = resolve_device(device)
    backend = resolve_backend(backend, dev)
    p = {k: v.to(dev) for k, v in params.items()}
    deg = sh_degree_of(p)
    solid = None
    if depth and sky is not None:
        centre = torch.as_tensor(sky.centre, dtype=torch.float32, device=dev)
        keep = (p["means"] - centre).norm(dim=1) <= sky.radius
        solid = {k: v[keep] for k, v in p.items()}
    c2w = geometry.as_pose(c2w).reshape(-1, 4, 4)
    viewmats = torch.from_numpy(geometry.invert(c2w)).float().to(dev)
    Kt = torch.as_tensor(np.asarray(K), dtype=torch.float32).to(dev)
    step = max(1, int(batch_frames))
    with torch.no_grad():
        for start in range(0, len(viewmats), step):
            vm = viewmats[start:start + step]
            Ks = Kt.expand(len(vm), 3, 3).contiguous()
            one_pass = depth and solid is None
            out, alpha, _ = render_gaussians(p, vm, Ks, int(width), int(height), sh_degree=deg,
                                   render_mode="RGB+ED" if one_pass else "RGB", backend=backend)
            rgb = (out[..., :3].clamp(0, 1) * 255.0).round().to(torch.uint8).cpu().numpy()
            z = None
            if one_pass:
                z, z_alpha = out[..., 3], alpha[..., 0]
            elif depth and solid is not None:
                ed, z_alpha, _ = render_gaussians(solid, vm, Ks, int(width), int(height), sh_degree=deg,
                                        render_mode="ED", backend=backend)
                z, z_alpha = ed[..., 0], z_alpha[..., 0]
            if z is not None:
                z = torch.where(z_alpha >= 0.5, z, torch.full_like(z, float("inf")))
                z = z.float().cpu().numpy()
            yield {"rgb": rgb, "alpha": alpha[..., 0].clamp(0, 1).float().cpu().numpy(), "depth": z}
