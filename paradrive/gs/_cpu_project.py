"""Numba kernels of the fused CPU rasterizer: EWA projection and its gradient.

The maths is ``rasterize._project`` written per Gaussian: one thread owns a Gaussian and walks
the cameras in order, so results do not depend on the thread count. float64 inside, float32 out.
Small matrices are row-major tuples (3x3 -> 9 values), which stay in registers: heap-allocated
arrays per Gaussian would cost more than the arithmetic.

Shapes: means (N, 3), quats (N, 4) wxyz any norm, scales (N, 3), opacities (N,),
viewmats (C, 4, 4) world-to-camera, Ks (C, 3, 3); outputs are (C, N, ...).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from paradrive.gs._cpu_kernels import ALPHA_MIN

RADIUS_SIGMAS = 3.33  # as rasterize._project: the opacity-aware box is capped at 3.33 sigma

Mat3 = tuple[float, float, float, float, float, float, float, float, float]
Vec3 = tuple[float, float, float]


@njit(cache=True, inline="always")
def _mul(A: Mat3, B: Mat3) -> Mat3:
    return (A[0] * B[0] + A[1] * B[3] + A[2] * B[6], A[0] * B[1] + A[1] * B[4] + A[2] * B[7],
            A[0] * B[2] + A[1] * B[5] + A[2] * B[8], A[3] * B[0] + A[4] * B[3] + A[5] * B[6],
            A[3] * B[1] + A[4] * B[4] + A[5] * B[7], A[3] * B[2] + A[4] * B[5] + A[5] * B[8],
            A[6] * B[0] + A[7] * B[3] + A[8] * B[6], A[6] * B[1] + A[7] * B[4] + A[8] * B[7],
            A[6] * B[2] + A[7] * B[5] + A[8] * B[8])


@njit(cache=True, inline="always")
def _tr(A: Mat3) -> Mat3:
    return (A[0], A[3], A[6], A[1], A[4], A[7], A[2], A[5], A[8])


@njit(cache=True, inline="always")
def _mv(A: Mat3, v: Vec3) -> Vec3:
    return (A[0] * v[0] + A[1] * v[1] + A[2] * v[2], A[3] * v[0] + A[4] * v[1] + A[5] * v[2],
            A[6] * v[0] + A[7] * v[1] + A[8] * v[2])


@njit(cache=True)
def _rotmat(q: np.ndarray) -> tuple[Mat3, tuple[float, float, float, float], float]:
    """(R, unit quaternion, norm) of a wxyz quaternion of any norm."""
    norm = max(math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]), 1e-12)
    w, x, y, z = q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm
    R = (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
         2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
         2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y))
    return R, (w, x, y, z), norm


@njit(cache=True)
def _rotmat_vjp(v: Mat3, qn: tuple[float, float, float, float], norm: float, out: np.ndarray) -> None:
    """out (4,) = gradient of the raw quaternion from the gradient v of its rotation matrix."""
    w, x, y, z = qn
    g0 = 2 * (-z * v[1] + y * v[2] + z * v[3] - x * v[5] - y * v[6] + x * v[7])
    g1 = 2 * (y * v[1] + z * v[2] + y * v[3] - 2 * x * v[4] - w * v[5] + z * v[6] + w * v[7]
              - 2 * x * v[8])
    g2 = 2 * (-2 * y * v[0] + x * v[1] + w * v[2] + x * v[3] + z * v[5] - w * v[6] + z * v[7]
              - 2 * y * v[8])
    g3 = 2 * (-2 * z * v[0] - w * v[1] + x * v[2] + w * v[3] - 2 * z * v[4] + y * v[5] + x * v[6]
              + y * v[7])
    # through q / max(|q|, 1e-12); the floor passes no gradient to the norm
    dot = (w * g0 + x * g1 + y * g2 + z * g3) if norm > 1e-12 else 0.0
    out[0], out[1], out[2], out[3] = ((g0 - w * dot) / norm, (g1 - x * dot) / norm,
                                      (g2 - y * dot) / norm, (g3 - z * dot) / norm)


@njit(cache=True)
def _covariance(q: np.ndarray, s: np.ndarray) -> tuple[Mat3, Mat3, Mat3]:
    """(cov3 = M M^T, M = R diag(s), R)."""
    R = _rotmat(q)[0]
    M = (R[0] * s[0], R[1] * s[1], R[2] * s[2], R[3] * s[0], R[4] * s[1], R[5] * s[2],
         R[6] * s[0], R[7] * s[1], R[8] * s[2])
    return _mul(M, _tr(M)), M, R


@njit(cache=True)
def _camera_space(mean: Vec3, cov3: Mat3, view: np.ndarray) -> tuple[Vec3, Mat3, Mat3]:
    """(camera-space mean, camera-space covariance, the view's rotation Rv)."""
    Rv = (view[0, 0], view[0, 1], view[0, 2], view[1, 0], view[1, 1], view[1, 2],
          view[2, 0], view[2, 1], view[2, 2])
    m = _mv(Rv, mean)
    mc = (m[0] + view[0, 3], m[1] + view[1, 3], m[2] + view[2, 3])
    return mc, _mul(_mul(Rv, cov3), _tr(Rv)), Rv


@njit(cache=True)
def _jacobian(mc: Vec3, K: np.ndarray, width: int, height: int, near: float, far: float):
    """(zs, in depth, clamped x / z, x clamped, clamped y / z, y clamped).

    As 3DGS: the view direction in the Jacobian J = [[fx/zs, 0, -fx tx/zs], [0, fy/zs, -fy ty/zs]]
    is clamped to 1.3x the field of view; a Gaussian outside the depth range gets the stand-in
    depth zs = 1 so nothing downstream is inf or nan.
    """
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    in_depth = near < mc[2] < far
    zs = mc[2] if in_depth else 1.0
    rx, ry = mc[0] / zs, mc[1] / zs
    tx = max(min(rx, (width - cx) / fx + 0.15 * width / fx), -(cx / fx + 0.15 * width / fx))
    ty = max(min(ry, (height - cy) / fy + 0.15 * height / fy), -(cy / fy + 0.15 * height / fy))
    return zs, in_depth, tx, tx != rx, ty, ty != ry


@njit(cache=True, inline="always")
def _cov2(S: Mat3, j00: float, j02: float, j11: float, j12: float) -> Vec3:
    """(c00, c11, c01) of J S J^T, J = [[j00, 0, j02], [0, j11, j12]]."""
    c00 = j00 * j00 * S[0] + 2 * j00 * j02 * S[2] + j02 * j02 * S[8]
    c11 = j11 * j11 * S[4] + 2 * j11 * j12 * S[5] + j12 * j12 * S[8]
    c01 = j00 * j11 * S[1] + j00 * j12 * S[2] + j02 * j11 * S[5] + j02 * j12 * S[8]
    return c00, c11, c01


@njit(cache=True)
def _project_one(mean, cov3, opacity, view, K, width, height, near, far, eps2d, radius_clip,
                 out2d, outconic, outdepth, outradii):
    mc, S, _ = _camera_space(mean, cov3, view)
    zs, in_depth, tx, _, ty, _ = _jacobian(mc, K, width, height, near, far)
    fx, fy = K[0, 0], K[1, 1]
    c00, c11, c01 = _cov2(S, fx / zs, -fx * tx / zs, fy / zs, -fy * ty / zs)
    c00 += eps2d
    c11 += eps2d
    det = c00 * c11 - c01 * c01
    d = max(det, 1e-10)
    outconic[0], outconic[1], outconic[2] = c11 / d, -c01 / d, c00 / d
    u = fx * mc[0] / zs + K[0, 2]
    v = fy * mc[1] / zs + K[1, 2]
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
        mean = (means[n, 0], means[n, 1], means[n, 2])
        for c in range(viewmats.shape[0]):
            _project_one(mean, cov3, opacities[n], viewmats[c], Ks[c], width, height, near, far,
                         eps2d, radius_clip, means2d[c, n], conics[c, n], depths[c, n], radii[c, n])


@njit(cache=True)
def _cov2_vjp(c00: float, c11: float, c01: float, v_conic: np.ndarray) -> Vec3:
    """(g00, g11, g01): the gradient of J S J^T (symmetric, g01 on each off-diagonal entry)
    from the conic's gradient; c00 and c11 include eps2d."""
    det = c00 * c11 - c01 * c01
    d = max(det, 1e-10)
    va, vb, vc = v_conic[0], v_conic[1], v_conic[2]
    v00, v11, v01 = vc / d, va / d, -vb / d
    if det > 1e-10:  # the clamp passes no gradient
        v_d = -(va * c11 - vb * c01 + vc * c00) / (d * d)
        v00 += v_d * c11
        v11 += v_d * c00
        v01 -= 2.0 * v_d * c01
    return v00, v11, 0.5 * v01


@njit(cache=True, inline="always")
def _sym_outer(g00: float, g11: float, g01: float, r0: Vec3, r1: Vec3) -> Mat3:
    """J^T G J for J with rows r0, r1 and G = [[g00, g01], [g01, g11]]."""
    return (g00 * r0[0] * r0[0] + 2 * g01 * r0[0] * r1[0] + g11 * r1[0] * r1[0],
            g00 * r0[0] * r0[1] + g01 * (r0[0] * r1[1] + r1[0] * r0[1]) + g11 * r1[0] * r1[1],
            g00 * r0[0] * r0[2] + g01 * (r0[0] * r1[2] + r1[0] * r0[2]) + g11 * r1[0] * r1[2],
            g00 * r0[1] * r0[0] + g01 * (r0[1] * r1[0] + r1[1] * r0[0]) + g11 * r1[1] * r1[0],
            g00 * r0[1] * r0[1] + 2 * g01 * r0[1] * r1[1] + g11 * r1[1] * r1[1],
            g00 * r0[1] * r0[2] + g01 * (r0[1] * r1[2] + r1[1] * r0[2]) + g11 * r1[1] * r1[2],
            g00 * r0[2] * r0[0] + g01 * (r0[2] * r1[0] + r1[2] * r0[0]) + g11 * r1[2] * r1[0],
            g00 * r0[2] * r0[1] + g01 * (r0[2] * r1[1] + r1[2] * r0[1]) + g11 * r1[2] * r1[1],
            g00 * r0[2] * r0[2] + 2 * g01 * r0[2] * r1[2] + g11 * r1[2] * r1[2])


@njit(cache=True)
def _backward_one(mean, cov3, view, K, width, height, near, far, eps2d, v2d, v_conic, v_depth
                  ) -> tuple[Vec3, Mat3]:
    """One camera's share of (v_mean, v_cov3)."""
    mc, S, Rv = _camera_space(mean, cov3, view)
    zs, in_depth, tx, clx, ty, cly = _jacobian(mc, K, width, height, near, far)
    fx, fy = K[0, 0], K[1, 1]
    r0 = (fx / zs, 0.0, -fx * tx / zs)
    r1 = (0.0, fy / zs, -fy * ty / zs)
    c00, c11, c01 = _cov2(S, r0[0], r0[2], r1[1], r1[2])
    g00, g11, g01 = _cov2_vjp(c00 + eps2d, c11 + eps2d, c01, v_conic)
    v_S = _sym_outer(g00, g11, g01, r0, r1)
    # v_J = 2 G J S, rows r_i S
    u0, u1 = _mv(S, r0), _mv(S, r1)  # S is symmetric: r S = S r
    vj00 = 2 * (g00 * u0[0] + g01 * u1[0])
    vj02 = 2 * (g00 * u0[2] + g01 * u1[2])
    vj11 = 2 * (g01 * u0[1] + g11 * u1[1])
    vj12 = 2 * (g01 * u0[2] + g11 * u1[2])
    z2 = zs * zs
    v_x = v2d[0] * fx / zs
    v_y = v2d[1] * fy / zs
    v_zs = -(v2d[0] * fx * mc[0] + v2d[1] * fy * mc[1]) / z2
    v_zs += (-vj00 * fx - vj11 * fy + vj02 * fx * tx + vj12 * fy * ty) / z2
    if not clx:  # tx = x / zs
        v_x -= vj02 * fx / z2
        v_zs += vj02 * fx * tx / z2
    if not cly:
        v_y -= vj12 * fy / z2
        v_zs += vj12 * fy * ty / z2
    v_z = v_depth + (v_zs if in_depth else 0.0)
    RvT = _tr(Rv)
    return _mv(RvT, (v_x, v_y, v_z)), _mul(_mul(RvT, v_S), Rv)


@njit(cache=True, inline="always")
def _no_gradient(v2d: np.ndarray, v_conic: np.ndarray, v_depth: float) -> bool:
    """True when a camera passes a Gaussian no gradient (its share would be exact zeros)."""
    return (v2d[0] == 0.0 and v2d[1] == 0.0 and v_conic[0] == 0.0 and v_conic[1] == 0.0
            and v_conic[2] == 0.0 and v_depth == 0.0)


@njit(cache=True)
def _gaussian_vjp(n, means, quats, scales, viewmats, Ks, width, height, near, far, eps2d,
                  v_means2d, v_conics, v_depths, v_means, v_quats, v_scales) -> None:
    """Row n of v_means, v_quats, v_scales, cameras summed in order."""
    used = False
    for c in range(viewmats.shape[0]):
        used |= not _no_gradient(v_means2d[c, n], v_conics[c, n], v_depths[c, n, 0])
    if not used:  # its rows stay 0: most Gaussians are outside a view
        return
    cov3, M, R = _covariance(quats[n], scales[n])
    mean = (means[n, 0], means[n, 1], means[n, 2])
    vm = (0.0, 0.0, 0.0)
    vc = (0.0,) * 9
    for c in range(viewmats.shape[0]):
        if _no_gradient(v_means2d[c, n], v_conics[c, n], v_depths[c, n, 0]):
            continue
        dm, dc = _backward_one(mean, cov3, viewmats[c], Ks[c], width, height, near, far, eps2d,
                               v_means2d[c, n], v_conics[c, n], v_depths[c, n, 0])
        vm = (vm[0] + dm[0], vm[1] + dm[1], vm[2] + dm[2])
        vc = (vc[0] + dc[0], vc[1] + dc[1], vc[2] + dc[2], vc[3] + dc[3], vc[4] + dc[4],
              vc[5] + dc[5], vc[6] + dc[6], vc[7] + dc[7], vc[8] + dc[8])
    v_means[n, 0], v_means[n, 1], v_means[n, 2] = vm
    vs = (vc[0] + vc[0], vc[1] + vc[3], vc[2] + vc[6], vc[3] + vc[1], vc[4] + vc[4],
          vc[5] + vc[7], vc[6] + vc[2], vc[7] + vc[5], vc[8] + vc[8])
    v_M = _mul(vs, M)  # d(M M^T) = (V + V^T) M
    s = scales[n]
    for j in range(3):
        v_scales[n, j] = v_M[j] * R[j] + v_M[3 + j] * R[3 + j] + v_M[6 + j] * R[6 + j]
    v_R = (v_M[0] * s[0], v_M[1] * s[1], v_M[2] * s[2], v_M[3] * s[0], v_M[4] * s[1],
           v_M[5] * s[2], v_M[6] * s[0], v_M[7] * s[1], v_M[8] * s[2])
    _, qn, norm = _rotmat(quats[n])
    _rotmat_vjp(v_R, qn, norm, v_quats[n])


@njit(cache=True, parallel=True)
def project_backward(means, quats, scales, viewmats, Ks, width, height, near, far, eps2d,
                     v_means2d, v_conics, v_depths):
    """(v_means (N, 3), v_quats (N, 4), v_scales (N, 3)) float64 from (C, N, ...) gradients."""
    N = means.shape[0]
    v_means = np.zeros((N, 3))
    v_quats = np.zeros((N, 4))
    v_scales = np.zeros((N, 3))
    for n in prange(N):
        _gaussian_vjp(n, means, quats, scales, viewmats, Ks, width, height, near, far, eps2d,
                      v_means2d, v_conics, v_depths, v_means, v_quats, v_scales)
    return v_means, v_quats, v_scales
