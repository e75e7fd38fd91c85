"""``video:<file or folder>?fx=…&k1=…&height_m=…`` scenes: one monocular camera, poses by SfM.

A dashcam video (any container PyAV reads) or a folder of frames (sorted by name) becomes a
canonical scene with one camera, ``front``: frames sampled over ``[start, end)`` seconds,
undistorted with the camera's lens model, poses from :mod:`paradrive.ingest.sfm` in metres (the
road plane and the camera's height above it measured by independent cues per frame range,
:mod:`paradrive.ingest.scalecue`, or a speed / GPS track beside the video), the
triangulated points stored where LiDAR points go (``lidar/<frame>.npy``, each point under every
frame that sees it) so the fit starts from them, no actors.

Query keys (all optional; :data:`KEYS` holds their ranges, and an unknown key or a value out of
range is a usage error, raised before any work):

- ``fps``: frames per second to sample (default: the video's own rate, at most
  ``ingest.video_max_fps``; a folder of frames is taken to be at ``fps``, default
  ``ingest.video_folder_fps``);
- ``fx, fy, cx, cy`` (pixels of the video, OpenCV's convention: pixel centres at integer
  coordinates, as ``calibrateCamera`` reports them; all four) and the lens distortion ``k1, k2,
  p1, p2, k3`` (OpenCV's radial-tangential model), or ``calib=FILE.json`` holding the same keys
  (and the ``width``/``height`` they were calibrated at), or ``fov_deg`` (horizontal, centred
  principal point): known intrinsics are held fixed and the frames are undistorted with
  :mod:`paradrive.ingest.undistort` (the code the Waymo reader uses); without them the focal
  length is found from the frames (:mod:`paradrive.ingest.focal`: a pinhole held fixed at
  candidate focals, the reprojection error's minimum on a bend) and reported; a drive that
  turns too little to show it is mapped with the focal at the middle of the range searched,
  which keeps lateral offsets at their size and leaves the lengths along the road as uncertain
  as the focal (``video.scale.uncertainty`` against ``across_uncertainty``, a warning);
- ``height_m``: the camera's height above the road (default 1.5 m, a car's dashcam);
- ``start``, ``end``: the time range in seconds;
- ``truth``: the ``synthetic:`` URI the video was rendered from (``paradrive export video``), so
  ``paradrive eval`` can compare shifted views with the true ones.

A track ``<stem>.csv`` beside the video, with columns ``t,speed_mps`` (t: seconds from the
video's start, speed in m/s) or ``t,lat,lon`` (degrees, WGS84), sets the scale instead of the
height: the distance it travels between the first and the last frame over the SfM path length.
Both scales are recorded, with their disagreement.

Frames are streamed, never held all at once: a first pass decodes each sampled frame at the
size SfM works at (``ingest.video_sfm_width``) and writes it for SfM; once the poses are known
a second pass decodes the kept frames at full size, undistorts and stores them. A 4K video then
needs a few frames' worth of memory, not the clip's.
"""

from __future__ import annotations

import contextlib
import csv
import json
import logging
import math
import resource
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from paradrive.errors import ConfigError, ParaDriveError, SceneError
from paradrive.ingest.common import fps_from, image_written, save_points
from paradrive.ingest.frameclock import Clock, frames_at, read_clock
from paradrive.ingest import scale_roadmotion, scale_roadpoints
from paradrive.ingest.focal import FOV_RANGE_DEG, FocalEstimate, estimate_focal
from paradrive.ingest.roadmotion import RoadMotion, road_motion_height
from paradrive.ingest.scalecue import (CombinedScale, ScaleError, combine, format_range, profile,
                                       split_ranges)
from paradrive.ingest.undistort import distortion_is_zero, undistort_image
from paradrive.ingest.videomasks import write_video_masks
from paradrive.ingest.sfm import (Intrinsics, Reconstruction, RoadPlane, SfmError, fit_road_plane,
                                  format_runs, level_with_path, metric_rig, path_length, reconstruct,
                                  registered_runs, steady_runs, without_drift)
from paradrive.scene import Camera, Frame, FrameCamera, Scene, write_image
from paradrive.uri import SceneURI

if TYPE_CHECKING:
    from paradrive.contracts.params import IngestParams

log = logging.getLogger("paradrive.ingest.video")

CAMERA = "front"
# nuScenes' CAM_FRONT sits 1.51 m above the road; a car's dashcam behind the windscreen is near it
DEFAULT_HEIGHT_M = 1.5
# SfM needs a few frames of parallax and the fit a few views; fewer kept frames is an error
MIN_FRAMES = 8
# a trajectory shorter than this (m) after scaling is a parked car: no baseline for SfM
MIN_PATH_M = 1.0
FRAME_SUFFIXES = (".jpg", ".jpeg", ".png")
INTRINSICS = ("fx", "fy", "cx", "cy")
DISTORTION = ("k1", "k2", "p1", "p2", "k3")
# the scale is measured per range of the kept frames, by each cue on its own: the halves of the
# run, each at least ingest.video_scale_range_frames long; a half's scale against the other's
# shows SfM's drift along the video
SCALE_RANGES = 2
# a speed or GPS track is taken at its word: a speedometer or a phone's GPS is good to about 1 %
TRACK_UNCERTAINTY = 0.01
UNCERTAIN_FIX = ("give a speed or GPS track as <stem>.csv (t,speed_mps or t,lat,lon), a longer "
                 "clip, or more frames (a higher fps=)")
# where nobody gave the camera: a wide lens left distorted bends the road out of its plane
UNCALIBRATED_FIX = ("; the camera's calibration with its lens distortion (calib=FILE.json or "
                    "fx=…&k1=…) lets the road be measured where a wide lens bends it")


@dataclass(frozen=True)
class Key:
    """One query key: its type and, for a number, its range (``low`` excluded when ``open_low``,
    ``high`` excluded when ``open_high``)."""

    kind: type
    text: str
    low: float = -math.inf
    high: float = math.inf
    open_low: bool = False
    open_high: bool = False

    def admits(self, value: float) -> bool:
        above = value > self.low if self.open_low else value >= self.low
        below = value < self.high if self.open_high else value <= self.high
        return math.isfinite(value) and above and below


