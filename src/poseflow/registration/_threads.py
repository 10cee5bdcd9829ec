"""Thread policy of the CPU solvers."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch

__all__ = ["serial_cpu_ops"]


@contextlib.contextmanager
def serial_cpu_ops(tensor: object) -> Iterator[None]:
    """Run torch's CPU ops on the calling thread only for the duration of the block.

    Applies when ``tensor`` (a solver's first input) is a CPU tensor; a no-op otherwise, so that
    malformed inputs still reach the solver's own checks.

    The solvers' tensors are small to medium (``B x N`` entries, or ``B x H x N`` per chunk):
    splitting each op across OpenMP threads saves little, and on a machine whose cores are busy
    with other work the worker threads wait for a core at every op, which made ICP and RANSAC
    several times slower on two busy cores (``benchmarks/LOG.md``). KD-tree searches still run
    in parallel (one Python thread per batch item). The previous setting is restored on exit;
    other threads running torch ops meanwhile see it too.
    """
    threads = torch.get_num_threads()
    on_cpu = isinstance(tensor, torch.Tensor) and tensor.device.type == "cpu"
    if not on_cpu or threads == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)
