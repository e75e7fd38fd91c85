"""Camera poses of a monocular image sequence by structure from motion (pycolmap), and their
metric scale and up axis from the road plane.

A video has no calibration and no LiDAR, so its poses come from the images alone:

1. :func:`reconstruct`: SIFT features, *sequential* matching (a drive is a sequence, so each
   frame is matched with the next 5 and those 8 and 16 frames on only, which is both faster and
   freer of repeated-texture false matches than exhaustive matching) and incremental mapping,
   single-threaded with fixed seeds so that one video always gives the same poses. Only the
   features are found on several threads (:func:`feature_threads`: ``OMP_NUM_THREADS``, else
   every CPU the process may use; :func:`extract_features`): each
   image's are the same on any thread count, and the images are numbered by name afterwards,
   as one thread numbers them (matching is not: its RANSAC draws depend on the thread). Known
   intrinsics are held fixed: with focal refinement on, forward motion leaves the focal length
   poorly constrained and bundle adjustment drifts it far from the truth. Unknown ones are
   estimated as one shared SIMPLE_RADIAL camera (the video reader finds the focal length first
   instead, :mod:`paradrive.ingest.focal`, and passes it as known).
2. :func:`fit_road_plane`: a RANSAC plane through the points seen below and ahead of the camera,
   among roughly level planes, and a first measure of the camera's height above it (the lowest
   dense layer of points in the ego lane, in reconstruction units). :func:`level_with_path`
   makes its normal perpendicular to the direction of travel; that is the up axis. The height
   that sets the metric scale against the known mount height comes from the road's own motion
   in the images (:mod:`paradrive.ingest.roadmotion`), which the points only start. A similarity
   fit of camera centres cannot give either on a straight road: the centres are collinear,
   which leaves the roll about the road and the up axis free.
3. :func:`metric_rig`: the poses in the builder's conventions (docs/conventions.md): metres, a
   world whose origin is the first ego pose with z up, and an ego frame level with the road
   (x forward, y left, z up) under the camera, so a lateral shift moves along the road surface.

4. :func:`steady_runs` splits the registered frames where the camera's step jumps (a frame SfM
   placed wrongly), and :func:`without_drift` evens out the scale along the path with a scale
   measured per range of frames (:mod:`paradrive.ingest.scalecue`).

Nothing here knows a scene folder; errors are :class:`SfmError` and the reader names the scene.
"""

from __future__ import annotations

import dataclasses
import os
import sqlite3
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from paradrive import geometry

__all__ = ["SfmError", "Intrinsics", "Reconstruction", "RoadPlane", "MetricRig", "reconstruct",
           "mapping_options", "extract_features", "registered_runs", "steady_runs", "fit_road_plane",
           "level_with_path", "metric_rig", "path_length", "without_drift", "format_runs"]


class SfmError(ValueError):
    """The images do not give a reconstruction; ``registered`` holds the frames that did register."""

    def __init__(self, message: str, registered: list[int] | None = None):
        super().__init__(message)
        self.registered = list(registered or [])


@dataclass(frozen=True)
class Intrinsics:
    """A pinhole camera in pixels (pixel centres at +0.5, as COLMAP and the builder use)."""

    fx: float
    fy: float
    cx: float
    cy: float

    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


@dataclass
class Reconstruction:
    """One SfM model of a sequence of ``n`` images, in the reconstruction's own frame and units.

    c2w: (n, 4, 4) OpenCV camera-to-world, NaN for frames that did not register.
    points / colors: (M, 3) float64 triangulated points and their uint8 colours; ``point_frame``:
    the first frame that observes each point, ``point_views`` how many frames observe it;
    ``seen_point`` / ``seen_frame``: every observation, a point index and its frame.
    intrinsics / distortion: the camera the model used (distortion as OpenCV's (k1, k2, p1, p2,
    k3); zero where intrinsics were given). ``estimated``: whether the intrinsics were estimated.
    """

    c2w: np.ndarray
    points: np.ndarray
    colors: np.ndarray
    point_frame: np.ndarray
    point_views: np.ndarray
    intrinsics: Intrinsics
    distortion: tuple[float, float, float, float, float]
    estimated: bool
    seconds: float
    models: int = 1
    seen_point: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    seen_frame: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    @property
    def registered(self) -> np.ndarray:
        return np.isfinite(self.c2w[:, 0, 0])


