"""The ``render`` stage: the frames the clips need, from the fitted checkpoints.

Per camera of ``render.cameras`` and for the union of the frames its clip windows cover
(:func:`paradrive.streams.clip_windows`), it writes these streams::

    target          the recorded frames, cropped and resized like the renders
    cond@000100 ..  the recorded trajectory rendered at each under-fitted checkpoint
    source+1m ..    the trajectory shifted laterally by each offset, at the source (final) checkpoint
    source+long+1m  with ``transform: longitudinal``: the camera moved that far along its own
                    recorded path instead (:func:`paradrive.streams.source_poses`); the clip
                    windows then lie where every such source stays on the path

Layout under ``<scene>/renders/``::

    renders.json                                   windows, streams, intrinsics, poses (below)
    <camera>/<stream>/<frame:06d>.png              8-bit RGB, lossless
    <camera>/<stream>/depth/<frame:06d>.exr        float32 z-depth in metres, channel "Z" (render.depth)
    <camera>/<stream>/alpha/<frame:06d>.png        8-bit accumulated opacity (render.alpha)

``renders.json`` holds, per camera: ``intrinsics`` [fx, fy, cx, cy] at the output size, the
``crop`` box in stored pixels, the clip ``windows`` and ``skipped`` clips (with reasons), the
rendered ``frames`` and their recorded ``c2w``, and per stream its ``kind`` (target, condition,
source), ``iteration``, ``offset_m``, folder and ``c2w`` per frame (16 floats, row-major).

``<frame>`` is the frame's position in ``scene.json``'s ``frames`` list. Output size is
``width`` x ``height``: when the stored images have another aspect ratio they are centre-cropped
to the output aspect, then resized; the pinhole intrinsics are shifted by the crop and scaled by
the resize (docs/conventions.md, "Intrinsics": fx, cx by sx; fy, cy by sy) and renders use the same ones, so render and
target pixels correspond. Depth of the target stream is not written (a log has no dense depth).

Depth is the expected z-depth of the scene's Gaussians, leaving out the fit's sky dome (Gaussians
farther than half the dome radius from the trajectory centre, ``fit.json``); a pixel whose
remaining opacity is below one half is sky and holds +inf, as the synthetic ground truth does.
Left in, a far dome seen through a half-transparent surface would pull its depth to hundreds of
metres.

A scene with an ego mask (``masks/ego/<camera>.png``: a video's hood) shows the recorded pixels
of the same frame there in every rendered stream, sources and conditions alike: the hood moves
with the camera, so a shifted camera sees the same hood, and the fit never learnt those pixels
(they are left out of its loss), so an under-fitted condition would show noise where the target
shows the hood. ``moving`` per camera holds, per rendered frame, the share of the target's
pixels masked as moving (``masks/dynamic``: moving actors' boxes; ``masks/motion``: a video's
moving masks), from which the clip stage takes each clip's ``dynamic_fraction``.

The whole ``renders/`` folder is assembled under a temporary name and renamed into place.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from pydantic import ValidationInfo, field_validator

from paradrive import geometry
from paradrive.errors import SceneError
from paradrive.exr import write_depth_exr
from paradrive.io import atomic_path, counted_stop
from paradrive.scene import Scene, load_scene, read_image, write_image
from paradrive.contracts.base import StageContext, StageParams
from paradrive.contracts.layout import SceneLayout, frame_file, stream_dir
from paradrive.contracts.records import (FitRecord, RenderedCamera, RenderedStream, RendersRecord,
                                      SkippedClip, SkyDomeRecord, WindowRecord)
from paradrive.streams import (ClipWindow, OutputCamera, StreamPlan, clip_shortfall, crop_resize,
                               format_offset, frames_needed, output_camera, path_shortfall,
                               plan_streams, source_clip_windows, source_poses)

if TYPE_CHECKING:
    from paradrive.gs.graph import FittedModel

log_default = logging.getLogger("paradrive.render")
Progress = Callable[[int, int], None]


class Params(StageParams):
    cameras: list[str]
    width: int
    height: int
    condition_checkpoints: list[int]
    source_checkpoint: int
    offsets_m: list[float]
    transform: str
    longitudinal_offsets_m: list[float]
    clips: list[str]
    clip_frames: int
    depth: bool
    alpha: bool
    batch_frames: int
    device: str
    backend: str
    threads: int
    keep_frames: bool

    @field_validator("offsets_m", "longitudinal_offsets_m")
    @classmethod
    def _offsets_once(cls, value: list[float]) -> list[float]:
        """Each offset once, as its stream is named (1 and 1.0 are one stream, ``+1m``): checked
        with the configuration, before any stage runs, not when render meets it after the fit."""
        return _once(value, format_offset, "offset")

    @field_validator("condition_checkpoints", "clips", "cameras")
    @classmethod
    def _names_once(cls, value: list, info: ValidationInfo) -> list:
        return _once(value, str, {"condition_checkpoints": "checkpoint", "clips": "clip",
                                  "cameras": "camera"}[str(info.field_name)])

    @property
    def source_offsets(self) -> list[float]:
        """The offsets of the chosen transform: ``offsets_m`` or ``longitudinal_offsets_m``."""
        return self.longitudinal_offsets_m if self.transform == "longitudinal" else self.offsets_m

    def streams(self) -> list[StreamPlan]:
        return plan_streams(self.condition_checkpoints, self.source_checkpoint, self.source_offsets,
                            self.transform)


def _once(values: list, name: Callable[[Any], str], what: str) -> list:
    """``values`` when no two give one name, else a ValueError naming the repeat and the fix."""
    seen: dict[str, Any] = {}
    for value in values:
        if name(value) in seen:
            first = seen[name(value)]
            both = f" ({first!r} and {value!r})" if repr(first) != repr(value) else ""
            raise ValueError(f"repeats the {what} {name(value)}{both}; list each {what} once")
        seen[name(value)] = value
    return values


@dataclass
class CameraPlan:
    """What one camera renders: its clip windows, the frames they cover, the output camera."""

    name: str
    windows: list[ClipWindow]
    skipped: list[dict]
    frames: list[int]
    out: OutputCamera


def check_params(params: Params, scene: Scene, layout: SceneLayout) -> None:
    sid = scene.scene_id
    w, h = params.width, params.height
    if w <= 0 or h <= 0:
        raise SceneError(f"render size {w}x{h} is not positive", scene_id=sid,
                         fix="set render.width and render.height to positive integers")
    if params.clip_frames <= 0:
        raise SceneError(f"render.clip_frames = {params.clip_frames} is not positive",
                         scene_id=sid, fix="set render.clip_frames >= 1")
    streams = params.streams()   # each named once: Params refused a repeated offset or checkpoint
    nodes = FitRecord.load(layout.fit_json).actors if layout.fit_json.is_file() else []
    for it in sorted({s.iteration for s in streams if s.iteration is not None}):
        for path in [layout.checkpoint(it)] + [layout.actor_checkpoint(it, a.file) for a in nodes]:
            if not path.is_file():
                raise SceneError(f"checkpoint for iteration {it} is missing", scene_id=sid, path=path,
                                 fix=f"add {it} to fit.checkpoints (render.condition_checkpoints and "
                                     f"render.source_checkpoint must be fitted) and re-run fit")
    unknown = [c for c in params.cameras if c not in scene.cameras]
    if unknown:
        raise SceneError(f"render.cameras names {', '.join(unknown)}, which the scene does not "
                         f"have (it has {', '.join(scene.cameras)})", scene_id=sid,
                         path=layout.scene_json,
                         fix="ingest those cameras (ingest.cameras) or drop them from render.cameras")


def admit(layout: SceneLayout, ingested: Mapping[str, Any], params: Params) -> None:
    """Refuse a scene that can give no clip before any stage spends compute on it (the runner
    asks before the fit): ``ingested`` is ingest's summary (``frames``, ``cameras``)."""
    if not ingested:
        return  # nothing recorded to judge by; render itself reports what it finds
    short = clip_shortfall(int(ingested.get("frames", 0)), list(ingested.get("cameras", [])),
                           params.cameras, params.clip_frames)
    if short is not None:
        raise SceneError(short.what, scene_id=layout.root.name, path=layout.scene_json, fix=short.fix)
    if params.transform == "longitudinal" and layout.scene_json.is_file():
        scene = load_scene(layout.root)  # the path's length decides where sources stay on it
        short = path_shortfall({name: scene.c2w(name) for name in params.cameras},
                               params.clip_frames, params.clips, params.source_offsets)
        if short is not None:
            raise SceneError(short.what, scene_id=scene.scene_id, path=layout.scene_json,
                             fix=short.fix)


