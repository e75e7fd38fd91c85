"""The ``clip`` stage (``stages/clip.yaml``): cut front / middle / rear clips and encode every
stream as video.

It reads ``renders/renders.json`` (:class:`RendersRecord`) and writes, per camera and clip
window::

    clips/<camera>/<clip>/<stream>.mp4            (H.264; .mkv for the lossless ffv1 codec)
    clips/<camera>/<clip>/depth/<stream>/<frame:06d>.exr   (with clip.depth)
    clips/clips.json                               (:class:`ClipsRecord`, what the manifest reads)

The whole ``clips/`` folder is assembled under a temporary name, ``clips.json`` last, and
renamed into place in one step: a reader never sees a half-written clip set.
"""

from __future__ import annotations

import logging
import os
import shutil
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from paradrive.errors import SceneError
from paradrive.io import atomic_path, counted_stop
from paradrive.metrics import frames_quality
from paradrive.scene import Scene, load_scene, read_image
from paradrive.contracts.base import StageContext, StageParams
from paradrive.contracts.layout import SceneLayout, clip_depth_dir, clip_file, frame_file
from paradrive.contracts.records import (CameraIntrinsics, CameraSkippedClip, ClipRecord, ClipsRecord,
                                      ClipStream, FitFigures, FitRecord, Quality, RenderedCamera,
                                      RenderedStream, RendersRecord, WindowRecord)
from paradrive.video import container_suffix, encode_video

Progress = Callable[[int, int], None]

# Streams of a clip read, scored and encoded at once (the stage's resources: two cores); the
# files do not depend on it.
ENCODERS = min(2, os.cpu_count() or 1)


class Params(StageParams):
    codec: str
    crf: int
    preset: str
    pix_fmt: str
    depth: bool
    gop: int


def fit_figures(layout: SceneLayout, iteration: int | None) -> FitFigures:
    """Training-view PSNR / SSIM of the fit at ``iteration`` (else its last checkpoint)."""
    try:
        entry = FitRecord.load(layout.fit_json, layout.scene_id).at(iteration)
    except SceneError:
        entry = None
    if entry is None:
        return FitFigures(iteration=iteration, train_psnr=None, train_ssim=None)
    return FitFigures(iteration=entry.iteration, train_psnr=entry.psnr, train_ssim=entry.ssim)


def _quality(cond: np.ndarray, target: np.ndarray) -> Quality:
    value, structure = frames_quality(cond, target)
    return Quality(psnr=round(value, 4), ssim=round(structure, 5))


def check_renders(renders: RendersRecord, params: Params, layout: SceneLayout) -> None:
    sid = layout.scene_id
    w, h = renders.width, renders.height
    if params.codec == "libx264" and params.pix_fmt.startswith("yuv420") and (w % 2 or h % 2):
        raise SceneError(f"renders are {w}x{h}; H.264 {params.pix_fmt} needs even sizes",
                         scene_id=sid, path=layout.renders_json,
                         fix="set render.width / render.height to even numbers or use clip.codec=ffv1")
    if params.depth and not renders.depth:
        raise SceneError("clip.depth is set but the renders have no depth", scene_id=sid,
                         path=layout.renders_json, fix="set render.depth=true and re-run render")


