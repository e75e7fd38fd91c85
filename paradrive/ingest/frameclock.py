"""The clock of a video file: when each frame is shown, whether the rate varies, and which frames
only repeat the one before (a clip resampled to a higher rate) and are dropped.

* **Times.** Frame ``i`` is the ``i``-th frame the file presents (:mod:`paradrive.video`), at the
  time its timestamp gives (seconds from the first frame). A stream without timestamps is timed
  by its header's rate.
* **Variable rate.** The rate varies where an interval between frames differs from the median
  interval by more than :data:`RATE_TOLERANCE` of it (and more than a millisecond, which a
  Matroska file's millisecond timestamps round to).
* **Repeated frames.** How much frame ``i`` changed from frame ``i - 1`` is measured on the frames
  in grey at :data:`DETECT_WIDTH` pixels across, cut into square tiles: the largest over the tiles
  of a tile's mean absolute difference, so a change in any part of the picture (a car passing one
  that stands at a light) counts as a change. A flickering sign or a clock overlay may then hide a
  repeat (it is kept); it never makes a changing frame look like one. Frame ``i`` repeats the one
  before where it changed less than ``ratio`` (``ingest.video_repeat_ratio``) of what the frames
  before it change and
  of what the frames after it change (each side: the largest change among its :data:`WINDOW`
  nearest frames, so a clip resampled up to six times its rate, five repeats in six, is found):
  the threshold follows the video's own motion and noise, not a level tuned to one clip; a flash
  or a scene cut on one side does not make the frames beside it repeats. A frame that changes
  little among frames that change little (slow driving, braking to a stop, moving off) is no
  repeat. Where every frame around is as still as noise (a parked car in an empty street), a frame
  cannot be told from a repeat: none is dropped, unless it changed far less than the sensor's
  noise does between frames (a resampler's copy there is found); where the frames around change by
  less than :data:`STILL_LEVEL` (a still picture, no noise) none is dropped at all. The first
  frame is never a repeat.

A dropped frame takes nothing from the clock: every kept frame keeps its own timestamp, which for
a resampled clip is when its picture first appeared.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from paradrive.errors import ParaDriveError, SceneError

# an interval this far from the median one (relative) makes the rate variable
RATE_TOLERANCE = 0.05
# Matroska stores milliseconds: a constant 29.97 fps rounds to 33 and 34 ms intervals
RATE_SLACK_S = 0.0011
# the repeated-frame test works on grey frames this wide (pixels), in square tiles of this side
DETECT_WIDTH = 160
TILE_PX = 10
# each side of a frame: this many frames, and its change the largest of theirs (a clip with
# five repeats in six still finds a frame that changes on either side)
WINDOW = 6
# frames whose most changed tiles change by less than one grey level (8 bits' step) on average
# show a still picture: among them nothing repeats (a parked camera's identical frames stay)
STILL_LEVEL = 1.0


@dataclass(frozen=True)
class Clock:
    """Every decoded frame's time (F,) in seconds from the first, presentation order; where the
    times came from (``timestamps``: the packets; ``rate``: the header's rate, a stream without
    them); the header's rate; each frame's change from the one before (F,) (NaN where not
    measured, inf for the first frame), the frames dropped as repeats, and the seconds the
    detection took."""

    times: np.ndarray
    source: str
    header_fps: float
    changes: np.ndarray
    repeated: tuple[int, ...] = ()
    seconds: float = 0.0
    detected: bool = True
    ratio: float | None = None

    @property
    def kept(self) -> list[int]:
        """The frames that remain, in order."""
        dropped = set(self.repeated)
        return [i for i in range(len(self.times)) if i not in dropped]

    @property
    def variable_rate(self) -> bool:
        return is_variable(self.times)

    @property
    def fps(self) -> float:
        """The rate of the frames that remain: the header's where they are its constant-rate
        frames, else one over their median interval."""
        kept = self.times[self.kept]
        if len(kept) < 2:
            return self.header_fps
        median = float(np.median(np.diff(kept)))
        if self.header_fps > 0 and not self.repeated and not is_variable(self.times) \
                and abs(median * self.header_fps - 1) < RATE_TOLERANCE:
            return self.header_fps
        return round(1.0 / median, 6) if median > 0 else self.header_fps   # no float noise

    def doc(self) -> dict[str, Any]:
        """What ``scene.json`` records under ``video.clock``."""
        steps = np.diff(self.times)
        return {"timestamps": self.source, "frames": int(len(self.times)),
                "header_fps": self.header_fps, "variable_rate": self.variable_rate,
                "interval_s": {"median": float(np.median(steps)), "min": float(steps.min()),
                               "max": float(steps.max())} if len(steps) else None,
                "repeated_frames_dropped": list(self.repeated), "fps": self.fps,
                "repeat_detection": {"done": self.detected, "width": DETECT_WIDTH,
                                     "ratio": self.ratio, "window": WINDOW,
                                     "seconds": self.seconds}}


def is_variable(times: np.ndarray) -> bool:
    """Whether the frames at ``times`` (F,) seconds come at a varying rate (module docstring)."""
    steps = np.diff(np.asarray(times, dtype=np.float64))
    if len(steps) < 2:
        return False
    median = float(np.median(steps))
    return bool(np.max(np.abs(steps - median)) > max(RATE_TOLERANCE * median, RATE_SLACK_S))


class Changes:
    """How much each frame changed from the one before, fed one frame at a time: ``add(rgb)``
    with uint8 (H, W, 3) frames (any size; at :data:`DETECT_WIDTH` across is what the
    thresholds were set at), then ``values`` (F,): inf for the first frame."""

    def __init__(self) -> None:
        self.previous: np.ndarray | None = None
        self._values: list[float] = []

    def add(self, rgb: np.ndarray) -> None:
        grey = np.asarray(rgb, dtype=np.float32).mean(axis=2)
        h, w = (grey.shape[0] // TILE_PX) * TILE_PX, (grey.shape[1] // TILE_PX) * TILE_PX
        grey = grey[:h, :w] if h and w else grey
        if self.previous is None or self.previous.shape != grey.shape:
            self._values.append(np.inf)
        else:
            diff = np.abs(grey - self.previous)
            if h and w:
                tiles = diff.reshape(h // TILE_PX, TILE_PX, w // TILE_PX, TILE_PX).mean(axis=(1, 3))
                self._values.append(float(tiles.max()))
            else:
                self._values.append(float(diff.mean()))
        self.previous = grey

    @property
    def values(self) -> np.ndarray:
        return np.asarray(self._values, dtype=np.float64)


def frame_changes(frames: Iterable[np.ndarray]) -> np.ndarray:
    """(F,) each frame's change from the one before (the first: inf), of uint8 (H, W, 3) frames."""
    changes = Changes()
    for frame in frames:
        changes.add(frame)
    return changes.values


