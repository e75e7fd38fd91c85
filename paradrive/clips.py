"""Clips: where the front / middle / rear windows fall, stream names, and the ``clip`` stage.

A clip is ``clip_frames`` consecutive frames of one camera (DESIGN.md, "Clips"). For a scene of
N >= F frames: front = [0, F), middle = [floor((N - F) / 2), + F), rear = [N - F, N). A shorter
scene has no clips; the reason is recorded and the other cameras and scenes go on.

The ``clip`` stage reads ``renders/renders.json`` (written by :mod:`paradrive.render`) and writes,
per camera and clip window::

    clips/<camera>/<clip>/<stream>.mp4            (H.264; .mkv for the lossless ffv1 codec)
    clips/<camera>/<clip>/depth/<stream>/<frame:06d>.exr   (with clip.depth)
    clips/clips.json                               (the index the manifest reads)

The whole ``clips/`` folder is assembled under a temporary name, ``clips.json`` last, and
renamed into place in one step: a reader never sees a half-written clip set.
"""

from __future__ import annotations

import json
import math
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from paradrive.errors import SceneError

__all__ = ["CLIP_NAMES", "ClipWindow", "clip_windows", "frames_needed", "format_offset",
           "condition_stream", "source_stream", "TARGET_STREAM", "run_stage", "write_clips"]

CLIP_NAMES = ("front", "middle", "rear")
TARGET_STREAM = "target"
CLIPS_SCHEMA_VERSION = 1


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


def frames_needed(windows: Iterable[ClipWindow]) -> list[int]:
    """Sorted union of the frame positions the windows cover (each frame once)."""
    return sorted({i for w in windows for i in w.frames})


def format_offset(offset_m: float) -> str:
    """``+1m``, ``-2m``, ``+0.5m``: the sign always, integers without decimals."""
    d = float(offset_m)
    if not math.isfinite(d):
        raise ValueError(f"offset must be finite, got {offset_m}")
    text = f"{d:+.0f}" if d == round(d) else f"{d:+g}"
    if text in ("+0", "-0"):
        text = "+0"
    return f"{text}m"


def condition_stream(iteration: int) -> str:
    """``cond@000100``: the recorded trajectory rendered at an under-fitted checkpoint."""
    return f"cond@{int(iteration):06d}"


def source_stream(offset_m: float) -> str:
    """``source+1m``: the recorded trajectory shifted ``offset_m`` (left > 0) at the final checkpoint."""
    return f"source{format_offset(offset_m)}"


# --------------------------------------------------------------------------- the clip stage

def _read_json(path: Path, scene_id: str, fix: str) -> dict:
    if not path.is_file():
        raise SceneError(f"{path.name} is missing", scene_id=scene_id, path=path, fix=fix)
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise SceneError(f"{path.name} is not valid JSON ({exc})", scene_id=scene_id, path=path,
                         fix=fix) from exc


