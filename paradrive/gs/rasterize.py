"""Differentiable 3D Gaussian splatting rasterizer: one entry point, three backends.

``rasterize`` uses gsplat's CUDA kernels when the tensors live on a CUDA device and the extension
loads, the fused CPU kernels (``cpu``: C++ built at install, the torch thread count,
byte-identical at any count; the torch-op stages where they were not built) for tensors on the
CPU, and otherwise a tile-based torch-op backend (``torch``, any device; the reference the fused
kernels are tested against, within tolerances). All match gsplat's conventions:
EWA projection with a 2D low-pass ``eps2d``, opacity-aware screen boxes, per-tile depth
sorting, front-to-back compositing with alpha clamped to 0.999, alpha < 1/255 skipped and early
termination at transmittance 1e-4.

Credit: the splatting of 3D Gaussian Splatting (Kerbl et al., ACM TOG 2023), re-implemented after
gsplat's conventions (nerfstudio-project/gsplat).
"""

from __future__ import annotations

import torch
from torch import Tensor

from paradrive.devices import gsplat_status, resolve_backend
from paradrive.gs._tiles import ALPHA_MIN, bin_gaussians, composite
from paradrive.gs.sh import shade

__all__ = ["rasterize", "cuda_backend_available"]

_RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")
# Tile edge of the torch backend. The image does not depend on it; 8 px tiles waste fewer
# pixel-Gaussian pairs than gsplat's 16 and are about 1.6x faster on CPUs.
TORCH_TILE_SIZE = 8
# Tile edge of the fused CPU kernels, which visit only the pixels inside each Gaussian's ellipse:
# measured, 16 px tiles (half the lists) are faster than 8.
CPU_TILE_SIZE = 16