def repeated_frames(changes: np.ndarray, ratio: float) -> np.ndarray:
    """(F,) bool: the frames that repeat the one before, from their changes (F,) as
    :func:`frame_changes` gives them: those that change less than ``ratio`` of the
    frames before them and of the frames after them (each side's largest change among its
    :data:`WINDOW` nearest frames; one side at the clip's ends), where both change by
    :data:`STILL_LEVEL` at least. Both sides, so the last frames of a stop (still after,
    moving before) and the first of a start are no repeats; NaN (not measured) and inf (the
    first frame) are never repeats."""
    changes = np.asarray(changes, dtype=np.float64)
    out = np.zeros(len(changes), dtype=bool)
    for i in np.flatnonzero(np.isfinite(changes)):
        sides = [_level(changes[max(0, i - WINDOW): i]), _level(changes[i + 1: i + 1 + WINDOW])]
        levels = [level for level in sides if level is not None]
        out[i] = bool(levels) and min(levels) >= STILL_LEVEL \
            and changes[i] < ratio * min(levels)
    return out


def _level(changes: np.ndarray) -> float | None:
    """How much the frames of a stretch change (the largest change); None where none was
    measured."""
    measured = changes[np.isfinite(changes)]
    return float(measured.max()) if len(measured) else None


def read_clock(path: Path, header: tuple[int, float, int, int], *, scene_id: str,
               repeat_ratio: float, detect: bool = True) -> Clock:
    """The clock of the video at ``path`` whose header gives ``(frames, fps, width, height)``: its
    frames' times from their timestamps (else the header's rate over its frames) and, with
    ``detect``, its repeated frames (:func:`repeated_frames` at ``repeat_ratio``), found on one
    decoding pass over the whole clip at
    :data:`DETECT_WIDTH` across.
    SceneError naming the file where it cannot be read."""
    from paradrive import video

    header_frames, header_fps, width, height = header
    try:
        stamped = video.frame_times(path)
    except ParaDriveError as exc:
        raise SceneError(f"video cannot be read ({exc})", scene_id=scene_id, path=path,
                         fix="the file is not a video or is corrupt: re-encode or re-download it"
                         ) from exc
    if stamped is not None:
        times, source = stamped[0], "timestamps"
    else:
        times, source = np.arange(header_frames, dtype=np.float64) / header_fps, "rate"
    if not detect:
        return Clock(times, source, header_fps, np.full(len(times), np.nan), detected=False)
    start = time.perf_counter()
    changes = _decoded_changes(path, (width, height), scene_id=scene_id)
    if source == "rate":
        times = np.arange(len(changes), dtype=np.float64) / header_fps
    elif len(changes) != len(times):
        # a frame the packets list that does not decode: not a repeat (NaN), the decoding pass
        # that wants it reports it
        padded = np.full(len(times), np.nan)
        padded[:min(len(times), len(changes))] = changes[:len(times)]
        changes = padded
    repeated = tuple(int(i) for i in np.flatnonzero(repeated_frames(changes, repeat_ratio)))
    return Clock(times, source, header_fps, changes, repeated, time.perf_counter() - start,
                 ratio=repeat_ratio)