def plan_camera(scene: Scene, name: str, params: Params, log: logging.Logger) -> CameraPlan:
    try:
        windows, skipped = source_clip_windows(scene.c2w(name), params.clip_frames, params.clips,
                                               params.source_offsets, params.transform)
    except ValueError as exc:
        raise SceneError(str(exc), scene_id=scene.scene_id, fix="fix render.clips") from exc
    for s in skipped:
        log.warning("render: %s camera %s clip %s skipped: %s", scene.scene_id, name, s["clip"],
                    s["reason"])
    cam = scene.cameras[name]
    out = output_camera(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, params.width,
                        params.height)
    return CameraPlan(name, windows, skipped, frames_needed(windows), out)


class _Renderer:
    """Writes the streams of one scene under a temporary ``renders/`` folder."""

    def __init__(self, scene: Scene, layout: SceneLayout, params: Params, root: Path,
                 progress: Progress | None, total: int):
        from paradrive.gs.views import sky_dome_of

        self.scene, self.layout, self.params, self.root = scene, layout, params, root
        self.progress, self.total, self.done = progress, total, 0
        self.fit = FitRecord.load(layout.fit_json) if layout.fit_json.is_file() else None
        init = self.fit.init if params.depth and self.fit is not None else None
        self.sky = sky_dome_of(scene, init) if params.depth else None
        self.cache: dict[int, FittedModel] = {}
        self.streams = params.streams()

    def tick(self, count: int = 1) -> None:
        self.done += count
        if self.progress:
            self.progress(self.done, self.total)

    def camera(self, plan: CameraPlan) -> RenderedCamera:
        frames = plan.frames
        path = self.scene.c2w(plan.name)
        recorded = path[frames] if frames else np.zeros((0, 4, 4))
        streams = {}
        for stream in self.streams if frames else []:
            # the whole path: a longitudinal source is found along it (windows keep it on the path)
            c2w = (source_poses(path, self.scene.ego2world(), stream.offset_m, stream.transform)[0][frames]
                   if stream.offset_m is not None else recorded)
            folder = self.root / stream_dir(plan.name, stream.name)
            folder.mkdir(parents=True)
            if stream.kind == "target":
                self.target(plan, folder)
            else:
                self.rendered(plan, stream, c2w, folder)
            streams[stream.name] = RenderedStream(kind=stream.kind, dir=stream_dir(plan.name, stream.name),
                                                  c2w=[geometry.as_floats(m) for m in c2w],
                                                  iteration=stream.iteration, offset_m=stream.offset_m)
        cam = self.scene.cameras[plan.name]
        return RenderedCamera(
            intrinsics=plan.out.intrinsics, stored_size=[cam.width, cam.height],
            crop=list(plan.out.crop),
            windows=[WindowRecord(clip=w.name, frame_start=w.start, num_frames=w.num_frames)
                     for w in plan.windows],
            skipped=[SkippedClip(**s) for s in plan.skipped], frames=frames,
            c2w=[geometry.as_floats(m) for m in recorded], streams=streams,
            moving=self.moving(plan) if frames else None)

    def target(self, plan: CameraPlan, folder: Path) -> None:
        for pos in plan.frames:
            image = self.scene.load_image(pos, plan.name)
            write_image(folder / frame_file(pos), crop_resize(image, plan.out))
            _frame_written()
            self.tick()

    def moving(self, plan: CameraPlan) -> list[float] | None:
        """Per rendered frame, the share of the target's pixels (the crop) masked as moving:
        the moving actors' boxes (``masks/dynamic``) or a video's moving masks (``masks/motion``);
        None where the scene has neither."""
        x0, y0, cw, ch = plan.out.crop
        shares, found = [], False
        for pos in plan.frames:
            index = self.scene.frames[pos].index
            hit = np.zeros((ch, cw), dtype=bool)
            for path in (self.layout.dynamic_mask(plan.name, index),
                         self.layout.motion_mask(plan.name, index)):
                if path.is_file():
                    found = True
                    hit |= read_image(path)[y0:y0 + ch, x0:x0 + cw, 0] > 127
            shares.append(round(float(hit.mean()), 6))
        return shares if found else None

    def ego(self, plan: CameraPlan) -> np.ndarray | None:
        """The camera's ego mask (the hood) at the output size as a weight in [0, 1], or None."""
        path = self.layout.ego_mask(plan.name)
        if not path.is_file():
            return None
        weight = crop_resize(read_image(path)[..., :1], plan.out)[..., 0].astype(np.float32) / 255.0
        return weight[..., None] if weight.any() else None

    def checkpoint(self, iteration: int) -> FittedModel:
        from paradrive.gs.graph import load_model

        if iteration not in self.cache:
            self.cache.clear()  # one checkpoint in memory at a time
            self.cache[iteration] = load_model(self.layout, iteration, self.scene, self.fit)
        return self.cache[iteration]

    def rendered(self, plan: CameraPlan, stream: StreamPlan, c2w: np.ndarray, folder: Path) -> None:
        from paradrive.gs.views import render_views

        assert stream.iteration is not None
        p = self.params
        k = 0
        ego = self.ego(plan)
        # only the ego moves in a shifted stream: the actors stand where the log saw them
        for result in render_views(self.checkpoint(stream.iteration), c2w, plan.out.K, p.width,
                                   p.height, frames=plan.frames, depth=p.depth, batch_frames=p.batch_frames,
                                   sky=self.sky, device=p.device, backend=p.backend):
            for j in range(len(result["rgb"])):
                if ego is not None:  # the hood moves with the camera: the recorded one, put back
                    recorded = crop_resize(self.scene.load_image(plan.frames[k], plan.name), plan.out)
                    blend = (1.0 - ego) * result["rgb"][j] + ego * recorded
                    result["rgb"][j] = np.clip(np.round(blend), 0, 255).astype(np.uint8)
                self.write_frame(folder, plan.frames[k], result, j)
                k += 1
            self.tick(len(result["rgb"]))

    def write_frame(self, folder: Path, pos: int, result: dict, j: int) -> None:
        write_image(folder / frame_file(pos), result["rgb"][j])
        _frame_written()
        if self.params.depth:
            write_depth_exr(folder / "depth" / frame_file(pos, ".exr"), result["depth"][j])
        if self.params.alpha:
            a8 = (result["alpha"][j] * 255.0).round().astype(np.uint8)
            write_image(folder / "alpha" / frame_file(pos), a8[..., None])


