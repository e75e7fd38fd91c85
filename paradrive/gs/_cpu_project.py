"""Numba kernels of the fused CPU rasterizer: EWA projection and its gradient.

The maths is ``rasterize._project`` written per Gaussian: one thread owns a Gaussian and walks
the cameras in order, so results do not depend on the thread count. float64 inside, float32 out.

Shapes: means (N, 3), quats (N, 4) wxyz any norm, scales (N, 3), opacities (N,),
viewmats (C, 4, 4) world-to-camera, Ks (C, 3, 3); outputs are (C, N, ...).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from paradrive.gs._cpu_kernels import ALPHA_MIN

RADIUS_SIGMAS = 3.33  # as rasterize._project: the opacity-aware box is capped at 3.33 sigma


@njit(cache=True)
def _mm(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """The matrix product of two small matrices (Numba's own needs SciPy's BLAS)."""
    out = np.zeros((A.shape[0], B.shape[1]))
    for i in range(A.shape[0]):
        for k in range(A.shape[1]):
            for j in range(B.shape[1]):
                out[i, j] += A[i, k] * B[k, j]
    return out


@njit(cache=True)
def _mv(A: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The product of a small matrix and a vector."""
    out = np.zeros(A.shape[0])
    for i in range(A.shape[0]):
        for k in range(A.shape[1]):
            out[i] += A[i, k] * v[k]
    return out


