"""Image quality metrics in torch: PSNR and SSIM (the 3DGS / Wang et al. 2004 definitions).

Images are float tensors in [0, 1], shaped ``(H, W, 3)`` or ``(B, H, W, 3)`` (channels last,
as renders come out of the rasterizer). Both functions are differentiable; ``ssim`` is also the
D-SSIM term of the fit loss. Its mean runs in the native kernels (``paradrive.kernels``) for float32
images on the CPU (where the library builds; ``PARADRIVE_KERNELS``), in torch operations
elsewhere.
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
def _gauss_taps(size: int, sigma: float) -> torch.Tensor:
    """The normalised 1-D Gaussian (size,) on the CPU; the 2-D window is its outer product."""
    x = torch.arange(size, dtype=torch.float32, device="cpu") - (size - 1) / 2.0
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def _blur(x: torch.Tensor, taps: torch.Tensor) -> torch.Tensor:
    """Each channel of x (B, C, H, W) filtered by the separable Gaussian, zero padding, same
    size. The window is symmetric, so this is also its own adjoint (the gradient's filter)."""
    n, k = x.shape[1], taps.shape[0]
    pad = k // 2
    x = F.conv2d(x, taps.view(1, 1, k, 1).expand(n, 1, k, 1), padding=(pad, 0), groups=n)
    return F.conv2d(x, taps.view(1, 1, 1, k).expand(n, 1, 1, k), padding=(0, pad), groups=n)


def _ssim_terms(x: torch.Tensor, y: torch.Tensor, taps: torch.Tensor, c1: float, c2: float
                ) -> tuple[torch.Tensor, ...]:
    """(SSIM map, its four factors A, B, C, D, mu_x, mu_y) for x, y (B, C, H, W):
    SSIM = A B / (C D), A = 2 mu_x mu_y + c1, B = 2 s_xy + c2, C = mu_x^2 + mu_y^2 + c1,
    D = s_xx + s_yy + c2, every moment blurred by the Gaussian window."""
    ch = x.shape[1]
    mu_x, mu_y, xx, yy, xy = _blur(torch.cat([x, y, x * x, y * y, x * y], dim=1), taps).split(ch, 1)
    A = 2 * mu_x * mu_y + c1
    B = 2 * (xy - mu_x * mu_y) + c2
    C = mu_x**2 + mu_y**2 + c1
    D = (xx - mu_x**2) + (yy - mu_y**2) + c2
    return A * B / (C * D), A, B, C, D, mu_x, mu_y


class _MeanSSIM(torch.autograd.Function):
    """Mean SSIM per image with its gradient in closed form: the map's derivatives with respect
    to the blurred moments mu_x, E[x^2] and E[xy], blurred back (the window is self-adjoint) and
    combined per pixel. Two filterings instead of autograd through five. No gradient to y."""

    @staticmethod
    def forward(ctx, x, y, taps, c1: float, c2: float):
        smap, A, B, C, D, mu_x, mu_y = _ssim_terms(x, y, taps, c1, c2)
        n = smap[0].numel()
        CD = C * D
        # dS/dmu_x, dS/dE[x^2], dS/dE[xy], each over the pixel count of the mean
        d_mu = (2 * mu_y * (B - A) / CD - 2 * mu_x * smap * (1 / C - 1 / D)) / n
        d_xx = -smap / D / n
        d_xy = 2 * A / CD / n
        ctx.save_for_backward(x, y, taps, d_mu, d_xx, d_xy)
        return smap.flatten(1).mean(1)

    @staticmethod
    def backward(ctx, grad):
        x, y, taps, d_mu, d_xx, d_xy = ctx.saved_tensors
        ch = x.shape[1]
        g_mu, g_xx, g_xy = _blur(torch.cat([d_mu, d_xx, d_xy], dim=1), taps).split(ch, 1)
        g = (g_mu + 2 * x * g_xx + y * g_xy) * grad.view(-1, 1, 1, 1)
        return g, None, None, None, None


class _NativeMeanSSIM(torch.autograd.Function):
    """:class:`_MeanSSIM` in the native kernels (``paradrive.kernels``) (CPU float32 images): one
    pass over each row computes the moments, the map and its derivatives; the backward blurs
    those back. x, y are (B, H, W, C) contiguous; the bytes do not depend on the thread count."""

    @staticmethod
    def forward(ctx, x, y, taps, c1: float, c2: float, kernels):
        from paradrive.devices import cpu_kernel_threads

        xn, yn, tn = x.detach().numpy(), y.detach().numpy(), taps.numpy()
        mean, d = kernels.ssim_forward(xn, yn, tn, c1, c2, ctx.needs_input_grad[0],
                                       cpu_kernel_threads())
        ctx.kernels, ctx.d = kernels, d
        ctx.save_for_backward(x, y, taps)
        return torch.from_numpy(mean.astype("float32"))

    @staticmethod
    def backward(ctx, grad):
        from paradrive.devices import cpu_kernel_threads

        x, y, taps = ctx.saved_tensors
        g = ctx.kernels.ssim_backward(x.detach().numpy(), y.numpy(), ctx.d, taps.numpy(),
                                      grad.detach().float().contiguous().numpy(),
                                      cpu_kernel_threads())
        return torch.from_numpy(g), None, None, None, None, None


# The widest window the native kernels take (their column pass keeps 32 rows).
NATIVE_MAX_WINDOW = 31


def _native_kernels(x: torch.Tensor):
    """The native kernels where they take these images (float32 on the CPU, the library built),
    else None: the torch operations run."""
    if x.device.type != "cpu" or x.dtype != torch.float32:
        return None
    from paradrive import kernels

    return kernels.load()


def ssim_window(window: int = 11, sigma: float = 1.5,
                max_val: float = 1.0) -> tuple[torch.Tensor, float, float]:
    """The SSIM's separable window taps (window,) on the CPU and its constants C1, C2."""
    return _gauss_taps(window, sigma), (0.01 * max_val) ** 2, (0.03 * max_val) ** 2


def ssim(a: torch.Tensor, b: torch.Tensor, window: int = 11, sigma: float = 1.5,
         max_val: float = 1.0, reduce: bool = True) -> torch.Tensor:
    """Structural similarity, 11x11 Gaussian window (sigma 1.5), C1=(0.01L)^2, C2=(0.03L)^2.

    a, b: (H, W, C) or (B, H, W, C). Zero padding at the borders ("same" size), as in the
    reference 3DGS code. Returns the mean SSIM per image: () or (B,); with reduce=False the
    SSIM map (B, C, H, W). The mean is differentiable with respect to ``a`` only (the render
    against its target; the gradient is in closed form), the map with respect to both.
    """
    single = a.dim() == 3
    taps, c1, c2 = ssim_window(window, sigma, max_val)
    xb, yb = _batch(a).float(), _batch(b).float()
    kernels = _native_kernels(xb) if reduce and window <= NATIVE_MAX_WINDOW else None
    if kernels is not None:
        out = _NativeMeanSSIM.apply(xb.contiguous(), yb.detach().contiguous(), taps, c1, c2,
                                    kernels)
        return out[0] if single else out
    x, y = xb.permute(0, 3, 1, 2), yb.permute(0, 3, 1, 2)
    taps = taps.to(x.device, x.dtype)
    if not reduce:
        return _ssim_terms(x, y, taps, c1, c2)[0]
    out = _MeanSSIM.apply(x, y.detach(), taps, c1, c2)
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
