"""The masks of a ``video:`` scene: the ego mask and, per frame, the moving things.

Both are found in the video alone, with the SfM poses and the road plane (no labels, no
weights), and saved where :class:`~paradrive.contracts.layout.SceneLayout` says:
``masks/ego/<camera>.png`` (the hood, :mod:`paradrive.ingest.egomask`, and still overlays
anywhere, :func:`overlay_mask`) and ``masks/motion/<camera>/<frame>.png`` (255 = moving). The
fit leaves both out of every loss; the render puts the recorded pixels back where the ego mask
is.

Moving things. A static point seen below the horizon lies no farther than the road behind it,
so between two frames it moves at least as far along its epipolar line as that road point would
(its share of the road's way is at least one). A car driving ahead at about the ego's speed
stays put in the image (a share near zero); one slower than the ego moves by its share of the
ego's speed. Per frame ``i`` and partner ``j`` (frames ``baselines`` camera heights back and
ahead along the path):

1. each pixel's ray meets the road plane (``ego2world``: z up, the road at the ego origin); the
   road point and the point at infinity project into ``j``, and the segment between them, the
   road's way, is where a point seen at that pixel can be in ``j``: at share 0 it moved with the
   camera, at share 1 it is the road, beyond it is nearer than the road;
2. frame ``j`` is sampled along the way (every ``step`` pixels from share ``reach[0]`` to
   ``reach[1]``) and compared with frame ``i`` over a small window (mean absolute difference of
   grey levels): the best match among the shares a static point can have (``static`` and
   beyond) against the best among those of a mover (``moving`` and below, negative ones for a
   car pulling away);
3. a pixel is moving for that partner when its moving match is clearly the better one (below
   ``contrast`` times the static one, less ``noise`` grey levels); a road of plain asphalt
   matches both and counts as neither. The shares are measured against the road's own: the
   median share of the pixels that match clearly at one place, which absorbs an error of the
   metric scale or of the road plane's height;
4. the test runs on a small image pyramid, each pixel at the levels where its road's way is
   ``way`` pixels long (shorter is noise, longer outruns the window), against every partner; a
   pixel is moving when at least ``vote`` of its tests say so. Comparing frames both back and
   ahead keeps a frame's ends covered, and a long baseline makes even the far road, behind a
   car's roof, move in the image;
5. the specks are removed and each moving region is stood up as a wall from its lowest pixels to
   ``object_height_m`` above the road there: the test only sees what has the road behind it,
   and a car's roof lies above the horizon. A region narrower than ``min_width_m`` where it
   meets the road is dropped: no road user is that narrow, while a static thing far nearer
   than the road behind it (a post of a barrier) whose true match lies beyond the shares
   searched, with a look-alike nearer along its way, makes such specks.

What no monocular motion test can see: oncoming traffic (it moves faster than the road, as a
static point nearer than the road would) and a car standing still. Plain surfaces of a moving
car match anywhere along their way and count as neither; the stand-up fills them. The shadow
a car casts moves with it and is masked with it.
docs/scene-layout.md ("Masks") has the figures on a real clip.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from paradrive.contracts.layout import SceneLayout
from paradrive.errors import SceneError
from paradrive.ingest.egomask import agreement, ego_mask, grey

__all__ = ["MaskScores", "MotionParams", "moving_masks", "overlay_mask", "path_along", "road_region",
           "scene_ego_mask", "score_masks", "write_video_masks"]

OFF = 1e4  # grey level of the world off the image: no window reaching it matches
EGO_WIDTH = 640       # the ego mask is found at this width (or less) and scaled up
EGO_PAIRS = 48        # successive frame pairs the ego mask looks at, spread over the video


@dataclass(frozen=True)
class MotionParams:
    """How moving pixels are found (the module's steps 1-5), in pixels of the working image,
    ``width`` wide (the frame's width if smaller), and of its ``levels`` - 1 halvings.

    baselines: camera heights along the path to the partner frames, each taken back and ahead;
    way: the shortest and longest road's way (pixels of a level) tested there; step: pixels
    between samples along the longest way; reach: the shares sampled, from and to; window: the
    comparison's square window per level (pixels); moving, static: a match at a share at most
    ``moving`` times the road's own moves, one at least ``static`` times it is static;
    contrast, noise: a moving match must be below ``contrast`` times the static one less
    ``noise`` grey levels (of 255); vote: the share of a pixel's tests that must say moving;
    far: camera heights beyond which the road counts as at infinity; object_height_m: metres
    above the road a moving region is stood up to (a tall car); min_area: the smallest moving
    region kept (pixels of the working image); grow: pixels the mask grows by there.
    """

    width: int = 320
    levels: int = 2
    baselines: tuple[float, ...] = (3.0, 8.0, 24.0)
    way: tuple[float, float] = (3.0, 24.0)
    step: float = 1.0
    reach: tuple[float, float] = (-0.5, 1.6)
    window: tuple[int, ...] = (5, 3)
    moving: float = 0.5
    static: float = 0.8
    contrast: float = 0.65
    noise: float = 3.0
    vote: float = 0.5
    far: float = 250.0
    object_height_m: float = 1.6
    min_area: int = 10
    min_width_m: float = 0.5
    grow: int = 1


def _cv2(scene_id: str):
    try:
        import cv2
    except ImportError as exc:
        raise SceneError("the video input's masks need OpenCV (opencv-python-headless)",
                         scene_id=scene_id, fix="pip install 'paradrive[video]'") from exc
    return cv2


def _work(rgb: np.ndarray, width: int, cv2) -> np.ndarray:
    g = (grey(rgb) * 255.0).astype(np.float32)
    h = int(round(rgb.shape[0] * width / rgb.shape[1]))
    return cv2.resize(g, (width, h), interpolation=cv2.INTER_AREA)


def scene_ego_mask(frame: Callable[[int], np.ndarray], n: int, *, scene_id: str,
                   along: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The ego mask of ``n`` frames (``frame(k)``: (H, W, 3) uint8) in two (H, W) bool parts:
    the hood, from up to EGO_PAIRS successive pairs spread over them, and the still overlays,
    from half as many pairs half the path apart (``along``: (n,) distance travelled at each frame;
    without it, half the frames apart), so that a stop on the way pairs no two frames of the
    same place."""
    cv2 = _cv2(scene_id)
    first = frame(0)
    width = min(EGO_WIDTH, first.shape[1])
    greys: dict[int, np.ndarray] = {}

    def work(k: int) -> np.ndarray:
        if k not in greys:
            greys[k] = _work(frame(k), width, cv2) / 255.0
        return greys[k]

    starts = np.unique(np.linspace(0, n - 2, min(EGO_PAIRS, n - 1)).round().astype(int))
    hood = ego_mask([(work(int(k)), work(int(k) + 1)) for k in starts])
    pairs = _far_pairs(np.arange(n, dtype=np.float64) if along is None else np.asarray(along), EGO_PAIRS // 2)
    overlays = (overlay_mask([(work(a), work(b)) for a, b in pairs], cv2) if pairs
                else np.zeros_like(hood))
    size = (first.shape[1], first.shape[0])
    return (cv2.resize(hood.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0,
            cv2.resize(overlays.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0)


def path_along(c2w: np.ndarray) -> np.ndarray:
    """(N,) the distance travelled at each of the cameras ``c2w`` (N, 4, 4), from the first."""
    return np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(c2w[:, :3, 3], axis=0), axis=1))]


def _far_pairs(along: np.ndarray, most: int) -> list[tuple[int, int]]:
    """Up to ``most`` pairs of frames half the path apart (``along``: the distance travelled
    at each frame), their first frames spread over the first half."""
    half = 0.5 * (along[-1] - along[0])
    if half <= 0:
        return []
    ends = np.searchsorted(along, along + half)
    firsts = np.flatnonzero(ends < len(along))
    picked = np.unique(firsts[np.linspace(0, len(firsts) - 1, min(most, len(firsts))).round().astype(int)])
    return [(int(k), int(ends[k])) for k in picked if ends[k] != k]


def overlay_mask(pairs: list[tuple[np.ndarray, np.ndarray]], cv2, *, window: int = 7,
                 sigma: float = 1.5, min_correlation: float = 0.5, texture: float = 2.0 / 255.0,
                 ring: float = 0.02, max_lasting: float = 0.5, margin: float = 0.005) -> np.ndarray:
    """(H, W) bool: still overlays anywhere in the image (a logo, the fixed text of a clock,
    dirt on the windscreen): regions whose texture stays the same between frames far apart in
    the video while the texture around them does not.

    pairs: frames far apart ((H, W) float grey levels in [0, 1]), a few dozen spread over the
    video. A pixel lasts where its band-passed texture (``texture`` or more, RMS) correlates
    above ``min_correlation`` in most pairs (:func:`paradrive.ingest.egomask.agreement`; window
    and sigma in pixels). Lasting pixels a window apart join into a region; a region is kept
    unless more than ``max_lasting`` of the textured pixels in a ring around it (``ring`` of
    the image width) last too (far scenery the camera never turns away from lasts, but so does
    the scenery around it; a flat sky around a logo has no texture and does not count). A kept
    region has its holes filled (the flat inside of a logo, a clock's changing digits), gives
    back the half window the correlation spread it by, and grows by ``margin`` of the image
    width. Whatever lasts is left out of the fit and shown as
    recorded in every rendered stream, which for far scenery is nearly right anyway.
    """
    measures = [agreement(a, b, window, sigma) for a, b in pairs]
    corr = np.median(np.stack([c for c, _ in measures]), axis=0)
    textured = np.median(np.stack([t for _, t in measures]), axis=0) >= texture
    lasting = textured & (corr > min_correlation)
    h, w = lasting.shape
    joined = cv2.morphologyEx(lasting.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((window, window), np.uint8))
    n, labels = cv2.connectedComponents(joined, connectivity=8)
    r = max(1, int(round(ring * w)))
    out = np.zeros((h, w), dtype=bool)
    for a in range(1, n):
        region = labels == a
        around = cv2.dilate(region.astype(np.uint8), np.ones((2 * r + 1,) * 2, np.uint8)) > 0
        around &= ~region
        if lasting[around].sum() <= max_lasting * max(int(textured[around].sum()), 1):
            out |= _filled(region, cv2)
    if out.any():  # the windows spread what lasts by half a window: taken back, then the margin
        g = max(1, int(round(margin * w)))
        out = cv2.erode(out.astype(np.uint8), np.ones((window // 2 * 2 + 1,) * 2, np.uint8),
                        borderType=cv2.BORDER_CONSTANT, borderValue=0)
        out = cv2.dilate(out, np.ones((2 * g + 1,) * 2, np.uint8)) > 0
    return out


def _filled(region: np.ndarray, cv2) -> np.ndarray:
    """``region`` with its holes filled: what the outside cannot reach from the image border."""
    outside = np.pad(~region, 1, constant_values=True).astype(np.uint8)
    mask = np.zeros((outside.shape[0] + 2, outside.shape[1] + 2), dtype=np.uint8)
    cv2.floodFill(outside, mask, (0, 0), 2)
    return (outside != 2)[1:-1, 1:-1]


def _finite(q: np.ndarray) -> np.ndarray:
    """Image positions as float32, undefined ones far off the image."""
    return np.nan_to_num(q, nan=-1e6, posinf=-1e6, neginf=-1e6).astype(np.float32)


class _Geometry:
    """The road and the cameras at one image size: pixel rays, the road's way between frames."""

    def __init__(self, c2w: np.ndarray, ego2world: np.ndarray, K: np.ndarray, width: int,
                 height: int):
        self.c2w, self.ego2world = c2w, ego2world
        self.K = np.array(K, dtype=np.float64)
        self.width, self.height = width, height
        yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
        self.pix = np.stack([xx + 0.5, yy + 0.5, np.ones_like(xx)], -1)
        self.camera_height = float(np.median(
            [(e[:3, 2] @ (c[:3, 3] - e[:3, 3])) for c, e in zip(c2w, ego2world)]))
        self.along = path_along(c2w)

    def halved(self) -> _Geometry:
        K = self.K.copy()
        K[:2] /= 2.0
        return _Geometry(self.c2w, self.ego2world, K, self.width // 2, self.height // 2)

    def partners(self, i: int, baselines: tuple[float, ...]) -> list[int]:
        """The frames nearest ``baselines`` camera heights back and ahead along the path (each
        once; none where the camera has not moved that far)."""
        out: list[int] = []
        for b in baselines:
            for sign in (-1.0, 1.0):
                k = int(np.argmin(np.abs(self.along - (self.along[i] + sign * b * self.camera_height))))
                if k != i and k not in out:
                    out.append(k)
        return out

    def project(self, j: int, points: np.ndarray) -> np.ndarray:
        """(..., 2) image positions in frame ``j`` of (..., 3) world points."""
        w2c = np.linalg.inv(self.c2w[j])
        q = (points @ w2c[:3, :3].T + w2c[:3, 3]) @ self.K.T
        with np.errstate(divide="ignore", invalid="ignore"):
            return q[..., :2] / q[..., 2:3]

    def way(self, i: int, j: int, far: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per pixel of frame ``i``, where its point at infinity and its road point land in
        frame ``j`` ((h, w, 2) float32 each: the rotation's homography and the road plane's),
        and the pixels whose ray meets the road within ``far`` camera heights and in front of
        both cameras."""
        rel = np.linalg.inv(self.c2w[j]) @ self.c2w[i]  # camera i -> camera j
        R, t = rel[:3, :3], rel[:3, 3]
        up = self.ego2world[i][:3, 2]
        normal = -(self.c2w[i][:3, :3].T @ up)  # down, in camera i
        height = float(up @ (self.c2w[i][:3, 3] - self.ego2world[i][:3, 3]))
        rays = self.pix @ np.linalg.inv(self.K).T  # camera i, unit depth
        down = rays @ normal
        with np.errstate(divide="ignore", invalid="ignore"):
            reach = height / down  # depth of the road point
        near = (down > 1e-9) & (reach * np.linalg.norm(rays, axis=-1) <= far * self.camera_height)
        q_inf = rays @ (self.K @ R).T
        q_road = rays @ (self.K @ (R + np.outer(t, normal) / height)).T
        has = near & (q_road[..., 2] * reach > 1e-3 * self.camera_height) & (q_inf[..., 2] > 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            q_inf = q_inf[..., :2] / q_inf[..., 2:3]
            q_road = np.where(has[..., None], q_road[..., :2] / q_road[..., 2:3], q_inf)
        return _finite(q_inf), _finite(q_road), has

    def inside(self, q: np.ndarray) -> np.ndarray:
        return (q[..., 0] >= 0) & (q[..., 0] < self.width) & (q[..., 1] >= 0) & (q[..., 1] < self.height)


def _share_test(geo: _Geometry, i: int, j: int, gi: np.ndarray, gj: np.ndarray, ego: np.ndarray,
                window: int, p: MotionParams, cv2) -> tuple[np.ndarray, np.ndarray]:
    """(moving, tested) (h, w) bool of frame ``i`` against frame ``j`` at one level (``gi``,
    ``gj`` float32 grey levels; ``ego``: the ego mask grown by the window there)."""
    q_inf, q_road, tested = geo.way(i, j, p.far)
    way = q_road - q_inf
    length = np.linalg.norm(way, axis=-1)
    lands = np.clip(q_road.round().astype(np.int64), 0, [geo.width - 1, geo.height - 1])
    tested &= ((length >= p.way[0]) & (length <= p.way[1]) & geo.inside(q_road) & ~ego
               & ~ego[lands[..., 1], lands[..., 0]])
    if not tested.any():
        return tested, tested
    rows = np.flatnonzero(tested.any(axis=1))
    r0, r1 = max(0, rows[0] - window), min(geo.height, rows[-1] + window + 1)
    q_inf, way, gi = q_inf[r0:r1], way[r0:r1], gi[r0:r1]
    shares = np.arange(p.reach[0], p.reach[1] + 1e-9, p.step / p.way[1], dtype=np.float32)
    errors = np.empty((len(shares),) + gi.shape, dtype=np.float32)
    for a, s in enumerate(shares):
        q = q_inf + s * way
        # a sample off the image costs OFF, and so does any window that reaches one
        sample = cv2.remap(gj, q[..., 0] - 0.5, q[..., 1] - 0.5, cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=OFF)
        errors[a] = cv2.blur(cv2.absdiff(gi, sample), (window, window))
    valid = errors <= 255.0
    best = errors.min(axis=0)
    mean = np.where(valid, errors, 0.0).sum(axis=0) / np.maximum(valid.sum(axis=0), 1)
    tested_c = tested[r0:r1] & (best <= 255.0)
    # the road's own share, where a match stands out from the rest of its way
    clear = tested_c & (best + p.noise < p.contrast * mean)
    scale = (float(np.clip(np.median(shares[np.argmin(errors[:, clear], axis=0)]), 0.5, 1.5))
             if clear.sum() >= 50 else 1.0)
    moved = errors[shares <= p.moving * scale].min(axis=0)
    still = errors[shares >= p.static * scale].min(axis=0)
    tested_c &= still <= 255.0
    moving = np.zeros_like(tested)
    moving[r0:r1] = tested_c & (moved < p.contrast * still - p.noise)
    tested[:] = False
    tested[r0:r1] = tested_c
    return moving, tested


def moving_pixels(geos: list[_Geometry], i: int, pyramids: Callable[[int], list[np.ndarray]],
                  egos: list[np.ndarray], p: MotionParams, cv2) -> np.ndarray:
    """(h, w) bool moving pixels of frame ``i`` at the working size: those that at least
    ``vote`` of their tests (partners and levels) find moving. ``pyramids(k)``: frame ``k``'s
    grey levels per level; ``egos``: the ego mask per level, grown by the window."""
    votes = np.zeros((geos[0].height, geos[0].width), dtype=np.float32)
    tests = np.zeros_like(votes)
    size = (geos[0].width, geos[0].height)
    for j in geos[0].partners(i, p.baselines):
        for level, (geo, ego, window) in enumerate(zip(geos, egos, p.window)):
            moving, tested = _share_test(geo, i, j, pyramids(i)[level], pyramids(j)[level], ego,
                                         window, p, cv2)
            if level:
                moving, tested = (cv2.resize(m.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
                                  for m in (moving, tested))
            votes += moving
            tests += tested
    return (tests > 0) & (votes >= p.vote * tests)


def stand_up(geo: _Geometry, i: int, moving: np.ndarray, p: MotionParams, cv2) -> np.ndarray:
    """Each moving region of frame ``i`` after removing specks, stood up as a wall from its
    lowest pixel per column to ``object_height_m`` above the road there."""
    opened = cv2.morphologyEx(moving.astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(opened, connectivity=8)
    out = np.zeros(moving.shape, dtype=bool)
    Kinv, R = np.linalg.inv(geo.K), geo.c2w[i][:3, :3]
    up, ground, centre = geo.ego2world[i][:3, 2], geo.ego2world[i][:3, 3], geo.c2w[i][:3, 3]
    for a in range(1, n):
        x0, y0, w, h, area = (int(v) for v in stats[a])
        if area < p.min_area:
            continue
        region = labels[y0:y0 + h, x0:x0 + w] == a
        has = region.any(axis=0)
        cols = np.arange(w)
        lowest = y0 + h - 1 - np.argmax(region[::-1], axis=0)
        lowest = np.interp(cols, cols[has], lowest[has]).round().astype(int)
        rays = np.stack([x0 + cols + 0.5, lowest + 0.5, np.ones(w)], -1) @ Kinv.T @ R.T
        down = rays @ up
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (up @ (ground - centre)) / down
            top = geo.project(i, centre + rays * t[:, None] + up * p.object_height_m)[:, 1]
        on_road = (down < 0) & np.isfinite(t)
        if on_road.any() and w * float(np.median(t[on_road])) / geo.K[0, 0] < p.min_width_m:
            continue
        top = np.where((down < 0) & np.isfinite(top), np.floor(top), y0).clip(0, None).astype(int)
        for c in range(w):
            out[min(top[c], y0):lowest[c] + 1, x0 + c] = True
    if p.grow:
        out = cv2.dilate(out.astype(np.uint8), np.ones((2 * p.grow + 1,) * 2, np.uint8)) > 0
    return out


def write_video_masks(frame: Callable[[int], np.ndarray], c2w: np.ndarray, ego2world: np.ndarray,
                      K: np.ndarray, root: Path, camera: str, *, scene_id: str,
                      params: MotionParams | None = None) -> dict:
    """Find and write the ego mask and the moving masks of the scene being written under
    ``root`` (frames ``frame(k)``, (H, W, 3) uint8 undistorted, pinhole ``K``, ``c2w`` and
    ``ego2world`` per frame in metres). Returns what ``scene.json`` records of them."""
    from paradrive.scene import write_image

    cv2 = _cv2(scene_id)
    p = params or MotionParams()
    start, cpu = time.perf_counter(), time.process_time()
    n = len(c2w)
    layout = SceneLayout(root)
    hood, overlays = scene_ego_mask(frame, n, scene_id=scene_id, along=path_along(c2w))
    count, labels = cv2.connectedComponents(overlays.astype(np.uint8), connectivity=8)
    covered = np.zeros(count)
    shares = []
    for i, moving in enumerate(moving_masks(frame, c2w, ego2world, K, hood | overlays, p, cv2)):
        moving &= ~hood
        covered += np.bincount(labels[moving], minlength=count)
        write_image(layout.motion_mask(camera, i), moving.astype(np.uint8)[..., None] * 255)
        shares.append(float(moving.mean()))
    # what lasts on a car driving ahead at the ego's speed (its number plate) is no overlay:
    # the car's moving mask covers it in most frames
    sizes = np.bincount(labels.ravel(), minlength=count)
    movers = np.flatnonzero(covered > 0.5 * n * sizes)
    mask = hood | (overlays & ~np.isin(labels, movers[movers > 0]))
    write_image(layout.ego_mask(camera), mask.astype(np.uint8)[..., None] * 255)
    return {"ego_share": round(float(mask.mean()), 5), "overlay_share": round(float((mask & ~hood).mean()), 5),
            "moving_share": round(float(np.mean(shares)), 5),
            "seconds": round(time.perf_counter() - start, 3),
            "cpu_seconds": round(time.process_time() - cpu, 3)}


def moving_masks(frame: Callable[[int], np.ndarray], c2w: np.ndarray, ego2world: np.ndarray,
                 K: np.ndarray, ego: np.ndarray, p: MotionParams, cv2) -> Iterator[np.ndarray]:
    """Per frame in order, its (H, W) bool moving mask at the frames' size (the arguments as
    for :func:`write_video_masks`; ``ego``: the (H, W) bool ego mask)."""
    finder = MovingFinder(frame, c2w, ego2world, K, ego, p, cv2)
    for i in range(len(c2w)):
        yield finder.mask(i)
        finder.forget(i + 1)


class MovingFinder:
    """The moving masks of one video, frame by frame, with the working images it needs cached."""

    def __init__(self, frame: Callable[[int], np.ndarray], c2w: np.ndarray, ego2world: np.ndarray,
                 K: np.ndarray, ego: np.ndarray, p: MotionParams, cv2):
        self.frame, self.p, self.cv2 = frame, p, cv2
        self.height, self.width = ego.shape
        ww = min(p.width, self.width)
        wh = int(round(self.height * ww / self.width))
        Kw = np.array(K, dtype=np.float64)
        Kw[0] *= ww / self.width
        Kw[1] *= wh / self.height
        self.geos = [_Geometry(c2w, ego2world, Kw, ww, wh)]
        while len(self.geos) < p.levels:
            self.geos.append(self.geos[-1].halved())
        small = cv2.resize(ego.astype(np.uint8), (ww, wh), interpolation=cv2.INTER_AREA)
        self.egos = []
        for geo, window in zip(self.geos, p.window):
            level = cv2.resize(small, (geo.width, geo.height), interpolation=cv2.INTER_AREA) > 0
            self.egos.append(cv2.dilate(level.astype(np.uint8), np.ones((window, window), np.uint8)) > 0)
        self.cache: dict[int, list[np.ndarray]] = {}

    def pyramid(self, k: int) -> list[np.ndarray]:
        """Frame ``k``'s grey levels (float32, 0-255) per level."""
        if k not in self.cache:
            levels = [_work(self.frame(k), self.geos[0].width, self.cv2)]
            for geo in self.geos[1:]:
                levels.append(self.cv2.resize(levels[-1], (geo.width, geo.height),
                                              interpolation=self.cv2.INTER_AREA))
            self.cache[k] = levels
        return self.cache[k]

    def forget(self, i: int) -> None:
        """Drop the working images that frame ``i`` and later ones no longer need."""
        reach = min([i, *self.geos[0].partners(min(i, len(self.geos[0].c2w) - 1), self.p.baselines)])
        for k in [k for k in self.cache if k < reach]:
            del self.cache[k]

    def seeds(self, i: int) -> np.ndarray:
        """(h, w) bool moving pixels of frame ``i`` at the working size."""
        return moving_pixels(self.geos, i, self.pyramid, self.egos, self.p, self.cv2)

    def mask(self, i: int) -> np.ndarray:
        """(H, W) bool moving mask of frame ``i``, its moving regions stood up."""
        moving = stand_up(self.geos[0], i, self.seeds(i), self.p, self.cv2)
        return self.cv2.resize(moving.astype(np.uint8), (self.width, self.height),
                               interpolation=self.cv2.INTER_NEAREST) > 0


# --------------------------------------------------------------------------- scoring

@dataclass(frozen=True)
class MaskScores:
    """Masks against hand-labelled boxes: ``coverage`` the share of the boxes' pixels masked
    (all frames and boxes pooled), per box name in ``named``, and its lowest frame;
    ``road_masked`` the share of the road region masked (pooled) and its highest frame; per
    frame in ``frames`` (coverage, road masked)."""

    coverage: float
    named: dict[str, float]
    worst_coverage: float
    road_masked: float
    worst_road_masked: float
    frames: dict[int, tuple[float, float]]


def road_region(c2w: np.ndarray, ego2world: np.ndarray, K: np.ndarray, width: int, height: int, *,
                near: float = 5.0, far: float = 40.0, side: float = 5.5) -> np.ndarray:
    """(H, W) bool: the pixels whose ray meets the road plane ``near``..``far`` m ahead of the
    ego origin and within ``side`` m of it to either side (the ego lane and one beside it)."""
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    rays = np.stack([xx + 0.5, yy + 0.5, np.ones_like(xx)], -1) @ np.linalg.inv(K).T @ c2w[:3, :3].T
    up, ground, centre = ego2world[:3, 2], ego2world[:3, 3], c2w[:3, 3]
    down = rays @ up
    with np.errstate(divide="ignore", invalid="ignore"):
        local = (centre + rays * ((up @ (ground - centre)) / down)[..., None] - ground) @ ego2world[:3, :3]
    return (down < 0) & (local[..., 0] > near) & (local[..., 0] < far) & (np.abs(local[..., 1]) < side)


def score_masks(masks: dict[int, np.ndarray], boxes: dict[int, dict[str, np.ndarray]],
                road: dict[int, np.ndarray], ego: np.ndarray) -> MaskScores:
    """Score moving ``masks`` per frame ((H, W) bool) against the hand-labelled ``boxes`` (per
    frame, per name, (H, W) bool) and the ``road`` region (per frame, (H, W) bool); the road
    measured is the region less the boxes grown by 2.5 % of the image height (a car's shadow
    moves with it) and less the ego mask."""
    per: dict[int, tuple[float, float]] = {}
    hits: dict[str, list[int]] = {}
    road_hit = road_total = 0
    for k, mask in masks.items():
        union = np.zeros(mask.shape, dtype=bool)
        for name, box in boxes[k].items():
            counts = hits.setdefault(name, [0, 0])
            counts[0] += int(mask[box].sum())
            counts[1] += int(box.sum())
            union |= box
        region = road[k] & ~_grow(union, max(1, int(0.025 * mask.shape[0]))) & ~ego
        per[k] = (float(mask[union].mean()), float(mask[region].mean()))
        road_hit, road_total = road_hit + int(mask[region].sum()), road_total + int(region.sum())
    hit, total = (sum(c[i] for c in hits.values()) for i in (0, 1))
    return MaskScores(coverage=hit / max(total, 1), named={n: c[0] / max(c[1], 1) for n, c in hits.items()},
                      worst_coverage=min(c for c, _ in per.values()),
                      road_masked=road_hit / max(road_total, 1),
                      worst_road_masked=max(r for _, r in per.values()), frames=per)


def _grow(mask: np.ndarray, r: int) -> np.ndarray:
    """``mask`` grown by ``r`` pixels (a square), not past the image's edges."""
    h, w = mask.shape
    padded = np.pad(mask, r)
    out = np.zeros_like(mask)
    for dy in range(2 * r + 1):
        for dx in range(2 * r + 1):
            out |= padded[dy:dy + h, dx:dx + w]
    return out


def labelled_scores(scene_dir: Path, labels: Path, calibration: Path,
                    camera: str = "front") -> MaskScores:
    """Score a ``video:`` scene's saved moving masks against boxes labelled by hand on the
    original (distorted) frames: ``labels`` is a JSON of ``boxes`` {video frame: {name: [x0, y0,
    x1, y1]}} (the format of tests/udacity_freeway_cars.json), ``calibration`` the camera's
    JSON with fx, fy, cx, cy, k1, k2, p1, p2, k3 of those frames. Frames the scene did not keep
    are skipped (a frame is found by its time: ``fps`` of the calibration, else the scene's). A
    stored pixel is in a box when its place in the original frame is."""
    import json

    from paradrive.ingest.undistort import distort_normalized
    from paradrive.scene import load_scene, read_image

    scene = load_scene(scene_dir)
    layout = SceneLayout(Path(scene_dir))
    cam = scene.cameras[camera]
    cal = json.loads(Path(calibration).read_text())
    doc = json.loads(Path(labels).read_text())
    rate = float(cal.get("fps", scene.fps))
    K = cam.K()
    yy, xx = np.mgrid[0:cam.height, 0:cam.width].astype(np.float64)
    xd, yd = distort_normalized((xx + 0.5 - K[0, 2]) / K[0, 0], (yy + 0.5 - K[1, 2]) / K[1, 1],
                                [cal[k] for k in ("k1", "k2", "p1", "p2", "k3")])
    u, v = xd * cal["fx"] + cal["cx"] + 0.5, yd * cal["fy"] + cal["cy"] + 0.5
    by_time = {int(round(f.timestamp_us * 1e-6 * rate)): k for k, f in enumerate(scene.frames)}
    ego = read_image(layout.ego_mask(camera))[..., 0] > 127
    masks, boxes, road = {}, {}, {}
    for frame, named in doc["boxes"].items():
        k = by_time.get(int(frame))
        if k is None:
            continue
        boxes[k] = {name: (u >= x0) & (u < x1) & (v >= y0) & (v < y1)
                    for name, (x0, y0, x1, y1) in named.items()}
        masks[k] = read_image(layout.motion_mask(camera, k))[..., 0] > 127
        road[k] = road_region(scene.frames[k].cameras[camera].c2w, scene.frames[k].ego2world, K,
                              cam.width, cam.height)
    if not masks:
        raise ValueError(f"no labelled frame of {labels} is among the scene's frames")
    return score_masks(masks, boxes, road, ego)
