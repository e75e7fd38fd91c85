"""The camera's height above the road from the road's own motion in the images (SfM units).

Triangulated road points are a poor ruler for the height: on forward motion structure from
motion trades a small rotation of every camera against the direction of travel (about 0.2 deg on
the synthetic street), and that lifts a point seen 10 m ahead by some 4 cm, a few per cent of a
dashcam's height, always the same way. The pixels of the road itself are a better one. Between
two frames ``i`` and ``j`` the road moves by the homography its plane induces,

    x_j ~ K (R + u n^T) K^-1 x_i,   u = t / d,

where ``X_j = R X_i + t`` is the relative pose from SfM (model units), ``n`` the road's unit
normal seen from camera ``i`` (pointing down) and ``d`` the camera's height above the road. With
``R`` and ``n`` held (``n`` made perpendicular to the pair's step: the vehicle drives on the
road, and the SfM points leave their plane tilted by a few tenths of a degree, which would cost
several per cent of height), the three numbers of ``u`` are fitted by aligning the ego lane's
road pixels of the later frame onto the earlier one, where the road was further ahead and
still in view (Gauss-Newton on a coarse-to-fine blur, with robust weights so that a vehicle in
the lane counts little). The step's own length from SfM then gives ``d = |t| / |u|``. Fitting
``u``'s direction too, rather than taking SfM's, keeps the rotation bias out of the size. The
height is the median over pairs spread along the video.

What moves with the camera is no road, and pulls the fit towards no motion at all (``u = 0``):

- the pixels that barely change over the video (a car's hood, a vehicle driving ahead at the
  same speed, the sky), found by their grey level's spread over the frames used (under half the
  median spread, or under ``static_std``) or given as the ego mask, are left out with their
  neighbours;
- what lies *over* the road and stays put in the image (a reflection of the dashboard in the
  windscreen, dirt, a text overlay) is subtracted: every frame is aligned after its frames' mean
  image is taken away, which removes anything added in the same place in every frame, while
  the road, which moves, keeps its texture. On a real freeway clip a windscreen reflection
  across the ego lane locked a third of the pairs onto ``u = 0`` before.

The median's uncertainty (:attr:`RoadMotion.uncertainty`) combines three figures, each
relative to the height: the heights' scatter (the standard error of a median, from their
interquartile range); their drift along the video (half the difference of the medians of the
first and the second half of the pairs: SfM's scale drifts along a monocular sequence, and one
height for the whole path then fits neither end exactly); and the band (half the difference of
the heights the near and the far half of the road pixels give on their own: a road that is no
plane, or a model that does not hold, shows there); and, where asked, the codec: how far the
height moves when the same frames go through one more H.264 encode. The pixels' fine texture
is what the alignment locks onto, and a codec keeps or smooths it differently from one encode
to the next: on the synthetic street at 320x192 one more encode at CRF 18 moved the height by
4.5 % and another encode of the same source by 8 %, with the pairs' scatter at 0.8 % in each,
since every pair moves alike. Pairs share the encode, so this part does not shrink with more of
them.

Pure numpy and deterministic: the same frames give the same height at any thread count.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from paradrive import geometry
from paradrive.ingest.egomask import blur
from paradrive.ingest.sfm import level_with_path

__all__ = ["RoadMotion", "road_motion_height", "still_pixels", "summarise"]

LUMA = np.array([0.299, 0.587, 0.114], dtype=np.float32)


@dataclass(frozen=True)
class RoadMotion:
    """The camera's height above the road (model units): the median over frame ``pairs`` of
    their ``heights``; ``spread`` is the heights' interquartile range over the median, ``scatter``
    the median's standard error and ``drift`` half the difference between the medians of the
    first and the second half of the pairs, both relative to the height. ``near_heights`` /
    ``far_heights``: each pair's height from the near and the far half of the road pixels alone
    (NaN where that half did not align)."""

    height: float
    heights: np.ndarray
    pairs: list[tuple[int, int]]
    spread: float
    scatter: float
    drift: float
    band: float | None
    near_heights: np.ndarray = field(default_factory=lambda: np.zeros(0))
    far_heights: np.ndarray = field(default_factory=lambda: np.zeros(0))
    codec: float | None = None
    recoded_heights: np.ndarray | None = None

    @property
    def uncertainty(self) -> float:
        """The height's relative uncertainty: scatter, drift, band (where both halves of the
        road could be aligned) and codec (where the frames were encoded once more) combined."""
        return float(np.sqrt(self.scatter ** 2 + self.drift ** 2 + (self.band or 0.0) ** 2
                             + (self.codec or 0.0) ** 2))

    def within(self, first: int, last: int, min_pairs: int = 5) -> RoadMotion | None:
        """The same figures from the pairs that start in frames ``first``..``last`` only; None
        where fewer than ``min_pairs`` do."""
        keep = [k for k, (i, _) in enumerate(self.pairs) if first <= i <= last]
        near = self.near_heights if len(self.near_heights) else np.full(len(self.pairs), np.nan)
        far = self.far_heights if len(self.far_heights) else np.full(len(self.pairs), np.nan)
        recoded = None if self.recoded_heights is None else self.recoded_heights[keep]
        return summarise(self.heights[keep], near[keep], far[keep],
                         [self.pairs[k] for k in keep], min_pairs, recoded)


def summarise(values: np.ndarray, near_h: np.ndarray, far_h: np.ndarray,
              used: list[tuple[int, int]], min_pairs: int,
              recoded_h: np.ndarray | None = None) -> RoadMotion | None:
    """The median height of frame pairs ``used`` (their heights ``values``, in the order along
    the video; ``near_h`` / ``far_h`` those of the two halves of the road pixels; ``recoded_h``
    those of the frames encoded once more, NaN where they did not align) and its uncertainty's
    parts; None where fewer than ``min_pairs``."""
    if len(values) < min_pairs:
        return None
    codec = None
    if recoded_h is not None:
        again = recoded_h[np.isfinite(recoded_h)]
        # a re-encode that loses the road's alignment says the cue rests on what codecs keep
        # or drop; its pairs that failed count as the whole height's worth
        codec = (abs(float(np.median(again)) / float(np.median(values)) - 1.0)
                 if len(again) >= min_pairs else 1.0)
    q1, median, q3 = np.percentile(values, [25, 50, 75])
    half = len(values) // 2
    # a median's standard error: 1.2533 sigma / sqrt(n), sigma from the IQR (1.349 sigma)
    scatter = 1.2533 * (q3 - q1) / 1.349 / np.sqrt(len(values)) / median
    drift = abs(np.median(values[half:]) - np.median(values[:half])) / (2 * median)
    both = np.isfinite(near_h) & np.isfinite(far_h)
    band = (abs(np.median(far_h[both]) - np.median(near_h[both])) / (2 * median)
            if both.sum() >= min_pairs else None)
    return RoadMotion(height=float(median), heights=np.asarray(values), pairs=list(used),
                      spread=float((q3 - q1) / median), scatter=float(scatter), drift=float(drift),
                      band=None if band is None else float(band), near_heights=np.asarray(near_h),
                      far_heights=np.asarray(far_h), codec=codec,
                      recoded_heights=np.asarray(recoded_h) if recoded_h is not None else None)


def road_motion_height(image: Callable[[int], np.ndarray], c2w: np.ndarray, K: np.ndarray,
                       up: np.ndarray, height: float, *, pairs: int = 40, baseline: float = 1.5,
                       near: float = 2.0, far: float = 8.0, lane: float = 1.4,
                       max_width: int = 640, blurs: tuple[float, ...] = (4.0, 2.0, 1.0, 0.5),
                       iterations: int = 8, min_pairs: int = 5,
                       static_std: float = 1.0 / 255.0, still_share: float = 0.5,
                       ego: np.ndarray | None = None,
                       codec_crf: int | None = None, bands: bool = True) -> RoadMotion | None:
    """The camera's height above the road by the road's motion, or None where fewer than
    ``min_pairs`` frame pairs align (no road texture, a camera that barely moves).

    image(k): frame ``k`` as (H, W, 3) uint8, pinhole ``K`` (undistorted). c2w: (F, 4, 4) OpenCV
    camera-to-world of those frames in model units. up / height: the road's unit normal towards
    the cameras and a first guess of the camera's height above it (from the SfM points), which
    also decides the road pixels: ``near``..``far`` heights ahead, within ``lane`` heights to
    either side. Pairs start at ``pairs`` evenly spaced frames; each pairs a frame with the first
    one ``baseline`` heights further along the path. Images wider than ``max_width`` are halved
    until they are not. ego: bool, True where pixels move with the camera (the ego mask), at the
    frames' size or any other (taken to it by the nearest pixel); None finds them: pixels whose
    grey level varies by less than ``static_std`` or than ``still_share`` of its median over the
    lower half of the image (standard deviations over the frames used, in [0, 1]). codec_crf:
    the frames used are encoded once more (H.264 at this CRF) and every pair fitted again on
    them; how far that moves the median is the ``codec`` part of the uncertainty (None: not
    measured). bands: fit the near and the far half of the road pixels too (the ``band``
    part; the codec's second measurement needs only the whole road's heights).
    """
    centres = c2w[:, :3, 3]
    along = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(centres, axis=0), axis=1))]
    starts = np.unique(np.linspace(0, len(c2w) - 1, pairs).round().astype(int))
    ends = np.searchsorted(along, along[starts] + baseline * height)
    chosen = [(int(i), int(j)) for i, j in zip(starts, ends) if j < len(c2w)]
    if len(chosen) < min_pairs:
        return None
    gray, Kp, shape = {}, np.array(K, dtype=np.float64), (0, 0)
    rgb: dict[int, np.ndarray] = {}   # each frame read once, kept for the codec's encode
    for k in sorted({k for pair in chosen for k in pair}):
        rgb[k] = image(k)
        frame = _gray(rgb[k])
        shape = frame.shape
        gray[k], Kp = _reduce(K, frame, max_width)
    # the same frames through one more H.264 encode, measured alike
    again = None if codec_crf is None else _recoded_motion(rgb, codec_crf, functools.partial(
        road_motion_height, c2w=c2w, K=K, up=up, height=height, pairs=pairs, baseline=baseline,
        near=near, far=far, lane=lane, max_width=max_width, blurs=blurs, iterations=iterations,
        min_pairs=min_pairs, static_std=static_std, still_share=still_share, ego=ego, bands=False))
    del rgb
    stack = np.stack(list(gray.values()))
    still = (still_pixels(stack, static_std, still_share) if ego is None
             else _reduce(K, _resized(np.asarray(ego, dtype=np.float32), shape), max_width)[0] > 0.0)
    # the blur would smear what moves with the camera over the road pixels next to it
    moving = ~_dilate(still, int(np.ceil(3 * max(blurs))))
    # what stays put over the road (a reflection in the windscreen, an overlay) cancels out
    frames = np.array(sorted(gray))
    total = stack.sum(axis=0)
    del stack
    heights, used = [], []
    for i, j in chosen:
        mean = _mean_elsewhere(gray, total, frames, along, (i, j), (far - near) * height,
                               min_frames=min_pairs)
        rel = geometry.invert(c2w[i]) @ c2w[j]  # X_i = R X_j + t
        down = -c2w[j, :3, :3].T @ level_with_path(up, c2w[[i, j]])
        later, earlier = gray[j] - mean, gray[i] - mean
        u = _fit_step(later, earlier, moving, Kp, rel[:3, :3], rel[:3, 3] / height, down, height,
                      near=near, far=far, lane=lane, blurs=blurs, iterations=iterations)
        if u is None:
            continue
        # the near and the far half of the road pixels alone, from the whole road's step (so at
        # the two finest blurs only)
        mid = _median_distance(moving, np.linalg.inv(Kp), down, near, far, lane)
        halves = [_fit_step(later, earlier, moving, Kp, rel[:3, :3], u, down, height, near=a, far=b,
                            lane=lane, blurs=blurs[-2:], iterations=iterations) if bands else None
                  for a, b in ((near, mid), (mid, far))]
        size = np.linalg.norm(rel[:3, 3])
        heights.append([size / np.linalg.norm(v) if v is not None else np.nan for v in (u, *halves)])
        used.append((i, j))
    if len(heights) < min_pairs:
        return None
    values, near_h, far_h = np.array(heights).T
    recoded_h = None if codec_crf is None else _by_pair(again, used)
    return summarise(values, near_h, far_h, used, min_pairs, recoded_h)


def _recoded_motion(rgb: dict[int, np.ndarray], crf: int,
                    measure: Callable[..., RoadMotion | None]) -> RoadMotion | None:
    """``measure`` (the road's motion without a codec part) on the frames ``rgb`` (by frame
    number) after one more encode at ``crf``."""
    return measure(_recoded(rgb, crf).__getitem__)


def _by_pair(motion: RoadMotion | None, used: list[tuple[int, int]]) -> np.ndarray:
    """``motion``'s height of each of the pairs ``used`` (NaN where it has none)."""
    heights = {} if motion is None else dict(zip(motion.pairs, motion.heights))
    return np.array([heights.get(pair, np.nan) for pair in used])


