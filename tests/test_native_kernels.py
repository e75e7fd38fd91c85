"""The CPU kernels built at install: one variant per instruction set, the widest this CPU runs
chosen at import, none compiled at run time; the torch-op path with one warning where none was
built; typed bindings that refuse arrays of the wrong dtype, layout or size; and the kernels
against their torch-op counterparts within stated tolerances, with the same bytes at any thread
count.

Tolerances, kernels against torch operations (float32; sums in another order):
- tile lists (binning): exact (integer tile boxes; the kernels' depth sort is stable, ties by
  id, where torch's leaves ties in any order);
- per-Gaussian gradient sums: 1e-6 relative, 1e-6 absolute (the kernels sum in double);
- densification sums: 1e-6 relative (norms of float32 pairs, cameras summed in order);
- fit loss: the value 1e-5 relative; its gradient 1e-6 absolute plus 1e-5 relative (the
  gradient's constants are rounded once, not as torch rounds each factor, and the SSIM term's
  windows are summed in another order; where the alpha is clamped at 1e-10 the depth channel's
  gradient reaches 1e4).
"""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from test_rasterize import H, W, make_cameras, make_scene

from paradrive.contracts.layout import SceneLayout
from paradrive import kernels as loader
from paradrive.gs.rasterize import rasterize

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def fresh_loader():
    """The loader with its memory cleared (restored afterwards)."""
    def clear():
        for f in (loader._import, loader._widest, loader._fallback_warning):
            f.cache_clear()
    clear()
    yield
    clear()


def _render(scene):
    out, alphas, _ = rasterize(*scene, *make_cameras(), W, H, backend="cpu")
    return out, alphas


def _kernels():
    kernels = loader.load()
    assert kernels is not None, "the kernels were not built at install"
    return kernels


def test_each_instruction_set_this_cpu_runs_was_built_into_the_package():
    """One module per variant, in the installed package (not a cache), whose vectors are one
    register of its unit: 16 float32 lanes with AVX-512, 8 with AVX2, 4 on the baseline; load()
    takes the widest."""
    lanes = {"avx512": 16, "avx2": 8, "base": 4}
    runnable = loader.runnable()
    assert runnable[-1] == "base"
    for name in runnable:
        kernels = loader.variant(name)
        assert kernels.lanes == lanes[name]
        assert Path(kernels.__file__).parent == Path(loader.__file__).parent
    assert loader.load() is loader.variant(runnable[0])
    with pytest.raises(loader.NativeUnavailable, match="no kernel variant 'sse9'"):
        loader.variant("sse9")


def test_each_variant_compiles_from_a_source_file_of_its_own(monkeypatch):
    """setup.py's extensions, as the build sees them: the variants compile side by side, and
    setuptools names an object file after its source, so a source shared between two variants
    lets one link the other's object (a base module that defined PyInit__kernels_avx2, once)."""
    import types

    import setuptools

    made: dict = {}

    class Extension:                       # pybind11's helper, recorded
        def __init__(self, name, sources, **kwargs):
            self.name, self.sources, self.kwargs = name, sources, kwargs

    helpers = types.ModuleType("pybind11.setup_helpers")
    helpers.Pybind11Extension = Extension  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "pybind11", types.ModuleType("pybind11"))
    monkeypatch.setitem(sys.modules, "pybind11.setup_helpers", helpers)
    monkeypatch.setattr(setuptools, "setup", lambda **kwargs: made.update(kwargs))
    monkeypatch.chdir(REPO)
    import runpy

    runpy.run_path(str(REPO / "setup.py"))
    extensions = made["ext_modules"]
    assert made["options"]["build_ext"]["parallel"] >= 1
    assert {e.name for e in extensions} >= {"paradrive.kernels._kernels_base"}
    sources = [src for e in extensions for src in e.sources]
    assert len(sources) == len(set(sources)) == len(extensions), sources
    for e in extensions:
        (source,) = e.sources
        assert Path(source).stem == e.name.rsplit(".", 1)[1]
        assert '#include "_bindings.cpp"' in (REPO / source).read_text()
        assert e.kwargs["define_macros"] == [("PD_MODULE", Path(source).stem)]


def test_a_cpu_of_a_lower_capability_gets_the_narrower_kernels():
    """The variant follows torch's CPU capability, which ATEN_CPU_CAPABILITY lowers (as on a
    machine without AVX-512 or AVX2): a fresh process then loads the narrower kernels."""
    expected = {"default": 4, "avx2": 8}
    for capability, lanes in expected.items():
        if capability == "avx2" and "avx2" not in loader.runnable():
            continue
        code = "from paradrive import kernels; print(kernels.load().lanes)"
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO,
                             env={**os.environ, "ATEN_CPU_CAPABILITY": capability}, check=True)
        assert out.stdout.split() == [str(lanes)], (capability, out.stderr)


