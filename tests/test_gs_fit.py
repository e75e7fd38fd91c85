"""The fit stage: 3DGS training, checkpoints, exact resume, densification, initialisation."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from paradrive.gs import init as gsinit
from paradrive.gs.fit import fit_scene, initial_model, load_views, render_checkpoint
from paradrive.gs.model import logit, new_params, scene_scale_of
from paradrive.gs.ply import load_ply
from paradrive.gs.strategy import DensifyStrategy
from paradrive.metrics import psnr, ssim

REPO = Path(__file__).resolve().parents[1]

# A few iterations on a tiny scene exercise every mechanism (densify from step 4, opacity reset
# at 12) in seconds; quality is tested on the smoke profile.
TINY_FIT = {
    "checkpoints": [5, 10, 20], "threads": 1, "init_points": 1500, "sky_points": 300,
    "refine_start_iter": 3, "refine_every": 4, "refine_stop_iter": 17, "reset_every": 12,
    "sh_degree_interval": 6, "eval_views": 4, "state_interval": 3, "max_gaussians": 4000,
}


def stage_params(profile: str | None = None, **overrides) -> dict:
    from paradrive.pipeline.specs import StageRegistry

    return StageRegistry().resolve(profile, {"fit": overrides} if overrides else None).params["fit"]


def _copy_scene(src: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("gs"))
    return dst


# --------------------------------------------------------------------------- metrics

def test_psnr_and_ssim_of_identical_and_noisy_images():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(32, 40, 3, generator=g)
    assert float(ssim(a, a)) == pytest.approx(1.0, abs=1e-5)
    assert float(psnr(a, a)) == pytest.approx(100.0)
    b = (a + 0.1 * torch.randn(a.shape, generator=g)).clamp(0, 1)
    assert 15 < float(psnr(a, b)) < 25
    assert float(ssim(a, b)) < 0.95
    batch = torch.stack([a, b])
    assert psnr(batch, torch.stack([a, a])).shape == (2,)


# --------------------------------------------------------------------------- quality

def test_smoke_fit_psnr_rises_across_checkpoints_and_reaches_25db(smoke_scene):
    params = stage_params("smoke")
    scene_dir = smoke_scene["data_dir"] / "scenes" / smoke_scene["report"].results[0].scene_id
    doc = json.loads((scene_dir / "gs" / "fit.json").read_text())
    assert doc["complete"]
    its = [c["iteration"] for c in doc["checkpoints"]]
    assert its == sorted(params["checkpoints"])
    values = [c["psnr"] for c in doc["checkpoints"]]
    assert all(b > a for a, b in zip(values, values[1:])), values
    assert values[-1] >= 25.0, values
    for c in doc["checkpoints"]:
        assert (scene_dir / "gs" / f"ckpt_{c['iteration']:06d}.ply").is_file()
        assert c["num_gaussians"] > 0 and c["seconds"] > 0 and c["peak_rss_mb"] > 0


# --------------------------------------------------------------------------- outputs and resume

def _run_fit_process(scene_dir: Path, params: dict, tmp: Path) -> subprocess.Popen:
    cfg = tmp / f"params-{scene_dir.name}.json"
    cfg.write_text(json.dumps(params))
    code = ("import json, sys\nfrom paradrive.gs.fit import fit_scene\n"
            "fit_scene(sys.argv[1], json.load(open(sys.argv[2])))\n")
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.Popen([sys.executable, "-c", code, str(scene_dir), str(cfg)], cwd=REPO,
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)


def test_killed_fit_resumes_to_byte_identical_checkpoints(tiny_scene, tmp_path):
    params = stage_params("smoke", **TINY_FIT)
    ref = _copy_scene(tiny_scene, tmp_path / "ref")
    killed = _copy_scene(tiny_scene, tmp_path / "killed")

    proc = _run_fit_process(ref, params, tmp_path)
    out, _ = proc.communicate(timeout=600)
    assert proc.returncode == 0, out.decode()

    # kill -9 once the state after the first checkpoint is on disk, then start again
    proc = _run_fit_process(killed, params, tmp_path)
    gs = killed / "gs"
    first = gs / "ckpt_000005.ply"
    deadline = time.time() + 600
    while time.time() < deadline and proc.poll() is None:
        st = gs / "state.pt"
        if first.is_file() and st.is_file() and st.stat().st_mtime_ns >= first.stat().st_mtime_ns:
            break
        time.sleep(0.01)
    assert proc.poll() is None, "the fit finished before it could be killed"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL
    assert (gs / "state.pt").is_file() and first.is_file()
    kept = first.stat().st_mtime_ns
    assert not (gs / "ckpt_000020.ply").exists()

    proc = _run_fit_process(killed, params, tmp_path)
    out, _ = proc.communicate(timeout=600)
    assert proc.returncode == 0, out.decode()

    for it in params["checkpoints"]:
        name = f"ckpt_{it:06d}.ply"
        assert (ref / "gs" / name).read_bytes() == (killed / "gs" / name).read_bytes(), name
    assert first.stat().st_mtime_ns == kept, "a checkpoint written before the kill was rewritten"
    for d in (ref, killed):
        doc = json.loads((d / "gs" / "fit.json").read_text())
        assert doc["complete"] and [c["iteration"] for c in doc["checkpoints"]] == [5, 10, 20]
        assert not (d / "gs" / "state.pt").exists()            # keep_state: false
        assert not list((d / "gs").glob(".*tmp*"))
    a = json.loads((ref / "gs" / "fit.json").read_text())["checkpoints"]
    b = json.loads((killed / "gs" / "fit.json").read_text())["checkpoints"]
    assert [c["psnr"] for c in a] == [c["psnr"] for c in b]
    assert max(c["num_gaussians"] for c in a) <= TINY_FIT["max_gaussians"]

    # a completed fit is not redone
    before = (ref / "gs" / "fit.json").stat().st_mtime_ns
    fit_scene(ref, params)
    assert (ref / "gs" / "fit.json").stat().st_mtime_ns == before

    # the render stage's entry point renders a checkpoint
    scene = json.loads((ref / "scene.json").read_text())
    cam = scene["cameras"]["front"]
    K = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1]])
    c2w = np.array([np.array(f["cameras"]["front"]["c2w"]).reshape(4, 4) for f in scene["frames"][:2]])
    out = render_checkpoint(ref / "gs" / "ckpt_000020.ply", c2w, K, cam["width"], cam["height"],
                            render_depth=True)
    assert out["rgb"].shape == (2, cam["height"], cam["width"], 3)
    assert out["alpha"].shape == out["depth"].shape == (2, cam["height"], cam["width"])
    assert 0.0 <= out["rgb"].min() and out["rgb"].max() <= 1.0
    assert out["alpha"][:, :4].mean() > 0.8                    # the sky dome closes the background


# --------------------------------------------------------------------------- densification

def _toy(n: int = 6):
    means = torch.zeros(n, 3)
    means[:, 0] = torch.arange(n, dtype=torch.float32)
    params = new_params(means, torch.full((n, 3), 0.5), torch.full((n, 3), 0.05), opacity=0.5)
    params = {k: torch.nn.Parameter(v) for k, v in params.items()}
    opts = {k: torch.optim.Adam([v], lr=1e-3) for k, v in params.items()}
    return params, opts


def _info(n: int, grads: torch.Tensor) -> dict:
    m2d = torch.zeros(1, n, 2, requires_grad=True)
    m2d.grad = torch.stack([grads, torch.zeros(n)], -1)[None]
    return {"means2d": m2d, "radii": torch.ones(1, n, dtype=torch.int32), "width": 2, "height": 2,
            "n_cameras": 1}


def test_densification_grows_and_prunes():
    params, opts = _toy(6)
    with torch.no_grad():
        params["scales"][1] = np.log(2.0)              # large -> split
        params["opacities"][4] = float(logit(0.001))   # transparent -> pruned
    # one Adam step so moments exist for the remapping
    sum(p.sum() for p in params.values()).backward()
    for o in opts.values():
        o.step()
    strat = DensifyStrategy(refine_start_iter=0, refine_every=1, reset_every=10_000, grow_scale3d=0.1)
    state = strat.initialize_state(6, scene_scale=1.0, is_sky=torch.tensor([0, 0, 0, 0, 0, 1], dtype=torch.bool))
    grads = torch.tensor([1.0, 1.0, 0.0, 0.0, 0.0, 1.0])   # Gaussian 0 small, 1 large, 5 sky
    out = strat.step_post_backward(params, opts, state, 1, _info(6, grads), torch.Generator().manual_seed(0))
    assert out["duplicated"] == 1 and out["split"] == 1 and out["pruned"] == 1
    n = params["means"].shape[0]
    assert n == 6 + 1 + 1 - 1
    assert all(p.shape[0] == n for p in params.values())
    assert state["is_sky"].sum() == 1 and state["grad2d"].shape == (n,)
    # the split pair shrank by 1.6 and lies around the parent
    big = torch.exp(params["scales"].detach()).max(-1).values
    assert (big > 1.9).sum() == 0                              # the parent is gone
    assert torch.isclose(big, torch.tensor(2.0 / 1.6), atol=0.01).sum() == 2
    pair = params["means"].detach()[-2:]
    assert (pair - torch.tensor([1.0, 0.0, 0.0])).norm(dim=1).max() < 4 * 2.0
    for key, o in opts.items():
        assert o.param_groups[0]["params"][0] is params[key]
        assert o.state[params[key]]["exp_avg"].shape[0] == n


def test_max_gaussians_cap_holds_and_keeps_the_largest_gradients():
    params, opts = _toy(6)
    strat = DensifyStrategy(refine_start_iter=0, refine_every=1, reset_every=10_000, grow_scale3d=0.1,
                            max_gaussians=8)
    state = strat.initialize_state(6, scene_scale=1.0)
    grads = torch.tensor([1.0, 2.0, 3.0, 4.0, 0.0, 0.0])
    strat.step_post_backward(params, opts, state, 1, _info(6, grads), torch.Generator())
    assert params["means"].shape[0] == 8
    # the two copies are of Gaussians 3 and 2 (highest gradients)
    assert sorted(params["means"][6:, 0].tolist()) == [2.0, 3.0]
    strat.step_post_backward(params, opts, state, 2, _info(8, torch.ones(8)), torch.Generator())
    assert params["means"].shape[0] == 8


def test_opacity_reset_spares_the_sky():
    params, opts = _toy(3)
    strat = DensifyStrategy(refine_start_iter=100, reset_every=5)
    state = strat.initialize_state(3, 1.0, torch.tensor([False, False, True]))
    strat.step_post_backward(params, opts, state, 5, _info(3, torch.zeros(3)), torch.Generator())
    op = torch.sigmoid(params["opacities"].detach())
    assert torch.allclose(op[:2], torch.tensor(0.01), atol=1e-6) and op[2] == pytest.approx(0.5)


# --------------------------------------------------------------------------- initialisation

def test_lidar_init_filters_points_and_colours_them_from_images(tiny_scene):
    from paradrive.scene import load_scene

    scene = load_scene(tiny_scene)
    views = load_views(scene, None, 1)
    p = stage_params("smoke", **{**TINY_FIT, "init": "lidar", "init_points": 800})
    raw, is_sky, desc = initial_model(scene, views, p, scene_scale_of(scene.c2w("front")),
                                      __import__("logging").getLogger("test"))
    assert desc["method"] == "lidar" and desc["points"] == 800
    assert int(is_sky.sum()) == p["sky_points"]
    assert raw["means"].shape[0] == 800 + p["sky_points"]
    rgb = raw["sh0"][:800, 0] * 0.28209479177387814 + 0.5
    assert (rgb - 0.5).abs().max() > 0.1                       # coloured from the images
    assert torch.isfinite(raw["scales"]).all() and raw["shN"].shape[1:] == (15, 3)


def test_lidar_free_init_lands_near_the_surfaces(tiny_scene):
    from paradrive.scene import load_scene

    scene = load_scene(tiny_scene)
    views = load_views(scene, None, 1)
    lidar = torch.from_numpy(scene.lidar_points())
    gen = lambda: torch.Generator().manual_seed(3)  # noqa: E731
    swept, rgb = gsinit.frustum_points_init(views, n_points=1200, depth_min=2, depth_max=80, generator=gen())
    rand, _ = gsinit.frustum_points_init(views, n_points=1200, depth_min=2, depth_max=80,
                                         generator=gen(), neighbours=0)
    assert swept.shape == (1200, 3) and rgb.shape == (1200, 3)

    def on_surface(pts):  # share of points within 0.3 m of a LiDAR return
        return float((torch.cdist(pts, lidar).min(1).values < 0.3).float().mean())

    assert on_surface(swept) > 1.5 * on_surface(rand), (on_surface(swept), on_surface(rand))
    # nothing behind the cameras
    for v in views[:2]:
        pc = (torch.linalg.inv(v.c2w).float()[:3, :3] @ swept.T).T
        assert pc.shape[0] == 1200


def test_lidar_free_fit_runs_when_the_scene_has_no_lidar(tiny_scene, tmp_path):
    import shutil

    scene_dir = _copy_scene(tiny_scene, tmp_path / "nolidar")
    shutil.rmtree(scene_dir / "lidar", ignore_errors=True)
    params = stage_params("smoke", **{**TINY_FIT, "checkpoints": [4, 8], "init": "auto"})
    doc = fit_scene(scene_dir, params)
    assert doc["init"]["method"] == "frustum"
    assert [c["iteration"] for c in doc["checkpoints"]] == [4, 8]
    assert doc["checkpoints"][-1]["psnr"] > 10
    q = load_ply(scene_dir / "gs" / "ckpt_000008.ply")
    assert q["means"].shape[0] == doc["checkpoints"][-1]["num_gaussians"]
