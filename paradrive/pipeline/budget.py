"""A disk and compute budget: what scenes hold now (footprint) and what a build will cost (plan).

``scene_footprint`` sums a scene folder's bytes by its top folders (``images``, ``lidar``,
``masks``, ``gs``, ``renders``, ``clips``; the rest is ``other``); ``paradrive build`` prints it
per scene at the end (:mod:`paradrive.commands.build`).

``plan_build`` projects, before anything runs, a scene list's pairs, media bytes (the clips),
intermediate bytes (everything else, at their peak and after the retention switches) and the
hours of each stage. It counts each stage's work in units (stored megapixels for ingest,
iterations for the fit, rendered and encoded megapixels for render and clip) and multiplies by
rates: measured on the finished scenes of the data root (the seconds in each stage's marker,
the bytes of its recorded outputs) when there are any, else the documented defaults of
``stages/budget/rates.yaml``. A scene already ingested gives its own frames and cameras; one
not yet ingested is read from its URI (synthetic) or takes the dataset's typical log
(``rates.yaml``: ``logs``). ``paradrive plan`` prints the plan (:mod:`paradrive.commands.plan`).
"""

from __future__ import annotations

import contextlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from paradrive.errors import ConfigError
from paradrive.io import is_temporary
from paradrive.pipeline.runner import read_marker
from paradrive.contracts.specs import ResolvedConfig
from paradrive.contracts.layout import SCENE_FOLDERS, SCENES_DIR, SceneLayout
from paradrive.storage import DataRoot
from paradrive.streams import (ClipWindow, clip_shortfall, clip_windows, frames_needed,
                               path_shortfall, plan_streams, source_clip_windows)
from paradrive.uri import parse_uri

OTHER = "other"
MB = 1e6
STAGE_OWNS = {stage: [f for f, owner in SCENE_FOLDERS.items() if owner == stage]
              for stage in dict.fromkeys(SCENE_FOLDERS.values())}


# --------------------------------------------------------------------------- footprint

def scene_footprint(root: DataRoot | str | Path, scene_id: str) -> dict[str, int]:
    """Bytes of one scene folder by top folder (:data:`SCENE_FOLDERS`, then ``other``); a URL
    data root is listed remotely."""
    root = DataRoot.of(root)
    mirror = root.mirror(scene_id)
    if mirror is not None:
        sizes = {rel: int(info.get("size") or 0) for rel, info in mirror.refresh().items()}
    else:
        sizes = folder_sizes(SceneLayout.of(root.local, scene_id).root)
    return by_folder(sizes)


def folder_sizes(folder: Path) -> dict[str, int]:
    """Files under ``folder`` (temporaries left out): relative path -> bytes. ``os.scandir``
    rather than a walk building a Path per file: a build prints every scene's footprint, and
    that walk was a third of a no-op re-run."""
    out: dict[str, int] = {}
    todo = [("", os.fspath(folder))] if folder.is_dir() else []
    while todo:
        prefix, path = todo.pop()
        with os.scandir(path) as entries:
            for entry in entries:
                if is_temporary(entry.name):
                    continue
                rel = prefix + entry.name
                if entry.is_dir():  # a link to a folder is not walked (as os.walk)
                    if not entry.is_symlink():
                        todo.append((rel + "/", entry.path))
                else:
                    with contextlib.suppress(FileNotFoundError):  # removed while listing
                        out[rel] = entry.stat().st_size
    return out


def by_folder(sizes: dict[str, int]) -> dict[str, int]:
    """Relative path -> bytes, summed by top folder."""
    out = {name: 0 for name in [*SCENE_FOLDERS, OTHER]}
    for rel, size in sizes.items():
        top = rel.split("/", 1)[0] if "/" in rel else OTHER
        out[top if top in SCENE_FOLDERS else OTHER] += size
    return out


# --------------------------------------------------------------------------- the plan

@dataclass
class Shape:
    """What a scene's costs scale with: its frames and its cameras' stored sizes."""

    frames: int
    cameras: dict[str, tuple[int, int]]
    known: str        # "ingested", "uri" or "typical <dataset> log"
    gaussians: float | None = None   # of every checkpoint, when a fit with these parameters ran
    sfm_frames: int = 0   # frames whose poses structure from motion finds (a video's)
    sfm_work: float = 0.0   # their cost in frames of the SfM rate's reference size (sfm_work())
    sfm_seconds: float = 0.0   # what SfM took, for an ingested video
    # a longitudinal build's cameras' recorded paths (N, 4, 4): where its sources stay on them
    paths: dict[str, np.ndarray] = field(default_factory=dict)


