"""Fitting a 3D Gaussian Splatting model of one scene (the fit stage's work, :mod:`paradrive.stages.fit`).

Outputs under ``<scene>/gs/``:

* ``ckpt_{iteration:06d}.ply`` at exactly the configured iterations (standard 3DGS PLY),
* the fit's :class:`FitRecord` (which the fit stage writes as ``fit.json``, handed over through
  ``on_record`` at every checkpoint): per checkpoint the training-view PSNR / SSIM (a fixed,
  evenly spaced subset of the training views, ``eval_views``), the number of Gaussians, seconds
  of fitting and peak RSS,
* ``state.pt`` while the fit runs: parameters, Adam moments, densification state, RNG states and
  the step, written atomically every ``state_interval`` iterations and at every checkpoint.
  A fit killed at any moment and started again resumes from it and writes byte-identical PLY
  files on CPU. It is removed when the fit completes unless ``keep_state`` is set.

Everything is written to a temporary name and renamed into place.

Loss: (1 - lambda) L1 + lambda D-SSIM (3DGS). The sky is a dome of Gaussians far outside the
scene (see :func:`paradrive.gs.init.sky_dome`), excluded from densification; where a scene has
sky masks, sky pixels whose rendered depth is nearer than half the dome radius are penalised,
which removes floaters in front of the sky. Geometry terms (:mod:`paradrive.gs.losses`): L1
between the rendered expected depth and the frame's LiDAR where the scene has it
(``depth_weight``), a flattening term on each Gaussian's smallest axis (``flatten_weight``) and
a sharp-shape term on its axis ratio (``shape_ratio_weight``). Pixels of moving actors without
a node of their own, and a video scene's ego mask (the hood) and moving masks (``masks/ego``,
``masks/motion``) are left out of every term: the photometric ones and the depth term.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import random
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any
from collections.abc import Callable, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from paradrive.actors import Actor, dynamic_mask, moving_actors
from paradrive.devices import resolve_backend, resolve_device
from paradrive.errors import SceneError
from paradrive.io import atomic_path, load_tensors, remove_stale_temporaries, stop_point
from paradrive.metrics import peak_rss_mb, psnr, ssim
from paradrive.contracts.layout import SceneLayout, actor_files
from paradrive.contracts.records import FitRecord

from . import init as gsinit
from ._fit_loss import FitLossTerms, fit_loss, fit_loss_kernels, fit_loss_torch
from .graph import (BACKGROUND, FittedModel, NodeRows, actor_points_init, boxes_containing,
                    node_poses, place, save_model)
from .init import Holdout, View
from .losses import DepthTarget, flatten_loss, lidar_depth_target, shape_ratio_loss
from .model import (PARAM_KEYS, Gaussians, Params, cat_params, deterministic_torch, new_params, render_gaussians,
                    scene_scale_of, sh_degree_of)
from .ply import load_ply
from .strategy import DensifyStrategy

if TYPE_CHECKING:
    from paradrive.contracts.params import FitParams

__all__ = ["fit_scene", "render_checkpoint", "load_ply", "load_views"]

STATE_VERSION = 2  # 2: RNG states as tensors and plain lists, loaded without pickle
log_default = logging.getLogger("paradrive.gs.fit")


# --------------------------------------------------------------------------- parameters

HOLDOUT_KEYS = ("holdout_every", "holdout_cameras")


def _fingerprint(p: dict[str, Any]) -> str:
    # a holdout left at its default (nothing held out) keeps the fingerprints of earlier fits
    keep = {k: p[k] for k in sorted(p) if k not in ("keep_state", "state_interval", "eval_views")
            and not (k in HOLDOUT_KEYS and not p[k])}
    return hashlib.sha256(json.dumps(keep, sort_keys=True, default=str).encode()).hexdigest()[:16]


# --------------------------------------------------------------------------- data

def _resize(x: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """(H, W, C) float -> (h, w, C) by area averaging."""
    if x.shape[0] == h and x.shape[1] == w:
        return x
    y = F.interpolate(x.permute(2, 0, 1)[None], size=(h, w), mode="area")
    return y[0].permute(1, 2, 0)


def load_views(scene, cameras: Sequence[str] | None, downscale: float,
               keep: Callable[[int, str], bool] | None = None) -> list[View]:
    """All (frame, camera) images of ``scene`` at 1/``downscale`` resolution, frame-major order;
    with ``keep(frame position, camera)``, only those it accepts (the others are not read)."""
    names = list(scene.cameras) if not cameras else list(cameras)
    unknown = [c for c in names if c not in scene.cameras]
    if unknown:
        raise SceneError(f"fit: cameras {unknown} are not in the scene (has {list(scene.cameras)})",
                         scene_id=scene.scene_id, fix="fix the 'cameras' parameter of the fit stage")
    views = []
    for fi, frame in enumerate(scene.frames):
        for name in names:
            if name not in frame.cameras or (keep is not None and not keep(fi, name)):
                continue
            cam = scene.cameras[name]
            w = max(1, int(round(cam.width / downscale)))
            h = max(1, int(round(cam.height / downscale)))
            img = scene.load_image(fi, name)
            if img.shape[:2] != (cam.height, cam.width):
                raise SceneError(f"image is {img.shape[1]}x{img.shape[0]}, scene.json says "
                                 f"{cam.width}x{cam.height}", scene_id=scene.scene_id,
                                 path=scene.image_path(fi, name), fix="re-run ingest")
            t = _resize(torch.from_numpy(img).float(), h, w).round().clamp(0, 255).to(torch.uint8)
            sky = scene.sky_mask(fi, name)
            if sky is not None:
                sky = _resize(torch.from_numpy(sky).float()[..., None], h, w)[..., 0] > 0.5
            K = torch.tensor(cam.K(), dtype=torch.float64)
            K[0] *= w / cam.width
            K[1] *= h / cam.height
            c2w = torch.tensor(np.asarray(frame.cameras[name].c2w), dtype=torch.float64)
            views.append(View(image=t.contiguous(), sky=sky, K=K.float(), c2w=c2w, camera=name,
                              frame=fi, ground_z=float(np.asarray(frame.ego2world)[2, 3]),
                              frame_index=frame.index))
    if not views:
        raise SceneError("fit: the scene has no images for the chosen cameras",
                         scene_id=scene.scene_id, fix="check scene.json frames / 'cameras'"
                         + (" / 'holdout_every' / 'holdout_cameras'" if keep is not None else ""))
    return views


# --------------------------------------------------------------------------- model building

@dataclass
class Graph:
    """The fit's actors: ``nodes`` get Gaussians of their own (in box frames); ``carved`` (the
    nodes and the moving actors whose pixels the loss leaves out) are cut from the background."""

    nodes: list[Actor] = field(default_factory=list)
    carved: list[Actor] = field(default_factory=list)

    @classmethod
    def of(cls, scene, p: FitParams, moving_threshold_m: float | None) -> Graph:
        moving = [] if p.dynamic == "off" else moving_actors(scene.actors, moving_threshold_m)
        return cls(nodes=[a for a in moving if a.rigid or p.nonrigid == "rigid"], carved=moving)

    @property
    def masked(self) -> list[Actor]:
        return [a for a in self.carved if a not in self.nodes]


def _lidar_split(scene, graph: Graph) -> tuple[np.ndarray | None, list[np.ndarray]]:
    """The scene's LiDAR without the moving actors' returns, and each node's returns (box frame)."""
    if not graph.carved:
        return scene.lidar_points(), [np.zeros((0, 3))] * len(graph.nodes)
    background: list[np.ndarray] = []
    local: list[list[np.ndarray]] = [[] for _ in graph.nodes]
    for fi, frame in enumerate(scene.frames):
        pts = scene.lidar_frame(fi)
        if pts is None:
            continue
        inside, parts = boxes_containing(pts.astype(np.float64), graph.carved, frame.index)
        background.append(pts[~inside])
        for k, actor in enumerate(graph.nodes):
            local[k].append(parts[graph.carved.index(actor)])
    if not background:
        return None, [np.zeros((0, 3))] * len(graph.nodes)
    return (np.concatenate(background),
            [np.concatenate(x) if x else np.zeros((0, 3)) for x in local])


