"""Where tensors live and which rasterizer draws them: one decision for fit, render, eval and train.

``device`` parameters read ``auto`` (CUDA when torch sees a GPU, else the CPU), ``cpu``, ``cuda``
or any torch device (``cuda:1``). ``backend`` parameters read ``auto`` (gsplat's CUDA kernels for
tensors on CUDA when its extension loads; the fused CPU kernels for tensors on the CPU; else the
torch-op rasterizer), ``cpu`` (the fused kernels), ``torch`` (the torch-op reference) or ``gsplat``.
"""

from __future__ import annotations

import logging
from functools import lru_cache, cache

import torch

from paradrive.errors import ConfigError

__all__ = ["resolve_device", "resolve_backend", "gsplat_status", "cpu_kernel_threads",
           "set_cpu_kernel_threads", "BACKENDS"]

BACKENDS = ("auto", "cpu", "torch", "gsplat")
log = logging.getLogger("paradrive.devices")

_cpu_kernel_threads = 0  # 0: torch's count


def cpu_kernel_threads() -> int:
    """Threads of the fused CPU kernels: the count set by :func:`set_cpu_kernel_threads`, else
    torch's. Their results do not depend on it."""
    return _cpu_kernel_threads or torch.get_num_threads()


def set_cpu_kernel_threads(n: int) -> int:
    """Run the fused CPU kernels on ``n`` threads (0: torch's count); returns the old setting."""
    global _cpu_kernel_threads
    old, _cpu_kernel_threads = _cpu_kernel_threads, max(int(n), 0)
    return old


def resolve_device(name: str) -> torch.device:
    """The torch device a ``device`` parameter names; ConfigError for CUDA on a machine without it."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except (RuntimeError, TypeError) as exc:
        raise ConfigError(f"device {name!r} is not a torch device ({exc}); use auto, cpu or cuda") from exc
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"device {name!r} asked for, but torch sees no CUDA GPU on this machine; "
                          "use device: auto (or cpu), or install a CUDA build of torch")
    return device


@lru_cache(maxsize=1)
def gsplat_status() -> tuple[bool, str]:
    """(True, "") when gsplat's compiled CUDA extension loads, else (False, why not). Checked once."""
    if not torch.cuda.is_available():
        return False, "torch sees no CUDA GPU"
    try:
        from gsplat.cuda._backend import _C
    except ImportError as exc:
        return False, f"gsplat is not installed or does not import ({exc}); pip install 'paradrive[gpu]'"
    except Exception as exc:  # a failed JIT build or a driver mismatch raises anything
        return False, f"gsplat's CUDA extension failed to load ({type(exc).__name__}: {exc})"
    if _C is None:
        return False, "gsplat's CUDA extension did not build (gsplat.cuda._backend._C is None)"
    return True, ""


def resolve_backend(name: str, device: torch.device) -> str:
    """The rasterizer backend (``cpu``, ``torch`` or ``gsplat``) for tensors on ``device``.

    ``auto`` on a CUDA device without a working gsplat falls back to the (much slower) torch
    rasterizer with a warning that says why; an explicit ``gsplat`` that cannot run is an error.
    """
    if name not in BACKENDS:
        raise ConfigError(f"backend {name!r}: expected one of {', '.join(BACKENDS)}")
    if name in ("auto", "cpu") and device.type == "cpu":
        return "cpu"
    if name == "torch" or (name == "auto" and device.type != "cuda"):
        return "torch"
    if name == "cpu":
        raise ConfigError(f"backend cpu runs the fused CPU kernels, but the tensors are on {device}; "
                          "use device: cpu, or backend: auto")
    if device.type != "cuda":
        raise ConfigError(f"backend gsplat needs a CUDA device, but the tensors are on {device}; "
                          "use backend: auto or torch, or device: cuda")
    ok, why = gsplat_status()
    if ok:
        return "gsplat"
    if name == "gsplat":
        raise ConfigError(f"backend gsplat asked for, but {why}; use backend: auto or torch")
    _warn_fallback(str(device), why)
    return "torch"


@cache
def _warn_fallback(device: str, why: str) -> None:
    """Once per process and device: the rasterizer is called every iteration."""
    log.warning("gsplat cannot rasterize on %s: %s; falling back to the torch rasterizer "
                "(correct but far slower on a GPU)", device, why)
