"""Ground-truth evaluation of a fitted synthetic scene (``paradrive eval`` prints it,
:mod:`paradrive.commands.eval`).

Only a synthetic scene knows what a laterally shifted camera really sees: the procedural street
renders any pose exactly. For one scene this measures

* **shifted**: the source (final) checkpoint rendered on the recorded trajectory shifted by each
  offset, against the street's true view from the same shifted poses (PSNR, SSIM, and the median
  relative error of the rendered z-depth on non-sky pixels), ``psnr_static`` on the pixels
  outside the moving actors' boxes (``dynamic_fraction`` of them inside: a static fit's ghosts)
  and ``psnr_dynamic`` on the pixels inside (the actors of a scene-graph fit, placed by their
  tracks; the same moments of the truth);
* **recorded**: the source checkpoint on the recorded trajectory against the recorded frames
  (offset 0, the fit's own quality on the clip frames);
* **conditions**: each under-fitted checkpoint on the recorded trajectory against the recorded
  frames, as the condition streams are made;
* **poses** (a video exported from a street, ``paradrive export video``): the SfM path's scale
  error and, with only the first camera placed on the street's, its largest position and
  rotation errors. Its shifted and recorded views are compared with the street's from the true
  camera of each frame (see ``_truth_from_scene``);
* **heldout** (any dataset, when the fit held views out, ``fit.holdout_every`` /
  ``fit.holdout_cameras``): each checkpoint rendered at the poses of the images the fit never saw,
  at the fit's resolution, against those images (PSNR, SSIM, and ``psnr_static`` /
  ``psnr_dynamic`` where moving actors exist); on a synthetic scene beside the same renders
  against the street's truth. A real log has no truth for a shifted view: held-out frames and
  held-out cameras are what it can check.

Frames and intrinsics are those of the render stage (its clip windows, output size and crop),
read from ``renders/renders.json`` when the scene was rendered, else computed the same way from
the render parameters; ``max_frames`` evenly spaced frames of them are used. Renders are made
afresh from the checkpoints with the render stage's own functions (identical to its PNGs).

A real log (Waymo, nuScenes, DriveStudio) gets the held-out part only. Writes ``eval/eval.json``
and ``eval/eval.png`` (or into ``out_dir``).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from paradrive.actors import views_mask
from paradrive.streams import (condition_stream, frames_needed, source_clip_windows, source_poses,
                               source_stream)
from paradrive.errors import SceneError
from paradrive.io import atomic_path, write_json
from paradrive.contracts.layout import SceneLayout
from paradrive.contracts.records import FitRecord, RendersRecord
from paradrive.streams import OutputCamera, output_camera

__all__ = ["evaluate_scene", "image_quality", "depth_abs_rel", "depth_signed_rel", "depth_errors",
           "plot_eval"]

EVAL_SCHEMA_VERSION = 1
if TYPE_CHECKING:  # the gs modules (torch) are imported where eval runs, not by the CLI's start-up
    from paradrive.contracts.params import FitParams
    from paradrive.gs.init import Holdout
    from paradrive.gs.views import HeldoutViews
    from paradrive.stages.render import Params as RenderParams

log_default = logging.getLogger("paradrive.eval")


# --------------------------------------------------------------------------- metrics

def image_quality(pred: np.ndarray, truth: np.ndarray) -> dict:
    """Mean PSNR (dB) and SSIM over frames of uint8 (N, H, W, 3) arrays (paradrive.metrics)."""
    from paradrive.metrics import frames_quality

    value, structure = frames_quality(pred, truth)
    return {"psnr": value, "ssim": structure}


def _relative_depth_error(pred: np.ndarray, truth: np.ndarray) -> np.ndarray | None:
    """(pred - truth) / truth on the pixels whose truth is finite (not sky); None when none is."""
    valid = np.isfinite(truth) & (truth > 0)
    if not valid.any():
        return None
    # a surface rendered as sky (+inf) counts as an infinite error, not as a missing pixel
    return (pred[valid] - truth[valid]) / truth[valid]


def depth_abs_rel(pred: np.ndarray, truth: np.ndarray) -> float | None:
    """Median of |pred - truth| / truth over pixels where the truth is finite (not sky).

    A predicted +inf (sky) on such a pixel is an infinite error.

    pred, truth: float (N, H, W) z-depth in metres. None when no pixel has a finite truth.
    """
    rel = _relative_depth_error(pred, truth)
    return None if rel is None else float(np.median(np.abs(rel)))


def depth_signed_rel(pred: np.ndarray, truth: np.ndarray) -> float | None:
    """Median of (pred - truth) / truth over pixels where the truth is finite (not sky).

    Negative: the geometry sits in front of the true surfaces (too near); positive: behind.
    pred, truth: float (N, H, W) z-depth in metres. None when no pixel has a finite truth.
    """
    rel = _relative_depth_error(pred, truth)
    return None if rel is None else float(np.median(rel))


def depth_errors(pred: np.ndarray, truth: np.ndarray) -> dict:
    """``depth_abs_rel`` and ``depth_signed_rel`` of one stream, as eval.json stores them."""
    return {"depth_abs_rel": depth_abs_rel(pred, truth),
            "depth_signed_rel": depth_signed_rel(pred, truth)}


# --------------------------------------------------------------------------- evaluation

def moving_actors(scene, ingested: dict) -> list:
    """The scene's actors that count as moving with the ingest's ``moving_threshold_m``."""
    from paradrive.actors import moving_actors as moving

    return moving(scene.actors, ingested.get("moving_threshold_m"))


def _plan_camera(scene, cam_name: str, render_params: RenderParams,
                 renders: RendersRecord | None) -> tuple[list[int], OutputCamera]:
    """(frames, OutputCamera) for a camera: from renders.json when present, else from params."""
    cam = scene.cameras[cam_name]
    rc = renders.cameras.get(cam_name) if renders else None
    if renders and rc and rc.frames:
        fx, fy, cx, cy = rc.intrinsics
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        x0, y0, cw, ch = rc.crop
        out = OutputCamera(width=renders.width, height=renders.height, crop=(x0, y0, cw, ch), K=K)
        return list(rc.frames), out
    windows, _ = source_clip_windows(scene.c2w(cam_name), render_params.clip_frames, render_params.clips,
                                     render_params.source_offsets, render_params.transform)
    frames = frames_needed(windows) or list(range(len(scene.frames)))
    out = output_camera(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy,
                        render_params.width, render_params.height)
    return frames, out


def _render(model, c2w, frames, K, width: int, height: int, *, depth: bool, batch: int, device: str,
            sky=None, backend: str = "auto"):
    from paradrive.gs.views import render_stack

    return render_stack(model, c2w, K, width, height, frames=frames, depth=depth,
                        batch_frames=batch, sky=sky, device=device, backend=backend)


def evaluate_scene(scene_dir: str | os.PathLike, render_params: RenderParams, *,
                   ingest_params: dict | None = None, cameras: list[str] | None = None,
                   max_frames: int | None = 16, out_dir: str | os.PathLike | None = None,
                   log: logging.Logger | None = None, fit_params: FitParams | None = None) -> dict:
    """Evaluate a fitted scene; returns eval.json's dict.

    render_params: the resolved ``render`` stage parameters (checkpoints, offsets, size, clips).
    ingest_params: used to rebuild the street when the scene has no ingest marker.
    cameras: default ``render_params.cameras``. Writes ``<out_dir or scene/eval>/eval.json``
    and ``eval.png``. Renders use the render stage's thread count, as its PNGs do.
    fit_params: the fit's parameters (resolution, cameras and, when fit.json records none, what
    was held out); with views held out, ``heldout`` measures them on any dataset. A real log
    without held-out views is an error: nothing else of it has a truth.
    """
    from paradrive.devices import resolve_backend, resolve_device
    from paradrive.gs.model import deterministic_torch

    backend = resolve_backend("auto", resolve_device(render_params.device))  # as _render draws
    with deterministic_torch(render_params.threads, backend):
        return _evaluate_scene(scene_dir, render_params, ingest_params=ingest_params,
                               cameras=cameras, max_frames=max_frames, out_dir=out_dir, log=log,
                               fit_params=fit_params)


class _EvalContext:
    """What evaluating one camera of a scene needs: the scene, its street, the fit, the params."""

    def __init__(self, scene, layout: SceneLayout, street, moving: list, render_params: RenderParams,
                 renders: RendersRecord | None, fit: FitRecord | None, log: logging.Logger):
        from paradrive.gs.views import sky_dome_of

        self.scene, self.layout, self.street, self.moving = scene, layout, street, moving
        self.anchors, self.instants = _truth_from_scene(scene, street)
        self.p, self.renders, self.fit, self.log = render_params, renders, fit, log
        self.sky = sky_dome_of(scene, fit.init if fit else None)

    def render(self, model, c2w, frames, out, depth: bool):
        return _render(model, c2w, frames, out.K, out.width, out.height, depth=depth,
                       batch=self.p.batch_frames, device=self.p.device,
                       sky=self.sky if depth else None)

    def model(self, iteration: int):
        from paradrive.gs.graph import load_model

        return load_model(self.layout, iteration, self.scene, self.fit)

    def camera(self, cam_name: str, max_frames: int | None) -> dict[str, Any]:
        from paradrive.gs.views import evenly_spaced
        from paradrive.streams import crop_resize

        scene, sid, p = self.scene, self.scene.scene_id, self.p
        frames, out = _plan_camera(scene, cam_name, p, self.renders)
        frames = evenly_spaced(frames, max_frames)
        recorded = scene.c2w(cam_name)[frames]
        target = np.stack([crop_resize(scene.load_image(f, cam_name), out) for f in frames])
        conditions = []
        for it in p.condition_checkpoints:
            rgb, _ = self.render(self.model(it), recorded, frames, out, depth=False)
            q = image_quality(rgb, target)
            conditions.append({"iteration": it, "stream": condition_stream(it), **q})
            self.log.info("eval: %s %s cond@%d: PSNR %.2f SSIM %.3f", sid, cam_name, it,
                          q["psnr"], q["ssim"])
        final = self.model(p.source_checkpoint)
        instants = [self.instants[f] for f in frames]  # actors move: truth at those frames
        rgb, dep = self.render(final, recorded, frames, out, depth=True)
        truth = self.street.render(self.to_street(recorded, frames), out.K, out.width, out.height,
                                   frames=instants)
        recorded_doc = {"iteration": p.source_checkpoint, **image_quality(rgb, target),
                        "psnr_vs_truth": image_quality(rgb, truth["rgb"])["psnr"],
                        **self.truth_quality(rgb, dep, truth, instants, recorded, out)}
        shifted_rows = [self.shifted(final, float(d), frames, out, cam_name) for d in p.source_offsets]
        return {"intrinsics": out.intrinsics, "frames": frames, "conditions": conditions,
                "shifted": shifted_rows, "recorded": recorded_doc,
                "shifted_by_abs_offset": _by_abs_offset(shifted_rows)}

    def to_street(self, c2w: np.ndarray, frames: list[int]) -> np.ndarray:
        """Poses of the scene at ``frames`` in the street's world."""
        return np.einsum("fij,fjk->fik", self.anchors[frames], c2w)

    def truth_quality(self, rgb, dep, truth: dict, instants: list[int], c2w, out) -> dict:
        from paradrive.gs.views import static_quality

        dynamic = views_mask(self.moving, instants, c2w, out.K, out.width, out.height)
        return {**static_quality(rgb, truth["rgb"], dynamic), **depth_errors(dep, truth["depth"])}

    def shifted(self, final, d: float, frames: list[int], out, cam_name: str) -> dict:
        poses, on_path = source_poses(self.scene.c2w(cam_name), self.scene.ego2world(), d, self.p.transform)
        # renders.json of another transform may hold frames a longitudinal source runs off
        frames = [f for f in frames if on_path[f]]
        if not frames:
            raise SceneError(f"camera {cam_name}: the {self.p.transform} source {d:+g} m runs off the "
                             f"recorded path on every frame evaluated", scene_id=self.scene.scene_id,
                             path=self.layout.renders_json, fix="evaluate with smaller offsets")
        shifted = poses[frames]
        name = source_stream(d, self.p.transform)
        instants = [self.instants[f] for f in frames]
        rgb, dep = self.render(final, shifted, frames, out, depth=True)
        truth = self.street.render(self.to_street(shifted, frames), out.K, out.width, out.height,
                                   frames=instants)
        q = image_quality(rgb, truth["rgb"])
        self.log.info("eval: %s %s %s: PSNR %.2f SSIM %.3f", self.scene.scene_id, cam_name,
                      name, q["psnr"], q["ssim"])
        return {"offset_m": d, "stream": name, "transform": self.p.transform,
                "iteration": self.p.source_checkpoint,
                **q, **self.truth_quality(rgb, dep, truth, instants, shifted, out)}