class _ClipWriter:
    """Encodes the clips of one scene under a temporary ``clips/`` folder."""

    def __init__(self, scene: Scene, layout: SceneLayout, renders: RendersRecord, params: Params,
                 tmp_root: Path, progress: Progress | None, total: int):
        self.scene, self.layout, self.renders, self.params = scene, layout, renders, params
        self.tmp_root, self.progress, self.total, self.done = tmp_root, progress, total, 0
        self.suffix = container_suffix(params.codec)
        self.timestamps = scene.timestamps_us()

    def clip(self, cam_name: str, cam: RenderedCamera, window: WindowRecord) -> ClipRecord:
        sid = self.scene.scene_id
        positions = list(range(window.frame_start, window.frame_start + window.num_frames))
        frame_rows = {p: r for r, p in enumerate(cam.frames)}
        missing = [p for p in positions if p not in frame_rows]
        if missing:
            raise SceneError(f"renders of camera {cam_name} lack frames {missing[:5]} of clip "
                             f"{window.clip}", scene_id=sid, path=self.layout.renders_json,
                             fix="re-run the render stage with the same clip parameters")
        rows = [frame_rows[p] for p in positions]
        ordered = sorted(cam.streams.items(), key=lambda kv: kv[1].kind != "target")
        # the target's frames, read once and kept to score each condition
        target = (self.frames(ordered[0][1], positions)
                  if ordered and ordered[0][1].kind == "target" else None)

        def one(name: str, stream: RenderedStream) -> tuple[ClipStream, Quality | None]:
            frames = (target if target is not None and stream.kind == "target"
                      else self.frames(stream, positions))
            score = (_quality(frames, target)
                     if stream.kind == "condition" and target is not None else None)
            return self.encode(cam_name, window.clip, name, stream, frames, positions, rows), score

        # ENCODERS streams at a time (x264's own threads barely help at clip sizes, so two
        # encoders keep two cores busy); the results in the streams' order, and the streams not
        # started are dropped when one fails
        streams, quality = {}, {}
        with ThreadPoolExecutor(ENCODERS) as pool:
            futures = [pool.submit(one, *kv) for kv in ordered]
            try:
                for (name, _), future in zip(ordered, futures, strict=True):
                    streams[name], score = future.result()
                    if score is not None:
                        quality[name] = score
                    self.done += 1
                    if self.progress:
                        self.progress(self.done, self.total)
            except BaseException:
                for future in futures:
                    future.cancel()
                raise
        return ClipRecord(
            camera=cam_name, clip=window.clip, frame_start=window.frame_start,
            num_frames=window.num_frames,
            frame_indices=[int(self.scene.frames[p].index) for p in positions],
            timestamps_us=[int(self.timestamps[p]) for p in positions],
            c2w=[cam.c2w[r] for r in rows], streams=streams, quality=quality,
            dynamic_fraction=(None if cam.moving is None
                              else round(float(np.mean([cam.moving[r] for r in rows])), 6)))

    def frames(self, stream: RenderedStream, positions: list[int]) -> np.ndarray:
        folder = self.layout.renders_dir / stream.dir
        sid = self.scene.scene_id
        frames = np.stack([read_image(folder / frame_file(p), scene_id=sid) for p in positions])
        w, h = self.renders.width, self.renders.height
        if frames.shape[1:3] != (h, w):
            raise SceneError(f"render {folder} is {frames.shape[2]}x{frames.shape[1]}, "
                             f"renders.json says {w}x{h}", scene_id=sid,
                             path=folder, fix="re-run the render stage")
        return frames

    def encode(self, cam_name: str, clip: str, name: str, stream: RenderedStream,
               frames: np.ndarray, positions: list[int], rows: list[int]) -> ClipStream:
        p = self.params
        rel = clip_file(cam_name, clip, name, self.suffix)
        info = encode_video(self.tmp_root.parent / _under(self.tmp_root, rel), frames,
                            self.scene.fps, codec=p.codec, crf=p.crf, preset=p.preset,
                            pix_fmt=p.pix_fmt if p.codec == "libx264" else None, gop=p.gop)
        _video_written()
        source = stream.kind == "source"
        return ClipStream(file=rel, bytes=info["bytes"], sha256=info["sha256"], kind=stream.kind,
                          iteration=stream.iteration,
                          offset_m=stream.offset_m if source else None,
                          c2w=[stream.c2w[r] for r in rows] if source else None,
                          depth_dir=self.depth(cam_name, clip, name, stream, positions)
                          if p.depth else None)

    def depth(self, cam_name: str, clip: str, name: str, stream: RenderedStream,
              positions: list[int]) -> str | None:
        """Copy the stream's depth EXRs next to the clip; its folder, or None without depth."""
        rel = clip_depth_dir(cam_name, clip, name)
        depth_dir = self.tmp_root.parent / _under(self.tmp_root, rel)
        depth_dir.mkdir(parents=True, exist_ok=True)
        for p in positions:
            src = self.layout.renders_dir / stream.dir / "depth" / frame_file(p, ".exr")
            if not src.is_file() and stream.kind != "target":
                raise SceneError("depth render is missing", scene_id=self.scene.scene_id,
                                 path=src, fix="re-run the render stage with render.depth=true")
            if src.is_file():
                shutil.copyfile(src, depth_dir / src.name)
        if any(depth_dir.iterdir()):
            return rel
        depth_dir.rmdir()
        return None


# each video encoded, for the tests that stop a build at its k-th (clip:video-<k>)
_video_written = counted_stop("clip:video")


def _under(tmp_root: Path, rel: str) -> Path:
    """``clips/<cam>/<clip>/x`` re-rooted under the temporary clips folder (relative to its parent)."""
    return Path(tmp_root.name, *Path(rel).parts[1:])


def write_clips(layout: SceneLayout | Path, params: Params, *, log: logging.Logger | None = None,
                progress: Progress | None = None) -> ClipsRecord:
    """Encode every stream of every clip window listed in ``renders/renders.json``."""
    layout = SceneLayout.at(layout)
    scene = load_scene(layout.root, check_files=False)
    renders = RendersRecord.load(layout.renders_json, scene.scene_id)
    check_renders(renders, params, layout)
    jobs = [(name, cam, w) for name, cam in renders.cameras.items() for w in cam.windows]
    total = sum(len(cam.streams) for _, cam, _ in jobs)
    with atomic_path(layout.clips_dir) as tmp_root:
        tmp_root.mkdir(parents=True)
        writer = _ClipWriter(scene, layout, renders, params, tmp_root, progress, total)
        clips = []
        for cam_name, cam, window in jobs:
            clips.append(writer.clip(cam_name, cam, window))
            if log:
                log.info("clip: %s %s/%s: %d streams x %d frames", scene.scene_id, cam_name,
                         window.clip, len(clips[-1].streams), window.num_frames)
        record = ClipsRecord(
            scene_id=scene.scene_id, dataset=scene.dataset, source=scene.source, fps=scene.fps,
            width=renders.width, height=renders.height, codec=params.codec,
            cameras={name: CameraIntrinsics(intrinsics=cam.intrinsics)
                     for name, cam in renders.cameras.items()},
            fit=fit_figures(layout, renders.source_checkpoint), clips=clips,
            skipped=[CameraSkippedClip(camera=name, clip=s.clip, reason=s.reason)
                     for name, cam in renders.cameras.items() for s in cam.skipped])
        record.save(tmp_root / layout.clips_json.name)
    return record


def run(ctx: StageContext[Params]) -> ClipsRecord:
    """The videos' sha256, computed while encoding, go to the runner (``ctx.hashes``), which
    records them in the stage's marker."""
    record = write_clips(ctx.layout, ctx.params, log=ctx.log, progress=ctx.progress)
    ctx.hashes.update(record.video_hashes())
    return record
