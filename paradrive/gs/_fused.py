"""Torch side of the fused CPU rasterizer: tile binning and a compositing autograd function whose
work runs in the vectorised kernels of ``_composite.cpp`` (built by ``_native``; the Numba kernels
of ``_cpu_kernels`` where no compiler is found), on ``torch.get_num_threads()`` threads.

Same interface as ``_tiles.bin_gaussians`` / ``_tiles.composite``, so the two compositors are
interchangeable behind ``rasterize``.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import torch
from torch import Tensor

from paradrive.gs import _cpu_kernels as K
from paradrive.gs import _cpu_project as P
from paradrive.gs import _cpu_sh as S
from paradrive.gs import _native
from paradrive.gs._tiles import TileBins, composite
from paradrive.gs.sh import shade

__all__ = ["bin_gaussians_fused", "composite_fused", "project_fused", "shade_fused"]


@contextmanager
def _kernel_threads() -> Iterator[None]:
    """Run Numba on torch's thread count and give torch its count back afterwards: Numba's
    OpenMP layer shares torch's OpenMP runtime and resets its thread count when it starts."""
    n = torch.get_num_threads()
    K.set_threads(n)
    try:
        yield
    finally:
        if torch.get_num_threads() != n:
            torch.set_num_threads(n)


def _f32(t: Tensor) -> np.ndarray:
    return t.detach().to(torch.float32).contiguous().numpy()


@torch.no_grad()
def bin_gaussians_fused(means2d: Tensor, radii_xy: Tensor, depths: Tensor, width: int,
                        height: int, tile_size: int) -> TileBins:
    """Per-tile depth-sorted lists, as ``_tiles.bin_gaussians`` builds them.

    means2d: (C, N, 2) pixels; radii_xy: (C, N, 2) int box half-sizes (0 = not visible);
    depths: (C, N). Ties in depth keep the lower flat id first (a stable sort).
    """
    C, N = depths.shape
    tiles_x, tiles_y = math.ceil(width / tile_size), math.ceil(height / tile_size)
    visible = torch.nonzero((radii_xy > 0).all(dim=-1).reshape(-1)).squeeze(1)
    order = visible[torch.sort(depths.detach().reshape(-1)[visible], stable=True).indices]
    m, r = _f32(means2d.reshape(-1, 2)), _f32(radii_xy.reshape(-1, 2))
    ids, offsets, counts = K.bin_lists(order.numpy(), m, r, max(N, 1), tile_size, tiles_x,
                                       tiles_y, C * tiles_x * tiles_y)
    return TileBins(C, width, height, tile_size, tiles_x, tiles_y, torch.from_numpy(ids),
                    torch.from_numpy(offsets), torch.from_numpy(counts))


def _gather(means2d: Tensor, conics: Tensor, opacities: Tensor, colors: Tensor,
            bins: TileBins) -> np.ndarray:
    """(n_isects, 6 + D) rows in tile list order; see ``_cpu_kernels``."""
    table = torch.cat([means2d, conics, opacities[:, None], colors], dim=1).detach()
    return table.to(torch.float32)[bins.flat_ids].numpy()


class FusedComposite(torch.autograd.Function):
    """``_tiles.Composite`` with the per-pixel work in the native (or Numba) kernels.

    Inputs: means2d (C*N, 2), conics (C*N, 3), opacities (C*N,), colors (C*N, D),
    backgrounds (C, D); bins: TileBins. Outputs: renders (C, H, W, D), alphas (C, H, W, 1).
    """

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, backgrounds, bins: TileBins):
        C, H, W, D = bins.n_cameras, bins.height, bins.width, colors.shape[-1]
        gauss = _gather(means2d, conics, opacities, colors, bins)
        bg = _f32(backgrounds)
        render = np.empty((C, H, W, D), dtype=np.float32)
        trans = np.empty((C, H, W), dtype=np.float32)
        last = np.empty((C, H, W), dtype=np.int64)
        args = (gauss, bins.offsets.numpy(), bins.counts.numpy(), bins.tile_size, bins.tiles_x,
                bins.tiles_y, bg, render, trans, last)
        native = _native.load()
        if native is not None:
            native.composite_forward(*args, torch.get_num_threads())
        else:
            with _kernel_threads():
                K.composite_forward(*args)
        ctx.bins, ctx.arrays, ctx.n_flat = bins, (gauss, bg, trans, last), means2d.shape[0]
        ctx.native = native
        ctx.save_for_backward(backgrounds)
        dtype = means2d.dtype
        renders = torch.from_numpy(render).to(dtype)
        alphas = (1.0 - torch.from_numpy(trans)[..., None]).to(dtype)
        return renders, alphas

    @staticmethod
    def backward(ctx, grad_renders, grad_alphas):
        (backgrounds,) = ctx.saved_tensors
        bins = ctx.bins
        gauss, bg, trans, last = ctx.arrays
        args = (gauss, bins.offsets.numpy(), bins.tile_size, bins.tiles_x, bins.tiles_y, bg, trans,
                last, _f32(grad_renders), _f32(grad_alphas[..., 0]))
        if ctx.native is not None:  # the backward of the kernels that ran the forward
            per_isect = ctx.native.composite_backward(*args, torch.get_num_threads())
        else:
            with _kernel_threads():
                per_isect = K.composite_backward(*args)
        dtype = grad_renders.dtype
        total = torch.from_numpy(K.sum_by_gaussian(per_isect, bins.flat_ids.numpy(),
                                                   ctx.n_flat)).to(dtype)
        g_bg = None
        if ctx.needs_input_grad[4]:
            g_bg = (grad_renders * torch.from_numpy(trans)[..., None].to(dtype)).sum(dim=(1, 2))
        return total[:, 0:2], total[:, 2:5], total[:, 5], total[:, 6:], g_bg, None


