"""Images estimated side by side in forked worker processes, one thread each.

On a few CPU cores, one image's work is many small products: two intra-op threads gain little on
an idle machine and lose several times over when another job holds a core (the threads wait on
each other). Images are independent, so :func:`map_forked` hands whole images to ``W`` worker
processes instead, each on one thread; the estimator, its prepared objects and its caches are
inherited from the parent at the fork, not loaded again. The outcomes come back in the order
one process gives them, so a seeded prediction is the same with any number of workers.
"""

from __future__ import annotations

import multiprocessing
import os
import warnings
from collections.abc import Callable, Iterator
from typing import Any, TypeVar

import torch

from poseflow.errors import ValueRangeError

__all__ = ["check_workers", "map_forked"]

T = TypeVar("T")

#: The function the workers call; set in the parent just before the fork, read by the children.
_TASK: Callable[[int], Any] | None = None


def check_workers(workers: int) -> int:
    """The number of worker processes that can be used: ``workers``, or 1 where none can fork.

    Raises:
        ValueRangeError: ``workers < 1``, or ``workers > 1`` once CUDA is initialised (a forked
            process cannot use it: split GPU runs with ``torchrun`` instead).
    """
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueRangeError(f"workers must be a positive integer, got {workers!r}")
    if workers == 1:
        return 1
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        raise ValueRangeError(
            f"workers={workers} forks processes, which cannot use CUDA once it is initialised; "
            "estimate on the GPU with workers=1, or split over GPUs with torchrun"
        )
    if "fork" not in multiprocessing.get_all_start_methods():
        warnings.warn(
            f"this platform cannot fork: estimating in one process, not {workers}", stacklevel=3
        )
        return 1
    return workers


def map_forked(task: Callable[[int], T], count: int, workers: int) -> Iterator[T]:
    """``task(n)`` for ``n`` in ``range(count)``, in that order, over ``workers`` processes.

    With ``workers == 1`` (or a single item) the calls run here, one after the other. Otherwise
    ``min(workers, count)`` processes are forked, each on one thread
    (:func:`poseflow.set_num_threads` ``(1)``), and take the items one at a time as they get
    free; an exception raised by ``task`` is raised here. ``task`` runs in the child: what it
    changes in its process is not seen by the parent, so it must return what the caller needs
    (picklable, e.g. numpy arrays rather than large tensors).

    Args:
        task: called with the item's index.
        count: number of items.
        workers: from :func:`check_workers`.

    Yields:
        ``task(0)``, ``task(1)``, ... as they become available in order.

    Example:
        >>> list(map_forked(lambda n: n * n, 4, workers=2))
        [0, 1, 4, 9]
    """
    workers = min(check_workers(workers), count)
    if workers <= 1:
        yield from map(task, range(count))
        return
    global _TASK
    _TASK = task
    try:
        context = multiprocessing.get_context("fork")
        with context.Pool(workers, initializer=_one_thread) as pool:
            yield from pool.imap(_run_task, range(count))
    finally:
        _TASK = None


def _one_thread() -> None:
    """A worker's start: every pool of the process on one thread."""
    from poseflow._threads import set_num_threads

    os.environ["OMP_NUM_THREADS"] = "1"
    set_num_threads(1)


def _run_task(n: int) -> Any:
    """Run the parent's task on item ``n`` (in a worker)."""
    assert _TASK is not None, "map_forked's task is set before the fork"
    return _TASK(n)
