"""The fit's loss past the render as one autograd node in the native kernels: L1 and SSIM on RGB,
the sky term and the LiDAR inverse-depth term on the expected depth (``_Fit._loss``'s
expression), with the gradient of the render and its alpha in closed form.

The torch expression is some eighty small operations and their backward a fit iteration; the
node's gradient matches it within float32 rounding (tests/test_native_kernels.py states the
tolerance). The loss value is summed in double (it is only shown in the progress lines).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from paradrive.devices import cpu_kernel_threads
from paradrive import kernels
from paradrive.gs.losses import DepthTarget, depth_loss
from paradrive import metrics
from paradrive.metrics import ssim

__all__ = ["FitLossTerms", "fit_loss", "fit_loss_kernels", "fit_loss_torch"]

_f32 = np.float32


@cache
def _ssim_window() -> tuple[np.ndarray, float, float]:
    """metrics.ssim's default window (the fit's): taps as an array, C1 and C2."""
    taps, c1, c2 = metrics.ssim_window()
    return taps.numpy(), c1, c2


@dataclass(frozen=True)
class FitLossTerms:
    """The loss's weights: ssim_lambda (SSIM against L1), the sky term's weight and scale (half
    the sky radius, m) and the LiDAR depth term's weight (inverse depth)."""

    ssim_lambda: float
    sky_weight: float
    sky_scale: float
    depth_weight: float


def fit_loss_kernels(render: Tensor) -> kernels.Kernels | None:
    """The native kernels where the node takes this render: where metrics.ssim runs natively
    (float32 on the CPU, the library built), as the node computes its SSIM term there; else
    None, and the torch expression runs."""
    return metrics._native_kernels(render)


class _FitLoss(torch.autograd.Function):
    """Inputs: render (1, H, W, D) (RGB, and when D is 4 the accumulated depth), alphas
    (1, H, W, 1), gt (H, W, 3), sky (H, W) bool or None, target (LiDAR pixels and their inverse
    depths) or None, terms, kernels. Output: the loss, a float32 scalar."""

    @staticmethod
    def forward(ctx, render, alphas, gt, sky, target, terms: FitLossTerms, kernels):
        _, H, W, D = render.shape
        P = H * W
        r = render.detach().contiguous().numpy().reshape(P, D)
        a = alphas.detach().contiguous().numpy().reshape(P)
        g = gt.detach().to(torch.float32).contiguous().numpy().reshape(P, 3)
        rgb = np.ascontiguousarray(r[:, :3]).reshape(1, H, W, 3)
        taps, c1, c2 = _ssim_window()
        mean, d = kernels.ssim_forward(rgb, g.reshape(1, H, W, 3), taps, c1, c2, True,
                                       cpu_kernel_threads())
        sky_np = None if sky is None else sky.contiguous().numpy().reshape(P)
        pixels, target_inv = target if target is not None else (_NO_PIXELS, _NO_DEPTHS)
        sums = kernels.fit_loss_terms(r, a, g, sky_np, terms.sky_scale, pixels, target_inv)
        lam = terms.ssim_lambda
        loss = (1.0 - lam) * sums[0] / (3 * P) + lam * (1.0 - float(mean[0]))
        n_sky = int(sky_np.sum()) if sky_np is not None else 0
        if sky_np is not None:
            loss += terms.sky_weight * sums[1] / n_sky
        if target is not None:
            loss += terms.depth_weight * sums[2] / pixels.shape[0]
        ctx.saved = (r, a, g, rgb, d, taps, sky_np, n_sky, pixels, target_inv, terms, kernels)
        ctx.shape = render.shape
        return torch.tensor(loss, dtype=torch.float32, device="cpu")

    @staticmethod
    def backward(ctx, grad):
        r, a, g, rgb, d, taps, sky_np, n_sky, pixels, target_inv, terms, kernels = ctx.saved
        P, D = r.shape
        g0 = grad.item()
        # each mean's gradient: the incoming one times its weight over the element count
        c_l1 = g0 * (1.0 - terms.ssim_lambda) / (3 * P)
        scale = np.array([-g0 * terms.ssim_lambda], dtype=_f32)
        g_ssim = kernels.ssim_backward(rgb, g.reshape(rgb.shape), d, taps, scale,
                                       cpu_kernel_threads())
        g_sky = g0 * terms.sky_weight / n_sky if n_sky else 0.0
        g_depth = g0 * terms.depth_weight / pixels.shape[0] if target_inv.shape[0] else 0.0
        d_render, d_alpha = kernels.fit_loss_backward(
            r, a, g, g_ssim.reshape(P, 3), c_l1, sky_np, g_sky, terms.sky_scale, pixels,
            target_inv, g_depth)
        d_render_t = torch.from_numpy(d_render).reshape(ctx.shape)
        d_alpha_t = (torch.from_numpy(d_alpha).reshape(*ctx.shape[:3], 1) if D == 4 else None)
        return d_render_t, d_alpha_t, None, None, None, None, None


_NO_PIXELS = np.zeros(0, np.int64)
_NO_DEPTHS = np.zeros(0, np.float32)


def fit_loss(render: Tensor, alphas: Tensor, gt: Tensor, sky: Tensor | None,
             target: DepthTarget | None, terms: FitLossTerms,
             kernels: kernels.Kernels) -> Tensor:
    """The fit's loss (see ``_Fit._loss``) of a render (1, H, W, D) with the accumulated depth
    as its 4th channel when there is a sky or depth term, its alphas (1, H, W, 1) and the
    target image gt (H, W, 3); sky (H, W) bool selects the sky term's pixels (None or none
    selected: no sky term). The torch expression's value and gradient to float32 rounding."""
    if sky is not None and not bool(sky.any()):
        sky = None
    if (sky is not None or target is not None) and render.shape[-1] != 4:
        raise ValueError("the sky and depth terms need the render's accumulated depth channel")
    packed = None
    if target is not None:
        packed = (target.pixels.to(torch.int64).contiguous().numpy(),
                  (1.0 / target.depth).to(torch.float32).contiguous().numpy())
    return _FitLoss.apply(render, alphas, gt, sky, packed, terms, kernels)


def fit_loss_torch(out: Tensor, gt: Tensor, sky: Tensor | None, target: DepthTarget | None,
                   terms: FitLossTerms, inverse: bool = True,
                   masked: Tensor | None = None) -> Tensor:
    """The same loss as torch operations, on any device: out (1, H, W, D) the render with the
    expected depth (not the accumulated one) as its 4th channel when there is a sky or depth
    term; ``inverse`` False takes the depth term in metres; ``masked`` (H, W) bool pixels (moving
    actors without a node, a video's ego and moving masks) cost nothing."""
    pred = out[0, ..., :3]
    if masked is not None:  # zero on both sides: no pull, and SSIM windows across the edge see
        # the same whatever was recorded there
        blank = torch.zeros((), dtype=pred.dtype, device=pred.device)
        pred = torch.where(masked[..., None], blank, pred)
        gt = torch.where(masked[..., None], blank.to(gt.dtype), gt)
    lam = terms.ssim_lambda
    loss = (1.0 - lam) * (pred - gt).abs().mean() + lam * (1.0 - ssim(pred, gt))
    if sky is not None and sky.any():
        depth = out[0, ..., 3][sky]
        loss = loss + terms.sky_weight * F.relu(1.0 - depth / terms.sky_scale).mean()
    if target is not None:
        loss = loss + terms.depth_weight * depth_loss(out[0, ..., 3], target, inverse)
    return loss
