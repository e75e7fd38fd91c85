"""The fit and render on a GPU at the paper's resolution, and what a scene costs in GPU-hours.

    .venv/bin/python bench/bench_gpu.py [--iterations 2000] [--frames 40] [--device cuda]

DriveStudio (which the paper keeps) fits Waymo's three front cameras at half resolution,
960x640. This ingests the synthetic street's three front cameras at that size, fits with the
paper's fit parameters (stages/fit.yaml) for ``--iterations`` (past the start of densification
at 500), and renders frames at the 480x832 output size. It reports fit iterations per second
before and after densification starts, render frames per second, and the projection for one
paper scene: 30,000 iterations plus (3 under-fitted checkpoints + 8 offsets) x 3 clips x 121
frames of renders, next to the paper's 8,240 GPU-hours for ~1.6K scenes (about 5.15 per scene,
on L20s). Baseline in the same run: the torch rasterizer on the same device.

Without CUDA it prints why and exits 0 (``--device cpu`` runs the same code on the CPU, small).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

PAPER_GPU_HOURS_PER_SCENE = 8240 / 1600
RENDERED_FRAMES_PER_SCENE = (3 + 8) * 3 * 121


def _ingest(root: Path, frames: int, width: int, height: int, profile: str | None = None) -> Path:
    from paradrive.pipeline import StageRegistry, run_build

    config = StageRegistry().resolve(profile, {"ingest": {
        "synthetic_frames": frames, "synthetic_width": width, "synthetic_height": height,
        "cameras": ["front", "front_left", "front_right"]}})
    report = run_build(config, ["synthetic:demo?seed=7"], root / "data", stages=["ingest"],
                       manifests_dir=root / "manifests", build="gpu")
    if report.failures():
        raise RuntimeError([r.error for r in report.failures()])
    (scene_dir,) = (root / "data" / "scenes").iterdir()
    return scene_dir


def _fit_rate(scene_dir: Path, device: str, backend: str, checkpoints: list[int], profile: str | None = None) -> dict:
    import shutil

    from paradrive.stages.fit import fit_scene
    from paradrive.pipeline import StageRegistry

    shutil.rmtree(scene_dir / "gs", ignore_errors=True)
    params = StageRegistry().resolve(profile, {"fit": {"checkpoints": checkpoints, "device": device, "backend": backend,
                                                    "eval_views": 1, "keep_state": False}}).typed("fit")
    doc = fit_scene(scene_dir, params).model_dump()
    marks = doc["checkpoints"]
    rates = []
    for a, b in zip([{"iteration": 0, "seconds": 0.0}] + marks, marks):
        rates.append({"iterations": [a["iteration"], b["iteration"]],
                      "iterations_per_second": round((b["iteration"] - a["iteration"])
                                                     / max(b["seconds"] - a["seconds"], 1e-9), 2),
                      "gaussians_at_end": b["num_gaussians"]})
    return {"backend": backend, "resolution": doc["resolution"], "views": doc["n_views"],
            "phases": rates, "psnr": round(marks[-1]["psnr"], 2),
            "peak_gpu_mb": marks[-1].get("peak_gpu_mb")}


def _render_rate(scene_dir: Path, device: str, frames: int) -> float:
    import numpy as np
    import torch

    from paradrive.gs.views import load_checkpoint, render_views
    from paradrive.scene import load_scene

    scene = load_scene(scene_dir)
    ckpt = sorted((scene_dir / "gs").glob("ckpt_*.ply"))[-1]
    params = load_checkpoint(ckpt)
    c2w = scene.c2w("front")[:frames]
    K = np.array([[800.0, 0, 416], [0, 800.0, 240], [0, 0, 1]])
    list(render_views(params, c2w[:2], K, 832, 480, device=device))   # warm-up
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    for _ in render_views(params, c2w, K, 832, 480, depth=True, batch_frames=8, device=device):
        pass
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    return len(c2w) / (time.perf_counter() - t0)


def main() -> None:
    import torch

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--iterations", type=int, default=2000)
    ap.add_argument("--baseline-iterations", type=int, default=100)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--width", type=int, default=960)
    ap.add_argument("--height", type=int, default=640)
    ap.add_argument("--profile", default=None, help="stage profile of the ingest and fit (default: the paper's)")
    args = ap.parse_args()
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        print(json.dumps({"bench": "gpu", "skipped": "torch sees no CUDA GPU on this machine"}))
        return
    with tempfile.TemporaryDirectory() as tmp:
        scene_dir = _ingest(Path(tmp), args.frames, args.width, args.height, args.profile)
        marks = sorted({min(500, args.iterations), args.iterations})
        fast = _fit_rate(scene_dir, args.device, "auto", marks, args.profile)
        fps = _render_rate(scene_dir, args.device, args.frames)
        base = _fit_rate(scene_dir, args.device, "torch", [args.baseline_iterations], args.profile)
    late = fast["phases"][-1]["iterations_per_second"]
    fit_hours = 30000 / late / 3600
    render_hours = RENDERED_FRAMES_PER_SCENE / fps / 3600
    out = {
        "bench": "gpu", "device": torch.cuda.get_device_name() if args.device.startswith("cuda")
        else args.device, "torch": torch.__version__, "fit": fast, "baseline_torch_rasterizer": base,
        "speedup_vs_torch_rasterizer": round(late / base["phases"][-1]["iterations_per_second"], 2),
        "render_frames_per_second_832x480": round(fps, 2),
        "projected_gpu_hours_per_scene": {"fit_30k": round(fit_hours, 3),
                                          "render": round(render_hours, 3),
                                          "total": round(fit_hours + render_hours, 3),
                                          "paper": round(PAPER_GPU_HOURS_PER_SCENE, 2)},
        "note": "the late-phase rate is held for all 30K iterations; Gaussians keep growing until "
                "refine_stop_iter (15K), so the projection is a lower bound",
    }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