def test_without_the_kernels_the_torch_op_path_renders_with_one_warning_naming_the_fix(
        fresh_loader, monkeypatch, caplog):
    """A machine that could not compile at install: the modules are missing, the 'cpu' backend
    runs the torch-op stages (the torch backend's images), warns once, and PARADRIVE_KERNELS=
    native says how to fix it."""
    scene = make_scene(n=120, seed=5)
    reference = rasterize(*scene, *make_cameras(), W, H, backend="torch")
    for name in loader.VARIANTS:
        monkeypatch.setitem(sys.modules, f"paradrive.kernels._kernels_{name}", None)  # import fails
    with caplog.at_level(logging.WARNING, logger="paradrive.kernels"):
        assert loader.load() is None
        out, alphas = _render(scene)
        _render(scene)
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "apt-get install g++" in warnings[0].getMessage()
    torch.testing.assert_close(out, reference[0], atol=1e-5, rtol=0)
    torch.testing.assert_close(alphas, reference[1], atol=1e-5, rtol=0)
    monkeypatch.setenv("PARADRIVE_KERNELS", "native")
    with pytest.raises(loader.NativeUnavailable, match="not built at install.*reinstall"):
        loader.load()


def test_an_unknown_kernel_choice_is_refused(monkeypatch):
    monkeypatch.setenv("PARADRIVE_KERNELS", "numba")
    with pytest.raises(ValueError, match="auto, native, torch"):
        loader.load()


def test_arrays_of_the_wrong_dtype_layout_or_size_never_reach_the_kernels():
    kernels = _kernels()
    depths = np.ones(4, np.float32)
    radii = np.ones((4, 2), np.float32)
    means2d = np.zeros((4, 2), np.float32)
    with pytest.raises(TypeError, match="depths .*float64.*expected float32"):
        kernels.bin_lists(depths.astype(np.float64), means2d, radii, 4, 16, 2, 2, 4)
    with pytest.raises(TypeError, match="means2d .*C-contiguous"):
        kernels.bin_lists(depths, np.zeros((4, 4), np.float32)[:, ::2], radii, 4, 16, 2, 2, 4)
    with pytest.raises(ValueError, match="radii .*at least 8 values"):
        kernels.bin_lists(depths, means2d, radii[:2], 4, 16, 2, 2, 4)
    with pytest.raises(TypeError):  # a float where the tile size goes
        kernels.bin_lists(depths, means2d, radii, 4, 16.5, 2, 2, 4)
    with pytest.raises(ValueError, match="an id outside the Gaussians"):
        kernels.sum_by_gaussian(np.ones((3, 9), np.float32), np.array([0, 1, 7]), 4, 1)
    ids, offsets, counts = kernels.bin_lists(depths, means2d, radii, 4, 16, 2, 2, 4)
    assert counts.sum() == len(ids) == 4   # each Gaussian at the origin touches the first tile


