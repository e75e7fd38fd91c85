"""Real spherical harmonics of bands 0..3 (the 3DGS convention): the constants, their evaluation
in torch, and the colour of a Gaussian seen from a camera. The torch rasterizer and the fused
CPU kernels share these."""

from __future__ import annotations

import torch
from torch import Tensor

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
          -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
          -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def eval_sh(degree: int, coeffs: Tensor, dirs: Tensor) -> Tensor:
    """Evaluate real SH of bands 0..degree.

    coeffs: (..., K, 3) with K >= (degree+1)^2; dirs: (..., 3) view directions (need not be unit).
    Returns (..., 3), without the +0.5 offset.
    """
    if not 0 <= degree <= 3:
        raise ValueError(f"sh_degree={degree} is not supported; use 0..3")
    if coeffs.shape[-2] < (degree + 1) ** 2:
        raise ValueError(f"sh_degree={degree} needs {(degree + 1) ** 2} coefficients per Gaussian, "
                         f"got colors of shape {tuple(coeffs.shape)}")
    out = SH_C0 * coeffs[..., 0, :]
    if degree == 0:
        return out
    d = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    x, y, z = (d[..., i:i + 1] for i in range(3))
    out = out + SH_C1 * (-y * coeffs[..., 1, :] + z * coeffs[..., 2, :] - x * coeffs[..., 3, :])
    if degree == 1:
        return out
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    out = (out
           + SH_C2[0] * xy * coeffs[..., 4, :]
           + SH_C2[1] * yz * coeffs[..., 5, :]
           + SH_C2[2] * (2.0 * zz - xx - yy) * coeffs[..., 6, :]
           + SH_C2[3] * xz * coeffs[..., 7, :]
           + SH_C2[4] * (xx - yy) * coeffs[..., 8, :])
    if degree == 2:
        return out
    return (out
            + SH_C3[0] * y * (3.0 * xx - yy) * coeffs[..., 9, :]
            + SH_C3[1] * xy * z * coeffs[..., 10, :]
            + SH_C3[2] * y * (4.0 * zz - xx - yy) * coeffs[..., 11, :]
            + SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * coeffs[..., 12, :]
            + SH_C3[4] * x * (4.0 * zz - xx - yy) * coeffs[..., 13, :]
            + SH_C3[5] * z * (xx - yy) * coeffs[..., 14, :]
            + SH_C3[6] * x * (xx - 3.0 * yy) * coeffs[..., 15, :])


def shade(sh_degree: int, means: Tensor, coeffs: Tensor, campos: Tensor) -> Tensor:
    """(C, N, 3) colours max(SH(mean - campos) + 0.5, 0); coeffs (N, K, 3) or (C, N, K, 3)."""
    C = campos.shape[0]
    dirs = means[None] - campos[:, None, :]  # (C, N, 3)
    coeffs = coeffs.expand((C,) + coeffs.shape) if coeffs.dim() == 3 else coeffs
    return torch.clamp_min(eval_sh(sh_degree, coeffs, dirs) + 0.5, 0.0)
