"""``video:<file or folder>?fps=…&fx=…&height_m=…`` scenes: one monocular camera, poses by SfM.

A dashcam video (any container PyAV reads) or a folder of frames (sorted by name) becomes a
canonical scene with one camera, ``front``: frames sampled at ``fps`` over ``[start, end)``
seconds, poses from :mod:`paradrive.ingest.sfm` in metres (the road plane and the camera's
height above it, or a speed / GPS track beside the video), the triangulated points stored where
LiDAR points go (``lidar/<frame>.npy``, each point under every frame that sees it) so the fit
starts from them, no actors.

Query keys (all optional):

- ``fps``: frames per second to sample (default 10, the rate of the paper's logs; a folder of
  frames is taken to be at this rate);
- ``fx, fy, cx, cy`` (pixels of the video; all four) or ``fov_deg`` (horizontal, centred
  principal point): known intrinsics are held fixed; without them SfM estimates one shared
  camera with radial distortion, the images are undistorted and the estimate is reported;
- ``height_m``: the camera's height above the road (default 1.5 m, a car's dashcam);
- ``start``, ``end``: the time range in seconds;
- ``truth``: the ``synthetic:`` URI the video was rendered from (``paradrive export video``), so
  ``paradrive eval`` can compare shifted views with the true ones.

A track ``<stem>.csv`` beside the video, with columns ``t,speed_mps`` (t: seconds from the
video's start, speed in m/s) or ``t,lat,lon`` (degrees, WGS84), sets the scale instead of the
height: the distance it travels between the first and the last frame over the SfM path length.
Both scales are recorded, with their disagreement.
"""

from __future__ import annotations

import csv
import math
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from paradrive.errors import ParaDriveError, SceneError
from paradrive.ingest.common import fps_from, save_points
from paradrive.ingest.roadmotion import road_motion_height
from paradrive.ingest.sfm import (Intrinsics, Reconstruction, RoadPlane, SfmError, fit_road_plane,
                                  format_runs, level_with_path, metric_rig, path_length, reconstruct,
                                  registered_runs)
from paradrive.ingest.undistort import distortion_is_zero, undistort_image
from paradrive.ingest.videomasks import write_video_masks
from paradrive.scene import Camera, Frame, FrameCamera, Scene, write_image
from paradrive.uri import SceneURI

if TYPE_CHECKING:
    from paradrive.contracts.params import IngestParams

CAMERA = "front"
DEFAULT_FPS = 10.0
# nuScenes' CAM_FRONT sits 1.51 m above the road; a car's dashcam behind the windscreen is near it
DEFAULT_HEIGHT_M = 1.5
# SfM needs a few frames of parallax and the fit a few views; fewer kept frames is an error
MIN_FRAMES = 8
# a trajectory shorter than this (m) after scaling is a parked car: no baseline for SfM
MIN_PATH_M = 1.0
QUERY_KEYS = {"fps": float, "fx": float, "fy": float, "cx": float, "cy": float,
              "fov_deg": float, "height_m": float, "start": float, "end": float, "truth": str}
FRAME_SUFFIXES = (".jpg", ".jpeg", ".png")


@dataclass(frozen=True)
class VideoOptions:
    """The URI's query, typed, with the defaults filled in."""

    fps: float
    height_m: float
    start: float
    end: float | None
    intrinsics: tuple[float, float, float, float] | None
    fov_deg: float | None
    truth: str | None