# a day of video at most: a time beyond it is a typo, and np.arange over it would not fit in memory
DAY_S = 86400.0
KEYS: dict[str, Key] = {
    "fps": Key(float, "(0, 1000] frames a second", 0.0, 1000.0, open_low=True),
    "fx": Key(float, "(0, 100000] px", 0.0, 1e5, open_low=True),
    "fy": Key(float, "(0, 100000] px", 0.0, 1e5, open_low=True),
    "cx": Key(float, "[0, 100000] px", 0.0, 1e5),
    "cy": Key(float, "[0, 100000] px", 0.0, 1e5),
    "k1": Key(float, "[-10, 10]", -10.0, 10.0),
    "k2": Key(float, "[-10, 10]", -10.0, 10.0),
    "p1": Key(float, "[-1, 1]", -1.0, 1.0),
    "p2": Key(float, "[-1, 1]", -1.0, 1.0),
    "k3": Key(float, "[-10, 10]", -10.0, 10.0),
    "calib": Key(str, "a JSON file with fx, fy, cx, cy (and k1, k2, p1, p2, k3, width, height)"),
    "fov_deg": Key(float, "(0, 180) degrees", 0.0, 180.0, open_low=True, open_high=True),
    "height_m": Key(float, "(0, 10] m", 0.0, 10.0, open_low=True),
    "start": Key(float, "[0, 86400) s", 0.0, DAY_S, open_high=True),
    "end": Key(float, "(0, 86400] s", 0.0, DAY_S, open_low=True),
    "truth": Key(str, "the synthetic: URI the video shows"),
}
# what a calibration file may hold besides the camera: its own description, as written by the
# tools that make one (the video it belongs to, its size and how it was calibrated)
CALIB_NOTES = ("file", "sha256", "fps", "frames", "model", "calibration")


def accepted_keys() -> str:
    """The keys and their ranges, for messages."""
    return "; ".join(f"{name} {key.text}" for name, key in KEYS.items())


def _usage(uri: SceneURI, what: str) -> ConfigError:
    return ConfigError(f"video URI {uri.text!r}: {what}; accepted keys: {accepted_keys()}")


@dataclass(frozen=True)
class Calibration:
    """A camera as given: pinhole ``fx, fy, cx, cy`` in OpenCV's convention (pixel centres at
    integer coordinates), OpenCV's ``distortion`` (k1, k2, p1, p2, k3), the ``size`` (width,
    height) it was calibrated at when known, and where it came from."""

    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...]
    size: tuple[int, int] | None
    source: str

    def at(self, width: int, height: int) -> Intrinsics:
        """The pinhole at a ``width`` x ``height`` video in the builder's convention (pixel
        centres at +0.5), scaled from the calibrated size (the same lens at another resolution)."""
        sx, sy = (1.0, 1.0) if self.size is None else (width / self.size[0], height / self.size[1])
        return Intrinsics(self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx, (self.cy + 0.5) * sy)


@dataclass(frozen=True)
class VideoOptions:
    """The URI's query, typed; None where the ingest parameters decide (``fps``)."""

    fps: float | None
    height_m: float
    start: float
    end: float | None
    calibration: Calibration | None
    fov_deg: float | None
    truth: str | None


def options_of(uri: SceneURI) -> VideoOptions:
    """The typed query of a ``video:`` URI; ConfigError (a usage error, exit 2) naming the
    accepted keys and ranges for an unknown key, a value out of range or a bad calibration file."""
    q: dict[str, Any] = {}
    for name, value in uri.query.items():
        key = KEYS.get(name)
        if key is None:
            raise _usage(uri, f"unknown key {name!r}")
        if key.kind is str:
            q[name] = value
            continue
        try:
            number = float(value)
        except ValueError:
            raise _usage(uri, f"{name}={value!r} is not a number") from None
        if not key.admits(number):
            raise _usage(uri, f"{name}={value} is outside {key.text}")
        q[name] = number
    start, end = q.get("start", 0.0), q.get("end")
    if end is not None and end <= start:
        raise _usage(uri, f"the time range start={start:g} end={end:g} is empty")
    return VideoOptions(fps=q.get("fps"), height_m=q.get("height_m", DEFAULT_HEIGHT_M),
                        start=start, end=end, calibration=_calibration(uri, q),
                        fov_deg=q.get("fov_deg"), truth=q.get("truth"))


def check(uri: SceneURI) -> None:
    """Refuse a ``video:`` URI that no ingest could take, before any work (ConfigError)."""
    options_of(uri)


def _calibration(uri: SceneURI, q: dict[str, Any]) -> Calibration | None:
    """The camera the URI gives: its keys, or ``calib=``'s file, or None."""
    given = [k for k in (*INTRINSICS, *DISTORTION) if k in q]
    if "calib" in q:
        if given or "fov_deg" in q:
            raise _usage(uri, f"calib= and {', '.join(given) or 'fov_deg'} both give the camera: "
                              f"give one of them")
        return _calibration_file(uri, q["calib"])
    if not given:
        return None
    if "fov_deg" in q:
        raise _usage(uri, f"fov_deg and {', '.join(given)} both give the camera: give one of them")
    missing = [k for k in INTRINSICS if k not in q]
    if missing:
        raise _usage(uri, f"{', '.join(given)} given without {', '.join(missing)}: the "
                          f"intrinsics need all of fx, fy, cx, cy")
    return Calibration(float(q["fx"]), float(q["fy"]), float(q["cx"]), float(q["cy"]),
                       distortion=tuple(float(q.get(k, 0.0)) for k in DISTORTION),
                       size=None, source="the URI")


def _calibration_file(uri: SceneURI, name: str) -> Calibration:
    """The camera of a calibration JSON (``calib=``; relative to the video's folder when not
    absolute), every value checked against :data:`KEYS`."""
    path = Path(name) if Path(name).is_absolute() else Path(uri.path).parent / name
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise _usage(uri, f"calib={name}: {path} cannot be read as JSON ({exc})") from exc
    if not isinstance(doc, dict):
        raise _usage(uri, f"calib={name}: {path} holds no JSON object")
    unknown = [k for k in doc if k not in (*INTRINSICS, *DISTORTION, "width", "height", *CALIB_NOTES)]
    missing = [k for k in INTRINSICS if k not in doc]
    if unknown or missing:
        what = f"unknown key(s) {', '.join(unknown)}" if unknown else f"no {', '.join(missing)}"
        raise _usage(uri, f"calib={name}: {path} has {what} (it holds fx, fy, cx, cy, k1, k2, "
                          f"p1, p2, k3 and optionally width, height)")
    values = {}
    for k in (*INTRINSICS, *DISTORTION):
        value = doc.get(k, 0.0)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not KEYS[k].admits(value):
            raise _usage(uri, f"calib={name}: {k}={value!r} in {path} is outside {KEYS[k].text}")
        values[k] = float(value)
    size = None
    if "width" in doc or "height" in doc:
        w, h = doc.get("width"), doc.get("height")
        if not all(isinstance(v, int) and not isinstance(v, bool) and 0 < v <= 100_000 for v in (w, h)):
            raise _usage(uri, f"calib={name}: width={w!r}, height={h!r} in {path} must both be "
                              f"positive whole pixels")
        size = (int(w), int(h))  # type: ignore[arg-type]
    return Calibration(values["fx"], values["fy"], values["cx"], values["cy"],
                       distortion=tuple(values[k] for k in DISTORTION),
                       size=size, source=str(path))


