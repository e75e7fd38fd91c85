"""The vectorised compositing kernels of ``_composite.cpp``: built with the machine's C++
compiler on first use, cached, and called through ctypes.

The library is built for the CPU it runs on (``-march=native``), so its cache key holds the
source, the compiler's version and the CPU's flags; a shared home on machines of several kinds
keeps one build per kind. The build writes to a temporary name and renames it into place, so
concurrent first uses (several fits, several builds) never load a half-written file.

``PARADRIVE_KERNELS`` chooses: ``auto`` (default: this library, the Numba kernels where no
compiler builds it), ``native`` (this library or an error) or ``numba``. The cache lives in
``PARADRIVE_CACHE`` (default ``~/.cache/paradrive``).
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import logging
import os
import platform
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np

__all__ = ["NativeBuildError", "kernel_choice", "load"]

log = logging.getLogger(__name__)

SOURCE = Path(__file__).with_name("_composite.cpp")
FLAGS = ("-O3", "-march=native", "-std=c++17", "-shared", "-fPIC", "-pthread")
CHOICES = ("auto", "native", "numba")

_f32 = ctypes.POINTER(ctypes.c_float)
_f64 = ctypes.POINTER(ctypes.c_double)
_i64 = ctypes.POINTER(ctypes.c_int64)
_int, _long = ctypes.c_int, ctypes.c_int64


class NativeBuildError(RuntimeError):
    """The compositing library could not be built or loaded."""


def kernel_choice() -> str:
    """``PARADRIVE_KERNELS``, checked."""
    choice = os.environ.get("PARADRIVE_KERNELS", "auto").strip().lower() or "auto"
    if choice not in CHOICES:
        raise ValueError(f"PARADRIVE_KERNELS={choice!r}: use one of {', '.join(CHOICES)}")
    return choice


def _compiler() -> str:
    for name in (os.environ.get("CXX", ""), "c++", "g++", "clang++"):
        if name and shutil.which(name):
            return name
    raise NativeBuildError("no C++ compiler (c++, g++ or clang++) on PATH; install one "
                           "(Debian: apt-get install g++) or set PARADRIVE_KERNELS=numba")


def _cpu_flags() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith(("flags", "Features")):
                return line
    except OSError:
        pass
    return platform.processor()


def _library_path(cxx: str) -> Path:
    try:
        source = SOURCE.read_text()
    except OSError as exc:
        raise NativeBuildError(f"cannot read {SOURCE}: {exc}; reinstall paradrive") from exc
    version = subprocess.run([cxx, "--version"], capture_output=True, text=True, check=False).stdout
    key = hashlib.sha256("\0".join([source, " ".join(FLAGS), version, _cpu_flags(),
                                    platform.machine()]).encode()).hexdigest()[:16]
    cache = Path(os.environ.get("PARADRIVE_CACHE", Path.home() / ".cache" / "paradrive"))
    return cache / "native" / f"composite-{key}.so"


def _build(cxx: str, target: Path) -> None:
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.stem}.", suffix=".so", dir=target.parent)
    os.close(fd)
    try:
        done = subprocess.run([cxx, *FLAGS, str(SOURCE), "-o", tmp], capture_output=True,
                              text=True, check=False)
        if done.returncode != 0:
            raise NativeBuildError(f"{cxx} could not build {SOURCE.name}:\n{done.stderr[-2000:]}")
        os.replace(tmp, target)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


class Kernels:
    """The two entry points, with numpy arguments checked for dtype and layout."""

    def __init__(self, lib: ctypes.CDLL, path: Path) -> None:
        self.path = path
        self._forward = lib.pd_composite_forward
        self._forward.restype = _int
        self._forward.argtypes = [_f32, _int, _i64, _i64, _long, _int, _int, _int, _int, _int,
                                  _int, _int, _f32, _f32, _f32, _i64, _int]
        self._backward = lib.pd_composite_backward
        self._backward.restype = _int
        self._backward.argtypes = [_f32, _int, _i64, _long, _int, _int, _int, _int, _int, _int,
                                   _int, _f32, _f32, _i64, _f32, _f32, _f64, _int]

    def composite_forward(self, gauss: np.ndarray, offsets: np.ndarray, counts: np.ndarray,
                          ts: int, tiles_x: int, tiles_y: int, bg: np.ndarray,
                          render: np.ndarray, trans: np.ndarray, last: np.ndarray,
                          threads: int) -> None:
        """``_cpu_kernels.composite_forward``, on ``threads`` threads."""
        C, H, W, D = render.shape
        rc = self._forward(_ptr(gauss, np.float32), gauss.shape[1], _ptr(offsets, np.int64),
                           _ptr(counts, np.int64), offsets.shape[0], ts, tiles_x, tiles_y, C, H,
                           W, D, _ptr(bg, np.float32), _ptr(render, np.float32),
                           _ptr(trans, np.float32), _ptr(last, np.int64), threads)
        if rc != 0:
            raise ValueError(f"composite_forward: {D} channels; the kernels carry 1 to 4")

    def composite_backward(self, gauss: np.ndarray, offsets: np.ndarray, ts: int, tiles_x: int,
                           tiles_y: int, bg: np.ndarray, trans: np.ndarray, last: np.ndarray,
                           d_render: np.ndarray, d_alpha: np.ndarray, threads: int) -> np.ndarray:
        """``_cpu_kernels.composite_backward``, on ``threads`` threads."""
        C, H, W, D = d_render.shape
        grads = np.zeros(gauss.shape, dtype=np.float64)
        rc = self._backward(_ptr(gauss, np.float32), gauss.shape[1], _ptr(offsets, np.int64),
                            offsets.shape[0], ts, tiles_x, tiles_y, C, H, W, D,
                            _ptr(bg, np.float32), _ptr(trans, np.float32), _ptr(last, np.int64),
                            _ptr(d_render, np.float32), _ptr(d_alpha, np.float32),
                            _ptr(grads, np.float64), threads)
        if rc != 0:
            raise ValueError(f"composite_backward: {D} channels; the kernels carry 1 to 4")
        return grads


_CTYPES: dict[str, type] = {"float32": ctypes.c_float, "float64": ctypes.c_double,
                            "int64": ctypes.c_int64}


def _ptr(a: np.ndarray, dtype: type) -> ctypes._Pointer:
    """A pointer to ``a``'s data, which must be C-contiguous and of ``dtype`` (the kernels read
    and write it in place)."""
    name = np.dtype(dtype).name
    if a.dtype != dtype or not a.flags.c_contiguous:
        raise TypeError(f"expected a C-contiguous {name} array, got "
                        f"{a.dtype} {'contiguous' if a.flags.c_contiguous else 'strided'}")
    return a.ctypes.data_as(ctypes.POINTER(_CTYPES[name]))


@functools.lru_cache(maxsize=1)
def _load() -> Kernels | NativeBuildError:
    """The kernels, or the reason they are not there (kept, so a failed build is not retried on
    every call)."""
    try:
        cxx = _compiler()
        path = _library_path(cxx)
        if not path.exists():
            _build(cxx, path)
        try:
            return Kernels(ctypes.CDLL(str(path)), path)
        except OSError as exc:
            raise NativeBuildError(f"could not load {path}: {exc}; delete it to rebuild") from exc
    except NativeBuildError as exc:
        return exc


@functools.lru_cache(maxsize=1)
def _fallback_warning(reason: str) -> None:
    log.warning("vectorised compositing unavailable, using the Numba kernels: %s", reason)


def load() -> Kernels | None:
    """The native kernels, or None where ``PARADRIVE_KERNELS`` asks for Numba or (``auto``) they
    cannot be built here; ``native`` raises NativeBuildError instead."""
    choice = kernel_choice()
    if choice == "numba":
        return None
    kernels = _load()
    if isinstance(kernels, Kernels):
        return kernels
    if choice == "native":
        raise kernels
    _fallback_warning(str(kernels).splitlines()[0])
    return None