def options_of(uri: SceneURI) -> VideoOptions:
    """The typed query of a ``video:`` URI; SceneError for an unknown key or a bad value."""
    q: dict[str, Any] = {}
    for key, value in uri.query.items():
        if key not in QUERY_KEYS:
            raise SceneError(f"unknown video option {key!r} in {uri.text!r}", scene_id=uri.scene_id,
                             fix=f"use one of {', '.join(QUERY_KEYS)}")
        try:
            q[key] = QUERY_KEYS[key](value)
        except ValueError as exc:
            raise SceneError(f"video option {key}={value!r} is not a number", scene_id=uri.scene_id,
                             fix="fix the scene URI") from exc
    given = [k for k in ("fx", "fy", "cx", "cy") if k in q]
    if given and len(given) < 4:
        raise SceneError(f"video URI {uri.text!r} gives {', '.join(given)} but not all of fx, fy, "
                         f"cx, cy", scene_id=uri.scene_id,
                         fix="give all four intrinsics, or fov_deg, or none to estimate them")
    for key in ("fps", "height_m", "fov_deg", "fx", "fy"):
        if key in q and not (q[key] > 0 and math.isfinite(q[key])):
            raise SceneError(f"video option {key}={uri.query[key]!r} must be positive",
                             scene_id=uri.scene_id, fix="fix the scene URI")
    if "fov_deg" in q and not q["fov_deg"] < 180:
        raise SceneError(f"video option fov_deg={uri.query['fov_deg']!r} must be below 180",
                         scene_id=uri.scene_id, fix="give the horizontal field of view in degrees")
    start, end = q.get("start", 0.0), q.get("end")
    if start < 0 or (end is not None and end <= start):
        raise SceneError(f"video time range start={start:g} end={end} is empty or negative",
                         scene_id=uri.scene_id, fix="give 0 <= start < end, in seconds")
    return VideoOptions(fps=q.get("fps", DEFAULT_FPS), height_m=q.get("height_m", DEFAULT_HEIGHT_M),
                        start=start, end=end,
                        intrinsics=tuple(q[k] for k in ("fx", "fy", "cx", "cy")) if given else None,
                        fov_deg=q.get("fov_deg"), truth=q.get("truth"))


# --------------------------------------------------------------------------- frames

@dataclass
class Footage:
    """The sampled frames: pixels (F, H, W, 3), their source frame numbers and times (s)."""

    pixels: np.ndarray
    source_frames: list[int]
    times: np.ndarray


def sample_times(count: int, rate: float, opts: VideoOptions) -> list[int]:
    """Source frame numbers of a ``count``-frame source at ``rate`` sampled at ``opts.fps``
    within ``[start, end)``: the nearest source frame to each sample time, without repeats."""
    duration = count / rate
    end = duration if opts.end is None else min(opts.end, duration)
    times = np.arange(opts.start, end - 1e-9, 1.0 / opts.fps)
    picks = np.minimum(np.round(times * rate).astype(np.int64), count - 1)
    return sorted(set(int(i) for i in picks))


def read_footage(path: Path, opts: VideoOptions, *, scene_id: str) -> Footage:
    """The sampled frames of a video file or a folder of frames; SceneErrors name the file."""
    if not path.exists():
        raise SceneError("video file is missing", scene_id=scene_id, path=path,
                         fix="check the path in the scene URI")
    if path.is_dir():
        return _folder_footage(path, opts, scene_id=scene_id)
    count, rate = _probe(path, scene_id=scene_id)
    wanted = sample_times(count, rate, opts)
    if not wanted:
        raise SceneError(f"no frame of the {count / rate:.2f} s video lies in the time range",
                         scene_id=scene_id, path=path, fix="give start/end within the video")
    from paradrive.video import decode_frames

    try:
        pixels = decode_frames(path, wanted, seek=False)
    except ParaDriveError as exc:
        raise SceneError(f"video is truncated or corrupt: frames up to {wanted[-1]} were expected "
                         f"({count} by its header) and do not decode", scene_id=scene_id, path=path,
                         fix="re-encode or re-download the video, or trim the range with end=") from exc
    return Footage(pixels=pixels, source_frames=wanted, times=np.asarray(wanted) / rate)


def _probe(path: Path, *, scene_id: str) -> tuple[int, float]:
    """Frame count and frame rate of a video file from its header."""
    import av

    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                raise SceneError("file has no video stream", scene_id=scene_id, path=path,
                                 fix="give a video file (mp4, mkv, mov, ...) or a folder of frames")
            stream = container.streams.video[0]
            rate = float(stream.average_rate or stream.guessed_rate or 0)
            count = int(stream.frames or 0)
            if not count and stream.duration and stream.time_base:
                count = int(round(float(stream.duration * stream.time_base) * rate))
    except (av.error.FFmpegError, OSError) as exc:
        raise SceneError(f"video cannot be opened ({exc})", scene_id=scene_id, path=path,
                         fix="the file is not a video or is corrupt: re-encode or re-download it"
                         ) from exc
    if rate <= 0 or count <= 0:
        raise SceneError(f"video header gives {count} frames at {rate:g} fps", scene_id=scene_id,
                         path=path, fix="re-encode the video (ffmpeg -i IN -c:v libx264 OUT.mp4)")
    return count, rate