def _decoded_changes(path: Path, size: tuple[int, int], *, scene_id: str) -> np.ndarray:
    """Every decoded frame's change from the one before (F,), decoded at :data:`DETECT_WIDTH`
    across from the video's ``size`` (width, height)."""
    from paradrive import video

    width, height = size
    w = min(width, DETECT_WIDTH)
    h = max(2, int(round(height * w / max(width, 1))))
    changes = Changes()
    try:
        video.each_frame(path, None, lambda i, rgb: changes.add(rgb), size=(h, w), seek=False)
    except ParaDriveError as exc:
        raise SceneError(f"video is truncated or corrupt: it does not decode to its end ({exc})",
                         scene_id=scene_id, path=path,
                         fix="re-encode or re-download the video, or trim the range with end=") from exc
    return changes.values


def frames_at(clock: Clock, fps: float, start: float, end: float | None) -> list[int]:
    """The frames (numbers of the file) to take at ``fps`` within ``[start, end)`` seconds from
    the kept ones: every kept frame where ``fps`` is at least the clock's rate, else the kept
    frame nearest each time of an ``fps`` grid from ``start``, without repeats."""
    kept = np.asarray(clock.kept, dtype=np.int64)
    times = clock.times[kept]
    inside = (times >= start - 1e-9) & (times < (np.inf if end is None else end) - 1e-9)
    kept, times = kept[inside], times[inside]
    if not len(kept):
        return []
    rate = clock.fps
    if fps >= rate * (1 - 1e-6):
        return [int(i) for i in kept]
    stop = times[-1] + 0.5 / rate if end is None else min(end, times[-1] + 0.5 / rate)
    grid = np.arange(start, stop, 1.0 / fps)
    after = np.searchsorted(times, grid)
    lo, hi = np.clip(after - 1, 0, len(times) - 1), np.clip(after, 0, len(times) - 1)
    nearest = np.where(np.abs(times[hi] - grid) < np.abs(times[lo] - grid), hi, lo)
    return sorted(set(int(kept[i]) for i in nearest))
