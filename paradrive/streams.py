"""What render, clip, manifest and eval agree on: clip windows, stream names, the output camera.

A clip is ``clip_frames`` consecutive frames of one camera (docs/scene-layout.md, "Clips"). For a scene of
N >= F frames: front = [0, F), middle = [floor((N - F) / 2), + F), rear = [N - F, N). A shorter
scene has no clips; the reason is recorded and the other cameras and scenes go on.

Every clip has streams: ``target`` (the recording), ``cond@<iteration:06d>`` (the recorded
trajectory at an under-fitted checkpoint) and ``source<offset>`` (the trajectory shifted
laterally at the final checkpoint), or with ``render.transform: longitudinal``
``source+long<offset>`` (the camera moved that far along its own path, as FreeVS and
StreetCrafter pair views). An offset is written one way everywhere (stream names, pair
ids, inference truth files): :func:`format_offset`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from paradrive import geometry

CLIP_NAMES = ("front", "middle", "rear")
TRANSFORMS = ("lateral", "longitudinal")
LONGITUDINAL_TAG = "+long"   # in a longitudinal source's stream name: source+long+4m
TARGET_STREAM = "target"


@dataclass(frozen=True)
class ClipWindow:
    """A clip: ``num_frames`` consecutive frames from position ``start`` of the scene's frames."""

    name: str
    start: int
    num_frames: int

    @property
    def stop(self) -> int:
        return self.start + self.num_frames

    @property
    def frames(self) -> range:
        return range(self.start, self.stop)