@dataclass
class Rate:
    value: float       # seconds (compute) or bytes (storage) per unit
    unit: str
    source: str
    device: str = ""   # compute: where the seconds were spent (cpu or gpu)


@dataclass
class Plan:
    scenes: int = 0
    pairs: int = 0
    bytes: dict[str, float] = field(default_factory=dict)      # by top folder
    kept: dict[str, float] = field(default_factory=dict)       # after the retention switches
    seconds: dict[str, float] = field(default_factory=dict)    # by stage
    rates: dict[str, Rate] = field(default_factory=dict)       # "compute:<stage>", "bytes:<folder>"
    shapes: dict[str, int] = field(default_factory=dict)       # how the scenes' shapes were known
    unfit: dict[str, str] = field(default_factory=dict)        # scene id -> why it can give no clip

    def hours(self, device: str) -> float:
        return sum(s for stage, s in self.seconds.items()
                   if self.rates[f"compute:{stage}"].device == device) / 3600.0

    def as_json(self) -> dict[str, Any]:
        media = self.bytes.get("clips", 0.0)
        outputs = media + self.bytes.get("latents", 0.0)   # the build's: the clips and the latent cache
        return {"scenes": self.scenes, "pairs": self.pairs, "media_bytes": round(media),
                "latent_bytes": round(self.bytes.get("latents", 0.0)),
                "intermediate_bytes": round(sum(self.bytes.values()) - outputs),
                "intermediate_bytes_kept": round(sum(self.kept.values()) - outputs),
                "bytes": {k: round(v) for k, v in self.bytes.items()},
                "bytes_kept": {k: round(v) for k, v in self.kept.items()},
                "seconds": {k: round(v, 1) for k, v in self.seconds.items()},
                "cpu_hours": round(self.hours("cpu"), 3), "gpu_hours": round(self.hours("gpu"), 3),
                "rates": {k: vars(r) for k, r in self.rates.items()}, "shapes": self.shapes,
                "unfit": self.unfit}


def load_rates(config: ResolvedConfig) -> dict[str, Any]:
    path = Path(config.stages_dir) / "budget" / "rates.yaml"
    try:
        return yaml.safe_load(path.read_text())
    except FileNotFoundError as exc:
        raise ConfigError(f"{path} is missing: the plan's default rates live there") from exc


def units(params: dict[str, dict], shape: Shape) -> dict[str, float]:
    """Work per stage and size per folder of one scene with these stage parameters."""
    ingest, fit, render = params["ingest"], params["fit"], params["render"]
    stored_mp = shape.frames * sum(w * h for w, h in shape.cameras.values()) / MB
    offsets = render["longitudinal_offsets_m"] if render.get("transform") == "longitudinal" \
        else render["offsets_m"]
    streams = len(plan_streams(render["condition_checkpoints"], render["source_checkpoint"], offsets))
    out_mp = render["width"] * render["height"] / MB
    cams = [c for c in render["cameras"] if c in shape.cameras] or list(render["cameras"])
    by_cam = camera_windows(render, shape, cams)
    windows = sum(len(w) for w in by_cam.values())
    checkpoints = sorted(fit["checkpoints"])
    rendered_mp = sum(len(frames_needed(w)) for w in by_cam.values()) * streams * out_mp
    encoded_mp = windows * streams * render["clip_frames"] * out_mp
    return {
        "compute:ingest": stored_mp, "compute:fit": float(checkpoints[-1]),
        "compute:render": rendered_mp, "compute:clip": encoded_mp,
        "compute:sfm": shape.sfm_work,
        "bytes:images": stored_mp, "bytes:masks": stored_mp,
        "bytes:lidar": float(shape.frames) if ingest["lidar"] else 0.0,
        # before a fit, an upper bound: under-fitted checkpoints near the initial points, the last at the cap
        "bytes:gs": shape.gaussians if shape.gaussians is not None
        else float(fit["init_points"] * (len(checkpoints) - 1) + fit["max_gaussians"]),
        "bytes:renders": rendered_mp, "bytes:clips": encoded_mp,
        "pairs": float(windows * len(offsets) * len(render["condition_checkpoints"])),
        **encode_units(params.get("encode"), render, windows * streams),
    }


