"""The fit's geometry: LiDAR depth supervision, the flattening and sharp-shape regularisers and
the road prior of the LiDAR-free init each move the fitted geometry towards the synthetic
street's true depth (the ray caster's, an independent truth)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from paradrive.gs import init as gsinit
from paradrive.stages.fit import fit_scene
from paradrive.gs.fit import lidar_depth_targets, load_views
from paradrive.gs.losses import (DepthTarget, depth_loss, flatten_loss, lidar_depth_target,
                                 shape_ratio_loss)
from paradrive.gs.ply import load_ply
from paradrive.scene import load_scene

# Short fits without densification: what differs between two runs is the term under test.
SHORT_FIT = {"checkpoints": [60], "threads": 1, "init_points": 2000, "sky_points": 300,
             "init_opacity": 0.9, "lr_means": 5e-3, "lr_means_final": 5e-3,
             "refine_start_iter": 10_000, "eval_views": 2, "state_interval": 10_000,
             "depth_weight": 0.0, "flatten_weight": 0.0, "shape_ratio_weight": 0.0}


def fit_params(**overrides) -> dict:
    from paradrive.contracts.specs import StageRegistry

    return StageRegistry().resolve("smoke", {"fit": {**SHORT_FIT, **overrides}}).typed("fit")


@pytest.fixture(scope="module")
def street_scene(tmp_path_factory):
    """Synthetic street, 10 frames of 96x64, with LiDAR and sky masks, and the street itself
    (the truth)."""
    from conftest import ingest_synthetic

    from paradrive.ingest.synthetic import street_from_uri
    from paradrive.pipeline import StageRegistry
    from paradrive.uri import parse_uri

    scene_dir = ingest_synthetic(tmp_path_factory.mktemp("street"), 10, 96, 64)
    config = StageRegistry().resolve("smoke", {"ingest": {
        "synthetic_frames": 10, "synthetic_width": 96, "synthetic_height": 64}})
    street = street_from_uri(parse_uri("synthetic:demo?seed=7"), config.typed("ingest"))
    return {"dir": scene_dir, "street": street}


def _true_depth(street, view) -> torch.Tensor:
    """(H, W) z-depth of the street seen from a training view (inf for sky)."""
    truth = street.render(view.c2w.numpy()[None], view.K.double().numpy(), view.width, view.height,
                          frames=view.frame)
    return torch.from_numpy(truth["depth"][0])


# each geometry term alone, strong enough to show within a short fit
TERMS = {"none": {}, "depth": {"depth_weight": 1.0, "depth_inverse": True},
         "flatten": {"flatten_weight": 10.0},
         "ratio": {"shape_ratio_weight": 1.0, "shape_ratio_every": 1, "shape_ratio_max": 1.1}}


@pytest.fixture(scope="module")
def fitted(street_scene, tmp_path_factory):
    """fitted(name): the final PLY of the same short fit with the geometry term ``name`` alone
    (``TERMS``), made once per module."""
    import shutil

    cache = {}

    def get(name: str):
        if name not in cache:
            d = tmp_path_factory.mktemp(f"fit_{name}") / "scene"
            shutil.copytree(street_scene["dir"], d)
            p = fit_params(**TERMS[name])
            fit_scene(d, p)
            cache[name] = load_ply(d / "gs" / f"ckpt_{p.checkpoints[-1]:06d}.ply")
        return cache[name]

    return get


def _signed_depth_error(params, street_scene) -> float:
    """Median (d - d_true) / d_true of the surfaces (the sky dome left out: a short fit's
    surfaces are still translucent) over non-sky pixels of every training view."""
    from paradrive.gs.fit import render_checkpoint

    solid = params["means"].norm(dim=1) < 500
    params = {k: v[solid] for k, v in params.items()}
    scene = load_scene(street_scene["dir"])
    errs = []
    for v in load_views(scene, None, 1):
        out = render_checkpoint(None, v.c2w.numpy(), v.K.numpy(), v.width, v.height,
                                render_depth=True, params=params, device="cpu")
        truth = _true_depth(street_scene["street"], v)
        ok = torch.isfinite(truth)
        pred = torch.from_numpy(out["depth"][0])
        errs.append(((pred - truth) / truth)[ok])
    return float(torch.cat(errs).median())


def _solid_scales(params) -> torch.Tensor:
    """Sorted standard deviations (N, 3) of the Gaussians that are not the sky dome."""
    s = torch.exp(params["scales"]).sort(dim=-1).values
    return s[params["means"].norm(dim=1) < 500]


# --------------------------------------------------------------------------- LiDAR depth targets

def test_lidar_target_keeps_the_nearest_return_per_pixel_and_no_sky():
    K = torch.tensor([[10.0, 0, 4], [0, 10.0, 4], [0, 0, 1]])
    sky = torch.zeros(8, 8, dtype=torch.bool)
    sky[0, :] = True
    view = gsinit.View(image=torch.zeros(8, 8, 3, dtype=torch.uint8), sky=sky, K=K,
                       c2w=torch.eye(4, dtype=torch.float64), camera="front", frame=0)
    pts = np.array([[0.0, 0.0, 10.0],    # pixel (4, 4), behind the next one
                    [0.0, 0.0, 5.0],     # pixel (4, 4), nearest: kept
                    [1.0, 0.0, 10.0],    # pixel (5, 4)
                    [0.0, -3.8, 10.0],   # pixel (4, 0): sky row, dropped
                    [0.0, 0.0, -5.0]],   # behind the camera
                   np.float32)
    t = lidar_depth_target(pts, view)
    assert sorted(zip(t.pixels.tolist(), t.depth.tolist())) == [(36, 5.0), (37, 10.0)]


def test_lidar_targets_agree_with_the_true_depth(street_scene):
    scene = load_scene(street_scene["dir"])
    views = load_views(scene, None, 1)
    targets = lidar_depth_targets(scene, views, torch.device("cpu"))
    assert len(targets) == len(views) and all(t is not None for t in targets)
    for v, t in zip(views[::3], targets[::3]):
        assert len(t.pixels) > 0.05 * v.width * v.height
        truth = _true_depth(street_scene["street"], v).reshape(-1)[t.pixels]
        rel = (t.depth - truth) / truth
        # the roof LiDAR sees a little the camera does not (parallax at edges): the median agrees
        assert float(rel.abs().median()) < 0.02, float(rel.abs().median())


# --------------------------------------------------------------------------- fit terms

def test_geometry_terms_on_known_values():
    depth = torch.tensor([[10.0, 4.0], [2.0, 8.0]])
    target = DepthTarget(pixels=torch.tensor([0, 3]), depth=torch.tensor([5.0, 8.0]))
    assert float(depth_loss(depth, target, inverse=False)) == pytest.approx((5.0 + 0.0) / 2)
    assert float(depth_loss(depth, target, inverse=True)) == pytest.approx((0.2 - 0.1) / 2)
    log_s = torch.log(torch.tensor([[0.1, 0.5, 2.0], [0.3, 0.3, 0.3], [1.0, 1.0, 50.0]]))
    solid = torch.tensor([True, True, False])
    assert float(flatten_loss(log_s, solid)) == pytest.approx((0.1 + 0.3) / 2)
    # axis ratios 20, 1 (and 50, not counted): only the first is over 10
    assert float(shape_ratio_loss(log_s, 10.0, solid)) == pytest.approx((20.0 - 10.0) / 2, rel=1e-5)



def test_depth_supervision_brings_the_rendered_depth_to_the_truth(fitted, street_scene):
    off = _signed_depth_error(fitted("none"), street_scene)
    on = _signed_depth_error(fitted("depth"), street_scene)
    assert abs(on) < 0.7 * abs(off), (on, off)


def test_flattening_shrinks_the_smallest_axis(fitted):
    off = float(_solid_scales(fitted("none"))[:, 0].median())
    on = float(_solid_scales(fitted("flatten"))[:, 0].median())
    assert on < 0.85 * off, (on, off)


def test_sharp_shape_term_bounds_the_axis_ratio(fitted):
    def over(params):  # share of Gaussians more elongated than the ratio the term allows
        s = _solid_scales(params)
        return float((s[:, 2] / s[:, 0] > TERMS["ratio"]["shape_ratio_max"]).float().mean())

    assert over(fitted("ratio")) < 0.5 * over(fitted("none")), (over(fitted("ratio")),
                                                                 over(fitted("none")))


# --------------------------------------------------------------------------- LiDAR-free init

def test_road_prior_puts_init_points_at_their_true_depth(street_scene):
    scene = load_scene(street_scene["dir"])
    views = load_views(scene, None, 1)
    n = 1500
    per_view = -(-n // len(views))

    def relative_errors(margin):
        pts, _ = gsinit.frustum_points_init(views, n_points=n, depth_min=2, depth_max=80,
                                            generator=torch.Generator().manual_seed(0),
                                            ground_margin=margin)
        errs = []
        for k, v in enumerate(views):   # points come view by view, per_view each
            uv, z, ok = gsinit.project(pts[k * per_view:(k + 1) * per_view], v)
            assert ok.all()               # in front of their own camera, inside its frame
            truth = _true_depth(street_scene["street"], v)
            t = truth[uv[:, 1].long().clamp(0, v.height - 1), uv[:, 0].long().clamp(0, v.width - 1)]
            errs.append(((z - t) / t)[torch.isfinite(t)])
        return torch.cat(errs)

    plain = relative_errors(None)
    prior = relative_errors(fit_params().init_ground_margin)
    assert float(prior.abs().median()) < 0.5 * float(plain.abs().median())
    def close(errs):  # share within 10 % of the true depth
        return float((errs.abs() < 0.1).float().mean())

    assert close(prior) > 1.5 * close(plain)
    # fewer floaters well in front of the surfaces
    assert float((prior < -0.3).float().mean()) < float((plain < -0.3).float().mean())
