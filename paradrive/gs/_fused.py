"""Torch side of the fused CPU rasterizer: autograd functions whose work runs in the vectorised
kernels of ``_composite.cpp`` (built at install, loaded by ``paradrive.kernels``), on
``devices.cpu_kernel_threads()`` threads (torch's count unless set). ``rasterize`` takes them
only where ``kernels.load()`` finds the kernels; elsewhere the torch-op stages run.

Same interface as ``_tiles.bin_gaussians`` / ``_tiles.composite`` and ``rasterize._project``,
so the stages are interchangeable behind ``rasterize``.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from paradrive.devices import cpu_kernel_threads
from paradrive import kernels
from paradrive.gs._tiles import TileBins, composite
from paradrive.gs.sh import shade

__all__ = ["bin_gaussians_fused", "composite_fused", "project_fused", "rasterize_fit",
           "shade_fused"]


# The compositing kernels carry up to this many channels (RGB and depth).
MAX_CHANNELS = 4


def _kernels() -> kernels.Kernels:
    native = kernels.load()
    if native is None:
        raise RuntimeError("the fused CPU stages need the native kernels (rasterize checks "
                           "kernels.load() first)")
    return native


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
    lists = _kernels().bin_lists(_f32(depths.reshape(-1)), _f32(means2d.reshape(-1, 2)),
                                 _f32(radii_xy.reshape(-1, 2)), max(N, 1), tile_size, tiles_x,
                                 tiles_y, C * tiles_x * tiles_y)
    return TileBins(C, width, height, tile_size, tiles_x, tiles_y,
                    *(torch.from_numpy(a) for a in lists))


def _table(means2d: Tensor, conics: Tensor, opacities: Tensor, colors: Tensor) -> np.ndarray:
    """(C*N, 6 + D) float32 rows per Gaussian: mean (2), conic (3), opacity, features (D)."""
    table = torch.cat([means2d, conics, opacities[:, None], colors], dim=1).detach()
    return table.to(torch.float32).contiguous().numpy()


class FusedComposite(torch.autograd.Function):
    """``_tiles.Composite`` with the per-pixel work in the native kernels.

    Inputs: means2d (C*N, 2), conics (C*N, 3), opacities (C*N,), colors (C*N, D),
    backgrounds (C, D); bins: TileBins. Outputs: renders (C, H, W, D), alphas (C, H, W, 1).
    """

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, backgrounds, bins: TileBins):
        C, H, W, D = bins.n_cameras, bins.height, bins.width, colors.shape[-1]
        table = _table(means2d, conics, opacities, colors)
        ids = bins.flat_ids.numpy()
        bg = _f32(backgrounds)
        render = np.empty((C, H, W, D), dtype=np.float32)
        trans = np.empty((C, H, W), dtype=np.float32)
        last = np.empty((C, H, W), dtype=np.int64)
        tail = (bins.offsets.numpy(), bins.counts.numpy(), bins.tile_size, bins.tiles_x,
                bins.tiles_y, bg, render, trans, last)
        native = _kernels()
        reach = np.empty((table.shape[0], 2), dtype=np.float32)  # each row's ellipse, for the backward
        native.composite_forward(table, ids, *tail, reach, cpu_kernel_threads())
        ctx.bins, ctx.arrays, ctx.n_flat = bins, (table, bg, trans, last), means2d.shape[0]
        ctx.native, ctx.reach = native, reach
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
        ids, threads = bins.flat_ids.numpy(), cpu_kernel_threads()
        tail = (bins.offsets.numpy(), bins.tile_size, bins.tiles_x, bins.tiles_y, bg, trans, last,
                _f32(grad_renders), _f32(grad_alphas[..., 0]))
        per_isect = ctx.native.composite_backward(gauss, ids, tail[0], bins.counts.numpy(),
                                                  *tail[1:], ctx.reach, threads)
        summed = ctx.native.sum_by_gaussian(per_isect, ids, ctx.n_flat, threads)
        dtype = grad_renders.dtype
        total = torch.from_numpy(summed).to(dtype)
        g_bg = None
        if ctx.needs_input_grad[4]:
            g_bg = (grad_renders * torch.from_numpy(trans)[..., None].to(dtype)).sum(dim=(1, 2))
        return total[:, 0:2], total[:, 2:5], total[:, 5], total[:, 6:], g_bg, None


def composite_fused(means2d: Tensor, conics: Tensor, opacities: Tensor, colors: Tensor,
                    backgrounds: Tensor, bins: TileBins) -> tuple[Tensor, Tensor]:
    """Differentiable compositing; see FusedComposite. Returns (renders, alphas). Features wider
    than the kernels' ``MAX_CHANNELS`` (RGB and depth) take the torch-op compositor."""
    if colors.shape[-1] > MAX_CHANNELS:
        return composite(means2d, conics, opacities, colors, backgrounds, bins)
    return FusedComposite.apply(means2d, conics, opacities, colors, backgrounds, bins)


