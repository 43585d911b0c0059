"""Data-parallel training under ``torchrun`` (torch DistributedDataParallel).

``prml2 train`` is the same command on one process and under
``torchrun --nproc_per_node N -m prml2_edge.cli.main train ...``: when torchrun's environment
(``WORLD_SIZE`` > 1) is present, :func:`init` joins the process group (gloo on CPU, nccl on
CUDA), every rank reads the same data, takes its shard of each epoch's shuffled windows
(:func:`shard`), and DDP averages the gradients, so all ranks keep identical weights. Only rank
0 writes checkpoints, logs and plots.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import torch
import torch.distributed as dist


@dataclass(frozen=True)
class DistInfo:
    """Where this process stands: ``rank`` of ``world_size``; ``enabled`` when a process group is up."""

    rank: int = 0
    world_size: int = 1
    enabled: bool = False

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def init(backend: str | None = None) -> DistInfo:
    """Join the process group torchrun describes in the environment; a no-op on a single process."""
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    if world_size <= 1:
        return DistInfo()
    if not dist.is_initialized():
        backend = backend or ("nccl" if torch.cuda.is_available() else "gloo")
        dist.init_process_group(backend=backend)
    return DistInfo(rank=dist.get_rank(), world_size=dist.get_world_size(), enabled=True)


def shutdown(info: DistInfo) -> None:
    """Leave the process group (if this module joined one)."""
    if info.enabled and dist.is_initialized():
        dist.barrier()
        dist.destroy_process_group()


def shard(indices: np.ndarray, info: DistInfo) -> np.ndarray:
    """This rank's share of ``indices`` (N,): every rank gets the same count (wrapping round).

    Equal counts mean equal numbers of optimizer steps, which DDP needs (each step all-reduces).
    """
    if info.world_size == 1:
        return indices
    n = len(indices)
    per_rank = -(-n // info.world_size)  # ceil
    padded = np.resize(indices, per_rank * info.world_size)  # repeats from the start
    return padded[info.rank :: info.world_size]


def all_reduce_sum(values: torch.Tensor, info: DistInfo) -> torch.Tensor:
    """Sum ``values`` over ranks (returns a new tensor; identity on a single process)."""
    if not info.enabled:
        return values
    out = values.clone()
    dist.all_reduce(out, op=dist.ReduceOp.SUM)
    return out


def broadcast_flag(flag: bool, info: DistInfo) -> bool:
    """Rank 0's ``flag`` on every rank."""
    if not info.enabled:
        return flag
    t = torch.tensor([1 if flag else 0], dtype=torch.int64)
    dist.broadcast(t, src=0)
    return bool(t.item())