def mapping_options(known: bool, seed: int):
    """pycolmap's options for a deterministic, single-threaded run of the whole pipeline."""
    import pycolmap

    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = 1
    extraction.use_gpu = False
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = 1
    matching.use_gpu = False
    pairing = pycolmap.SequentialPairingOptions()
    pairing.num_threads = 1
    pairing.overlap = 5
    pairing.quadratic_overlap = True
    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = 1
    # bundle adjustment is most of the time on a video: a global one each time the model grew by
    # 40 % (COLMAP: 10 %) and capped iterations cut the mapping of a 160-frame freeway clip from
    # 61 to 31 CPU seconds with the same registration; local ones keep every new frame refined
    mapping.ba_global_frames_ratio = 1.4
    mapping.ba_global_points_ratio = 1.4
    mapping.ba_global_max_num_iterations = 50
    mapping.ba_local_max_num_iterations = 25
    # bundle adjustment goes multi-threaded above this many residuals, whatever num_threads says
    mapping.ba_min_num_residuals_for_cpu_multi_threading = 2**31 - 1
    mapping.random_seed = seed
    mapping.mapper.num_threads = 1
    mapping.mapper.random_seed = seed
    mapping.triangulation.random_seed = seed
    mapping.extract_colors = True
    # a forward-moving camera: allow a smaller initial triangulation angle than COLMAP's 16 deg
    mapping.mapper.init_min_tri_angle = 4.0
    mapping.mapper.init_max_forward_motion = 0.999
    if known:
        mapping.ba_refine_focal_length = False
        mapping.ba_refine_principal_point = False
        mapping.ba_refine_extra_params = False
        mapping.mapper.abs_pose_refine_focal_length = False
        mapping.mapper.abs_pose_refine_extra_params = False
    return extraction, matching, pairing, mapping


def feature_threads() -> int:
    """The threads feature extraction uses: ``OMP_NUM_THREADS`` where it is set (Ray sets it to
    a task's CPUs, so an ingest task asking for one CPU extracts on one), else every CPU this
    process may run on."""
    given = os.environ.get("OMP_NUM_THREADS", "").strip()
    if given.isdigit() and int(given) > 0:
        return int(given)
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def extract_features(database: Path, image_dir: Path, names: list[str], reader, extraction) -> None:
    """SIFT features of ``names`` into ``database`` (one shared camera), on
    :func:`feature_threads` threads, numbered as one thread numbers them."""
    import pycolmap

    extraction.num_threads = feature_threads()
    pycolmap.extract_features(database, image_dir, image_names=names,
                              camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              extraction_options=extraction, device=pycolmap.Device.cpu)
    if extraction.num_threads > 1:
        _number_by_name(database)


def _number_by_name(database: Path) -> None:
    """Image ids in name order, each image's frame numbered as its image (one camera a frame).

    Several extraction threads store the images in the order they finish; the matcher's and the
    mapper's choices follow the ids, so a video must get the same ids on any thread count."""
    db = sqlite3.connect(database)
    try:
        rows = db.execute("SELECT image_id, name FROM images").fetchall()
        new_id = {old: new for new, (old, _) in enumerate(sorted(rows, key=lambda r: r[1]), start=1)}
        shift = 1 << 30  # out of the way of every id while they move
        with db:
            for old, new in new_id.items():
                for table in ("images", "keypoints", "descriptors"):
                    db.execute(f"UPDATE {table} SET image_id = ? WHERE image_id = ?", (new + shift, old))
            for table in ("images", "keypoints", "descriptors"):
                db.execute(f"UPDATE {table} SET image_id = image_id - ? WHERE image_id > ?", (shift, shift))
            # frame_data has no key of its own: written again in frame order, as one thread writes it
            links = db.execute("SELECT data_id, sensor_id, sensor_type FROM frame_data").fetchall()
            db.execute("DELETE FROM frame_data")
            db.executemany("INSERT INTO frame_data VALUES (?, ?, ?, ?)",
                           sorted((new_id[d], new_id[d], sensor, kind) for d, sensor, kind in links))
    finally:
        db.close()


