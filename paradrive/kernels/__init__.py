"""The fused CPU rasterizer's kernels (``_composite.cpp`` with its bindings ``_bindings.cpp``),
compiled when the package is installed into one extension module per instruction set:
``_kernels_avx512``, ``_kernels_avx2`` and ``_kernels_base`` (the platform's baseline, 128-bit
vectors). :func:`load` imports the widest one that was built and that this CPU runs (as torch
reports it: ``torch.backends.cpu.get_cpu_capability()``, which ``ATEN_CPU_CAPABILITY`` can
lower), so one wheel or cluster image serves machines of every kind. Nothing is compiled at run
time.

``PARADRIVE_KERNELS`` chooses: ``auto`` (default: these kernels, the torch-op rasterizer where
none was built), ``native`` (these kernels or an error) or ``torch`` (the torch operations).
"""

from __future__ import annotations

import functools
import importlib
import logging
import os
import types

import torch

__all__ = ["NativeUnavailable", "Kernels", "kernel_choice", "load", "runnable", "variant"]

log = logging.getLogger(__name__)

CHOICES = ("auto", "native", "torch")
# Widest first; each runs on the CPUs torch reports with these capabilities (the baseline on all).
VARIANTS = ("avx512", "avx2", "base")
_CAPABLE: dict[str, tuple[str, ...] | None] = {"avx512": ("AVX512",), "avx2": ("AVX512", "AVX2"),
                                               "base": None}
FIX = ("install a C++ compiler (Debian: apt-get install g++) and reinstall paradrive "
       "(pip install --force-reinstall --no-deps .), or set PARADRIVE_KERNELS=torch")

# A built variant: the extension module, whose functions take numpy arrays (see _bindings.cpp).
Kernels = types.ModuleType


class NativeUnavailable(RuntimeError):
    """The kernels were not built at install, or not for this CPU."""


def kernel_choice() -> str:
    """``PARADRIVE_KERNELS``, checked."""
    choice = os.environ.get("PARADRIVE_KERNELS", "auto").strip().lower() or "auto"
    if choice not in CHOICES:
        raise ValueError(f"PARADRIVE_KERNELS={choice!r}: use one of {', '.join(CHOICES)}")
    return choice


def runnable() -> tuple[str, ...]:
    """The variants this CPU runs, widest first, built or not."""
    capability = torch.backends.cpu.get_cpu_capability()
    return tuple(v for v in VARIANTS if capability in (_CAPABLE[v] or (capability,)))


@functools.cache
def _import(name: str) -> Kernels | NativeUnavailable:
    if name not in VARIANTS:
        return NativeUnavailable(f"no kernel variant {name!r}; the variants are {', '.join(VARIANTS)}")
    if name not in runnable():
        return NativeUnavailable(f"the {name} kernels do not run on this CPU "
                                 f"({torch.backends.cpu.get_cpu_capability()})")
    try:
        return importlib.import_module(f"paradrive.kernels._kernels_{name}")
    except ImportError as exc:
        return NativeUnavailable(f"the {name} kernels were not built at install ({exc}); {FIX}")


def variant(name: str) -> Kernels:
    """The kernels built for instruction set ``name`` (one of VARIANTS); NativeUnavailable where
    they were not built or this CPU cannot run them."""
    kernels = _import(name)
    if isinstance(kernels, NativeUnavailable):
        raise kernels
    return kernels


@functools.cache
def _widest() -> Kernels | NativeUnavailable:
    for name in runnable():
        kernels = _import(name)
        if not isinstance(kernels, NativeUnavailable):
            return kernels
    return NativeUnavailable(f"the CPU kernels were not built at install; {FIX}")


@functools.lru_cache(maxsize=1)
def _fallback_warning(reason: str) -> None:
    log.warning("paradrive: fused CPU kernels unavailable, using the torch-op rasterizer "
                "(about 10x slower): %s", reason)


def load() -> Kernels | None:
    """The widest built kernels this CPU runs, or None where ``PARADRIVE_KERNELS`` asks for the
    torch operations or (``auto``, with one warning) none were built; ``native`` raises
    NativeUnavailable instead."""
    choice = kernel_choice()
    if choice == "torch":
        return None
    kernels = _widest()
    if not isinstance(kernels, NativeUnavailable):
        return kernels
    if choice == "native":
        raise kernels
    _fallback_warning(str(kernels))
    return None
