"""The fused CPU rasterizer (backend 'cpu'): images and gradients against the torch-op reference
within the tolerances of test_rasterize (renders and alphas 1e-4 absolute; gradients 1e-5
absolute plus 2e-4 of the reference's largest, see assert_grads_close), and byte-identical
results at any thread count. Every test runs on each kernel variant installed that this CPU
runs (AVX-512, AVX2, the 128-bit baseline: their pixel blocks and sums differ) and on the
torch-op stages the backend falls back to where none was built."""

from __future__ import annotations

import pytest
import torch
from test_rasterize import (
    H,
    W,
    _grads,
    _leaves,
    _loss_weights,
    assert_grads_close,
    make_cameras,
    make_scene,
)

from paradrive import kernels as loader
from paradrive.gs.rasterize import rasterize


@pytest.fixture(autouse=True, params=[*loader.VARIANTS, "torch"])
def kernels(request, monkeypatch):
    """Each test once per kernel variant this CPU runs (it fails where one was not built at
    install), and once with PARADRIVE_KERNELS=torch: no kernels, the torch-op stages."""
    choice = request.param
    if choice == "torch":
        monkeypatch.setenv("PARADRIVE_KERNELS", "torch")
        assert loader.load() is None
        return choice
    if choice not in loader.runnable():
        pytest.skip(f"this CPU does not run the {choice} kernels")
    built = loader.variant(choice)
    monkeypatch.setattr(loader, "load", lambda: built)
    return choice


BG = torch.tensor([[0.2, 0.5, 0.9], [1.0, 0.0, 0.3]])


def _both(scene, weights, **kw):
    """(cpu, torch) results of _grads for the same scene, cameras and loss."""
    cams = make_cameras()
    return [_grads(lambda *x, b=b, **k: rasterize(*x, backend=b, **kw, **k), scene, cams, weights)
            for b in ("cpu", "torch")]


def _assert_same(ours, ref, channels=slice(None)):
    (r, a, g), (r_ref, a_ref, g_ref) = ours, ref
    torch.testing.assert_close(r[..., channels], r_ref[..., channels], atol=1e-4, rtol=0)
    torch.testing.assert_close(a, a_ref, atol=1e-4, rtol=0)
    assert_grads_close(g, g_ref)


def test_rgb_with_background_matches_torch_reference():
    ours, ref = _both(make_scene(seed=3), _loss_weights(3, seed=4), backgrounds=BG)
    assert ours[1].max() > 0.5  # the scene is not empty
    _assert_same(ours, ref)


@pytest.mark.parametrize("degree", [0, 3])
def test_spherical_harmonics_match_torch_reference(degree):
    scene = make_scene(n=150, seed=10 + degree, sh_k=16)
    ours, ref = _both(scene, _loss_weights(3, seed=20 + degree), sh_degree=degree)
    _assert_same(ours, ref)
    if degree < 3:
        assert ours[2][4][:, (degree + 1) ** 2:].abs().max() == 0  # unused bands get no gradient


def test_opaque_scene_terminates_early_like_torch_reference():
    means, quats, scales, opac, colors = make_scene(n=400, seed=5)
    scene = [means, quats, scales * 5.0, torch.where(opac > 0.5, 1.0, 0.97), colors]
    ours, ref = _both(scene, _loss_weights(3, seed=6))
    assert (ours[1] > 0.999).float().mean() > 0.3  # saturated pixels and clamped alphas
    _assert_same(ours, ref)


def test_expected_depth_matches_torch_reference():
    ours, ref = _both(make_scene(seed=8), _loss_weights(4, seed=9), render_mode="RGB+ED",
                      backgrounds=BG)
    assert ours[0].shape == (2, H, W, 4)
    _assert_same(ours, ref, channels=slice(0, 3))
    covered = ours[1][..., 0] > 0.05
    torch.testing.assert_close(ours[0][..., 3][covered], ref[0][..., 3][covered], atol=1e-3, rtol=1e-4)


