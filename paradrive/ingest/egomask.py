"""The ego mask of a video: the pixels that move with the camera (a car's hood, a dashboard).

A hood does not keep its grey levels over a drive: it reflects the sky and the trees, and
shadows cross it, so a pixel's spread over time is no test (on a real freeway clip the hood's
grey levels spread as much as the road's). What it keeps is its place: from one frame to the
next its fine texture is the same, while the road just in front of it, the nearest and so the
fastest moving part of the scene, is new in every frame. So, per pair of successive frames, the
zero-mean normalised correlation of their band-passed grey levels over a small window (a
pixel also counts as unchanged where both frames are flat and equal there); its median over the
pairs is high on the hood (about 0.8 on that clip) and near zero on the road before it (0.07).
The ego mask is what of that lies below the fast road: per image column, the unbroken run of
unchanged pixels that starts at the bottom row, its height smoothed across columns (a lane line
parallel to the drive also looks unchanged and would reach up from the hood's edge), grown by a
margin. Far things look unchanged between successive frames too, but the moving road cuts them
off from the bottom.

A still overlay away from the bottom edge (a logo, a clock) is found by comparing frames far
apart instead (:func:`paradrive.ingest.videomasks.overlay_mask`, with :func:`agreement`).

Pure numpy and deterministic.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["agreement", "blur", "ego_mask", "grey"]

LUMA = np.array([0.299, 0.587, 0.114], dtype=np.float32)


def grey(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 -> (H, W) float32 grey levels in [0, 1]."""
    return (np.asarray(rgb, dtype=np.float32) @ LUMA) / 255.0


def ego_mask(pairs: Sequence[tuple[np.ndarray, np.ndarray]], *, window: int = 7, sigma: float = 1.5,
             min_correlation: float = 0.5, flat: float = 0.5 / 255.0, smooth: float = 0.06,
             margin: float = 0.01) -> np.ndarray:
    """(H, W) bool: the pixels attached to the bottom edge that stay the same from frame to frame.

    pairs: successive frames (a frame and the next one kept), (H, W) float grey levels in
    [0, 1], ideally a few dozen pairs spread over the video, a few hundred pixels wide. ``window``: the correlation's
    square window (pixels); ``sigma``: the band-pass's Gaussian (pixels); ``min_correlation``:
    the median correlation above which a pixel stays the same; ``flat``: a window whose grey
    levels differ by less than this on average between the two frames is the same too (a
    flat hood; a road is never this still);
    ``smooth``: the width, as a share of the image width, of the running median of the run
    heights across columns; ``margin``: what the mask grows by upwards, as a share of the image height (the
    correlation window blurs the hood's edge).
    """
    if not pairs:
        raise ValueError("ego_mask needs at least one pair of frames")
    same = np.median(np.stack([_unchanged(a, b, window, sigma, flat) for a, b in pairs]), axis=0)
    still = same > min_correlation
    h, w = still.shape
    # per column, the unbroken run of still pixels from the bottom row
    runs = np.argmin(still[::-1], axis=0)
    runs[still.all(axis=0)] = h
    k = max(1, int(round(smooth * w)) // 2)
    padded = np.pad(runs, k, mode="edge")
    runs = np.array([np.median(padded[x:x + 2 * k + 1]) for x in range(w)])
    tops = np.where(runs > 0, h - runs - int(np.ceil(margin * h)), h)
    return np.arange(h)[:, None] >= tops[None, :]


def _unchanged(a: np.ndarray, b: np.ndarray, window: int, sigma: float, flat: float) -> np.ndarray:
    """Per pixel, how much frames ``a`` and ``b`` agree around it: the windowed correlation of
    their band-passed grey levels, or 1 where both are flat and equal."""
    corr, _ = agreement(a, b, window, sigma)
    equal = _box(np.abs(np.asarray(a, dtype=np.float32) - np.asarray(b, dtype=np.float32)), window) < flat
    return np.where(equal, 1.0, corr)


def agreement(a: np.ndarray, b: np.ndarray, window: int, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) float32 each: the windowed correlation of two frames' band-passed grey levels
    (``a``, ``b``: (H, W) in [0, 1]; the band-pass takes away a Gaussian blur of ``sigma``
    pixels; ``window``: the square window, pixels), and the texture in two directions both
    frames have there: the smaller of the two frames' smaller structure-tensor eigenvalue, as
    an RMS gradient (an edge or a line along which things may slide has none)."""
    a, b = np.asarray(a, dtype=np.float32), np.asarray(b, dtype=np.float32)
    da, db = a - blur(a, sigma), b - blur(b, sigma)
    noise = (0.5 / 255.0) ** 2  # below any texture a video keeps
    corr = _box(da * db, window) / np.sqrt((_box(da * da, window) + noise)
                                           * (_box(db * db, window) + noise))
    return corr, np.minimum(_corner(da, window), _corner(db, window))


def _corner(d: np.ndarray, window: int) -> np.ndarray:
    """The square root of the smaller eigenvalue of ``d``'s structure tensor over the window."""
    gy, gx = np.gradient(d)
    xx, yy, xy = _box(gx * gx, window), _box(gy * gy, window), _box(gx * gy, window)
    half = 0.5 * (xx + yy)
    low = half - np.sqrt(np.maximum(half ** 2 - (xx * yy - xy ** 2), 0.0))
    return np.sqrt(np.maximum(low, 0.0))


def _box(img: np.ndarray, size: int) -> np.ndarray:
    """Mean over a ``size`` x ``size`` window (edges replicated), by cumulative sums."""
    r = size // 2
    padded = np.pad(img.astype(np.float64), r, mode="edge")
    c = np.cumsum(np.cumsum(padded, axis=0), axis=1)
    c = np.pad(c, ((1, 0), (1, 0)))
    h, w = img.shape
    s = c[size:size + h, size:size + w] - c[:h, size:size + w] - c[size:size + h, :w] + c[:h, :w]
    return (s / (size * size)).astype(np.float32)


def blur(img: np.ndarray, sigma: float) -> np.ndarray:
    """Separable Gaussian blur with edge replication."""
    r = max(1, int(np.ceil(3 * sigma)))
    taps = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    taps = (taps / taps.sum()).astype(np.float32)
    h, w = img.shape
    padded = np.pad(img, ((0, 0), (r, r)), mode="edge")
    rows = sum(t * padded[:, k:k + w] for k, t in enumerate(taps))
    padded = np.pad(rows, ((r, r), (0, 0)), mode="edge")
    return sum(t * padded[k:k + h] for k, t in enumerate(taps))
