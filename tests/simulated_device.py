"""A stand-in accelerator for CPU-only machines: tensors that live "on another device".

The development machines and CI have no GPU, yet most users fit on CUDA, where joining a CPU
tensor with a device tensor is an error. :func:`simulated_device` makes a second device out of
the CPU so that this class of bug fails here too:

* inside the context, a tensor created with ``device=DEVICE`` (or moved there with ``.to``) is a
  :class:`OnDevice` wrapper: its ``.device`` is ``DEVICE`` while its values live in a CPU tensor,
  so the code computes exactly what it computes on the CPU;
* every operation checks its tensor arguments as CUDA's kernels do: wrapped and plain CPU tensors
  may not meet, except 0-dim CPU tensors (scalars), CPU index tensors, copies between devices and
  ``torch.Generator`` s of the same device type as the tensor they fill;
* the results of an operation on wrapped tensors are wrapped again.

``DEVICE`` is the ``meta`` device: unlike a fake ``cuda`` one, it needs no device runtime in
torch's autograd engine, so a whole fit (forward, backward, Adam, densification) runs through it.
Everything stays on the host: no real meta tensor (which holds no data) is ever made.
"""

from __future__ import annotations

from contextlib import contextmanager
from typing import Any
from collections.abc import Iterator

import torch
from torch.utils import _pytree as pytree
from torch.overrides import TorchFunctionMode
from torch.utils._python_dispatch import TorchDispatchMode

DEVICE = torch.device("meta")

aten = torch.ops.aten
# ops whose tensor arguments may sit on different devices in CUDA too
_CROSS_DEVICE = {aten.copy_.default, aten._to_copy.default, aten._copy_from.default,
                 aten.lift_fresh.default, aten.lift_fresh_copy.default}
# ops whose index tensors may stay on the CPU while the indexed tensor is on the device
_INDEXING = {aten.index.Tensor, aten.index_put_.default, aten.index_put.default,
             aten._index_put_impl_.default, aten._unsafe_index.Tensor}


class DeviceMismatch(RuntimeError):
    """Tensors on different devices met in one operation (what CUDA raises too)."""


class OnDevice(torch.Tensor):
    """A tensor whose ``.device`` is :data:`DEVICE`; its values are the CPU tensor ``elem``."""

    elem: torch.Tensor

    @staticmethod
    def __new__(cls, elem: torch.Tensor) -> OnDevice:
        r = torch.Tensor._make_wrapper_subclass(
            cls, elem.size(), strides=elem.stride(), storage_offset=elem.storage_offset(),
            dtype=elem.dtype, layout=elem.layout, device=DEVICE, requires_grad=elem.requires_grad)
        r.elem = elem
        return r

    __torch_function__ = torch._C._disabled_torch_function_impl

    def __repr__(self) -> str:  # noqa: D105
        return f"OnDevice({self.elem!r})"

    @classmethod
    def __torch_dispatch__(cls, func, types, args=(), kwargs=None):
        return _dispatch(func, args, kwargs or {})


def _check_generator(func, kwargs: dict, target: torch.device) -> None:
    gen = kwargs.get("generator")
    if gen is not None and gen.device.type != target.type:
        raise DeviceMismatch(f"{func}: a {gen.device.type} generator cannot fill a tensor on "
                             f"{target} (draw on the generator's device, then move the result)")


def _check_devices(func, args, kwargs) -> bool:
    """True when a wrapped tensor takes part; DeviceMismatch when a CPU tensor meets it."""
    if func in _INDEXING:
        main = [args[0]] + ([args[2]] if len(args) > 2 and isinstance(args[2], torch.Tensor) else [])
        indices = [t for t in (args[1] if len(args) > 1 else []) if isinstance(t, torch.Tensor)]
        flat = main
        on_device = any(isinstance(t, OnDevice) for t in main)
        stray = [t for t in indices if isinstance(t, OnDevice) and not on_device]
        if stray:
            raise DeviceMismatch(f"{func}: indices on {DEVICE} index a CPU tensor")
    else:
        flat = [a for a in pytree.tree_leaves((args, kwargs)) if isinstance(a, torch.Tensor)]
    wrapped = [t for t in flat if isinstance(t, OnDevice)]
    if not wrapped or func in _CROSS_DEVICE:
        return bool(wrapped)
    cpu = [t for t in flat if not isinstance(t, OnDevice) and t.dim() > 0]
    if cpu:
        shapes = ", ".join(str(tuple(t.shape)) for t in cpu)
        raise DeviceMismatch(f"Expected all tensors to be on the same device, but found at least "
                             f"two devices, {DEVICE} and cpu! ({func}: CPU tensors of shape {shapes})")
    return True


