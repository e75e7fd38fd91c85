"""The Gaussian rasterizer: images and gradients against two independent references.

References:
- gsplat's pure-torch reference functions (projection, SH, tile intersection, tile compositing)
  assembled into a pipeline. Its compositor asks two helpers that only exist as CUDA / nerfacc
  code, so small torch stand-ins for them are provided here.
- a brute-force compositor: every visible Gaussian at every pixel, in depth order, one at a time.
"""

from __future__ import annotations

import math
import sys
import types

import gsplat.cuda._torch_impl as gsplat_ref   # the oracle: part of the test extras, never skipped
import pytest
import torch

from paradrive.gs.rasterize import rasterize
from paradrive.gs.sh import eval_sh

W, H = 70, 45  # not multiples of the 16-pixel tile


# ---------------------------------------------------------------- scenes

def make_cameras(n_cams=2, width=W, height=H, dtype=torch.float32):
    viewmats, Ks = [], []
    for i in range(n_cams):
        ang = 0.15 * i
        R = torch.tensor([[math.cos(ang), 0.0, -math.sin(ang)],
                          [0.0, 1.0, 0.0],
                          [math.sin(ang), 0.0, math.cos(ang)]], dtype=torch.float64)
        t = torch.tensor([0.2 * i, -0.1 * i, 0.3 * i], dtype=torch.float64)
        V = torch.eye(4, dtype=torch.float64)
        V[:3, :3], V[:3, 3] = R, t
        viewmats.append(V)
        f = 0.9 * width
        Ks.append(torch.tensor([[f, 0, width / 2 + 1.3 * i], [0, f, height / 2 - 0.7 * i], [0, 0, 1]],
                               dtype=torch.float64))
    return torch.stack(viewmats).to(dtype), torch.stack(Ks).to(dtype)


