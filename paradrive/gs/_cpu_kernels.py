"""Numba kernels of the fused CPU rasterizer: tile binning, forward and backward compositing.

The compositing normally runs in the vectorised C++ of ``_composite.cpp`` (see ``_native``),
which follows the same rules on the same layouts; the kernels here stand in where no compiler
builds it, or with ``PARADRIVE_KERNELS=numba``.

Every kernel parallelises over tiles (``prange``) and each tile is the work of one thread, in a
fixed order inside it, so images and gradients do not depend on the thread count. Per-Gaussian
gradients are first written per tile-Gaussian pair and then summed in list order by one thread.

A tile walks its depth-sorted list (front to back, or back to front for the gradient) and each
Gaussian visits only the pixels of its rows where sigma <= SIGMA_CUT, the rest having alpha
< 1/255; along a row exp(-sigma) is stepped by multiplication. The compositing rules are gsplat's,
as in the torch compositor of ``_tiles``: alpha = min(0.999, opacity * exp(-sigma)); sigma < 0 or
alpha < 1/255 is skipped; a pixel stops before the Gaussian that would bring its transmittance to
<= 1e-4. Arithmetic is float64 inside, the arrays are float32.

Array layouts: ``gauss`` (n_isects, 6 + D) holds one row per tile-Gaussian pair, in tile list
order: mean x, mean y, conic a, b, c, opacity, then D colour channels. ``offsets``/``counts``
(n_tiles,) address each tile's rows; tile t covers camera t // (tiles_x * tiles_y).
"""

from __future__ import annotations

import math
import warnings

import numba
import numpy as np
from numba import njit, prange

# Numba tries TBB first and warns when the installed one is too old; OpenMP is used then.
warnings.filterwarnings("ignore", message="The TBB threading layer requires", category=Warning)

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.999
T_MIN = 1e-4
# Beyond it alpha < 1/255 for any opacity <= 1 (log 255 = 5.5413): pixels past it are not visited.
SIGMA_CUT = 5.55
# Channels the compositing kernels carry per Gaussian (RGB and depth); wider features take the
# torch-op compositor.
MAX_CHANNELS = 4


@njit(cache=True)
def tile_ranges(mx: float, my: float, rx: float, ry: float, ts: int, tiles_x: int,
                tiles_y: int) -> tuple[int, int, int, int]:
    """Tiles [x0, x1) x [y0, y1) touched by a box of half-size (rx, ry) around (mx, my)."""
    x0 = min(max(math.floor((mx - rx) / ts), 0), tiles_x)
    x1 = min(max(math.ceil((mx + rx) / ts), 0), tiles_x)
    y0 = min(max(math.floor((my - ry) / ts), 0), tiles_y)
    y1 = min(max(math.ceil((my + ry) / ts), 0), tiles_y)
    return x0, x1, y0, y1


@njit(cache=True)
def _bin_pass(order: np.ndarray, means2d: np.ndarray, radii: np.ndarray, n_per_cam: int,
              ts: int, tiles_x: int, tiles_y: int, fill: np.ndarray, ids: np.ndarray) -> None:
    """Walk every (Gaussian, touched tile) pair: fill[t] += 1, and ids[fill[t]] = g first when
    ids is not empty. order: (M,) flat ids of visible Gaussians, front to back."""
    for g in order:
        cam = g // n_per_cam
        x0, x1, y0, y1 = tile_ranges(means2d[g, 0], means2d[g, 1], radii[g, 0], radii[g, 1],
                                     ts, tiles_x, tiles_y)
        for ty in range(y0, y1):
            for tx in range(x0, x1):
                t = (cam * tiles_y + ty) * tiles_x + tx
                if ids.shape[0]:
                    ids[fill[t]] = g
                fill[t] += 1


