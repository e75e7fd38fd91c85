"""The native kernel library: built once per machine into the cache and reused, the Numba
kernels where no compiler builds it, and a clear error where native kernels are required; its
binning and gradient sums give the Numba kernels' bytes, and SH coefficients in two parts
render as their concatenation."""

from __future__ import annotations

import logging

import pytest
import torch
from test_rasterize import H, W, make_cameras, make_scene

from paradrive.gs import _native
from paradrive.gs.rasterize import rasterize


@pytest.fixture
def fresh_loader(monkeypatch, tmp_path):
    """The loader with its memory cleared and its cache in tmp_path (restored afterwards)."""
    monkeypatch.setenv("PARADRIVE_CACHE", str(tmp_path / "cache"))
    _native._load.cache_clear()
    _native._fallback_warning.cache_clear()
    yield tmp_path / "cache"
    _native._load.cache_clear()
    _native._fallback_warning.cache_clear()


def _render(scene):
    out, alphas, _ = rasterize(*scene, *make_cameras(), W, H, backend="cpu")
    return out, alphas


def test_the_library_is_built_once_into_the_cache_and_reused(fresh_loader, monkeypatch):
    """Built once, then loaded from the cache; each load marks the build used, and builds no
    load touched for UNUSED_DAYS (another source version, say) are removed."""
    import os
    import time

    monkeypatch.setenv("PARADRIVE_KERNELS", "native")
    kernels = _native.load()
    assert kernels is not None and kernels.path.parent == fresh_loader / "native"
    built = kernels.path.stat().st_ino
    assert [p.name for p in kernels.path.parent.iterdir()] == [kernels.path.name]  # no temp file
    day, now = 86400, time.time()
    stale, recent = (kernels.path.with_name(f"composite-{n}.so") for n in ("stale", "recent"))
    for path, age_days in ((kernels.path, 40), (stale, _native.UNUSED_DAYS + 1), (recent, 1)):
        path.touch()
        os.utime(path, (now - age_days * day, now - age_days * day))
    _native._load.cache_clear()  # a new process: finds the build and loads it without compiling

    def no_build(*_):
        raise AssertionError("rebuilt a library that is in the cache")

    monkeypatch.setattr(_native, "_build", no_build)
    assert _native.load().path == kernels.path
    assert kernels.path.stat().st_ino == built  # the same file, not a new one renamed into place
    assert kernels.path.stat().st_mtime > now - day  # marked used
    assert sorted(p.name for p in kernels.path.parent.iterdir()) == sorted(
        [kernels.path.name, recent.name])


def test_without_a_compiler_the_numba_kernels_render_and_native_says_how_to_fix(
        fresh_loader, monkeypatch, tmp_path, caplog):
    scene = make_scene(n=120, seed=5)
    monkeypatch.setenv("PARADRIVE_KERNELS", "numba")
    reference = _render(scene)
    empty = tmp_path / "bin"
    empty.mkdir()
    monkeypatch.setenv("PATH", str(empty))
    monkeypatch.delenv("CXX", raising=False)
    monkeypatch.setenv("PARADRIVE_KERNELS", "auto")
    with caplog.at_level(logging.WARNING, logger="paradrive.gs._native"):
        assert _native.load() is None
        out, alphas = _render(scene)
    assert "no C++ compiler" in caplog.text and "using the Numba kernels" in caplog.text
    assert torch.equal(out, reference[0]) and torch.equal(alphas, reference[1])
    monkeypatch.setenv("PARADRIVE_KERNELS", "native")
    with pytest.raises(_native.NativeBuildError, match="PARADRIVE_KERNELS=numba"):
        _native.load()


def test_a_source_the_compiler_rejects_is_reported_with_its_error(fresh_loader, monkeypatch,
                                                                 tmp_path):
    broken = tmp_path / "broken.cpp"
    broken.write_text("this is not C++\n")
    monkeypatch.setattr(_native, "SOURCE", broken)
    monkeypatch.setenv("PARADRIVE_KERNELS", "native")
    with pytest.raises(_native.NativeBuildError, match="could not build broken.cpp"):
        _native.load()
    assert not any((fresh_loader / "native").iterdir())  # nothing half-written left