def _by_abs_offset(rows: list[dict]) -> dict[str, dict]:
    by_abs: dict[str, list[dict]] = {}
    for row in rows:
        by_abs.setdefault(f"{abs(row['offset_m']):g}", []).append(row)
    return {k: {"psnr": float(np.mean([r["psnr"] for r in v])),
                "ssim": float(np.mean([r["ssim"] for r in v]))}
            for k, v in sorted(by_abs.items(), key=lambda kv: float(kv[0]))}


# --------------------------------------------------------------------------- held-out views

def _holdout_of(fit: FitRecord | None, fit_params: FitParams | None) -> Holdout:
    """What the fit held out: its fit.json's record, else the fit parameters eval runs with."""
    from paradrive.gs.init import Holdout

    if fit is not None and fit.heldout is not None:
        return Holdout(every=fit.heldout.every, cameras=tuple(fit.heldout.cameras))
    return Holdout.of(fit_params) if fit_params is not None else Holdout()


def _check_fit_held_out(scene, fit: FitRecord | None, holdout: Holdout, path) -> None:
    """Refuse to call views held out that the fit trained on: without a fit.json record of the
    holdout, the count of views it trained on must be what the holdout leaves."""
    if fit is None or fit.heldout is not None:
        return
    trained = sum(1 for fi, frame in enumerate(scene.frames) for cam in frame.cameras
                  if cam in fit.cameras and holdout.trained(fi, cam))
    if trained != fit.n_views:
        raise SceneError(f"the fit trained on {fit.n_views} views, and holding out "
                         f"{holdout.describe()} leaves {trained}: it did not hold these views out",
                         scene_id=scene.scene_id, path=path,
                         fix="evaluate with the fit's own fit.holdout_every / holdout_cameras, "
                             "or fit again with them")


