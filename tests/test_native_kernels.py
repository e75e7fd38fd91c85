"""The native compositing library: built once per machine into the cache and reused, the Numba
kernels where no compiler builds it, and a clear error where native kernels are required."""

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
    monkeypatch.setenv("PARADRIVE_KERNELS", "native")
    kernels = _native.load()
    assert kernels is not None and kernels.path.parent == fresh_loader / "native"
    built = kernels.path.stat().st_mtime_ns
    assert [p.name for p in kernels.path.parent.iterdir()] == [kernels.path.name]  # no temp file
    _native._load.cache_clear()  # a new process: finds the build and loads it without compiling

    def no_build(*_):
        raise AssertionError("rebuilt a library that is in the cache")

    monkeypatch.setattr(_native, "_build", no_build)
    assert _native.load().path == kernels.path
    assert kernels.path.stat().st_mtime_ns == built


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


def test_an_unknown_kernel_choice_is_refused(monkeypatch):
    monkeypatch.setenv("PARADRIVE_KERNELS", "cuda")
    with pytest.raises(ValueError, match="auto, native, numba"):
        _native.load()
