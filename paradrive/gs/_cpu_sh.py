"""Numba kernels of the fused CPU rasterizer: view-dependent colour from spherical harmonics.

``sh.eval_sh`` per Gaussian and camera, colour = max(SH(view dir) + 0.5, 0), and its
gradient to the coefficients and the means. One thread owns a Gaussian and walks the cameras in
order, so results do not depend on the thread count.

Shapes: means (N, 3), campos (C, 3) camera centres, colours (C, N, 3); the coefficients in
the fit's two parts, c0 (N, 1, 3) (band 0) and cN (N, K - 1, 3) (bands 1..3).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from paradrive.gs.sh import SH_C0 as C0
from paradrive.gs.sh import SH_C1 as C1
from paradrive.gs.sh import SH_C2 as C2
from paradrive.gs.sh import SH_C3 as C3

Vec3 = tuple[float, float, float]


@njit(cache=True, inline="always")
def _basis(degree: int, x: float, y: float, z: float, out: np.ndarray) -> None:
    """out[:(degree+1)^2] = the real SH basis at the unit direction (x, y, z)."""
    out[0] = C0
    if degree < 1:
        return
    out[1], out[2], out[3] = -C1 * y, C1 * z, -C1 * x
    if degree < 2:
        return
    xx, yy, zz = x * x, y * y, z * z
    out[4], out[5], out[6] = C2[0] * x * y, C2[1] * y * z, C2[2] * (2 * zz - xx - yy)
    out[7], out[8] = C2[3] * x * z, C2[4] * (xx - yy)
    if degree < 3:
        return
    out[9], out[10] = C3[0] * y * (3 * xx - yy), C3[1] * x * y * z
    out[11], out[12] = C3[2] * y * (4 * zz - xx - yy), C3[3] * z * (2 * zz - 3 * xx - 3 * yy)
    out[13], out[14] = C3[4] * x * (4 * zz - xx - yy), C3[5] * z * (xx - yy)
    out[15] = C3[6] * x * (xx - 3 * yy)


@njit(cache=True, inline="always")
def _basis_vjp(degree: int, x: float, y: float, z: float, w: np.ndarray) -> Vec3:
    """Gradient of sum_k w[k] * basis_k with respect to the unit direction (x, y, z)."""
    gx = gy = gz = 0.0
    if degree >= 1:
        gx, gy, gz = -C1 * w[3], -C1 * w[1], C1 * w[2]
    if degree >= 2:
        gx += C2[0] * y * w[4] - 2 * C2[2] * x * w[6] + C2[3] * z * w[7] + 2 * C2[4] * x * w[8]
        gy += C2[0] * x * w[4] + C2[1] * z * w[5] - 2 * C2[2] * y * w[6] - 2 * C2[4] * y * w[8]
        gz += C2[1] * y * w[5] + 4 * C2[2] * z * w[6] + C2[3] * x * w[7]
    if degree >= 3:
        xx, yy, zz = x * x, y * y, z * z
        gx += (6 * C3[0] * x * y * w[9] + C3[1] * y * z * w[10] - 2 * C3[2] * x * y * w[11]
               - 6 * C3[3] * x * z * w[12] + C3[4] * (4 * zz - 3 * xx - yy) * w[13]
               + 2 * C3[5] * x * z * w[14] + 3 * C3[6] * (xx - yy) * w[15])
        gy += (3 * C3[0] * (xx - yy) * w[9] + C3[1] * x * z * w[10]
               + C3[2] * (4 * zz - xx - 3 * yy) * w[11] - 6 * C3[3] * y * z * w[12]
               - 2 * C3[4] * x * y * w[13] - 2 * C3[5] * y * z * w[14] - 6 * C3[6] * x * y * w[15])
        gz += (C3[1] * x * y * w[10] + 8 * C3[2] * y * z * w[11]
               + C3[3] * (6 * zz - 3 * xx - 3 * yy) * w[12] + 8 * C3[4] * x * z * w[13]
               + C3[5] * (xx - yy) * w[14])
    return gx, gy, gz


@njit(cache=True, inline="always")
def _unit_dir(mean: np.ndarray, campos: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, |d|) of d = mean - campos, normalised as eval_sh does (norm floored at 1e-12)."""
    dx, dy, dz = mean[0] - campos[0], mean[1] - campos[1], mean[2] - campos[2]
    norm = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-12)
    return dx / norm, dy / norm, dz / norm, norm