# --------------------------------------------------------------------------- the camera

def camera_of(opts: VideoOptions, width: int, height: int, *, scene_id: str,
              path: Path) -> tuple[Intrinsics | None, tuple[float, ...]]:
    """The given pinhole at the video's size (None: SfM estimates it) and the lens distortion;
    SceneError where the calibration cannot be this video's camera."""
    cal = opts.calibration
    if cal is None:
        if opts.fov_deg is None:
            return None, (0.0,) * 5
        f = 0.5 * width / math.tan(math.radians(opts.fov_deg) / 2)
        return Intrinsics(f, f, 0.5 * width, 0.5 * height), (0.0,) * 5
    if cal.size is not None:
        sx, sy = width / cal.size[0], height / cal.size[1]
        if abs(sx / sy - 1) > 0.01:
            raise SceneError(f"the calibration ({cal.source}) is for {cal.size[0]}x{cal.size[1]}, "
                             f"the video is {width}x{height}: another shape", scene_id=scene_id,
                             path=path, fix="give the calibration of this camera at this size")
    K = cal.at(width, height)
    if not (0 <= K.cx <= width and 0 <= K.cy <= height):
        raise SceneError(f"the principal point ({K.cx - 0.5:g}, {K.cy - 0.5:g}) of {cal.source} lies "
                         f"outside the {width}x{height} video", scene_id=scene_id, path=path,
                         fix="give cx, cy of this video (pixels, OpenCV's convention)")
    folds = _fold_radius(cal.distortion, K, width, height)
    if folds is not None:
        raise SceneError(f"the lens model of {cal.source} folds the image back beyond "
                         f"{folds:.0f} px from the principal point: it cannot be this camera's",
                         scene_id=scene_id, path=path,
                         fix="check the signs and scale of k1, k2, k3 (OpenCV's model)")
    return K, cal.distortion


def _fold_radius(dist: tuple[float, ...], K: Intrinsics, width: int, height: int) -> float | None:
    """The radius (pixels) within the image's corners where the radial model stops growing (it
    would fold the image), or None where it grows all the way."""
    k1, k2, _, _, k3 = dist
    corners = np.array([[0, 0], [width, 0], [0, height], [width, height]], dtype=np.float64)
    r_max = float(np.max(np.hypot((corners[:, 0] - K.cx) / K.fx, (corners[:, 1] - K.cy) / K.fy)))
    r = np.linspace(0.0, r_max, 512)
    growth = 1 + 3 * k1 * r ** 2 + 5 * k2 * r ** 4 + 7 * k3 * r ** 6
    bad = np.flatnonzero(growth <= 0)
    return None if not len(bad) else float(r[bad[0]] * K.fx)


# --------------------------------------------------------------------------- frames

@dataclass
class Footage:
    """The sampled frames of a video file (or folder ``files``): their source frame numbers (the
    file's presented frames, repeats included) and times (s from the first frame, the file's
    timestamps), the frames' size, the rate sampled at and the source's own (of the frames that
    remain once repeats are dropped; None for a folder)."""

    path: Path
    source_frames: list[int]
    times: np.ndarray
    width: int
    height: int
    fps: float
    native_fps: float | None
    files: list[Path] | None = None
    # a file's clock (frameclock): its frames' times, and the repeats dropped before sampling
    clock: Clock | None = None

    @property
    def skipped(self) -> int:
        """Source frames within the sampled range that were not sampled (repeats dropped are
        not counted: no rate brings them back)."""
        if not self.source_frames:
            return 0
        first, last = self.source_frames[0], self.source_frames[-1]
        repeats = 0 if self.clock is None else sum(first <= i <= last for i in self.clock.repeated)
        return last - first + 1 - len(self.source_frames) - repeats


def sample_times(count: int, rate: float, fps: float, start: float, end: float | None) -> list[int]:
    """Source frame numbers of a ``count``-frame source at ``rate`` sampled at ``fps`` within
    ``[start, end)``: the nearest source frame to each sample time, without repeats."""
    duration = count / rate
    stop = duration if end is None else min(end, duration)
    fps = min(fps, rate)   # above the source's own rate every frame is taken once
    times = np.arange(start, stop - 1e-9, 1.0 / fps) if stop > start else np.zeros(0)
    picks = np.minimum(np.round(times * rate).astype(np.int64), count - 1)
    return sorted(set(int(i) for i in picks))


def sample(path: Path, opts: VideoOptions, params: IngestParams, *, scene_id: str,
           repeats: bool = True) -> Footage:
    """Which frames of the video file or folder to take, by the file's timestamps and, with
    ``repeats``, without its repeated frames (:mod:`paradrive.ingest.frameclock`: one decoding
    pass); SceneErrors name the file."""
    if not path.exists():
        raise SceneError("video file is missing", scene_id=scene_id, path=path,
                         fix="check the path in the scene URI")
    if path.is_dir():
        return _folder(path, opts, params, scene_id=scene_id)
    header = _probe(path, scene_id=scene_id)
    _, _, width, height = header
    clock = read_clock(path, header, scene_id=scene_id, detect=repeats,
                       repeat_ratio=params.video_repeat_ratio)
    rate = clock.fps   # of the frames that remain
    fps = opts.fps if opts.fps is not None else min(rate, params.video_max_fps)
    uniform = not clock.repeated and not clock.variable_rate
    wanted = sample_times(len(clock.times), rate, fps, opts.start, opts.end) if uniform \
        else frames_at(clock, fps, opts.start, opts.end)
    if not wanted:
        raise SceneError(f"no frame of the {clock.times[-1] + 1 / rate:.2f} s video lies in the "
                         f"time range", scene_id=scene_id, path=path,
                         fix="give start/end within the video")
    return Footage(path, wanted, clock.times[wanted], width, height, min(fps, rate), rate,
                   clock=clock)