def _check_no_bare_meta(func, args, kwargs) -> None:
    """torch builds some tensors below the dispatcher (a Python list used as an index becomes an
    index tensor on the indexed tensor's device): on the stand-in those are real meta tensors that
    hold no values, so they are refused rather than read as garbage."""
    for t in pytree.tree_leaves((args, kwargs)):
        if isinstance(t, torch.Tensor) and not isinstance(t, OnDevice) and t.device.type == DEVICE.type:
            raise DeviceMismatch(f"{func}: a tensor made on {DEVICE} outside the stand-in (index with "
                                 "a tensor made with device=..., not a Python list)")


def _dispatch(func, args, kwargs):
    _check_no_bare_meta(func, args, kwargs)
    if kwargs.get("device") is not None:   # a factory, or a copy to a named device
        target = torch.device(kwargs["device"])
        if target.type == DEVICE.type:
            _check_generator(func, kwargs, target)
            kwargs = {**kwargs, "device": torch.device("cpu")}
    elif func is aten._to_copy.default:     # a dtype change keeps the device
        target = DEVICE if isinstance(args[0], OnDevice) else torch.device("cpu")
    else:
        target = DEVICE if _check_devices(func, args, kwargs) else torch.device("cpu")
    inputs = {id(a.elem): a for a in pytree.tree_leaves((args, kwargs)) if isinstance(a, OnDevice)}
    args, kwargs = pytree.tree_map_only(OnDevice, lambda t: t.elem, (args, kwargs))
    out = func(*args, **kwargs)
    if target.type != DEVICE.type:
        return out

    def wrap(t: torch.Tensor) -> torch.Tensor:
        own = inputs.get(id(t))   # in-place ops hand back their own wrapper
        return OnDevice(t) if own is None else own
    return pytree.tree_map_only(torch.Tensor, wrap, out)


class _SimulatedDeviceMode(TorchDispatchMode):
    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        return _dispatch(func, args, kwargs or {})


def _lists_to_cpu_indices(index: Any) -> Any:
    if isinstance(index, list):
        return torch.tensor(index)
    if isinstance(index, tuple):
        return tuple(_lists_to_cpu_indices(i) for i in index)
    return index


class _DataOnHostMode(TorchFunctionMode):
    """torch builds tensors from Python data below the dispatcher, straight on the target device
    (``torch.tensor(data, device=...)``, a Python list used as an index): on the stand-in they
    would be meta tensors without values. Build them on the CPU and move them through the
    dispatcher instead; CUDA accepts CPU index tensors."""

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func in (torch.tensor, torch.as_tensor) and kwargs.get("device") is not None \
                and torch.device(kwargs["device"]).type == DEVICE.type:
            return func(*args, **{**kwargs, "device": "cpu"}).to(DEVICE)
        if func in (torch.Tensor.__getitem__, torch.Tensor.__setitem__):
            args = (args[0], _lists_to_cpu_indices(args[1]), *args[2:])
        return func(*args, **kwargs)


@contextmanager
def simulated_device() -> Iterator[torch.device]:
    """Within the context :data:`DEVICE` behaves as an accelerator holding real values."""
    with _DataOnHostMode(), _SimulatedDeviceMode():
        yield DEVICE


def to_cpu(x: Any) -> Any:
    """Unwrap every :class:`OnDevice` in a nested structure (for assertions)."""
    return pytree.tree_map_only(OnDevice, lambda t: t.elem, x)