def clip_windows(n_frames: int, clip_frames: int,
                 names: Sequence[str] = CLIP_NAMES) -> tuple[list[ClipWindow], list[dict]]:
    """The clip windows of a sequence of ``n_frames`` frames, and the clips that do not fit.

    names: any of ``front`` ([0, F)), ``middle`` ([floor((N-F)/2), +F)) and ``rear`` ([N-F, N)),
    in the order wanted. Returns (windows, skipped) where skipped is a list of
    ``{"clip": name, "reason": "..."}`` (every clip when N < F). A name outside those three
    or a non-positive ``clip_frames`` is a ValueError.
    """
    n, f = int(n_frames), int(clip_frames)
    if f <= 0:
        raise ValueError(f"clip_frames must be positive, got {clip_frames}")
    unknown = [x for x in names if x not in CLIP_NAMES]
    if unknown:
        raise ValueError(f"unknown clip name(s) {', '.join(map(repr, unknown))}; "
                         f"clips are {', '.join(CLIP_NAMES)}")
    if n < f:
        reason = f"scene has {n} frames, a clip needs {f}"
        return [], [{"clip": name, "reason": reason} for name in names]
    starts = {"front": 0, "middle": (n - f) // 2, "rear": n - f}
    return [ClipWindow(name, starts[name], f) for name in names], []


class Shortfall(NamedTuple):
    """Why a scene can give no clip: what it lacks, and the fix."""

    what: str
    fix: str


def clip_shortfall(frames: int, scene_cameras: Sequence[str], cameras: Sequence[str],
                   clip_frames: int) -> Shortfall | None:
    """Why a scene of ``frames`` frames of ``scene_cameras`` cannot give the clips of ``cameras``
    (render.cameras), or None when it can. Every clip window is ``clip_frames`` long, so a
    scene with fewer frames gives none."""
    missing = [c for c in cameras if c not in scene_cameras]
    if missing:
        return Shortfall(f"it has no camera {', '.join(missing)}, which render.cameras needs for "
                         f"its pairs (it has {', '.join(scene_cameras) or 'none'})",
                         "ingest that camera (ingest.cameras), name another one in "
                         "render.cameras, or use another scene")
    if frames < clip_frames:
        return Shortfall(f"it has {frames} frame{'' if frames == 1 else 's'}, and a clip needs "
                         f"{clip_frames} (render.clip_frames)",
                         f"set a shorter render.clip_frames (at most {frames}) or use another scene")
    return None


def source_poses(c2w_path: np.ndarray, ego2world: np.ndarray, offset_m: float,
                 transform: str) -> tuple[np.ndarray, np.ndarray]:
    """The poses of a source stream over a camera's whole recorded path, and where they exist.

    c2w_path, ego2world: (N, 4, 4) every frame of the scene. ``lateral``: the parallel lane
    :func:`geometry.lateral_shift` makes (always on the path); ``longitudinal``: the camera
    ``offset_m`` metres ahead (behind when negative) along its own path
    (:func:`geometry.longitudinal_shift`). Returns (N, 4, 4) poses and ``on_path`` (N,) bool.
    """
    if transform == "longitudinal":
        return geometry.longitudinal_shift(c2w_path, offset_m)
    if transform != "lateral":
        raise ValueError(f"unknown transform {transform!r}; transforms are {', '.join(TRANSFORMS)}")
    return geometry.lateral_shift(c2w_path, ego2world, offset_m), np.ones(len(c2w_path), dtype=bool)


def source_clip_windows(c2w_path: np.ndarray, clip_frames: int, names: Sequence[str],
                        offsets_m: Sequence[float], transform: str) -> tuple[list[ClipWindow], list[dict]]:
    """The clip windows of a camera whose every source pose lies on its recorded path.

    A lateral source always does, so these are :func:`clip_windows` of the whole scene. A
    longitudinal one runs off the path within ``max(offsets)`` metres of its end (or ``-min``
    of its start): the windows are then laid over the frames where every offset stays on it,
    so front starts and rear ends further in and no frame off the path is rendered; the clips
    that do not fit there are skipped with that reason.
    """
    n = len(c2w_path)
    on_path = np.ones(n, dtype=bool)
    if transform == "longitudinal":
        for d in offsets_m:
            on_path &= geometry.longitudinal_shift(c2w_path, d)[1]
    kept = np.flatnonzero(on_path)
    span = range(int(kept[0]), int(kept[-1]) + 1) if len(kept) else range(0)
    windows, skipped = clip_windows(len(span), clip_frames, names)
    if len(span) == n:
        return windows, skipped
    where = f" ({span.start}..{span.stop - 1})" if len(span) else ""
    reason = (f"its longitudinal sources stay on the recorded path ({geometry.arc_length(c2w_path)[-1]:.1f} m) "
              f"for {len(span)} of its {n} frames{where}, a clip needs {clip_frames}")
    return ([ClipWindow(w.name, w.start + span.start, w.num_frames) for w in windows],
            [{"clip": s["clip"], "reason": reason} for s in skipped])


def path_shortfall(paths: Mapping[str, np.ndarray], clip_frames: int, names: Sequence[str],
                   offsets_m: Sequence[float]) -> Shortfall | None:
    """Why a longitudinal build's cameras, moving along ``paths`` ((N, 4, 4) each), give no clip
    that keeps every source on the recorded path, or None when each gives one."""
    for name, c2w in paths.items():
        windows, skipped = source_clip_windows(c2w, clip_frames, names, offsets_m, "longitudinal")
        if not windows:
            return Shortfall(f"camera {name}: {skipped[0]['reason']}",
                             "set a shorter render.clip_frames, smaller "
                             "render.longitudinal_offsets_m, or use another scene")
    return None


def frames_needed(windows: Iterable[ClipWindow]) -> list[int]:
    """Sorted union of the frame positions the windows cover (each frame once)."""
    return sorted({i for w in windows for i in w.frames})


def format_offset(offset_m: float) -> str:
    """``+1m``, ``-2m``, ``+0.5m``, ``+1000000m``: the sign always, integers without decimals,
    no exponent, and one name for zero (``+0m``, also for -0.0)."""
    d = float(offset_m)
    if not math.isfinite(d):
        raise ValueError(f"offset must be finite, got {offset_m}")
    if d == 0:
        return "+0m"
    if d == round(d):
        return f"{d:+.0f}m"
    return f"{np.format_float_positional(d, sign=True, trim='-')}m"


def condition_stream(iteration: int) -> str:
    """``cond@000100``: the recorded trajectory rendered at an under-fitted checkpoint."""
    return f"cond@{int(iteration):06d}"


def source_stream(offset_m: float, transform: str = "lateral") -> str:
    """``source+1m``: the recorded trajectory shifted ``offset_m`` (left > 0) at the final
    checkpoint; ``source+long+4m`` (longitudinal): moved ``offset_m`` along it (ahead > 0)."""
    return f"source{LONGITUDINAL_TAG if transform == 'longitudinal' else ''}{format_offset(offset_m)}"


def stream_transform(name: str) -> str:
    """``longitudinal`` for a ``source+long..`` stream name, else ``lateral``."""
    return "longitudinal" if name.startswith("source" + LONGITUDINAL_TAG) else "lateral"


@dataclass(frozen=True)
class StreamPlan:
    """One stream a camera gets: its name, kind, checkpoint iteration and lateral offset."""

    name: str
    kind: str                 # target | condition | source
    iteration: int | None = None
    offset_m: float | None = None
    transform: str = "lateral"   # how a source is moved: lateral or longitudinal


def plan_streams(condition_checkpoints: Sequence[int], source_checkpoint: int,
                 offsets_m: Sequence[float], transform: str = "lateral") -> list[StreamPlan]:
    """The streams a camera gets: target, one per condition checkpoint, one per offset."""
    streams = [StreamPlan(TARGET_STREAM, "target")]
    streams += [StreamPlan(condition_stream(it), "condition", int(it)) for it in condition_checkpoints]
    streams += [StreamPlan(source_stream(d, transform), "source", int(source_checkpoint), float(d),
                           transform) for d in offsets_m]
    return streams


# --------------------------------------------------------------------------- the output camera

@dataclass(frozen=True)
class OutputCamera:
    """How stored images map to the output: crop box (pixels of the stored image), then resize.

    ``K`` (3, 3) is the pinhole matrix at the output resolution.
    """

    width: int
    height: int
    crop: tuple[int, int, int, int]   # x0, y0, crop width, crop height
    K: np.ndarray

    @property
    def intrinsics(self) -> list[float]:
        return [float(self.K[0, 0]), float(self.K[1, 1]), float(self.K[0, 2]), float(self.K[1, 2])]


def output_camera(stored_width: int, stored_height: int, fx: float, fy: float, cx: float,
                  cy: float, width: int, height: int) -> OutputCamera:
    """Centre-crop (to the output aspect ratio) then resize a stored image to ``width x height``.

    Pixel coordinates are continuous with pixel centres at +0.5, so a crop subtracts its corner
    from (cx, cy) and a resize by (sx, sy) scales (fx, cx) by sx and (fy, cy) by sy.
    """
    W, H, w, h = int(stored_width), int(stored_height), int(width), int(height)
    if min(W, H, w, h) <= 0:
        raise ValueError(f"sizes must be positive: stored {W}x{H}, output {w}x{h}")
    if W * h > w * H:      # stored is wider: keep full height
        cw, ch = min(W, max(1, round(H * w / h))), H
    else:                  # stored is taller (or equal): keep full width
        cw, ch = W, min(H, max(1, round(W * h / w)))
    x0, y0 = (W - cw) // 2, (H - ch) // 2
    sx, sy = w / cw, h / ch
    fx2, fy2, cx2, cy2 = geometry.scale_intrinsics(fx, fy, cx - x0, cy - y0, sx, sy)
    K = np.array([[fx2, 0.0, cx2], [0.0, fy2, cy2], [0.0, 0.0, 1.0]])
    return OutputCamera(width=w, height=h, crop=(x0, y0, cw, ch), K=K)


def crop_resize(image: np.ndarray, out: OutputCamera) -> np.ndarray:
    """Apply ``out``'s crop and resize to a uint8 (H, W, C) image; returns uint8 (h, w, C).

    The resize is area-preserving (antialiased bilinear), half-pixel aligned like the intrinsics.
    """
    import torch
    import torch.nn.functional as F

    x0, y0, cw, ch = out.crop
    img = image[y0:y0 + ch, x0:x0 + cw]
    if img.shape[:2] == (out.height, out.width):
        return np.ascontiguousarray(img)
    t = torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1)[None].float()
    r = F.interpolate(t, size=(out.height, out.width), mode="bilinear", align_corners=False,
                      antialias=True)
    return r[0].permute(1, 2, 0).round().clamp(0, 255).to(torch.uint8).numpy()