def _folder_footage(folder: Path, opts: VideoOptions, *, scene_id: str) -> Footage:
    """Frames of a folder, sorted by name, taken to be at ``opts.fps``."""
    from paradrive.scene import read_image

    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in FRAME_SUFFIXES)
    if not files:
        raise SceneError(f"folder has no frames ({', '.join(FRAME_SUFFIXES)})", scene_id=scene_id,
                         path=folder, fix="give a video file or a folder of JPEG/PNG frames")
    wanted = sample_times(len(files), opts.fps, opts)
    pixels = [read_image(files[i], scene_id=scene_id) for i in wanted]
    if any(p.shape != pixels[0].shape for p in pixels):
        raise SceneError("frames of the folder differ in size", scene_id=scene_id, path=folder,
                         fix="give frames of one camera at one size")
    return Footage(pixels=np.stack(pixels), source_frames=wanted,
                   times=np.asarray(wanted) / opts.fps)


def given_intrinsics(opts: VideoOptions, width: int, height: int) -> Intrinsics | None:
    """The URI's intrinsics (fx, fy, cx, cy, or fov_deg with a centred principal point)."""
    if opts.intrinsics is not None:
        return Intrinsics(*opts.intrinsics)
    if opts.fov_deg is not None:
        f = 0.5 * width / math.tan(math.radians(opts.fov_deg) / 2)
        return Intrinsics(f, f, 0.5 * width, 0.5 * height)
    return None


# --------------------------------------------------------------------------- the track

def track_path(video: Path) -> Path:
    """``<stem>.csv`` beside the video (for a folder of frames: ``<folder>.csv`` beside it)."""
    return video.with_suffix(".csv") if video.is_file() else video.parent / f"{video.name}.csv"


def track_distance(path: Path, t0: float, t1: float, *, scene_id: str) -> tuple[float, str]:
    """Metres travelled between ``t0`` and ``t1`` seconds by the track at ``path``, and its kind
    (``speed`` or ``gps``): the speed integrated (trapezoids on a 0.01 s grid) or the great-circle
    polyline through the positions interpolated on that grid."""
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
        cols = set(rows[0]) if rows else set()
        t = np.array([float(r["t"]) for r in rows])
        kind = "speed" if {"t", "speed_mps"} <= cols else "gps" if {"t", "lat", "lon"} <= cols else ""
        if not kind:
            raise KeyError("columns")
        grid = np.arange(t0, t1 + 1e-9, 0.01)
        if kind == "speed":
            speed = np.interp(grid, t, [float(r["speed_mps"]) for r in rows])
            return float(np.sum(0.5 * (speed[1:] + speed[:-1]) * np.diff(grid))), kind
        lat = np.radians(np.interp(grid, t, [float(r["lat"]) for r in rows]))
        lon = np.radians(np.interp(grid, t, [float(r["lon"]) for r in rows]))
        a = (np.sin(np.diff(lat) / 2) ** 2
             + np.cos(lat[:-1]) * np.cos(lat[1:]) * np.sin(np.diff(lon) / 2) ** 2)
        return float(np.sum(2 * 6371008.8 * np.arcsin(np.sqrt(a)))), kind
    except (OSError, KeyError, ValueError, TypeError) as exc:
        raise SceneError(f"track is not a CSV with columns t,speed_mps or t,lat,lon ({exc})",
                         scene_id=scene_id, path=path,
                         fix="fix the track's columns, or remove it to scale by the camera height"
                         ) from exc


# --------------------------------------------------------------------------- the scene

def _work_images(footage: Footage, work: Path) -> list[str]:
    """The sampled frames as PNGs for SfM (lossless, so features see what the video holds)."""
    names = [f"{i:06d}.png" for i in range(len(footage.pixels))]
    for name, pixels in zip(names, footage.pixels):
        write_image(work / "images" / name, pixels)
    return names