def test_binning_and_gradient_sums_match_the_torch_operations():
    """The tile lists hold the torch-op binning's Gaussians, exactly, sorted by depth with ties
    by id, on two cameras with depth ties and unseen Gaussians; the per-Gaussian sums of list entries
    are index_add's within 1e-6, with the same bytes on 1, 2 and 3 threads."""
    from paradrive.gs._fused import _f32
    from paradrive.gs._tiles import bin_gaussians

    native = _kernels()
    g = torch.Generator().manual_seed(3)
    C, N, ts = 2, 400, 16
    means2d = torch.rand(C, N, 2, generator=g) * torch.tensor([W + 40.0, H + 40.0]) - 20.0
    radii = torch.randint(0, 30, (C, N, 2), generator=g, dtype=torch.int32)
    depths = torch.randint(1, 40, (C, N), generator=g).float() * 0.25  # many equal depths
    tiles_x, tiles_y = -(-W // ts), -(-H // ts)
    ours = native.bin_lists(_f32(depths.reshape(-1)), _f32(means2d.reshape(-1, 2)),
                            _f32(radii.reshape(-1, 2)), N, ts, tiles_x, tiles_y,
                            C * tiles_x * tiles_y)
    ref = bin_gaussians(means2d, radii, depths, W, H, ts)
    ids, offsets, counts = ours
    assert len(ids) > 500 and (radii == 0).any()
    assert np.array_equal(counts, ref.counts.numpy()) and np.array_equal(offsets, ref.offsets.numpy())
    flat_depths = depths.reshape(-1).numpy()
    for t in range(len(counts)):
        tile = ids[offsets[t]:offsets[t] + counts[t]]
        assert np.array_equal(np.sort(tile), np.sort(ref.flat_ids[offsets[t]:offsets[t] + counts[t]]))
        key = np.lexsort((tile, flat_depths[tile]))  # torch's sort leaves ties in any order
        assert np.array_equal(key, np.arange(len(tile)))
    grads = torch.randn(len(ours[0]), 9, generator=g)
    sums = [native.sum_by_gaussian(grads.numpy(), ours[0], C * N, threads) for threads in (1, 2, 3)]
    expected = torch.zeros(C * N, 9).index_add_(0, torch.from_numpy(ours[0]), grads)
    torch.testing.assert_close(torch.from_numpy(sums[0]), expected, rtol=1e-6, atol=1e-6)
    assert all(s.tobytes() == sums[0].tobytes() for s in sums)


@pytest.mark.parametrize("choice", ["native", "torch"])
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


def test_kernels_run_in_a_child_forked_after_the_parent_started_its_worker_threads():
    """The kernels keep their worker threads between calls; a child forked afterwards (a
    process pool on Linux) has none of them and starts its own instead of waiting forever."""
    import select

    from paradrive.devices import set_cpu_kernel_threads

    _kernels()
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
def test_densification_sums_in_the_kernels_match_the_torch_operations(cameras, monkeypatch):
    """The densification's running sums of projected-gradient norms and counts, taken by the
    kernels from the gradients where the fit's render leaves them (two columns of its table),
    match the torch operations over several steps (norms 1e-6 relative, counts exactly), for
    one camera and three."""
    from paradrive.gs import strategy as S

    _kernels()
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
        states.append((state["grad2d"].clone(), state["count"].clone()))
    assert any(calls)   # the kernels took the sums
    (g1, c1), (g2, c2) = states
    torch.testing.assert_close(g1, g2, rtol=1e-6, atol=0)
    assert torch.equal(c1, c2)
    assert int((g1 != 0).sum()) > n // 2 and c1.max() >= 2 * (cameras > 1)


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
def test_the_fit_loss_node_matches_the_torch_expression(terms):
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
    torch.testing.assert_close(r_node, r_torch, atol=1e-6, rtol=1e-5)
    if terms == "rgb":
        assert a_node is None and a_torch is None
    else:
        torch.testing.assert_close(a_node, a_torch, atol=1e-6, rtol=1e-5)
        assert bool((a_node != 0).any()) == (terms != "neither")
    if target is not None:  # the depth term reaches the render's last channel
        assert bool((r_node[0, ..., 3].reshape(-1)[target.pixels] != 0).any())


# --------------------------------------------------------------------------- fits in processes

_FIT_CODE = """\
import json, sys
from paradrive import kernels as loader
from paradrive.stages.fit import fit_scene
from paradrive.stages.fit import Params
fit_scene(sys.argv[1], Params.of('fit', json.load(open(sys.argv[2]))))
print('kernels', loader.load().__name__)
"""


@pytest.mark.slow
def test_four_fits_started_at_once_with_no_compiler_and_an_unwritable_cache_agree(
        tiny_scene, tmp_path):
    """Four workers start a fit at the same moment on a machine with no C++ compiler on PATH
    (CXX=/bin/false) and a PARADRIVE_CACHE that cannot be created (under a file): each loads
    the installed kernels, nothing is compiled or written to the cache, and all four write the
    same checkpoint bytes."""
    import shutil

    from test_gs_fit import TINY_FIT, fit_params

    params = fit_params("smoke", **{**TINY_FIT, "checkpoints": [4]})
    cfg = tmp_path / "params.json"
    cfg.write_text(json.dumps(params.source))
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("")
    no_tools = tmp_path / "bin"
    no_tools.mkdir()
    env = {**os.environ, "PYTHONPATH": str(REPO), "PATH": str(no_tools), "CXX": "/bin/false",
           "CC": "/bin/false", "PARADRIVE_CACHE": str(blocker / "cache")}
    scenes = []
    for i in range(4):
        scenes.append(tmp_path / f"scene{i}")
        shutil.copytree(tiny_scene, scenes[-1], ignore=shutil.ignore_patterns("gs"))
    procs = [subprocess.Popen([sys.executable, "-c", _FIT_CODE, str(d), str(cfg)], cwd=REPO,
                              env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
             for d in scenes]
    outs = [p.communicate(timeout=600)[0].decode() for p in procs]
    for p, out in zip(procs, outs, strict=True):
        assert p.returncode == 0, out
        assert f"kernels paradrive.kernels._kernels_{loader.runnable()[0]}" in out, out
    ckpts = [SceneLayout.at(d).checkpoint(4).read_bytes() for d in scenes]
    assert all(c == ckpts[0] for c in ckpts[1:])
    assert blocker.read_text() == ""