def reconstruct(image_dir: Path, names: list[str], work_dir: Path, *,
                intrinsics: Intrinsics | None = None, seed: int = 0) -> Reconstruction:
    """Poses of the images ``names`` (in time order) under ``image_dir``; scratch files in
    ``work_dir``. The largest model wins where the mapper splits the sequence into several.

    Raises SfmError when no model forms (a static camera, too few or featureless frames).
    """
    import pycolmap

    start = time.perf_counter()
    pycolmap.logging.minloglevel = 2  # errors only: COLMAP logs every image at INFO
    pycolmap.set_random_seed(seed)
    work_dir.mkdir(parents=True, exist_ok=True)
    database = work_dir / "database.db"
    reader = pycolmap.ImageReaderOptions()
    if intrinsics is not None:
        reader.camera_model = "PINHOLE"
        reader.camera_params = ",".join(
            repr(float(v)) for v in (intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy))
    else:
        reader.camera_model = "SIMPLE_RADIAL"
    extraction, matching, pairing, mapping = mapping_options(intrinsics is not None, seed)
    extract_features(database, image_dir, names, reader, extraction)
    pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing,
                              device=pycolmap.Device.cpu)
    models = pycolmap.incremental_mapping(database, image_dir, work_dir / "sparse", mapping)
    if not models:
        raise SfmError("structure from motion found no initial pair of frames with enough "
                       "parallax: the camera does not move, or the frames have too few features")
    model = max(models.values(), key=lambda m: (m.num_reg_images(), -min(m.images)))
    rec = _read_model(model, names, intrinsics)
    rec.seconds = time.perf_counter() - start
    rec.models = len(models)
    return rec


def _read_model(model, names: list[str], given: Intrinsics | None) -> Reconstruction:
    """A pycolmap model as arrays indexed by frame (the position of an image's name in ``names``)."""
    frame_of = {name: i for i, name in enumerate(names)}
    c2w = np.full((len(names), 4, 4), np.nan)
    image_frame = {}
    for image_id, image in model.images.items():
        if not image.has_pose:
            continue
        i = frame_of[image.name]
        image_frame[image_id] = i
        w2c = np.eye(4)
        w2c[:3] = image.cam_from_world().matrix()
        c2w[i] = geometry.invert(w2c)
    ids = sorted(model.points3D)
    points = np.array([model.points3D[p].xyz for p in ids], dtype=np.float64).reshape(-1, 3)
    colors = np.array([model.points3D[p].color for p in ids], dtype=np.uint8).reshape(-1, 3)
    seen = [(k, image_frame[e.image_id]) for k, p in enumerate(ids)
            for e in model.points3D[p].track.elements]
    seen_point, seen_frame = np.array(seen, dtype=np.int64).reshape(-1, 2).T
    first = np.full(len(ids), len(names), dtype=np.int64)
    np.minimum.at(first, seen_point, seen_frame)
    views = np.array([model.points3D[p].track.length() for p in ids], dtype=np.int64)
    camera = next(iter(model.cameras.values()))
    intrinsics, distortion = _camera(camera)
    return Reconstruction(c2w=c2w, points=points, colors=colors, point_frame=first, point_views=views,
                          intrinsics=given or intrinsics, distortion=distortion,
                          estimated=given is None, seconds=0.0, seen_point=seen_point,
                          seen_frame=seen_frame)