@pytest.mark.parametrize("channels", [1, 2, 6])
def test_feature_widths_other_than_rgb_match_torch_reference(channels):
    """The kernels carry up to four channels in registers (one and two here); wider features
    (six) take the torch-op compositor behind the same call."""
    means, quats, scales, opac, _ = make_scene(n=180, seed=30 + channels)
    feats = torch.rand(180, channels, generator=torch.Generator().manual_seed(channels))
    bg = torch.rand(2, channels, generator=torch.Generator().manual_seed(40 + channels))
    ours, ref = _both([means, quats, scales, opac, feats], _loss_weights(channels, seed=7),
                      backgrounds=bg)
    assert ours[0].shape == (2, H, W, channels) and ours[1].max() > 0.5
    _assert_same(ours, ref)


def test_means2d_gradient_and_radii_match_torch_reference():
    scene = make_scene(seed=14)
    cams = make_cameras()
    infos = []
    for backend in ("cpu", "torch"):
        r, _, info = rasterize(*_leaves(scene), *cams, W, H, backend=backend)
        r.sum().backward()
        infos.append(info)
    assert infos[0]["backend"] == "cpu" and infos[1]["backend"] == "torch"
    assert (infos[0]["radii"] > 0).sum() > 100
    assert torch.equal(infos[0]["radii"], infos[1]["radii"])
    torch.testing.assert_close(infos[0]["means2d"].grad, infos[1]["means2d"].grad, atol=1e-4, rtol=1e-4)


def test_empty_and_culled_scenes_return_the_background():
    cams = make_cameras()
    z = torch.zeros(0, 3)
    r, a, _ = rasterize(z, torch.zeros(0, 4), z, torch.zeros(0), z, *cams, W, H, backgrounds=BG,
                        backend="cpu")
    torch.testing.assert_close(r, BG[:, None, None, :].expand(2, H, W, 3))
    assert (a == 0).all()
    means, quats, scales, opac, colors = _leaves(make_scene(n=20, seed=13))
    r, a, _ = rasterize(-means, quats, scales, opac, colors, *cams, W, H, backgrounds=BG,
                        backend="cpu")
    torch.testing.assert_close(r, BG[:, None, None, :].expand(2, H, W, 3))
    (r.sum() + a.sum()).backward()
    assert means.grad.abs().max() == 0


def test_images_and_gradients_are_byte_identical_at_any_thread_count(kernels):
    if kernels == "torch":
        pytest.skip("torch's own operations promise no bytes across thread counts")
    scene = make_scene(n=300, seed=21, sh_k=16)
    cams = make_cameras()
    weights = _loss_weights(4, seed=22)
    old = torch.get_num_threads()
    results = []
    try:
        for threads in (1, 2, 1):
            torch.set_num_threads(threads)
            results.append(_grads(lambda *x, **k: rasterize(*x, backend="cpu", sh_degree=3,
                                                            render_mode="RGB+ED", **k),
                                  scene, cams, weights))
    finally:
        torch.set_num_threads(old)
    for r, a, g in results[1:]:
        assert torch.equal(r, results[0][0]) and torch.equal(a, results[0][1])
        assert all(torch.equal(x, y) for x, y in zip(g, results[0][2], strict=True))


def test_torch_keeps_its_thread_count_after_the_kernels_run():
    """The kernels run on their own threads; a fit's fixed thread count must survive them."""
    old = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        scene = _leaves(make_scene(n=50, seed=30, sh_k=16))
        r, a, _ = rasterize(*scene, *make_cameras(), W, H, sh_degree=3, backend="cpu")
        (r.sum() + a.sum()).backward()
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(old)


def test_fused_shading_colours_only_the_gaussians_a_view_draws(kernels):
    if kernels == "torch":
        pytest.skip("the fused shading is a kernel")
    from paradrive.gs._fused import shade_fused
    from paradrive.gs.sh import shade

    g = torch.Generator().manual_seed(7)
    means = (torch.randn(60, 3, generator=g) * 2).requires_grad_()
    coeffs = (torch.randn(60, 16, 3, generator=g) * 0.3).requires_grad_()
    campos = torch.tensor([[0.0, 0.0, -5.0], [1.0, 2.0, -4.0]])
    visible = torch.rand(2, 60, generator=g) > 0.5
    never = ~visible.any(0)
    assert never.any() and visible.any()
    ours = shade_fused(3, means, coeffs, campos, visible)
    means_ref, coeffs_ref = means.detach().clone().requires_grad_(), coeffs.detach().clone().requires_grad_()
    ref = shade(3, means_ref, coeffs_ref, campos)
    torch.testing.assert_close(ours[visible], ref[visible], atol=1e-6, rtol=0)
    assert ours[~visible].abs().max() == 0
    # gradient only where a Gaussian is drawn, as the compositor passes it: the reference's gradient
    w = torch.rand(2, 60, 3, generator=g) * visible[..., None]
    (ours * w).sum().backward()
    (ref * w).sum().backward()
    torch.testing.assert_close(coeffs.grad, coeffs_ref.grad, atol=1e-5, rtol=0)
    torch.testing.assert_close(means.grad, means_ref.grad, atol=1e-5, rtol=0)
    assert coeffs.grad[never].abs().max() == 0 and means.grad[never].abs().max() == 0


