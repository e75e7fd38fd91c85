"""Adaptive density control of the 3DGS paper (the semantics of gsplat's ``DefaultStrategy``).

Every ``refine_every`` steps in (``refine_start_iter``, ``refine_stop_iter``): Gaussians whose
average view-space positional gradient exceeds ``grow_grad2d`` are duplicated (small ones) or
split in two, sampled from the Gaussian itself (large ones); Gaussians with opacity below
``prune_opa`` (and, after the first reset, too large ones) are removed. Every ``reset_every``
steps opacities are clamped to ``2 * prune_opa``. ``max_gaussians`` bounds the count: when the
candidates would exceed it, the ones with the largest gradients win.

Sky-dome Gaussians (``state["is_sky"]``) are left alone: never grown, pruned or reset. Other
per-Gaussian state (a scene graph's ``node``) follows its Gaussians through every change; a split
samples its children in the Gaussian's own frame, so actor nodes densify in their box frames.

The mutable state is an explicit dict of tensors, saved with the fit for exact resumption.
Every topology change is expressed as an index map (new Gaussian i comes from old ``index[i]``)
applied alike to parameters, optimizer moments (zeroed for new Gaussians) and per-Gaussian state.

Credit: the density control of 3D Gaussian Splatting (Kerbl et al., ACM TOG 2023), re-implemented
with the semantics and defaults of gsplat's ``DefaultStrategy`` (nerfstudio-project/gsplat).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from .model import logit
from .rasterize import quat_to_rotmat

__all__ = ["DensifyStrategy"]


def split_noise(generator: torch.Generator, n: int, device: torch.device) -> torch.Tensor:
    """(2, n, 3) standard normal samples for the two children of n split Gaussians.

    Drawn from ``generator`` on its own device (the fit keeps a CPU generator, so a resumed fit
    draws the same numbers on any machine), then moved to ``device``.
    """
    return torch.randn(2, n, 3, generator=generator, device=generator.device).to(device)


@torch.no_grad()
def remap(params: dict[str, torch.nn.Parameter], optimizers: dict[str, torch.optim.Optimizer],
          state: dict[str, Any], index: torch.Tensor, is_new: torch.Tensor,
          values: dict[str, torch.Tensor] | None = None) -> None:
    """Re-index every per-Gaussian tensor in place of the dicts.

    index: (M,) source Gaussian of each new one; is_new: (M,) bool, True where Adam moments start
    at zero; values: replacement parameter data for some keys (already re-indexed, (M, ...)).
    """
    values = values or {}
    n_old = params["means"].shape[0]
    for key in list(params.keys()):
        old = params[key]
        data = values[key] if key in values else old.data.index_select(0, index)
        new = torch.nn.Parameter(data.contiguous(), requires_grad=old.requires_grad)
        opt = optimizers[key]
        st = opt.state.pop(old, None)
        if st is not None:
            for name in ("exp_avg", "exp_avg_sq"):
                if name in st:
                    m = st[name].index_select(0, index)
                    st[name] = m.masked_fill_(is_new.view(-1, *[1] * (m.dim() - 1)), 0.0)
            opt.state[new] = st
        opt.param_groups[0]["params"] = [new]
        params[key] = new
    for key, v in list(state.items()):
        if isinstance(v, torch.Tensor) and v.dim() >= 1 and v.shape[0] == n_old:
            state[key] = v.index_select(0, index)


class _Changes:
    """The topology changes of one refinement (duplicate, split, prune) composed into one index
    map from the Gaussians before them, so that the parameters, moments and state are gathered
    once (each gather of a 150k-Gaussian model's SH moments costs tens of milliseconds).

    ``data(key)`` is a parameter as the changes so far left it; ``then(index, is_new, values)``
    adds a change as :func:`remap` takes it (``index`` into the Gaussians after the changes so
    far).
    """

    def __init__(self, params: dict[str, torch.nn.Parameter], state: dict[str, Any]) -> None:
        self.params, self.state = params, state
        n, dev = params["means"].shape[0], params["means"].device
        self.index = torch.arange(n, device=dev)
        self.is_new = torch.zeros(n, dtype=torch.bool, device=dev)
        self.values: dict[str, torch.Tensor] = {}
        self.changed = False

    def data(self, key: str, rows: torch.Tensor | None = None) -> torch.Tensor:
        """Parameter ``key`` (its ``rows``, or all) after the changes so far."""
        if key in self.values:
            return self.values[key] if rows is None else self.values[key][rows]
        return self.params[key].data[self.index if rows is None else self.index[rows]]

    def sky(self) -> torch.Tensor:
        return self.state["is_sky"][self.index]

    def then(self, index: torch.Tensor, is_new: torch.Tensor,
             values: dict[str, torch.Tensor] | None = None) -> None:
        self.index, self.is_new = self.index[index], self.is_new[index] | is_new
        self.values = {k: v[index] for k, v in self.values.items()} | (values or {})
        self.changed = True

    def apply(self, optimizers: dict[str, torch.optim.Optimizer]) -> None:
        if self.changed:
            remap(self.params, optimizers, self.state, self.index, self.is_new, self.values)


def _native_sums(grads: torch.Tensor, scale: tuple[float, float], radii: torch.Tensor,
                 state: dict[str, Any]) -> bool:
    """``update_state``'s sums in one pass of the native kernels (its torch operations are a
    dozen, about 0.5 ms a fit iteration at 40k Gaussians). False, with
    nothing done, where the library is missing or the tensors are not float32 CPU ones (radii
    int32 (C, N)) in the layouts it reads."""
    from paradrive.devices import cpu_kernel_threads
    from paradrive import kernels

    grad2d, count = state["grad2d"], state["count"]
    tensors = (grads, radii, grad2d, count)
    if (any(t.device.type != "cpu" for t in tensors) or radii.dim() != 2
            or radii.dtype != torch.int32 or not radii.is_contiguous()
            or any(t.dtype != torch.float32 for t in (grads, grad2d, count))
            or not (grad2d.is_contiguous() and count.is_contiguous())):
        return False
    native = kernels.load()
    if native is None:
        return False
    try:
        native.grad_norms(grads.detach().numpy(), *scale, radii.numpy(), grad2d.numpy(),
                          count.numpy(), cpu_kernel_threads())
    except TypeError:  # rows not evenly spaced
        return False
    return True


@dataclass
class DensifyStrategy:
    """3DGS densification knobs (defaults: the 3DGS paper / gsplat DefaultStrategy)."""

    prune_opa: float = 0.005
    grow_grad2d: float = 0.0002
    grow_scale3d: float = 0.01
    prune_scale3d: float = 0.1
    refine_start_iter: int = 500
    refine_stop_iter: int = 15_000
    reset_every: int = 3000
    refine_every: int = 100
    max_gaussians: int = 0  # 0: no cap

    def initialize_state(self, n: int, scene_scale: float, is_sky: torch.Tensor | None = None,
                         device: torch.device | str = "cpu") -> dict[str, Any]:
        """Accumulators for ``n`` Gaussians on ``device`` (``is_sky``: (n,) bool, moved there)."""
        return {
            "grad2d": torch.zeros(n, device=device),
            "count": torch.zeros(n, device=device),
            "is_sky": (torch.zeros(n, dtype=torch.bool, device=device) if is_sky is None
                       else is_sky.to(device=device, copy=True)),
            "scene_scale": float(scene_scale),
        }

    @torch.no_grad()
    def update_state(self, state: dict[str, Any], info: dict[str, Any]) -> None:
        """Accumulate the view-space gradient norms of ``info['means2d']`` (C, M, 2).

        ``info['gaussian_ids']`` (M,), when set, maps the rendered Gaussians to the model's (a
        scene-graph frame renders only the nodes present at it); None or absent = all of them.
        """
        m2d = info["means2d"]
        if m2d.grad is None:
            return
        c = info["n_cameras"]
        scale = (info["width"] / 2.0 * c, info["height"] / 2.0 * c)
        radii = info["radii"]
        ids = info.get("gaussian_ids")
        if ids is None and _native_sums(m2d.grad, scale, radii, state):
            return
        grads = m2d.grad.detach().clone()
        grads[..., 0] *= scale[0]
        grads[..., 1] *= scale[1]
        visible = radii > 0 if radii.dim() == 2 else (radii > 0).all(-1)   # (C, N)
        norms = torch.where(visible, grads.norm(dim=-1), torch.zeros_like(grads[..., 0]))
        if ids is None:
            state["grad2d"] += norms.sum(0)
            state["count"] += visible.float().sum(0)
        else:
            state["grad2d"].index_add_(0, ids, norms.sum(0))
            state["count"].index_add_(0, ids, visible.float().sum(0))

    @torch.no_grad()
    def step_post_backward(self, params, optimizers, state: dict[str, Any], step: int,
                           info: dict[str, Any], generator: torch.Generator) -> dict[str, int]:
        """Call after ``loss.backward()`` and the optimizer step of 0-based iteration ``step``.

        Returns counts of what changed this step (duplicated, split, pruned, reset).
        """
        out = {"duplicated": 0, "split": 0, "pruned": 0, "reset": 0}
        if step >= self.refine_stop_iter:
            return out
        self.update_state(state, info)
        if step > self.refine_start_iter and step % self.refine_every == 0:
            changes = _Changes(params, state)
            out["duplicated"], out["split"] = self._grow(changes, generator)
            out["pruned"] = self._prune(changes, step)
            changes.apply(optimizers)
            state["grad2d"].zero_()
            state["count"].zero_()
        if step > 0 and step % self.reset_every == 0:
            self._reset_opacity(params, optimizers, state)
            out["reset"] = 1
        return out

    def _grow(self, changes: _Changes, generator: torch.Generator) -> tuple[int, int]:
        params, state = changes.params, changes.state
        n = params["means"].shape[0]
        dev = params["means"].device
        grads = state["grad2d"] / state["count"].clamp_min(1)
        high = (grads > self.grow_grad2d) & ~state["is_sky"]
        if self.max_gaussians > 0:
            budget = max(0, self.max_gaussians - n)
            if int(high.sum()) > budget:
                ranked = torch.argsort(torch.where(high, grads, torch.full_like(grads, -1.0)),
                                       descending=True, stable=True)
                keep = torch.zeros_like(high)
                keep[ranked[:budget]] = True
                high &= keep
        small = torch.exp(params["scales"]).max(-1).values <= self.grow_scale3d * state["scene_scale"]
        dup = high & small
        spl = high & ~small
        n_dup, n_split = int(dup.sum()), int(spl.sum())
        if n_dup:
            sel = torch.nonzero(dup).squeeze(1)
            changes.then(torch.cat([torch.arange(n, device=dev), sel]),
                         torch.cat([torch.zeros(n, dtype=torch.bool, device=dev),
                                    torch.ones(n_dup, dtype=torch.bool, device=dev)]))
            spl = torch.cat([spl, torch.zeros(n_dup, dtype=torch.bool, device=dev)])
        if n_split:
            rest = torch.nonzero(~spl).squeeze(1)
            sel = torch.nonzero(spl).squeeze(1)
            scales = torch.exp(changes.data("scales", sel))                    # (S, 3)
            rot = quat_to_rotmat(changes.data("quats", sel))                   # (S, 3, 3)
            noise = split_noise(generator, n_split, dev) * scales               # (2, S, 3)
            offsets = torch.einsum("sij,bsj->bsi", rot, noise).reshape(-1, 3)
            means = torch.cat([changes.data("means", rest),
                               changes.data("means", sel).repeat(2, 1) + offsets])
            new_scales = torch.cat([changes.data("scales", rest),
                                    torch.log(scales / 1.6).repeat(2, 1)])
            changes.then(torch.cat([rest, sel, sel]),
                         torch.cat([torch.zeros(len(rest), dtype=torch.bool, device=dev),
                                    torch.ones(2 * n_split, dtype=torch.bool, device=dev)]),
                         {"means": means, "scales": new_scales})
        return n_dup, n_split

    def _prune(self, changes: _Changes, step: int) -> int:
        prune = torch.sigmoid(changes.data("opacities")) < self.prune_opa
        if step > self.reset_every:
            big = (torch.exp(changes.data("scales")).max(-1).values
                   > self.prune_scale3d * changes.state["scene_scale"])
            prune |= big
        prune &= ~changes.sky()
        n_prune = int(prune.sum())
        if n_prune:
            keep = torch.nonzero(~prune).squeeze(1)
            changes.then(keep, torch.zeros(len(keep), dtype=torch.bool, device=keep.device))
        return n_prune

    def _reset_opacity(self, params, optimizers, state) -> None:
        p = params["opacities"]
        cap = float(logit(2.0 * self.prune_opa))
        reset = ~state["is_sky"]
        p.data[reset] = p.data[reset].clamp_max(cap)
        st = optimizers["opacities"].state.get(p)
        if st:
            for name in ("exp_avg", "exp_avg_sq"):
                if name in st:
                    st[name][reset] = 0.0