def composite_fused(means2d: Tensor, conics: Tensor, opacities: Tensor, colors: Tensor,
                    backgrounds: Tensor, bins: TileBins) -> tuple[Tensor, Tensor]:
    """Differentiable compositing; see FusedComposite. Returns (renders, alphas). Features wider
    than the kernels' ``MAX_CHANNELS`` (RGB and depth) take the torch-op compositor."""
    if colors.shape[-1] > K.MAX_CHANNELS:
        return composite(means2d, conics, opacities, colors, backgrounds, bins)
    return FusedComposite.apply(means2d, conics, opacities, colors, backgrounds, bins)


class FusedProjection(torch.autograd.Function):
    """``rasterize._project`` in Numba kernels; viewmats and Ks get no gradient.

    Inputs: means (N, 3), quats (N, 4), scales (N, 3), opacities (N,), viewmats (C, 4, 4),
    Ks (C, 3, 3) and the camera settings. Outputs: means2d (C, N, 2), conics (C, N, 3),
    depths (C, N) and radii_xy (C, N, 2) int32 (not differentiable).
    """

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmats, Ks, settings: tuple):
        C, N = viewmats.shape[0], means.shape[0]
        dtype = means.dtype
        means2d = np.empty((C, N, 2), dtype=np.float32)
        conics = np.empty((C, N, 3), dtype=np.float32)
        depths = np.empty((C, N, 1), dtype=np.float32)
        radii = np.empty((C, N, 2), dtype=np.int32)
        arrays = (_f32(means), _f32(quats), _f32(scales), _f32(opacities), _f32(viewmats),
                  _f32(Ks))
        with _kernel_threads():
            P.project_forward(*arrays, *settings, means2d, conics, depths, radii)
        ctx.arrays, ctx.settings, ctx.dtype = arrays, settings, dtype
        ctx.mark_non_differentiable(radii_t := torch.from_numpy(radii))
        return (torch.from_numpy(means2d).to(dtype), torch.from_numpy(conics).to(dtype),
                torch.from_numpy(depths[..., 0]).to(dtype), radii_t)

    @staticmethod
    def backward(ctx, v_means2d, v_conics, v_depths, _v_radii):
        means, quats, scales, _, viewmats, Ks = ctx.arrays
        width, height, near, far, eps2d, _ = ctx.settings
        with _kernel_threads():
            grads = P.project_backward(means, quats, scales, viewmats, Ks, width, height, near, far,
                                       eps2d, _f32(v_means2d), _f32(v_conics),
                                       _f32(v_depths[..., None]))
        v_means, v_quats, v_scales = (torch.from_numpy(g).to(ctx.dtype) for g in grads)
        return v_means, v_quats, v_scales, None, None, None, None


def project_fused(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor,
                  viewmats: Tensor, Ks: Tensor, width: int, height: int, near_plane: float,
                  far_plane: float, eps2d: float, radius_clip: float
                  ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Same arguments and outputs as ``rasterize._project``; see FusedProjection."""
    settings = (width, height, float(near_plane), float(far_plane), float(eps2d), float(radius_clip))
    return FusedProjection.apply(means, quats, scales, opacities, viewmats, Ks, settings)


class FusedSH(torch.autograd.Function):
    """``sh.shade`` in Numba kernels: means (N, 3), coeffs (N, K, 3), campos (C, 3) and
    visible (C, N) bool (no gradient) -> colours (C, N, 3), 0 where a Gaussian is not visible."""

    @staticmethod
    def forward(ctx, means, coeffs, campos, visible, degree: int):
        colors = np.empty((campos.shape[0], means.shape[0], 3), dtype=np.float32)
        arrays = (_f32(means), _f32(coeffs), _f32(campos))
        with _kernel_threads():
            S.sh_forward(degree, *arrays, visible.contiguous().numpy(), colors)
        ctx.arrays, ctx.colors, ctx.degree, ctx.dtype = arrays, colors, degree, means.dtype
        return torch.from_numpy(colors).to(means.dtype)

    @staticmethod
    def backward(ctx, v_colors):
        with _kernel_threads():
            v_means, v_coeffs = S.sh_backward(ctx.degree, *ctx.arrays, ctx.colors, _f32(v_colors))
        return (torch.from_numpy(v_means).to(ctx.dtype), torch.from_numpy(v_coeffs).to(ctx.dtype),
                None, None, None)


def shade_fused(sh_degree: int, means: Tensor, coeffs: Tensor, campos: Tensor,
                visible: Tensor | None = None) -> Tensor:
    """``sh.shade`` for the Gaussians ``visible`` (C, N) marks (default: all); the others get
    colour 0. Per-camera coefficients (C, N, K, 3) take the torch path, which colours all."""
    if coeffs.dim() != 3:
        return shade(sh_degree, means, coeffs, campos)
    _check_sh(sh_degree, coeffs)
    if visible is None:
        visible = torch.ones(campos.shape[0], means.shape[0], dtype=torch.bool, device="cpu")
    return FusedSH.apply(means, coeffs, campos.detach(), visible.detach().to("cpu"), sh_degree)


def _check_sh(degree: int, coeffs: Tensor) -> None:
    """The errors eval_sh gives, before the kernel indexes past the coefficients."""
    if not 0 <= degree <= 3:
        raise ValueError(f"sh_degree={degree} is not supported; use 0..3")
    if coeffs.shape[-2] < (degree + 1) ** 2:
        raise ValueError(f"sh_degree={degree} needs {(degree + 1) ** 2} coefficients per Gaussian, "
                         f"got colors of shape {tuple(coeffs.shape)}")