def _kept_run(rec: Reconstruction, *, scene_id: str, path: Path) -> tuple[int, int]:
    """The longest contiguous run of registered frames; SceneError when it is too short."""
    runs = registered_runs(rec.registered)
    n = len(rec.registered)
    best = max(runs, key=lambda r: (r[1] - r[0], -r[0]), default=None)
    if best is None or best[1] - best[0] + 1 < MIN_FRAMES:
        raise SceneError(f"structure from motion registered frames {format_runs(runs)} of 0-{n - 1}: "
                         f"no contiguous run of {MIN_FRAMES} frames", scene_id=scene_id, path=path,
                         fix="lower fps= (more motion between frames), give the intrinsics "
                             "(fx=&fy=&cx=&cy= or fov_deg=), or trim start=/end= to the moving part")
    return best


def read(uri: SceneURI, out_dir: Path, params: IngestParams, scene_id: str) -> Scene:
    opts = options_of(uri)
    path = Path(uri.path)
    footage = read_footage(path, opts, scene_id=scene_id)
    if params.max_frames is not None:
        keep = params.max_frames
        footage = Footage(footage.pixels[:keep], footage.source_frames[:keep], footage.times[:keep])
    n, height, width = footage.pixels.shape[:3]
    if n < MIN_FRAMES:
        raise SceneError(f"{n} frames sampled at {opts.fps:g} fps, at least {MIN_FRAMES} are needed",
                         scene_id=scene_id, path=path,
                         fix="use a longer video or time range, or a higher fps=")
    work = out_dir / "sfm"
    try:
        rec = reconstruct(work / "images", _work_images(footage, work), work,
                          intrinsics=given_intrinsics(opts, width, height))
    except SfmError as exc:
        raise SceneError(f"structure from motion failed: {exc}", scene_id=scene_id, path=path,
                         fix="a video from a moving vehicle is needed: trim start=/end= to where "
                             "it drives, lower fps=, or give the intrinsics") from exc
    finally:
        shutil.rmtree(work / "images", ignore_errors=True)
    first, last = _kept_run(rec, scene_id=scene_id, path=path)
    scene = _scene(uri, rec, footage, opts, (first, last), out_dir, params, scene_id)
    shutil.rmtree(work, ignore_errors=True)
    return scene


def _scale(rec: Reconstruction, run: slice, plane: RoadPlane, up: np.ndarray, frame,
           opts: VideoOptions, footage: Footage, path: Path,
           scene_id: str) -> tuple[float, float, dict]:
    """Metres per model unit, from the camera's height above the road (measured by the road's
    motion, else by the SfM points on it) or from the track where there is one; that height in
    model units; what was measured."""
    start = time.perf_counter()
    motion = road_motion_height(frame, rec.c2w[run], rec.intrinsics.K(), up, plane.height)
    seconds = time.perf_counter() - start
    camera_height = motion.height if motion is not None else plane.height
    by_height = opts.height_m / camera_height
    doc: dict[str, Any] = {"source": "height", "height_m": opts.height_m, "by_height": by_height,
                           "height_from": "road motion" if motion is not None else "road points",
                           "by_road_points": opts.height_m / plane.height}
    if motion is not None:
        doc["road_motion"] = {"pairs": len(motion.pairs), "spread": motion.spread,
                              "seconds": seconds}
    track = track_path(path)
    if track.is_file():
        times = footage.times[run]
        metres, kind = track_distance(track, float(times[0]), float(times[-1]), scene_id=scene_id)
        by_track = metres / path_length(rec.c2w[run])
        doc.update(source=kind, track=str(track), by_track=by_track,
                   height_vs_track=by_height / by_track - 1.0,
                   camera_height_by_track_m=camera_height * by_track)
        return by_track, camera_height, doc
    return by_height, camera_height, doc