def _fit_figures(scene_dir: Path, iteration: int | None) -> dict:
    """Training-view PSNR / SSIM of the fit at ``iteration`` (else its last checkpoint)."""
    path = scene_dir / "gs" / "fit.json"
    try:
        doc = json.loads(path.read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return {"iteration": iteration, "train_psnr": None, "train_ssim": None}
    entries = [e for e in doc.get("checkpoints", []) if isinstance(e, dict) and "iteration" in e]
    if not entries:
        return {"iteration": iteration, "train_psnr": None, "train_ssim": None}
    match = [e for e in entries if e["iteration"] == iteration]
    entry = match[0] if match else max(entries, key=lambda e: e["iteration"])
    return {"iteration": int(entry["iteration"]), "train_psnr": entry.get("psnr"),
            "train_ssim": entry.get("ssim")}


def _quality(cond: np.ndarray, target: np.ndarray) -> dict:
    """Mean PSNR (dB) and SSIM over frames of uint8 (F, H, W, 3) arrays."""
    import torch

    from paradrive.metrics import psnr, ssim

    a = torch.from_numpy(cond).float() / 255.0
    b = torch.from_numpy(target).float() / 255.0
    return {"psnr": round(float(psnr(a, b).mean()), 4), "ssim": round(float(ssim(a, b).mean()), 5)}


def write_clips(scene_dir: Path, params: dict, *, log=None, progress=None) -> dict:
    """Encode every stream of every clip window listed in ``renders/renders.json``.

    Returns a small summary; writes ``clips/`` as described in the module docstring.
    """
    from paradrive.io import atomic_path, write_json
    from paradrive.scene import load_scene, read_image
    from paradrive.video import container_suffix, encode_video

    scene_dir = Path(scene_dir)
    scene = load_scene(scene_dir, check_files=False)
    sid = scene.scene_id
    renders_json = scene_dir / "renders" / "renders.json"
    renders = _read_json(renders_json, sid, "run the render stage for this scene first")
    codec = str(params["codec"])
    suffix = container_suffix(codec)
    width, height = int(renders["width"]), int(renders["height"])
    pix_fmt = params.get("pix_fmt") if codec == "libx264" else None
    if codec == "libx264" and str(pix_fmt).startswith("yuv420") and (width % 2 or height % 2):
        raise SceneError(f"renders are {width}x{height}; H.264 {pix_fmt} needs even sizes",
                         scene_id=sid, path=renders_json,
                         fix="set render.width / render.height to even numbers or use clip.codec=ffv1")
    want_depth = bool(params.get("depth"))
    if want_depth and not renders.get("depth"):
        raise SceneError("clip.depth is set but the renders have no depth", scene_id=sid,
                         path=renders_json, fix="set render.depth=true and re-run render")
    timestamps = scene.timestamps_us()
    frame_index = [f.index for f in scene.frames]
    jobs = [(cam_name, cam, w) for cam_name, cam in renders["cameras"].items()
            for w in cam["windows"]]
    total = sum(len(cam["streams"]) for _, cam, _ in jobs)
    done = 0
    doc_clips, skipped, cameras = [], [], {}
    for cam_name, cam in renders["cameras"].items():
        cameras[cam_name] = {"intrinsics": [float(x) for x in cam["intrinsics"]]}
        skipped.extend({"camera": cam_name, **s} for s in cam.get("skipped", []))

    with atomic_path(scene_dir / "clips") as tmp_root:
        tmp_root.mkdir(parents=True)
        for cam_name, cam, window in jobs:
            start, count, clip = int(window["frame_start"]), int(window["num_frames"]), window["clip"]
            positions = list(range(start, start + count))
            frame_rows = {int(p): r for r, p in enumerate(cam["frames"])}
            missing = [p for p in positions if p not in frame_rows]
            if missing:
                raise SceneError(f"renders of camera {cam_name} lack frames {missing[:5]} of clip "
                                 f"{clip}", scene_id=sid, path=renders_json,
                                 fix="re-run the render stage with the same clip parameters")
            rows = [frame_rows[p] for p in positions]
            rel_dir = Path("clips") / cam_name / clip
            streams, quality = {}, {}
            target = None   # kept to score the conditions; one other stream in memory at a time
            # the target first, so each condition is scored as soon as it is read
            for name, stream in sorted(cam["streams"].items(), key=lambda kv: kv[1]["kind"] != "target"):
                folder = scene_dir / "renders" / stream["dir"]
                frames = np.stack([read_image(folder / f"{p:06d}.png", scene_id=sid)
                                   for p in positions])
                if frames.shape[1:3] != (height, width):
                    raise SceneError(f"render {folder} is {frames.shape[2]}x{frames.shape[1]}, "
                                     f"renders.json says {width}x{height}", scene_id=sid,
                                     path=folder, fix="re-run the render stage")
                if stream["kind"] == "target":
                    target = frames
                elif stream["kind"] == "condition" and target is not None:
                    quality[name] = _quality(frames, target)
                rel = rel_dir / f"{name}{suffix}"
                info = encode_video(tmp_root.parent / _under(tmp_root, rel), frames,
                                    scene.fps, codec=codec, crf=int(params["crf"]),
                                    preset=str(params["preset"]), pix_fmt=pix_fmt,
                                    gop=params["gop"])
                entry = {"file": rel.as_posix(), "bytes": info["bytes"], "sha256": info["sha256"],
                         "kind": stream["kind"]}
                if stream.get("iteration") is not None:
                    entry["iteration"] = int(stream["iteration"])
                if stream["kind"] == "source":
                    entry["offset_m"] = float(stream["offset_m"])
                    entry["c2w"] = [stream["c2w"][r] for r in rows]
                if want_depth:
                    depth_dir = tmp_root / cam_name / clip / "depth" / name
                    depth_dir.mkdir(parents=True, exist_ok=True)
                    for p in positions:
                        src = folder / "depth" / f"{p:06d}.exr"
                        if not src.is_file() and stream["kind"] != "target":
                            raise SceneError("depth render is missing", scene_id=sid, path=src,
                                             fix="re-run the render stage with render.depth=true")
                        if src.is_file():
                            shutil.copyfile(src, depth_dir / src.name)
                    if any(depth_dir.iterdir()):
                        entry["depth_dir"] = (rel_dir / "depth" / name).as_posix()
                    else:
                        depth_dir.rmdir()
                streams[name] = entry
                done += 1
                if progress:
                    progress(done, total)
            recorded = cam["c2w"]
            doc_clips.append({
                "camera": cam_name, "clip": clip, "frame_start": start, "num_frames": count,
                "frame_indices": [int(frame_index[p]) for p in positions],
                "timestamps_us": [int(timestamps[p]) for p in positions],
                "c2w": [recorded[r] for r in rows],
                "streams": streams, "quality": quality})
            if log:
                log.info("clip: %s %s/%s: %d streams x %d frames", sid, cam_name, clip,
                         len(streams), count)
        doc = {"schema_version": CLIPS_SCHEMA_VERSION, "scene_id": sid, "dataset": scene.dataset,
               "source": scene.source, "fps": float(scene.fps), "width": width, "height": height,
               "codec": codec, "cameras": cameras,
               "fit": _fit_figures(scene_dir, renders.get("source_checkpoint")),
               "clips": doc_clips, "skipped": skipped}
        write_json(tmp_root / "clips.json", doc)
    return {"clips": len(doc_clips), "streams": sum(len(c["streams"]) for c in doc_clips),
            "skipped": len(skipped), "codec": codec}


def _under(tmp_root: Path, rel: Path) -> Path:
    """``clips/<cam>/<clip>/x`` re-rooted under the temporary clips folder (relative to its parent)."""
    return Path(tmp_root.name, *rel.parts[1:])


def run_stage(ctx) -> dict:
    """Stage entry (``stages/clip.yaml``). The videos' sha256, computed while encoding, go to the
    runner (``ctx.hashes``), which records them in the stage's marker."""
    summary = write_clips(ctx.scene_dir, ctx.params, log=getattr(ctx, "log", None),
                          progress=getattr(ctx, "progress", None))
    hashes = getattr(ctx, "hashes", None)
    if hashes is not None:
        doc = json.loads((Path(ctx.scene_dir) / "clips" / "clips.json").read_text())
        hashes.update({e["file"]: e["sha256"] for c in doc["clips"] for e in c["streams"].values()})
    return summary