def make_scene(n=200, seed=0, sh_k=None, dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    z = 2.0 + 6.0 * torch.rand(n, generator=g)
    xy = (torch.rand(n, 2, generator=g) - 0.5) * z[:, None] * torch.tensor([0.9, 0.6])
    means = torch.cat([xy, z[:, None]], 1)
    quats = torch.randn(n, 4, generator=g) * 2.0  # not normalised on purpose
    scales = torch.exp(torch.empty(n, 3).uniform_(math.log(0.02), math.log(0.35), generator=g))
    opac = torch.rand(n, generator=g) * 0.98 + 0.01
    if sh_k is None:
        colors = torch.rand(n, 3, generator=g)
    else:
        colors = torch.randn(n, sh_k, 3, generator=g) * 0.3
        colors[:, 0] += 0.5
    return [t.to(dtype) for t in (means, quats, scales, opac, colors)]


# ---------------------------------------------------------------- reference 1: gsplat pipeline

def _indices_in_range(range_start, range_end, transmittances, means2d, conics, opacities,
                      image_width, image_height, tile_size, isect_offsets, flatten_ids):
    """Torch stand-in for gsplat's CUDA `rasterize_to_indices_in_range` (same rules)."""
    I, th, tw = isect_offsets.shape
    N = means2d.shape[-2]
    P = tile_size * tile_size
    n_isects = flatten_ids.numel()
    offs = torch.cat([isect_offsets.flatten().long(), torch.tensor([n_isects])])
    e = torch.arange(n_isects)
    tile = torch.searchsorted(offs, e, right=True) - 1
    pos = e - offs[tile]
    sel = (pos >= range_start * P) & (pos < range_end * P)
    e, tile = e[sel], tile[sel]
    fid = flatten_ids[e].long()
    img = tile // (th * tw)
    t_in = tile % (th * tw)
    p = torch.arange(P)
    px = (t_in % tw)[:, None] * tile_size + (p % tile_size)[None]
    py = (t_in // tw)[:, None] * tile_size + (p // tile_size)[None]
    m = means2d.detach().reshape(-1, 2)[fid]
    c = conics.detach().reshape(-1, 3)[fid]
    o = opacities.detach().reshape(-1)[fid]
    dx = px + 0.5 - m[:, :1]
    dy = py + 0.5 - m[:, 1:]
    sigma = 0.5 * (c[:, :1] * dx * dx + c[:, 2:] * dy * dy) + c[:, 1:2] * dx * dy
    alpha = torch.clamp_max(o[:, None] * torch.exp(-sigma), 0.999)
    ok = (sigma >= 0) & (alpha >= 1.0 / 255.0) & (px < image_width) & (py < image_height)
    img_e = img[:, None].expand_as(px)
    pix = (py * image_width + px)
    ray = (img_e * image_height * image_width + pix)[ok]
    alpha, gid, img_e, pix = alpha[ok], fid[:, None].expand_as(px)[ok], img_e[ok], pix[ok]
    # group by ray; a stable sort keeps the per-tile depth order inside a ray
    order = torch.sort(ray, stable=True).indices
    ray, alpha, gid, img_e, pix = ray[order], alpha[order], gid[order], img_e[order], pix[order]
    logs = torch.log1p(-alpha.double())
    csum = torch.cumsum(logs, 0)
    first = torch.ones_like(ray, dtype=torch.bool)
    first[1:] = ray[1:] != ray[:-1]
    seg = torch.cumsum(first.long(), 0) - 1
    base = (csum - logs)[first][seg]
    t0 = transmittances.detach().reshape(-1)[ray].double()
    keep = t0 * torch.exp(csum - base) > 1e-4
    return (gid[keep] % N).int(), pix[keep].int(), img_e[keep].int()


def _render_weight_from_alpha(alphas, ray_indices, n_rays):
    logs = torch.log1p(-alphas.double())
    csum = torch.cumsum(logs, 0)
    first = torch.ones_like(ray_indices, dtype=torch.bool)
    first[1:] = ray_indices[1:] != ray_indices[:-1]
    seg = torch.cumsum(first.long(), 0) - 1
    excl = csum - logs
    trans = torch.exp(excl - excl[first][seg]).to(alphas.dtype)
    return alphas * trans, trans


def _accumulate_along_rays(weights, values, ray_indices, n_rays):
    src = weights[:, None] if values is None else weights[:, None] * values
    out = torch.zeros(n_rays, src.shape[1], dtype=src.dtype)
    return out.index_add(0, ray_indices.long(), src)


def install_cpu_stand_ins(setitem=None, setattr_=None):
    """Route gsplat's reference compositor to the torch stand-ins above (used by the bench too)."""
    import gsplat.cuda._wrapper as wrapper

    fake = types.ModuleType("nerfacc")
    fake.render_weight_from_alpha = _render_weight_from_alpha
    fake.accumulate_along_rays = _accumulate_along_rays
    if setitem is None:
        sys.modules["nerfacc"] = fake
        wrapper.rasterize_to_indices_in_range = _indices_in_range
    else:
        setitem(sys.modules, "nerfacc", fake)
        setattr_(wrapper, "rasterize_to_indices_in_range", _indices_in_range)


@pytest.fixture
def gsplat_reference(monkeypatch):
    install_cpu_stand_ins(monkeypatch.setitem, monkeypatch.setattr)
    return reference_rasterize


def reference_rasterize(means, quats, scales, opacities, colors, viewmats, Ks, width, height,
                        sh_degree=None, backgrounds=None, render_mode="RGB", tile_size=16):
    C, N = viewmats.shape[0], means.shape[0]
    covars, _ = gsplat_ref._quat_scale_to_covar_preci(quats, scales, compute_preci=False)
    radii, means2d, depths, conics, _ = gsplat_ref._fully_fused_projection(
        means, covars, viewmats, Ks, width, height)
    if sh_degree is not None:
        campos = torch.inverse(viewmats)[:, :3, 3]
        dirs = means[None] - campos[:, None]
        colors = torch.clamp_min(
            gsplat_ref._spherical_harmonics(sh_degree, dirs, colors.expand((C,) + colors.shape)) + 0.5, 0)
    else:
        colors = colors.expand(C, N, colors.shape[-1])
    if render_mode == "RGB+ED":
        colors = torch.cat([colors, depths[..., None]], -1)
        if backgrounds is not None:
            backgrounds = torch.cat([backgrounds, backgrounds.new_zeros(C, 1)], -1)
    tw, th = math.ceil(width / tile_size), math.ceil(height / tile_size)
    _, isect_ids, flatten_ids = gsplat_ref._isect_tiles(means2d, radii, depths, tile_size, tw, th)
    offsets = gsplat_ref._isect_offset_encode(isect_ids, C, tw, th)
    renders, alphas = gsplat_ref._rasterize_to_pixels(
        means2d, conics, colors, opacities.expand(C, N), width, height, tile_size, offsets,
        flatten_ids, backgrounds=backgrounds)
    if render_mode == "RGB+ED":
        renders = torch.cat([renders[..., :-1], renders[..., -1:] / alphas.clamp(min=1e-10)], -1)
    return renders, alphas, {"means2d": means2d, "radii": radii}


# ---------------------------------------------------------------- reference 2: brute force

def brute_force_rasterize(means, quats, scales, opacities, colors, viewmats, Ks, width, height,
                          backgrounds=None):
    """Every visible Gaussian at every pixel, composited one at a time in depth order."""
    C = viewmats.shape[0]
    covars, _ = gsplat_ref._quat_scale_to_covar_preci(quats, scales, compute_preci=False)
    radii, means2d, depths, conics, _ = gsplat_ref._fully_fused_projection(
        means, covars, viewmats, Ks, width, height)
    ys, xs = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    px, py = xs.reshape(-1) + 0.5, ys.reshape(-1) + 0.5
    out = []
    alpha_out = []
    for c in range(C):
        vis = torch.nonzero((radii[c] > 0).all(-1)).squeeze(1)
        order = vis[torch.argsort(depths[c, vis])]
        T = torch.ones(px.shape[0])
        done = torch.zeros(px.shape[0], dtype=torch.bool)
        rgb = torch.zeros(px.shape[0], colors.shape[-1])
        for i in order.tolist():
            dx, dy = px - means2d[c, i, 0], py - means2d[c, i, 1]
            a, b, cc = conics[c, i]
            sigma = 0.5 * (a * dx * dx + cc * dy * dy) + b * dx * dy
            alpha = torch.clamp_max(opacities[i] * torch.exp(-sigma), 0.999)
            live = (alpha >= 1 / 255) & (sigma >= 0) & ~done
            next_T = T * (1 - alpha)
            stop = live & (next_T <= 1e-4)
            use = live & ~stop
            done = done | stop
            rgb = rgb + torch.where(use, alpha * T, 0.0)[:, None] * colors[i]
            T = torch.where(use, next_T, T)
        if backgrounds is not None:
            rgb = rgb + T[:, None] * backgrounds[c]
        out.append(rgb.reshape(height, width, -1))
        alpha_out.append((1 - T).reshape(height, width, 1))
    return torch.stack(out), torch.stack(alpha_out)


# ---------------------------------------------------------------- helpers

def _leaves(tensors):
    return [t.detach().clone().requires_grad_(True) for t in tensors]


def _grads(fn, scene, cams, weights, **kw):
    leaves = _leaves(scene)
    renders, alphas, *_ = fn(*leaves, *cams, W, H, **kw)
    loss = (renders * weights[0]).sum() + (alphas * weights[1]).sum()
    loss.backward()
    return renders.detach(), alphas.detach(), [t.grad for t in leaves]


def _loss_weights(channels, C=2, seed=1):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(C, H, W, channels, generator=g), torch.randn(C, H, W, 1, generator=g)


def assert_grads_close(ours, ref, names=("means", "quats", "scales", "opacities", "colors")):
    for name, a, b in zip(names, ours, ref):
        scale = b.abs().max().item() + 1e-6
        err = (a - b).abs().max().item()
        assert err <= 2e-4 * scale + 1e-5, f"grad {name}: max err {err:.3g} (ref max {scale:.3g})"


# ---------------------------------------------------------------- tests

def test_matches_gsplat_reference_images_and_gradients(gsplat_reference):
    scene = make_scene()
    cams = make_cameras()
    w = _loss_weights(3)
    r, a, g = _grads(lambda *x, **k: rasterize(*x, backend="torch", **k), scene, cams, w)
    r_ref, a_ref, g_ref = _grads(gsplat_reference, scene, cams, w)
    assert r.shape == (2, H, W, 3) and a.shape == (2, H, W, 1)
    assert a.max() > 0.5  # the scene is not empty
    torch.testing.assert_close(r, r_ref, atol=1e-4, rtol=0)
    torch.testing.assert_close(a, a_ref, atol=1e-4, rtol=0)
    assert_grads_close(g, g_ref)


def test_matches_brute_force_compositor():
    scene = make_scene(seed=3)
    cams = make_cameras()
    bg = torch.tensor([[0.2, 0.5, 0.9], [1.0, 0.0, 0.3]])
    w = _loss_weights(3, seed=4)
    r, a, g = _grads(lambda *x, **k: rasterize(*x, backgrounds=bg, backend="torch", **k), scene, cams, w)
    r_bf, a_bf, g_bf = _grads(lambda *x, **k: brute_force_rasterize(*x, backgrounds=bg, **k),
                              scene, cams, w)
    torch.testing.assert_close(r, r_bf, atol=1e-4, rtol=0)
    torch.testing.assert_close(a, a_bf, atol=1e-4, rtol=0)
    assert_grads_close(g, g_bf)


def test_opaque_scene_terminates_early_like_reference(gsplat_reference):
    means, quats, scales, opac, colors = make_scene(n=400, seed=5)
    opac = torch.where(opac > 0.5, 1.0, 0.97)  # hits the 0.999 alpha clamp and saturates pixels
    scales = scales * 5.0
    cams = make_cameras()
    w = _loss_weights(3, seed=6)
    scene = [means, quats, scales, opac, colors]
    r, a, g = _grads(lambda *x, **k: rasterize(*x, backend="torch", **k), scene, cams, w)
    r_ref, a_ref, g_ref = _grads(gsplat_reference, scene, cams, w)
    assert (a > 0.999).float().mean() > 0.3
    torch.testing.assert_close(r, r_ref, atol=1e-4, rtol=0)
    assert_grads_close(g, g_ref)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_spherical_harmonics_degrees_match_reference(gsplat_reference, degree):
    scene = make_scene(n=120, seed=10 + degree, sh_k=16)  # K=16 coefficients, lower degrees used
    cams = make_cameras()
    w = _loss_weights(3, seed=20 + degree)
    r, a, g = _grads(lambda *x, **k: rasterize(*x, sh_degree=degree, backend="torch", **k),
                     scene, cams, w)
    r_ref, a_ref, g_ref = _grads(lambda *x, **k: gsplat_reference(*x, sh_degree=degree, **k),
                                 scene, cams, w)
    torch.testing.assert_close(r, r_ref, atol=1e-4, rtol=0)
    assert_grads_close(g, g_ref)
    if degree < 3:
        assert g[4][:, (degree + 1) ** 2:].abs().max() == 0  # unused bands get no gradient


def test_eval_sh_matches_reference_bases():
    g = torch.Generator().manual_seed(0)
    dirs = torch.randn(500, 3, generator=g, dtype=torch.float64)
    coeffs = torch.randn(500, 16, 3, generator=g, dtype=torch.float64)
    for degree in range(4):
        ours = eval_sh(degree, coeffs, dirs)
        ref = gsplat_ref._spherical_harmonics(degree, dirs, coeffs)
        torch.testing.assert_close(ours, ref, atol=1e-10, rtol=1e-10)


def test_background_fills_uncovered_pixels_and_gets_gradient(gsplat_reference):
    scene = make_scene(n=60, seed=7)
    cams = make_cameras()
    bg = torch.tensor([[0.1, 0.2, 0.3], [0.9, 0.8, 0.7]], requires_grad=True)
    r, a, _ = rasterize(*scene, *cams, W, H, backgrounds=bg, backend="torch")
    r_ref, a_ref, _ = gsplat_reference(*scene, *cams, W, H, backgrounds=bg.detach())
    torch.testing.assert_close(r, r_ref, atol=1e-4, rtol=0)
    r.sum().backward()
    expected = (1 - a.detach()).sum(dim=(1, 2)).expand(2, 3)
    torch.testing.assert_close(bg.grad, expected, atol=1e-3, rtol=1e-5)


def test_rgb_plus_expected_depth_matches_reference(gsplat_reference):
    scene = make_scene(seed=8)
    cams = make_cameras()
    bg = torch.tensor([[0.3, 0.3, 0.3], [0.0, 0.0, 1.0]])
    w = _loss_weights(4, seed=9)
    kw = dict(render_mode="RGB+ED", backgrounds=bg)
    r, a, g = _grads(lambda *x, **k: rasterize(*x, backend="torch", **kw, **k), scene, cams, w)
    r_ref, a_ref, g_ref = _grads(lambda *x, **k: gsplat_reference(*x, **kw, **k), scene, cams, w)
    assert r.shape == (2, H, W, 4)
    covered = a[..., 0] > 0.05
    torch.testing.assert_close(r[..., :3], r_ref[..., :3], atol=1e-4, rtol=0)
    torch.testing.assert_close(r[..., 3][covered], r_ref[..., 3][covered], atol=1e-3, rtol=1e-4)
    depth = r[..., 3][a[..., 0] > 0.5]
    assert depth.min() > 1.5 and depth.max() < 9.0  # scene z is in [2, 8]
    assert_grads_close(g, g_ref)


def test_depth_only_modes():
    scene = make_scene(seed=11)
    cams = make_cameras()
    rgbed, a, _ = rasterize(*scene, *cams, W, H, render_mode="RGB+ED", backend="torch")
    ed, a2, _ = rasterize(*scene, *cams, W, H, render_mode="ED", backend="torch")
    d, _, _ = rasterize(*scene, *cams, W, H, render_mode="D", backend="torch")
    assert ed.shape == (2, H, W, 1)
    torch.testing.assert_close(ed, rgbed[..., 3:], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(d, ed * a, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(a, a2)


def test_gaussians_behind_camera_are_ignored():
    means, quats, scales, opac, colors = make_scene(n=100, seed=12)
    cams = make_cameras()
    r0, a0, info0 = rasterize(means, quats, scales, opac, colors, *cams, W, H, backend="torch")
    behind = means.clone()
    behind[:, 2] = -behind[:, 2]  # mirrored behind the first camera
    m = torch.cat([means, behind])
    extra = lambda t: torch.cat([t, t])  # noqa: E731
    leaves = _leaves([m, extra(quats), extra(scales), extra(opac), extra(colors)])
    r1, a1, info1 = rasterize(*leaves, *cams, W, H, backend="torch")
    assert (info1["radii"][0, 100:] == 0).all()
    torch.testing.assert_close(r1[0], r0[0], atol=1e-6, rtol=0)
    (r1.sum() + a1.sum()).backward()
    for t in leaves:
        assert torch.isfinite(t.grad).all()
    assert leaves[0].grad[100:][info1["radii"][:, 100:].amax(0) == 0].abs().max() == 0


def test_empty_scene_returns_background():
    cams = make_cameras()
    bg = torch.tensor([[0.25, 0.5, 0.75], [1.0, 0.0, 0.0]])
    z = torch.zeros(0, 3)
    r, a, info = rasterize(z, torch.zeros(0, 4), z, torch.zeros(0), z, *cams, W, H,
                           backgrounds=bg, backend="torch")
    assert r.shape == (2, H, W, 3) and a.shape == (2, H, W, 1)
    assert (a == 0).all()
    torch.testing.assert_close(r, bg[:, None, None, :].expand(2, H, W, 3))
    # all Gaussians culled (behind the camera) behaves the same
    means, quats, scales, opac, colors = make_scene(n=20, seed=13)
    means[:, 2] = -means[:, 2]
    r, a, info = rasterize(means, quats, scales, opac, colors, *cams, W, H, backgrounds=bg,
                           backend="torch")
    torch.testing.assert_close(r, bg[:, None, None, :].expand(2, H, W, 3))
    assert (info["radii"] == 0).all()


def test_info_means2d_receives_gradient_and_radii_match_visibility():
    scene = make_scene(seed=14)
    scene[0][:20, 0] -= 50.0  # far outside every view
    scene = _leaves(scene)
    cams = make_cameras()
    r, a, info = rasterize(*scene, *cams, W, H, backend="torch")
    assert info["means2d"].shape == (2, 200, 2)
    assert info["radii"].shape == (2, 200) and info["depths"].shape == (2, 200)
    assert info["width"] == W and info["height"] == H and info["n_cameras"] == 2
    r.sum().backward()
    grad2d = info["means2d"].grad
    assert grad2d is not None and grad2d.shape == (2, 200, 2)
    assert grad2d[info["radii"] == 0].abs().max() == 0
    assert grad2d[info["radii"] > 0].abs().sum() > 0


def test_tile_size_does_not_change_the_image(monkeypatch):
    import paradrive.gs.rasterize as rast

    scene = make_scene(seed=15)
    cams = make_cameras()
    images = {}
    for ts in (4, 8, 16):
        monkeypatch.setattr(rast, "TORCH_TILE_SIZE", ts)
        images[ts], _, info = rasterize(*scene, *cams, W, H, backend="torch")
        assert info["tile_size"] == ts
    torch.testing.assert_close(images[4], images[16], atol=1e-5, rtol=0)
    torch.testing.assert_close(images[8], images[16], atol=1e-5, rtol=0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_backend_matches_torch_backend():
    from paradrive.gs.rasterize import cuda_backend_available

    if not cuda_backend_available():
        pytest.skip("gsplat CUDA extension does not load")
    scene = make_scene(seed=16)
    cams = make_cameras()
    bg = torch.tensor([[0.2, 0.5, 0.9], [1.0, 0.0, 0.3]])
    w = _loss_weights(4, seed=17)
    kw = dict(render_mode="RGB+ED", backgrounds=bg)

    def run(backend, device):
        leaves = [t.detach().to(device).requires_grad_(True) for t in scene]
        r, a, info = rasterize(*leaves, *[c.to(device) for c in cams], W, H, backend=backend,
                               **{k: (v.to(device) if torch.is_tensor(v) else v) for k, v in kw.items()})
        loss = (r * w[0].to(device)).sum() + (a * w[1].to(device)).sum()
        loss.backward()
        return r.detach().cpu(), a.detach().cpu(), [t.grad.cpu() for t in leaves], info

    r_cuda, a_cuda, g_cuda, info_cuda = run("auto", "cuda")
    assert info_cuda["backend"] == "gsplat"
    assert info_cuda["radii"].shape == (2, 200) and info_cuda["means2d"].grad is not None
    r_t, a_t, g_t, info_t = run("torch", "cuda")
    assert info_t["backend"] == "torch"
    torch.testing.assert_close(r_cuda[..., :3], r_t[..., :3], atol=1e-4, rtol=0)
    torch.testing.assert_close(a_cuda, a_t, atol=1e-4, rtol=0)
    assert_grads_close(g_t, g_cuda)
    r_cpu, _, g_cpu, _ = run("torch", "cpu")
    torch.testing.assert_close(r_cpu, r_t, atol=1e-4, rtol=1e-4)