def _camera(camera) -> tuple[Intrinsics, tuple[float, float, float, float, float]]:
    """Pinhole intrinsics and OpenCV distortion of a PINHOLE, SIMPLE_PINHOLE or SIMPLE_RADIAL camera
    (COLMAP's radial term k multiplies r^2 of normalised coordinates, as OpenCV's k1 does)."""
    p = [float(v) for v in camera.params]
    name = camera.model_name
    if name == "PINHOLE":
        return Intrinsics(p[0], p[1], p[2], p[3]), (0.0, 0.0, 0.0, 0.0, 0.0)
    if name == "SIMPLE_PINHOLE":
        return Intrinsics(p[0], p[0], p[1], p[2]), (0.0, 0.0, 0.0, 0.0, 0.0)
    if name == "SIMPLE_RADIAL":
        return Intrinsics(p[0], p[0], p[1], p[2]), (p[3], 0.0, 0.0, 0.0, 0.0)
    raise SfmError(f"camera model {name} is not one the video reader asks for")


def registered_runs(registered: np.ndarray) -> list[tuple[int, int]]:
    """Contiguous runs of True as inclusive (first, last) frame ranges, in order."""
    runs: list[tuple[int, int]] = []
    for i, ok in enumerate(np.asarray(registered, dtype=bool)):
        if ok and runs and runs[-1][1] == i - 1:
            runs[-1] = (runs[-1][0], i)
        elif ok:
            runs.append((i, i))
    return runs


def steady_runs(c2w: np.ndarray, runs: list[tuple[int, int]], *, times: np.ndarray | None = None,
                max_ratio: float = 2.0, still: float = 0.2) -> list[tuple[int, int]]:
    """``runs`` (inclusive frame ranges of ``c2w`` (n, 4, 4)) split where the camera's speed
    between frames jumps: a step per second over ``max_ratio`` times the one before it, or under
    its inverse. ``times`` (n,) seconds of the frames (a variable-rate video's or one with frames
    dropped, whose steps span unequal intervals); None = evenly spaced. A vehicle's speed changes
    by under 1 g: at 10 frames a second that is under 1 m/s from one step to the next, so two
    consecutive speeds differ by a factor 2 only at a walking pace or below; such a jump is a
    frame SfM placed wrongly (seen: 5 steps of a 130-frame synthetic street 3 to 10 times their
    neighbours', the path 23 % long). Speeds both under ``still`` of the run's median (near a
    standstill, where SfM's noise dominates the step) are not compared."""
    out: list[tuple[int, int]] = []
    for first, last in runs:
        centres = c2w[first:last + 1, :3, 3]
        steps = np.linalg.norm(np.diff(centres, axis=0), axis=1)
        if times is not None:
            steps = steps / np.maximum(np.diff(np.asarray(times, dtype=np.float64)[first:last + 1]), 1e-9)
        if len(steps) < 2:
            out.append((first, last))
            continue
        floor = still * float(np.median(steps))
        start = first
        for k in range(1, len(steps)):
            a, b = steps[k - 1], steps[k]
            if max(a, b) > floor and max(a, b) > max_ratio * max(min(a, b), 1e-12):
                out.append((start, first + k))   # the frame between the two steps ends a run
                start = first + k
        out.append((start, last))
    return out


def format_runs(runs: list[tuple[int, int]]) -> str:
    """``0-41, 45-90`` (or ``none``) for messages."""
    return ", ".join(f"{a}-{b}" if b > a else f"{a}" for a, b in runs) or "none"


def path_length(c2w: np.ndarray) -> float:
    """Length of the polyline through the camera centres (units of the poses)."""
    centres = np.asarray(c2w)[:, :3, 3]
    return float(np.linalg.norm(np.diff(centres, axis=0), axis=1).sum())


# --------------------------------------------------------------------------- the road plane

