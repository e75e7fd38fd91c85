"""Views of a fitted checkpoint: load a 3DGS PLY, render it from many cameras in batches (RGB,
alpha and depth with the sky dome left out).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from paradrive import geometry
from paradrive.gs.ply import load_checkpoint

if TYPE_CHECKING:
    from paradrive.contracts.records import FitInit

__all__ = ["SkyDome", "sky_dome_of", "render_views", "load_checkpoint"]


# --------------------------------------------------------------------------- rendering

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


def render_views(model, c2w: np.ndarray, K: np.ndarray, width: int, height: int, *,
                 frames: Sequence[int] | None = None, depth: bool = False, batch_frames: int = 8,
                 sky: SkyDome | None = None, device: str = "auto",
                 backend: str = "auto") -> Iterator[dict]:
    """Render a checkpoint from cameras ``c2w`` (N, 4, 4) (camera-to-world, OpenCV), all with
    intrinsics ``K`` (3, 3) at ``width x height``.

    model: Gaussian parameters, or a :class:`paradrive.gs.graph.FittedModel`; a scene graph's
    actors are placed at ``frames`` (N,) (scene frame positions, one per camera), and the cameras
    of one frame share a rasterizer pass. A static model renders ``batch_frames`` cameras per pass.

    Yields one dict per pass: ``rgb`` uint8 (B, H, W, 3), ``alpha`` float32 (B, H, W) and, with
    ``depth``, ``depth`` float32 (B, H, W): the expected z-depth in metres of the Gaussians
    outside the ``sky`` dome, +inf where their opacity is below 0.5 (None without ``depth``).
    """
    import torch

    from paradrive.devices import resolve_backend, resolve_device
    from paradrive.gs.graph import FittedModel

    dev = resolve_device(device)
    backend = resolve_backend(backend, dev)
    fitted = (model if isinstance(model, FittedModel) else FittedModel(dict(model))).to(dev)
    c2w = geometry.as_pose(c2w).reshape(-1, 4, 4)
    if fitted.dynamic and (frames is None or len(frames) != len(c2w)):
        raise ValueError("a scene-graph checkpoint renders at frames: pass one frame per camera")
    viewmats = torch.from_numpy(geometry.invert(c2w)).float().to(dev)
    Kt = torch.as_tensor(np.asarray(K), dtype=torch.float32).to(dev)
    centre = None if sky is None else torch.as_tensor(sky.centre, dtype=torch.float32, device=dev)
    placed: tuple | None = None   # (frame, Gaussians, their solid part): a static model's once
    with torch.no_grad():
        for batch in _passes(len(viewmats), frames if fitted.dynamic else None, batch_frames):
            frame = frames[batch.start] if fitted.dynamic and frames is not None else None
            if placed is None or placed[0] != frame:
                p = fitted.at(frame)
                solid = None
                if depth and centre is not None and sky is not None:
                    keep = (p["means"] - centre).norm(dim=1) <= sky.radius
                    solid = {k: v[keep] for k, v in p.items()}
                placed = (frame, p, solid)
            Ks = Kt.expand(batch.stop - batch.start, 3, 3).contiguous()
            yield _render_pass(placed[1], placed[2], viewmats[batch], Ks, int(width), int(height), depth,
                               backend)


def _passes(n: int, frames: Sequence[int] | None, batch_frames: int) -> Iterator[slice]:
    """Consecutive cameras rendered together: ``batch_frames`` at a time, never two frames of a
    scene graph in one pass."""
    step = max(1, int(batch_frames))
    start = 0
    while start < n:
        stop = min(start + step, n)
        if frames is not None:
            stop = start + 1
            while stop < min(start + step, n) and frames[stop] == frames[start]:
                stop += 1
        yield slice(start, stop)
        start = stop


def _render_pass(p, solid, vm, Ks, width: int, height: int, depth: bool, backend: str) -> dict:
    """One rasterizer pass of Gaussians ``p`` (and, for depth without the sky, ``solid``)."""
    import torch

    from paradrive.gs.model import render_gaussians, sh_degree_of

    deg = sh_degree_of(p)
    one_pass = depth and solid is None
    out, alpha, _ = render_gaussians(p, vm, Ks, width, height, sh_degree=deg,
                                     render_mode="RGB+ED" if one_pass else "RGB", backend=backend)
    rgb = (out[..., :3].clamp(0, 1) * 255.0).round().to(torch.uint8).cpu().numpy()
    z = None
    if one_pass:
        z, z_alpha = out[..., 3], alpha[..., 0]
    elif depth and solid is not None:
        ed, z_alpha, _ = render_gaussians(solid, vm, Ks, width, height, sh_degree=deg,
                                          render_mode="ED", backend=backend)
        z, z_alpha = ed[..., 0], z_alpha[..., 0]
    if z is not None:
        z = torch.where(z_alpha >= 0.5, z, torch.full_like(z, float("inf")))
        z = z.float().cpu().numpy()
    return {"rgb": rgb, "alpha": alpha[..., 0].clamp(0, 1).float().cpu().numpy(), "depth": z}
