"""``paradrive view``: a scene or a build as a Rerun recording (``.rrd``) to scrub through in the
Rerun viewer (``rerun FILE.rrd``); the file is written offline, no viewer is needed to write it.

A scene shows what its stages have written so far, in the scene world (z up), on the timelines
``frame`` (the scene's frame index) and ``time`` (seconds since its first frame)::

    world/ego_path, world/ego                 the ego path; the ego pose per frame
    world/cameras/<camera>                    the recorded camera per frame (c2w)
    world/cameras/<camera>/image              its pinhole and image (JPEG) per frame
    world/cameras/<camera>/image/sky|dynamic  the sky and moving-actor masks (segmentation)
    world/lidar                               the LiDAR points per frame
    world/actors/<id>                         an actor's box2world per frame: box (id and class)
                                              and, after the fit, its node's Gaussians (gaussians)
    world/gaussians/ckpt_<iteration>[/sky]    a checkpoint's Gaussians as coloured points; only
                                              the final one is shown at first, the sky hidden
    world/renders/<camera>/<stream>           a rendered stream's camera per frame, its image:
                                              the clips as videos (one entity per clip), or the
                                              rendered frames (JPEG) before the clip stage
    world/render_paths/<camera>/<stream>      that camera's path

A build shows its pairs on the ``frame`` timeline (each pair's frame indices)::

    media/<scene_id>/clips/...                each video of the build once, at its URI (a
                                              video asset)
    pairs/<pair_id>/target|source             the target camera (target_c2w) and the source
                                              camera (target_c2w @ rel_pose) per frame, each
                                              with its video
    pairs/<pair_id>/condition                 the condition video
    pairs/<pair_id>/scores                    the pair's scores (text)

Videos are logged as video assets with a frame reference per frame, so a clip costs its MP4's
bytes. FFV1 ``.mkv`` clips, which the viewer cannot decode, are left out and reported. A
checkpoint keeps at most :data:`MAX_GAUSSIANS` Gaussians, the most opaque ones.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import time
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from paradrive.actors import CLASSES, Actor
from paradrive.contracts.layout import INDEX_JSON, SceneLayout, frame_file
from paradrive.contracts.records import ClipsRecord, FitRecord, IndexRecord, RendersRecord
from paradrive.errors import ConfigError, ParaDriveError, SceneError
from paradrive.gs.model import SH_C0
from paradrive.io import path_inside, write_bytes
from paradrive.pairs import build_file, read_index, read_pairs
from paradrive.scene import Frame, Scene, load_scene, read_image
from paradrive.uri import parse_uri

__all__ = ["MAX_GAUSSIANS", "MAX_LIDAR_POINTS", "MAX_PAIRS", "ViewReport", "require_rerun", "resolve_target",
           "default_output", "view_scene", "view_build", "open_viewer"]

INSTALL_FIX = 'pip install "paradrive[view]"'
APPLICATION_ID = "paradrive"
# a checkpoint's points: 200k coloured points are 3.2 MB in the file and stay fluid in the viewer
MAX_GAUSSIANS = 200_000
# a frame's LiDAR points at most (evenly picked): a 64-beam sweep is ~150k, 1.8 MB a frame
MAX_LIDAR_POINTS = 50_000
# a build viewed without --pair: its first pairs by pair id, this many at most
MAX_PAIRS = 200
JPEG_QUALITY = 85
VIDEO_SUFFIX = ".mp4"   # H.264 in MP4: what the viewer decodes
# a Gaussian this far from the ego path's centre (times the fit's sky radius) belongs to the sky
SKY_FRACTION = 0.5
MASK_CLASSES = {"sky": (1, (70, 130, 180)), "dynamic": (2, (220, 20, 60))}
ACTOR_COLOURS = {"vehicle": (242, 140, 0), "pedestrian": (26, 153, 51), "cyclist": (140, 51, 178),
                 "other": (102, 102, 102)}
STREAM_COLOURS = {"target": (255, 255, 255), "condition": (240, 200, 40), "source": (60, 140, 255)}
ROLE_COLUMNS = (("source", "source_uri"), ("condition", "condition_uri"), ("target", "target_uri"))


@dataclass
class ViewReport:
    """What a recording holds: its file, counts by kind, and what was left out (one line each)."""

    path: Path
    subject: str
    counts: Counter[str] = field(default_factory=Counter)
    left_out: list[str] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def bytes(self) -> int:
        return self.path.stat().st_size


# --------------------------------------------------------------------------- the recording

def require_rerun() -> Any:
    """The ``rerun`` module, or a ParaDriveError naming the fix when it is not installed."""
    try:
        import rerun
    except ModuleNotFoundError as exc:
        if exc.name != "rerun":
            raise
        raise ParaDriveError(f"paradrive view needs the rerun-sdk package, which is not installed; "
                             f"{INSTALL_FIX}") from exc
    return rerun


@contextlib.contextmanager
def _recording(out: Path, recording_id: str) -> Iterator[Any]:
    """A recording stream whose bytes land at ``out`` once complete, by rename.

    The recording is kept in memory and written here (the demo scene's is 47 MB): Rerun's own
    file sink, once a write of it fails (a full disk, the file size limit), leaves its flush and
    its disconnect waiting for ever, so the command would hang instead of saying what happened.
    """
    rr = require_rerun()
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id)
    rr.set_log_time_enabled(False, recording=rec)   # no wall-clock timeline: only the data's
    memory = rec.memory_recording()
    try:
        yield rec
        data = memory.drain_as_bytes()
    finally:
        rec.disconnect()
    write_bytes(out, data)


def _part(name: str) -> str:
    """One entity path part for a name of the data (actor ids hold ':', pair ids '/')."""
    import rerun as rr

    return str(rr.escape_entity_path_part(name))


def _transforms(rec: Any, entity: str, poses: np.ndarray, times: list[Any]) -> None:
    """Log ``poses`` (N, 4, 4) parent-from-entity at ``times`` (the time columns of N rows)."""
    import rerun as rr

    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    rec.send_columns(entity, indexes=times,
                     columns=rr.Transform3D.columns(translation=poses[:, :3, 3], mat3x3=poses[:, :3, :3]))


def _pinhole(intrinsics: Sequence[float], width: int, height: int, colour=None) -> Any:
    import rerun as rr

    fx, fy, cx, cy = (float(v) for v in intrinsics)
    return rr.Pinhole(image_from_camera=[[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]],
                      resolution=[int(width), int(height)], camera_xyz=rr.ViewCoordinates.RDF,
                      color=colour)


def _jpeg(path: Path, scene_id: str) -> Any:
    """An image file as JPEG bytes: a JPEG as it is, anything else compressed."""
    import rerun as rr

    if path.suffix.lower() in (".jpg", ".jpeg"):
        return rr.EncodedImage(path=path)
    return rr.Image(read_image(path, scene_id=scene_id)).compress(jpeg_quality=JPEG_QUALITY)


def _video(rec: Any, entity: str, file: Path, frames: Sequence[int], seconds: Sequence[float] | None = None,
           *, asset: str | None = None) -> int:
    """Frame references of the video at ``asset`` (``file`` logged there, or at ``entity`` when
    None) on the given frames; returns how many (the shorter of the video and ``frames``)."""
    import rerun as rr

    video = rr.AssetVideo(path=file)
    if asset is None:
        rec.log(entity, video, static=True)
    stamps = video.read_frame_timestamps_nanos()
    n = min(len(stamps), len(frames))
    times = [rr.TimeColumn("frame", sequence=np.asarray(frames[:n], dtype=np.int64))]
    if seconds is not None:
        times.append(rr.TimeColumn("time", duration=np.asarray(seconds[:n], dtype=np.float64)))
    rec.send_columns(entity, indexes=times, columns=rr.VideoFrameReference.columns_nanos(stamps[:n]))
    if asset is not None:
        rec.log(entity, rr.VideoFrameReference.from_fields(video_reference=asset), static=True)
    return n


def _write(out: Path, recording_id: str, subject: str, log: Callable[[Any, ViewReport], None]) -> ViewReport:
    """Run ``log(rec, report)`` into a recording at ``out``; the report with the time it took."""
    start = time.perf_counter()
    report = ViewReport(Path(out), subject)
    with _recording(report.path, recording_id) as rec:
        log(rec, report)
    report.seconds = time.perf_counter() - start
    return report


# --------------------------------------------------------------------------- a scene

class _Clock:
    """The scene's timelines: ``frame`` (frame index) and ``time`` (seconds since frame 0)."""

    def __init__(self, scene: Scene, where: Path):
        self.scene = scene
        self.where = where
        self.t0 = scene.frames[0].timestamp_us
        self.position = {f.index: p for p, f in enumerate(scene.frames)}

    def set(self, rec: Any, frame: Frame) -> None:
        rec.set_time("frame", sequence=frame.index)
        rec.set_time("time", duration=(frame.timestamp_us - self.t0) * 1e-6)

    def seconds(self, frame: Frame) -> float:
        return (frame.timestamp_us - self.t0) * 1e-6

    def columns(self, frames: Sequence[Frame]) -> list[Any]:
        import rerun as rr

        return [rr.TimeColumn("frame", sequence=np.array([f.index for f in frames], dtype=np.int64)),
                rr.TimeColumn("time", duration=np.array([self.seconds(f) for f in frames]))]

    def at_positions(self, positions: Sequence[int], what: str) -> list[Frame]:
        """The frames at ``positions`` of ``scene.json``; a SceneError naming ``what`` otherwise."""
        bad = [p for p in positions if not 0 <= int(p) < len(self.scene.frames)]
        if bad:
            raise SceneError(f"{what} names frame position {bad[0]}, but the scene has "
                             f"{len(self.scene.frames)} frames", scene_id=self.scene.scene_id,
                             path=self.where, fix="re-run that stage for this scene")
        return [self.scene.frames[int(p)] for p in positions]

    def at_indices(self, indices: Sequence[int], what: str) -> list[Frame]:
        """The frames with these ``Frame.index`` values; a SceneError naming ``what`` otherwise."""
        missing = [i for i in indices if int(i) not in self.position]
        if missing:
            raise SceneError(f"{what} names frame {missing[0]}, which the scene does not have",
                             scene_id=self.scene.scene_id, path=self.where,
                             fix="re-run that stage for this scene")
        return [self.scene.frames[self.position[int(i)]] for i in indices]

    def after(self, frame: Frame) -> Frame | None:
        """The scene frame after ``frame``, None after the last."""
        p = self.position[frame.index] + 1
        return self.scene.frames[p] if p < len(self.scene.frames) else None


def _colour_by_height(points: np.ndarray) -> np.ndarray:
    """uint8 (N, 3) colours running blue -> green -> yellow -> red with the height (z)."""
    z = points[:, 2]
    lo, hi = np.percentile(z, [2, 98]) if len(z) else (0.0, 1.0)
    t = np.clip((z - lo) / max(hi - lo, 1e-6), 0.0, 1.0)
    stops = np.array([0.0, 0.33, 0.66, 1.0])
    ramp = np.array([[40, 80, 220], [40, 200, 120], [240, 220, 40], [230, 50, 40]], dtype=np.float64)
    return np.stack([np.interp(t, stops, ramp[:, c]) for c in range(3)], 1).astype(np.uint8)


def _log_world(rec: Any, scene: Scene) -> None:
    """What does not change with time: axes, class colours, the ego path, the pinholes, a note."""
    import rerun as rr

    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    rec.log("world/actors", rr.AnnotationContext(
        [rr.AnnotationInfo(id=k + 1, label=c, color=ACTOR_COLOURS[c]) for k, c in enumerate(CLASSES)]),
        static=True)
    # class 0 (neither sky nor a moving actor) transparent, else the viewer tints the whole image
    masks = [rr.AnnotationInfo(id=0, label="none", color=(0, 0, 0, 0))]
    masks += [rr.AnnotationInfo(id=i, label=name, color=colour) for name, (i, colour) in MASK_CLASSES.items()]
    rec.log("world/cameras", rr.AnnotationContext(masks), static=True)
    rec.log("world/ego_path", rr.LineStrips3D([scene.ego2world()[:, :3, 3]], colors=[(255, 255, 255)]),
            static=True)
    rec.log("world/ego", rr.TransformAxes3D(2.0), static=True)
    for name, cam in scene.cameras.items():
        rec.log(f"world/cameras/{_part(name)}/image",
                _pinhole((cam.fx, cam.fy, cam.cx, cam.cy), cam.width, cam.height), static=True)
    first = scene.frames[0]
    rec.log("scene", rr.TextDocument(
        f"# {scene.scene_id}\n\n- dataset: {scene.dataset}\n- source: `{scene.source}`\n"
        f"- frames: {len(scene.frames)} at {scene.fps:g} fps, first at {first.timestamp_us} us\n"
        f"- cameras: {', '.join(scene.cameras)}\n- actors: {len(scene.actors)}",
        media_type="text/markdown"), static=True)


def _log_masks(rec: Any, scene: Scene, position: int, camera: str, entity: str) -> int:
    """The frame's sky and dynamic masks as segmentation images; how many were found."""
    import rerun as rr

    layout = SceneLayout(scene._require_root())
    index = scene.frames[position].index
    found = 0
    for name, path in (("sky", layout.sky_mask(camera, index)), ("dynamic", layout.dynamic_mask(camera, index))):
        if path.is_file():
            mask = read_image(path, scene_id=scene.scene_id)[..., 0] > 127
            rec.log(f"{entity}/{name}", rr.SegmentationImage(mask.astype(np.uint8) * MASK_CLASSES[name][0]))
            found += 1
    return found


def _log_frames(rec: Any, scene: Scene, clock: _Clock, report: ViewReport) -> None:
    """Per frame: the ego pose, every camera's pose, image and masks, the LiDAR points."""
    import rerun as rr

    _transforms(rec, "world/ego", scene.ego2world(), clock.columns(scene.frames))
    for name in scene.cameras:
        frames = [f for f in scene.frames if name in f.cameras]
        _transforms(rec, f"world/cameras/{_part(name)}", np.stack([f.cameras[name].c2w for f in frames]),
                    clock.columns(frames))
    for position, frame in enumerate(scene.frames):
        clock.set(rec, frame)
        for name in frame.cameras:
            entity = f"world/cameras/{_part(name)}/image"
            rec.log(entity, _jpeg(scene.image_path(position, name), scene.scene_id))
            report.counts["images"] += 1
            report.counts["masks"] += _log_masks(rec, scene, position, name, entity)
        points = scene.lidar_frame(position)
        if points is not None:
            if len(points) > MAX_LIDAR_POINTS:
                report.counts["lidar_points_left_out"] += len(points) - MAX_LIDAR_POINTS
                points = points[np.linspace(0, len(points) - 1, MAX_LIDAR_POINTS).astype(np.int64)]
            rec.log("world/lidar", rr.Points3D(points, colors=_colour_by_height(points), radii=0.03))
            report.counts["lidar_frames"] += 1
            report.counts["lidar_points"] += len(points)
    report.counts["frames"] = len(scene.frames)
    report.counts["cameras"] = len(scene.cameras)


@dataclass
class _Points:
    """Coloured points: positions (N, 3) float32, colours (N, 4) uint8 RGBA, radii (N,) metres."""

    positions: np.ndarray
    colours: np.ndarray
    radii: np.ndarray

    def __len__(self) -> int:
        return len(self.positions)

    def take(self, keep: np.ndarray) -> _Points:
        return _Points(self.positions[keep], self.colours[keep], self.radii[keep])

    def most_opaque(self, cap: int) -> _Points:
        """The ``cap`` most opaque points (all when there are no more), in their order."""
        if len(self) <= cap:
            return self
        return self.take(np.sort(np.argsort(-self.colours[:, 3], kind="stable")[:cap]))

    def archetype(self) -> Any:
        import rerun as rr

        return rr.Points3D(self.positions, colors=self.colours, radii=self.radii)


def _gaussian_points(path: Path, scene_id: str) -> _Points:
    """A 3DGS checkpoint as points: the band-0 colour, the opacity as alpha, the mean scale as
    radius."""
    from paradrive.gs.ply import load_checkpoint

    params = load_checkpoint(path, scene_id=scene_id)
    rgb = np.clip(params["sh0"].numpy().reshape(-1, 3) * SH_C0 + 0.5, 0.0, 1.0)
    alpha = 1.0 / (1.0 + np.exp(-params["opacities"].numpy().astype(np.float64)))
    colours = (np.concatenate([rgb, alpha[:, None]], 1) * 255).round().astype(np.uint8)
    # the mean scale, capped: a sky or background Gaussian metres wide would hide the street
    radii = np.clip(np.exp(params["scales"].numpy()).mean(1), 0.01, 0.08).astype(np.float32)
    return _Points(params["means"].numpy().astype(np.float32), colours, radii)


def _log_checkpoints(rec: Any, layout: SceneLayout, scene: Scene, fit: FitRecord, cap: int,
                     report: ViewReport) -> list[int]:
    """Every checkpoint's Gaussians (static), the sky apart; the iterations logged."""
    centre = scene.ego2world()[:, :3, 3].mean(0)
    logged = []
    for ckpt in sorted(fit.checkpoints, key=lambda c: c.iteration):
        path = layout.checkpoint(ckpt.iteration)
        if not path.is_file():
            report.left_out.append(f"checkpoint {ckpt.iteration}: {path} is missing")
            continue
        every = _gaussian_points(path, scene.scene_id)
        points = every.most_opaque(cap)
        sky = np.linalg.norm(points.positions - centre, axis=1) > SKY_FRACTION * fit.init.sky_radius_m
        entity = f"world/gaussians/ckpt_{ckpt.iteration:06d}"
        rec.log(entity, points.take(~sky).archetype(), static=True)
        rec.log(f"{entity}/sky", points.take(sky).archetype(), static=True)
        report.counts["gaussians"] += len(points)
        if len(points) < len(every):
            report.left_out.append(f"checkpoint {ckpt.iteration}: the {len(points)} most opaque of its "
                                   f"{len(every)} Gaussians")
        logged.append(ckpt.iteration)
    report.counts["checkpoints"] = len(logged)
    return logged


def _actor_nodes(layout: SceneLayout, scene: Scene, fit: FitRecord | None) -> dict[str, _Points]:
    """The final checkpoint's actor nodes (box frame) by actor id; none without a scene-graph fit."""
    last = fit.at(None) if fit is not None else None
    if fit is None or last is None:
        return {}
    nodes = {}
    for node in fit.actors:
        path = layout.actor_checkpoint(last.iteration, node.file)
        if path.is_file():
            nodes[node.id] = _gaussian_points(path, scene.scene_id)
    return nodes


def _log_actor(rec: Any, actor: Actor, clock: _Clock, node: _Points | None) -> None:
    """One actor: its pose per track frame; its box and node from the first frame of each run of
    frames it is seen in, cleared at the first frame it is not."""
    import rerun as rr

    entity = f"world/actors/{_part(actor.id)}"
    frames = clock.at_indices([int(f) for f in actor.frames], f"actor {actor.id} track")
    _transforms(rec, entity, actor.box2world, clock.columns(frames))
    seen = {f.index for f in frames}
    box = rr.Boxes3D(half_sizes=[0.5 * actor.size], labels=[f"{actor.id} ({actor.cls})"], show_labels=True,
                     class_ids=[CLASSES.index(actor.cls) + 1 if actor.cls in CLASSES else 0])
    previous: int | None = None
    for frame in frames:
        if previous is None or clock.position[frame.index] != clock.position[previous] + 1:
            clock.set(rec, frame)
            rec.log(f"{entity}/box", box)
            if node is not None:
                rec.log(f"{entity}/gaussians", node.archetype())
        after = clock.after(frame)
        if after is not None and after.index not in seen:
            clock.set(rec, after)
            rec.log(entity, rr.Clear(recursive=True))
        previous = frame.index


def _log_renders(rec: Any, layout: SceneLayout, clock: _Clock, renders: RendersRecord, frames: bool,
                 report: ViewReport) -> None:
    """Each rendered stream's camera per frame and its path; with ``frames``, its rendered
    frames too (JPEG), those the render stage kept."""
    import rerun as rr

    where = f"{layout.renders_json}"
    for camera, rendered in renders.cameras.items():
        scene_frames = clock.at_positions(rendered.frames, f"renders.json camera {camera} frames")
        for name, stream in rendered.streams.items():
            entity = f"world/renders/{_part(camera)}/{_part(name)}"
            c2w = np.asarray(stream.c2w, dtype=np.float64).reshape(-1, 4, 4)
            _transforms(rec, entity, c2w, clock.columns(scene_frames[:len(c2w)]))
            colour = STREAM_COLOURS.get(stream.kind, STREAM_COLOURS["source"])
            rec.log(f"{entity}/image", _pinhole(rendered.intrinsics, renders.width, renders.height, colour),
                    static=True)
            rec.log(f"world/render_paths/{_part(camera)}/{_part(name)}",
                    rr.LineStrips3D([c2w[:, :3, 3]], colors=[colour]), static=True)
            report.counts["render_streams"] += 1
            if not frames:
                continue
            for position, frame in zip(rendered.frames, scene_frames):
                path = path_inside(layout.renders_dir, f"{stream.dir}/{frame_file(position)}",
                                   f"{where}: stream {name} frame {position}")
                if path.is_file():
                    clock.set(rec, frame)
                    rec.log(f"{entity}/image", _jpeg(path, renders.scene_id))
                    report.counts["render_frames"] += 1


def _log_clips(rec: Any, layout: SceneLayout, clock: _Clock, clips: ClipsRecord, report: ViewReport) -> None:
    """Every clip stream as a video under its rendered camera, shown over the clip's frames."""
    import rerun as rr

    for clip in clips.clips:
        what = f"{layout.clips_json}: clip {clip.camera}/{clip.clip}"
        frames = clock.at_indices(clip.frame_indices, what)
        for name, stream in clip.streams.items():
            file = path_inside(layout.root, stream.file, f"{what} stream {name}")
            if file.suffix.lower() != VIDEO_SUFFIX:
                report.left_out.append(f"{stream.file}: the viewer plays {VIDEO_SUFFIX} (H.264) videos only")
                continue
            entity = f"world/renders/{_part(clip.camera)}/{_part(name)}/image/{_part(clip.clip)}"
            report.counts["video_frames"] += _video(rec, entity, file, [f.index for f in frames],
                                                    [clock.seconds(f) for f in frames])
            report.counts["videos"] += 1
            after = clock.after(frames[-1])
            if after is not None:
                clock.set(rec, after)
                rec.log(entity, rr.Clear(recursive=False))


def _scene_blueprint(scene: Scene, checkpoints: list[int], renders: RendersRecord | None) -> Any:
    """The 3D world (the final checkpoint shown, earlier ones and the sky hidden) beside the
    recorded cameras, and a tab of each rendered camera's streams."""
    import rerun.blueprint as rrb

    hidden: dict[Any, Any] = {f"world/gaussians/ckpt_{it:06d}": rrb.EntityBehavior(visible=False)
                              for it in checkpoints[:-1]}
    hidden.update({f"world/gaussians/ckpt_{it:06d}/sky": rrb.EntityBehavior(visible=False)
                   for it in checkpoints[-1:]})
    world = rrb.Spatial3DView(origin="world", name=scene.scene_id, overrides=hidden)
    recorded = [rrb.Spatial2DView(origin=f"world/cameras/{_part(c)}/image", name=c) for c in scene.cameras]
    tabs: list[Any] = [rrb.Vertical(*recorded, name="recorded")]
    for camera, rendered in (renders.cameras.items() if renders is not None else []):
        tabs.append(rrb.Grid(*[rrb.Spatial2DView(origin=f"world/renders/{_part(camera)}/{_part(s)}/image", name=s)
                               for s in rendered.streams], name=f"rendered {camera}"))
    return rrb.Blueprint(rrb.Horizontal(world, rrb.Tabs(*tabs), column_shares=[3, 2]))


def _record(path: Path, scene_id: str, record_type):
    """A stage's record of the scene when the stage has written it, else None."""
    return record_type.load(path, scene_id) if path.is_file() else None


def view_scene(scene_dir: str | Path, out: str | Path, *, max_gaussians: int = MAX_GAUSSIANS) -> ViewReport:
    """Write the recording of a scene folder (ingested, and whatever later stages wrote) to ``out``."""
    layout = SceneLayout.at(Path(scene_dir))
    scene = load_scene(layout.root)
    fit = _record(layout.fit_json, scene.scene_id, FitRecord)
    renders = _record(layout.renders_json, scene.scene_id, RendersRecord)
    clips = _record(layout.clips_json, scene.scene_id, ClipsRecord)
    clock = _Clock(scene, layout.scene_json)

    def log(rec: Any, report: ViewReport) -> None:
        _log_world(rec, scene)
        _log_frames(rec, scene, clock, report)
        nodes = _actor_nodes(layout, scene, fit)
        for actor in scene.actors:
            _log_actor(rec, actor, clock, nodes.get(actor.id))
        report.counts["actors"] = len(scene.actors)
        report.counts["actor_nodes"] = len(nodes)
        checkpoints = _log_checkpoints(rec, layout, scene, fit, max_gaussians, report) if fit else []
        if renders is not None:
            _log_renders(rec, layout, clock, renders, clips is None, report)
        if clips is not None:
            _log_clips(rec, layout, clock, clips, report)
        rec.send_blueprint(_scene_blueprint(scene, checkpoints, renders))

    return _write(Path(out), f"scene-{scene.scene_id}", f"scene {scene.scene_id}", log)


# --------------------------------------------------------------------------- a build

BUILD_COLUMNS = ["pair_id", "scene_id", "camera", "clip", "offset_m", "frame_indices", "width", "height",
                 "intrinsics", "rel_pose", "target_c2w", "condition_iteration", "source_iteration",
                 "source_uri", "condition_uri", "target_uri", "condition_psnr", "condition_ssim",
                 "fit_train_psnr", "fit_train_ssim"]


def _pair_entity(pair_id: str) -> str:
    return "pairs/" + "/".join(_part(p) for p in pair_id.split("/") if p)


def _scores(row: dict) -> str:
    def fmt(value, digits: int) -> str:
        return "-" if value is None else f"{value:.{digits}f}"

    return (f"# {row['pair_id']}\n\n| | |\n|---|---|\n| scene | {row['scene_id']} |\n"
            f"| camera / clip | {row['camera']} / {row['clip']} |\n| offset | {row['offset_m']:+g} m |\n"
            f"| condition checkpoint | {row['condition_iteration']} |\n"
            f"| source checkpoint | {row['source_iteration']} |\n"
            f"| condition PSNR / SSIM | {fmt(row['condition_psnr'], 2)} dB / {fmt(row['condition_ssim'], 3)} |\n"
            f"| fit PSNR / SSIM (training views) | {fmt(row['fit_train_psnr'], 2)} dB / "
            f"{fmt(row['fit_train_ssim'], 3)} |\n")


def _log_pair(rec: Any, build_dir: Path, index: IndexRecord, row: dict, media: dict[str, str],
              report: ViewReport) -> None:
    """One pair: the target and source cameras per frame with their videos, the condition video
    and the scores; each video file is logged once, under ``media/``."""
    import rerun as rr

    entity = _pair_entity(row["pair_id"])
    frames = [int(f) for f in row["frame_indices"]]
    target = np.asarray(row["target_c2w"], dtype=np.float64).reshape(-1, 4, 4)
    cameras = {"target": target, "source": target @ np.asarray(row["rel_pose"], dtype=np.float64).reshape(-1, 4, 4)}
    times = [rr.TimeColumn("frame", sequence=np.asarray(frames[:len(target)], dtype=np.int64))]
    for role, c2w in cameras.items():
        _transforms(rec, f"{entity}/{role}", c2w, times)
        rec.log(f"{entity}/{role}/image", _pinhole(row["intrinsics"], row["width"], row["height"],
                                                   STREAM_COLOURS[role]), static=True)
    for role, column in ROLE_COLUMNS:
        uri = row[column]
        if uri is None:   # an inference row may have no target
            continue
        file = build_file(build_dir, uri, f"{build_dir / INDEX_JSON}: row {row['pair_id']} column {column}", index)
        if file.suffix.lower() != VIDEO_SUFFIX:
            report.left_out.append(f"{uri}: the viewer plays {VIDEO_SUFFIX} (H.264) videos only")
            continue
        if uri not in media:
            media[uri] = "/".join(_part(p) for p in uri.split("/"))   # media/<scene_id>/clips/...
            rec.log(media[uri], rr.AssetVideo(path=file), static=True)
            report.counts["videos"] += 1
        where = f"{entity}/{role}/image" if role in cameras else f"{entity}/{role}"
        report.counts["video_frames"] += _video(rec, where, file, frames, asset=media[uri])
    rec.log(f"{entity}/scores", rr.TextDocument(_scores(row), media_type="text/markdown"), static=True)
    report.counts["pairs"] += 1


def _pair_blueprint(row: dict) -> Any:
    """One pair: source, condition and target side by side; below, both cameras in 3D and the scores."""
    import rerun.blueprint as rrb

    entity = _pair_entity(row["pair_id"])
    videos = [rrb.Spatial2DView(origin=f"{entity}/source/image", name="source"),
              rrb.Spatial2DView(origin=f"{entity}/condition", name="condition"),
              rrb.Spatial2DView(origin=f"{entity}/target/image", name="target")]
    # the condition video has no camera of its own (it is the target camera's render): 2D only
    below = [rrb.Spatial3DView(origin=entity, contents=["$origin/**", "- $origin/condition/**"],
                               name="rel_pose: source and target cameras"),
             rrb.TextDocumentView(origin=f"{entity}/scores", name="scores")]
    return rrb.Blueprint(rrb.Vertical(rrb.Horizontal(*videos), rrb.Horizontal(*below)))


def _chosen_pairs(rows: list[dict], pair_ids: Sequence[str], build_dir: Path) -> tuple[list[dict], list[str]]:
    """The rows of ``pair_ids``, or without them the first :data:`MAX_PAIRS` by pair id; and a
    line saying what was left out."""
    if pair_ids:
        known = {r["pair_id"]: r for r in rows}
        missing = [p for p in pair_ids if p not in known]
        if missing:
            raise ConfigError(f"{build_dir}: no pair {missing[0]!r} in this build; see its pair ids "
                              f"in the shards its {INDEX_JSON} lists (paradrive inspect {build_dir})")
        return [known[p] for p in dict.fromkeys(pair_ids)], []
    rows = sorted(rows, key=lambda r: r["pair_id"])
    if len(rows) > MAX_PAIRS:
        return rows[:MAX_PAIRS], [f"pairs: the first {MAX_PAIRS} of {len(rows)} by pair id (pick others with --pair)"]
    return rows, []


def view_build(build_dir: str | Path, out: str | Path, *, pair_ids: Sequence[str] = ()) -> ViewReport:
    """Write the recording of a published build's pairs (``pair_ids``, or its first ones) to ``out``."""
    build_dir = Path(build_dir)
    index = read_index(build_dir)
    rows = read_pairs(build_dir, BUILD_COLUMNS, index).to_pylist()
    if not rows:
        raise ParaDriveError(f"{build_dir / INDEX_JSON}: the build has no pairs to show; build "
                             f"scenes into it first (paradrive build)")

    chosen, left_out = _chosen_pairs(rows, pair_ids, build_dir)

    def log(rec: Any, report: ViewReport) -> None:
        report.left_out += left_out
        media: dict[str, str] = {}
        for row in chosen:
            _log_pair(rec, build_dir, index, row, media, report)
        rec.send_blueprint(_pair_blueprint(chosen[0]))

    return _write(Path(out), f"build-{index.build}", f"build {index.build}", log)


# --------------------------------------------------------------------------- the command

def resolve_target(target: str, data_dir: str | Path) -> tuple[str, Path]:
    """("build" | "scene", folder) of what ``paradrive view`` was given: a build folder (holding
    index.json), a scene folder (holding scene.json), or a scene URI found under ``data_dir``."""
    path = Path(target)
    if (path / INDEX_JSON).is_file():
        return "build", path
    if SceneLayout(path).scene_json.is_file():
        return "scene", path
    if path.is_dir():
        raise ConfigError(f"{path} holds neither scene.json (a scene folder after ingest) nor "
                          f"{INDEX_JSON} (a published build); pass one of those folders")
    try:
        scene_id = parse_uri(target).scene_id
    except ConfigError as exc:
        raise ConfigError(f"{target!r} is not a folder; pass a scene folder, a build folder or a "
                          f"scene URI ({exc})") from exc
    layout = SceneLayout.of(data_dir, scene_id)
    if not layout.scene_json.is_file():
        raise ConfigError(f"scene {scene_id}: {layout.scene_json} is missing; ingest it first "
                          f"(paradrive build --scene '{target}' --stages ingest --data {data_dir}) or "
                          f"pass the --data folder it was built in")
    return "scene", layout.root


def default_output(folder: Path) -> Path:
    """Beside the scene or build folder: ``<folder>.rrd``."""
    return folder.with_name(folder.name + ".rrd")


def open_viewer(path: Path) -> subprocess.Popen:
    """Start the Rerun viewer on ``path``; a ParaDriveError when this machine has no display."""
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise ParaDriveError(f"--spawn: this machine has no display (neither DISPLAY nor WAYLAND_DISPLAY "
                             f"is set); {path} is written: open it with `rerun {path}` where a screen is")
    require_rerun()
    return subprocess.Popen([sys.executable, "-m", "rerun", str(path)], start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def describe(report: ViewReport) -> str:
    """``wrote FILE (1.2 MB in 3.4 s): 24 frames, 3 cameras, ...``"""
    counts = ", ".join(f"{n} {k.replace('_', ' ')}" for k, n in report.counts.items() if n)
    return (f"wrote {report.path} ({report.bytes / 1e6:.1f} MB in {report.seconds:.1f} s): "
            f"{report.subject}: {counts}")