def _frustum_init(views: list[View], n_points: int, scene, graph: Graph, p: FitParams,
                  gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """``n_points`` rays of the image-based init, less those inside a moving actor's swept box."""
    means, rgb = gsinit.frustum_points_init(views, n_points=n_points, depth_min=p.init_depth_min,
                                            depth_max=p.init_depth_max,
                                            depth_candidates=p.init_depth_candidates,
                                            ground_margin=p.init_ground_margin, generator=gen)
    keep = _outside_swept_boxes(means, scene, graph)
    return means[keep], rgb[keep]


def _outside_swept_boxes(means: torch.Tensor, scene, graph: Graph) -> torch.Tensor:
    """(N,) bool: points in no moving actor's box at any frame (a LiDAR-free init cannot tell
    which frame a point came from, so the whole swept volume is left to the actors)."""
    keep = np.ones(len(means), dtype=bool)
    pts = means.double().numpy()
    for frame in scene.frames if graph.carved else []:
        inside, _ = boxes_containing(pts, graph.carved, frame.index)
        keep &= ~inside
    return torch.from_numpy(keep)


def initial_model(scene, views: list[View], p: FitParams, scene_scale: float,
                  log: logging.Logger, graph: Graph | None = None,
                  ) -> tuple[Params, torch.Tensor, torch.Tensor, dict]:
    """Initial raw parameters, the sky flag and node (:data:`BACKGROUND` or an index into
    ``graph.nodes``) per Gaussian, and a description for fit.json."""
    graph = graph or Graph()
    gen = torch.Generator().manual_seed(p.seed)
    # colour look-ups walk the views in time order, spread over the whole drive
    order = sorted(range(len(views)), key=lambda i: (views[i].frame, views[i].camera))
    ordered = [views[i] for i in order]
    mode = p.init
    lidar, node_lidar = _lidar_split(scene, graph) if mode in ("auto", "lidar") else (None, [])
    if mode == "lidar" and lidar is None:
        raise SceneError("fit: init 'lidar' asked but the scene has no lidar/", scene_id=scene.scene_id,
                         fix="use init: auto or frustum, or ingest the LiDAR")
    cap = p.max_gaussians if p.max_gaussians > 0 else None
    n_sky = p.sky_points
    # the nodes' points come out of init_points (at most a quarter of them), so a scene graph
    # starts with as many Gaussians as the static model of the same scene
    per_node = min(p.actor_init_points, p.init_points // max(4 * len(graph.nodes), 1))
    budget = p.init_points - per_node * len(graph.nodes)
    budget = budget if cap is None else min(budget, max(cap - n_sky - per_node * len(graph.nodes), 1))
    if lidar is not None and len(lidar):
        means, rgb = gsinit.lidar_points_init(lidar, ordered, voxel=p.lidar_voxel,
                                              max_points=min(p.lidar_max_points, budget),
                                              generator=gen)
        how = "lidar"
        if len(means) < p.init_top_up * budget:  # sparse: a video's SfM points
            f_means, f_rgb = _frustum_init(ordered, budget - len(means), scene, graph, p, gen)
            means, rgb = torch.cat([means, f_means]), torch.cat([rgb, f_rgb])
            how = "lidar+frustum"
    else:
        means, rgb = _frustum_init(ordered, budget, scene, graph, p, gen)
        how = "frustum"
    scales = gsinit.knn_scales(means, max_scale=0.1 * scene_scale)
    params = new_params(means, rgb, scales, opacity=p.init_opacity,
                        sh_degree=p.sh_degree)
    node = torch.full((len(means),), BACKGROUND, dtype=torch.int64)
    actor_points = []
    for k, actor in enumerate(graph.nodes):
        local = node_lidar[k] if k < len(node_lidar) else np.zeros((0, 3))
        a_means, a_rgb = actor_points_init(actor, local, ordered, n_points=per_node,
                                           voxel=p.lidar_voxel, generator=gen)
        a_scales = gsinit.knn_scales(a_means, max_scale=0.25 * float(min(actor.size)))
        params = cat_params(params, new_params(a_means, a_rgb, a_scales, opacity=p.init_opacity,
                                               sh_degree=p.sh_degree))
        node = torch.cat([node, torch.full((len(a_means),), k, dtype=torch.int64)])
        actor_points.append(len(a_means))
    is_sky = torch.zeros(len(node), dtype=torch.bool)
    radius = p.sky_radius
    if n_sky > 0:
        centers = torch.stack([v.c2w[:3, 3] for v in views]).float()
        s_means, s_rgb, s_scales = gsinit.sky_dome(ordered, n_points=n_sky, radius=radius,
                                                   center=centers.mean(0))
        sky = new_params(s_means, s_rgb, s_scales, opacity=0.9, sh_degree=p.sh_degree)
        params = cat_params(params, sky)
        is_sky = torch.cat([is_sky, torch.ones(len(s_means), dtype=torch.bool)])
        node = torch.cat([node, torch.full((len(s_means),), BACKGROUND, dtype=torch.int64)])
    desc = {"method": how, "points": int(len(means)), "sky_points": int(is_sky.sum()),
            "sky_radius_m": radius, "scene_scale_m": scene_scale}
    log.info("fit: init %s with %d points + %d sky + %d in %d actor nodes", how, len(means),
             int(is_sky.sum()), sum(actor_points), len(graph.nodes))
    return params, is_sky, node, {"init": desc, "actor_points": actor_points}


def lidar_depth_targets(scene, views: Sequence[View],
                        device: torch.device) -> list[DepthTarget | None]:
    """Per view, the LiDAR sweep of its frame projected into it (None where the frame has none)."""
    sweeps: dict[int, np.ndarray | None] = {}
    targets: list[DepthTarget | None] = []
    for v in views:
        if v.frame not in sweeps:
            sweeps[v.frame] = scene.lidar_frame(v.frame)
        pts = sweeps[v.frame]
        target = None if pts is None or not len(pts) else lidar_depth_target(pts, v)
        targets.append(target.to(device) if target is not None and len(target.pixels) else None)
    return targets


def _loss_masks(actors: list[Actor], views: Sequence[View], device: torch.device,
                layout: SceneLayout | None = None) -> list[torch.Tensor | None]:
    """Per view, the pixels the loss leaves out: those of ``actors`` (moving, no node of their
    own), and a video scene's ego mask (``masks/ego``: the hood) and moving masks
    (``masks/motion``), scaled to the view."""
    masks: list[torch.Tensor | None] = []
    for v in views:
        hit = np.zeros((v.height, v.width), dtype=bool)
        if actors and v.frame_index is not None:
            hit |= dynamic_mask(actors, v.frame_index, v.c2w.numpy(), v.K.double().numpy(), v.width, v.height)
        if layout is not None:
            hit |= _saved_mask(layout.ego_mask(v.camera), v) | _saved_mask(
                layout.motion_mask(v.camera, v.frame_index if v.frame_index is not None else v.frame), v)
        masks.append(torch.from_numpy(hit).to(device) if hit.any() else None)
    return masks


def _saved_mask(path: Path, view: View) -> np.ndarray:
    """A mask PNG (255 = left out) at the view's size; none where the file is absent."""
    from paradrive.scene import read_image

    if not path.is_file():
        return np.zeros((view.height, view.width), dtype=bool)
    mask = torch.from_numpy(read_image(path)[..., :1].astype(np.float32) / 255.0)
    return (_resize(mask, view.height, view.width)[..., 0] > 0.0).numpy()


def _unmasked_depth(targets: Sequence[DepthTarget | None], masks: list[torch.Tensor | None]
                    ) -> list[DepthTarget | None]:
    """The depth targets less their pixels the loss leaves out."""
    out: list[DepthTarget | None] = []
    for target, mask in zip(targets, masks):
        if target is not None and mask is not None:
            keep = ~mask.reshape(-1)[target.pixels]
            target = DepthTarget(target.pixels[keep], target.depth[keep]) if keep.any() else None
        out.append(target)
    return out


# Devices where Adam takes torch's fused step (one kernel per parameter instead of a dozen tensor
# operations; about 5x faster on the CPU at the demo's 50k Gaussians). Elsewhere, the plain step.
FUSED_ADAM_DEVICES = ("cpu", "cuda")


def _make_optimizers(params: dict[str, torch.nn.Parameter], p: FitParams,
                     scene_scale: float) -> dict[str, torch.optim.Optimizer]:
    lrs = {"means": p.lr_means * scene_scale, "scales": p.lr_scales,
           "quats": p.lr_quats, "opacities": p.lr_opacities,
           "sh0": p.lr_sh0, "shN": p.lr_shN}
    fused = params["means"].device.type in FUSED_ADAM_DEVICES
    return {k: torch.optim.Adam([params[k]], lr=lrs[k], eps=1e-15, fused=fused) for k in PARAM_KEYS}


@torch.no_grad()
def _step(optimizers: Sequence[torch.optim.Optimizer]) -> None:
    """``step()`` then ``zero_grad(set_to_none=True)`` of each optimizer."""
    for o in optimizers:
        o.step()
        o.zero_grad(set_to_none=True)


# --------------------------------------------------------------------------- state

def _rng_state(gen: torch.Generator) -> dict:
    """Every RNG the fit draws from, as tensors and plain numbers (loadable without pickle)."""
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    version, internal, gauss_next = random.getstate()
    return {"train": gen.get_state(), "torch": torch.get_rng_state(),
            "numpy": {"kind": str(kind), "keys": torch.from_numpy(np.asarray(keys).astype(np.int64)),
                      "pos": int(pos), "has_gauss": int(has_gauss), "cached_gaussian": float(cached)},
            "python": {"version": int(version), "internal": [int(x) for x in internal],
                       "gauss_next": gauss_next}}


def _set_rng_state(gen: torch.Generator, st: dict) -> None:
    gen.set_state(st["train"])
    torch.set_rng_state(st["torch"])
    n, py = st["numpy"], st["python"]
    np.random.set_state((n["kind"], n["keys"].numpy().astype(np.uint32), n["pos"], n["has_gauss"],
                         n["cached_gaussian"]))
    random.setstate((py["version"], tuple(py["internal"]), py["gauss_next"]))


def _to_cpu(tree: Any) -> Any:
    """Every tensor of a nested dict / list moved to the CPU: a state file loads on any machine."""
    if isinstance(tree, torch.Tensor):
        return tree.detach().cpu()
    if isinstance(tree, dict):
        return {k: _to_cpu(v) for k, v in tree.items()}
    if isinstance(tree, (list, tuple)):
        return type(tree)(_to_cpu(v) for v in tree)
    return tree


def _save_state(path: Path, *, step, params, optimizers, strategy_state, gen, order, cursor,
                metrics, elapsed, fingerprint, extra) -> None:
    doc = {
        "version": STATE_VERSION, "step": int(step), "fingerprint": fingerprint,
        "params": _to_cpu(dict(params)),
        "optimizers": {k: _to_cpu(o.state_dict()) for k, o in optimizers.items()},
        "strategy": _to_cpu(strategy_state),
        "rng": _rng_state(gen), "order": order.clone(), "cursor": int(cursor),
        "metrics": list(metrics), "elapsed": float(elapsed), "extra": extra,
    }
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            try:
                torch.save(doc, f)
            except RuntimeError as exc:  # torch reports a failed write ("unexpected pos") so
                if isinstance(exc.__context__, OSError):  # the write's own error says why
                    raise exc.__context__ from None
                raise
            f.flush()
            os.fsync(f.fileno())


# --------------------------------------------------------------------------- evaluation

@torch.no_grad()
def evaluate(model: Gaussians | FittedModel, views: Sequence[View], indices: Sequence[int], sh_degree: int,
             device: torch.device, backend: str = "auto") -> dict:
    """Mean PSNR (dB) and SSIM of renders against the training images of ``indices``."""
    model = model if isinstance(model, FittedModel) else FittedModel(dict(model))
    ps, ss = [], []
    for i in indices:
        v = views[i]
        out, _, _ = render_gaussians(model.at(v.frame), v.viewmat()[None].to(device), v.K[None].to(device),
                                     v.width, v.height, sh_degree=sh_degree, backend=backend)
        pred = out[0, ..., :3].clamp(0, 1).cpu()
        gt = v.rgb()
        ps.append(float(psnr(pred, gt)))
        ss.append(float(ssim(pred, gt)))
    return {"psnr": float(np.mean(ps)), "ssim": float(np.mean(ss))}


def _eval_indices(n_views: int, n_eval: int) -> list[int]:
    if n_eval <= 0 or n_eval >= n_views:
        return list(range(n_views))
    return sorted({int(round(x)) for x in np.linspace(0, n_views - 1, n_eval)})


# --------------------------------------------------------------------------- the fit

def fit_scene(scene: SceneLayout | str | Path, p: FitParams, *,
              log: logging.Logger | None = None,
              progress: Callable[..., None] | None = None,
              stop_after: int | None = None, moving_threshold_m: float | None = None,
              on_record: Callable[[FitRecord], None] | None = None) -> FitRecord:
    """Fit the scene folder ``scene`` with the fit stage's parameters ``p``; returns the fit's
    record. ``on_record`` is handed the record at every checkpoint and at the end (the fit stage
    writes it as ``fit.json``); this library writes only the checkpoints and its resume state.

    Resumes from ``gs/state.pt`` when present and made with the same parameters.
    ``stop_after``: return after this many total iterations (tests; the state is saved).
    ``moving_threshold_m``: the ingest's (a track moving farther is a moving actor: a node of
    the scene graph unless ``p.dynamic`` is off); None = no actor moves.
    """
    from paradrive.scene import load_scene

    layout = SceneLayout.at(scene)
    layout.gs_dir.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(layout.gs_dir)
    device = resolve_device(p.device)
    with deterministic_torch(p.threads, resolve_backend(p.backend, device)):
        loaded = load_scene(layout.root)
        graph = Graph.of(loaded, p, moving_threshold_m)
        run = _Fit(loaded, layout, p, device, log or log_default, graph, on_record)
        return _fit(run, progress, stop_after)


def _fit(run: _Fit, progress, stop_after) -> FitRecord:
    p, layout = run.p, run.layout
    total = p.iterations
    while run.step < total:
        if stop_after is not None and run.step >= stop_after:
            run.save_state()
            return run.record(False)
        loss = run.iterate()
        if run.step in p.checkpoints:
            run.checkpoint()
            stop_point(f"fit:checkpoint-{run.step}")
        elif run.step % max(p.state_interval, 1) == 0:
            run.save_state()
        if progress is not None and (run.step % 10 == 0 or run.step == total):
            progress(run.step, total, loss=loss, gaussians=run.params["means"].shape[0],
                     psnr=lambda: evaluate(run.model(), run.views, run.eval_idx, p.sh_degree, run.device,
                                           run.backend)["psnr"])
    record = run.record(True)
    if not p.keep_state:
        layout.fit_state.unlink(missing_ok=True)
    return record


def _load_state(path: Path, fp: str, log: logging.Logger) -> dict | None:
    """The resume state at ``path`` when it is one and was made with the same parameters."""
    if not path.is_file():
        return None
    try:
        saved = load_tensors(path)
    except Exception as exc:  # an older version's state, a foreign file, one that needs pickle
        log.warning("fit: %s not loaded (%s); starting over", path, exc)
        return None
    if not isinstance(saved, dict):
        log.warning("fit: %s is not a resume state; starting over", path)
        return None
    if saved.get("version") != STATE_VERSION or saved.get("fingerprint") != fp:
        log.warning("fit: %s was made with other parameters; starting over", path)
        return None
    return saved


class _Fit:
    """One fit in progress: the model, its optimizers and densification state, the training
    order and the clocks; :meth:`iterate` takes one step, the rest writes what a step earned."""

    def __init__(self, scene, layout: SceneLayout, p: FitParams, device: torch.device,
                 log: logging.Logger, graph: Graph | None = None,
                 on_record: Callable[[FitRecord], None] | None = None):
        self.scene, self.layout, self.p, self.device, self.log = scene, layout, p, device, log
        self.on_record = on_record
        self.graph = graph = graph or Graph()
        ids = [a.id for a in graph.nodes]
        self.fp = _fingerprint({**p.source, "checkpoints": p.checkpoints,
                                **({"nodes": ids, "masked": [a.id for a in graph.masked]}
                                   if graph.carved else {})})
        self.files = actor_files(ids)
        self.poses = node_poses(scene, graph.nodes).to(device) if graph.nodes else None
        self.node_rows: NodeRows | None = None   # the rows place() moves, kept between refinements
        holdout = Holdout.of(p)   # held-out images are never read: no loss, densification or init
        holdout.check(scene)
        self.views = views = load_views(scene, p.cameras, p.downscale,
                                        keep=holdout.trained if holdout.active else None)
        scene_scale = scene_scale_of(torch.stack([v.c2w for v in views]))
        self.strategy = DensifyStrategy(
            prune_opa=p.prune_opa, grow_grad2d=p.grow_grad2d, grow_scale3d=p.grow_scale3d,
            prune_scale3d=p.prune_scale3d, refine_start_iter=p.refine_start_iter,
            refine_stop_iter=p.refine_stop_iter, reset_every=p.reset_every,
            refine_every=p.refine_every, max_gaussians=p.max_gaussians)
        self.backend = resolve_backend(p.backend, device)
        # the training order and split samples come from a CPU generator on every device, so a
        # fit resumed on another machine draws the same numbers
        self.gen = torch.Generator(device="cpu").manual_seed(p.seed + 1)
        saved = _load_state(layout.fit_state, self.fp, log)
        raw = self._resume(saved) if saved is not None else self._start(scene_scale)
        self.params = {k: torch.nn.Parameter(raw[k].to(device).contiguous()) for k in PARAM_KEYS}
        self.optimizers = _make_optimizers(self.params, p, scene_scale)
        # box refinement: per frame and node a translation and a turn about the box's z axis
        self.boxes = None
        if self.poses is not None and p.actor_pose_lr > 0:
            start = raw.get("boxes")
            zeros = torch.zeros(len(scene.frames), len(graph.nodes), 4, device="cpu")
            self.boxes = torch.nn.Parameter((zeros if start is None else start).to(device))
            self.optimizers["boxes"] = torch.optim.Adam([self.boxes], lr=p.actor_pose_lr, eps=1e-15)
        self.strat_state: dict[str, Any] = {k: (v.to(device) if isinstance(v, torch.Tensor) else v)
                                            for k, v in self.strat_state.items()}
        if saved is not None:
            for k, o in self.optimizers.items():
                o.load_state_dict(saved["optimizers"][k])
            _set_rng_state(self.gen, saved["rng"])
        self.densify = self.extra.setdefault("densify", {})   # running totals, saved with the state
        self.lr0 = p.lr_means * scene_scale
        self.gamma = (p.lr_means_final / p.lr_means) ** (1.0 / max(p.iterations, 1))
        self.has_sky = (int(self.strat_state["is_sky"].sum()) > 0
                        and any(v.sky is not None for v in views))
        self.depth_targets = (lidar_depth_targets(scene, views, device) if p.depth_weight > 0
                              else [None] * len(views))
        self.loss_masks = _loss_masks(graph.masked, views, device, layout)
        self.depth_targets = _unmasked_depth(self.depth_targets, self.loss_masks)
        self.loss_terms = FitLossTerms(p.ssim_lambda, p.sky_depth_weight, 0.5 * p.sky_radius,
                                       p.depth_weight)
        self.eval_idx = _eval_indices(len(views), p.eval_views)
        self.gpu_views = [(v.viewmat()[None].to(device), v.K[None].to(device)) for v in views]
        self.t_start, self.c_start = time.perf_counter(), time.process_time()

    def _resume(self, saved: dict) -> Params:
        self.extra = saved["extra"]
        self.strat_state = dict(saved["strategy"])
        self.step = int(saved["step"])
        self.metrics = list(saved["metrics"])
        self.elapsed0 = float(saved["elapsed"])
        self.cpu0 = float(self.extra.pop("cpu_seconds", 0.0))
        self.order, self.cursor = saved["order"].clone(), int(saved["cursor"])
        self.log.info("fit: %s resumes at iteration %d", self.scene.scene_id, self.step)
        return saved["params"]

    def _start(self, scene_scale: float) -> Params:
        raw, is_sky, node, init = initial_model(self.scene, self.views, self.p, scene_scale, self.log,
                                                self.graph)
        nodes = [{"id": a.id, "cls": a.cls, "rigid": a.rigid, "file": f, "init_points": n}
                 for a, f, n in zip(self.graph.nodes, self.files, init["actor_points"])]
        self.extra = {"init": init["init"], "scene_scale": scene_scale, "dynamic": bool(nodes),
                      "actors": nodes}
        self.strat_state = self.strategy.initialize_state(len(is_sky), scene_scale, is_sky,
                                                          device=self.device)
        self.strat_state["node"] = node.to(self.device)
        self.step, self.metrics, self.elapsed0, self.cpu0 = 0, [], 0.0, 0.0
        self.order, self.cursor = torch.randperm(len(self.views), generator=self.gen), 0
        return raw

    def elapsed(self) -> float:
        return self.elapsed0 + time.perf_counter() - self.t_start

    def cpu_seconds(self) -> float:
        return self.cpu0 + time.process_time() - self.c_start

    def iterate(self) -> torch.Tensor:
        """One training step: render a view, take the loss, step the optimizers, densify; returns
        the step's loss (detached)."""
        p, step = self.p, self.step
        if self.cursor >= len(self.order):
            self.order, self.cursor = torch.randperm(len(self.views), generator=self.gen), 0
        vi = int(self.order[self.cursor])
        self.cursor += 1
        for group in self.optimizers["means"].param_groups:
            group["lr"] = self.lr0 * self.gamma**step
        loss, info = self._loss(vi, min(step // max(p.sh_degree_interval, 1), p.sh_degree))
        loss.backward()
        _step(list(self.optimizers.values()))
        changed = self.strategy.step_post_backward(self.params, self.optimizers, self.strat_state,
                                                   step, info, self.gen)
        for key, count in changed.items():
            self.densify[key] = self.densify.get(key, 0) + count
        self.step += 1
        return loss.detach()

    def _loss(self, vi: int, deg: int) -> tuple[torch.Tensor, dict]:
        p, view, device = self.p, self.views[vi], self.device
        viewmat, K = self.gpu_views[vi]
        use_sky = self.has_sky and view.sky is not None and p.sky_depth_weight > 0
        target = self.depth_targets[vi]
        node = self.strat_state.get("node")
        if node is not None:
            self.node_rows = NodeRows.of(node, self.node_rows)
        gaussians = place(self.params, node, self.poses, view.frame, self.boxes, self.node_rows)
        with_depth = use_sky or target is not None
        masked = self.loss_masks[vi]
        gt = view.rgb().to(device)
        kernels = fit_loss_kernels(gaussians["means"]) if masked is None and p.depth_inverse else None
        if kernels is not None:  # the same loss and gradient bytes as below, as one node
            raw, alphas, info = render_gaussians(gaussians, viewmat, K, view.width, view.height,
                                                 sh_degree=deg, backend=self.backend,
                                                 render_mode="RGB+D" if with_depth else "RGB")
            loss = fit_loss(raw, alphas, gt, view.sky if use_sky else None, target,
                            self.loss_terms, kernels)
        else:
            loss, info = self._loss_torch(gaussians, vi, deg, gt, with_depth, use_sky, target)
        solid = ~self.strat_state["is_sky"]
        if p.flatten_weight > 0:
            loss = loss + p.flatten_weight * flatten_loss(self.params["scales"], solid)
        if p.shape_ratio_weight > 0 and self.step % max(p.shape_ratio_every, 1) == 0:
            loss = loss + p.shape_ratio_weight * shape_ratio_loss(self.params["scales"],
                                                                 p.shape_ratio_max, solid)
        return loss, info

    def _loss_torch(self, gaussians: Gaussians, vi: int, deg: int, gt: torch.Tensor,
                    with_depth: bool, use_sky: bool, target: DepthTarget | None
                    ) -> tuple[torch.Tensor, dict]:
        """The photometric, sky and depth terms of :meth:`_loss` as torch operations."""
        p, view = self.p, self.views[vi]
        viewmat, K = self.gpu_views[vi]
        out, _, info = render_gaussians(gaussians, viewmat, K, view.width, view.height,
                                        sh_degree=deg, backend=self.backend,
                                        render_mode="RGB+ED" if with_depth else "RGB")
        sky = view.sky.to(self.device) if use_sky and view.sky is not None else None
        loss = fit_loss_torch(out, gt, sky, target, self.loss_terms, p.depth_inverse,
                              self.loss_masks[vi])
        return loss, info

    def checkpoint(self) -> None:
        """The PLY of this iteration, its metrics, the resume state and the record."""
        step, params, device = self.step, self.params, self.device
        model = self.model()
        save_model(self.layout, step, params, model.node, self.files, self.boxes)
        m = evaluate(model, self.views, self.eval_idx, self.p.sh_degree, device, self.backend)
        entry = {"iteration": step, **m, "num_gaussians": int(params["means"].shape[0]),
                 "seconds": round(self.elapsed(), 3), "cpu_seconds": round(self.cpu_seconds(), 3),
                 "peak_rss_mb": round(peak_rss_mb(), 1)}
        if device.type == "cuda" and torch.cuda.is_available():
            entry["peak_gpu_mb"] = round(torch.cuda.max_memory_allocated(device) / 2**20, 1)
        self.metrics = [x for x in self.metrics if x["iteration"] != step] + [entry]
        self.log.info("fit: %s iteration %d: PSNR %.2f dB, SSIM %.4f, %d Gaussians, %.1f s",
                      self.scene.scene_id, step, m["psnr"], m["ssim"], params["means"].shape[0],
                      self.elapsed())
        self.save_state()
        self.record(step >= self.p.iterations)

    def model(self) -> FittedModel:
        """The model as a renderer loads its checkpoint (refined boxes applied)."""
        if self.poses is None:
            return FittedModel(self.params)
        poses = self.poses if self.boxes is None else self.poses.corrected(self.boxes)
        return FittedModel(self.params, self.strat_state["node"], poses)

    def save_state(self) -> None:
        boxes = {} if self.boxes is None else {"boxes": self.boxes}
        _save_state(self.layout.fit_state, step=self.step, params={**self.params, **boxes},
                    optimizers=self.optimizers, strategy_state=self.strat_state, gen=self.gen,
                    order=self.order, cursor=self.cursor, metrics=self.metrics,
                    elapsed=self.elapsed(), fingerprint=self.fp,
                    extra={**self.extra, "cpu_seconds": self.cpu_seconds()})

    def record(self, complete: bool) -> FitRecord:
        views = self.views
        record = FitRecord(scene_id=self.scene.scene_id, complete=complete, fingerprint=self.fp,
                           iterations=self.p.iterations, checkpoints=self.metrics,
                           eval_views=len(self.eval_idx),
                           resolution=[views[0].width, views[0].height], n_views=len(views),
                           cameras=sorted({v.camera for v in views}), device=str(self.device),
                           **self.extra)
        if self.on_record is not None:
            self.on_record(record)
        return record


# --------------------------------------------------------------------------- views

@torch.no_grad()
def render_checkpoint(ply_path: str | os.PathLike | None, c2w, K, width: int, height: int, *,
                      render_depth: bool = False, params: Params | None = None,
                      device: str = "auto", backend: str = "auto") -> dict:
    """Render a checkpoint from N cameras sharing one intrinsic matrix.

    ply_path: a 3DGS PLY (or None with ``params`` from :func:`load_ply` to skip re-reading);
    c2w: (N, 4, 4) or (4, 4) camera-to-world, OpenCV, scene world; K: (3, 3) pixels of the
    (width x height) output. Returns numpy float32 arrays: ``rgb`` (N, H, W, 3) in [0, 1],
    ``alpha`` (N, H, W), and ``depth`` (N, H, W) expected z-depth in metres (None unless
    ``render_depth``). The sky dome counts as geometry (alpha ~ 1, depth ~ dome distance).
    backend: the rasterizer, see :func:`paradrive.devices.resolve_backend`.
    """
    if params is None:
        if ply_path is None:
            raise ValueError("render_checkpoint needs ply_path or params")
        params = load_ply(ply_path)
    dev = resolve_device(device)
    params = {k: v.to(dev) for k, v in params.items()}
    c2w = torch.as_tensor(np.asarray(c2w), dtype=torch.float64)
    if c2w.dim() == 2:
        c2w = c2w[None]
    viewmats = torch.linalg.inv(c2w).float().to(dev)
    Kt = torch.as_tensor(np.asarray(K), dtype=torch.float32).to(dev)
    deg = sh_degree_of(params)
    rgbs, alphas, depths = [], [], []
    for i in range(len(viewmats)):
        out, alpha, _ = render_gaussians(params, viewmats[i:i + 1], Kt[None], int(width), int(height),
                                         sh_degree=deg, render_mode="RGB+ED" if render_depth else "RGB",
                                         backend=backend)
        rgbs.append(out[0, ..., :3].clamp(0, 1).float().cpu().numpy())
        alphas.append(alpha[0, ..., 0].clamp(0, 1).float().cpu().numpy())
        if render_depth:
            depths.append(out[0, ..., 3].float().cpu().numpy())
    return {"rgb": np.stack(rgbs), "alpha": np.stack(alphas),
            "depth": np.stack(depths) if render_depth else None}