def _recoded(rgb: dict[int, np.ndarray], crf: int) -> dict[int, np.ndarray]:
    """The uint8 RGB frames ``rgb`` (by frame number) after one H.264 encode at ``crf`` in
    frame order (one encoder thread: the same bytes every time), as they decode."""
    import tempfile
    from pathlib import Path

    from paradrive.video import decode_frames, encode_video

    keys = sorted(rgb)
    h, w = rgb[keys[0]].shape[:2]
    pad = ((0, h % 2), (0, w % 2), (0, 0))   # 4:2:0 needs even sizes: an edge row or column again
    with tempfile.TemporaryDirectory(prefix="paradrive-recode-") as tmp:
        path = Path(tmp) / "road.mp4"
        encode_video(path, (np.pad(rgb[k], pad, mode="edge") for k in keys), 10.0, crf=crf,
                     threads=1)
        decoded = decode_frames(path)
    return {k: frame[:h, :w] for k, frame in zip(keys, decoded)}


def _mean_elsewhere(gray: dict[int, np.ndarray], total: np.ndarray, frames: np.ndarray,
                    along: np.ndarray, pair: tuple[int, int], reach: float,
                    min_frames: int) -> np.ndarray | float:
    """The mean of the frames that show none of the road ``pair`` aligns: those more than
    ``reach`` (the depth of the road pixels, model units) along the path from both frames of the
    pair; the frames near them would put a copy of the pair's own road into the mean, which
    holds the fit towards no motion. 0 where fewer than ``min_frames`` are that far (a short
    clip): nothing is subtracted."""
    far = np.all([np.abs(along[frames] - along[k]) > reach for k in pair], axis=0)
    if far.sum() < min_frames:
        return 0.0
    near = sum((gray[int(k)] for k in frames[~far]), np.zeros_like(total))
    return (total - near) / float(far.sum())