def quat_to_rotmat(quats: Tensor) -> Tensor:
    """(N, 4) wxyz, any norm -> (N, 3, 3) rotation."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(quats.shape[:-1] + (3, 3))


def _project(means, quats, scales, opacities, viewmats, Ks, width, height,
             near_plane, far_plane, eps2d, radius_clip):
    """EWA projection of N Gaussians into C pinhole cameras.

    Returns means2d (C, N, 2), conics (C, N, 3) = (a, b, c) of the inverse 2D covariance,
    depths (C, N) camera z, radii_xy (C, N, 2) int32 box half-sizes (0 = culled).
    """
    R = quat_to_rotmat(quats)
    M = R * scales[:, None, :]
    cov3 = M @ M.transpose(1, 2)  # (N, 3, 3)
    Rv = viewmats[:, :3, :3]
    tv = viewmats[:, :3, 3]
    means_c = torch.einsum("cij,nj->cni", Rv, means) + tv[:, None, :]  # (C, N, 3)
    cov_c = torch.einsum("cij,njk,clk->cnil", Rv, cov3, Rv)  # (C, N, 3, 3)
    x, y, z = means_c.unbind(-1)
    depths = z
    with torch.no_grad():
        in_depth = (z > near_plane) & (z < far_plane)
    # A harmless stand-in depth for culled Gaussians keeps inf/nan out of the backward pass.
    zs = torch.where(in_depth, z, torch.ones_like(z))
    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    # Clamp the Jacobian's view direction to 1.3x the field of view, as 3DGS does.
    lim_xp = (width - cx) / fx + 0.3 * (0.5 * width / fx)
    lim_xn = cx / fx + 0.3 * (0.5 * width / fx)
    lim_yp = (height - cy) / fy + 0.3 * (0.5 * height / fy)
    lim_yn = cy / fy + 0.3 * (0.5 * height / fy)
    tx = zs * torch.maximum(torch.minimum(x / zs, lim_xp), -lim_xn)
    ty = zs * torch.maximum(torch.minimum(y / zs, lim_yp), -lim_yn)
    zero = torch.zeros_like(zs)
    J = torch.stack([fx / zs, zero, -fx * tx / (zs * zs),
                     zero, fy / zs, -fy * ty / (zs * zs)], dim=-1).reshape(z.shape + (2, 3))
    cov2 = J @ cov_c @ J.transpose(-1, -2)  # (C, N, 2, 2)
    c00 = cov2[..., 0, 0] + eps2d
    c11 = cov2[..., 1, 1] + eps2d
    c01 = 0.5 * (cov2[..., 0, 1] + cov2[..., 1, 0])
    det = (c00 * c11 - c01 * c01)
    det_safe = det.clamp_min(1e-10)
    conics = torch.stack([c11 / det_safe, -c01 / det_safe, c00 / det_safe], dim=-1)
    means2d = torch.stack([fx * x / zs + cx, fy * y / zs + cy], dim=-1)

    with torch.no_grad():
        # Opacity-aware box: beyond it alpha < 1/255, so it loses nothing (capped at 3.33 sigma).
        op = opacities.detach().expand(z.shape)
        extend = torch.sqrt(2.0 * torch.log((op / ALPHA_MIN).clamp_min(1.0))).clamp(max=3.33)
        rx = torch.ceil(extend * torch.sqrt(c00.detach().clamp_min(0)))
        ry = torch.ceil(extend * torch.sqrt(c11.detach().clamp_min(0)))
        m = means2d.detach()
        ok = (in_depth & (det.detach() > 0) & (op >= ALPHA_MIN) & (rx > 0) & (ry > 0)
              & ~((rx <= radius_clip) & (ry <= radius_clip))
              & (m[..., 0] + rx > 0) & (m[..., 0] - rx < width)
              & (m[..., 1] + ry > 0) & (m[..., 1] - ry < height))
        radii_xy = torch.where(ok[..., None], torch.stack([rx, ry], -1), 0.0).to(torch.int32)
    return means2d, conics, depths, radii_xy


def _torch_rasterize(means, quats, scales, opacities, colors, viewmats, Ks, width, height,
                     sh_degree, backgrounds, near_plane, far_plane, render_mode, eps2d,
                     radius_clip, tile_size, backend="torch"):
    if backend == "cpu" and _fit_case(means, colors, sh_degree, render_mode):
        from paradrive.gs._fused import rasterize_fit

        c0, cN = colors if isinstance(colors, tuple) else (colors[:, :1], colors[:, 1:])
        renders, alphas, info = rasterize_fit(
            means, quats, scales, opacities, c0, cN, viewmats, Ks, width, height, sh_degree,
            backgrounds, near_plane, far_plane, render_mode != "RGB", eps2d, radius_clip,
            tile_size)
        return _expected_depth(renders, alphas, render_mode), alphas, info
    C, N = viewmats.shape[0], means.shape[0]
    project, shade, binner, compositor = _stages(backend)
    if isinstance(colors, tuple):  # the torch-op stages take the coefficients whole
        colors = torch.cat(colors, 1)[:, :(int(sh_degree) + 1) ** 2]
    means2d, conics, depths, radii_xy = project(
        means, quats, scales, opacities, viewmats, Ks, width, height,
        near_plane, far_plane, eps2d, radius_clip)

    if render_mode in ("RGB", "RGB+D", "RGB+ED"):
        if sh_degree is None:
            feats = colors.expand(C, N, colors.shape[-1]) if colors.dim() == 2 else colors
        else:
            campos = -torch.einsum("cji,cj->ci", viewmats[:, :3, :3], viewmats[:, :3, 3])
            # both projections zero both half-sizes of a culled Gaussian, so one tells
            feats = shade(sh_degree, means, colors, campos, radii_xy[..., 0] > 0)
        D = feats.shape[-1]
        if render_mode != "RGB":
            feats = torch.cat([feats, depths[..., None]], dim=-1)
        bg = backgrounds if backgrounds is not None else means.new_zeros(C, D)
        if render_mode != "RGB":
            bg = torch.cat([bg, bg.new_zeros(C, 1)], dim=-1)
    else:
        feats = depths[..., None]
        bg = means.new_zeros(C, 1)

    bins = binner(means2d, radii_xy, depths, width, height, tile_size)
    if means2d.requires_grad:
        means2d.retain_grad()
    op = opacities.expand(C, N).reshape(C * N)
    renders, alphas = compositor(
        means2d.reshape(C * N, 2), conics.reshape(C * N, 3), op,
        feats.reshape(C * N, feats.shape[-1]).contiguous(), bg.to(means.dtype), bins)

    renders = _expected_depth(renders, alphas, render_mode)
    radii = torch.maximum(radii_xy[..., 0], radii_xy[..., 1])
    info = {
        "means2d": means2d, "radii": radii, "radii_xy": radii_xy, "depths": depths,
        "conics": conics, "width": width, "height": height, "n_cameras": C,
        "tile_size": tile_size, "tile_width": bins.tiles_x, "tile_height": bins.tiles_y,
        "n_isects": int(bins.flat_ids.numel()), "backend": backend,
    }
    return renders, alphas, info


def _expected_depth(renders: Tensor, alphas: Tensor, render_mode: str) -> Tensor:
    """The last channel divided by the alpha in the expected-depth modes ('ED', 'RGB+ED')."""
    if render_mode not in ("ED", "RGB+ED"):
        return renders
    return torch.cat([renders[..., :-1], renders[..., -1:] / alphas.clamp_min(1e-10)], -1)


def _fit_case(means: Tensor, colors, sh_degree, render_mode: str) -> bool:
    """Whether the fused kernels run this render as one node (``_fused.rasterize_fit``): SH
    coefficients (in two parts or (N, K, 3)), an RGB mode, float32 and the native library."""
    from paradrive import kernels

    if sh_degree is None or render_mode not in ("RGB", "RGB+D", "RGB+ED"):
        return False
    parts = colors if isinstance(colors, tuple) else (colors,)
    if not isinstance(colors, tuple) and colors.dim() != 3:
        return False
    if means.dtype != torch.float32 or any(t.dtype != torch.float32 for t in parts):
        return False
    return kernels.load() is not None


def _stages(backend: str):
    """(projection, SH colour, binning, compositing) of a CPU-capable backend: the torch-op
    reference, or the fused kernels where they were built."""
    from paradrive import kernels

    if backend == "torch" or kernels.load() is None:
        return _project, _shade_all, bin_gaussians, composite
    from paradrive.gs._fused import bin_gaussians_fused, composite_fused, project_fused, shade_fused

    return project_fused, shade_fused, bin_gaussians_fused, composite_fused


def _shade_all(sh_degree: int, means: Tensor, coeffs: Tensor, campos: Tensor, visible: Tensor) -> Tensor:
    """The torch-op reference colours every Gaussian, drawn or not."""
    return shade(sh_degree, means, coeffs, campos)


def cuda_backend_available() -> bool:
    """True when gsplat's compiled CUDA extension loads (checked once)."""
    return gsplat_status()[0]


