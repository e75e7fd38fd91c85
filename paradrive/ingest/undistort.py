"""OpenCV-style lens distortion (radial k1, k2, k3 and tangential p1, p2) without OpenCV.

Model, on normalised coordinates ``x = (u - cx) / fx``, ``y = (v - cy) / fy``::

    r2 = x^2 + y^2
    radial = 1 + k1 r2 + k2 r2^2 + k3 r2^3
    x_d = x radial + 2 p1 x y + p2 (r2 + 2 x^2)
    y_d = y radial + p1 (r2 + 2 y^2) + 2 p2 x y

Pixel coordinates follow the builder's convention (as Waymo's and the renderers'): pixel
``(row v, column u)`` covers ``[u, u + 1) x [v, v + 1)``, so its centre is ``(u + 0.5, v + 0.5)``.

``undistort_image`` maps every pixel of the undistorted output (same size, same pinhole
fx, fy, cx, cy) to where it lies in the distorted input and samples it bilinearly (inverse
mapping; torch ``grid_sample``, the sampling grid cached per camera; torch is imported when an
image is sampled, so reading a camera's model does not load it). ``distort_image`` does
the opposite, inverting the model by fixed-point iteration; the exporters use it to write
distorted test logs.
"""

from __future__ import annotations

import functools

import numpy as np


def distortion_is_zero(dist) -> bool:
    return dist is None or not np.any(np.asarray(dist, dtype=np.float64))


def distort_normalized(x, y, dist):
    """Apply the distortion to normalised coordinates; dist = (k1, k2, p1, p2, k3)."""
    k1, k2, p1, p2, k3 = (float(d) for d in dist)
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return xd, yd


def undistort_normalized(xd, yd, dist, iterations: int = 20):
    """Invert ``distort_normalized`` by fixed-point iteration (as OpenCV's undistortPoints)."""
    k1, k2, p1, p2, k3 = (float(d) for d in dist)
    x, y = np.array(xd, dtype=np.float64), np.array(yd, dtype=np.float64)
    for _ in range(iterations):
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        x = (xd - dx) / radial
        y = (yd - dy) / radial
    return x, y


def bilinear_sample(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Sample uint8 ``image`` (H, W, C) at image coordinates (u, v) (pixel centres at +0.5).

    Positions outside the image clamp to the border. Returns uint8 (*u.shape, C).
    """
    import torch

    h, w = image.shape[:2]
    grid = np.stack([2.0 * np.asarray(u) / w - 1.0, 2.0 * np.asarray(v) / h - 1.0], -1)
    return _sample(image, torch.from_numpy(grid.astype(np.float32)))


def _sample(image: np.ndarray, grid) -> np.ndarray:
    """torch grid_sample (bilinear, border) of a uint8 image at a normalised (H', W', 2) grid."""
    import torch

    h, w = image.shape[:2]
    # float copy first: decoded images may be read-only buffers
    src = torch.from_numpy(image.reshape(h, w, -1).astype(np.float32))
    src = src.permute(2, 0, 1)[None]
    with torch.no_grad():
        out = torch.nn.functional.grid_sample(src, grid[None], mode="bilinear",
                                              padding_mode="border", align_corners=False)
    out = out[0].permute(1, 2, 0).round_().clamp_(0, 255).to(torch.uint8)
    return out.numpy()


def _pixel_grid(width: int, height: int):
    """Image coordinates (u, v) of every pixel centre."""
    v, u = np.meshgrid(np.arange(height, dtype=np.float64) + 0.5,
                       np.arange(width, dtype=np.float64) + 0.5, indexing="ij")
    return u, v


@functools.lru_cache(maxsize=16)
def _undistort_grid(width: int, height: int, K: tuple, dist: tuple):
    """Normalised sampling grid (H, W, 2) of ``undistort_image``, cached per camera."""
    import torch

    fx, fy, cx, cy = K
    u, v = _pixel_grid(width, height)
    xd, yd = distort_normalized((u - cx) / fx, (v - cy) / fy, dist)
    grid = np.stack([2.0 * (xd * fx + cx) / width - 1.0, 2.0 * (yd * fy + cy) / height - 1.0], -1)
    return torch.from_numpy(grid.astype(np.float32))


def undistort_image(image: np.ndarray, K, dist) -> np.ndarray:
    """Undistorted image (same size, same pinhole K) of a distorted ``image`` (H, W, C) uint8.

    K: (3, 3) pinhole intrinsics; dist: (k1, k2, p1, p2, k3).
    """
    if distortion_is_zero(dist):
        return image
    K = np.asarray(K, dtype=np.float64)
    h, w = image.shape[:2]
    grid = _undistort_grid(w, h, (K[0, 0], K[1, 1], K[0, 2], K[1, 2]),
                           tuple(float(d) for d in dist))
    return _sample(image, grid).reshape(image.shape)


def distort_image(image: np.ndarray, K, dist) -> np.ndarray:
    """The image a lens with distortion ``dist`` would record of the pinhole ``image``."""
    if distortion_is_zero(dist):
        return image
    K = np.asarray(K, dtype=np.float64)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    h, w = image.shape[:2]
    u, v = _pixel_grid(w, h)
    x, y = undistort_normalized((u - cx) / fx, (v - cy) / fy, dist)
    out = bilinear_sample(image, x * fx + cx, y * fy + cy)
    return out.reshape(image.shape)