@njit(cache=True)
def bin_lists(order: np.ndarray, means2d: np.ndarray, radii: np.ndarray, n_per_cam: int,
              ts: int, tiles_x: int, tiles_y: int, n_tiles: int
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(flat Gaussian ids grouped by tile, offsets, counts); walking ``order`` front to back
    keeps each tile's list depth-sorted."""
    counts = np.zeros(n_tiles, dtype=np.int64)
    _bin_pass(order, means2d, radii, n_per_cam, ts, tiles_x, tiles_y, counts,
              np.empty(0, dtype=np.int64))
    offsets = np.cumsum(counts) - counts
    ids = np.empty(counts.sum(), dtype=np.int64)
    _bin_pass(order, means2d, radii, n_per_cam, ts, tiles_x, tiles_y, offsets.copy(), ids)
    return ids, offsets, counts


@njit(cache=True, inline="always")
def _row_span(gauss: np.ndarray, e: int, py: float, x_lo: int, x_hi: int) -> tuple[int, int]:
    """Pixels [x0, x1) of the row at py, clipped to [x_lo, x_hi), outside which entry e has
    sigma > SIGMA_CUT: the roots of the quadratic in x, widened by a small margin."""
    a, b, c = gauss[e, 2], gauss[e, 3], gauss[e, 4]
    if a <= 0.0:
        return x_lo, x_hi
    dy = gauss[e, 1] - py
    disc = (b * b - a * c) * dy * dy + 2.0 * a * SIGMA_CUT
    if disc < 0.0:
        return x_lo, x_lo
    root = math.sqrt(disc) / a
    mid = gauss[e, 0] + b * dy / a - 0.5  # pixel x whose centre is the parabola's vertex
    x0 = max(x_lo, math.ceil(mid - root - 1e-3))
    x1 = min(x_hi, math.floor(mid + root + 1e-3) + 1)
    return x0, max(x0, x1)


@njit(cache=True, inline="always")
def _row_range(gauss: np.ndarray, e: int, y_lo: int, y_hi: int) -> tuple[int, int]:
    """Rows [y0, y1) of [y_lo, y_hi) that entry e's ellipse sigma <= SIGMA_CUT can reach (where
    ``_row_span`` has a real root: (b^2 - ac) dy^2 + 2 a SIGMA_CUT >= 0), widened by a margin;
    rows outside it have empty spans, so skipping them changes nothing."""
    a, b, c = gauss[e, 2], gauss[e, 3], gauss[e, 4]
    det = a * c - b * b
    if a <= 0.0 or det <= 0.0:
        return y_lo, y_hi
    half = math.sqrt(2.0 * SIGMA_CUT * a / det) + 1e-3
    y0 = max(y_lo, math.ceil(gauss[e, 1] - half - 0.5))
    y1 = min(y_hi, math.floor(gauss[e, 1] + half - 0.5) + 1)
    return y0, max(y0, y1)


@njit(cache=True, inline="always")
def _row_alphas(gauss: np.ndarray, e: int, py: float, x_lo: int, x_hi: int, ratio: float,
                out: np.ndarray) -> tuple[int, int]:
    """Alphas of entry e along the row at py: out[x - x_lo] for x in the returned [x0, x1).

    Along a row sigma is a quadratic in x, so exp(-sigma) steps by a factor that itself changes
    by ``ratio`` = exp(-a) (the entry's, computed once): two multiplications per pixel instead
    of an exp(). A pixel with sigma < 0 (exp(-sigma) > 1) or alpha < 1/255 gets 0.
    """
    x0, x1 = _row_span(gauss, e, py, x_lo, x_hi)
    if x0 == x1:
        return x0, x1
    a, b, c, op = gauss[e, 2], gauss[e, 3], gauss[e, 4], gauss[e, 5]
    dx = gauss[e, 0] - (x0 + 0.5)
    dy = gauss[e, 1] - py
    E = math.exp(-(0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy))
    step = math.exp(a * dx - 0.5 * a + b * dy)
    for x in range(x0, x1):
        alpha = min(ALPHA_MAX, op * E)
        out[x - x_lo] = alpha if E <= 1.0 and alpha >= ALPHA_MIN else 0.0
        E *= step
        step *= ratio
    return x0, x1


@njit(cache=True, inline="always")
def _colour(gauss: np.ndarray, e: int, k: int, D: int) -> float:
    """Channel k of entry e, 0 past its D channels (the kernels keep up to four in registers)."""
    return gauss[e, 6 + k] if k < D else 0.0


@njit(cache=True)
def _tile_box(t: int, ts: int, tiles_x: int, tiles_y: int, H: int, W: int
              ) -> tuple[int, int, int, int, int]:
    """(camera, y_lo, y_hi, x_lo, x_hi) of tile t, clipped to the image."""
    per_cam = tiles_x * tiles_y
    cam, r = t // per_cam, t % per_cam
    y_lo, x_lo = (r // tiles_x) * ts, (r % tiles_x) * ts
    return cam, y_lo, min(y_lo + ts, H), x_lo, min(x_lo + ts, W)


@njit(cache=True)
def _forward_tile(t: int, gauss: np.ndarray, start: int, n: int, ts: int, tiles_x: int,
                  tiles_y: int, bg: np.ndarray, render: np.ndarray, trans: np.ndarray,
                  last: np.ndarray) -> None:
    """Entries front to back, each over the pixels of its ellipse; a pixel that saturates is done."""
    C, H, W, D = render.shape
    cam, y_lo, y_hi, x_lo, x_hi = _tile_box(t, ts, tiles_x, tiles_y, H, W)
    T = np.ones(ts * ts)
    acc = np.zeros((ts * ts, MAX_CHANNELS))
    stop = np.zeros(ts * ts, dtype=np.int64)
    done = np.zeros(ts * ts, dtype=np.bool_)
    alphas = np.empty(ts)
    active = (y_hi - y_lo) * (x_hi - x_lo)
    for j in range(n):
        e = start + j
        c0, c1, c2, c3 = (_colour(gauss, e, 0, D), _colour(gauss, e, 1, D),
                          _colour(gauss, e, 2, D), _colour(gauss, e, 3, D))
        ratio = math.exp(-gauss[e, 2])
        ya, yb = _row_range(gauss, e, y_lo, y_hi)
        for y in range(ya, yb):
            x0, x1 = _row_alphas(gauss, e, y + 0.5, x_lo, x_hi, ratio, alphas)
            for x in range(x0, x1):
                p = (y - y_lo) * ts + x - x_lo
                alpha = alphas[x - x_lo]
                if done[p] or alpha == 0.0:
                    continue
                next_T = T[p] * (1.0 - alpha)
                if next_T <= T_MIN:
                    done[p] = True
                    active -= 1
                    continue
                w = alpha * T[p]
                acc[p, 0] += w * c0
                if D > 1:
                    acc[p, 1] += w * c1
                if D > 2:
                    acc[p, 2] += w * c2
                if D > 3:
                    acc[p, 3] += w * c3
                T[p] = next_T
                stop[p] = j + 1
        if active == 0:
            break
    _write_tile(cam, y_lo, y_hi, x_lo, x_hi, ts, acc, T, stop, bg, render, trans, last)


@njit(cache=True)
def _write_tile(cam: int, y_lo: int, y_hi: int, x_lo: int, x_hi: int, ts: int, acc: np.ndarray,
                T: np.ndarray, stop: np.ndarray, bg: np.ndarray, render: np.ndarray,
                trans: np.ndarray, last: np.ndarray) -> None:
    """Copy a tile's pixels out, the background behind what is left of their transmittance."""
    for y in range(y_lo, y_hi):
        for x in range(x_lo, x_hi):
            p = (y - y_lo) * ts + x - x_lo
            for k in range(render.shape[3]):
                render[cam, y, x, k] = acc[p, k] + T[p] * bg[cam, k]
            trans[cam, y, x] = T[p]
            last[cam, y, x] = stop[p]


@njit(cache=True, parallel=True)
def composite_forward(gauss: np.ndarray, offsets: np.ndarray, counts: np.ndarray, ts: int,
                      tiles_x: int, tiles_y: int, bg: np.ndarray, render: np.ndarray,
                      trans: np.ndarray, last: np.ndarray) -> None:
    """Fill render (C, H, W, D), final transmittance trans (C, H, W) and last (C, H, W): the
    number of list entries each pixel walked before it stopped (its last contribution + 1).
    D <= MAX_CHANNELS."""
    for t in prange(offsets.shape[0]):
        _forward_tile(t, gauss, offsets[t], counts[t], ts, tiles_x, tiles_y, bg, render, trans,
                      last)


@njit(cache=True)
def _pixel_state(cam: int, y_lo: int, y_hi: int, x_lo: int, x_hi: int, ts: int, bg: np.ndarray,
                 trans: np.ndarray, last: np.ndarray, d_render: np.ndarray, d_alpha: np.ndarray,
                 T: np.ndarray, q: np.ndarray, stop: np.ndarray, dC: np.ndarray) -> None:
    """A tile's per-pixel state before the walk back to front: T the final transmittance, stop
    the entries walked, dC the colour gradient and q = T_final (dA - bg . dC)."""
    for y in range(y_lo, y_hi):
        for x in range(x_lo, x_hi):
            p = (y - y_lo) * ts + x - x_lo
            T[p], stop[p] = trans[cam, y, x], last[cam, y, x]
            bg_dot = 0.0
            for k in range(d_render.shape[3]):
                dC[p, k] = d_render[cam, y, x, k]
                bg_dot += bg[cam, k] * dC[p, k]
            q[p] = T[p] * (d_alpha[cam, y, x] - bg_dot)


@njit(cache=True, inline="always")
def _channel_vjp(c: float, d: float, T: float, ra: float, w: float, behind: float
                 ) -> tuple[float, float, float]:
    """One colour channel of one pixel, walking back: (the entry's colour gradient w d, its share
    of the alpha gradient, the colour behind the entry with it added)."""
    return w * d, (c * T - behind * ra) * d, behind + c * w


@njit(cache=True)
def _backward_tile(t: int, gauss: np.ndarray, start: int, ts: int, tiles_x: int, tiles_y: int,
                   bg: np.ndarray, trans: np.ndarray, last: np.ndarray, d_render: np.ndarray,
                   d_alpha: np.ndarray, grads: np.ndarray) -> None:
    """Entries back to front, each over the pixels of its ellipse that it reached. Per pixel,
    walking back: T and buf (the colour behind the entry) are its running state; an entry's
    gradient sums in registers over its pixels and is written once."""
    C, H, W, D = d_render.shape
    cam, y_lo, y_hi, x_lo, x_hi = _tile_box(t, ts, tiles_x, tiles_y, H, W)
    P = ts * ts
    T, q = np.zeros(P), np.zeros(P)
    stop = np.zeros(P, dtype=np.int64)
    buf, dC = np.zeros((P, MAX_CHANNELS)), np.zeros((P, MAX_CHANNELS))
    _pixel_state(cam, y_lo, y_hi, x_lo, x_hi, ts, bg, trans, last, d_render, d_alpha, T, q, stop, dC)
    alphas = np.empty(ts)
    for j in range(stop.max() - 1, -1, -1):
        e = start + j
        mx, my, a, b, c, op = gauss[e, 0], gauss[e, 1], gauss[e, 2], gauss[e, 3], gauss[e, 4], gauss[e, 5]
        c0, c1, c2, c3 = (_colour(gauss, e, 0, D), _colour(gauss, e, 1, D),
                          _colour(gauss, e, 2, D), _colour(gauss, e, 3, D))
        g0 = g1 = g2 = g3 = g4 = g5 = h0 = h1 = h2 = h3 = 0.0
        ratio = math.exp(-a)
        ya, yb = _row_range(gauss, e, y_lo, y_hi)
        for y in range(ya, yb):
            x0, x1 = _row_alphas(gauss, e, y + 0.5, x_lo, x_hi, ratio, alphas)
            dy = my - (y + 0.5)
            for x in range(x0, x1):
                p = (y - y_lo) * ts + x - x_lo
                alpha = alphas[x - x_lo]
                if j >= stop[p] or alpha == 0.0:
                    continue
                ra = 1.0 / (1.0 - alpha)
                T[p] *= ra  # transmittance in front of this Gaussian
                w = alpha * T[p]
                v_alpha = q[p] * ra
                dh, dv, buf[p, 0] = _channel_vjp(c0, dC[p, 0], T[p], ra, w, buf[p, 0])
                h0, v_alpha = h0 + dh, v_alpha + dv
                if D > 1:
                    dh, dv, buf[p, 1] = _channel_vjp(c1, dC[p, 1], T[p], ra, w, buf[p, 1])
                    h1, v_alpha = h1 + dh, v_alpha + dv
                if D > 2:
                    dh, dv, buf[p, 2] = _channel_vjp(c2, dC[p, 2], T[p], ra, w, buf[p, 2])
                    h2, v_alpha = h2 + dh, v_alpha + dv
                if D > 3:
                    dh, dv, buf[p, 3] = _channel_vjp(c3, dC[p, 3], T[p], ra, w, buf[p, 3])
                    h3, v_alpha = h3 + dh, v_alpha + dv
                if alpha >= ALPHA_MAX:
                    continue  # clamped: no gradient to opacity and shape
                v_sigma = -alpha * v_alpha
                dx = mx - (x + 0.5)
                g0 += v_sigma * (a * dx + b * dy)
                g1 += v_sigma * (b * dx + c * dy)
                g2 += 0.5 * v_sigma * dx * dx
                g3 += v_sigma * dx * dy
                g4 += 0.5 * v_sigma * dy * dy
                g5 += alpha / op * v_alpha
        grads[e, 0], grads[e, 1], grads[e, 2], grads[e, 3], grads[e, 4], grads[e, 5] = g0, g1, g2, g3, g4, g5
        for k, h in enumerate((h0, h1, h2, h3)):
            if k < D:
                grads[e, 6 + k] = h


@njit(cache=True, parallel=True)
def composite_backward(gauss: np.ndarray, offsets: np.ndarray, ts: int, tiles_x: int,
                       tiles_y: int, bg: np.ndarray, trans: np.ndarray, last: np.ndarray,
                       d_render: np.ndarray, d_alpha: np.ndarray) -> np.ndarray:
    """Gradients per list entry, (n_isects, 6 + D) in the layout of ``gauss``; D <= MAX_CHANNELS."""
    grads = np.zeros(gauss.shape, dtype=np.float64)
    for t in prange(offsets.shape[0]):
        _backward_tile(t, gauss, offsets[t], ts, tiles_x, tiles_y, bg, trans, last, d_render,
                       d_alpha, grads)
    return grads


@njit(cache=True)
def sum_by_gaussian(grads: np.ndarray, flat_ids: np.ndarray, n: int) -> np.ndarray:
    """(n, F) float32 sums of the (n_isects, F) rows per Gaussian id, in list order."""
    out = np.zeros((n, grads.shape[1]), dtype=np.float64)
    for e in range(flat_ids.shape[0]):
        out[flat_ids[e]] += grads[e]
    return out.astype(np.float32)


def set_threads(n: int) -> None:
    """Use n threads (at most the cores Numba started with; 0 or less = all of them)."""
    limit = int(getattr(numba.config, "NUMBA_NUM_THREADS"))
    numba.set_num_threads(limit if n <= 0 else min(n, limit))
