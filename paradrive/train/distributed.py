"""Data-parallel training across processes: which process this is, and what they share.

A run on N processes is started by ``torchrun --nproc_per_node N`` (one node) or with its
``--nnodes`` / rendezvous options (several); torchrun sets ``RANK``, ``WORLD_SIZE`` and
``LOCAL_RANK`` in each process, and :func:`join` reads them and joins the process group:
NCCL when the run trains on CUDA, gloo on CPUs. Without them the run is one process and nothing
is initialised.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch

from paradrive.errors import ConfigError


@dataclass(frozen=True)
class World:
    """This process's place among the run's processes."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0

    @property
    def main(self) -> bool:
        """Rank 0: the one process that writes checkpoints, metrics and progress lines."""
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world_size > 1


def _env_int(name: str, default: int) -> int:
    raw = os.environ.get(name)
    if raw is None:
        return default
    try:
        return int(raw)
    except ValueError as exc:
        raise ConfigError(f"environment {name}={raw!r} is not a whole number; start the run with "
                          f"torchrun (it sets RANK, WORLD_SIZE and LOCAL_RANK)") from exc


def world_from_env() -> World:
    """The :class:`World` torchrun's environment describes (one process when it is not set)."""
    world = World(_env_int("RANK", 0), _env_int("WORLD_SIZE", 1), _env_int("LOCAL_RANK", 0))
    if not 0 <= world.rank < world.world_size:
        raise ConfigError(f"RANK={world.rank} is outside WORLD_SIZE={world.world_size}; start the run "
                          f"with torchrun --nproc_per_node N")
    return world


def join(device: torch.device) -> World:
    """Join the run's process group (once per process) and return this process's place. NCCL
    for a CUDA ``device``, gloo otherwise."""
    world = world_from_env()
    if world.distributed and not torch.distributed.is_initialized():
        backend = "nccl" if device.type == "cuda" else "gloo"
        torch.distributed.init_process_group(backend=backend, rank=world.rank, world_size=world.world_size)
    return world


def device_for(device: torch.device, world: World) -> torch.device:
    """The device of this process: ``cuda`` means this process's GPU (``cuda:LOCAL_RANK``) in a run
    of several processes; any other device is used as named."""
    if device.type == "cuda" and world.distributed and device.index is None:
        return torch.device("cuda", world.local_rank)
    return device


def mean_over_ranks(value: float, world: World, device: torch.device) -> float:
    """The mean of ``value`` over every process (the value itself in a one-process run)."""
    if not world.distributed:
        return value
    kind = device if device.type == "cuda" else torch.device("cpu")
    total = torch.tensor([value], dtype=torch.float64, device=kind)
    torch.distributed.all_reduce(total)
    return float(total.item()) / world.world_size


def all_agree(flag: bool, world: World) -> bool:
    """True when ``flag`` holds on every process (one process: ``flag``)."""
    if not world.distributed:
        return flag
    backend = torch.distributed.get_backend()
    device = torch.device("cuda", torch.cuda.current_device()) if backend == "nccl" else torch.device("cpu")
    value = torch.tensor([0 if flag else 1], dtype=torch.int64, device=device)
    torch.distributed.all_reduce(value)
    return int(value.item()) == 0


def barrier(world: World) -> None:
    """Wait until every process reaches this point (nothing in a one-process run)."""
    if world.distributed:
        torch.distributed.barrier()


def leave() -> None:
    """Leave the process group, if this process joined one."""
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        torch.distributed.destroy_process_group()
