"""Multi-process training with `torchrun` (one process per GPU, or per CPU slot with gloo).

`torchrun` tells each process its place through the RANK, WORLD_SIZE and LOCAL_RANK variables;
the command reads them and passes them here (modules do not read the environment themselves).
Rank 0 alone logs, validates and writes checkpoints; the others wait at a barrier.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import torch
import torch.distributed as dist
from torch import nn


@dataclass(frozen=True)
class DistributedContext:
    """Where this process sits in the job and which device it drives."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    device: torch.device = torch.device("cpu")

    @property
    def is_main(self) -> bool:
        """True on the process that logs and writes checkpoints."""
        return self.rank == 0

    @property
    def enabled(self) -> bool:
        """True when more than one process takes part."""
        return self.world_size > 1

    def barrier(self) -> None:
        """Wait for every process (no-op when running alone)."""
        if self.enabled:
            dist.barrier()

    def wrap(self, model: nn.Module) -> nn.Module:
        """The model wrapped in DistributedDataParallel when several processes train, else itself."""
        if not self.enabled:
            return model
        device_ids = [self.device.index] if self.device.type == "cuda" else None
        return nn.parallel.DistributedDataParallel(model, device_ids=device_ids)

    def all_reduce_mean(self, value: float) -> float:
        """Mean of a float over all processes."""
        if not self.enabled:
            return value
        tensor = torch.tensor([value], dtype=torch.float64, device=self.device if self.device.type == "cuda" else "cpu")
        dist.all_reduce(tensor)
        return float(tensor.item()) / self.world_size

    def broadcast_flag(self, flag: bool) -> bool:
        """Rank 0's value of a boolean (e.g. 'stop early'), on every process."""
        if not self.enabled:
            return flag
        tensor = torch.tensor([1 if flag else 0], device=self.device if self.device.type == "cuda" else "cpu")
        dist.broadcast(tensor, src=0)
        return bool(tensor.item())


def context_from_env(environ: Mapping[str, str], device: str = "auto", backend: str = "auto") -> DistributedContext:
    """Join the process group `torchrun` set up (when WORLD_SIZE > 1) and pick this process's device.

    `device` "auto" takes CUDA device LOCAL_RANK when CUDA is available, else the CPU; `backend`
    "auto" is NCCL on CUDA and gloo on the CPU.
    """
    world_size = int(environ.get("WORLD_SIZE", "1"))
    rank = int(environ.get("RANK", "0"))
    local_rank = int(environ.get("LOCAL_RANK", "0"))
    use_cuda = torch.cuda.is_available() if device == "auto" else device.startswith("cuda")
    torch_device = torch.device("cuda", local_rank) if use_cuda else torch.device("cpu")
    if use_cuda:
        torch.cuda.set_device(torch_device)
    if world_size > 1 and not dist.is_initialized():
        chosen = ("nccl" if use_cuda else "gloo") if backend == "auto" else backend
        dist.init_process_group(backend=chosen, rank=rank, world_size=world_size)
    return DistributedContext(rank=rank, world_size=world_size, local_rank=local_rank, device=torch_device)


def shutdown(context: DistributedContext) -> None:
    """Leave the process group at the end of a distributed run."""
    if context.enabled and dist.is_initialized():
        dist.destroy_process_group()
