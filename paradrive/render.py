"""The ``render`` stage: the frames the clips need, from the fitted checkpoints.

Per camera of ``render.cameras`` and for the union of the frames its clip windows cover
(:func:`paradrive.clips.clip_windows`), it writes these streams::

    target          the recorded frames, cropped and resized like the renders
    cond@000100 ..  the recorded trajectory rendered at each under-fitted checkpoint
    source+1m ..    the trajectory shifted laterally by each offset, at the source (final) checkpoint

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
the resize (DESIGN.md: fx, cx by sx; fy, cy by sy) and renders use the same ones, so render and
target pixels correspond. Depth of the target stream is not written (a log has no dense depth).

Depth is the expected z-depth of the scene's Gaussians, leaving out the fit's sky dome (Gaussians
farther than half the dome radius from the trajectory centre, ``fit.json``); a pixel whose
remaining opacity is below one half is sky and holds +inf, as the synthetic ground truth does.
Left in, a far dome seen through a half-transparent surface would pull its depth to hundreds of
metres.

The whole ``renders/`` folder is assembled under a temporary name and renamed into place.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from paradrive import geometry
from paradrive.clips import (TARGET_STREAM, clip_windows, condition_stream, frames_needed,
                             source_stream)
from paradrive.errors import SceneError
from paradrive.io import atomic_path, write_json

__all__ = ["OutputCamera", "output_camera", "crop_resize", "SkyDome", "sky_dome_of",
           "render_views", "write_depth_exr",
           "read_depth_exr", "load_checkpoint", "checkpoint_file", "render_scene", "run_stage"]

RENDERS_SCHEMA_VERSION = 1
log_default = logging.getLogger("paradrive.render")


# --------------------------------------------------------------------------- intrinsics

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
    x0, y0, cw, ch = out.crop
    img = image[y0:y0 + ch, x0:x0 + cw]
    if img.shape[:2] == (out.height, out.width):
        return np.ascontiguousarray(img)
    import torch
    import torch.nn.functional as F

    t = torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1)[None].float()
    r = F.interpolate(t, size=(out.height, out.width), mode="bilinear", align_corners=False,
                      antialias=True)
    return r[0].permute(1, 2, 0).round().clamp(0, 255).to(torch.uint8).numpy()


# --------------------------------------------------------------------------- files

def write_depth_exr(path: str | os.PathLike, depth: np.ndarray) -> None:
    """Write float32 depth (H, W) as a single-channel ("Z") ZIP-compressed OpenEXR, atomically."""
    import OpenEXR

    depth = np.ascontiguousarray(depth, dtype=np.float32)
    if depth.ndim != 2:
        raise ValueError(f"depth must be (H, W), got {depth.shape}")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path) as tmp:
        OpenEXR.File(header, {"Z": depth}).write(str(tmp))


def read_depth_exr(path: str | os.PathLike) -> np.ndarray:
    """float32 (H, W) depth from an EXR written by :func:`write_depth_exr` (channel "Z")."""
    import OpenEXR

    with OpenEXR.File(str(path)) as f:
        channels = f.channels()
        if "Z" not in channels:
            raise ValueError(f"{path}: no 'Z' channel (has {', '.join(channels)})")
        return np.array(channels["Z"].pixels, dtype=np.float32)


def _write_png(path: Path, pixels: np.ndarray) -> None:
    from paradrive.scene import write_image

    write_image(path, pixels)


# --------------------------------------------------------------------------- rendering

def checkpoint_file(scene_dir: Path, iteration: int) -> Path:
    return Path(scene_dir) / "gs" / f"ckpt_{int(iteration):06d}.ply"


def load_checkpoint(path: str | os.PathLike, *, scene_id: str | None = None) -> dict:
    """Gaussian parameters of a 3DGS PLY checkpoint (see :mod:`paradrive.gs.ply`)."""
    from paradrive.gs.ply import load_ply

    path = Path(path)
    try:
        return load_ply(path)
    except (OSError, ValueError, KeyError) as exc:
        raise SceneError(f"checkpoint cannot be read: {type(exc).__name__}: {exc}",
                         scene_id=scene_id, path=path, fix="re-run the fit stage") from exc


@dataclass(frozen=True)
class SkyDome:
    """Where a fit keeps its sky: Gaussians farther than ``radius`` metres from ``centre``."""

    centre: np.ndarray   # (3,) world
    radius: float


def sky_dome_of(scene, scene_dir: Path) -> SkyDome | None:
    """The sky dome of a scene's fit (``gs/fit.json`` init), or None when it has none.

    The dome is centred on the mean camera position of the scene; everything beyond half its
    radius counts as sky (street geometry lies within a few hundred metres, the dome at ~1 km).
    """
    import json

    try:
        init = json.loads((Path(scene_dir) / "gs" / "fit.json").read_text()).get("init", {})
    except (FileNotFoundError, ValueError):
        return None
    radius = init.get("sky_radius_m")
    if not radius or not init.get("sky_points"):
        return None
    centres = np.concatenate([scene.c2w(c)[:, :3, 3] for c in scene.cameras])
    return SkyDome(centre=centres.mean(0), radius=0.5 * float(radius))


def render_views(params: dict, c2w: np.ndarray, K: np.ndarray, width: int, height: int, *,
                 depth: bool = False, batch_frames: int = 8, sky: SkyDome | None = None,
                 device: str = "auto", backend: str = "auto") -> Iterator[dict]:
    """Render Gaussians ``params`` from cameras ``c2w`` (N, 4, 4) (camera-to-world, OpenCV),
    ``batch_frames`` cameras per rasterizer call, all with intrinsics ``K`` (3, 3) at
    ``width x height``.

    Yields one dict per batch: ``rgb`` uint8 (B, H, W, 3), ``alpha`` float32 (B, H, W) and, with
    ``depth``, ``depth`` float32 (B, H, W): the expected z-depth in metres of the Gaussians
    outside the ``sky`` dome, +inf where their opacity is below 0.5 (None without ``depth``).
    """
    import torch

    from paradrive.devices import resolve_backend, resolve_device
    from paradrive.gs.model import render, sh_degree_of

    dev = resolve_device(device)
    backend = resolve_backend(backend, dev)
    p = {k: v.to(dev) for k, v in params.items()}
    deg = sh_degree_of(p)
    solid = None
    if depth and sky is not None:
        centre = torch.as_tensor(sky.centre, dtype=torch.float32, device=dev)
        keep = (p["means"] - centre).norm(dim=1) <= sky.radius
        solid = {k: v[keep] for k, v in p.items()}
    c2w = geometry.as_pose(c2w).reshape(-1, 4, 4)
    viewmats = torch.from_numpy(geometry.invert(c2w)).float().to(dev)
    Kt = torch.as_tensor(np.asarray(K), dtype=torch.float32).to(dev)
    step = max(1, int(batch_frames))
    with torch.no_grad():
        for start in range(0, len(viewmats), step):
            vm = viewmats[start:start + step]
            Ks = Kt.expand(len(vm), 3, 3).contiguous()
            one_pass = depth and solid is None
            out, alpha, _ = render(p, vm, Ks, int(width), int(height), sh_degree=deg,
                                   render_mode="RGB+ED" if one_pass else "RGB", backend=backend)
            rgb = (out[..., :3].clamp(0, 1) * 255.0).round().to(torch.uint8).cpu().numpy()
            z = None
            if one_pass:
                z, z_alpha = out[..., 3], alpha[..., 0]
            elif depth:
                ed, z_alpha, _ = render(solid, vm, Ks, int(width), int(height), sh_degree=deg,
                                        render_mode="ED", backend=backend)
                z, z_alpha = ed[..., 0], z_alpha[..., 0]
            if z is not None:
                z = torch.where(z_alpha >= 0.5, z, torch.full_like(z, float("inf")))
                z = z.float().cpu().numpy()
            yield {"rgb": rgb, "alpha": alpha[..., 0].clamp(0, 1).float().cpu().numpy(), "depth": z}


# --------------------------------------------------------------------------- the stage

def _flat(m: np.ndarray) -> list[float]:
    return [float(x) for x in np.asarray(m, dtype=np.float64).reshape(16)]


def _check_params(params: dict, scene_id: str) -> None:
    w, h = params["width"], params["height"]
    if not (isinstance(w, int) and isinstance(h, int) and w > 0 and h > 0):
        raise SceneError(f"render size {w}x{h} is not positive", scene_id=scene_id,
                         fix="set render.width and render.height to positive integers")
    if int(params["clip_frames"]) <= 0:
        raise SceneError(f"render.clip_frames = {params['clip_frames']} is not positive",
                         scene_id=scene_id, fix="set render.clip_frames >= 1")
    offsets = [float(d) for d in params["offsets_m"]]
    if len({source_stream(d) for d in offsets}) != len(offsets):
        raise SceneError(f"render.offsets_m {offsets} repeats an offset", scene_id=scene_id,
                         fix="list each lateral offset once")


def plan_streams(params: dict) -> list[dict]:
    """The streams a camera gets: target, one per condition checkpoint, one per offset."""
    streams = [{"name": TARGET_STREAM, "kind": "target", "iteration": None, "offset_m": None}]
    for it in params["condition_checkpoints"]:
        streams.append({"name": condition_stream(it), "kind": "condition",
                        "iteration": int(it), "offset_m": None})
    for d in params["offsets_m"]:
        streams.append({"name": source_stream(d), "kind": "source",
                        "iteration": int(params["source_checkpoint"]), "offset_m": float(d)})
    return streams


def render_scene(scene_dir: str | os.PathLike, params: dict, *,
                 log: logging.Logger | None = None, progress=None) -> dict:
    """Render every stream of ``scene_dir`` with the resolved ``render`` stage ``params``.

    Writes ``renders/`` (module docstring) and returns a small summary.
    """
    from paradrive.scene import load_scene

    log = log or log_default
    scene_dir = Path(scene_dir)
    scene = load_scene(scene_dir)
    sid = scene.scene_id
    _check_params(params, sid)
    width, height = int(params["width"]), int(params["height"])
    want_depth, want_alpha = bool(params["depth"]), bool(params["alpha"])
    batch = int(params["batch_frames"])
    device, backend = str(params["device"]), str(params["backend"])
    streams = plan_streams(params)
    sky = sky_dome_of(scene, scene_dir) if want_depth else None
    iterations = sorted({s["iteration"] for s in streams if s["iteration"] is not None})
    for it in iterations:
        if not checkpoint_file(scene_dir, it).is_file():
            raise SceneError(f"checkpoint for iteration {it} is missing", scene_id=sid,
                             path=checkpoint_file(scene_dir, it),
                             fix=f"add {it} to fit.checkpoints (render.condition_checkpoints and "
                                 f"render.source_checkpoint must be fitted) and re-run fit")
    cams = list(params["cameras"])
    unknown = [c for c in cams if c not in scene.cameras]
    if unknown:
        raise SceneError(f"render.cameras names {', '.join(unknown)}, which the scene does not "
                         f"have (it has {', '.join(scene.cameras)})", scene_id=sid,
                         path=scene_dir / "scene.json",
                         fix="ingest those cameras (ingest.cameras) or drop them from render.cameras")

    # Plan first: which frames each camera needs, so progress has a total.
    plans = {}
    for cam_name in cams:
        try:
            windows, skipped = clip_windows(len(scene.frames), int(params["clip_frames"]),
                                            params["clips"])
        except ValueError as exc:
            raise SceneError(str(exc), scene_id=sid, fix="fix render.clips") from exc
        for s in skipped:
            log.warning("render: %s camera %s clip %s skipped: %s", sid, cam_name, s["clip"],
                        s["reason"])
        cam = scene.cameras[cam_name]
        out = output_camera(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, width, height)
        plans[cam_name] = (windows, skipped, frames_needed(windows), out)
    total = sum(len(p[2]) * len(streams) for p in plans.values())
    done = 0

    doc_cams = {}
    cache: dict[int, dict] = {}
    with atomic_path(scene_dir / "renders") as tmp_root:
        tmp_root.mkdir(parents=True)
        for cam_name, (windows, skipped, frames, out) in plans.items():
            recorded = scene.c2w(cam_name)[frames] if frames else np.zeros((0, 4, 4))
            ego = scene.ego2world()[frames] if frames else np.zeros((0, 4, 4))
            cam_doc = {"intrinsics": out.intrinsics,
                       "stored_size": [scene.cameras[cam_name].width, scene.cameras[cam_name].height],
                       "crop": list(out.crop),
                       "windows": [{"clip": w.name, "frame_start": w.start, "num_frames": w.num_frames}
                                   for w in windows],
                       "skipped": skipped, "frames": frames,
                       "c2w": [_flat(m) for m in recorded], "streams": {}}
            for stream in streams if frames else []:
                name = stream["name"]
                folder = tmp_root / cam_name / name
                folder.mkdir(parents=True)
                if stream["kind"] == "source":
                    c2w = geometry.lateral_shift(recorded, ego, stream["offset_m"])
                else:
                    c2w = recorded
                if stream["kind"] == "target":
                    for pos in frames:
                        image = scene.load_image(pos, cam_name)
                        _write_png(folder / f"{pos:06d}.png", crop_resize(image, out))
                        done += 1
                        if progress:
                            progress(done, total)
                else:
                    it = stream["iteration"]
                    if it not in cache:
                        cache.clear()  # one checkpoint in memory at a time
                        cache[it] = load_checkpoint(checkpoint_file(scene_dir, it), scene_id=sid)
                    k = 0
                    for result in render_views(cache[it], c2w, out.K, width, height,
                                               depth=want_depth, batch_frames=batch, sky=sky,
                                               device=device, backend=backend):
                        for j in range(len(result["rgb"])):
                            pos = frames[k]
                            _write_png(folder / f"{pos:06d}.png", result["rgb"][j])
                            if want_depth:
                                write_depth_exr(folder / "depth" / f"{pos:06d}.exr",
                                                result["depth"][j])
                            if want_alpha:
                                a8 = (result["alpha"][j] * 255.0).round().astype(np.uint8)
                                _write_png(folder / "alpha" / f"{pos:06d}.png", a8[..., None])
                            k += 1
                            done += 1
                        if progress:
                            progress(done, total)
                entry = {"kind": stream["kind"], "dir": f"{cam_name}/{name}",
                         "c2w": [_flat(m) for m in c2w]}
                if stream["iteration"] is not None:
                    entry["iteration"] = stream["iteration"]
                if stream["offset_m"] is not None:
                    entry["offset_m"] = stream["offset_m"]
                cam_doc["streams"][name] = entry
            doc_cams[cam_name] = cam_doc
            log.info("render: %s camera %s: %d frames x %d streams, %d clips skipped", sid,
                     cam_name, len(frames), len(streams) if frames else 0, len(skipped))
        doc = {"schema_version": RENDERS_SCHEMA_VERSION, "scene_id": sid,
               "width": width, "height": height, "frame_naming": "position in scene.json frames",
               "condition_checkpoints": [int(i) for i in params["condition_checkpoints"]],
               "source_checkpoint": int(params["source_checkpoint"]),
               "offsets_m": [float(d) for d in params["offsets_m"]],
               "clip_frames": int(params["clip_frames"]), "depth": want_depth, "alpha": want_alpha,
               "depth_units": "metres, z-depth along the camera axis; +inf = sky",
               "sky_dome": None if sky is None else {"centre": [float(x) for x in sky.centre],
                                                     "radius_m": sky.radius},
               "cameras": doc_cams}
        write_json(tmp_root / "renders.json", doc)
    return {"cameras": len(doc_cams),
            "frames": sum(len(c["frames"]) for c in doc_cams.values()),
            "streams": sum(len(c["streams"]) for c in doc_cams.values()),
            "skipped_clips": sum(len(c["skipped"]) for c in doc_cams.values())}


def run_stage(ctx) -> dict:
    """Stage entry (``stages/render.yaml``)."""
    from paradrive.gs.model import deterministic_torch

    with deterministic_torch(int(ctx.params["threads"])):
        return render_scene(ctx.scene_dir, ctx.params, log=getattr(ctx, "log", None),
                            progress=getattr(ctx, "progress", None))
