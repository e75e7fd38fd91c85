"""Numba kernels of the fused CPU rasterizer: tile binning, forward and backward compositing.

Every kernel parallelises over tiles (``prange``) and each tile is the work of one thread, in a
fixed order inside it, so images and gradients do not depend on the thread count. Per-Gaussian
gradients are first written per tile-Gaussian pair and then summed in list order by one thread.

Compositing follows gsplat's CUDA rules, as the torch compositor in ``_tiles`` does:
alpha = min(0.999, opacity * exp(-sigma)); sigma < 0 or alpha < 1/255 is skipped; a pixel stops
before the Gaussian that would bring its transmittance to <= 1e-4. Arithmetic is float64 inside,
the arrays are float32.

Array layouts: ``gauss`` (n_isects, 6 + D) holds one row per tile-Gaussian pair, in tile list
order: mean x, mean y, conic a, b, c, opacity, then D colour channels. ``offsets``/``counts``
(n_tiles,) address each tile's rows; tile t covers camera t // (tiles_x * tiles_y).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import njit, prange

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.999
T_MIN = 1e-4


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
def bin_counts(order: np.ndarray, means2d: np.ndarray, radii: np.ndarray, n_per_cam: int,
               ts: int, tiles_x: int, tiles_y: int, n_tiles: int) -> np.ndarray:
    """Gaussians per tile. order: (M,) flat ids of visible Gaussians, front to back."""
    counts = np.zeros(n_tiles, dtype=np.int64)
    for g in order:
        cam = g // n_per_cam
        x0, x1, y0, y1 = tile_ranges(means2d[g, 0], means2d[g, 1], radii[g, 0], radii[g, 1],
                                     ts, tiles_x, tiles_y)
        for ty in range(y0, y1):
            for tx in range(x0, x1):
                counts[(cam * tiles_y + ty) * tiles_x + tx] += 1
    return counts


@njit(cache=True)
def bin_fill(order: np.ndarray, means2d: np.ndarray, radii: np.ndarray, n_per_cam: int,
             ts: int, tiles_x: int, tiles_y: int, offsets: np.ndarray, n_isects: int) -> np.ndarray:
    """Flat Gaussian ids per tile; walking ``order`` front to back keeps each list depth-sorted."""
    ids = np.empty(n_isects, dtype=np.int64)
    fill = offsets.copy()
    for g in order:
        cam = g // n_per_cam
        x0, x1, y0, y1 = tile_ranges(means2d[g, 0], means2d[g, 1], radii[g, 0], radii[g, 1],
                                     ts, tiles_x, tiles_y)
        for ty in range(y0, y1):
            for tx in range(x0, x1):
                t = (cam * tiles_y + ty) * tiles_x + tx
                ids[fill[t]] = g
                fill[t] += 1
    return ids


@njit(cache=True, inline="always")
def _alpha(row: np.ndarray, px: float, py: float) -> float:
    """Alpha of one Gaussian row at pixel centre (px, py); 0 where it is skipped."""
    dx = row[0] - px
    dy = row[1] - py
    sigma = 0.5 * (row[2] * dx * dx + row[4] * dy * dy) + row[3] * dx * dy
    if sigma < 0.0:
        return 0.0
    alpha = min(ALPHA_MAX, row[5] * math.exp(-sigma))
    return alpha if alpha >= ALPHA_MIN else 0.0


@njit(cache=True)
def _forward_tile(t: int, gauss: np.ndarray, start: int, n: int, ts: int, tiles_x: int,
                  tiles_y: int, bg: np.ndarray, render: np.ndarray, trans: np.ndarray,
                  last: np.ndarray) -> None:
    C, H, W, D = render.shape
    per_cam = tiles_x * tiles_y
    cam, r = t // per_cam, t % per_cam
    y_lo, x_lo = (r // tiles_x) * ts, (r % tiles_x) * ts
    acc = np.empty(D)
    for y in range(y_lo, min(y_lo + ts, H)):
        for x in range(x_lo, min(x_lo + ts, W)):
            acc[:] = 0.0
            T = 1.0
            stop = 0
            for j in range(n):
                row = gauss[start + j]
                alpha = _alpha(row, x + 0.5, y + 0.5)
                if alpha == 0.0:
                    continue
                next_T = T * (1.0 - alpha)
                if next_T <= T_MIN:
                    break
                w = alpha * T
                for k in range(D):
                    acc[k] += w * row[6 + k]
                T = next_T
                stop = j + 1
            for k in range(D):
                render[cam, y, x, k] = acc[k] + T * bg[cam, k]
            trans[cam, y, x] = T
            last[cam, y, x] = stop


@njit(cache=True, parallel=True)
def composite_forward(gauss: np.ndarray, offsets: np.ndarray, counts: np.ndarray, ts: int,
                      tiles_x: int, tiles_y: int, bg: np.ndarray, render: np.ndarray,
                      trans: np.ndarray, last: np.ndarray) -> None:
    """Fill render (C, H, W, D), final transmittance trans (C, H, W) and last (C, H, W): the
    number of list entries each pixel walked before it stopped (its last contribution + 1)."""
    for t in prange(offsets.shape[0]):
        _forward_tile(t, gauss, offsets[t], counts[t], ts, tiles_x, tiles_y, bg, render, trans,
                      last)


@njit(cache=True)
def _backward_pixel(gauss: np.ndarray, start: int, stop: int, px: float, py: float,
                    T_final: float, dC: np.ndarray, dA: float, bg_dot: float, buf: np.ndarray,
                    grads: np.ndarray) -> None:
    """Walk one pixel's list back to front and add its share to grads[start + j]."""
    D = dC.shape[0]
    buf[:] = 0.0
    T = T_final
    for j in range(stop - 1, -1, -1):
        row = gauss[start + j]
        alpha = _alpha(row, px, py)
        if alpha == 0.0:
            continue
        ra = 1.0 / (1.0 - alpha)
        T *= ra  # transmittance in front of this Gaussian
        w = alpha * T
        g = grads[start + j]
        v_alpha = T_final * ra * (dA - bg_dot)
        for k in range(D):
            g[6 + k] += w * dC[k]
            v_alpha += (row[6 + k] * T - buf[k] * ra) * dC[k]
            buf[k] += row[6 + k] * w
        if alpha >= ALPHA_MAX:
            continue  # clamped: no gradient to opacity and shape
        vis = alpha / row[5]
        v_sigma = -alpha * v_alpha
        dx = row[0] - px
        dy = row[1] - py
        g[0] += v_sigma * (row[2] * dx + row[3] * dy)
        g[1] += v_sigma * (row[3] * dx + row[4] * dy)
        g[2] += 0.5 * v_sigma * dx * dx
        g[3] += v_sigma * dx * dy
        g[4] += 0.5 * v_sigma * dy * dy
        g[5] += vis * v_alpha