def _gsplat_rasterize(means, quats, scales, opacities, colors, viewmats, Ks, width, height,
                      sh_degree, backgrounds, near_plane, far_plane, render_mode, eps2d,
                      radius_clip, tile_size):
    from gsplat import rasterization

    renders, alphas, meta = rasterization(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height,
        near_plane=near_plane, far_plane=far_plane, radius_clip=radius_clip, eps2d=eps2d,
        sh_degree=sh_degree, packed=False, tile_size=tile_size, backgrounds=backgrounds,
        render_mode=render_mode, rasterize_mode="classic")
    means2d = meta["means2d"]
    if means2d.requires_grad:
        means2d.retain_grad()
    radii = meta["radii"]
    radii_xy = radii if radii.dim() == 3 else torch.stack([radii, radii], -1)
    info = dict(meta)
    info.update({
        "means2d": means2d, "radii": radii_xy.max(dim=-1).values.int(), "radii_xy": radii_xy,
        "depths": meta["depths"], "width": width, "height": height,
        "n_cameras": viewmats.shape[0], "backend": "gsplat",
    })
    return renders, alphas, info


def rasterize(means, quats, scales, opacities, colors, viewmats, Ks, width, height, *,
              sh_degree=None, backgrounds=None, near_plane=0.01, far_plane=1e10,
              render_mode="RGB", eps2d=0.3, radius_clip=0.0, tile_size=16, backend="auto"):
    """Render N 3D Gaussians into C pinhole cameras.

    means (N, 3) world; quats (N, 4) wxyz (need not be normalised); scales (N, 3) activated;
    opacities (N,) activated in [0, 1]; colors (N, 3) RGB (or (C, N, D) per camera), or SH
    coefficients (N, K, 3) with sh_degree set (colour = SH(view dir) + 0.5, clamped at 0; the
    first (sh_degree + 1)^2 are used), or those in two parts (sh0 (N, 1, 3), shN (N, K - 1, 3)),
    as a fit keeps them: the fused CPU kernels read them in place, other backends concatenate;
    viewmats (C, 4, 4) world-to-camera (OpenCV); Ks (C, 3, 3); backgrounds (C, 3) or None.
    render_mode: 'RGB' -> (C, H, W, 3); 'RGB+ED' -> (C, H, W, 4), last channel the expected
    depth (alpha-normalised z); 'RGB+D' accumulated depth; 'D' / 'ED' -> (C, H, W, 1).
    backend: 'auto' ('cpu' for CPU tensors; gsplat CUDA when the tensors are on CUDA and its
    extension loads, else torch, with a warning), 'cpu' (the fused kernels on
    torch.get_num_threads() threads; viewmats and Ks get no gradient), 'torch' or 'gsplat'
    (ConfigError when it cannot run); see
    :func:`paradrive.devices.resolve_backend`. tile_size is gsplat's; the torch backend uses
    TORCH_TILE_SIZE, the fused CPU kernels ('cpu') CPU_TILE_SIZE.

    Returns (renders, alphas (C, H, W, 1), info) with info keys 'means2d' (C, N, 2; in the
    autograd graph, retain_grad() called when it requires grad), 'radii' (C, N) int32 (0 = not
    visible), 'depths' (C, N), 'width', 'height', 'n_cameras' and more.
    """
    if render_mode not in _RENDER_MODES:
        raise ValueError(f"render_mode={render_mode!r}; expected one of {_RENDER_MODES}")
    if viewmats.dim() != 3 or viewmats.shape[-2:] != (4, 4):
        raise ValueError(f"viewmats must be (C, 4, 4), got {tuple(viewmats.shape)}")
    if Ks.shape != (viewmats.shape[0], 3, 3):
        raise ValueError(f"Ks must be (C, 3, 3) with C={viewmats.shape[0]}, got {tuple(Ks.shape)}")
    if means.dim() != 2 or means.shape[-1] != 3:
        raise ValueError(f"means must be (N, 3), got {tuple(means.shape)}")
    width, height = int(width), int(height)
    backend = resolve_backend(backend, means.device)
    if isinstance(colors, tuple):
        if sh_degree is None:
            raise ValueError("colors in two parts (sh0, shN) are SH coefficients: set sh_degree")
        if backend != "cpu":
            colors = torch.cat(colors, 1)[:, :(int(sh_degree) + 1) ** 2]
    args = (means, quats, scales, opacities, colors, viewmats, Ks, width, height,
            sh_degree, backgrounds, near_plane, far_plane, render_mode, eps2d,
            radius_clip, tile_size)
    if backend in ("torch", "cpu"):
        from paradrive import kernels

        ts = CPU_TILE_SIZE if backend == "cpu" and kernels.load() is not None else TORCH_TILE_SIZE
        return _torch_rasterize(*args[:-1], ts, backend)
    return _gsplat_rasterize(*args)
