"""Tile binning and front-to-back alpha compositing for the torch rasterizer backend.

The compositor works on tiles of ``tile_size x tile_size`` pixels. Every tile owns a depth-sorted
list of the Gaussians whose screen-space box touches it. Lists are walked in chunks of ``K``
Gaussians for many tiles at once (a ``[tiles, K, pixels]`` block), the transmittance is carried from
one chunk to the next, and a tile drops out as soon as it has no Gaussians left or all of its
pixels are saturated. The backward pass recomputes each block from the transmittance saved at its
start instead of keeping an autograd graph of every block, so memory stays bounded by one block.

Compositing rules follow gsplat's CUDA kernels so both backends agree:
alpha = min(0.999, opacity * exp(-sigma)); a Gaussian with alpha < 1/255 is skipped;
a pixel stops before the Gaussian that would bring its transmittance to <= 1e-4.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.999
T_MIN = 1e-4
# threshold() keeps values strictly above its cut-off; this keeps alpha >= 1/255 in float32.
_ALPHA_MIN_BELOW = float(torch.nextafter(torch.tensor(ALPHA_MIN), torch.tensor(0.0)))
# Gaussians per chunk along a tile's list, and the element budget of one [tiles, K, pixels] block.
CHUNK = 32
BLOCK_ELEMENTS = 1 << 18


@dataclass
class TileBins:
    """Depth-sorted Gaussian lists per tile, for C cameras of tiles_y x tiles_x tiles each.

    flat_ids: (n_isects,) int64 index into the flattened (C*N) Gaussian arrays, grouped by tile
    (tile index = camera * tiles_y * tiles_x + ty * tiles_x + tx) and sorted front to back inside
    a tile; offsets, counts: (C*tiles_y*tiles_x,) int64 start and length of each tile's list.
    """

    n_cameras: int
    width: int
    height: int
    tile_size: int
    tiles_x: int
    tiles_y: int
    flat_ids: Tensor
    offsets: Tensor
    counts: Tensor

    @property
    def n_tiles(self) -> int:
        return self.n_cameras * self.tiles_x * self.tiles_y


@torch.no_grad()
def bin_gaussians(
    means2d: Tensor, radii_xy: Tensor, depths: Tensor, width: int, height: int, tile_size: int
) -> TileBins:
    """Build per-tile depth-sorted lists.

    means2d: (C, N, 2) pixel coordinates; radii_xy: (C, N, 2) integer box half-sizes in pixels,
    0 where the Gaussian is not visible; depths: (C, N) camera z used for sorting.
    """
    C, N = depths.shape
    device = means2d.device
    tiles_x = math.ceil(width / tile_size)
    tiles_y = math.ceil(height / tile_size)
    n_tiles = C * tiles_x * tiles_y

    visible = (radii_xy > 0).all(dim=-1).reshape(-1)
    vis_ids = torch.nonzero(visible).squeeze(1)
    m = means2d.detach().reshape(-1, 2)[vis_ids]
    r = radii_xy.reshape(-1, 2)[vis_ids].to(m.dtype)
    x0 = torch.floor((m[:, 0] - r[:, 0]) / tile_size).clamp(0, tiles_x).long()
    x1 = torch.ceil((m[:, 0] + r[:, 0]) / tile_size).clamp(0, tiles_x).long()
    y0 = torch.floor((m[:, 1] - r[:, 1]) / tile_size).clamp(0, tiles_y).long()
    y1 = torch.ceil((m[:, 1] + r[:, 1]) / tile_size).clamp(0, tiles_y).long()
    span_x = x1 - x0
    n_per = span_x * (y1 - y0)
    keep = n_per > 0
    vis_ids, x0, y0, span_x, n_per = vis_ids[keep], x0[keep], y0[keep], span_x[keep], n_per[keep]

    M = vis_ids.numel()
    if M == 0:
        empty = torch.zeros(0, dtype=torch.long, device=device)
        zeros = torch.zeros(n_tiles, dtype=torch.long, device=device)
        return TileBins(C, width, height, tile_size, tiles_x, tiles_y, empty, zeros, zeros.clone())

    # Depth rank of every listed Gaussian, so one int64 sort orders by (tile, depth).
    order = torch.argsort(depths.detach().reshape(-1)[vis_ids])
    rank = torch.empty_like(order)
    rank[order] = torch.arange(M, device=device)

    owner = torch.repeat_interleave(torch.arange(M, device=device), n_per)
    start = torch.cumsum(n_per, 0) - n_per
    j = torch.arange(owner.numel(), device=device) - start[owner]
    sx = span_x[owner]
    tx = x0[owner] + j % sx
    ty = y0[owner] + j // sx
    cam = vis_ids[owner] // N
    tile = (cam * tiles_y + ty) * tiles_x + tx
    key = tile * M + rank[owner]
    _, perm = torch.sort(key)
    flat_ids = vis_ids[owner[perm]]
    counts = torch.bincount(tile, minlength=n_tiles)
    offsets = torch.cumsum(counts, 0) - counts
    return TileBins(C, width, height, tile_size, tiles_x, tiles_y, flat_ids, offsets, counts)


def tiles_to_image(x: Tensor, bins: TileBins) -> Tensor:
    """(n_tiles, P, D) per-tile pixels -> (C, H, W, D) images."""
    C, ts, tx, ty = bins.n_cameras, bins.tile_size, bins.tiles_x, bins.tiles_y
    D = x.shape[-1]
    img = x.reshape(C, ty, tx, ts, ts, D).permute(0, 1, 3, 2, 4, 5).reshape(C, ty * ts, tx * ts, D)
    return img[:, : bins.height, : bins.width]


def image_to_tiles(img: Tensor, bins: TileBins) -> Tensor:
    """(C, H, W, D) images -> (n_tiles, P, D) per-tile pixels (zero padded past the border)."""
    C, ts, tx, ty = bins.n_cameras, bins.tile_size, bins.tiles_x, bins.tiles_y
    D = img.shape[-1]
    pad = img.new_zeros(C, ty * ts, tx * ts, D)
    pad[:, : bins.height, : bins.width] = img
    return pad.reshape(C, ty, ts, tx, ts, D).permute(0, 1, 3, 2, 4, 5).reshape(C * ty * tx, ts * ts, D)


class _Geometry:
    """Per-tile pixel layout, shared by forward and backward.

    Pixels are addressed in coordinates relative to their tile's centre, (u, v), so the quadratic
    form of a Gaussian over a tile is one small matrix product with the basis (u², uv, v², u, v, 1)
    and its numbers stay small.
    """

    def __init__(self, bins: TileBins, dtype, device):
        ts = bins.tile_size
        t = torch.arange(bins.n_tiles, device=device)
        in_cam = t % (bins.tiles_x * bins.tiles_y)
        half = 0.5 * ts
        self.center_x = ((in_cam % bins.tiles_x) * ts).to(dtype) + half
        self.center_y = ((in_cam // bins.tiles_x) * ts).to(dtype) + half
        self.camera = t // (bins.tiles_x * bins.tiles_y)
        p = torch.arange(ts * ts, device=device)
        u = (p % ts).to(dtype) + 0.5 - half
        v = (p // ts).to(dtype) + 0.5 - half
        self.basis = torch.stack([u * u, u * v, v * v, u, v, torch.ones_like(u)])  # (6, P)
        self.basis_t = self.basis.t().contiguous()  # (P, 6)
        px = self.center_x[:, None] + u[None]
        py = self.center_y[:, None] + v[None]
        self.inside = (px < bins.width) & (py < bins.height)  # (n_tiles, P)


def _block(tiles: Tensor, k: int, K: int, bins: TileBins, geo: _Geometry,
           means2d: Tensor, conics: Tensor, opacities: Tensor, T_in: Tensor):
    """Evaluate chunk k (Gaussians k*K .. k*K+K-1 of each tile's list) for a group of G tiles.

    Returns ids (G, K), tile-local means mu, mv (G, K), conics (G, K, 3), opacities (G, K) and
    the (G, P, K) tensors both passes need: raw alpha, 1 - used alpha, transmittance before each
    Gaussian, inclusion indicator (1.0 / 0.0) and blending weight. K is the last axis because
    scans along the last axis are much faster on CPUs; masks are applied arithmetically because
    torch.where is slow there.
    """
    pos = k * K + torch.arange(K, device=tiles.device)
    valid = pos[None, :] < bins.counts[tiles][:, None]  # (G, K)
    idx = torch.where(valid, bins.offsets[tiles][:, None] + pos[None, :], 0)
    fid = bins.flat_ids[idx]
    con = conics[fid]  # (G, K, 3)
    mu = means2d[fid, 0] - geo.center_x[tiles][:, None]  # (G, K)
    mv = means2d[fid, 1] - geo.center_y[tiles][:, None]
    op = opacities[fid] * valid
    a, b, c = con.unbind(-1)
    # -sigma(u, v) = -(a/2 (u-mu)² + b (u-mu)(v-mv) + c/2 (v-mv)²), expanded in the basis.
    ru = a * mu + b * mv
    rv = b * mu + c * mv
    coef = torch.stack([-0.5 * a, -b, -0.5 * c, ru, rv, -0.5 * (mu * ru + mv * rv)], dim=1)
    # Far pixels would give denormal exp() results, which are very slow on CPUs; exp(-20) * opacity
    # is already far below the 1/255 cut-off.
    neg_sigma = torch.matmul(geo.basis_t, coef).clamp_min_(-20.0)  # (G, P, K)
    alpha_raw = torch.exp_(neg_sigma).mul_(op[:, None, :])
    one_minus = F.threshold(alpha_raw, _ALPHA_MIN_BELOW, 0.0).clamp_(max=ALPHA_MAX).neg_().add_(1.0)
    T_incl = torch.cumprod(one_minus, dim=2).mul_(T_in[:, :, None])  # after each Gaussian
    # A prefix along K: the pixel stops before the first Gaussian that fails.
    incl = torch.sign(F.threshold(T_incl, T_MIN, 0.0))
    T_excl = torch.cat([T_in[:, :, None], T_incl[:, :, :-1]], dim=2)
    w = (1.0 - one_minus).mul_(T_excl).mul_(incl)
    return fid, mu, mv, con, op, alpha_raw, one_minus, T_excl, incl, w


def _groups(active: Tensor, K: int, P: int):
    G = max(1, BLOCK_ELEMENTS // (K * P))
    return active.split(G)


class Composite(torch.autograd.Function):
    """Front-to-back compositing of projected Gaussians into per-tile pixel buffers.

    Inputs: means2d (C*N, 2), conics (C*N, 3) upper-triangle inverse covariance (a, b, c),
    opacities (C*N,), colors (C*N, D), backgrounds (C, D); bins: TileBins.
    Outputs: renders (C, H, W, D), alphas (C, H, W, 1).
    """

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, backgrounds, bins: TileBins):
        dtype, device = means2d.dtype, means2d.device
        P = bins.tile_size ** 2
        D = colors.shape[-1]
        K = CHUNK
        geo = _Geometry(bins, dtype, device)
        # A ones column makes the colour product also return the summed weights.
        colors1 = torch.cat([colors, colors.new_ones(colors.shape[0], 1)], dim=1)
        T_carry = geo.inside.to(dtype)  # 0 = pixel finished (or off-image)
        T_final = torch.ones(bins.n_tiles, P, dtype=dtype, device=device)
        accum = torch.zeros(bins.n_tiles, P, D, dtype=dtype, device=device)
        saved = []
        k = 0
        while True:
            active = torch.nonzero((bins.counts > k * K) & (T_carry > 0).any(dim=1)).squeeze(1)
            if active.numel() == 0:
                break
            for tiles in _groups(active, K, P):
                T_in = T_carry[tiles]
                fid, *_, incl, w = _block(tiles, k, K, bins, geo, means2d, conics, opacities, T_in)
                out = torch.bmm(w, colors1[fid])  # (G, P, D+1)
                accum[tiles] += out[..., :D]
                T_new = T_in - out[..., D]
                T_final[tiles] = torch.where(T_in > 0, T_new, T_final[tiles])
                T_carry[tiles] = T_new * incl[:, :, -1]
                saved.append((k, tiles, T_in))
            k += 1

        renders_t = accum + T_final[..., None] * backgrounds[geo.camera][:, None, :]
        renders = tiles_to_image(renders_t, bins)
        alphas = tiles_to_image((1.0 - T_final)[..., None], bins)
        ctx.bins, ctx.saved_blocks, ctx.geo = bins, saved, geo
        ctx.save_for_backward(means2d, conics, opacities, colors, backgrounds, T_final)
        return renders, alphas

    @staticmethod
    def backward(ctx, grad_renders, grad_alphas):
        means2d, conics, opacities, colors, backgrounds, T_final = ctx.saved_tensors
        bins, geo = ctx.bins, ctx.geo
        K = CHUNK
        D = colors.shape[-1]
        dC = image_to_tiles(grad_renders, bins)  # (n_tiles, P, D)
        dA = image_to_tiles(grad_alphas, bins)[..., 0]  # (n_tiles, P)
        # dC . (colour of everything behind), starting with the background's share; the alpha
        # output's gradient enters the same way with the opposite sign.
        carry = T_final * (dC * backgrounds[geo.camera][:, None, :]).sum(-1) - dA * T_final
        colors_t = colors.t().contiguous()  # (D, C*N)

        g_means = torch.zeros_like(means2d)
        g_conics = torch.zeros_like(conics)
        g_op = torch.zeros_like(opacities)
        g_col_t = torch.zeros_like(colors_t)
        for k, tiles, T_in in reversed(ctx.saved_blocks):
            fid, mu, mv, con, op, alpha_raw, one_minus, T_excl, incl, w = _block(
                tiles, k, K, bins, geo, means2d, conics, opacities, T_in)
            dCt = dC[tiles]  # (G, P, D)
            g = torch.bmm(dCt, colors_t[:, fid].permute(1, 0, 2))  # (G, P, K): dC . colour
            csum = torch.cumsum(w * g, dim=2)
            last = csum[:, :, -1]
            # d render / d alpha_i = T_i c_i - (everything behind i) / (1 - alpha_i)
            behind = (last + carry[tiles])[:, :, None] - csum
            carry[tiles] += last
            d_alpha = T_excl.mul_(g).sub_(behind.div_(one_minus))
            # Clamped or skipped alphas pass no gradient to opacity and shape.
            live = F.threshold(alpha_raw, _ALPHA_MIN_BELOW, 0.0).neg_()
            live = F.threshold(live, -ALPHA_MAX, 0.0).neg_()
            d_sigma = d_alpha.mul_(live).mul_(incl)  # = -dL/dsigma
            # Moments of dL/dsigma over the tile's pixels in the (u², uv, v², u, v, 1) basis.
            m = torch.matmul(geo.basis, d_sigma)  # (G, 6, K)
            Muu, Muv, Mvv, Mu, Mv, M1 = m.unbind(1)
            a, b, c = con.unbind(-1)
            Su = Mu - mu * M1  # sum dsig * (u - mu)
            Sv = Mv - mv * M1
            Suu = Muu - 2.0 * mu * Mu + mu * mu * M1
            Svv = Mvv - 2.0 * mv * Mv + mv * mv * M1
            Suv = Muv - mu * Mv - mv * Mu + mu * mv * M1
            gc = -torch.stack([0.5 * Suu, Suv, 0.5 * Svv], dim=-1)
            gm = torch.stack([a * Su + b * Sv, b * Su + c * Sv], dim=-1)
            gop = M1 / torch.where(op > 0, op, 1.0)
            flat = fid.reshape(-1)
            g_means.index_add_(0, flat, gm.reshape(-1, 2))
            g_conics.index_add_(0, flat, gc.reshape(-1, 3))
            g_op.index_add_(0, flat, gop.reshape(-1))
            gcol = torch.bmm(dCt.transpose(1, 2), w)  # (G, D, K)
            g_col_t.index_add_(1, flat, gcol.permute(1, 0, 2).reshape(D, -1))

        g_bg = None
        if ctx.needs_input_grad[4]:
            T_img = tiles_to_image(T_final[..., None], bins)
            g_bg = (grad_renders * T_img).sum(dim=(1, 2))
        return g_means, g_conics, g_op, g_col_t.t(), g_bg, None


def composite(means2d, conics, opacities, colors, backgrounds, bins: TileBins):
    """Differentiable compositing; see Composite. Returns (renders (C,H,W,D), alphas (C,H,W,1))."""
    return Composite.apply(means2d, conics, opacities, colors, backgrounds, bins)
