"""The fit's optimizer step: with the fused CPU kernels, every parameter's Adam in one native call.

A fit keeps one ``torch.optim.Adam`` per parameter (its own learning rate; densification edits
their moments). Stepping them one by one costs torch's per-call bookkeeping six times per
iteration and runs its fused CPU kernel on one thread. :func:`step` instead updates every
fused, float32, CPU Adam in one call of ``_composite.cpp``'s ``pd_adam_step`` on the kernels'
threads, reading and writing the optimizers' own state (``step``, ``exp_avg``, ``exp_avg_sq``),
so state dicts, resumes and densification see torch's layout. The arithmetic is Adam's in
float32 with the bias corrections in double, as torch's; the bytes do not depend on the thread
count, though they may differ from torch's kernel in the last bit. Other optimizers (plain,
CUDA, weight decay, amsgrad) take their own ``step()``.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import torch

from paradrive.devices import cpu_kernel_threads
from paradrive.gs import _native

__all__ = ["step"]


def _native_param(opt: torch.optim.Optimizer) -> torch.Tensor | None:
    """The parameter of a single-tensor fused float32 CPU Adam the kernel can step, else None."""
    if type(opt) is not torch.optim.Adam or len(opt.param_groups) != 1:
        return None
    group = opt.param_groups[0]
    if (len(group["params"]) != 1 or not group["fused"] or group["amsgrad"]
            or group["maximize"] or group["weight_decay"] != 0 or group["differentiable"]
            or isinstance(group["lr"], torch.Tensor)):
        return None
    p = group["params"][0]
    g = p.grad
    ok = (p.device.type == "cpu" and p.dtype == torch.float32 and p.is_contiguous()
          and g is not None and g.dtype == torch.float32 and g.is_contiguous()
          and g.shape == p.shape)
    return p if ok else None


def _state(opt: torch.optim.Optimizer, p: torch.Tensor) -> dict:
    """The parameter's Adam state, created as torch creates it for a fused Adam."""
    st = opt.state[p]
    if not st:
        st["step"] = torch.zeros((), dtype=torch.float32, device=p.device)
        st["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
        st["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
    return st


def step(optimizers: Iterable[torch.optim.Optimizer], kernels: bool = True) -> None:
    """Step every optimizer and clear its gradients (set to None). ``kernels``: whether the
    native Adam may step the ones it can (a fit on the fused CPU kernels); False steps all
    with torch (the torch-op backend, the reference the fused path is measured against)."""
    native = _native.load() if kernels else None
    batch: list[tuple[torch.optim.Optimizer, torch.Tensor]] = []
    for opt in optimizers:
        p = _native_param(opt) if native is not None else None
        if p is None:
            opt.step()
            opt.zero_grad(set_to_none=True)
        else:
            batch.append((opt, p))
    if not batch or native is None:
        return
    addresses = np.empty((len(batch), 4), dtype=np.int64)
    sizes = np.empty(len(batch), dtype=np.int64)
    settings = np.empty((len(batch), 5), dtype=np.float64)
    for k, (opt, p) in enumerate(batch):
        st = _state(opt, p)
        m, v = st["exp_avg"], st["exp_avg_sq"]
        if not (m.is_contiguous() and v.is_contiguous() and m.dtype == v.dtype == torch.float32):
            raise ValueError(f"Adam moments of a {tuple(p.shape)} parameter are not contiguous "
                             f"float32 ({m.dtype}, {v.dtype})")
        st["step"] += 1
        group = opt.param_groups[0]
        beta1, beta2 = group["betas"]
        assert p.grad is not None  # checked by _native_param
        addresses[k] = (p.data_ptr(), p.grad.data_ptr(), m.data_ptr(), v.data_ptr())
        sizes[k] = p.numel()
        settings[k] = (group["lr"], float(st["step"]), beta1, beta2, group["eps"])
    native.adam_step(addresses, sizes, settings, cpu_kernel_threads())
    for _, p in batch:
        p.grad = None