@njit(cache=True, inline="always")
def _coef(c0: np.ndarray, cN: np.ndarray, n: int, k: int, ch: int) -> float:
    return c0[n, 0, ch] if k == 0 else cN[n, k - 1, ch]


CHUNK = 256  # Gaussians a task walks with one scratch basis (an allocation per Gaussian costs more)


@njit(cache=True, parallel=True)
def sh_forward(degree: int, means: np.ndarray, c0: np.ndarray, cN: np.ndarray,
               campos: np.ndarray, visible: np.ndarray, colors: np.ndarray) -> None:
    """Fill colors (C, N, 3) = max(SH + 0.5, 0) where ``visible`` (C, N) is set, 0 elsewhere
    (the compositor reads no colour of a Gaussian it does not draw)."""
    N = means.shape[0]
    for chunk in prange((N + CHUNK - 1) // CHUNK):
        basis = np.empty(16)
        for n in range(chunk * CHUNK, min(N, (chunk + 1) * CHUNK)):
            _sh_one(n, degree, means, c0, cN, campos, visible, colors, basis)


@njit(cache=True, inline="always")
def _sh_one(n: int, degree: int, means, c0, cN, campos, visible, colors, basis) -> None:
    nb = (degree + 1) ** 2
    for c in range(campos.shape[0]):
        if not visible[c, n]:
            colors[c, n, 0] = colors[c, n, 1] = colors[c, n, 2] = 0.0
            continue
        x, y, z, _ = _unit_dir(means[n], campos[c])
        _basis(degree, x, y, z, basis)
        for ch in range(3):
            v = 0.5
            for k in range(nb):
                v += basis[k] * _coef(c0, cN, n, k, ch)
            colors[c, n, ch] = max(v, 0.0)


@njit(cache=True, inline="always")
def _sh_vjp_one(n: int, degree: int, means, c0, cN, campos, colors, v_colors, v_means, v_c0,
                v_cN, basis, w) -> None:
    nb = (degree + 1) ** 2
    for c in range(campos.shape[0]):
        if v_colors[c, n, 0] == 0.0 and v_colors[c, n, 1] == 0.0 and v_colors[c, n, 2] == 0.0:
            continue  # adds nothing: most Gaussians are outside a view
        x, y, z, norm = _unit_dir(means[n], campos[c])
        _basis(degree, x, y, z, basis)
        w[:] = 0.0
        for ch in range(3):
            g = v_colors[c, n, ch] if colors[c, n, ch] > 0.0 else 0.0  # clamp at 0
            v_c0[n, 0, ch] += basis[0] * g
            w[0] += c0[n, 0, ch] * g
            for k in range(1, nb):
                v_cN[n, k - 1, ch] += basis[k] * g
                w[k] += cN[n, k - 1, ch] * g
        gx, gy, gz = _basis_vjp(degree, x, y, z, w)
        dot = x * gx + y * gy + z * gz if norm > 1e-12 else 0.0
        v_means[n, 0] += (gx - x * dot) / norm
        v_means[n, 1] += (gy - y * dot) / norm
        v_means[n, 2] += (gz - z * dot) / norm


@njit(cache=True, parallel=True)
def sh_backward(degree: int, means, c0, cN, campos, colors, v_colors, v_means, v_c0, v_cN):
    """Fill v_means (N, 3), v_c0 and v_cN (zeros, the parts' shapes, float32) from v_colors
    (C, N, 3); the coefficients' gradient is accumulated in the dtype torch takes it in."""
    N = means.shape[0]
    for chunk in prange((N + CHUNK - 1) // CHUNK):
        basis, w = np.empty(16), np.zeros(16)
        for n in range(chunk * CHUNK, min(N, (chunk + 1) * CHUNK)):
            _sh_vjp_one(n, degree, means, c0, cN, campos, colors, v_colors, v_means, v_c0, v_cN,
                        basis, w)