def test_with_the_fused_kernels_torch_runs_on_one_thread_and_the_kernels_on_the_rest(kernels):
    """deterministic_torch(n, 'cpu'): the kernels take the n threads, torch's own operations
    one (its idle workers would spin on the kernels' cores); both restored afterwards. Without
    kernels torch's operations do the work, on the n threads."""
    from paradrive.devices import cpu_kernel_threads
    from paradrive.gs.model import deterministic_torch

    torch_threads = 3 if kernels == "torch" else 1
    old = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        with deterministic_torch(3, "cpu"):
            assert torch.get_num_threads() == torch_threads and cpu_kernel_threads() == 3
            scene = _leaves(make_scene(n=50, seed=31, sh_k=16))
            r, a, _ = rasterize(*scene, *make_cameras(), W, H, sh_degree=3, backend="cpu")
            (r.sum() + a.sum()).backward()
            assert torch.get_num_threads() == torch_threads
        assert torch.get_num_threads() == 2 and cpu_kernel_threads() == 2
        with deterministic_torch(3, "torch"):
            assert torch.get_num_threads() == 3 and cpu_kernel_threads() == 3
    finally:
        torch.set_num_threads(old)


def _graph(fn) -> set[str]:
    """The names of the autograd nodes behind a tensor's grad_fn."""
    names, todo = set(), [fn]
    while todo:
        node = todo.pop()
        if node is not None and type(node).__name__ not in names:
            names.add(type(node).__name__)
            todo.extend(f for f, _ in node.next_functions)
    return names


@pytest.mark.parametrize("render_mode", ["RGB", "RGB+ED"])
def test_the_fit_s_render_is_one_node_with_the_bytes_of_the_kernels_run_one_by_one(
        kernels, render_mode, monkeypatch):
    """The fit's render (SH coefficients in two parts, float32, the native library) runs
    projection, colour, binning and compositing as one autograd node with no torch operation
    between them; its images, alphas, gradients and the projected means' gradient (what
    densification reads) are the bytes of the same kernels run as separate nodes."""
    import paradrive.gs.rasterize as R

    if kernels == "torch":
        pytest.skip("one node needs the native kernels")
    means, quats, scales, opac, sh = make_scene(n=300, seed=31, sh_k=16)
    weights = _loss_weights(3 if render_mode == "RGB" else 4, seed=32)
    results = []
    for one_node in (True, False):
        if not one_node:
            monkeypatch.setattr(R, "_fit_case", lambda *a: False)
        leaves = _leaves([means, quats, scales, opac, sh[:, :1], sh[:, 1:]])
        out, alphas, info = rasterize(*leaves[:4], (leaves[4], leaves[5]), *make_cameras(), W, H,
                                      sh_degree=3, backend="cpu", render_mode=render_mode,
                                      backgrounds=BG)
        nodes = _graph(out.grad_fn)
        assert ("FusedRasterizeBackward" in nodes) == one_node
        assert ("FusedCompositeBackward" in nodes) != one_node
        ((out * weights[0]).sum() + (alphas * weights[1]).sum()).backward()
        results.append([out, alphas, info["means2d"].grad, info["radii"]]
                       + [t.grad for t in leaves])
    assert results[0][1].max() > 0.5 and info["n_isects"] > 100
    for a, b in zip(*results, strict=True):
        assert a is not None and a.dtype == b.dtype and torch.equal(a, b)