def camera_windows(render: dict, shape: Shape, cams: list[str]) -> dict[str, list[ClipWindow]]:
    """Each camera's clip windows: over the whole scene, or in a longitudinal build whose paths
    are known, over the frames where every source stays on the camera's path (as render lays
    them); a log not yet ingested is counted as if they all did."""
    if render.get("transform") == "longitudinal" and shape.paths:
        return {c: source_clip_windows(shape.paths[c], render["clip_frames"], render["clips"],
                                       render["longitudinal_offsets_m"], "longitudinal")[0]
                for c in cams if c in shape.paths}
    windows, _ = clip_windows(shape.frames, render["clip_frames"], render["clips"])
    return {c: windows for c in cams}


def encode_units(encode: dict | None, render: dict, videos: int) -> dict[str, float]:
    """The encode stage's work (megapixel-frames through the VAE) and latent bytes (exact: 16 x T'
    x H/8 x W/8 values in encode.dtype) for ``videos`` clip videos, each encoded once (a latent
    shard stores a distinct video once); nothing while the stage is off (encode.vae null)."""
    if not encode or encode.get("vae") is None:
        return {"compute:encode": 0.0, "bytes:latents": 0.0}
    frames = encode["num_frames"] or 1 + (render["clip_frames"] - 1) // 4 * 4
    height, width = encode["size"] or (render["height"], render["width"])
    values = 16 * (1 + (frames - 1) // 4) * (height // 8) * (width // 8)
    item = {"bfloat16": 2, "float16": 2, "float32": 4}[encode["dtype"]]
    return {"compute:encode": videos * frames * height * width / MB, "bytes:latents": float(videos * values * item)}


def sfm_work(frames: int, pixels: float, model: dict) -> float:
    """Structure from motion's work on ``frames`` frames of ``pixels`` pixels, in frames of the
    rate's reference size: each counts ``(pixels / reference_pixels) ** exponent``, the power law
    through SfM's seconds measured at two sizes (``rates.yaml``: ``compute.sfm``)."""
    return frames * (pixels / model["reference_pixels"]) ** model["exponent"] if frames else 0.0


def focal_work(frames: int, pixels: float, model: dict) -> float:
    """The focal search of a video nobody calibrated, on ``frames`` frames of ``pixels`` pixels,
    in SfM frames of the reference size (``rates.yaml``: ``compute.sfm.focal_search_frames`` a
    frame searched)."""
    return model["focal_search_frames"] * sfm_work(frames, pixels, model)


def road_motion_work(pixels: float, model: dict) -> float:
    """The road's motion of one video (the scale's cue, a fixed number of frame pairs whatever
    the clip's length) on frames of ``pixels`` pixels, in SfM frames of the reference size
    (``rates.yaml``: ``compute.sfm.road_motion_frames``)."""
    return sfm_work(model["road_motion_frames"], pixels, model)


def shape_of(config: ResolvedConfig, uri: str, data_dir: Path | None, rates_doc: dict) -> Shape:
    """The scene's frames and cameras: from its scene.json when ingested, else its URI (a video
    from its file's header where it can be read)."""
    parsed = parse_uri(uri)
    logs, sfm_model = rates_doc["logs"], rates_doc["compute"]["sfm"]
    if data_dir is not None:
        layout = SceneLayout.of(data_dir, parsed.scene_id)
        if layout.scene_json.is_file():
            shape = _ingested_shape(layout, config.params["fit"], sfm_model)
            if _longitudinal(config):
                from paradrive.scene import load_scene

                scene = load_scene(layout.root)
                shape.paths = {c: scene.c2w(c) for c in scene.cameras}
            return shape
    params = config.typed("ingest")
    if parsed.kind == "synthetic":
        from paradrive.ingest.synthetic import street_from_uri

        street = street_from_uri(parsed, params)
        frames = min(street.frames, params.max_frames or street.frames)
        paths = {c: street.c2w(c)[:frames] for c in street.cameras} if _longitudinal(config) else {}
        return Shape(frames, {c: (street.width, street.height) for c in street.cameras}, "uri",
                     paths=paths)
    if parsed.kind == "video":
        return _video_shape(parsed, params, logs["video"], sfm_model)
    typical = logs[parsed.kind]
    names = (params.camera_sets.get(parsed.kind) or typical["cameras"]) if params.cameras == "auto" \
        else params.cameras or typical["cameras"]
    frames = min(typical["frames"], params.max_frames or typical["frames"])
    return Shape(frames, {c: (typical["width"], typical["height"]) for c in names},
                 f"typical {parsed.kind} log")


def _video_shape(parsed, params, typical: dict, sfm_model: dict) -> Shape:
    """A video not yet ingested: its frames and size from its header (a typical dashcam's where
    the file is not there to read); SfM runs on them downscaled to ``ingest.video_sfm_width``."""
    from paradrive.ingest.video import needs_focal_search, planned_frames, sfm_size

    found = planned_frames(parsed, params)
    frames, width, height = found or (min(typical["frames"], params.max_frames or typical["frames"]),
                                      typical["width"], typical["height"])
    w, h = sfm_size(width, height, params.video_sfm_width)
    searched = min(frames, params.video_focal_frames) if needs_focal_search(parsed) else 0
    return Shape(frames, {name: (width, height) for name in typical["cameras"]},
                 "video header" if found else "typical video log", sfm_frames=frames,
                 sfm_work=sfm_work(frames, w * h, sfm_model) + focal_work(searched, w * h, sfm_model)
                 + road_motion_work(w * h, sfm_model))


def _longitudinal(config: ResolvedConfig) -> bool:
    return config.params["render"].get("transform") == "longitudinal"


def _ingested_shape(layout: SceneLayout, fit_params: dict | None, sfm_model: dict) -> Shape:
    """An ingested scene's shape; its Gaussians too when its fit ran with ``fit_params`` (None:
    whatever it ran with)."""
    from paradrive.contracts.records import FitRecord

    doc = json.loads(layout.scene_json.read_text())
    cams = {name: (int(c["width"]), int(c["height"])) for name, c in doc["cameras"].items()}
    shape = Shape(len(doc["frames"]), cams, "ingested")
    video = doc.get("video")
    if doc.get("dataset") == "video" and video:  # SfM saw every sampled frame, at its own size
        size = video.get("sfm") or {}
        pixels = size.get("width", 0) * size.get("height", 0) or sum(w * h for w, h in cams.values())
        shape.sfm_frames = int(video.get("sampled", len(doc["frames"])))
        searched = int(((video.get("intrinsics") or {}).get("focal_search") or {}).get("frames", 0))
        # its seconds hold the focal search's too (sfm.focal_seconds), and the road's motion's
        # are beside them: so does its work
        motion = ((video.get("scale") or {}).get("road_motion") or {}).get("seconds")
        shape.sfm_work = (sfm_work(shape.sfm_frames, pixels, sfm_model) + focal_work(searched, pixels, sfm_model)
                          + (road_motion_work(pixels, sfm_model) if motion is not None else 0.0))
        shape.sfm_seconds = float(size.get("seconds", video.get("sfm_seconds", 0.0))) + float(motion or 0.0)
    marker = read_marker(layout.root, "fit")
    if marker and layout.fit_json.is_file() and fit_params in (None, marker.params):
        shape.gaussians = float(sum(c.num_gaussians for c in FitRecord.load(layout.fit_json).checkpoints))
    return shape


def default_rates(rates_doc: dict) -> dict[str, Rate]:
    out = {f"compute:{stage}": Rate(r["seconds"], r["unit"], r["source"], r["device"])
           for stage, r in rates_doc["compute"].items()}
    out.update({f"bytes:{folder}": Rate(r["bytes"], r["unit"], r["source"])
                for folder, r in rates_doc["bytes"].items()})
    return out


def measured_rates(data_dir: Path, defaults: dict[str, Rate], config: ResolvedConfig,
                   sfm_model: dict) -> dict[str, Rate]:
    """The defaults, replaced where the finished scenes of ``data_dir`` measure a rate: each stage
    marker's seconds, and the bytes of its outputs (those let go included), over the work its
    recorded parameters make. Where scenes ran a stage on different devices, the device most of
    them used gives the rate."""
    totals: dict[tuple[str, str], list[float]] = {}   # (rate, device) -> [amount, work, scenes]
    folder = Path(data_dir) / SCENES_DIR
    for scene_dir in sorted(folder.iterdir()) if folder.is_dir() else []:
        for key, device, amount, work in _samples(scene_dir, config, sfm_model):
            total = totals.setdefault((key, device), [0.0, 0.0, 0])
            total[0] += amount
            total[1] += work
            total[2] += 1
    out = dict(defaults)
    for key, default in defaults.items():
        groups = [(device, t) for (k, device), t in totals.items() if k == key and t[1] > 0]
        if groups:
            device, (amount, work, scenes) = max(groups, key=lambda g: g[1][2])
            out[key] = Rate(amount / work, default.unit, f"measured on {int(scenes)} scene(s)", device)
    return out


def _samples(scene_dir: Path, config: ResolvedConfig,
             sfm_model: dict) -> list[tuple[str, str, float, float]]:
    """(rate, device, seconds or bytes, work) of each stage one scene finished, and of a video's
    structure from motion (its seconds in scene.json)."""
    from paradrive.contracts.records import FitRecord

    markers = {s: read_marker(scene_dir, s) for s in STAGE_OWNS}
    layout = SceneLayout(scene_dir)
    if markers["ingest"] is None or not layout.scene_json.is_file():
        return []
    params = {s: {**config.params[s], **((m.params if m else None) or {})} for s, m in markers.items()}
    shape = _ingested_shape(layout, None, sfm_model)
    u = units(params, shape)
    fitted = layout.fit_json.is_file() and FitRecord.load(layout.fit_json).device.startswith("cuda")
    gpu = "gpu" if fitted else "cpu"
    specs = config.registry().specs
    out = []
    for stage, marker in markers.items():
        if marker is None or marker.outputs is None:
            continue
        device = gpu if specs[stage].resources.gpu > 0 else "cpu"
        out.append((f"compute:{stage}", device, float(marker.seconds or 0.0), u[f"compute:{stage}"]))
        files = {**marker.outputs, **(marker.dropped.files if marker.dropped else {})}
        sizes = by_folder({rel: info.bytes for rel, info in files.items()})
        out += [(f"bytes:{name}", "", float(sizes[name]), u[f"bytes:{name}"])
                for name in STAGE_OWNS[stage] if sizes[name] and u[f"bytes:{name}"]]
    if shape.sfm_work and shape.sfm_seconds and markers["ingest"].outputs is not None:
        out.append(("compute:sfm", "cpu", shape.sfm_seconds, shape.sfm_work))
    return out


def plan_build(config: ResolvedConfig, uris: list[str], data_dir: Path | None) -> Plan:
    """Project the pairs, bytes and hours of building ``uris`` with ``config``."""
    rates_doc = load_rates(config)
    rates = default_rates(rates_doc)
    if data_dir is not None:
        rates = measured_rates(Path(data_dir), rates, config, rates_doc["compute"]["sfm"])
    plan = Plan(rates=rates)
    released = {name for stage, spec in config.registry().specs.items()
                for glob in spec.released(config.params[stage]) for name in [glob.split("/", 1)[0]]}
    for uri in dict.fromkeys(uris):
        shape = shape_of(config, uri, data_dir, rates_doc)
        plan.shapes[shape.known] = plan.shapes.get(shape.known, 0) + 1
        u = units(config.params, shape)
        plan.scenes += 1
        short = clip_shortfall(shape.frames, list(shape.cameras), config.params["render"]["cameras"],
                               config.params["render"]["clip_frames"])
        reason = short and f"{short.what}; {short.fix}"
        render = config.params["render"]
        if reason is None and shape.paths:  # as render's admit: sources kept on the path
            short = path_shortfall({c: shape.paths[c] for c in render["cameras"] if c in shape.paths},
                                   render["clip_frames"], render["clips"],
                                   render["longitudinal_offsets_m"])
            reason = short and f"{short.what}; {short.fix}"
        if reason is not None:
            # the build fails such a scene right after its ingest: only the ingest is spent
            plan.unfit[parse_uri(uri).scene_id] = reason
            u = {k: v if k in ("compute:ingest", "compute:sfm", "bytes:images", "bytes:masks", "bytes:lidar") else 0.0
                 for k, v in u.items()}
        plan.pairs += int(u["pairs"])
        for key, rate in rates.items():
            kind, name = key.split(":", 1)
            value = u[key] * rate.value
            target = plan.seconds if kind == "compute" else plan.bytes
            target[name] = target.get(name, 0.0) + value
            if kind == "bytes":
                plan.kept[name] = plan.kept.get(name, 0.0) + (0.0 if name in released else value)
    return plan