def needs_focal_search(uri: SceneURI) -> bool:
    """Whether ingesting ``uri`` searches the focal length: no calibration, intrinsics or
    ``fov_deg`` give the camera."""
    opts = options_of(uri)
    return opts.calibration is None and opts.fov_deg is None


def planned_frames(uri: SceneURI, params: IngestParams) -> tuple[int, int, int] | None:
    """What ingesting ``uri`` would sample, from its file's header: (frames, width, height);
    None where there is no file to read yet (a plan made before the videos arrive). A URI no
    ingest could take is a ConfigError."""
    opts = options_of(uri)
    try:
        footage = sample(Path(uri.path), opts, params, scene_id=uri.scene_id, repeats=False)
    except SceneError:
        return None
    frames = len(footage.source_frames)
    return min(frames, params.max_frames or frames), footage.width, footage.height


def _probe(path: Path, *, scene_id: str) -> tuple[int, float, int, int]:
    """Frame count, frame rate and size of a video file from its header."""
    import av

    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                raise SceneError("file has no video stream", scene_id=scene_id, path=path,
                                 fix="give a video file (mp4, mkv, mov, ...) or a folder of frames")
            stream = container.streams.video[0]
            rate = float(stream.average_rate or stream.guessed_rate or 0)
            # the stream's duration over its rate, where known: an MP4's frame count may count
            # frames that never decode (162 in the header of a 160-frame, 6.4 s clip)
            count = int(stream.frames or 0)
            if stream.duration and stream.time_base:
                count = int(round(float(stream.duration * stream.time_base) * rate)) or count
            width, height = int(stream.codec_context.width), int(stream.codec_context.height)
    except MemoryError as exc:
        raise _out_of_memory(path, scene_id, "opening the video") from exc
    except (av.error.FFmpegError, OSError) as exc:
        if not _room_for(0, 0):
            raise _out_of_memory(path, scene_id, "opening the video") from exc
        raise SceneError(f"video cannot be opened ({exc})", scene_id=scene_id, path=path,
                         fix="the file is not a video or is corrupt: re-encode or re-download it"
                         ) from exc
    if rate <= 0 or count <= 0 or width <= 0 or height <= 0:
        raise SceneError(f"video header gives {count} frames of {width}x{height} at {rate:g} fps",
                         scene_id=scene_id, path=path,
                         fix="re-encode the video (ffmpeg -i IN -c:v libx264 OUT.mp4)")
    return count, rate, width, height


def _folder(folder: Path, opts: VideoOptions, params: IngestParams, *, scene_id: str) -> Footage:
    """Frames of a folder, sorted by name, taken to be at ``fps``."""
    from PIL import Image

    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in FRAME_SUFFIXES)
    if not files:
        raise SceneError(f"folder has no frames ({', '.join(FRAME_SUFFIXES)})", scene_id=scene_id,
                         path=folder, fix="give a video file or a folder of JPEG/PNG frames")
    fps = opts.fps if opts.fps is not None else params.video_folder_fps
    wanted = sample_times(len(files), fps, fps, opts.start, opts.end)
    if not wanted:
        raise SceneError(f"no frame of the {len(files) / fps:.2f} s of frames lies in the time "
                         f"range", scene_id=scene_id, path=folder, fix="give start/end within it")
    try:
        with Image.open(files[wanted[0]]) as first:
            width, height = first.size
    except OSError as exc:
        raise SceneError(f"frame cannot be read ({exc})", scene_id=scene_id, path=files[wanted[0]],
                         fix="replace or remove the file") from exc
    return Footage(folder, wanted, np.asarray(wanted) / fps, width, height, fps, None, files)


def each_frame(footage: Footage, sink: Callable[[int, np.ndarray], None], *, scene_id: str,
               size: tuple[int, int] | None = None, only: list[int] | None = None) -> None:
    """Hand sampled frame ``k`` (uint8 (H, W, 3), resized to ``size`` = (height, width) with an
    area filter when given) to ``sink(k, pixels)``, one at a time in order; ``only``: those ``k``.
    Decoding runs out of memory as a memory error, never as a corrupt file."""
    picks = list(range(len(footage.source_frames))) if only is None else list(only)
    try:
        if footage.files is not None:
            _each_file(footage, picks, sink, size, scene_id=scene_id)
        else:
            _each_decoded(footage, picks, sink, size, scene_id=scene_id)
    except MemoryError as exc:
        raise _out_of_memory(footage.path, scene_id, _decoding(footage)) from exc


def _decoding(footage: Footage) -> str:
    return (f"decoding its {footage.width}x{footage.height} frames "
            f"({footage.width * footage.height * 3 / 1e6:.1f} MB each)")


def _each_decoded(footage: Footage, picks: list[int], sink: Callable[[int, np.ndarray], None],
                  size: tuple[int, int] | None, *, scene_id: str) -> None:
    from paradrive import video

    k_of = {footage.source_frames[k]: k for k in picks}
    try:
        video.each_frame(footage.path, sorted(k_of), lambda i, pixels: sink(k_of[i], pixels),
                         size=size, seek=False)
    except ParaDriveError as exc:
        if not _room_for(footage.width, footage.height):
            raise _out_of_memory(footage.path, scene_id, _decoding(footage)) from exc
        raise SceneError(f"video is truncated or corrupt: frames up to {max(k_of)} were expected "
                         f"and do not decode", scene_id=scene_id, path=footage.path,
                         fix="re-encode or re-download the video, or trim the range with end=") from exc


def _each_file(footage: Footage, picks: list[int], sink: Callable[[int, np.ndarray], None],
               size: tuple[int, int] | None, *, scene_id: str) -> None:
    from PIL import Image

    from paradrive.scene import read_image

    assert footage.files is not None
    for k in picks:
        file = footage.files[footage.source_frames[k]]
        pixels = read_image(file, scene_id=scene_id)
        if pixels.shape[:2] != (footage.height, footage.width):
            raise SceneError(f"frames of the folder differ in size ({pixels.shape[1]}x"
                             f"{pixels.shape[0]}, the first is {footage.width}x{footage.height})",
                             scene_id=scene_id, path=file, fix="give frames of one camera at one size")
        if size is not None and size != pixels.shape[:2]:
            pixels = np.asarray(Image.fromarray(pixels).resize((size[1], size[0]), Image.Resampling.BOX))
        sink(k, pixels)