class FusedProjection(torch.autograd.Function):
    """``rasterize._project`` in the native kernels; viewmats and Ks get no gradient.

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
        native = _kernels()
        native.project_forward(*arrays, *settings, means2d, conics, depths, radii, None, -1,
                               cpu_kernel_threads())
        ctx.arrays, ctx.settings, ctx.dtype, ctx.native = arrays, settings, dtype, native
        ctx.mark_non_differentiable(radii_t := torch.from_numpy(radii))
        return (torch.from_numpy(means2d).to(dtype), torch.from_numpy(conics).to(dtype),
                torch.from_numpy(depths[..., 0]).to(dtype), radii_t)

    @staticmethod
    def backward(ctx, v_means2d, v_conics, v_depths, _v_radii):
        means, quats, scales, _, viewmats, Ks = ctx.arrays
        width, height, near, far, eps2d, _ = ctx.settings
        args = (means, quats, scales, viewmats, Ks, width, height, near, far, eps2d,
                _f32(v_means2d), _f32(v_conics), _f32(v_depths[..., None]))
        grads = ctx.native.project_backward(*args, cpu_kernel_threads())
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
    """``sh.shade`` in the native kernels: means (N, 3),
    the coefficients in two parts c0 (N, 1, 3) and cN (N, K - 1, 3), campos (C, 3) and visible
    (C, N) bool (no gradient) -> colours (C, N, 3), 0 where a Gaussian is not visible."""

    @staticmethod
    def forward(ctx, means, c0, cN, campos, visible, degree: int):
        colors = np.empty((campos.shape[0], means.shape[0], 3), dtype=np.float32)
        arrays = (_f32(means), _f32(c0), _f32(cN), _f32(campos))
        native = _kernels()
        native.sh_forward(degree, *arrays, visible.contiguous().numpy(), colors, cpu_kernel_threads())
        ctx.arrays, ctx.colors, ctx.degree, ctx.dtype = arrays, colors, degree, means.dtype
        ctx.native = native
        return torch.from_numpy(colors).to(means.dtype)

    @staticmethod
    def backward(ctx, v_colors):
        means, c0, cN, _ = ctx.arrays
        # the kernel fills every row
        out = (np.empty(means.shape, np.float32), np.empty(c0.shape, np.float32),
               np.empty(cN.shape, np.float32))
        ctx.native.sh_backward(ctx.degree, *ctx.arrays, ctx.colors, _f32(v_colors), *out,
                               cpu_kernel_threads())
        v_means, v_c0, v_cN = (torch.from_numpy(g).to(ctx.dtype) for g in out)
        return v_means, v_c0, v_cN, None, None, None


SHCoefficients = Tensor | tuple[Tensor, Tensor]


def shade_fused(sh_degree: int, means: Tensor, coeffs: SHCoefficients, campos: Tensor,
                visible: Tensor | None = None) -> Tensor:
    """``sh.shade`` for the Gaussians ``visible`` (C, N) marks (default: all); the others get
    colour 0. ``coeffs`` (N, K, 3), or its two parts (sh0 (N, 1, 3), shN (N, K - 1, 3)) as the
    fit keeps them, read in place (no concatenated copy). Per-camera coefficients
    (C, N, K, 3) take the torch path, which colours all."""
    if isinstance(coeffs, tuple):
        c0, cN = coeffs
    elif coeffs.dim() != 3:
        return shade(sh_degree, means, coeffs, campos)
    else:
        c0, cN = coeffs[:, :1], coeffs[:, 1:]
    _check_sh(sh_degree, c0.shape[0], 1 + cN.shape[1])
    if visible is None:
        visible = torch.ones(campos.shape[0], means.shape[0], dtype=torch.bool, device="cpu")
    return FusedSH.apply(means, c0, cN, campos.detach(), visible.detach().to("cpu"), sh_degree)


def _check_sh(degree: int, n: int, k: int) -> None:
    """The errors eval_sh gives, before the kernel indexes past the coefficients."""
    if not 0 <= degree <= 3:
        raise ValueError(f"sh_degree={degree} is not supported; use 0..3")
    if k < (degree + 1) ** 2:
        raise ValueError(f"sh_degree={degree} needs {(degree + 1) ** 2} coefficients per Gaussian, "
                         f"got colors of shape {(n, k, 3)}")


class FusedRasterize(torch.autograd.Function):
    """The fit's case (SH colours in the fit's two parts, RGB with or without a depth channel)
    as one autograd node: projection, SH colour, binning and compositing forward, and their
    backward, in the native kernels with no torch operations between them.

    Inputs: means (N, 3), quats (N, 4), scales (N, 3), opacities (N,), c0 (N, 1, 3),
    cN (N, K - 1, 3), viewmats (C, 4, 4), Ks (C, 3, 3), backgrounds (C, 3) or None (no
    gradient), settings, and ``screen`` (C, N, 2) float32: gets the projected means, and from the
    backward their gradient as its ``grad`` (what densification reads).
    Outputs: renders (C, H, W, 3 or 4: the 4th the accumulated depth), alphas (C, H, W, 1),
    conics (C, N, 3), depths (C, N), radii_xy (C, N, 2) int32 and the number of list entries;
    only the first two are differentiable.
    """

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, c0, cN, viewmats, Ks, backgrounds,
                settings: tuple, screen: Tensor):
        native = _kernels()
        width, height, near, far, eps2d, radius_clip, degree, with_depth, ts = settings
        C, N, threads = viewmats.shape[0], means.shape[0], cpu_kernel_threads()
        arrays = [_f32(t) for t in (means, quats, scales, opacities, viewmats, Ks, c0, cN)]
        m, q, s, op, vm, Ks_, c0_, cN_ = arrays
        means2d = screen.numpy()  # the projected means, written in place
        conics = np.empty((C, N, 3), dtype=np.float32)
        depths = np.empty((C, N, 1), dtype=np.float32)
        radii = np.empty((C, N, 2), dtype=np.int32)
        # the compositing table's rows, written by the projection (mean, conic, opacity, depth)
        # and the SH colours in place
        D = 3 + int(with_depth)
        table = np.empty((C * N, 6 + D), dtype=np.float32)
        native.project_forward(m, q, s, op, vm, Ks_, width, height, near, far, eps2d, radius_clip,
                               means2d, conics, depths, radii, table, 9 if with_depth else -1,
                               threads)
        campos = -np.einsum("cji,cj->ci", vm[:, :3, :3], vm[:, :3, 3]).astype(np.float32)
        colors = table[:, 6:9]
        native.sh_forward(degree, m, c0_, cN_, campos, radii[..., 0] > 0, colors, threads)
        tiles_x, tiles_y = math.ceil(width / ts), math.ceil(height / ts)
        ids, offsets, counts = native.bin_lists(
            depths.reshape(-1), means2d.reshape(-1, 2), radii.reshape(-1, 2).astype(np.float32),
            max(N, 1), ts, tiles_x, tiles_y, C * tiles_x * tiles_y)
        bg = np.zeros((C, D), dtype=np.float32)
        if backgrounds is not None:
            bg[:, :3] = _f32(backgrounds)
        render = np.empty((C, height, width, D), dtype=np.float32)
        trans = np.empty((C, height, width), dtype=np.float32)
        last = np.empty((C, height, width), dtype=np.int64)
        reach = np.empty((C * N, 2), dtype=np.float32)  # each row's ellipse, for the backward too
        native.composite_forward(table, ids, offsets, counts, ts, tiles_x, tiles_y, bg, render,
                                 trans, last, reach, threads)
        ctx.native, ctx.settings, ctx.screen = native, settings, screen
        ctx.tiles = (tiles_x, tiles_y)
        ctx.arrays = (arrays, campos, colors, table, ids, offsets, counts, bg, trans, last, reach)
        radii_t = torch.from_numpy(radii)
        conics_t, depths_t = torch.from_numpy(conics), torch.from_numpy(depths[..., 0])
        ctx.mark_non_differentiable(conics_t, depths_t, radii_t)
        ctx.set_materialize_grads(False)  # no zero-filled gradients of the outputs left unused
        alphas = 1.0 - torch.from_numpy(trans)[..., None]
        return (torch.from_numpy(render), alphas, conics_t, depths_t, radii_t,
                torch.tensor(ids.shape[0], device="cpu"))

    @staticmethod
    def backward(ctx, v_render, v_alphas, *_):
        native, threads = ctx.native, cpu_kernel_threads()
        width, height, near, far, eps2d, _, degree, with_depth, ts = ctx.settings
        arrays, campos, colors, table, ids, offsets, counts, bg, trans, last, reach = ctx.arrays
        m, q, s, _, vm, Ks_, c0_, cN_ = arrays
        C, N = vm.shape[0], m.shape[0]
        tiles_x, tiles_y = ctx.tiles
        D = table.shape[1] - 6
        d_render = (np.zeros((C, height, width, D), np.float32) if v_render is None
                    else _f32(v_render))
        d_alpha = (np.zeros((C, height, width), np.float32) if v_alphas is None
                   else _f32(v_alphas[..., 0]))
        per_entry = native.composite_backward(table, ids, offsets, counts, ts, tiles_x, tiles_y,
                                              bg, trans, last, d_render, d_alpha, reach,
                                              threads)
        # the table's gradients, read in place (column slices) by the projection's and SH's backward
        total = native.sum_by_gaussian(per_entry, ids, C * N, threads)
        v_depths = (total[:, 9:10] if with_depth
                    else np.zeros((C, N, 1), dtype=np.float32))
        v_means, v_quats, v_scales = native.project_backward(
            m, q, s, vm, Ks_, width, height, near, far, eps2d, total[:, 0:2],
            total[:, 2:5], v_depths, threads)
        sh = (np.empty_like(m), np.empty_like(c0_), np.empty_like(cN_))
        native.sh_backward(degree, m, c0_, cN_, campos, colors, total[:, 6:9], *sh,
                           threads)
        v_means += sh[0]
        total = total.reshape(C, N, -1)
        ctx.screen.grad = torch.from_numpy(total)[..., 0:2]  # a view of the table's gradients
        v_op = total[..., 5].sum(axis=0)
        g_bg = None
        if ctx.needs_input_grad[8] and v_render is not None:
            g_bg = (v_render[..., :3] * torch.from_numpy(trans)[..., None]).sum(dim=(1, 2))
        return (*(torch.from_numpy(a) for a in (v_means, v_quats, v_scales, v_op, *sh[1:])),
                None, None, g_bg, None, None)


def rasterize_fit(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor,
                  c0: Tensor, cN: Tensor, viewmats: Tensor, Ks: Tensor, width: int, height: int,
                  sh_degree: int, backgrounds: Tensor | None, near_plane: float, far_plane: float,
                  with_depth: bool, eps2d: float, radius_clip: float, tile_size: int
                  ) -> tuple[Tensor, Tensor, dict]:
    """``_torch_rasterize``'s result for SH colours (c0, cN) through FusedRasterize: renders
    (C, H, W, 3 or 4, the 4th the accumulated depth), alphas (C, H, W, 1) and the info dict,
    whose ``means2d`` gets its ``grad`` from the backward."""
    _check_sh(sh_degree, c0.shape[0], 1 + cN.shape[1])
    C, N = viewmats.shape[0], means.shape[0]
    screen = torch.empty(C, N, 2, device="cpu")
    settings = (width, height, float(near_plane), float(far_plane), float(eps2d),
                float(radius_clip), int(sh_degree), bool(with_depth), tile_size)
    renders, alphas, conics, depths, radii_xy, n_isects = FusedRasterize.apply(
        means, quats, scales, opacities, c0, cN, viewmats.detach(), Ks.detach(), backgrounds,
        settings, screen)
    info = {
        "means2d": screen, "radii": torch.maximum(radii_xy[..., 0], radii_xy[..., 1]),
        "radii_xy": radii_xy, "depths": depths, "conics": conics, "width": width,
        "height": height, "n_cameras": C, "tile_size": tile_size,
        "tile_width": math.ceil(width / tile_size), "tile_height": math.ceil(height / tile_size),
        "n_isects": int(n_isects), "backend": "cpu",
    }
    return renders, alphas, info
