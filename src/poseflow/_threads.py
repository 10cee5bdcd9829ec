"""One thread count for every pool that poseflow's CPU work runs in.

:func:`set_num_threads` ``(n)`` applies ``n`` to

- torch's intra-op pool (``torch.set_num_threads``; this also sizes MKL and torch's OpenMP);
- numba's pool (``numba.set_num_threads``, at most ``NUMBA_NUM_THREADS``): it runs umap-learn's
  parallel kernels. numba is imported and its pool started here, because starting it later (as
  umap-learn does) resets torch's OpenMP thread count to every core;
- the BLAS and OpenMP libraries loaded so far (NumPy's and SciPy's OpenBLAS, OpenMP runtimes),
  through threadpoolctl when it is installed;
- Open3D's ray casting: :class:`~poseflow.render.Renderer` casts with :func:`get_num_threads`
  threads unless given ``nthreads``.

Not covered: torch's inter-op pool (poseflow starts no inter-op work, and torch sizes it once),
libraries loaded after the call (set it again after importing them), and Open3D's other TBB work.

``import poseflow`` changes no pool: until :func:`set_num_threads` is called, poseflow's count is
torch's own (``OMP_NUM_THREADS``, else the physical cores). The command line sets
:func:`default_num_threads` unless given ``--threads``.
"""

from __future__ import annotations

import contextlib
import os
import warnings
from collections.abc import Iterator
from typing import Any

from poseflow.errors import ValueRangeError

__all__ = ["default_num_threads", "get_num_threads", "num_threads", "set_num_threads"]

#: The count :func:`set_num_threads` was given last (None: never called, torch's count stands).
_requested: int | None = None


def _check(n: object) -> int:
    """``n`` if it is an integer of at least 1 (bool excluded), else a ValueRangeError."""
    if isinstance(n, bool) or not isinstance(n, int):
        raise ValueRangeError(f"the number of threads must be an integer, got {n!r}")
    if n < 1:
        raise ValueRangeError(f"the number of threads must be at least 1, got {n}")
    return n


def default_num_threads() -> int:
    """The command line's thread count: ``OMP_NUM_THREADS`` when set, else 1.

    One thread is the count that more threads do not beat on a machine shared with other work:
    OpenMP's threads wait for each other at every op, and with a core taken by another process
    two threads made the demo's estimates 3-6x slower than one (``benchmarks/threads.py``).
    Ask for more (``--threads``, :func:`set_num_threads`) where the cores are free.

    Raises:
        ValueRangeError: ``OMP_NUM_THREADS`` is set to something other than a positive integer.

    Example:
        >>> import os; os.environ.get("OMP_NUM_THREADS") is not None or default_num_threads() == 1
        True
    """
    raw = os.environ.get("OMP_NUM_THREADS", "").strip()
    if not raw:
        return 1
    try:
        return _check(int(raw))
    except ValueError:
        raise ValueRangeError(
            f"OMP_NUM_THREADS={raw!r} is not a positive integer; set it to the number of threads"
        ) from None


def get_num_threads() -> int:
    """The thread count poseflow runs with: the last :func:`set_num_threads`, else torch's.

    Example:
        >>> with num_threads(1):
        ...     get_num_threads()
        1
    """
    if _requested is not None:
        return _requested
    import torch

    return torch.get_num_threads()


def _numba() -> Any:
    """numba, with its pool started (None when numba does not import)."""
    try:
        import numba
    except ImportError:
        return None
    with warnings.catch_warnings():  # Open3D's older TBB, when loaded first: numba takes OpenMP
        warnings.filterwarnings("ignore", message=".*TBB threading layer.*")
        numba.get_num_threads()  # starts the pool, which sets OpenMP's count to every core
    return numba


def _apply(n: int) -> Any:
    """Set ``n`` threads in every pool; returns threadpoolctl's limiter (None without it)."""
    import torch

    numba = _numba()
    if numba is not None:
        numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))
    torch.set_num_threads(n)  # after numba's start, which resets it
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        return None
    return threadpool_limits(limits=n)


def set_num_threads(n: int) -> None:
    """Run poseflow's CPU work on ``n`` threads: torch, numba, BLAS/OpenMP and Open3D.

    Args:
        n: threads, at least 1.

    Raises:
        ValueRangeError: ``n`` is not an integer of at least 1.

    Example:
        >>> import torch
        >>> with num_threads(2):  # the counts are restored after the block
        ...     set_num_threads(1)
        ...     torch.get_num_threads(), get_num_threads()
        (1, 1)
    """
    global _requested
    n = _check(n)
    _apply(n)
    _requested = n


@contextlib.contextmanager
def num_threads(n: int) -> Iterator[None]:
    """:func:`set_num_threads` ``(n)`` for the block; the previous counts are restored on exit.

    Raises:
        ValueRangeError: ``n`` is not an integer of at least 1.

    Example:
        >>> import torch
        >>> with num_threads(1):
        ...     torch.get_num_threads()
        1
    """
    global _requested
    import torch

    n = _check(n)
    saved = _requested
    torch_threads = torch.get_num_threads()
    numba = _numba()
    numba_threads = None if numba is None else numba.get_num_threads()
    limiter = _apply(n)
    _requested = n
    try:
        yield
    finally:
        if limiter is not None:
            limiter.restore_original_limits()
        if numba is not None:
            numba.set_num_threads(numba_threads)
        torch.set_num_threads(torch_threads)
        _requested = saved