def render_scene(layout: SceneLayout | Path, params: Params, *, log: logging.Logger | None = None,
                 progress: Progress | None = None) -> RendersRecord:
    """Render every stream of the scene with the render stage's ``params``; writes ``renders/``."""
    log = log or log_default
    layout = SceneLayout.at(layout)
    scene = load_scene(layout.root)
    check_params(params, scene, layout)
    plans = [plan_camera(scene, name, params, log) for name in params.cameras]
    n_streams = len(params.streams())
    total = sum(len(p.frames) for p in plans) * n_streams
    with atomic_path(layout.renders_dir) as tmp_root:
        tmp_root.mkdir(parents=True)
        renderer = _Renderer(scene, layout, params, tmp_root, progress, total)
        cameras = {}
        for plan in plans:
            cameras[plan.name] = renderer.camera(plan)
            log.info("render: %s camera %s: %d frames x %d streams, %d clips skipped",
                     scene.scene_id, plan.name, len(plan.frames),
                     n_streams if plan.frames else 0, len(plan.skipped))
        sky = renderer.sky
        record = RendersRecord(
            scene_id=scene.scene_id, width=params.width, height=params.height,
            condition_checkpoints=params.condition_checkpoints,
            source_checkpoint=params.source_checkpoint, offsets_m=params.source_offsets,
            clip_frames=params.clip_frames, depth=params.depth, alpha=params.alpha,
            sky_dome=None if sky is None else SkyDomeRecord(centre=[float(x) for x in sky.centre],
                                                            radius_m=sky.radius),
            cameras=cameras)
        record.save(tmp_root / layout.renders_json.name)
    return record


def run(ctx: StageContext[Params]) -> RendersRecord:
    from paradrive.devices import resolve_backend, resolve_device
    from paradrive.gs.model import deterministic_torch

    p = ctx.params
    with deterministic_torch(p.threads, resolve_backend(p.backend, resolve_device(p.device))):
        return render_scene(ctx.layout, ctx.params, log=ctx.log, progress=ctx.progress)


# each frame written, for the tests that stop a build at its k-th (render:frame-<k>)
_frame_written = counted_stop("render:frame")
