"""Process-group set-up for training under ``torchrun`` (DDP), and a few collectives.

``torchrun --nproc_per_node=K script.py`` starts K processes with ``RANK``, ``WORLD_SIZE``,
``LOCAL_RANK``, ``MASTER_ADDR`` and ``MASTER_PORT`` in their environment.
:func:`init_distributed` reads them, initialises the default process group (``nccl`` when the
process owns a GPU, ``gloo`` on CPU) and tells the process which device is its own. Without
those variables (a plain ``python script.py``) it returns a single-process context and
initialises nothing, so the same script runs both ways.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
import torch.distributed as dist

from poseflow._env import env_int
from poseflow.errors import ValueRangeError

__all__ = [
    "DistributedContext",
    "all_reduce_mean",
    "barrier",
    "destroy_distributed",
    "init_distributed",
    "main_rank_succeeded",
]


@dataclass(frozen=True)
class DistributedContext:
    """Where this process stands in the job.

    Attributes:
        rank: global rank, 0 .. world_size - 1.
        world_size: number of processes.
        local_rank: rank on this machine (selects the GPU).
        device: the device this process trains on.
        backend: ``"nccl"``, ``"gloo"``, ... or ``None`` for a single process.
    """

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))
    backend: str | None = None

    @property
    def is_main(self) -> bool:
        """True on rank 0, the process that logs and writes checkpoints."""
        return self.rank == 0

    @property
    def is_distributed(self) -> bool:
        """True when a process group with more than one process is active."""
        return self.world_size > 1


def init_distributed(
    *, backend: str | None = None, device: torch.device | str | None = None
) -> DistributedContext:
    """Join the ``torchrun`` job described by the environment, or run as a single process.

    Args:
        backend: process-group backend; default ``nccl`` on CUDA devices, ``gloo`` otherwise.
        device: the device to train on; default ``cuda:LOCAL_RANK`` when CUDA is available,
            else CPU.

    Returns:
        The :class:`DistributedContext`. If the default process group already exists it is
        used as is.

    Raises:
        ValueRangeError: ``WORLD_SIZE`` or ``RANK`` are malformed.

    Example:
        >>> ctx = init_distributed(device="cpu")  # no torchrun variables: one process
        >>> ctx.world_size, ctx.is_main
        (1, True)
    """
    env_world = env_int("WORLD_SIZE", 1)
    local_rank = env_int("LOCAL_RANK", 0)
    if device is None:
        device = f"cuda:{local_rank}" if torch.cuda.is_available() else "cpu"
    device = torch.device(device)
    if device.type == "cuda":
        if device.index is None:  # a bare "cuda" means this process's current GPU
            device = torch.device("cuda", torch.cuda.current_device())
        torch.cuda.set_device(device)
    if dist.is_available() and dist.is_initialized():
        return DistributedContext(
            rank=dist.get_rank(),
            world_size=dist.get_world_size(),
            local_rank=local_rank,
            device=device,
            backend=str(dist.get_backend()),
        )
    if env_world <= 1:
        return DistributedContext(device=device)
    rank = env_int("RANK", 0)
    if not 0 <= rank < env_world:
        raise ValueRangeError(f"RANK={rank} is outside 0..{env_world - 1}")
    backend = backend or ("nccl" if device.type == "cuda" else "gloo")
    dist.init_process_group(backend=backend, rank=rank, world_size=env_world)
    return DistributedContext(
        rank=rank, world_size=env_world, local_rank=local_rank, device=device, backend=backend
    )


def destroy_distributed() -> None:
    """Tear down the default process group if one is active (call once at the end of a script).

    Every rank waits for the others first, so that none closes its connections while another
    still uses them (gloo aborts a rank whose peer went away mid-teardown).

    Example:
        >>> destroy_distributed()  # no group: nothing to do
    """
    if dist.is_available() and dist.is_initialized():
        dist.barrier()
        dist.destroy_process_group()


def barrier(ctx: DistributedContext) -> None:
    """Wait for every rank (no-op for a single process)."""
    if ctx.is_distributed:
        dist.barrier()


def main_rank_succeeded(ctx: DistributedContext, ok: bool = True) -> bool:
    """A barrier that carries one bit: whether rank 0's part (``ok`` there) succeeded.

    Every rank calls it; rank 0 passes its own outcome and the others learn it, so that a
    failure on rank 0 (say, while it builds a cache the others will read) stops them at once
    instead of leaving them at a barrier until its timeout. Returns ``ok`` for a single process.

    Example:
        >>> main_rank_succeeded(DistributedContext(), False)
        False
    """
    if not ctx.is_distributed:
        return ok
    where = ctx.device if ctx.backend == "nccl" else torch.device("cpu")
    flag = torch.tensor([int(ok) if ctx.is_main else 0], device=where)
    dist.broadcast(flag, src=0)
    return bool(flag.item())


def all_reduce_mean(value: torch.Tensor, ctx: DistributedContext) -> torch.Tensor:
    """Average a tensor over ranks (returns a new tensor; identity for a single process).

    Example:
        >>> all_reduce_mean(torch.tensor(2.0), DistributedContext())
        tensor(2.)
    """
    out = value.detach().clone()
    if ctx.is_distributed:
        dist.all_reduce(out, op=dist.ReduceOp.SUM)
        out /= ctx.world_size
    return out