@njit(cache=True)
def _rotmat(q: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(R (3, 3), unit quaternion (4,), norm) of a wxyz quaternion of any norm."""
    norm = max(math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]), 1e-12)
    w, x, y, z = q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm
    R = np.empty((3, 3))
    R[0, 0], R[0, 1], R[0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    R[1, 0], R[1, 1], R[1, 2] = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    R[2, 0], R[2, 1], R[2, 2] = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
    return R, np.array([w, x, y, z]), norm


@njit(cache=True)
def _rotmat_vjp(v_R: np.ndarray, qn: np.ndarray, norm: float) -> np.ndarray:
    """Gradient of the raw quaternion from the gradient of its rotation matrix."""
    w, x, y, z = qn[0], qn[1], qn[2], qn[3]
    g = np.empty(4)
    g[0] = 2 * (-z * v_R[0, 1] + y * v_R[0, 2] + z * v_R[1, 0] - x * v_R[1, 2]
                - y * v_R[2, 0] + x * v_R[2, 1])
    g[1] = 2 * (y * v_R[0, 1] + z * v_R[0, 2] + y * v_R[1, 0] - 2 * x * v_R[1, 1]
                - w * v_R[1, 2] + z * v_R[2, 0] + w * v_R[2, 1] - 2 * x * v_R[2, 2])
    g[2] = 2 * (-2 * y * v_R[0, 0] + x * v_R[0, 1] + w * v_R[0, 2] + x * v_R[1, 0]
                + z * v_R[1, 2] - w * v_R[2, 0] + z * v_R[2, 1] - 2 * y * v_R[2, 2])
    g[3] = 2 * (-2 * z * v_R[0, 0] - w * v_R[0, 1] + x * v_R[0, 2] + w * v_R[1, 0]
                - 2 * z * v_R[1, 1] + y * v_R[1, 2] + x * v_R[2, 0] + y * v_R[2, 1])
    # through q / |q| (the 1e-12 floor passes no gradient to the norm)
    return (g - qn * np.sum(qn * g)) / norm if norm > 1e-12 else g / norm


@njit(cache=True)
def _camera_frame(mean: np.ndarray, cov3: np.ndarray, view: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(camera-space mean (3,), covariance (3, 3), rotation (3, 3))."""
    Rv = view[:3, :3].astype(np.float64)
    mc = _mv(Rv, mean) + view[:3, 3].astype(np.float64)
    return mc, _mm(_mm(Rv, cov3), Rv.T), Rv


@njit(cache=True)
def _jacobian(mc: np.ndarray, K: np.ndarray, width: int, height: int, near: float, far: float
              ) -> tuple[np.ndarray, float, bool, bool, float, bool, float]:
    """(J (2, 3), stand-in depth zs, in depth, x clamped, clamp x, y clamped, clamp y).

    As 3DGS: the view direction in J is clamped to 1.3x the field of view; a Gaussian outside
    the depth range gets zs = 1 so nothing downstream is inf or nan.
    """
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    in_depth = near < mc[2] < far
    zs = mc[2] if in_depth else 1.0
    lim_xp = (width - cx) / fx + 0.3 * (0.5 * width / fx)
    lim_xn = cx / fx + 0.3 * (0.5 * width / fx)
    lim_yp = (height - cy) / fy + 0.3 * (0.5 * height / fy)
    lim_yn = cy / fy + 0.3 * (0.5 * height / fy)
    rx, ry = mc[0] / zs, mc[1] / zs
    cl_x, cl_y = max(min(rx, lim_xp), -lim_xn), max(min(ry, lim_yp), -lim_yn)
    J = np.zeros((2, 3))
    J[0, 0], J[0, 2] = fx / zs, -fx * cl_x / zs
    J[1, 1], J[1, 2] = fy / zs, -fy * cl_y / zs
    return J, zs, in_depth, cl_x != rx, cl_x, cl_y != ry, cl_y


@njit(cache=True)
def _covariance(q: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                        np.ndarray, float]:
    """(cov3 (3, 3), M = R diag(s), R, unit quaternion, quaternion norm)."""
    R, qn, norm = _rotmat(q)
    M = R * s.astype(np.float64)[None, :]
    return _mm(M, M.T), M, R, qn, norm


@njit(cache=True)
def _project_one(mean, cov3, opacity, view, K, width, height, near, far, eps2d, radius_clip,
                 out2d, outconic, outdepth, outradii):
    mc, covc, _ = _camera_frame(mean, cov3, view)
    J, zs, in_depth, _, _, _, _ = _jacobian(mc, K, width, height, near, far)
    cov2 = _mm(_mm(J, covc), J.T)
    c00, c11 = cov2[0, 0] + eps2d, cov2[1, 1] + eps2d
    c01 = 0.5 * (cov2[0, 1] + cov2[1, 0])
    det = c00 * c11 - c01 * c01
    d = max(det, 1e-10)
    outconic[0], outconic[1], outconic[2] = c11 / d, -c01 / d, c00 / d
    u = K[0, 0] * mc[0] / zs + K[0, 2]
    v = K[1, 1] * mc[1] / zs + K[1, 2]
    out2d[0], out2d[1] = u, v
    outdepth[0] = mc[2]
    extend = min(math.sqrt(2.0 * math.log(max(opacity / ALPHA_MIN, 1.0))), RADIUS_SIGMAS)
    rx = math.ceil(extend * math.sqrt(max(c00, 0.0)))
    ry = math.ceil(extend * math.sqrt(max(c11, 0.0)))
    ok = (in_depth and det > 0 and opacity >= ALPHA_MIN and rx > 0 and ry > 0
          and not (rx <= radius_clip and ry <= radius_clip)
          and u + rx > 0 and u - rx < width and v + ry > 0 and v - ry < height)
    outradii[0], outradii[1] = (rx, ry) if ok else (0, 0)


@njit(cache=True, parallel=True)
def project_forward(means, quats, scales, opacities, viewmats, Ks, width, height, near, far,
                    eps2d, radius_clip, means2d, conics, depths, radii):
    """Fill means2d (C, N, 2), conics (C, N, 3), depths (C, N, 1), radii (C, N, 2) int32."""
    for n in prange(means.shape[0]):
        cov3 = _covariance(quats[n], scales[n])[0]
        mean = means[n].astype(np.float64)
        for c in range(viewmats.shape[0]):
            _project_one(mean, cov3, opacities[n], viewmats[c], Ks[c].astype(np.float64),
                         width, height, near, far, eps2d, radius_clip, means2d[c, n], conics[c, n],
                         depths[c, n], radii[c, n])


@njit(cache=True)
def _cov2_vjp(cov2: np.ndarray, eps2d: float, v_conic: np.ndarray) -> np.ndarray:
    """Gradient of the 2D covariance J cov J^T (2, 2) from the conic's gradient."""
    c00, c11 = cov2[0, 0] + eps2d, cov2[1, 1] + eps2d
    c01 = 0.5 * (cov2[0, 1] + cov2[1, 0])
    det = c00 * c11 - c01 * c01
    d = max(det, 1e-10)
    va, vb, vc = v_conic[0], v_conic[1], v_conic[2]
    v00, v11, v01 = vc / d, va / d, -vb / d
    if det > 1e-10:  # the clamp passes no gradient
        v_d = -(va * c11 - vb * c01 + vc * c00) / (d * d)
        v00 += v_d * c11
        v11 += v_d * c00
        v01 -= 2.0 * v_d * c01
    G = np.empty((2, 2))
    G[0, 0], G[1, 1], G[0, 1], G[1, 0] = v00, v11, 0.5 * v01, 0.5 * v01
    return G


@njit(cache=True)
def _backward_one(mean, cov3, view, K, width, height, near, far, eps2d, v2d, v_conic, v_depth,
                  v_mean, v_cov3):
    """Add one camera's share to v_mean (3,) and v_cov3 (3, 3)."""
    mc, covc, Rv = _camera_frame(mean, cov3, view)
    J, zs, in_depth, clx, tx, cly, ty = _jacobian(mc, K, width, height, near, far)
    fx, fy = K[0, 0], K[1, 1]
    G = _cov2_vjp(_mm(_mm(J, covc), J.T), eps2d, v_conic)
    v_covc = _mm(_mm(J.T, G), J)
    v_J = 2.0 * _mm(_mm(G, J), covc)
    v_mc = np.zeros(3)
    v_mc[0] = v2d[0] * fx / zs
    v_mc[1] = v2d[1] * fy / zs
    v_zs = -(v2d[0] * fx * mc[0] + v2d[1] * fy * mc[1]) / (zs * zs)
    # J = [[fx/zs, 0, -fx tx/zs], [0, fy/zs, -fy ty/zs]] with tx = x/zs unless clamped
    v_zs -= (v_J[0, 0] * fx + v_J[1, 1] * fy) / (zs * zs)
    v_zs += (v_J[0, 2] * fx * tx + v_J[1, 2] * fy * ty) / (zs * zs)
    if not clx:  # J02 = -fx x / zs²
        v_mc[0] -= v_J[0, 2] * fx / (zs * zs)
        v_zs += v_J[0, 2] * fx * tx / (zs * zs)
    if not cly:
        v_mc[1] -= v_J[1, 2] * fy / (zs * zs)
        v_zs += v_J[1, 2] * fy * ty / (zs * zs)
    if in_depth:
        v_mc[2] += v_zs
    v_mc[2] += v_depth
    v_mean[:] += _mv(Rv.T, v_mc)
    v_cov3[:] += _mm(_mm(Rv.T, v_covc), Rv)


@njit(cache=True)
def _gaussian_vjp(mean, quat, scale, viewmats, Ks, width, height, near, far, eps2d, v2d, v_conic,
                  v_depth):
    """(v_mean (3,), v_quat (4,), v_scale (3,)) of one Gaussian, cameras summed in order."""
    cov3, M, R, qn, norm = _covariance(quat, scale)
    mean = mean.astype(np.float64)
    v_mean = np.zeros(3)
    v_cov3 = np.zeros((3, 3))
    for c in range(viewmats.shape[0]):
        _backward_one(mean, cov3, viewmats[c], Ks[c].astype(np.float64), width, height, near,
                      far, eps2d, v2d[c], v_conic[c], v_depth[c], v_mean, v_cov3)
    v_M = _mm(v_cov3 + v_cov3.T, M)
    v_scale = (v_M * R).sum(axis=0)
    v_quat = _rotmat_vjp(v_M * scale.astype(np.float64)[None, :], qn, norm)
    return v_mean, v_quat, v_scale


@njit(cache=True, parallel=True)
def project_backward(means, quats, scales, viewmats, Ks, width, height, near, far, eps2d,
                     v_means2d, v_conics, v_depths):
    """(v_means (N, 3), v_quats (N, 4), v_scales (N, 3)) float64 from (C, N, ...) gradients."""
    N = means.shape[0]
    v_means = np.zeros((N, 3))
    v_quats = np.zeros((N, 4))
    v_scales = np.zeros((N, 3))
    for n in prange(N):
        v_means[n], v_quats[n], v_scales[n] = _gaussian_vjp(
            means[n], quats[n], scales[n], viewmats, Ks, width, height, near, far, eps2d,
            v_means2d[:, n], v_conics[:, n], v_depths[:, n, 0])
    return v_means, v_quats, v_scales
