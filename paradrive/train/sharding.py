"""Sharded data parallel training (``train.fsdp``): PyTorch's FSDP2 (``fully_shard``) in place of
DDP in a torchrun run of several processes.

Each process then keeps a 1/N shard of every weight, gradient and optimiser moment instead of a
whole copy. The model is one unit: its weights are gathered whole for each forward and backward
and freed after, so what the sharding saves is the resting weights, the gradients and AdamW's two
moments (for the 1.3B model, 5.2 GB of fp32 weights and 2 x 4 bytes a trained parameter, split
N ways), not the gathered weights during a step. Per-block units would free a block's weights
as soon as it has run, but the ReCamDriving forward reads a Wan block's pieces (its modulation
table, its norms) outside the block's own forward, where FSDP gathers them; so they are not
split. Frozen and trained parameters share the unit. What a checkpoint holds does not change: :func:`whole`
gathers every sharded tensor back into a whole one before rank 0 writes it, so a checkpoint of a
sharded run resumes on DDP or one process's model as well as on a sharded one.
"""

from __future__ import annotations

from typing import Any

import torch

__all__ = ["shard_training", "whole"]


def shard_training(model: torch.nn.Module, optimizer: Any,
                   ema: dict[str, torch.Tensor] | None) -> tuple[Any, dict[str, torch.Tensor] | None]:
    """Shard ``model`` in place over the process group and return the optimiser and EMA made over
    its sharded parameters: the same class, settings and parameter order, with the state (a
    resumed run's moments, the EMA) cut into the same shards as the parameters it belongs to.

    Every process of the group must call it, with the same model and state."""
    from torch.distributed.fsdp import fully_shard
    from torch.distributed.tensor import distribute_tensor

    names = {id(p): n for n, p in model.named_parameters()}
    order = [[names[id(p)] for p in group["params"]] for group in optimizer.param_groups]
    state = optimizer.state_dict()
    fully_shard(model)
    params = dict(model.named_parameters())

    def like(name: str, value: Any) -> Any:
        p: Any = params[name]   # a DTensor parameter now
        if isinstance(value, torch.Tensor) and value.shape == p.shape and value.dim() > 0:
            return distribute_tensor(value.to(device=p.device_mesh.device_type), p.device_mesh, p.placements)
        return value

    groups = [{k: v for k, v in group.items() if k != "params"} for group in optimizer.param_groups]
    # every setting is in the groups, so the class's own defaults are never used
    make: Any = type(optimizer)
    sharded = make([{**g, "params": [params[n] for n in names_]} for g, names_ in zip(groups, order)])
    flat = [n for names_ in order for n in names_]
    state["state"] = {i: {k: like(flat[i], v) for k, v in moments.items()} for i, moments in state["state"].items()}
    sharded.load_state_dict(state)
    if ema is not None:
        ema = {n: like(n, t) for n, t in ema.items()}
    return sharded, ema


def whole(value: Any) -> Any:
    """``value`` with every sharded tensor (DTensor) in it gathered into a whole one on the CPU
    (dicts and lists walked; other values as they are). Collective when anything is sharded:
    every process must call it, in the same order."""
    from torch.distributed.tensor import DTensor

    if isinstance(value, DTensor):
        return value.full_tensor().detach().cpu()
    if isinstance(value, dict):
        return {k: whole(v) for k, v in value.items()}
    if isinstance(value, list):
        return [whole(v) for v in value]
    return value