@dataclass(frozen=True)
class RoadPlane:
    """The plane ``normal . x + offset = 0`` (unit normal towards the cameras), the camera's
    height above it (model units), and the points that decided the height out of the candidates
    below the cameras."""

    normal: np.ndarray
    offset: float
    height: float
    inliers: int
    candidates: int
    depths: np.ndarray = field(default_factory=lambda: np.zeros(0))
    frames: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    def within(self, first: int, last: int, min_points: int = 12) -> tuple[float, float, int] | None:
        """The height from the points whose overhead camera is frame ``first``..``last`` only
        (``depths``: each deciding point's depth below it, ``frames`` that camera's frame), its
        standard error (relative) and the points' count; None under ``min_points``."""
        inside = (self.frames >= first) & (self.frames <= last)
        n = int(inside.sum())
        if n < min_points:
            return None
        depth = self.depths[inside]
        height = float(depth.mean())
        return height, float(depth.std(ddof=1) / np.sqrt(n) / height), n


def _camera_local(rec: Reconstruction) -> np.ndarray:
    """Each point in the OpenCV frame of the first camera that sees it (M, 3)."""
    pose = rec.c2w[rec.point_frame]
    return np.einsum("nji,nj->ni", pose[:, :3, :3], rec.points - pose[:, :3, 3])


def fit_road_plane(rec: Reconstruction, *, seed: int = 0, iterations: int = 2000,
                   tolerance: float = 0.05, max_tilt_deg: float = 20.0, lane: float = 1.4,
                   min_views: int = 3, scatter: float = 0.08, min_share: float = 0.2,
                   min_points: int = 12, max_grade_deg: float = 8.0) -> RoadPlane:
    """The road under the cameras: its normal, and the camera's height above it.

    The normal: RANSAC over the points below and ahead of their camera, among planes within
    ``max_tilt_deg`` of the cameras' mean up axis (a dashcam is mounted roughly level, and this
    keeps facades out) and within ``max_grade_deg`` of level along the path and sideways (an
    embankment beside a plain road can hold more points), inliers within ``tolerance`` of the
    points' median depth below the camera, refined by least squares. Where that plane is a
    higher surface beside the lane (a row of car roofs), the lowest layer under the path gives
    the rough height that picks the lane's points.

    The height, from the points of the ego lane only (seen in ``min_views`` frames or more, as
    short tracks triangulate poorly):

    - Each point's depth is taken below the camera that later passes over it, not the one that
      first saw it some ten heights back: a 0.5 degree pitch error of the normal then moves the
      depth by ``lateral * tan(0.5 deg)``, about 1 %, instead of ``10 * tan(0.5 deg)``, about 9 %.
      Points beyond either end of the path have no camera over them and are left out.
    - Kerbs, sidewalks and parked cars stand beside the lane, and on a street with plain asphalt
      they outnumber the road's own features (lane markings) and sit 0.1-0.2 m above it; keeping
      points within ``lane`` heights of the camera sideways (about +-2.2 m for a car) keeps them
      out while keeping the lane's own markings.
    - What is left in the lane above the road (a vehicle ahead) is a separate, higher layer: the
      depths' kernel density splits into layers at its minima, and the road is the lowest layer
      (largest depth) that holds ``min_share`` of the points. The kernel is ``scatter`` heights
      wide because a forward-moving camera triangulates ground points with several per cent of
      scatter along their viewing rays, which would otherwise split the road into spurious
      layers above and below it. The height is the mean depth of that layer's points.

    Raises SfmError when fewer than ``min_points`` points are left at any step: a camera that
    sees no road.
    """
    local = _camera_local(rec)
    below = (local[:, 2] > 0) & (local[:, 1] > 0)
    if below.sum() < min_points:
        raise SfmError(f"only {int(below.sum())} reconstructed points lie below and ahead of the "
                       f"camera, {min_points} are needed to find the road")
    pts = rec.points[below]
    cams = rec.c2w[rec.point_frame[below]][:, :3, 3]
    down = rec.c2w[rec.registered][:, :3, 1].mean(axis=0)
    down /= np.linalg.norm(down)
    centres = rec.c2w[rec.registered][:, :3, 3]
    threshold, min_cos = float(np.median((pts - cams) @ down)) * tolerance, np.cos(np.deg2rad(max_tilt_deg))
    try:
        normal, offset = _level_plane(pts, threshold, down, min_cos, seed, iterations, min_points,
                                      along=_level_axes(rec, centres, max_grade_deg))
    except SfmError:  # a path that bends or pitches over its length: the tilt bound alone
        normal, offset = _level_plane(pts, threshold, down, min_cos, seed, iterations, min_points)
    if normal @ down > 0:  # point it up, towards the cameras
        normal, offset = -normal, -offset
    rough = float(np.median(centres @ normal + offset))
    depth, sideways, over = _depth_below_overhead_camera(pts, centres, normal)
    seen = rec.point_views[below] >= min_views

    def in_lane(height: float) -> np.ndarray:
        return (sideways < lane * height) & seen & (depth > 0.5 * height)

    near = in_lane(rough)
    under = np.isfinite(sideways) & seen & (depth > 0)
    if near.sum() < min_points and under.sum() >= min_points:
        # the level plane with the most points can be a higher surface (kerbs, car roofs) where
        # the road itself shows few features; the lowest layer under the path is the road then
        layer = _lowest_layer(depth[under], scatter * float(np.median(depth[under])), min_share)
        rough = float(depth[under][layer].mean())
        near = in_lane(rough)
    if near.sum() < min_points:
        raise SfmError(f"only {int(near.sum())} well-seen points lie on the road near the camera, "
                       f"{min_points} are needed to measure its height")
    layer = _lowest_layer(depth[near], scatter * rough, min_share)
    if layer.sum() < min_points:
        raise SfmError(f"only {int(layer.sum())} points lie on the lowest surface under the "
                       f"camera, {min_points} are needed to measure its height")
    frame_of = np.flatnonzero(rec.registered)
    return RoadPlane(normal=normal, offset=float(offset), height=float(depth[near][layer].mean()),
                     inliers=int(layer.sum()), candidates=int(below.sum()),
                     depths=depth[near][layer], frames=frame_of[over[near][layer]])