def _heldout_doc(ctx: _EvalContext, views: HeldoutViews, iterations: list[int]) -> dict:
    """eval.json's ``heldout``: what was held out, the final checkpoint's mean over the held-out
    views and, in ``per_camera``, each camera's held-out frames and every checkpoint on them."""
    p, sid = ctx.p, ctx.scene.scene_id
    render = {"batch_frames": p.batch_frames, "device": p.device}
    per_it = {it: views.evaluate(ctx.model(it), render) for it in iterations}
    cams = {}
    for cam, vs in views.by_camera.items():
        rows = [{"iteration": it, **per_it[it][cam]} for it in iterations]
        for r in rows:
            ctx.log.info("eval: %s %s heldout %s@%d: PSNR %.2f SSIM %.3f", sid, cam, views.kind(cam),
                         r["iteration"], r["psnr"], r["ssim"])
        cams[cam] = {"kind": views.kind(cam), "frames": [v.frame for v in vs], "checkpoints": rows}
    last = per_it[iterations[-1]]
    final = views.record(last, iterations[-1]).model_dump()
    final.pop("per_camera")
    if views.street is not None:
        n = {cam: len(vs) for cam, vs in views.by_camera.items()}
        final["psnr_vs_truth"] = sum(last[c]["psnr_vs_truth"] * n[c] for c in n) / sum(n.values())
    return {**final, "per_camera": cams}