def _scene(uri: SceneURI, rec: Reconstruction, footage: Footage, opts: VideoOptions,
           kept: tuple[int, int], out_dir: Path, params: IngestParams, scene_id: str) -> Scene:
    path = Path(uri.path)
    run = slice(kept[0], kept[1] + 1)
    try:
        plane = fit_road_plane(rec)
    except SfmError as exc:
        raise SceneError(f"no metric scale: {exc}", scene_id=scene_id, path=path,
                         fix="the camera must see the road ahead: trim start=/end= to where it "
                             "does, or give a speed/GPS track as <stem>.csv (t,speed_mps)") from exc
    K, dist = rec.intrinsics, rec.distortion

    def frame(k: int) -> np.ndarray:
        """Kept frame ``k``, undistorted."""
        pixels = footage.pixels[kept[0] + k]
        return pixels if distortion_is_zero(dist) else undistort_image(pixels, K.K(), dist)

    up = level_with_path(plane.normal, rec.c2w[run])
    scale, camera_height, scale_doc = _scale(rec, run, plane, up, frame, opts, footage, path,
                                             scene_id)
    rig = metric_rig(rec.c2w[run], up, camera_height, scale)
    travelled = path_length(rig.c2w)
    if travelled < MIN_PATH_M:
        raise SceneError(f"the camera moves {travelled:.2f} m over the kept frames: a static "
                         f"camera gives no baseline", scene_id=scene_id, path=path,
                         fix="trim start=/end= to where the vehicle drives")
    camera = Camera(name=CAMERA, width=int(footage.pixels.shape[2]),
                    height=int(footage.pixels.shape[1]), fx=K.fx, fy=K.fy, cx=K.cx, cy=K.cy,
                    cam2ego=rig.cam2ego)
    frames = []
    for k, i in enumerate(range(kept[0], kept[1] + 1)):
        rel = f"images/{CAMERA}/{k:06d}.{params.image_ext}"
        write_image(out_dir / rel, frame(k), quality=params.jpeg_quality)
        frames.append(Frame(index=k, timestamp_us=int(round(footage.times[i] * 1e6)),
                            ego2world=rig.ego2world[k],
                            cameras={CAMERA: FrameCamera(image=rel, c2w=rig.c2w[k])}))
    if params.lidar:
        _save_model_points(rec, rig, kept, out_dir)
    masks = write_video_masks(frame, rig.c2w, rig.ego2world, K.K(), out_dir, CAMERA, scene_id=scene_id)
    video = {"file": uri.path, "fps": opts.fps, "source_frames": footage.source_frames[run],
             "intrinsics": {"fx": K.fx, "fy": K.fy, "cx": K.cx, "cy": K.cy,
                            "estimated": rec.estimated, "distortion": list(dist)},
             "registered": format_runs(registered_runs(rec.registered)),
             "sampled": len(footage.source_frames), "kept": [kept[0], kept[1]],
             "scale_m_per_unit": scale, "scale": scale_doc, "path_m": travelled,
             "road_plane": {"inliers": plane.inliers, "candidates": plane.candidates},
             "points": int(len(rec.points)), "sfm_seconds": rec.seconds, "models": rec.models,
             "masks": masks}
    if opts.truth:
        video["truth"] = opts.truth
    stamps = [f.timestamp_us for f in frames]  # a video slower than fps= keeps its own rate
    return Scene(scene_id=scene_id, dataset="video", source=uri.text, fps=fps_from(stamps, opts.fps),
                 cameras={CAMERA: camera}, frames=frames, extra={"video": video})


def _save_model_points(rec: Reconstruction, rig, kept: tuple[int, int], out_dir: Path) -> None:
    """The triangulated points in the scene world, each under every kept frame that sees it
    (``lidar/<frame>.npy``), as a LiDAR sweep holds what its frame sees: the fit's depth term
    then checks each point in all its views, near ones included, not only where it was first
    seen far ahead; its point initialisation merges the copies (voxel filter)."""
    world = rig.points(rec.points).astype(np.float32)
    inside = (rec.seen_frame >= kept[0]) & (rec.seen_frame <= kept[1])
    frame, point = rec.seen_frame[inside] - kept[0], rec.seen_point[inside]
    for k in np.unique(frame):
        save_points(out_dir, int(k), world[point[frame == k]])
