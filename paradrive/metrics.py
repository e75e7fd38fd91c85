"""Image quality metrics in torch: PSNR and SSIM (the 3DGS / Wang et al. 2004 definitions).

Images are float tensors in [0, 1], shaped ``(H, W, 3)`` or ``(B, H, W, 3)`` (channels last,
as renders come out of the rasterizer). Both functions are differentiable; ``ssim`` is also the
D-SSIM term of the fit loss.
"""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F

__all__ = ["psnr", "ssim", "mse", "frames_quality", "peak_rss_mb"]


def _batch(img: torch.Tensor) -> torch.Tensor:
    if img.dim() == 3:
        img = img[None]
    if img.dim() != 4:
        raise ValueError(f"expected (H, W, C) or (B, H, W, C) image, got shape {tuple(img.shape)}")
    return img


def mse(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Mean squared error per image: (B,) for batched input, () for a single image."""
    single = a.dim() == 3
    d = (_batch(a).float() - _batch(b).float()) ** 2
    out = d.flatten(1).mean(1)
    return out[0] if single else out


def psnr(a: torch.Tensor, b: torch.Tensor, max_val: float = 1.0) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB, per image (mean over pixels and channels).

    a, b: (H, W, C) or (B, H, W, C) in [0, max_val]. Returns () or (B,). Identical images give
    a large finite value (the MSE is floored at 1e-10, i.e. 100 dB for max_val 1).
    """
    m = mse(a, b).clamp_min(1e-10)
    return 10.0 * torch.log10(max_val**2 / m)


@functools.lru_cache(maxsize=8)
def _gauss_window(size: int, sigma: float, channels: int) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float32) - (size - 1) / 2.0
    g = torch.exp(-(x**2) / (2 * sigma**2))
    g = g / g.sum()
    w2 = g[:, None] @ g[None, :]
    return w2.expand(channels, 1, size, size).contiguous()


def ssim(a: torch.Tensor, b: torch.Tensor, window: int = 11, sigma: float = 1.5,
         max_val: float = 1.0, reduce: bool = True) -> torch.Tensor:
    """Structural similarity, 11x11 Gaussian window (sigma 1.5), C1=(0.01L)^2, C2=(0.03L)^2.

    a, b: (H, W, C) or (B, H, W, C). Zero padding at the borders ("same" size), as in the
    reference 3DGS code. Returns the mean SSIM per image: () or (B,); with reduce=False the
    SSIM map (B, C, H, W).
    """
    single = a.dim() == 3
    x = _batch(a).float().permute(0, 3, 1, 2)
    y = _batch(b).float().permute(0, 3, 1, 2)
    ch = x.shape[1]
    w = _gauss_window(window, sigma, ch).to(x.device, x.dtype)
    pad = window // 2
    mu_x = F.conv2d(x, w, padding=pad, groups=ch)
    mu_y = F.conv2d(y, w, padding=pad, groups=ch)
    sxx = F.conv2d(x * x, w, padding=pad, groups=ch) - mu_x**2
    syy = F.conv2d(y * y, w, padding=pad, groups=ch) - mu_y**2
    sxy = F.conv2d(x * y, w, padding=pad, groups=ch) - mu_x * mu_y
    c1 = (0.01 * max_val) ** 2
    c2 = (0.03 * max_val) ** 2
    smap = ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (sxx + syy + c2))
    if not reduce:
        return smap
    out = smap.flatten(1).mean(1)
    return out[0] if single else out


def peak_rss_mb() -> float:
    """The process's peak resident memory so far, MiB (Linux reports KiB)."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def frames_quality(a, b) -> tuple[float, float]:
    """Mean PSNR (dB) and SSIM over frames of two uint8 (N, H, W, 3) arrays (the shorter length)."""
    import numpy as np

    n = min(len(a), len(b))
    x = torch.from_numpy(np.ascontiguousarray(a[:n])).float() / 255.0
    y = torch.from_numpy(np.ascontiguousarray(b[:n])).float() / 255.0
    with torch.no_grad():
        return float(psnr(x, y).mean()), float(ssim(x, y).mean())