def test_the_kernels_vectors_are_one_register_of_the_machine_s_vector_unit():
    """16 float32 lanes with AVX-512, 8 with AVX2, 4 elsewhere (SSE, NEON): wider vectors than
    the unit are split by the compiler through the stack, which made every kernel 5-10x slower
    on AVX2."""
    try:
        _native._compiler()
    except _native.NativeBuildError:
        pytest.skip("no C++ compiler on this machine")
    kernels = _native.load()
    assert kernels is not None, "the library did not build"
    flags = set(_native._cpu_flags().split())
    assert kernels.lanes == (16 if "avx512f" in flags else 8 if "avx2" in flags else 4)


def test_an_unknown_kernel_choice_is_refused(monkeypatch):
    monkeypatch.setenv("PARADRIVE_KERNELS", "cuda")
    with pytest.raises(ValueError, match="auto, native, numba"):
        _native.load()


def test_native_binning_and_gradient_sums_give_the_numba_kernels_bytes():
    """The tile lists (sorted by depth, ties by id) and the per-Gaussian sums of the native
    library are the Numba kernels' own, on two cameras with depth ties and unseen Gaussians."""
    from paradrive.gs import _cpu_kernels as K
    from paradrive.gs._fused import _f32

    native = _native.load()
    if native is None:
        pytest.skip("no C++ compiler here")
    g = torch.Generator().manual_seed(3)
    C, N, ts = 2, 400, 16
    means2d = torch.rand(C, N, 2, generator=g) * torch.tensor([W + 40.0, H + 40.0]) - 20.0
    radii = torch.randint(0, 30, (C, N, 2), generator=g, dtype=torch.int32)
    depths = torch.randint(1, 40, (C, N), generator=g).float() * 0.25  # many equal depths
    tiles_x, tiles_y = -(-W // ts), -(-H // ts)
    ours = native.bin_lists(_f32(depths.reshape(-1)), _f32(means2d.reshape(-1, 2)),
                            _f32(radii.reshape(-1, 2)), N, ts, tiles_x, tiles_y,
                            C * tiles_x * tiles_y)
    visible = torch.nonzero((radii > 0).all(-1).reshape(-1)).squeeze(1)
    order = visible[torch.sort(depths.reshape(-1)[visible], stable=True).indices]
    ref = K.bin_lists(order.numpy(), _f32(means2d.reshape(-1, 2)), _f32(radii.reshape(-1, 2)),
                      N, ts, tiles_x, tiles_y, C * tiles_x * tiles_y)
    assert len(ours[0]) > 500 and (radii == 0).any()
    for a, b in zip(ours, ref, strict=True):
        assert a.dtype == b.dtype and (a == b).all()
    grads = torch.randn(len(ref[0]), 9, generator=g).numpy()
    sums = [native.sum_by_gaussian(grads, ref[0], C * N, threads) for threads in (1, 2, 3)]
    expected = K.sum_by_gaussian(grads, ref[0], C * N)
    assert all(s.tobytes() == expected.tobytes() for s in sums)


@pytest.mark.parametrize("choice", ["native", "numba"])
def test_sh_coefficients_in_two_parts_render_as_the_concatenated_tensor(monkeypatch, choice):
    """A fit's sh0 and shN go to the kernels as they are: same images and gradients as their
    concatenation, and the torch-op path (which concatenates them) agrees."""
    monkeypatch.setenv("PARADRIVE_KERNELS", choice)
    means, quats, scales, opac, colors = make_scene(n=150, seed=5, sh_k=16)
    cams = make_cameras()
    results = []
    for backend, parts in (("cpu", False), ("cpu", True), ("torch", True)):
        leaves = [t.detach().clone().requires_grad_() for t in (means, quats, scales, opac)]
        sh0 = colors[:, :1].clone().requires_grad_()
        shN = colors[:, 1:].clone().requires_grad_()
        coeffs = (sh0, shN) if parts else torch.cat([sh0, shN], 1)
        r, a, _ = rasterize(*leaves, coeffs, *cams, W, H, sh_degree=2, backend=backend)
        (r.square().sum() + a.sum()).backward()
        results.append((r.detach(), [t.grad for t in leaves] + [sh0.grad, shN.grad]))
    (r0, g0), (r1, g1), (r2, g2) = results
    assert r0.max() > 0.3 and torch.equal(r0, r1)
    assert all(torch.equal(x, y) for x, y in zip(g0, g1, strict=True))
    assert g1[-1][:, 8:].abs().max() == 0 and g1[-1][:, :8].abs().max() > 0  # bands 3: unused
    torch.testing.assert_close(r1, r2, atol=1e-4, rtol=0)
    for x, y in zip(g1, g2, strict=True):
        torch.testing.assert_close(x, y, atol=2e-3, rtol=2e-3)
    with pytest.raises(ValueError, match="set sh_degree"):
        rasterize(means, quats, scales, opac, (colors[:, :1], colors[:, 1:]), *cams, W, H,
                  backend="cpu")


def test_arrays_of_the_wrong_dtype_or_layout_never_reach_the_library():
    """The library takes raw addresses, so the dtype and layout are checked before each call."""
    import numpy as np

    kernels = _native.load()
    if kernels is None:
        pytest.skip("PARADRIVE_KERNELS=numba: no library")
    depths = np.ones(4, np.float32)
    radii = np.ones((4, 2), np.float32)
    means2d = np.zeros((4, 2), np.float32)
    with pytest.raises(TypeError, match="C-contiguous float32 array, got float64"):
        kernels.bin_lists(depths.astype(np.float64), means2d, radii, 4, 16, 2, 2, 4)
    with pytest.raises(TypeError, match="C-contiguous float32 array, got float32 strided"):
        kernels.bin_lists(depths, np.zeros((4, 4), np.float32)[:, ::2], radii, 4, 16, 2, 2, 4)
    ids, offsets, counts = kernels.bin_lists(depths, means2d, radii, 4, 16, 2, 2, 4)
    assert counts.sum() == len(ids) == 4   # each Gaussian at the origin touches the first tile


def test_kernels_run_in_a_child_forked_after_the_parent_started_its_worker_threads():
    """The kernels keep their worker threads between calls; a child forked afterwards (a
    process pool on Linux) has none of them and starts its own instead of waiting forever."""
    import os
    import select

    from paradrive.devices import set_cpu_kernel_threads

    if _native.load() is None:
        pytest.skip("no C++ compiler here")
    scene = make_scene()
    old = set_cpu_kernel_threads(2)
    try:
        expected = _render(scene)[0].numpy().tobytes()   # the parent's workers are running now
        read, write = os.pipe()
        pid = os.fork()
        if pid == 0:   # the child: render on two threads, report, leave without cleanup
            try:
                torch.set_num_threads(1)   # torch's OpenMP pool does not survive a fork
                same = _render(scene)[0].numpy().tobytes() == expected
                os.write(write, b"same" if same else b"diff")
            finally:
                os._exit(0)
        os.close(write)
        ready, _, _ = select.select([read], [], [], 120)
        answer = os.read(read, 4) if ready else b""
        if not ready:
            os.kill(pid, 9)
        os.waitpid(pid, 0)
        os.close(read)
    finally:
        set_cpu_kernel_threads(old)
    assert answer == b"same", "the forked child hung or rendered other bytes"


@pytest.mark.parametrize("cameras", [1, 3])
def test_densification_sums_in_the_library_keep_the_bytes_of_the_torch_operations(
        cameras, monkeypatch):
    """The densification's running sums of projected-gradient norms and counts, taken by the
    library from the gradients where the fit's render leaves them (two columns of its table),
    are the bytes of the torch operations, over several steps, for one camera and three."""
    import numpy as np

    from paradrive.gs import strategy as S

    if _native.load() is None:
        pytest.skip("no C++ compiler here")
    n, gen = 5000, torch.Generator().manual_seed(cameras)
    strat = S.DensifyStrategy()
    states, calls = [], []
    for native in (True, False):
        if not native:
            monkeypatch.setattr(S, "_native_sums", lambda *a: False)
        state = strat.initialize_state(n, 1.0, torch.zeros(n, dtype=torch.bool))
        gen.manual_seed(cameras)
        for _ in range(4):
            table = torch.randn(cameras, n, 10, generator=gen) * torch.exp(
                4.0 * torch.randn(cameras, n, 1, generator=gen))
            table[:, : n // 10] = 0.0                              # no gradient
            radii = torch.randint(0, 3, (cameras, n), generator=gen, dtype=torch.int32)
            m2d = torch.zeros(cameras, n, 2, requires_grad=True)
            m2d.grad = table[..., 3:5]                              # a view, as the fit's render sets it
            calls.append(S._native_sums(m2d.grad, (80.0, 48.0), radii, {
                "grad2d": torch.zeros(n), "count": torch.zeros(n)}) if native else False)
            strat.update_state(state, {"means2d": m2d, "radii": radii, "width": 160,
                                       "height": 96, "n_cameras": cameras})
        states.append((state["grad2d"].numpy().copy(), state["count"].numpy().copy()))
    assert any(calls)   # the library took the sums
    (g1, c1), (g2, c2) = states
    assert g1.tobytes() == g2.tobytes() and c1.tobytes() == c2.tobytes()
    assert np.count_nonzero(g1) > n // 2 and c1.max() >= 2 * (cameras > 1)


def _loss_inputs(seed: int, H: int = 24, W: int = 40):
    """A render (1, H, W, 4) with its accumulated depth and alphas, a target image, a sky mask and
    LiDAR pixels (not on the sky), with the edge cases of each term: pixels equal to the target
    (a zero L1 sign), alphas at and below the 1e-10 clamp, expected depths below the 1e-3 clamp
    and sky pixels on both sides of the sky term's hinge."""
    from paradrive.gs.losses import DepthTarget

    g = torch.Generator().manual_seed(seed)
    gt = torch.rand(H, W, 3, generator=g)
    rgb = torch.rand(H, W, 3, generator=g)
    same = torch.rand(H, W, generator=g) < 0.1
    rgb[same] = gt[same]
    alphas = torch.rand(1, H, W, 1, generator=g)
    alphas.view(-1)[:7] = torch.tensor([0.0, 1e-12, 1e-10, 2e-10, 1.0, 0.999, 1e-3])
    ed = torch.rand(H, W, generator=g) * 60.0
    ed.view(-1)[7:12] = torch.tensor([0.0, 1e-4, 1e-3, 2e-3, 800.0])
    ed[: H // 3] = torch.rand(H // 3, W, generator=g) * 1500.0  # the sky rows: past 500 m or not
    render = torch.cat([rgb, (ed * alphas[0, ..., 0])[..., None]], -1)[None]
    sky = torch.zeros(H, W, dtype=torch.bool)
    sky[: H // 3] = torch.rand(H // 3, W, generator=g) < 0.7
    free = torch.nonzero(~sky.reshape(-1)).squeeze(1)
    pixels = free[torch.randperm(free.numel(), generator=g)[: free.numel() // 2]].sort().values
    target = DepthTarget(pixels, torch.rand(pixels.numel(), generator=g) * 50.0 + 0.5)
    return render, alphas, gt, sky, target


@pytest.mark.parametrize("terms", ["sky+depth", "sky", "depth", "neither", "rgb"])
def test_the_fit_loss_node_gives_the_torch_expression_s_gradient_bytes(terms):
    from paradrive.gs._fit_loss import FitLossTerms, fit_loss, fit_loss_kernels, fit_loss_torch
    from paradrive.gs.rasterize import _expected_depth

    render, alphas, gt, sky, target = _loss_inputs(seed=len(terms))
    if terms == "rgb":
        render = render[..., :3].contiguous()
    sky = sky if "sky" in terms else None
    target = target if "depth" in terms else None
    weights = FitLossTerms(ssim_lambda=0.2, sky_weight=0.1, sky_scale=500.0, depth_weight=1.0)
    kernels = fit_loss_kernels(render)
    assert kernels is not None

    def grads(node: bool):
        r, a = render.clone().requires_grad_(True), alphas.clone().requires_grad_(True)
        if node:
            loss = fit_loss(r, a, gt, sky, target, weights, kernels)
        else:
            out = _expected_depth(r, a, "RGB" if terms == "rgb" else "RGB+ED")
            loss = fit_loss_torch(out, gt, sky, target, weights)
        loss.backward()
        return loss.detach(), r.grad, a.grad

    (l_node, r_node, a_node), (l_torch, r_torch, a_torch) = grads(True), grads(False)
    assert float(l_node) == pytest.approx(float(l_torch), rel=1e-5)
    assert r_node.numpy().tobytes() == r_torch.numpy().tobytes()
    if terms == "rgb":
        assert a_node is None and a_torch is None
    else:
        assert a_node.numpy().tobytes() == a_torch.numpy().tobytes()
        assert bool((a_node != 0).any()) == (terms != "neither")
    if target is not None:  # the depth term reaches the render's last channel
        assert bool((r_node[0, ..., 3].reshape(-1)[target.pixels] != 0).any())