def _depth_below_overhead_camera(points: np.ndarray, centres: np.ndarray, up: np.ndarray,
                                 chunk: int = 512) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per point: its depth along ``up`` below the camera centre nearest to it across ``up`` (the
    camera over it), that horizontal distance and that camera's index in ``centres``; infinite
    distance for points whose nearest camera is the first or the last (they lie beyond the
    path's ends). Chunked: (points x
    cameras) distances of a long video would not fit in memory at once."""
    depth = np.empty(len(points))
    sideways = np.empty(len(points))
    over = np.empty(len(points), dtype=np.int64)
    for start in range(0, len(points), chunk):
        d = centres[None] - points[start:start + chunk, None]
        along = d @ up
        across = np.linalg.norm(d - along[..., None] * up, axis=2)
        j = across.argmin(axis=1)
        rows = np.arange(len(j))
        depth[start:start + chunk] = along[rows, j]
        ends = (j == 0) | (j == len(centres) - 1)
        sideways[start:start + chunk] = np.where(ends, np.inf, across[rows, j])
        over[start:start + chunk] = j
    return depth, sideways, over


def _lowest_layer(depth: np.ndarray, bandwidth: float, min_share: float) -> np.ndarray:
    """Mask of the points in the lowest layer (largest depth) of ``depth``'s Gaussian kernel
    density that holds ``min_share`` of them (the most populous where none does: scattered
    points with no dominant surface still give the likeliest one); layers are split at the
    density's local minima."""
    grid = np.linspace(depth.min() - bandwidth, depth.max() + bandwidth, 512)
    density = np.zeros(len(grid))
    for start in range(0, len(depth), 4096):
        density += np.exp(-0.5 * ((grid[:, None] - depth[None, start:start + 4096])
                                  / bandwidth) ** 2).sum(axis=1)
    inner = np.flatnonzero((density[1:-1] < density[:-2]) & (density[1:-1] <= density[2:])) + 1
    edges = np.r_[-np.inf, grid[inner], np.inf]
    layers = [(depth > lo) & (depth <= hi) for hi, lo in zip(edges[::-1][:-1], edges[::-1][1:])]
    dense = [layer for layer in layers if layer.mean() >= min_share]
    return dense[0] if dense else max(layers, key=lambda layer: int(layer.sum()))


