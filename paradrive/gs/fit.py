"""The ``fit`` stage: train a 3D Gaussian Splatting model of one scene and write checkpoints.

Outputs under ``<scene>/gs/``:

* ``ckpt_{iteration:06d}.ply`` at exactly the configured iterations (standard 3DGS PLY),
* ``fit.json``: per checkpoint the training-view PSNR / SSIM (a fixed, evenly spaced subset of the
  training views, ``eval_views``), the number of Gaussians, seconds of fitting and peak RSS,
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
a sharp-shape term on its axis ratio (``shape_ratio_weight``).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import random
import resource
import time
from pathlib import Path
from typing import Any, Callable, Dict, Optional, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from paradrive.devices import resolve_backend, resolve_device
from paradrive.errors import ConfigError, SceneError
from paradrive.io import atomic_path, load_tensors, remove_stale_temporaries, write_json
from paradrive.metrics import psnr, ssim

from . import init as gsinit
from .init import View
from .losses import DepthTarget, depth_loss, flatten_loss, lidar_depth_target, shape_ratio_loss
from .model import (PARAM_KEYS, Params, cat_params, deterministic_torch, new_params, render,
                    scene_scale_of, sh_degree_of)
from .ply import load_ply, save_ply
from .strategy import DensifyStrategy

__all__ = ["run_stage", "fit_scene", "render_checkpoint", "load_ply", "checkpoint_path",
           "load_views"]

STATE_VERSION = 2  # 2: RNG states as tensors and plain lists, loaded without pickle
log_default = logging.getLogger("paradrive.gs.fit")


def checkpoint_path(gs_dir: Path, iteration: int) -> Path:
    return Path(gs_dir) / f"ckpt_{int(iteration):06d}.ply"


# --------------------------------------------------------------------------- parameters

_REQUIRED = (
    "checkpoints", "cameras", "downscale", "seed", "threads", "device", "sh_degree",
    "sh_degree_interval", "ssim_lambda", "lr_means", "lr_means_final", "lr_scales", "lr_quats",
    "lr_opacities", "lr_sh0", "lr_shN", "grow_grad2d", "grow_scale3d", "prune_scale3d",
    "prune_opa", "refine_start_iter", "refine_stop_iter", "refine_every", "reset_every",
    "max_gaussians", "init", "init_points", "init_opacity", "init_depth_min", "init_depth_max",
    "init_depth_candidates", "init_ground_margin", "lidar_voxel", "lidar_max_points", "sky_points",
    "sky_radius", "sky_depth_weight", "depth_weight", "depth_inverse", "flatten_weight",
    "shape_ratio_weight", "shape_ratio_max", "shape_ratio_every", "eval_views", "state_interval",
    "keep_state", "backend",
)


def _check_params(p: Dict[str, Any]) -> Dict[str, Any]:
    missing = [k for k in _REQUIRED if k not in p]
    if missing:
        raise ConfigError(f"fit: parameters missing: {', '.join(missing)}; they are declared in "
                          "stages/fit.yaml (pass the resolved stage parameters)")
    cps = sorted({int(c) for c in p["checkpoints"]})
    if not cps or cps[0] <= 0:
        raise ConfigError(f"fit: checkpoints must be positive iterations, got {p['checkpoints']!r}")
    if p["init"] not in ("auto", "lidar", "frustum"):
        raise ConfigError(f"fit: init must be auto, lidar or frustum, got {p['init']!r}")
    if float(p["downscale"]) < 1.0:
        raise ConfigError(f"fit: downscale must be >= 1, got {p['downscale']!r}")
    return {**p, "checkpoints": cps}


def _float_or_none(x: Any) -> Optional[float]:
    return None if x is None else float(x)


def _fingerprint(p: Dict[str, Any]) -> str:
    keep = {k: p[k] for k in sorted(p) if k not in ("keep_state", "state_interval", "eval_views")}
    return hashlib.sha256(json.dumps(keep, sort_keys=True, default=str).encode()).hexdigest()[:16]


# --------------------------------------------------------------------------- data

def _resize(x: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """(H, W, C) float -> (h, w, C) by area averaging."""
    if x.shape[0] == h and x.shape[1] == w:
        return x
    y = F.interpolate(x.permute(2, 0, 1)[None], size=(h, w), mode="area")
    return y[0].permute(1, 2, 0)


def load_views(scene, cameras: Optional[Sequence[str]], downscale: float) -> list[View]:
    """All (frame, camera) images of ``scene`` at 1/``downscale`` resolution, frame-major order."""
    names = list(scene.cameras) if not cameras else list(cameras)
    unknown = [c for c in names if c not in scene.cameras]
    if unknown:
        raise SceneError(f"fit: cameras {unknown} are not in the scene (has {list(scene.cameras)})",
                         scene_id=scene.scene_id, fix="fix the 'cameras' parameter of the fit stage")
    views = []
    for fi, frame in enumerate(scene.frames):
        for name in names:
            if name not in frame.cameras:
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
                              frame=fi, ground_z=float(np.asarray(frame.ego2world)[2, 3])))
    if not views:
        raise SceneError("fit: the scene has no images for the chosen cameras",
                         scene_id=scene.scene_id, fix="check scene.json frames / 'cameras'")
    return views


# --------------------------------------------------------------------------- model building

def initial_model(scene, views: list[View], p: Dict[str, Any], scene_scale: float,
                  log: logging.Logger) -> tuple[Params, torch.Tensor, dict]:
    """Initial raw parameters, the sky flag per Gaussian, and a description for fit.json."""
    gen = torch.Generator().manual_seed(int(p["seed"]))
    # colour look-ups walk the views in time order, spread over the whole drive
    order = sorted(range(len(views)), key=lambda i: (views[i].frame, views[i].camera))
    ordered = [views[i] for i in order]
    mode = p["init"]
    lidar = scene.lidar_points() if mode in ("auto", "lidar") else None
    if mode == "lidar" and lidar is None:
        raise SceneError("fit: init 'lidar' asked but the scene has no lidar/", scene_id=scene.scene_id,
                         fix="use init: auto or frustum, or ingest the LiDAR")
    cap = int(p["max_gaussians"]) if int(p["max_gaussians"]) > 0 else None
    n_sky = int(p["sky_points"])
    budget = int(p["init_points"]) if cap is None else min(int(p["init_points"]), max(cap - n_sky, 1))
    if lidar is not None and len(lidar):
        means, rgb = gsinit.lidar_points_init(lidar, ordered, voxel=float(p["lidar_voxel"]),
                                              max_points=min(int(p["lidar_max_points"]), budget),
                                              generator=gen)
        how = "lidar"
    else:
        means, rgb = gsinit.frustum_points_init(ordered, n_points=budget,
                                                depth_min=float(p["init_depth_min"]),
                                                depth_max=float(p["init_depth_max"]),
                                                depth_candidates=int(p["init_depth_candidates"]),
                                                ground_margin=_float_or_none(p["init_ground_margin"]),
                                                generator=gen)
        how = "frustum"
    scales = gsinit.knn_scales(means, max_scale=0.1 * scene_scale)
    params = new_params(means, rgb, scales, opacity=float(p["init_opacity"]),
                        sh_degree=int(p["sh_degree"]))
    is_sky = torch.zeros(len(means), dtype=torch.bool)
    radius = float(p["sky_radius"])
    if n_sky > 0:
        centers = torch.stack([v.c2w[:3, 3] for v in views]).float()
        s_means, s_rgb, s_scales = gsinit.sky_dome(ordered, n_points=n_sky, radius=radius,
                                                   center=centers.mean(0))
        sky = new_params(s_means, s_rgb, s_scales, opacity=0.9, sh_degree=int(p["sh_degree"]))
        params = cat_params(params, sky)
        is_sky = torch.cat([is_sky, torch.ones(len(s_means), dtype=torch.bool)])
    desc = {"method": how, "points": int(len(means)), "sky_points": int(is_sky.sum()),
            "sky_radius_m": radius, "scene_scale_m": scene_scale}
    log.info("fit: init %s with %d points + %d sky", how, len(means), int(is_sky.sum()))
    return params, is_sky, desc


def lidar_depth_targets(scene, views: Sequence[View],
                        device: torch.device) -> list[Optional[DepthTarget]]:
    """Per view, the LiDAR sweep of its frame projected into it (None where the frame has none)."""
    sweeps: dict[int, Optional[np.ndarray]] = {}
    targets: list[Optional[DepthTarget]] = []
    for v in views:
        if v.frame not in sweeps:
            sweeps[v.frame] = scene.lidar_frame(v.frame)
        pts = sweeps[v.frame]
        target = None if pts is None or not len(pts) else lidar_depth_target(pts, v)
        targets.append(target.to(device) if target is not None and len(target.pixels) else None)
    return targets


def _make_optimizers(params: Dict[str, torch.nn.Parameter], p: Dict[str, Any],
                     scene_scale: float) -> Dict[str, torch.optim.Optimizer]:
    lrs = {"means": float(p["lr_means"]) * scene_scale, "scales": float(p["lr_scales"]),
           "quats": float(p["lr_quats"]), "opacities": float(p["lr_opacities"]),
           "sh0": float(p["lr_sh0"]), "shN": float(p["lr_shN"])}
    return {k: torch.optim.Adam([params[k]], lr=lrs[k], eps=1e-15) for k in PARAM_KEYS}


# --------------------------------------------------------------------------- state

def _rng_state(gen: torch.Generator) -> dict:
    """Every RNG the fit draws from, as tensors and plain numbers (loadable without pickle)."""
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    version, internal, gauss_next = random.getstate()
    return {"train": gen.get_state(), "torch": torch.get_rng_state(),
            "numpy": {"kind": str(kind), "keys": torch.from_numpy(keys.astype(np.int64)),
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
            torch.save(doc, f)
            f.flush()
            os.fsync(f.fileno())


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


# --------------------------------------------------------------------------- evaluation

@torch.no_grad()
def evaluate(params: Params, views: Sequence[View], indices: Sequence[int], sh_degree: int,
             device: torch.device, backend: str = "auto") -> dict:
    """Mean PSNR (dB) and SSIM of renders against the training images of ``indices``."""
    ps, ss = [], []
    for i in indices:
        v = views[i]
        out, _, _ = render(params, v.viewmat()[None].to(device), v.K[None].to(device), v.width,
                           v.height, sh_degree=sh_degree, backend=backend)
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

def fit_scene(scene_dir: str | os.PathLike, params: Dict[str, Any], *,
              log: Optional[logging.Logger] = None,
              progress: Optional[Callable[[int, int], None]] = None,
              stop_after: Optional[int] = None) -> dict:
    """Fit the scene at ``scene_dir`` with the resolved stage ``params``; returns fit.json's dict.

    Resumes from ``gs/state.pt`` when present and made with the same parameters.
    ``stop_after``: return after this many total iterations (tests; the state is saved).
    """
    from paradrive.scene import load_scene

    log = log or log_default
    p = _check_params(dict(params))
    scene_dir = Path(scene_dir)
    scene = load_scene(scene_dir)
    gs_dir = scene_dir / "gs"
    gs_dir.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(gs_dir)
    fp = _fingerprint(p)
    fit_json = gs_dir / "fit.json"
    cps = p["checkpoints"]
    total = cps[-1]
    if fit_json.is_file():
        try:
            done = json.loads(fit_json.read_text())
        except json.JSONDecodeError:
            done = {}
        if (done.get("complete") and done.get("fingerprint") == fp
                and all(checkpoint_path(gs_dir, c).is_file() for c in cps)):
            log.info("fit: %s already complete", scene.scene_id)
            return done

    device = resolve_device(str(p["device"]))

    with deterministic_torch(int(p["threads"])):
        return _fit(scene, gs_dir, p, fp, device, log, progress, stop_after)


def _fit(scene, gs_dir: Path, p: Dict[str, Any], fp: str, device: torch.device,
         log: logging.Logger, progress, stop_after) -> dict:
    cps = p["checkpoints"]
    total = cps[-1]
    views = load_views(scene, p["cameras"], float(p["downscale"]))
    scene_scale = scene_scale_of(torch.stack([v.c2w for v in views]))
    strategy = DensifyStrategy(prune_opa=float(p["prune_opa"]), grow_grad2d=float(p["grow_grad2d"]),
                               grow_scale3d=float(p["grow_scale3d"]),
                               prune_scale3d=float(p["prune_scale3d"]),
                               refine_start_iter=int(p["refine_start_iter"]),
                               refine_stop_iter=int(p["refine_stop_iter"]),
                               reset_every=int(p["reset_every"]), refine_every=int(p["refine_every"]),
                               max_gaussians=int(p["max_gaussians"]))
    backend = resolve_backend(str(p["backend"]), device)
    # the training order and split samples come from a CPU generator on every device, so a fit
    # resumed on another machine draws the same numbers
    gen = torch.Generator(device="cpu").manual_seed(int(p["seed"]) + 1)
    state_path = gs_dir / "state.pt"
    saved = None
    if state_path.is_file():
        try:
            saved = load_tensors(state_path)
        except Exception as exc:  # an older version's state, a foreign file, one that needs pickle
            log.warning("fit: %s not loaded (%s); starting over", state_path, exc)
        if saved is not None and not isinstance(saved, dict):
            log.warning("fit: %s is not a resume state; starting over", state_path)
            saved = None
        if saved is not None and (saved.get("version") != STATE_VERSION or saved.get("fingerprint") != fp):
            log.warning("fit: %s was made with other parameters; starting over", state_path)
            saved = None

    if saved is not None:
        raw = saved["params"]
        extra = saved["extra"]
        strat_state = dict(saved["strategy"])
        step = int(saved["step"])
        metrics = list(saved["metrics"])
        elapsed0 = float(saved["elapsed"])
        cpu0 = float(extra.pop("cpu_seconds", 0.0))
        order, cursor = saved["order"].clone(), int(saved["cursor"])
        log.info("fit: %s resumes at iteration %d", scene.scene_id, step)
    else:
        raw, is_sky, init_desc = initial_model(scene, views, p, scene_scale, log)
        extra = {"init": init_desc, "scene_scale": scene_scale}
        strat_state = strategy.initialize_state(len(is_sky), scene_scale, is_sky, device=device)
        step, metrics, elapsed0, cpu0 = 0, [], 0.0, 0.0
        order, cursor = torch.randperm(len(views), generator=gen), 0

    params = {k: torch.nn.Parameter(raw[k].to(device).contiguous()) for k in PARAM_KEYS}
    optimizers = _make_optimizers(params, p, scene_scale)
    strat_state = {k: (v.to(device) if isinstance(v, torch.Tensor) else v) for k, v in strat_state.items()}
    if saved is not None:
        for k, o in optimizers.items():
            o.load_state_dict(saved["optimizers"][k])
        _set_rng_state(gen, saved["rng"])
        del saved

    densify = extra.setdefault("densify", {})   # running totals, saved with the state
    lr0 = float(p["lr_means"]) * scene_scale
    gamma = (float(p["lr_means_final"]) / float(p["lr_means"])) ** (1.0 / max(total, 1))
    lam = float(p["ssim_lambda"])
    sky_w = float(p["sky_depth_weight"])
    sky_radius = float(p["sky_radius"])
    has_sky = int(strat_state["is_sky"].sum()) > 0 and any(v.sky is not None for v in views)
    depth_w = float(p["depth_weight"])
    depth_inv = bool(p["depth_inverse"])
    depth_targets = (lidar_depth_targets(scene, views, device) if depth_w > 0
                     else [None] * len(views))
    flat_w = float(p["flatten_weight"])
    ratio_w, ratio_max = float(p["shape_ratio_weight"]), float(p["shape_ratio_max"])
    ratio_every = max(int(p["shape_ratio_every"]), 1)
    eval_idx = _eval_indices(len(views), int(p["eval_views"]))
    max_deg = int(p["sh_degree"])
    interval = max(int(p["sh_degree_interval"]), 1)
    state_every = max(int(p["state_interval"]), 1)
    gpu_views = [(v.viewmat()[None].to(device), v.K[None].to(device)) for v in views]
    t_start = time.perf_counter()
    c_start = time.process_time()

    def elapsed() -> float:
        return elapsed0 + time.perf_counter() - t_start

    def cpu_seconds() -> float:
        return cpu0 + time.process_time() - c_start

    def save_state() -> None:
        _save_state(state_path, step=step, params=params, optimizers=optimizers,
                    strategy_state=strat_state, gen=gen, order=order, cursor=cursor,
                    metrics=metrics, elapsed=elapsed(), fingerprint=fp,
                    extra={**extra, "cpu_seconds": cpu_seconds()})

    def write_summary(complete: bool) -> dict:
        doc = {"scene_id": scene.scene_id, "complete": complete, "fingerprint": fp,
               "iterations": total, "checkpoints": metrics, "eval_views": len(eval_idx),
               "resolution": [views[0].width, views[0].height], "n_views": len(views),
               "cameras": sorted({v.camera for v in views}),
               "device": str(device), **extra}
        write_json(gs_dir / "fit.json", doc)
        return doc

    while step < total:
        if stop_after is not None and step >= stop_after:
            save_state()
            return write_summary(False)
        if cursor >= len(order):
            order, cursor = torch.randperm(len(views), generator=gen), 0
        vi = int(order[cursor])
        cursor += 1
        view = views[vi]
        viewmat, K = gpu_views[vi]
        for group in optimizers["means"].param_groups:
            group["lr"] = lr0 * gamma**step
        deg = min(step // interval, max_deg)
        use_sky = has_sky and view.sky is not None and sky_w > 0
        target = depth_targets[vi]
        out, alphas, info = render(params, viewmat, K, view.width, view.height, sh_degree=deg,
                                   render_mode="RGB+ED" if use_sky or target is not None else "RGB",
                                   backend=backend)
        pred = out[0, ..., :3]
        gt = view.rgb().to(device)
        loss = (1.0 - lam) * (pred - gt).abs().mean() + lam * (1.0 - ssim(pred, gt))
        if use_sky:
            sky = view.sky.to(device)
            if sky.any():
                depth = out[0, ..., 3][sky]
                loss = loss + sky_w * F.relu(1.0 - depth / (0.5 * sky_radius)).mean()
        if target is not None:
            loss = loss + depth_w * depth_loss(out[0, ..., 3], target, depth_inv)
        solid = ~strat_state["is_sky"]
        if flat_w > 0:
            loss = loss + flat_w * flatten_loss(params["scales"], solid)
        if ratio_w > 0 and step % ratio_every == 0:
            loss = loss + ratio_w * shape_ratio_loss(params["scales"], ratio_max, solid)
        loss.backward()
        for o in optimizers.values():
            o.step()
            o.zero_grad(set_to_none=True)
        changed = strategy.step_post_backward(params, optimizers, strat_state, step, info, gen)
        for key, count in changed.items():
            densify[key] = densify.get(key, 0) + count
        del out, alphas, info, loss, pred
        step += 1
        if step in cps:
            save_ply(checkpoint_path(gs_dir, step), params)
            m = evaluate(params, views, eval_idx, max_deg, device, backend)
            metrics = [x for x in metrics if x["iteration"] != step]
            metrics.append({"iteration": step, **m, "num_gaussians": int(params["means"].shape[0]),
                            "seconds": round(elapsed(), 3),
                            "cpu_seconds": round(cpu_seconds(), 3), "peak_rss_mb": round(_peak_rss_mb(), 1)})
            if device.type == "cuda" and torch.cuda.is_available():
                metrics[-1]["peak_gpu_mb"] = round(torch.cuda.max_memory_allocated(device) / 2**20, 1)
            log.info("fit: %s iteration %d: PSNR %.2f dB, SSIM %.4f, %d Gaussians, %.1f s",
                     scene.scene_id, step, m["psnr"], m["ssim"], params["means"].shape[0], elapsed())
            save_state()
            write_summary(step >= total)
        elif step % state_every == 0:
            save_state()
        if progress is not None and (step % 10 == 0 or step == total):
            progress(step, total)

    doc = write_summary(True)
    if not bool(p["keep_state"]):
        state_path.unlink(missing_ok=True)
    return doc


# --------------------------------------------------------------------------- entry points

def run_stage(ctx) -> dict:
    """Stage entry (``stages/fit.yaml``): fit ``ctx.scene_dir`` with ``ctx.params``."""
    return fit_scene(ctx.scene_dir, ctx.params, log=getattr(ctx, "log", None),
                     progress=getattr(ctx, "progress", None))


@torch.no_grad()
def render_checkpoint(ply_path: str | os.PathLike | None, c2w, K, width: int, height: int, *,
                      render_depth: bool = False, params: Optional[Params] = None,
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
        out, alpha, _ = render(params, viewmats[i:i + 1], Kt[None], int(width), int(height),
                               sh_degree=deg, render_mode="RGB+ED" if render_depth else "RGB",
                               backend=backend)
        rgbs.append(out[0, ..., :3].clamp(0, 1).float().cpu().numpy())
        alphas.append(alpha[0, ..., 0].clamp(0, 1).float().cpu().numpy())
        if render_depth:
            depths.append(out[0, ..., 3].float().cpu().numpy())
    return {"rgb": np.stack(rgbs), "alpha": np.stack(alphas),
            "depth": np.stack(depths) if render_depth else None}
