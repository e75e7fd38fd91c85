"""The masks of a ``video:`` scene: the ego mask and, per frame, the moving things.

Both are found in the video alone, with the SfM poses and the road plane (no labels, no
weights), and saved where :class:`~paradrive.contracts.layout.SceneLayout` says:
``masks/ego/<camera>.png`` (:mod:`paradrive.ingest.egomask`: the hood) and
``masks/motion/<camera>/<frame>.png`` (255 = moving). The fit leaves both out of every loss; the
render puts the recorded pixels back where the ego mask is.

Moving things. A static point seen below the horizon lies no farther than the road behind it,
so between two frames it moves at least as far along its epipolar line as that road point
would. A car driving ahead at about the ego's speed barely moves in the image while the road
behind it flows: it moves less than anything static could. Per frame ``i``, against the frame
``j`` a few camera heights back along the path (the road ``i`` sees was then farther ahead and
in view; the first frames take one ahead):

1. the static prediction: each pixel's ray meets the road plane (``ego2world``: z up, the
   road at the ego origin) and that point projects into ``j``; above the horizon, or farther
   than ``far`` camera heights, the point at infinity;
2. frame ``j`` is resampled at those positions (the road then lines up with frame ``i``, with
   no change of scale, which a flow method cannot follow near the camera), and OpenCV's DIS
   optical flow (a classic coarse-to-fine patch flow) finds what is left; the position it
   gives is read back through the same map;
3. along the epipolar line, from the point at infinity towards the road prediction, a pixel
   that covers less than ``alpha`` of the road's way (measured against the median share of
   the road pixels, which absorbs an error of the metric scale) is moving;
4. the specks are removed and each moving region is stood up as a wall from its lowest pixels
   to ``object_height`` camera heights above the road there: the flow test only sees the parts
   of a car whose background road is near, and a car's top lies near the horizon, where
   nothing moves in the image.

A car slower than the ego shows only its lowest rows (its share of the road's way is its
share of the ego's speed there); oncoming traffic moves faster than the road and passes as
static. docs/scene-layout.md ("Masks") has the figures on a real clip.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from paradrive.contracts.layout import SceneLayout
from paradrive.errors import SceneError
from paradrive.ingest.egomask import ego_mask, grey

__all__ = ["MaskScores", "MotionParams", "moving_mask", "road_region", "scene_ego_mask", "score_masks",
           "write_video_masks"]

WORK_WIDTH = 640      # masks are found at this width (or less) and scaled up
EGO_PAIRS = 48        # successive frame pairs the ego mask looks at, spread over the video


@dataclass(frozen=True)
class MotionParams:
    """baseline: camera heights along the path between the two frames compared; alpha: the
    share of the road's way below which a pixel moves; min_way: pixels (at WORK_WIDTH) the
    road must move for a pixel to be tested; far: camera heights beyond which the road counts as
    at infinity; object_height: how high (camera heights) a moving region is stood up; min_area:
    the smallest moving region kept (pixels at WORK_WIDTH); grow: pixels the mask grows by."""

    baseline: float = 3.0
    alpha: float = 0.5
    min_way: float = 1.0
    far: float = 250.0
    object_height: float = 1.3
    min_area: int = 40
    grow: int = 2


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
    return cv2.resize(g, (width, h), interpolation=cv2.INTER_AREA).astype(np.uint8)


def scene_ego_mask(frame: Callable[[int], np.ndarray], n: int, *, scene_id: str) -> np.ndarray:
    """(H, W) bool ego mask of ``n`` frames (``frame(k)``: (H, W, 3) uint8), from up to
    EGO_PAIRS successive pairs spread over them."""
    cv2 = _cv2(scene_id)
    first = frame(0)
    width = min(WORK_WIDTH, first.shape[1])
    starts = np.unique(np.linspace(0, n - 2, min(EGO_PAIRS, n - 1)).round().astype(int))
    pairs = [(_work(frame(int(k)), width, cv2) / 255.0, _work(frame(int(k) + 1), width, cv2) / 255.0)
             for k in starts]
    small = ego_mask(pairs).astype(np.uint8)
    return cv2.resize(small, (first.shape[1], first.shape[0]), interpolation=cv2.INTER_NEAREST) > 0


class _Geometry:
    """The road and the cameras at the working size: pixel rays, the road prediction."""

    def __init__(self, c2w: np.ndarray, ego2world: np.ndarray, K: np.ndarray, width: int,
                 height: int):
        self.c2w, self.ego2world = c2w, ego2world
        self.K = np.array(K, dtype=np.float64)
        self.width, self.height = width, height
        yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
        self.pix = np.stack([xx + 0.5, yy + 0.5, np.ones_like(xx)], -1)
        self.camera_height = float(np.median(
            [(e[:3, 2] @ (c[:3, 3] - e[:3, 3])) for c, e in zip(c2w, ego2world)]))
        centres = c2w[:, :3, 3]
        self.along = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(centres, axis=0), axis=1))]

    def partner(self, i: int, baseline: float) -> int:
        """The frame ``baseline`` camera heights back along the path, else ahead."""
        step = baseline * self.camera_height
        back = int(np.searchsorted(self.along, self.along[i] - step, side="right")) - 1
        if back >= 0 and back != i:
            return back
        return int(min(np.searchsorted(self.along, self.along[i] + step), len(self.along) - 1))

    def rays(self, i: int) -> np.ndarray:
        return self.pix @ np.linalg.inv(self.K).T @ self.c2w[i][:3, :3].T

    def road(self, i: int, rays: np.ndarray, far: float) -> tuple[np.ndarray, np.ndarray]:
        """Distance along each ray to the road plane of frame ``i`` (inf above the horizon or
        beyond ``far`` camera heights), and the rays below the horizon."""
        up, ground, centre = self.ego2world[i][:3, 2], self.ego2world[i][:3, 3], self.c2w[i][:3, 3]
        down = rays @ up
        below = down < -1e-9
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(below, (up @ (ground - centre)) / down, np.inf)
        t = np.where(t * np.linalg.norm(rays, axis=-1) > far * self.camera_height, np.inf, t)
        return t, below

    def project(self, j: int, points: np.ndarray, w: float) -> np.ndarray:
        """Image positions in frame ``j`` of world points (w = 1) or directions (w = 0)."""
        w2c = np.linalg.inv(self.c2w[j])
        cam = points @ w2c[:3, :3].T + w * w2c[:3, 3]
        q = cam @ self.K.T
        with np.errstate(divide="ignore", invalid="ignore"):
            return q[..., :2] / q[..., 2:3]


def moving_mask(geo: _Geometry, i: int, j: int, gi: np.ndarray, gj: np.ndarray,
                ego: np.ndarray, p: MotionParams, cv2) -> np.ndarray:
    """(h, w) bool moving pixels of frame ``i`` against frame ``j`` (work-size grey uint8
    images; ``ego``: the work-size ego mask)."""
    rays = geo.rays(i)
    t, below = geo.road(i, rays, p.far)
    centre = geo.c2w[i][:3, 3]
    q_inf = geo.project(j, rays, 0.0)
    finite = np.isfinite(t)
    q_road = np.where(finite[..., None],
                      geo.project(j, centre + rays * np.where(finite, t, 0.0)[..., None], 1.0), q_inf)
    q_road = np.nan_to_num(q_road, nan=-1e6, posinf=-1e6, neginf=-1e6).astype(np.float32)
    warped = cv2.remap(gj, q_road[..., 0] - 0.5, q_road[..., 1] - 0.5, cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_REPLICATE)
    flow = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM).calc(gi, warped, None)
    grid = geo.pix[..., :2].astype(np.float32) - 0.5
    q = np.stack([cv2.remap(q_road[..., c], grid[..., 0] + flow[..., 0], grid[..., 1] + flow[..., 1],
                            cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE) for c in (0, 1)], -1)
    way = q_road - q_inf
    length = np.linalg.norm(way, axis=-1)
    share = ((q - q_inf) * way).sum(-1) / np.maximum(length, 1e-9) ** 2
    h, w = gi.shape
    seen = ((q_road[..., 0] >= 0) & (q_road[..., 0] < w) & (q_road[..., 1] >= 0)
            & (q_road[..., 1] < h))
    lands = np.clip(q_road.round().astype(np.int64), 0, [w - 1, h - 1])
    seen &= ~ego[lands[..., 1], lands[..., 0]] & ~ego
    tested = below & finite & seen & (length >= p.min_way)
    road = tested & (length >= 2.0) & (length < 0.05 * w)
    scale = float(np.clip(np.median(share[road]), 0.5, 1.5)) if road.sum() > 100 else 1.0
    return tested & (share < p.alpha * scale)


def stand_up(geo: _Geometry, i: int, moving: np.ndarray, p: MotionParams, cv2) -> np.ndarray:
    """Each moving region of frame ``i`` after removing specks, stood up as a wall from its
    lowest pixel per column to ``object_height`` camera heights above the road there."""
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
        top = geo.project(i, centre + rays * t[:, None] + up * p.object_height * geo.camera_height,
                          1.0)[:, 1]
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
    ego = scene_ego_mask(frame, n, scene_id=scene_id)
    write_image(layout.ego_mask(camera), ego.astype(np.uint8)[..., None] * 255)
    height, width = ego.shape
    ww = min(WORK_WIDTH, width)
    wh = int(round(height * ww / width))
    Ks = np.array(K, dtype=np.float64)
    Ks[0] *= ww / width
    Ks[1] *= wh / height
    geo = _Geometry(c2w, ego2world, Ks, ww, wh)
    small_ego = cv2.resize(ego.astype(np.uint8), (ww, wh), interpolation=cv2.INTER_AREA) > 0
    greys: dict[int, np.ndarray] = {}

    def work(k: int) -> np.ndarray:
        if k not in greys:
            greys[k] = _work(frame(k), ww, cv2)
        return greys[k]

    shares = []
    for i in range(n):
        j = geo.partner(i, p.baseline)
        moving = stand_up(geo, i, moving_mask(geo, i, j, work(i), work(j), small_ego, p, cv2), p, cv2)
        full = cv2.resize(moving.astype(np.uint8), (width, height), interpolation=cv2.INTER_NEAREST) > 0
        full &= ~ego
        write_image(layout.motion_mask(camera, i), full.astype(np.uint8)[..., None] * 255)
        shares.append(float(full.mean()))
        for k in [k for k in greys if k < min(i, j) - 1]:
            del greys[k]
    return {"ego_share": round(float(ego.mean()), 5), "moving_share": round(float(np.mean(shares)), 5),
            "seconds": round(time.perf_counter() - start, 3),
            "cpu_seconds": round(time.process_time() - cpu, 3)}


# --------------------------------------------------------------------------- scoring

@dataclass(frozen=True)
class MaskScores:
    """Masks against hand-labelled boxes: ``coverage`` the share of the boxes' pixels masked
    (all frames pooled) and its lowest frame, ``road_masked`` the share of the road region
    masked (pooled) and its highest frame, per frame in ``frames``."""

    coverage: float
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


def score_masks(masks: dict[int, np.ndarray], boxes: dict[int, np.ndarray],
                road: dict[int, np.ndarray], ego: np.ndarray) -> MaskScores:
    """Score moving ``masks`` per frame against the hand-labelled ``boxes`` (per frame, (H, W)
    bool: the union of the boxes) and the ``road`` region (per frame, (H, W) bool); the road
    measured is the region less the boxes grown by a tenth of the image height around them
    (a car's shadow moves with it) and less the ego mask."""
    per: dict[int, tuple[float, float]] = {}
    hit = total = road_hit = road_total = 0
    for k, mask in masks.items():
        box = boxes[k]
        grow = max(1, int(0.025 * box.shape[0]))
        near = _grow(box, grow)
        region = road[k] & ~near & ~ego
        per[k] = (float(mask[box].mean()), float(mask[region].mean()))
        hit, total = hit + int(mask[box].sum()), total + int(box.sum())
        road_hit, road_total = road_hit + int(mask[region].sum()), road_total + int(region.sum())
    return MaskScores(coverage=hit / max(total, 1), worst_coverage=min(c for c, _ in per.values()),
                      road_masked=road_hit / max(road_total, 1),
                      worst_road_masked=max(r for _, r in per.values()), frames=per)


def _grow(mask: np.ndarray, r: int) -> np.ndarray:
    out = mask.copy()
    for axis in (0, 1):
        src = out.copy()
        for s in range(1, r + 1):
            out |= np.roll(src, s, axis=axis) | np.roll(src, -s, axis=axis)
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
        box = np.zeros((cam.height, cam.width), dtype=bool)
        for x0, y0, x1, y1 in named.values():
            box |= (u >= x0) & (u < x1) & (v >= y0) & (v < y1)
        masks[k] = read_image(layout.motion_mask(camera, k))[..., 0] > 127
        boxes[k] = box
        road[k] = road_region(scene.frames[k].cameras[camera].c2w, scene.frames[k].ego2world, K,
                              cam.width, cam.height)
    if not masks:
        raise ValueError(f"no labelled frame of {labels} is among the scene's frames")
    return score_masks(masks, boxes, road, ego)