def _level_axes(rec: Reconstruction, centres: np.ndarray,
                max_grade_deg: float) -> list[tuple[np.ndarray, float]]:
    """Directions the road runs along, each with the sine of the largest angle the road's plane
    may make with it: the path from the first camera to the last (the vehicle drives on the road;
    left out where the path comes back near its start) and the cameras' mean sideways axis (a
    dashcam is mounted with little roll), both within ``max_grade_deg``."""
    sine = float(np.sin(np.deg2rad(max_grade_deg)))
    right = rec.c2w[rec.registered][:, :3, 0].mean(axis=0)
    axes = [(right / np.linalg.norm(right), sine)]
    travel = centres[-1] - centres[0]
    if np.linalg.norm(travel) >= 0.5 * np.linalg.norm(np.diff(centres, axis=0), axis=1).sum():
        axes.append((travel / np.linalg.norm(travel), sine))
    return axes


def _level_plane(pts: np.ndarray, threshold: float, down: np.ndarray, min_cos: float, seed: int,
                 iterations: int, min_points: int, *,
                 along: list[tuple[np.ndarray, float]] | None = None) -> tuple[np.ndarray, float]:
    """RANSAC plane with the most inliers among those whose normal is within acos(min_cos) of
    ``down`` and makes at most each given angle (as its sine) with each direction of ``along``
    (a kerb and the road beside it, or a row of parked cars, can otherwise hold more points than
    a plain road), refined by least squares on its inliers."""
    rng = np.random.default_rng(seed)
    best = np.zeros(len(pts), dtype=bool)
    for _ in range(iterations):
        a, b, c = pts[rng.choice(len(pts), 3, replace=False)]
        normal = np.cross(b - a, c - a)
        norm = np.linalg.norm(normal)
        if norm < 1e-12 or abs(normal @ down) < min_cos * norm:
            continue
        if any(abs(normal @ axis) > sine * norm for axis, sine in along or ()):
            continue
        inliers = np.abs((pts - a) @ (normal / norm)) < abs(threshold)
        if inliers.sum() > best.sum():
            best = inliers
    if best.sum() < min_points:
        raise SfmError(f"no road plane: at most {int(best.sum())} of {len(pts)} points below the "
                       f"camera lie on one level plane, {min_points} are needed")
    return _plane_through(pts[best])


