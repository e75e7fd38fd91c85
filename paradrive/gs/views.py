"""Views of a fitted checkpoint: load a 3DGS PLY, render it from many cameras in batches (RGB,
alpha and depth with the sky dome left out), and which recorded views a fit holds out.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from paradrive import geometry
from paradrive.actors import views_mask
from paradrive.contracts.records import HeldoutCamera, HeldoutRecord
from paradrive.gs.init import Holdout
from paradrive.gs.ply import load_checkpoint
from paradrive.metrics import frames_quality

if TYPE_CHECKING:
    from paradrive.contracts.layout import SceneLayout
    from paradrive.contracts.records import FitInit, FitRecord

__all__ = ["SkyDome", "sky_dome_of", "render_views", "render_stack", "load_checkpoint",
           "HeldoutViews", "heldout_record", "evenly_spaced", "masked_psnr", "static_quality"]


# --------------------------------------------------------------------------- rendering

@dataclass(frozen=True)
class SkyDome:
    """Where a fit keeps its sky: Gaussians farther than ``radius`` metres from ``centre``."""

    centre: np.ndarray   # (3,) world
    radius: float


def sky_dome_of(scene, init: FitInit | None) -> SkyDome | None:
    """The sky dome of a fit (its record's ``init``), or None when it has none.

    The dome is centred on the mean camera position of the scene; everything beyond half its
    radius counts as sky (street geometry lies within a few hundred metres, the dome at ~1 km).
    """
    if init is None or not init.sky_radius_m or not init.sky_points:
        return None
    centres = np.concatenate([scene.c2w(c)[:, :3, 3] for c in scene.cameras])
    return SkyDome(centre=centres.mean(0), radius=0.5 * init.sky_radius_m)


def render_views(model, c2w: np.ndarray, K: np.ndarray, width: int, height: int, *,
                 frames: Sequence[int] | None = None, depth: bool = False, batch_frames: int = 8,
                 sky: SkyDome | None = None, device: str = "auto",
                 backend: str = "auto") -> Iterator[dict]:
    """Render a checkpoint from cameras ``c2w`` (N, 4, 4) (camera-to-world, OpenCV), all with
    intrinsics ``K`` (3, 3) at ``width x height``.

    model: Gaussian parameters, or a :class:`paradrive.gs.graph.FittedModel`; a scene graph's
    actors are placed at ``frames`` (N,) (scene frame positions, one per camera), and the cameras
    of one frame share a rasterizer pass. A static model renders ``batch_frames`` cameras per pass.

    Yields one dict per pass: ``rgb`` uint8 (B, H, W, 3), ``alpha`` float32 (B, H, W) and, with
    ``depth``, ``depth`` float32 (B, H, W): the expected z-depth in metres of the Gaussians
    outside the ``sky`` dome, +inf where their opacity is below 0.5 (None without ``depth``).
    """
    import torch

    from paradrive.devices import resolve_backend, resolve_device
    from paradrive.gs.graph import FittedModel

    dev = resolve_device(device)
    backend = resolve_backend(backend, dev)
    fitted = (model if isinstance(model, FittedModel) else FittedModel(dict(model))).to(dev)
    c2w = geometry.as_pose(c2w).reshape(-1, 4, 4)
    if fitted.dynamic and (frames is None or len(frames) != len(c2w)):
        raise ValueError("a scene-graph checkpoint renders at frames: pass one frame per camera")
    viewmats = torch.from_numpy(geometry.invert(c2w)).float().to(dev)
    Kt = torch.as_tensor(np.asarray(K), dtype=torch.float32).to(dev)
    centre = None if sky is None else torch.as_tensor(sky.centre, dtype=torch.float32, device=dev)
    placed: tuple | None = None   # (frame, Gaussians, their solid part): a static model's once
    with torch.no_grad():
        for batch in _passes(len(viewmats), frames if fitted.dynamic else None, batch_frames):
            frame = frames[batch.start] if fitted.dynamic and frames is not None else None
            if placed is None or placed[0] != frame:
                p = fitted.at(frame)
                solid = None
                if depth and centre is not None and sky is not None:
                    keep = (p["means"] - centre).norm(dim=1) <= sky.radius
                    solid = {k: v[keep] for k, v in p.items()}
                placed = (frame, p, solid)
            Ks = Kt.expand(batch.stop - batch.start, 3, 3).contiguous()
            yield _render_pass(placed[1], placed[2], viewmats[batch], Ks, int(width), int(height), depth,
                               backend)


def render_stack(model, c2w: np.ndarray, K: np.ndarray, width: int, height: int, *,
                 frames: Sequence[int] | None = None, depth: bool = False, batch_frames: int = 8,
                 sky: SkyDome | None = None, device: str = "auto",
                 backend: str = "auto") -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`render_views` gathered: rgb uint8 (N, H, W, 3) and, with ``depth``, depth (N, H, W)."""
    rgb, dep = [], []
    for r in render_views(model, c2w, K, width, height, frames=frames, depth=depth,
                          batch_frames=batch_frames, sky=sky, device=device, backend=backend):
        rgb.append(r["rgb"])
        if depth:
            dep.append(r["depth"])
    return np.concatenate(rgb), (np.concatenate(dep) if depth else None)


def _passes(n: int, frames: Sequence[int] | None, batch_frames: int) -> Iterator[slice]:
    """Consecutive cameras rendered together: ``batch_frames`` at a time, never two frames of a
    scene graph in one pass."""
    step = max(1, int(batch_frames))
    start = 0
    while start < n:
        stop = min(start + step, n)
        if frames is not None:
            stop = start + 1
            while stop < min(start + step, n) and frames[stop] == frames[start]:
                stop += 1
        yield slice(start, stop)
        start = stop


def _render_pass(p, solid, vm, Ks, width: int, height: int, depth: bool, backend: str) -> dict:
    """One rasterizer pass of Gaussians ``p`` (and, for depth without the sky, ``solid``)."""
    import torch

    from paradrive.gs.model import render_gaussians, sh_degree_of

    deg = sh_degree_of(p)
    one_pass = depth and solid is None
    out, alpha, _ = render_gaussians(p, vm, Ks, width, height, sh_degree=deg,
                                     render_mode="RGB+ED" if one_pass else "RGB", backend=backend)
    rgb = (out[..., :3].clamp(0, 1) * 255.0).round().to(torch.uint8).cpu().numpy()
    z = None
    if one_pass:
        z, z_alpha = out[..., 3], alpha[..., 0]
    elif depth and solid is not None:
        ed, z_alpha, _ = render_gaussians(solid, vm, Ks, width, height, sh_degree=deg,
                                          render_mode="ED", backend=backend)
        z, z_alpha = ed[..., 0], z_alpha[..., 0]
    if z is not None:
        z = torch.where(z_alpha >= 0.5, z, torch.full_like(z, float("inf")))
        z = z.float().cpu().numpy()
    return {"rgb": rgb, "alpha": alpha[..., 0].clamp(0, 1).float().cpu().numpy(), "depth": z}


# --------------------------------------------------------------------------- quality

def masked_psnr(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float | None:
    """PSNR (dB) of uint8 (N, H, W, 3) images on the pixels of ``mask`` (N, H, W): the mean
    squared error over every such pixel of every frame (a frame with a small actor weighs by its
    pixels); None when the mask is empty."""
    if not mask.any():
        return None
    err = ((pred.astype(np.float64) - truth.astype(np.float64)) / 255.0) ** 2
    return float(10.0 * np.log10(1.0 / max(float(err[mask].mean()), 1e-10)))


def static_quality(pred: np.ndarray, truth: np.ndarray, dynamic: np.ndarray) -> dict:
    """``psnr_static``: mean PSNR (dB) over frames of uint8 (N, H, W, 3) images on the pixels
    outside ``dynamic`` (N, H, W) (moving actors' boxes; None when no pixel is left),
    ``psnr_dynamic`` on the pixels inside (:func:`masked_psnr`), and ``dynamic_fraction``, the
    share of pixels inside."""
    err = ((pred.astype(np.float64) - truth.astype(np.float64)) / 255.0) ** 2
    keep = ~dynamic
    values = [10.0 * np.log10(1.0 / max(float(err[i][keep[i]].mean()), 1e-10))
              for i in range(len(err)) if keep[i].any()]
    return {"psnr_static": float(np.mean(values)) if values else None,
            "psnr_dynamic": masked_psnr(pred, truth, dynamic),
            "dynamic_fraction": float(dynamic.mean())}


# --------------------------------------------------------------------------- held-out views

def evenly_spaced(frames: list[int], max_frames: int | None) -> list[int]:
    """At most ``max_frames`` of ``frames``, evenly spaced, first and last kept (None = all)."""
    if not max_frames or len(frames) <= max_frames:
        return list(frames)
    pick = np.linspace(0, len(frames) - 1, int(max_frames)).round().astype(int)
    return [frames[i] for i in sorted(set(pick.tolist()))]


class HeldoutViews:
    """The images a fit held out (:class:`Holdout`) at the fit's resolution, by camera: a held-out
    camera's every frame, and the held-out frames of the cameras the fit trained on
    (``fit_cameras``, None = all). ``max_frames`` evenly spaced of each camera's (None = all)."""

    def __init__(self, scene, holdout: Holdout, fit_cameras: list[str] | None, downscale: float, *,
                 moving: list, street=None, max_frames: int | None = None):
        from paradrive.gs.fit import load_views
        from paradrive.errors import SceneError

        holdout.check(scene)
        self.holdout, self.moving, self.street = holdout, moving, street
        chosen: dict[str, list[int]] = {}
        for fi, frame in enumerate(scene.frames):
            for cam in frame.cameras:
                fitted = cam in holdout.cameras or not fit_cameras or cam in fit_cameras
                if fitted and cam in scene.cameras and holdout.held(fi, cam):
                    chosen.setdefault(cam, []).append(fi)
        if not chosen:
            raise SceneError(f"no image is held out ({holdout.describe()} over "
                             f"{len(scene.frames)} frames)", scene_id=scene.scene_id,
                             fix="fit with fit.holdout_every between 2 and the frame count, or "
                                 "with fit.holdout_cameras naming a camera of the scene")
        keep = {(fi, cam) for cam, fis in chosen.items() for fi in evenly_spaced(fis, max_frames)}
        self.by_camera: dict[str, list] = {}
        for v in load_views(scene, None, downscale, keep=lambda fi, cam: (fi, cam) in keep):
            self.by_camera.setdefault(v.camera, []).append(v)

    def kind(self, cam: str) -> str:
        return "camera" if cam in self.holdout.cameras else "frames"

    def quality(self, model, cam: str, render: dict) -> dict:
        """One camera's held-out images against ``model`` rendered at their poses (``render``:
        more arguments of :func:`render_stack`)."""
        views = self.by_camera[cam]
        c2w = np.stack([v.c2w.numpy() for v in views])
        K = views[0].K.double().numpy()
        w, h = views[0].width, views[0].height
        instants = [v.frame_index for v in views]
        rgb, _ = render_stack(model, c2w, K, w, h, frames=[v.frame for v in views], **render)
        target = np.stack([v.image.numpy() for v in views])
        psnr, ssim = frames_quality(rgb, target)
        row: dict[str, Any] = {"psnr": psnr, "ssim": ssim}
        if self.moving:
            row.update(static_quality(rgb, target, views_mask(self.moving, instants, c2w, K, w, h)))
        if self.street is not None:   # a synthetic scene: the same renders against the truth
            truth = self.street.render(c2w, K, w, h, frames=instants)["rgb"]
            psnr, ssim = frames_quality(rgb, truth)
            row.update(psnr_vs_truth=psnr, ssim_vs_truth=ssim,
                       recorded_psnr_vs_truth=frames_quality(target, truth)[0])
        return row

    def evaluate(self, model, render: dict) -> dict[str, dict]:
        return {cam: self.quality(model, cam, render) for cam in self.by_camera}

    def record(self, rows: dict[str, dict], iteration: int) -> HeldoutRecord:
        """fit.json's ``heldout``: the views-weighted mean over cameras and each camera's row."""
        n = {cam: len(v) for cam, v in self.by_camera.items()}
        total = sum(n.values())
        per_camera = {cam: HeldoutCamera(kind=self.kind(cam), views=n[cam], psnr=r["psnr"],
                                         ssim=r["ssim"], psnr_static=r.get("psnr_static"),
                                         psnr_dynamic=r.get("psnr_dynamic"))
                      for cam, r in rows.items()}
        return HeldoutRecord(every=self.holdout.every, cameras=list(self.holdout.cameras),
                             iteration=iteration, views=total,
                             psnr=sum(rows[c]["psnr"] * n[c] for c in rows) / total,
                             ssim=sum(rows[c]["ssim"] * n[c] for c in rows) / total,
                             per_camera=per_camera)


def heldout_record(layout: SceneLayout, p: Any, fit: FitRecord,
                   moving_threshold_m: float | None) -> HeldoutRecord:
    """The fit's final checkpoint on every image it held out (``p``: the fit's parameters); the
    fit stage records it in fit.json, so a build can sort and filter scenes by it unrendered."""
    from paradrive.actors import moving_actors as moving
    from paradrive.devices import resolve_backend, resolve_device
    from paradrive.gs.graph import load_model
    from paradrive.gs.model import deterministic_torch
    from paradrive.scene import load_scene

    scene = load_scene(layout.root)
    backend = resolve_backend(p.backend, resolve_device(p.device))
    final = p.checkpoints[-1]
    with deterministic_torch(p.threads, backend):
        views = HeldoutViews(scene, Holdout.of(p), p.cameras, p.downscale,
                             moving=moving(scene.actors, moving_threshold_m))
        model = load_model(layout, final, scene, fit)
        rows = views.evaluate(model, {"device": p.device, "backend": p.backend})
    return views.record(rows, final)