def _room_for(width: int, height: int, frames: int = 4) -> bool:
    """Whether a few frames' worth of memory can still be had. FFmpeg's decoders report an
    allocation that failed as "invalid data" as often as not: a decode that fails where this
    does too ran out of memory, and is not a corrupt file."""
    try:
        np.empty(max(frames * width * height * 3, 64 * 2**20), dtype=np.uint8)
    except MemoryError:
        return False
    return True


def _out_of_memory(path: Path, scene_id: str, doing: str) -> SceneError:
    """An allocation that failed: how much this process held and what bounds it."""
    held = _status_gb("VmHWM") or resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    limit = "no address-space limit" if soft == resource.RLIM_INFINITY else \
        f"an address-space limit of {soft / 2**30:.2f} GB, {_status_gb('VmSize'):.2f} GB mapped"
    return SceneError(f"out of memory {doing}: the process held {held:.2f} GB at its peak, under "
                      f"{limit}", scene_id=scene_id, path=path,
                      fix="give the ingest more memory (stages/ingest.yaml resources.memory_gb and "
                          "the machine's limit), or a smaller video or range (end=)")


def _status_gb(field: str) -> float:
    """A memory figure of this process from /proc/self/status (GB), 0 where there is none."""
    with contextlib.suppress(OSError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(f"{field}:"):
                return int(line.split()[1]) / 2**20
    return 0.0


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


# --------------------------------------------------------------------------- structure from motion

@dataclass
class SfmInput:
    """The frames as SfM sees them: PNGs under ``folder`` named ``names`` (sampled order), at
    ``size`` (width, height), the given pinhole at that size (None: estimated) and the lens
    distortion still in them (zero where they were undistorted on the way)."""

    folder: Path
    names: list[str]
    size: tuple[int, int]
    intrinsics: Intrinsics | None
    distortion: tuple[float, ...]
    seconds: float

    def scale(self, footage: Footage) -> tuple[float, float]:
        """Video pixels per SfM pixel, across and down."""
        return footage.width / self.size[0], footage.height / self.size[1]


def sfm_size(width: int, height: int, max_width: int) -> tuple[int, int]:
    """The size SfM works at: the video's, or ``max_width`` wide with its aspect (even sizes)."""
    if width <= max_width:
        return width, height
    return max_width, max(2, int(round(height * max_width / width / 2)) * 2)


def _sfm_input(footage: Footage, K: Intrinsics | None, dist: tuple[float, ...], work: Path,
               params: IngestParams, *, scene_id: str) -> SfmInput:
    """First pass: every sampled frame at SfM's size, undistorted where the lens is known."""
    start = time.perf_counter()
    size = sfm_size(footage.width, footage.height, params.video_sfm_width)
    sx, sy = size[0] / footage.width, size[1] / footage.height
    small = None if K is None else Intrinsics(K.fx * sx, K.fy * sy, K.cx * sx, K.cy * sy)
    names = [f"{k:06d}.png" for k in range(len(footage.source_frames))]
    folder = work / "images"

    def keep(k: int, pixels: np.ndarray) -> None:
        if small is not None and not distortion_is_zero(dist):
            pixels = undistort_image(pixels, small.K(), dist)
        write_image(folder / names[k], pixels)

    each_frame(footage, keep, scene_id=scene_id, size=(size[1], size[0]))
    undistorted = small is not None
    return SfmInput(folder, names, size, small, (0.0,) * 5 if undistorted else dist,
                    time.perf_counter() - start)


# --------------------------------------------------------------------------- the scene

def _kept_run(rec: Reconstruction, times: np.ndarray, *, scene_id: str, path: Path) -> tuple[int, int]:
    """The longest contiguous run of registered frames whose speeds do not jump
    (:func:`~paradrive.ingest.sfm.steady_runs`, on the frames' own ``times``, seconds);
    SceneError when it is too short."""
    runs = registered_runs(rec.registered)
    steady = steady_runs(rec.c2w, runs, times=times)
    n = len(rec.registered)
    best = max(steady, key=lambda r: (r[1] - r[0], -r[0]), default=None)
    if best is None or best[1] - best[0] + 1 < MIN_FRAMES:
        jumps = "" if steady == runs else f", in steady runs {format_runs(steady)}"
        raise SceneError(f"structure from motion registered frames {format_runs(runs)} of 0-{n - 1}"
                         f"{jumps}: no contiguous run of {MIN_FRAMES} frames", scene_id=scene_id, path=path,
                         fix="lower fps= (more motion between frames), give the intrinsics "
                             "(fx=&fy=&cx=&cy= or fov_deg=), or trim start=/end= to the moving part")
    return best


def read(uri: SceneURI, out_dir: Path, params: IngestParams, scene_id: str) -> Scene:
    try:
        opts = options_of(uri)
    except ConfigError as exc:  # a build checks this first; a direct call fails the scene
        raise SceneError(str(exc), scene_id=scene_id, path=uri.path,
                         fix="fix the scene URI") from exc
    path = Path(uri.path)
    footage = sample(path, opts, params, scene_id=scene_id)
    if params.max_frames is not None and len(footage.source_frames) > params.max_frames:
        keep = params.max_frames
        footage.source_frames, footage.times = footage.source_frames[:keep], footage.times[:keep]
    n = len(footage.source_frames)
    if n < MIN_FRAMES:
        raise SceneError(f"{n} frames sampled at {footage.fps:g} fps, at least {MIN_FRAMES} are "
                         f"needed", scene_id=scene_id, path=path,
                         fix="use a longer video or time range, or a higher fps=")
    K, dist = camera_of(opts, footage.width, footage.height, scene_id=scene_id, path=path)
    work = out_dir / "sfm"
    try:
        sfm_in = _sfm_input(footage, K, dist, work, params, scene_id=scene_id)
        focal = None
        if sfm_in.intrinsics is None:  # nobody calibrated it: the focal from the frames
            focal = _focal(sfm_in, work / "focal", params, scene_id=scene_id, path=path)
            sfm_in.intrinsics = focal.intrinsics(*sfm_in.size)
        rec = _reconstruct(sfm_in, work, scene_id=scene_id, path=path)
        first, last = _kept_run(rec, footage.times, scene_id=scene_id, path=path)
        if focal is not None and not focal.observable:
            turn = _turn_deg(rec.c2w[first:last + 1])
            if turn > params.video_unmeasured_focal_max_turn_deg:
                raise SceneError(_unmeasured_focal_on_a_bend(focal, turn, params),
                                 scene_id=scene_id, path=path,
                                 fix="give fov_deg= (the horizontal field of view) or "
                                     "fx=&fy=&cx=&cy=, or trim start=/end= to a straight stretch"
                                     + UNCALIBRATED_FIX)
            # a straight drive, mapped at the range's middle: only lengths along the road suffer
            log.warning("scene %s (%s): %s", scene_id, path,
                        _unmeasured_focal(focal, params.video_focal_min_rise))
        return _scene(uri, rec, sfm_in, footage, opts, (first, last), out_dir, params, scene_id,
                      focal=focal)
    finally:
        shutil.rmtree(work, ignore_errors=True)


def _focal(sfm_in: SfmInput, work: Path, params: IngestParams, *, scene_id: str,
           path: Path) -> FocalEstimate:
    """The focal length of an uncalibrated camera from its SfM frames (:mod:`paradrive.ingest.focal`)."""
    try:
        return estimate_focal(sfm_in.folder, sfm_in.names, work, sfm_in.size,
                              max_frames=params.video_focal_frames,
                              min_rise=params.video_focal_min_rise)
    except MemoryError as exc:
        raise _out_of_memory(path, scene_id, "searching the focal length") from exc
    except SfmError as exc:
        raise SceneError(f"the focal length could not be found: {exc}", scene_id=scene_id,
                         path=path, fix="give fov_deg= (the horizontal field of view) or "
                                        "fx=&fy=&cx=&cy=, or trim start=/end= to where it drives"
                         ) from exc


def _unmeasured_focal(focal: FocalEstimate, min_rise: float) -> str:
    """Why the frames gave no focal length, in one line, with the search's figures."""
    fov = 2 * math.degrees(math.atan(0.5 * focal.width / focal.held))
    return (f"the focal length could not be measured from the frames: the drive turns too "
            f"little to show it ({_search_figures(focal, min_rise)}); mapped "
            f"with it held at {focal.held:.0f} px (a {fov:.0f} deg field of view, the middle of "
            f"the {FOV_RANGE_DEG[0]:g}-{FOV_RANGE_DEG[1]:g} deg searched): lateral shifts keep "
            f"their size (the camera's height sets it), lengths along the road are uncertain by "
            f"{focal.scale_uncertainty:.0%}; fov_deg= or fx=&fy=&cx=&cy= would fix that")


def _search_figures(focal: FocalEstimate, min_rise: float) -> str:
    """The focal search's trials and the rise it asked for, as a message says them."""
    errors = ", ".join(f"{t.error:.2f} px at {t.focal:.0f}" for t in focal.trials
                       if math.isfinite(t.error))
    return (f"mean reprojection error over {focal.frames} frames: {errors}; no single minimum "
            f"that a focal one step away raises by {min_rise:.0%}")


def _turn_deg(c2w: np.ndarray) -> float:
    """How far the camera's line of sight turns from the first frame's (degrees, the most)."""
    ahead = c2w[:, :3, 2]
    return float(np.degrees(np.arccos(np.clip(ahead @ ahead[0], -1.0, 1.0))).max())


def _unmeasured_focal_on_a_bend(focal: FocalEstimate, turn: float, params: IngestParams) -> str:
    """Why a clip whose focal was not measured cannot be taken as a straight drive."""
    return (f"the focal length could not be measured from the frames "
            f"({_search_figures(focal, params.video_focal_min_rise)}), and the camera turns {turn:.1f} deg "
            f"over the kept frames (more than ingest.video_unmeasured_focal_max_turn_deg = "
            f"{params.video_unmeasured_focal_max_turn_deg:g}): a focal guessed wrong stretches a "
            f"straight drive along the road only, but bends a turning one (a wide lens left "
            f"distorted bends any), so neither its lateral shifts nor its lengths could be trusted")


def _reconstruct(sfm_in: SfmInput, work: Path, *, scene_id: str, path: Path) -> Reconstruction:
    try:
        return reconstruct(sfm_in.folder, sfm_in.names, work, intrinsics=sfm_in.intrinsics)
    except MemoryError as exc:
        raise _out_of_memory(path, scene_id, f"in structure from motion at {sfm_in.size[0]}x"
                                             f"{sfm_in.size[1]}") from exc
    except SfmError as exc:
        raise SceneError(f"structure from motion failed: {exc}", scene_id=scene_id, path=path,
                         fix="a video from a moving vehicle is needed: trim start=/end= to where "
                             "it drives, lower fps=, or give the intrinsics") from exc


def _no_road(exc: SfmError, footage: Footage) -> str:
    """The fix of a scene whose road could not be measured: more frames where some were skipped."""
    fix = ("the camera must see the road ahead: trim start=/end= to where it does, or give a "
           "speed/GPS track as <stem>.csv (t,speed_mps)")
    if footage.native_fps is not None and footage.skipped:
        fix = (f"{footage.skipped} of the video's frames were skipped (fps={footage.fps:g} of its "
               f"{footage.native_fps:g}): more frames may fix it (a higher fps=, up to "
               f"{footage.native_fps:g}); else {fix}")
    return fix


def _scale(rec: Reconstruction, run: slice, plane: RoadPlane, up: np.ndarray,
           image: Callable[[int], np.ndarray], K_image: np.ndarray, opts: VideoOptions,
           footage: Footage, params: IngestParams, scene_id: str, *,
           ego: np.ndarray | None = None,
           focal: FocalEstimate | None = None) -> tuple[float, float, np.ndarray, dict]:
    """Metres per model unit, from the camera's height above the road measured by independent
    cues per frame range (:mod:`paradrive.ingest.scalecue`: the road's motion, the road's SfM
    points), or from the track where there is one; that height in model units; what was
    measured (``uncertainty``: the scale's relative uncertainty, biases and the estimated focal
    length's included); each kept frame's scale over the whole path's (a scale per range takes
    out SfM's drift along the video; ones with a track). ``ego``: the pixels that move with the
    camera (any size), left out of the road's motion. SceneError where no cue measured the
    scale, where cues contradict each other, or where the uncertainty is above
    ``ingest.video_max_scale_uncertainty``."""
    start = time.perf_counter()
    motion = road_motion_height(image, rec.c2w[run], K_image, up, plane.height, ego=ego,
                                codec_crf=params.video_codec_crf)
    seconds = time.perf_counter() - start
    ranges = split_ranges(run.stop - run.start, params.video_scale_range_frames, SCALE_RANGES)
    cues = [cue for frames in ranges for cue in (
        scale_roadmotion.measure(motion, frames, opts.height_m),
        scale_roadpoints.measure(plane, frames, opts.height_m, offset=run.start,
                                 bias=params.video_road_points_bias))]
    common = {} if focal is None else {"focal": focal.scale_uncertainty}
    steps = np.r_[0.0, np.linalg.norm(np.diff(rec.c2w[run][:, :3, 3], axis=0), axis=1)]
    lengths = [float(steps[a + 1:b + 1].sum()) + 1e-12 for a, b in ranges]
    track = track_path(footage.path)
    try:
        combined: CombinedScale | None = combine(cues, ranges, lengths=lengths, common=common)
    except ScaleError as exc:
        if not track.is_file():
            raise SceneError(str(exc), scene_id=scene_id, path=footage.path,
                             fix="give a speed or GPS track as <stem>.csv (t,speed_mps or "
                                 "t,lat,lon), or trim start=/end= to where the camera sees the "
                                 "road" + (UNCALIBRATED_FIX if focal is not None else "")) from exc
        combined, failed = None, str(exc)   # the track sets the scale; the cues are recorded
    doc: dict[str, Any] = {"source": "height", "height_m": opts.height_m,
                           "by_road_points": opts.height_m / plane.height}
    if combined is not None:
        by_height = combined.scale
        doc.update(by_height=by_height,
                   height_from=max((scale_roadmotion.NAME, scale_roadpoints.NAME),
                                   key=combined.weight_of),
                   weights={name: combined.weight_of(name) for name in
                            (scale_roadmotion.NAME, scale_roadpoints.NAME)},
                   uncertainty=combined.uncertainty, **combined.doc())
    else:
        by_height = doc["by_road_points"]
        doc.update(by_height=by_height, height_from=scale_roadpoints.NAME, cues_failed=failed)
    camera_height = opts.height_m / by_height
    if motion is not None:
        doc["road_motion"] = _motion_doc(motion, seconds)
    if track.is_file():
        by_track = _by_track(track, footage.times[run], rec.c2w[run], doc, common.get("focal", 0.0),
                             params, scene_id)
        return by_track, camera_height, np.ones(run.stop - run.start), doc
    assert combined is not None   # no track: a failed combination raised above
    # the focal's error stretches lengths along the road only (paradrive.ingest.focal): what
    # the lateral shifts rest on is the cues' figure without it
    doc["across_uncertainty"] = combined.without("focal")
    if doc["across_uncertainty"] > params.video_max_scale_uncertainty:
        raise SceneError(_uncertain(doc, combined, params), scene_id=scene_id, path=footage.path,
                         fix=UNCERTAIN_FIX + (UNCALIBRATED_FIX if focal is not None else ""))
    if doc["uncertainty"] > params.video_max_scale_uncertainty:
        log.warning("scene %s (%s): lengths along the road (the path, the speed, longitudinal "
                    "shifts) are uncertain by %.1f%%, above ingest.video_max_scale_uncertainty = "
                    "%g, for the focal length's %.1f%%; lateral shifts are uncertain by %.1f%%",
                    scene_id, footage.path, 100 * doc["uncertainty"],
                    params.video_max_scale_uncertainty, 100 * combined.parts.get("focal", 0.0),
                    100 * doc["across_uncertainty"])
    return by_height, camera_height, profile(combined, run.stop - run.start), doc


def _by_track(track: Path, times: np.ndarray, c2w: np.ndarray, doc: dict[str, Any], focal: float,
              params: IngestParams, scene_id: str) -> float:
    """Metres per model unit by the track over the kept frames (``times``, ``c2w``), recorded
    in the scale's ``doc`` beside the height's; ``focal``: the estimated focal's uncertainty."""
    metres, kind = track_distance(track, float(times[0]), float(times[-1]), scene_id=scene_id)
    by_track = metres / path_length(c2w)
    doc.update(source=kind, track=str(track), by_track=by_track,
               height_vs_track=doc["by_height"] / by_track - 1.0,
               camera_height_by_track_m=doc["height_m"] / doc["by_height"] * by_track,
               uncertainty=TRACK_UNCERTAINTY,
               # the track sets lengths along the road: a focal's error is then across it
               across_uncertainty=math.hypot(TRACK_UNCERTAINTY, focal))
    if doc["across_uncertainty"] > params.video_max_scale_uncertainty:
        log.warning("scene %s (%s): the track sets the lengths along the road; across it (the "
                    "lateral shifts) they are uncertain by %.1f%%, the focal length's: give "
                    "fov_deg= or fx=&fy=&cx=&cy=", scene_id, track, 100 * doc["across_uncertainty"])
    return by_track


def _motion_doc(motion: RoadMotion, seconds: float) -> dict[str, Any]:
    return {"pairs": len(motion.pairs), "spread": motion.spread, "scatter": motion.scatter,
            "drift": motion.drift, "band": motion.band, "codec": motion.codec,
            "heights_q10_q90": [float(q) / motion.height for q in np.percentile(motion.heights, [10, 90])],
            "seconds": seconds}


def _uncertain(doc: dict[str, Any], combined: CombinedScale, params: IngestParams) -> str:
    """Why the scale cannot be trusted, in one line: the figure, its parts, each range's cues."""
    parts = ", ".join(f"{name} {value:.1%}" for name, value in
                      sorted(combined.parts.items(), key=lambda kv: -kv[1])
                      if value > 0 and name not in ("between_ranges", "focal"))
    ranges = "; ".join(
        f"{format_range(r.frames)}: " + ", ".join(
            f"{c.name} {c.uncertainty:.1%}" if c.scale is not None else f"{c.name} not measured ({c.why})"
            for c in r.cues) for r in combined.ranges)
    return (f"the metric scale is uncertain by {doc['across_uncertainty']:.1%} (above "
            f"ingest.video_max_scale_uncertainty = {params.video_max_scale_uncertainty:g}): "
            f"{parts}; {ranges}")


def _scene(uri: SceneURI, rec: Reconstruction, sfm_in: SfmInput, footage: Footage,
           opts: VideoOptions, kept: tuple[int, int], out_dir: Path, params: IngestParams,
           scene_id: str, *, focal: FocalEstimate | None = None) -> Scene:
    path = Path(uri.path)
    run = slice(kept[0], kept[1] + 1)
    try:
        plane = fit_road_plane(rec)
    except SfmError as exc:
        raise SceneError(f"no metric scale: {exc}", scene_id=scene_id, path=path,
                         fix=_no_road(exc, footage)) from exc
    small, left = rec.intrinsics, rec.distortion if rec.estimated else sfm_in.distortion
    sx, sy = sfm_in.scale(footage)
    K = Intrinsics(small.fx * sx, small.fy * sy, small.cx * sx, small.cy * sy)  # the video's pixels
    dist = rec.distortion if rec.estimated else _lens(opts)

    def image(k: int) -> np.ndarray:
        """Kept frame ``k`` at SfM's size, undistorted."""
        from paradrive.scene import read_image

        pixels = read_image(sfm_in.folder / sfm_in.names[kept[0] + k], scene_id=scene_id)
        return pixels if distortion_is_zero(left) else undistort_image(pixels, small.K(), left)

    # the kept frames stored (full size, undistorted) before the scale
    rels = _write_frames(footage, kept, K, dist, out_dir, params, scene_id=scene_id)
    # None: the road's motion finds what barely changes itself (the hood, the cars keeping pace);
    # on the real clip its scale is 0.58 % uncertain so, 1.1 % with the video's ego mask instead
    ego = None
    up = level_with_path(plane.normal, rec.c2w[run])
    scale, camera_height, ratio, scale_doc = _scale(rec, run, plane, up, image, small.K(), opts,
                                                    footage, params, scene_id, ego=ego, focal=focal)
    rec = without_drift(rec, kept[0], ratio)
    rig = metric_rig(rec.c2w[run], up, camera_height, scale)
    travelled = path_length(rig.c2w)
    if travelled < MIN_PATH_M:
        raise SceneError(f"the camera moves {travelled:.2f} m over the kept frames: a static "
                         f"camera gives no baseline", scene_id=scene_id, path=path,
                         fix="trim start=/end= to where the vehicle drives")
    camera = Camera(name=CAMERA, width=footage.width, height=footage.height, fx=K.fx, fy=K.fy,
                    cx=K.cx, cy=K.cy, cam2ego=rig.cam2ego)
    frames = [Frame(index=k, timestamp_us=int(round(footage.times[i] * 1e6)),
                    ego2world=rig.ego2world[k],
                    cameras={CAMERA: FrameCamera(image=rels[k], c2w=rig.c2w[k])})
              for k, i in enumerate(range(kept[0], kept[1] + 1))]
    if params.lidar:
        _save_model_points(rec, rig, kept, out_dir)
    video = _video_doc(uri, rec, sfm_in, footage, opts, kept, (K, dist), scale, scale_doc, travelled,
                       plane)
    if focal is not None:
        video["intrinsics"].update(
            estimated=True, focal_search=focal.doc(),
            given_by="focal search" if focal.observable else "focal search: not measured, "
                                                              "the middle of the range searched")
        # the search is SfM work too: the plan counts it at the rate this scene measured
        video["sfm"].update(seconds=video["sfm"]["seconds"] + focal.seconds,
                            focal_seconds=focal.seconds)
        video["sfm_seconds"] = video["sfm"]["seconds"]

    def stored(k: int) -> np.ndarray:
        from paradrive.scene import read_image

        return read_image(out_dir / rels[k], scene_id=scene_id)

    # the hood, overlays and moving traffic, found on the stored frames (masks/)
    video["masks"] = write_video_masks(stored, rig.c2w, rig.ego2world, K.K(), out_dir, CAMERA,
                                       scene_id=scene_id)
    stamps = [f.timestamp_us for f in frames]  # a video slower than fps= keeps its own rate
    return Scene(scene_id=scene_id, dataset="video", source=uri.text,
                 fps=fps_from(stamps, footage.fps), cameras={CAMERA: camera}, frames=frames,
                 extra={"video": video})


def _lens(opts: VideoOptions) -> tuple[float, ...]:
    """The given lens distortion (zero for fov_deg or none)."""
    return opts.calibration.distortion if opts.calibration is not None else (0.0,) * 5


def _write_frames(footage: Footage, kept: tuple[int, int], K: Intrinsics, dist: tuple[float, ...],
                  out_dir: Path, params: IngestParams, *, scene_id: str) -> list[str]:
    """Second pass: the kept frames at full size, undistorted to the pinhole ``K``, stored."""
    rels = [f"images/{CAMERA}/{k:06d}.{params.image_ext}" for k in range(kept[1] - kept[0] + 1)]

    def store(k: int, pixels: np.ndarray) -> None:
        pixels = pixels if distortion_is_zero(dist) else undistort_image(pixels, K.K(), dist)
        write_image(out_dir / rels[k - kept[0]], pixels, quality=params.jpeg_quality)
        image_written()

    each_frame(footage, store, scene_id=scene_id, only=list(range(kept[0], kept[1] + 1)))
    return rels


def _video_doc(uri: SceneURI, rec: Reconstruction, sfm_in: SfmInput, footage: Footage,
               opts: VideoOptions, kept: tuple[int, int], camera: tuple[Intrinsics, tuple],
               scale: float, scale_doc: dict, travelled: float, plane: RoadPlane) -> dict[str, Any]:
    """What ``scene.json`` records under ``video``."""
    K, dist = camera
    run = slice(kept[0], kept[1] + 1)
    given = opts.calibration
    intrinsics: dict[str, Any] = {
        "fx": K.fx, "fy": K.fy, "cx": K.cx, "cy": K.cy, "estimated": rec.estimated,
        "distortion": list(dist), "undistorted": not distortion_is_zero(dist),
        "given_by": given.source if given is not None else "fov_deg" if opts.fov_deg else None}
    video = {"file": uri.path, "fps": footage.fps, "native_fps": footage.native_fps,
             "source_frames": footage.source_frames[run], "skipped_frames": footage.skipped,
             "intrinsics": intrinsics,
             "registered": format_runs(registered_runs(rec.registered)),
             "sampled": len(footage.source_frames), "kept": [kept[0], kept[1]],
             "scale_m_per_unit": scale, "scale": scale_doc, "path_m": travelled,
             "road_plane": {"inliers": plane.inliers, "candidates": plane.candidates},
             "points": int(len(rec.points)), "sfm_seconds": rec.seconds,
             "sfm": {"width": sfm_in.size[0], "height": sfm_in.size[1],
                     "downscaled": sfm_in.size != (footage.width, footage.height),
                     "seconds": rec.seconds, "prepare_seconds": sfm_in.seconds},
             "models": rec.models}
    if opts.truth:
        video["truth"] = opts.truth
    if footage.clock is not None:
        video["clock"] = footage.clock.doc()
    return video


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