def _plane_through(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares plane (unit normal, offset) through ``points``."""
    centre = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centre)
    normal = vt[-1] / np.linalg.norm(vt[-1])
    return normal, float(-normal @ centre)


def without_drift(rec: Reconstruction, first: int, ratio: np.ndarray) -> Reconstruction:
    """``rec`` with its scale made even along frames ``first``.. ``first + len(ratio) - 1``:
    ``ratio`` (F,) is each frame's scale over the whole path's (metres per unit there over the
    mean), so each step between two frames is stretched by the ratio at its middle, and each
    point by the ratio of the frame that first saw it, about that camera. Rotations, and the
    frames outside the range, are kept (those follow the range's ends rigidly)."""
    c2w = rec.c2w.copy()
    run = c2w[first:first + len(ratio)]
    centres = run[:, :3, 3].copy()
    mid = np.r_[ratio[0], 0.5 * (ratio[1:] + ratio[:-1])]
    steps = np.diff(centres, axis=0, prepend=centres[:1]) * mid[:, None]
    moved = centres[0] + np.cumsum(steps, axis=0)
    run[:, :3, 3] = moved
    frame = np.clip(rec.point_frame - first, 0, len(ratio) - 1)
    before = centres[frame]
    points = moved[frame] + ratio[frame][:, None] * (rec.points - before)
    return dataclasses.replace(rec, c2w=c2w, points=points)


def level_with_path(up: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    """``up`` made perpendicular to the direction from the first camera of ``c2w`` to the last.

    A vehicle drives on the road, so its path runs level with the road's plane, while the plane
    through triangulated points comes out tilted along the road by a few tenths of a degree: on
    forward motion SfM trades a small pitch of every camera against the direction of travel,
    which lifts each point by its distance times that pitch.
    """
    travel = c2w[-1, :3, 3] - c2w[0, :3, 3]
    travel = travel / np.linalg.norm(travel)
    level = up - (up @ travel) * travel
    return level / np.linalg.norm(level)


# --------------------------------------------------------------------------- metric poses

@dataclass
class MetricRig:
    """Poses in the builder's conventions: ``c2w`` and ``ego2world`` (F, 4, 4) in metres, the
    world at the first ego pose with z up; ``cam2ego`` the camera's fixed mount; ``scale``
    metres per reconstruction unit; ``world_from_model`` the similarity that maps reconstruction
    points into the world (points = (R s x + t))."""

    c2w: np.ndarray
    ego2world: np.ndarray
    cam2ego: np.ndarray
    scale: float
    world_from_model: np.ndarray = field(repr=False)

    def points(self, model_points: np.ndarray) -> np.ndarray:
        return model_points @ self.world_from_model[:3, :3].T + self.world_from_model[:3, 3]


def _level_frame(up: np.ndarray, forward: np.ndarray) -> np.ndarray:
    """Rotation whose columns are x forward (``forward`` made level), y left, z ``up``."""
    x = forward - (forward @ up) * up
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(up, x), up], axis=1)


def _mean_rotation(rotations: np.ndarray) -> np.ndarray:
    """The rotation nearest the element-wise mean of ``rotations`` (chordal L2 mean)."""
    u, _, vt = np.linalg.svd(rotations.mean(axis=0))
    r = u @ vt
    if np.linalg.det(r) < 0:
        r = u @ np.diag([1.0, 1.0, -1.0]) @ vt
    return r


def metric_rig(c2w_model: np.ndarray, up: np.ndarray, height: float, scale: float) -> MetricRig:
    """Metric poses of registered cameras ``c2w_model`` (F, 4, 4) ``height`` model units above
    a road whose unit normal is ``up``.

    The camera's mount on the vehicle is fixed: ``cam2ego`` is the mean over frames of the
    camera's attitude relative to a level frame whose x is its forward direction along the road,
    placed on the road under the camera. Each frame's ego pose is then its camera pose times the
    inverse mount, so ``c2w = ego2world . cam2ego`` holds exactly and the ego's y axis (the
    lateral shift) is level with the road wherever the camera's attitude on the vehicle is.
    """
    level = np.stack([_level_frame(up, c[:3, 2]) for c in c2w_model])
    mount = _mean_rotation(np.einsum("fji,fjk->fik", level, c2w_model[:, :3, :3]))
    cam2ego = geometry.make_pose(mount, [0.0, 0.0, height * scale])
    # model frame -> metric frame at the first ego pose: rotate, scale, re-anchor
    ego0 = c2w_model[0] @ geometry.invert(geometry.make_pose(mount, [0.0, 0.0, height]))
    rot0 = ego0[:3, :3].T
    world_from_model = np.eye(4)
    world_from_model[:3, :3] = scale * rot0
    world_from_model[:3, 3] = -scale * rot0 @ ego0[:3, 3]
    c2w = np.repeat(np.eye(4)[None], len(c2w_model), axis=0)
    c2w[:, :3, :3] = np.einsum("ij,fjk->fik", rot0, c2w_model[:, :3, :3])
    c2w[:, :3, 3] = (c2w_model[:, :3, 3] - ego0[:3, 3]) @ (scale * rot0).T
    ego2world = c2w @ geometry.invert(cam2ego)
    return MetricRig(c2w=c2w, ego2world=ego2world, cam2ego=cam2ego, scale=float(scale),
                     world_from_model=world_from_model)