def _check_checkpoints(layout: SceneLayout, fit: FitRecord | None, iterations: list[int], sid: str) -> None:
    for it in iterations:
        if not layout.checkpoint(it).is_file():
            have = [c.iteration for c in fit.checkpoints] if fit is not None else []
            raise SceneError(f"checkpoint for iteration {it} is missing", scene_id=sid,
                             path=layout.checkpoint(it),
                             fix=(f"this scene's fit has checkpoints {have}: evaluate with the "
                                  f"profile it was built with (--profile NAME; make eval "
                                  f"PROFILE=NAME), or run the fit stage with this profile first"
                                  if have else "run the fit stage with the same profile first"))


def _truth_uri(scene) -> str | None:
    """The synthetic street a scene shows: its own URI, or for a video exported from one
    (``paradrive export video``) the ``truth=`` its URI names; None for a real log."""
    if scene.dataset == "synthetic":
        return scene.source
    return scene.extra.get("video", {}).get("truth") if scene.dataset == "video" else None


def _truth_from_scene(scene, street) -> tuple[np.ndarray, list[int]]:
    """Per scene frame, street-world-from-scene-world (F, 4, 4) and the street's frame.

    The identity and the same frame for a synthetic scene. A video's world is its own, found by
    SfM: each frame's transform puts that frame's recorded camera on the street's camera of the
    same moment, so a shifted view is compared with the street's view from the same offset
    beside the true camera. The scale and the up axis count in the figures (the offset is taken
    in the video's metres, along its road plane); drift along the path does not, as the fit saw
    the images where SfM placed them: ``video_pose_errors`` measures it.
    """
    n = len(scene.frames)
    if street is None or scene.dataset == "synthetic":
        return np.repeat(np.eye(4)[None], n, axis=0), [f.index for f in scene.frames]
    source = [int(i) for i in scene.extra["video"]["source_frames"]]
    recorded = scene.c2w("front")
    return np.einsum("fij,fjk->fik", street.c2w("front")[source], np.linalg.inv(recorded)), source


