"""Geometry terms of the fit, beside its photometric loss: they make the fitted depth match the
world, which is what the shifted renders' parallax rests on.

* LiDAR depth supervision (DriveStudio's default on Waymo): the LiDAR sweep of a frame is
  projected into each training view of that frame (the nearest return per pixel) and the
  rendered expected depth is pulled towards it, L1 on metric or inverse depth.
* Flattening (PGSR, NeuSG, the 2DGS idea in a 3DGS): the smallest axis of each Gaussian is
  penalised, so surfaces become thin discs instead of thick shells whose front half, seen at a
  grazing angle (the road), pulls the composited depth towards the camera.
* Sharp-shape regulariser (PhysGaussian, DriveStudio's ``sharp_shape_reg``): the ratio of the
  largest to the smallest axis is penalised above a threshold, against needles that streak in
  shifted views.

Every function takes tensors on the fit's device and creates nothing on another.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .init import View, project

__all__ = ["DepthTarget", "lidar_depth_target", "depth_loss", "flatten_loss", "shape_ratio_loss"]


@dataclass
class DepthTarget:
    """Sparse depth of one view: ``pixels`` (K,) long flat indices y * W + x into the view's
    image, ``depth`` (K,) float32 camera z-depth (m) there."""

    pixels: torch.Tensor
    depth: torch.Tensor

    def to(self, device: torch.device) -> DepthTarget:
        return DepthTarget(self.pixels.to(device), self.depth.to(device))


def lidar_depth_target(points: np.ndarray, view: View, min_depth: float = 0.5) -> DepthTarget:
    """Project world LiDAR points (M, 3) into ``view``; the nearest point per pixel wins (a
    z-buffer, so returns hidden from the camera behind a nearer return do not count).
    Sky pixels (where the view has a sky mask) and points nearer than ``min_depth`` are dropped.
    Returns CPU tensors; move them with :meth:`DepthTarget.to`.
    """
    pts = torch.from_numpy(np.ascontiguousarray(points, dtype=np.float32))
    uv, z, ok = project(pts, view)
    ok &= z > min_depth
    x = uv[ok, 0].long().clamp(0, view.width - 1)
    y = uv[ok, 1].long().clamp(0, view.height - 1)
    flat = y * view.width + x
    zbuf = torch.full((view.height * view.width,), float("inf"))
    zbuf.scatter_reduce_(0, flat, z[ok], reduce="amin")
    if view.sky is not None:
        zbuf[view.sky.reshape(-1)] = float("inf")
    pixels = torch.nonzero(torch.isfinite(zbuf)).squeeze(1)
    return DepthTarget(pixels=pixels, depth=zbuf[pixels].float())


def depth_loss(depth: torch.Tensor, target: DepthTarget, inverse: bool) -> torch.Tensor:
    """Mean L1 between a rendered expected depth (H, W) and a sparse target on its pixels;
    on inverse depth (1/m) when ``inverse``, else in metres (DriveStudio's default)."""
    pred = depth.reshape(-1)[target.pixels]
    if inverse:
        return (1.0 / pred.clamp_min(1e-3) - 1.0 / target.depth).abs().mean()
    return (pred - target.depth).abs().mean()


def flatten_loss(log_scales: torch.Tensor, keep: torch.Tensor | None = None) -> torch.Tensor:
    """Mean of the smallest standard deviation (m) of the Gaussians; log_scales (N, 3) raw
    parameters, keep (N,) bool selects the ones it applies to (e.g. not the sky dome)."""
    s = log_scales if keep is None else log_scales[keep]
    if s.shape[0] == 0:
        return log_scales.sum() * 0.0
    return torch.exp(s.amin(dim=-1)).mean()


def shape_ratio_loss(log_scales: torch.Tensor, max_ratio: float,
                     keep: torch.Tensor | None = None) -> torch.Tensor:
    """Mean of max(largest / smallest axis, ``max_ratio``) - ``max_ratio`` (PhysGaussian's
    anisotropy term); log_scales (N, 3) raw, keep (N,) bool as in :func:`flatten_loss`."""
    s = log_scales if keep is None else log_scales[keep]
    if s.shape[0] == 0:
        return log_scales.sum() * 0.0
    ratio = torch.exp(s.amax(dim=-1) - s.amin(dim=-1))
    return (ratio.clamp_min(float(max_ratio)) - float(max_ratio)).mean()
