"""Progress of long loops: a bar on a terminal, a status line every 30 s in a log file."""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Iterable, Iterator
from typing import TypeVar

__all__ = ["LOG_INTERVAL", "progress", "status_line"]

T = TypeVar("T")

#: Seconds between two status lines when the output is not a terminal.
LOG_INTERVAL = 30.0

_LOG = logging.getLogger("poseflow")


def progress(
    items: Iterable[T],
    *,
    total: int,
    desc: str,
    enabled: bool = True,
    interval: float = LOG_INTERVAL,
) -> Iterator[T]:
    """Yield ``items``; show how far the loop got.

    On a terminal a tqdm bar; otherwise (a log file, CI, a cluster job) a line through the
    ``poseflow`` logger at most every ``interval`` seconds and at the end:
    ``desc: done/total (percent), elapsed, ETA``, with no escape codes.

    Example:
        >>> list(progress(range(3), total=3, desc="steps", enabled=False))
        [0, 1, 2]
    """
    if not enabled:
        yield from items
        return
    if sys.stderr.isatty():
        from tqdm.auto import tqdm

        yield from tqdm(items, total=total, desc=desc, mininterval=1.0)
        return
    start = last = time.perf_counter()
    done = 0
    for item in items:
        yield item
        done += 1
        now = time.perf_counter()
        if now - last >= interval or done == total:
            last = now
            _LOG.info("%s", status_line(desc, done, total, now - start))


def status_line(desc: str, done: int, total: int, elapsed: float) -> str:
    """``desc: done/total (percent), elapsed m:ss, ETA m:ss``.

    Example:
        >>> status_line("train", 50, 200, 30.0)
        'train: 50/200 (25%), elapsed 0:30, ETA 1:30'
    """
    eta = elapsed / done * (total - done) if done else float("nan")
    pct = 100 * done / total if total else 100.0

    def clock(s: float) -> str:
        return "?" if s != s else f"{int(s) // 60}:{int(s) % 60:02d}"

    return f"{desc}: {done}/{total} ({pct:.0f}%), elapsed {clock(elapsed)}, ETA {clock(eta)}"