@njit(cache=True)
def _backward_tile(t: int, gauss: np.ndarray, start: int, ts: int, tiles_x: int, tiles_y: int,
                   bg: np.ndarray, trans: np.ndarray, last: np.ndarray, d_render: np.ndarray,
                   d_alpha: np.ndarray, grads: np.ndarray) -> None:
    C, H, W, D = d_render.shape
    per_cam = tiles_x * tiles_y
    cam, r = t // per_cam, t % per_cam
    y_lo, x_lo = (r // tiles_x) * ts, (r % tiles_x) * ts
    buf = np.empty(D)
    dC = np.empty(D)
    for y in range(y_lo, min(y_lo + ts, H)):
        for x in range(x_lo, min(x_lo + ts, W)):
            bg_dot = 0.0
            for k in range(D):
                dC[k] = d_render[cam, y, x, k]
                bg_dot += bg[cam, k] * dC[k]
            _backward_pixel(gauss, start, last[cam, y, x], x + 0.5, y + 0.5, trans[cam, y, x],
                            dC, d_alpha[cam, y, x], bg_dot, buf, grads)


@njit(cache=True, parallel=True)
def composite_backward(gauss: np.ndarray, offsets: np.ndarray, ts: int, tiles_x: int,
                       tiles_y: int, bg: np.ndarray, trans: np.ndarray, last: np.ndarray,
                       d_render: np.ndarray, d_alpha: np.ndarray) -> np.ndarray:
    """Gradients per list entry, (n_isects, 6 + D) in the layout of ``gauss``."""
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
    limit = numba.config.NUMBA_NUM_THREADS
    numba.set_num_threads(limit if n <= 0 else min(n, limit))
