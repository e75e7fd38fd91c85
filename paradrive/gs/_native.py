"""The vectorised kernels of ``_composite.cpp`` (projection, SH shading, tile binning,
compositing, and the fit loss's SSIM): built with the machine's C++ compiler on first use,
cached, and called through ctypes.

The library is built for the CPU it runs on (``-march=native``), so its cache key holds the
source, the compiler's version and the CPU's flags; a shared home on machines of several kinds
keeps one build per kind. The build writes to a temporary name and renames it into place, so
concurrent first uses (several fits, several builds) never load a half-written file.

``PARADRIVE_KERNELS`` chooses: ``auto`` (default: this library, the Numba kernels where no
compiler builds it), ``native`` (this library or an error) or ``numba``. The cache lives in
``PARADRIVE_CACHE`` (default ``~/.cache/paradrive``). Each load marks its build as used (its
modification time); builds no process loaded for ``UNUSED_DAYS`` (older versions of the source,
a compiler or a machine kind gone) are removed then.
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
import time
from pathlib import Path

import numpy as np

__all__ = ["NativeBuildError", "kernel_choice", "load", "with_lanes"]

log = logging.getLogger(__name__)

SOURCE = Path(__file__).with_name("_composite.cpp")
FLAGS = ("-O3", "-march=native", "-fno-math-errno", "-std=c++17", "-shared", "-fPIC", "-pthread")
CHOICES = ("auto", "native", "numba")
UNUSED_DAYS = 30

# Arrays go to the library as their addresses (``_ptr`` checks dtype and layout first, which is
# cheaper than ctypes' typed pointers: a fit iteration passes about 80 of them). The names say
# what each argument points to.
_f32 = _i64 = _i32 = _f64 = _u8 = ctypes.c_void_p
_int, _long = ctypes.c_int, ctypes.c_int64


class NativeBuildError(RuntimeError):
    """The kernel library could not be built or loaded."""


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


def _library_path(cxx: str, extra: tuple[str, ...] = ()) -> Path:
    try:
        source = SOURCE.read_text()
    except OSError as exc:
        raise NativeBuildError(f"cannot read {SOURCE}: {exc}; reinstall paradrive") from exc
    version = subprocess.run([cxx, "--version"], capture_output=True, text=True, check=False).stdout
    key = hashlib.sha256("\0".join([source, " ".join(FLAGS + extra), version, _cpu_flags(),
                                    platform.machine()]).encode()).hexdigest()[:16]
    cache = Path(os.environ.get("PARADRIVE_CACHE", Path.home() / ".cache" / "paradrive"))
    return cache / "native" / f"composite-{key}.so"


def _build(cxx: str, target: Path, extra: tuple[str, ...] = ()) -> None:
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.stem}.", suffix=".so", dir=target.parent)
    os.close(fd)
    try:
        done = subprocess.run([cxx, *FLAGS, *extra, str(SOURCE), "-o", tmp], capture_output=True,
                              text=True, check=False)
        if done.returncode != 0:
            raise NativeBuildError(f"{cxx} could not build {SOURCE.name}:\n{done.stderr[-2000:]}")
        os.replace(tmp, target)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def _mark_used(path: Path) -> None:
    """Touch the build ``path`` and remove the cache's other builds untouched for UNUSED_DAYS (a
    cache that cannot be written is left as it is)."""
    cutoff = time.time() - UNUSED_DAYS * 86400
    try:
        os.utime(path)
    except OSError as exc:  # a read-only cache
        log.debug("kernel cache: %s left as it is: %s", path, exc)
    for other in path.parent.glob("composite-*.so"):
        try:
            if other != path and other.stat().st_mtime < cutoff:
                other.unlink()
        except OSError as exc:  # another process removed it first, or a read-only cache
            log.debug("kernel cache: %s left as it is: %s", other, exc)


class Kernels:
    """The entry points, with numpy arguments checked for dtype and layout.

    The compositing takes a per-Gaussian ``table`` (C*N, 6 + D) and the lists' ``ids`` instead
    of the Numba kernels' gathered rows: row ``ids[e]`` of the table is their row e.
    """

    def __init__(self, lib: ctypes.CDLL, path: Path) -> None:
        self.path = path
        # float32 lanes a vector: 16 with AVX-512, 8 with AVX2, else 4
        self.lanes: int = _entry(lib.pd_lanes, _int, [])()
        _flt = ctypes.c_float
        tiles = [_long, _int, _int, _int, _int, _int, _int, _int]  # tiles, ts, tiles_x/y, C H W D
        self._forward = _entry(lib.pd_composite_forward, _int, [
            _f32, _long, _int, _i64, _i64, _i64, *tiles, _f32, _f32, _f32, _i64, _f32, _int])
        self._backward = _entry(lib.pd_composite_backward, _int, [
            _f32, _long, _int, _i64, _i64, _i64, *tiles, _f32, _f32, _i64, _f32, _f32, _f32, _f32,
            _int])
        self._bin_count = _entry(lib.pd_bin_count, _long, [
            _f32, _f32, _f32, _long, _long, _int, _int, _int, _i64, _i64])
        self._bin_fill = _entry(lib.pd_bin_fill, None, [
            _i64, _long, _f32, _f32, _long, _int, _int, _int, _i64, _i64])
        self._sum = _entry(lib.pd_sum_by_gaussian, None, [_f32, _i64, _long, _int, _long, _f32, _int])
        self._project = _entry(lib.pd_project_forward, None, [
            *[_f32] * 6, _long, _int, _int, _int, _flt, _flt, _flt, _flt, _f32, _f32, _f32, _i32,
            _f32, _int, _int, _int])
        self._sh = _entry(lib.pd_sh_forward, None, [
            _int, _f32, _f32, _f32, _int, _f32, _long, _int, _u8, _f32, _int, _int])
        self._sh_vjp = _entry(lib.pd_sh_backward, None, [
            _int, _f32, _f32, _f32, _int, _f32, _long, _int, _f32, _int, _f32, _int, _f32, _f32,
            _f32, _int])
        self._project_vjp = _entry(lib.pd_project_backward, None, [
            *[_f32] * 5, _long, _int, _int, _int, _flt, _flt, _flt, _f32, _int, _f32, _int, _f32,
            _int, _f32, _f32, _f32, _int])
        self._grad_norms = _entry(lib.pd_grad_norms, None, [
            _f32, _long, _int, _long, _flt, _flt, _i32, _f32, _f32, _int])
        self._ssim = _entry(lib.pd_ssim_forward, None, [
            _f32, _f32, _long, _int, _int, _int, _f32, _int, _flt, _flt, _f32, _f64, _f32, _int])
        self._loss_terms = _entry(lib.pd_fit_loss_terms, None, [
            _f32, _f32, _f32, _long, _int, _u8, _flt, _i64, _f32, _long, _f64])
        self._loss_vjp = _entry(lib.pd_fit_loss_backward, None, [
            _f32, _f32, _f32, _f32, _long, _int, _flt, _u8, _flt, _flt, _i64, _f32, _long, _flt,
            _f32, _f32])
        self._ssim_vjp = _entry(lib.pd_ssim_backward, None, [
            _f32, _f32, _f32, _long, _int, _int, _int, _f32, _int, _f32, _f32, _f32, _int])
        # both: three arrays in, N, the node rows (rows, nodes, M, boxes, rotations, present),
        # three arrays out, threads
        place = [_f32, _f32, _f32, _long, _i64, _i64, _long, _f32, _f32, _u8, _f32, _f32, _f32,
                 _int]
        self._place = _entry(lib.pd_place_forward, None, place)
        self._place_vjp = _entry(lib.pd_place_backward, None, place)

    def composite_forward(self, table: np.ndarray, ids: np.ndarray, offsets: np.ndarray,
                          counts: np.ndarray, ts: int, tiles_x: int, tiles_y: int,
                          bg: np.ndarray, render: np.ndarray, trans: np.ndarray, last: np.ndarray,
                          threads: int, reach: np.ndarray) -> None:
        """``_cpu_kernels.composite_forward``, on ``threads`` threads. ``reach`` (C*N, 2)
        float32 gets each row's ellipse half-extents, which the backward takes."""
        C, H, W, D = render.shape
        rc = self._forward(_ptr(table, np.float32), table.shape[0], table.shape[1],
                           _ptr(ids, np.int64),
                           _ptr(offsets, np.int64), _ptr(counts, np.int64), offsets.shape[0], ts,
                           tiles_x, tiles_y, C, H, W, D, _ptr(bg, np.float32),
                           _ptr(render, np.float32), _ptr(trans, np.float32),
                           _ptr(last, np.int64), _reach(reach, table), threads)
        if rc != 0:
            raise ValueError(f"composite_forward: {D} channels; the kernels carry 1 to 4")

    def composite_backward(self, table: np.ndarray, ids: np.ndarray, offsets: np.ndarray,
                           counts: np.ndarray, ts: int, tiles_x: int, tiles_y: int,
                           bg: np.ndarray, trans: np.ndarray, last: np.ndarray,
                           d_render: np.ndarray, d_alpha: np.ndarray, threads: int,
                           reach: np.ndarray) -> np.ndarray:
        """``_cpu_kernels.composite_backward`` (one row per list entry; float32, the lanes'
        sums), on ``threads`` threads; ``reach`` as the forward filled it."""
        C, H, W, D = d_render.shape
        grads = np.empty((ids.shape[0], table.shape[1]), dtype=np.float32)
        rc = self._backward(_ptr(table, np.float32), table.shape[0], table.shape[1],
                            _ptr(ids, np.int64),
                            _ptr(offsets, np.int64), _ptr(counts, np.int64), offsets.shape[0], ts,
                            tiles_x, tiles_y, C, H, W, D, _ptr(bg, np.float32),
                            _ptr(trans, np.float32), _ptr(last, np.int64),
                            _ptr(d_render, np.float32), _ptr(d_alpha, np.float32),
                            _reach(reach, table), _ptr(grads, np.float32), threads)
        if rc != 0:
            raise ValueError(f"composite_backward: {D} channels; the kernels carry 1 to 4")
        return grads

    def bin_lists(self, depths: np.ndarray, means2d: np.ndarray, radii: np.ndarray,
                  n_per_cam: int, ts: int, tiles_x: int, tiles_y: int, n_tiles: int
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ids, offsets, counts) as ``_fused.bin_gaussians_fused`` builds them with
        ``_cpu_kernels.bin_lists``: depths (C*N,), means2d and radii (C*N, 2), all float32."""
        n = depths.shape[0]
        order = np.empty(n, dtype=np.int64)
        counts = np.zeros(n_tiles, dtype=np.int64)
        m = self._bin_count(_ptr(depths, np.float32), _ptr(means2d, np.float32),
                            _ptr(radii, np.float32), n, n_per_cam, ts, tiles_x, tiles_y,
                            _ptr(order, np.int64), _ptr(counts, np.int64))
        offsets = np.cumsum(counts) - counts
        ids = np.empty(int(counts.sum()), dtype=np.int64)
        fill = offsets.copy()
        self._bin_fill(_ptr(order, np.int64), m, _ptr(means2d, np.float32),
                       _ptr(radii, np.float32), n_per_cam, ts, tiles_x, tiles_y,
                       _ptr(fill, np.int64), _ptr(ids, np.int64))
        return ids, offsets, counts

    def project_forward(self, means: np.ndarray, quats: np.ndarray, scales: np.ndarray,
                        opacities: np.ndarray, viewmats: np.ndarray, Ks: np.ndarray, width: int,
                        height: int, near: float, far: float, eps2d: float, radius_clip: float,
                        means2d: np.ndarray, conics: np.ndarray, depths: np.ndarray,
                        radii: np.ndarray, threads: int, *, table: np.ndarray | None = None,
                        depth_column: int = -1) -> None:
        """``_cpu_project.project_forward`` in float32, on ``threads`` threads. With ``table``
        (C*N, F), the compositing table's columns 0..5 (mean, conic, opacity) and
        ``depth_column`` (the depth, if >= 0) are written too."""
        f32 = np.float32
        if table is not None and (table.shape[0] != means2d.shape[0] * means2d.shape[1]
                                  or not 6 <= table.shape[1] or depth_column >= table.shape[1]):
            raise ValueError(f"project_forward: a table of shape {table.shape} for "
                             f"{means2d.shape[:2]} projections (depth column {depth_column})")
        self._project(_ptr(means, f32), _ptr(quats, f32), _ptr(scales, f32),
                      _ptr(opacities, f32), _ptr(viewmats, f32), _ptr(Ks, f32), means.shape[0],
                      viewmats.shape[0], width, height, near, far, eps2d, radius_clip,
                      _ptr(means2d, f32), _ptr(conics, f32), _ptr(depths, f32),
                      _ptr(radii, np.int32), None if table is None else _ptr(table, f32),
                      0 if table is None else table.shape[1], depth_column, threads)

    def project_backward(self, means: np.ndarray, quats: np.ndarray, scales: np.ndarray,
                         viewmats: np.ndarray, Ks: np.ndarray, width: int, height: int,
                         near: float, far: float, eps2d: float, v_means2d: np.ndarray,
                         v_conics: np.ndarray, v_depths: np.ndarray, threads: int
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``_cpu_project.project_backward`` in float32 (v_means, v_quats, v_scales); the
        output gradients (C, N, 2), (C, N, 3) and (C, N, 1), or column slices of one table."""
        f32, N, C = np.float32, means.shape[0], viewmats.shape[0]
        out = (np.zeros((N, 3), f32), np.zeros((N, 4), f32), np.zeros((N, 3), f32))
        self._project_vjp(_ptr(means, f32), _ptr(quats, f32), _ptr(scales, f32),
                          _ptr(viewmats, f32), _ptr(Ks, f32), N, C, width, height, near, far,
                          eps2d, *_rows(v_means2d, 2, C * N), *_rows(v_conics, 3, C * N),
                          *_rows(v_depths, 1, C * N), *(_ptr(a, f32) for a in out), threads)
        return out

    def sh_forward(self, degree: int, means: np.ndarray, c0: np.ndarray, cN: np.ndarray,
                   campos: np.ndarray, visible: np.ndarray, colors: np.ndarray,
                   threads: int) -> None:
        """``_cpu_sh.sh_forward``: visible (C, N) bool, colors (C, N, 3) (or three columns of a
        table) filled."""
        f32, N, C = np.float32, means.shape[0], campos.shape[0]
        self._sh(degree, _ptr(means, f32), _ptr(c0, f32), _ptr(cN, f32), cN.shape[1],
                 _ptr(campos, f32), N, C, _ptr(visible.view(np.uint8), np.uint8),
                 *_rows(colors, 3, C * N), threads)

    def sh_backward(self, degree: int, means: np.ndarray, c0: np.ndarray, cN: np.ndarray,
                    campos: np.ndarray, colors: np.ndarray, v_colors: np.ndarray,
                    v_means: np.ndarray, v_c0: np.ndarray, v_cN: np.ndarray,
                    threads: int) -> None:
        """``_cpu_sh.sh_backward``, filling v_means, v_c0 and v_cN (float32; need not be
        zeroed); colors and v_colors (C, N, 3), or three columns of tables."""
        f32, N, C = np.float32, means.shape[0], campos.shape[0]
        self._sh_vjp(degree, _ptr(means, f32), _ptr(c0, f32), _ptr(cN, f32), cN.shape[1],
                     _ptr(campos, f32), N, C, *_rows(colors, 3, C * N),
                     *_rows(v_colors, 3, C * N), _ptr(v_means, f32), _ptr(v_c0, f32),
                     _ptr(v_cN, f32), threads)

    def grad_norms(self, grads: np.ndarray, scale: tuple[float, float], radii: np.ndarray,
                   grad2d: np.ndarray, count: np.ndarray, threads: int) -> None:
        """``DensifyStrategy.update_state``'s sums in place (the same bytes): for each camera's
        drawn Gaussians (radii (C, N) > 0), grad2d (N,) += the norm of grads (C, N, 2) (or two
        columns of a table) scaled by ``scale``, and count (N,) += 1."""
        C, N = radii.shape
        self._grad_norms(*_rows(grads, 2, C * N), C, N, scale[0], scale[1], _ptr(radii, np.int32),
                         _ptr(grad2d, np.float32), _ptr(count, np.float32), threads)

    def ssim_forward(self, x: np.ndarray, y: np.ndarray, taps: np.ndarray, c1: float, c2: float,
                     derivatives: bool, threads: int) -> tuple[np.ndarray, np.ndarray | None]:
        """Mean SSIM per image of x and y (B, H, W, C) float32 with the separable window ``taps``:
        (means (B,) float64, and when ``derivatives`` the (3, B, H, W, C) maps the backward
        takes)."""
        f32, (B, H, W, C) = np.float32, x.shape
        mean = np.empty(B, np.float64)
        d = np.empty((3, *x.shape), f32) if derivatives else None
        work = np.empty((5, *x.shape), f32)
        self._ssim(_ptr(x, f32), _ptr(y, f32), B, H, W, C, _ptr(taps, f32), taps.shape[0], c1, c2,
                   _ptr(work, f32), _ptr(mean, np.float64), None if d is None else _ptr(d, f32),
                   threads)
        return mean, d

    def ssim_backward(self, x: np.ndarray, y: np.ndarray, d: np.ndarray, taps: np.ndarray,
                      grad: np.ndarray, threads: int) -> np.ndarray:
        """The gradient with respect to x of sum_b grad[b] * (mean SSIM of image b), from the
        forward's maps ``d``."""
        f32, (B, H, W, C) = np.float32, x.shape
        g = np.empty(x.shape, f32)
        work = np.empty((3, *x.shape), f32)
        self._ssim_vjp(_ptr(x, f32), _ptr(y, f32), _ptr(d, f32), B, H, W, C, _ptr(taps, f32),
                       taps.shape[0], _ptr(grad, f32), _ptr(work, f32), _ptr(g, f32), threads)
        return g

    def fit_loss_terms(self, render: np.ndarray, alphas: np.ndarray, gt: np.ndarray,
                       sky: np.ndarray | None, sky_scale: float, pixels: np.ndarray,
                       target_inv: np.ndarray) -> np.ndarray:
        """The sums of the fit loss's terms, float64 (3,): L1 over the RGB values, the sky term
        over the sky pixels, the inverse-depth L1 over the LiDAR pixels. render (P, D) float32
        (RGB and, when D is 4, the accumulated depth), alphas (P,), gt (P, 3), sky (P,) bool or
        None, pixels (K,) int64 and target_inv (K,) float32."""
        f32 = np.float32
        terms = np.zeros(3, np.float64)
        self._loss_terms(_ptr(render, f32), _ptr(alphas, f32), _ptr(gt, f32), render.shape[0],
                         render.shape[1], None if sky is None else _ptr(sky, np.bool_), sky_scale,
                         _ptr(pixels, np.int64), _ptr(target_inv, f32), pixels.shape[0],
                         _ptr(terms, np.float64))
        return terms

    def fit_loss_backward(self, render: np.ndarray, alphas: np.ndarray, gt: np.ndarray,
                          g_ssim: np.ndarray, c_l1: float, sky: np.ndarray | None, g_sky: float,
                          sky_scale: float, pixels: np.ndarray, target_inv: np.ndarray,
                          g_depth: float) -> tuple[np.ndarray, np.ndarray]:
        """(d_render (P, D), d_alpha (P,)) of the fit loss; see pd_fit_loss_backward."""
        f32 = np.float32
        d_render = np.empty(render.shape, f32)
        d_alpha = np.empty(render.shape[0], f32)
        self._loss_vjp(_ptr(render, f32), _ptr(alphas, f32), _ptr(gt, f32), _ptr(g_ssim, f32),
                       render.shape[0], render.shape[1], c_l1,
                       None if sky is None else _ptr(sky, np.bool_), g_sky, sky_scale,
                       _ptr(pixels, np.int64), _ptr(target_inv, f32), pixels.shape[0], g_depth,
                       _ptr(d_render, f32), _ptr(d_alpha, f32))
        return d_render, d_alpha

    def place_forward(self, means: np.ndarray, quats: np.ndarray, opacities: np.ndarray,
                      rows: np.ndarray, node: np.ndarray, box: np.ndarray, nq: np.ndarray,
                      present: np.ndarray, threads: int
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``graph.place``'s Gaussians (the same bytes): copies of means (N, 3), quats (N, 4)
        and opacities (N,) with the ``rows`` (M,) of nodes ``node`` (M,) moved by their box
        (K, 4, 4) and turned by its rotation nq (K, 4), hidden where ``present`` (K,) is not."""
        f32, N = np.float32, means.shape[0]
        out = (np.empty((N, 3), f32), np.empty((N, 4), f32), np.empty(N, f32))
        self._place(_ptr(means, f32), _ptr(quats, f32), _ptr(opacities, f32), N,
                    *_node_rows(rows, node, box, nq, present), *(_ptr(a, f32) for a in out),
                    threads)
        return out

    def place_backward(self, g_means: np.ndarray | None, g_quats: np.ndarray | None,
                       g_opacities: np.ndarray | None, rows: np.ndarray, node: np.ndarray,
                       box: np.ndarray, nq: np.ndarray, present: np.ndarray, threads: int
                       ) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None]:
        """The gradients of :meth:`place_forward`'s means, quats and opacities from those of
        its outputs (None: not wanted), with autograd's bytes for ``graph.place``."""
        def like(g: np.ndarray | None) -> np.ndarray | None:
            return None if g is None else np.empty(g.shape, np.float32)

        grads = (g_means, g_quats, g_opacities)
        out = (like(g_means), like(g_quats), like(g_opacities))
        n = next(g.shape[0] for g in grads if g is not None)
        self._place_vjp(*(None if g is None else _ptr(g, np.float32) for g in grads), n,
                        *_node_rows(rows, node, box, nq, present),
                        *(None if a is None else _ptr(a, np.float32) for a in out), threads)
        return out

    def sum_by_gaussian(self, grads: np.ndarray, ids: np.ndarray, n: int,
                        threads: int) -> np.ndarray:
        """``_cpu_kernels.sum_by_gaussian`` of float32 rows (the same bytes), on ``threads``
        threads."""
        out = np.empty((n, grads.shape[1]), dtype=np.float32)
        self._sum(_ptr(grads, np.float32), _ptr(ids, np.int64), ids.shape[0], grads.shape[1], n,
                  _ptr(out, np.float32), threads)
        return out


def _node_rows(rows: np.ndarray, node: np.ndarray, box: np.ndarray, nq: np.ndarray,
               present: np.ndarray) -> tuple[int, int, int, int, int, int]:
    """The placement's row arguments, checked: rows and their nodes (M,) int64, the nodes' boxes
    (K, 4, 4) and rotations (K, 4) float32, present (K,) bool."""
    K = box.shape[0]
    if (rows.shape != node.shape or box.shape != (K, 4, 4) or nq.shape != (K, 4)
            or present.shape != (K,) or present.dtype != np.bool_):
        raise ValueError(f"place: rows {rows.shape}, nodes {node.shape}, boxes {box.shape}, "
                         f"rotations {nq.shape}, present {present.shape} {present.dtype}")
    return (_ptr(rows, np.int64), _ptr(node, np.int64), rows.shape[0], _ptr(box, np.float32),
            _ptr(nq, np.float32), _ptr(present.view(np.uint8), np.uint8))


def _entry(fn, restype, argtypes: list):
    """The library's function ``fn`` with its result and argument types set."""
    fn.restype, fn.argtypes = restype, argtypes
    return fn


def _reach(reach: np.ndarray, table: np.ndarray) -> int:
    """The address of a compositing call's per-row reach array (table rows, 2)."""
    if reach.shape != (table.shape[0], 2):
        raise ValueError(f"reach {reach.shape} does not match the table's {table.shape[0]} rows")
    return _ptr(reach, np.float32)


def _ptr(a: np.ndarray, dtype: type) -> int:
    """The address of ``a``'s data, which must be C-contiguous and of ``dtype`` (the kernels read
    and write it in place)."""
    if a.dtype != dtype or not a.flags.c_contiguous:
        raise TypeError(f"expected a C-contiguous {np.dtype(dtype).name} array, got "
                        f"{a.dtype} {'contiguous' if a.flags.c_contiguous else 'strided'}")
    return a.ctypes.data


def _rows(a: np.ndarray, width: int, rows: int) -> tuple[int, int]:
    """(address, distance between rows in floats) of ``rows`` rows of ``width`` float32 values:
    a C-contiguous array, or a slice of columns of a wider table (``table[:, 6:9]``), whose
    rows are evenly spaced; the kernels read and write it in place, without a strided copy."""
    ok = (a.dtype == np.float32 and a.ndim >= 1 and a.shape[-1] == width and a.size == rows * width
          and a.strides[-1] == 4)
    step = a.strides[-2] if a.ndim > 1 and a.shape[-2] > 1 else 4 * width
    ok = ok and step >= 4 * width and step % 4 == 0
    inner = step  # bytes from one row to the next, across the leading axes too
    for axis in range(a.ndim - 2, -1, -1):
        if a.shape[axis] > 1 and a.strides[axis] != inner:
            ok = False
        inner *= a.shape[axis]
    if not ok:
        raise TypeError(f"expected {rows} evenly spaced rows of {width} float32 values, got an "
                        f"array of shape {a.shape}, {a.dtype}, strides {a.strides}")
    return a.ctypes.data, step // 4


@functools.cache
def _load(extra: tuple[str, ...] = ()) -> Kernels | NativeBuildError:
    """The kernels built with the ``extra`` compiler flags, or the reason they are not there
    (kept, so a failed build is not retried on every call)."""
    try:
        cxx = _compiler()
        path = _library_path(cxx, extra)
        if not path.exists():
            _build(cxx, path, extra)
        _mark_used(path)
        try:
            return Kernels(ctypes.CDLL(str(path)), path)
        except OSError as exc:
            raise NativeBuildError(f"could not load {path}: {exc}; delete it to rebuild") from exc
    except NativeBuildError as exc:
        return exc


@functools.lru_cache(maxsize=1)
def _fallback_warning(reason: str) -> None:
    log.warning("vectorised kernels unavailable, using the Numba kernels: %s", reason)


def with_lanes(lanes: int) -> Kernels:
    """The library built with ``lanes`` float32 lanes a vector (4, 8 or 16) whatever the machine's
    vector unit, for checking the other units' vector layouts on this one (vectors wider than
    the unit run slowly, split by the compiler); NativeBuildError where it cannot be built."""
    if lanes not in (4, 8, 16):
        raise ValueError(f"lanes={lanes}: the kernels take 4, 8 or 16")
    kernels = _load((f"-DPD_LANES={lanes}", "-Wno-psabi"))
    if isinstance(kernels, NativeBuildError):
        raise kernels
    return kernels


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