def video_pose_errors(scene, street) -> dict:
    """A video scene's poses against the street's: the path's scale error, and with the first
    camera placed on the street's first camera (no other alignment), the largest position error
    (metres and share of the path) and rotation error (degrees)."""
    from paradrive.ingest.sfm import path_length

    source = [int(i) for i in scene.extra["video"]["source_frames"]]
    truth = street.c2w("front")[source]
    est = scene.c2w("front")
    placed = np.einsum("ij,fjk->fik", truth[0] @ np.linalg.inv(est[0]), est)
    path = path_length(truth)
    position = np.linalg.norm(placed[:, :3, 3] - truth[:, :3, 3], axis=1).max()
    cos = (np.einsum("fij,fij->f", placed[:, :3, :3], truth[:, :3, :3]) - 1.0) / 2.0
    return {"path_m": path, "scale_error": path_length(est) / path - 1.0,
            "position_error_m": float(position), "position_error_of_path": float(position / path),
            "rotation_error_deg": float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))).max())}


def _evaluate_scene(scene_dir, render_params: RenderParams, *, ingest_params, cameras, max_frames,
                    out_dir, log, fit_params: FitParams | None = None) -> dict:
    from paradrive.inference import scene_ingest_params
    from paradrive.ingest.synthetic import street_from_uri
    from paradrive.scene import load_scene
    from paradrive.contracts.params import params_of
    from paradrive.uri import parse_uri

    log = log or log_default
    scene_dir = Path(scene_dir)
    layout = SceneLayout(scene_dir)
    scene = load_scene(scene_dir)
    sid = scene.scene_id
    truth_uri = _truth_uri(scene)
    synthetic = truth_uri is not None
    fit = FitRecord.load(layout.fit_json, sid) if layout.fit_json.is_file() else None
    holdout = _holdout_of(fit, fit_params)
    if not synthetic and not holdout.active:
        raise SceneError(f"eval of a {scene.dataset} scene measures its held-out views, and this "
                         f"fit held none out: only a synthetic street has true shifted views",
                         scene_id=sid, path=layout.fit_json,
                         fix="fit with fit.holdout_every=N (every Nth frame) or "
                             "fit.holdout_cameras=[CAMERA], or evaluate a 'synthetic:' scene")
    ingested = scene_ingest_params(scene_dir, ingest_params)
    street = street_from_uri(parse_uri(truth_uri), params_of(ingested, ingest_params)) if truth_uri else None
    moving = moving_actors(scene, ingested)
    renders = RendersRecord.load(layout.renders_json, sid) if layout.renders_json.is_file() else None
    conds = render_params.condition_checkpoints
    final = render_params.source_checkpoint
    _check_checkpoints(layout, fit, conds + [final], sid)
    cams = list(cameras or render_params.cameras) if synthetic else []
    for c in cams:
        if c not in scene.cameras or street is None or c not in street.cameras:
            raise SceneError(f"camera {c} is not in the scene", scene_id=sid,
                             path=layout.scene_json, fix="choose a camera the scene has")

    ctx = _EvalContext(scene, layout, street, moving, render_params, renders, fit, log)
    doc_cams = {cam_name: ctx.camera(cam_name, max_frames) for cam_name in cams}
    heldout = None
    if holdout.active:
        from paradrive.gs.views import HeldoutViews

        _check_fit_held_out(scene, fit, holdout, layout.fit_json)
        views = HeldoutViews(scene, holdout, fit_params.cameras if fit_params else None,
                             fit_params.downscale if fit_params else 1.0, moving=moving,
                             street=street if scene.dataset == "synthetic" else None,
                             max_frames=max_frames)
        heldout = _heldout_doc(ctx, views, conds + [final])

    doc = {"schema_version": EVAL_SCHEMA_VERSION, "scene_id": sid, "source": scene.source,
           "dataset": scene.dataset, "width": render_params.width, "height": render_params.height,
           "condition_checkpoints": conds, "source_checkpoint": final,
           "metrics": {"psnr": "dB, mean over frames", "ssim": "11x11 Gaussian window",
                       "depth_abs_rel": "median |d - d_true| / d_true on non-sky pixels",
                       "depth_signed_rel": "median (d - d_true) / d_true on non-sky pixels "
                                           "(< 0: too near)",
                       "heldout": "images the fit never saw, at their own poses and the fit's "
                                  "resolution; psnr_vs_truth: the same renders against the "
                                  "synthetic street's truth"},
           "cameras": doc_cams, **({"heldout": heldout} if heldout is not None else {})}
    if scene.dataset == "video" and street is not None:
        doc["poses"] = video_pose_errors(scene, street)
    folder = Path(out_dir) if out_dir is not None else scene_dir / "eval"
    folder.mkdir(parents=True, exist_ok=True)
    plot_eval(doc, folder / "eval.png")
    write_json(folder / "eval.json", doc)
    return doc