def still_pixels(gray: np.ndarray, static_std: float, share: float) -> np.ndarray:
    """(H, W) bool: the pixels of the frames ``gray`` (F, H, W) in [0, 1] whose standard
    deviation over the frames is at most ``static_std`` or below ``share`` of its median over
    the image (a hood's reflections and a vehicle keeping pace vary, but far less than the road
    passing under the camera)."""
    spread = np.std(gray, axis=0)
    road = float(np.median(spread[spread.shape[0] // 2:]))  # the lower half: mostly road
    return (spread <= static_std) | (spread < share * road)


def _gray(rgb: np.ndarray) -> np.ndarray:
    return (np.asarray(rgb, dtype=np.float32) @ LUMA) / 255.0


def _reduce(K: np.ndarray, img: np.ndarray, max_width: int) -> tuple[np.ndarray, np.ndarray]:
    """The image box-halved until at most ``max_width`` wide, and K to match (pixel centres at
    +0.5, so halving maps image coordinates x to x / 2 exactly)."""
    K = np.array(K, dtype=np.float64)
    while img.shape[1] > max_width:
        img = _halve(img)
        K[:2] *= 0.5
    return img, K


def _resized(mask: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """``mask`` at another size (``shape``, rows and columns), nearest pixel: an ego mask made on
    the stored frames, used on the smaller ones SfM saw."""
    if mask.shape == shape:
        return mask
    rows = ((np.arange(shape[0]) + 0.5) * mask.shape[0] / shape[0]).astype(int)
    cols = ((np.arange(shape[1]) + 0.5) * mask.shape[1] / shape[1]).astype(int)
    return mask[rows][:, cols]


def _halve(img: np.ndarray) -> np.ndarray:
    h, w = (img.shape[0] // 2) * 2, (img.shape[1] // 2) * 2
    img = img[:h, :w]
    return 0.25 * (img[0::2, 0::2] + img[1::2, 0::2] + img[0::2, 1::2] + img[1::2, 1::2])


def _dilate(mask: np.ndarray, r: int) -> np.ndarray:
    """``mask`` grown by ``r`` pixels (a square window)."""
    h, w = mask.shape
    padded = np.pad(mask, r)
    rows = np.zeros((h + 2 * r, w), dtype=bool)
    for k in range(2 * r + 1):
        rows |= padded[:, k:k + w]
    out = np.zeros((h, w), dtype=bool)
    for k in range(2 * r + 1):
        out |= rows[k:k + h]
    return out


@functools.lru_cache(maxsize=4)
def _pixel_rays(shape: tuple[int, ...], kinv: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Every pixel centre of an image of ``shape`` (N, 3 homogeneous) and its ray ``K^-1 x``,
    made once per image size and camera (the fit asks for them at every step)."""
    rows, cols = np.mgrid[0:shape[0], 0:shape[1]]
    pix = np.stack([cols + 0.5, rows + 0.5, np.ones(shape)], -1).reshape(-1, 3)
    rays = pix @ np.array(kinv).reshape(3, 3).T
    pix.flags.writeable = rays.flags.writeable = False
    return pix, rays


def _road_pixels(moving: np.ndarray, Kinv: np.ndarray, down: np.ndarray, height: float,
                 near: float, far: float, lane: float) -> np.ndarray:
    """(N, 3) homogeneous centres of the ``moving`` pixels whose ray meets the road
    ``near``..``far`` heights ahead and within ``lane`` heights to the side."""
    pix, rays = _pixel_rays(moving.shape, tuple(np.asarray(Kinv, dtype=np.float64).ravel()))
    towards = rays @ down
    with np.errstate(divide="ignore", invalid="ignore"):
        ground = rays * (height / towards)[:, None]
    keep = (moving.reshape(-1) & (towards > 1e-6) & (ground[:, 2] > near * height) & (ground[:, 2] < far * height)
            & (np.abs(ground[:, 0]) < lane * height))
    return pix[keep]


def _median_distance(moving: np.ndarray, Kinv: np.ndarray, down: np.ndarray, near: float,
                     far: float, lane: float) -> float:
    """The median distance ahead (in heights) of the road pixels: it splits them into a near and
    a far half of equal size."""
    pix = _road_pixels(moving, Kinv, down, 1.0, near, far, lane)
    if not len(pix):
        return float(np.sqrt(near * far))
    rays = pix @ Kinv.T
    return float(np.median(rays[:, 2] / (rays @ down)))


def _sample(img: np.ndarray, x: np.ndarray, y: np.ndarray):
    """Bilinear samples of ``img`` at image coordinates (pixel centres at +0.5), and a mask of
    the points inside it."""
    h, w = img.shape
    fx, fy = x - 0.5, y - 0.5
    inside = (fx >= 0) & (fy >= 0) & (fx <= w - 1.001) & (fy <= h - 1.001)
    fx, fy = np.clip(fx, 0, w - 1.001), np.clip(fy, 0, h - 1.001)
    x0, y0 = fx.astype(np.int64), fy.astype(np.int64)
    ax, ay = fx - x0, fy - y0
    top = img[y0, x0] * (1 - ax) + img[y0, x0 + 1] * ax
    bottom = img[y0 + 1, x0] * (1 - ax) + img[y0 + 1, x0 + 1] * ax
    return top * (1 - ay) + bottom * ay, inside


def _fit_step(a: np.ndarray, b: np.ndarray, moving: np.ndarray, K: np.ndarray, R: np.ndarray,
              u: np.ndarray, down: np.ndarray, height: float, *, near: float, far: float, lane: float,
              blurs: tuple[float, ...], iterations: int, min_pixels: int = 400,
              max_turn_deg: float = 5.0) -> np.ndarray | None:
    """u = t / d that aligns image ``b`` onto image ``a``'s ``moving`` road pixels, from ``u``;
    None when too few road pixels stay in view or the fitted step turns more than
    ``max_turn_deg`` from SfM's (the alignment locked onto something else)."""
    Kinv = np.linalg.inv(K)
    pix = _road_pixels(moving, Kinv, down, height, near, far, lane)
    if len(pix) < min_pixels:
        return None
    start = u.copy()
    still = (~moving).astype(np.float32)
    base = pix @ (K @ R @ Kinv).T       # K R K^-1 x, per pixel
    plane = pix @ (Kinv.T @ down)       # n^T K^-1 x, per pixel
    for sigma in blurs:
        sa, sb = blur(a, sigma), blur(b, sigma)
        ref, _ = _sample(sa, pix[:, 0], pix[:, 1])
        gy, gx = np.gradient(sb)
        for _ in range(iterations):
            y = base + plane[:, None] * (K @ u)[None]
            qx, qy = y[:, 0] / y[:, 2], y[:, 1] / y[:, 2]
            value, inside = _sample(sb, qx, qy)
            inside &= _sample(still, qx, qy)[0] < 0.01  # not onto what moves with the camera
            if inside.sum() < min_pixels:
                return None
            ix, _ = _sample(gx, qx, qy)
            iy, _ = _sample(gy, qx, qy)
            # d value / d u = grad . d q / d y . plane * K
            dq = np.stack([ix / y[:, 2], iy / y[:, 2],
                           -(ix * y[:, 0] + iy * y[:, 1]) / y[:, 2] ** 2], -1)
            J = (dq @ K) * plane[:, None]
            r = value - ref
            w = inside / np.sqrt(r * r + 0.02 ** 2)  # Charbonnier weights: a car ahead counts little
            # einsum, not BLAS: sums in one order at any thread count
            H = np.einsum("ni,n,nj->ij", J, w, J)
            if not np.isfinite(H).all() or np.trace(H) <= 1e-12:
                return None  # no texture to align
            gradient = np.einsum("ni,n,n->i", J, w, r)
            step = np.linalg.solve(H + 1e-9 * np.trace(H) * np.eye(3), -gradient)
            u = u + step
            if np.linalg.norm(step) < 1e-5 * np.linalg.norm(u):
                break
    if not np.isfinite(u).all():
        return None
    cos = u @ start / (np.linalg.norm(u) * np.linalg.norm(start))
    return u if cos > np.cos(np.deg2rad(max_turn_deg)) else None