def plot_eval(doc: dict, path: str | os.PathLike) -> None:
    """PSNR / SSIM against lateral offset (left) and against the condition iteration (right)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4))
    for cam, c in doc["cameras"].items():
        rows = sorted(c["shifted"] + [{"offset_m": 0.0, "psnr": c["recorded"]["psnr_vs_truth"]}],
                      key=lambda r: r["offset_m"])
        ax1.plot([r["offset_m"] for r in rows], [r["psnr"] for r in rows], "o-", label=cam)
        conds = c["conditions"]
        ax2.plot([r["iteration"] for r in conds], [r["psnr"] for r in conds], "s-", label=cam)
    ax1.set_xlabel("lateral offset (m, left > 0)")
    ax1.set_ylabel("PSNR vs true view (dB)")
    ax1.set_title(f"shifted renders @ {doc['source_checkpoint']}")
    ax2.set_xscale("log")
    ax2.set_xticks(doc["condition_checkpoints"], [str(i) for i in doc["condition_checkpoints"]])
    ax2.minorticks_off()
    ax2.set_xlabel("checkpoint iteration")
    ax2.set_ylabel("PSNR vs recorded frames (dB)")
    ax2.set_title("condition renders")
    for cam, c in doc.get("heldout", {}).get("per_camera", {}).items():
        rows = c["checkpoints"]
        ax2.plot([r["iteration"] for r in rows], [r["psnr"] for r in rows], "^--",
                 label=f"{cam} held out")
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend()
    fig.suptitle(doc["scene_id"])
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    plt.close(fig)
