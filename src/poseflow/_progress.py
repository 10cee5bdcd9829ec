"""Progress of long loops: a bar on a terminal, a status line every 30 s in a log file."""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Iterable, Iterator, Mapping
from typing import Any, TypeVar

__all__ = ["LOG_INTERVAL", "ProgressBar", "progress", "status_line"]

T = TypeVar("T")

#: Seconds between two status lines when the output is not a terminal.
LOG_INTERVAL = 30.0

_LOG = logging.getLogger("poseflow")


class ProgressBar:
    """How far a loop driven by hand got: :meth:`update`, :meth:`set_postfix`, :meth:`close`.

    On a terminal a tqdm bar; otherwise (a log file, CI, a cluster job) a :func:`status_line`
    through the ``poseflow`` logger at most every ``interval`` seconds and one at :meth:`close`,
    with the postfix values after it and no escape codes:
    ``cfm: 120/2000 (6%), elapsed 1:02, ETA 16:10, loss 0.4123``. Disabled, it only counts.

    Args:
        total: the count at which the loop is done.
        desc: the name in front of the bar or line.
        initial: the count it starts at (a resumed run); the ETA uses only the steps done here.
        enabled: False shows nothing.
        interval: seconds between two status lines.

    Example:
        >>> with ProgressBar(10, desc="steps", initial=4, enabled=False) as bar:
        ...     bar.update(3)
        ...     bar.set_postfix(loss="0.4123")
        >>> bar.done
        7
    """

    def __init__(
        self,
        total: int,
        *,
        desc: str,
        initial: int = 0,
        enabled: bool = True,
        interval: float = LOG_INTERVAL,
    ) -> None:
        self.total, self.desc, self.initial, self.interval = total, desc, initial, interval
        self.done = initial
        self._postfix: dict[str, Any] = {}
        self._logs = enabled and not sys.stderr.isatty()
        self._bar: Any = None
        if enabled and not self._logs:
            from tqdm.auto import tqdm

            self._bar = tqdm(
                total=total, initial=initial, desc=desc, mininterval=1.0, dynamic_ncols=True
            )
        self._start = self._last = time.perf_counter()
        self._pending = False  # a change that no status line shows yet

    def update(self, n: int = 1) -> None:
        """Count ``n`` more done."""
        self.done += n
        if self._bar is not None:
            self._bar.update(n)
        elif self._logs:
            self._pending = True
            if time.perf_counter() - self._last >= self.interval:
                self._log()

    def set_postfix(self, **values: Any) -> None:
        """Show ``values`` after the count, e.g. ``set_postfix(loss="0.4123")``."""
        self._postfix = values
        self._pending = True
        if self._bar is not None:
            self._bar.set_postfix(values)

    def close(self) -> None:
        """Close the bar, or log the last status line."""
        if self._bar is not None:
            self._bar.close()
        elif self._logs and self._pending:
            self._log()

    def __enter__(self) -> ProgressBar:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _log(self) -> None:
        self._last = time.perf_counter()
        self._pending = False
        line = status_line(
            self.desc, self.done, self.total, self._last - self._start,
            initial=self.initial, postfix=self._postfix,
        )  # fmt: skip
        _LOG.info("%s", line)


def progress(
    items: Iterable[T],
    *,
    total: int,
    desc: str,
    enabled: bool = True,
    interval: float = LOG_INTERVAL,
) -> Iterator[T]:
    """Yield ``items``; show how far the loop got, as :class:`ProgressBar` does.

    Example:
        >>> list(progress(range(3), total=3, desc="steps", enabled=False))
        [0, 1, 2]
    """
    with ProgressBar(total, desc=desc, enabled=enabled, interval=interval) as bar:
        for item in items:
            yield item
            bar.update()


def status_line(
    desc: str,
    done: int,
    total: int,
    elapsed: float,
    *,
    initial: int = 0,
    postfix: Mapping[str, Any] | None = None,
) -> str:
    """``desc: done/total (percent), elapsed m:ss, ETA m:ss[, key value ...]``.

    The ETA extrapolates the ``done - initial`` steps taken in ``elapsed`` seconds.

    Example:
        >>> status_line("train", 50, 200, 30.0)
        'train: 50/200 (25%), elapsed 0:30, ETA 1:30'
        >>> status_line("cfm", 120, 2000, 62.0, initial=100, postfix={"loss": "0.4123"})
        'cfm: 120/2000 (6%), elapsed 1:02, ETA 97:08, loss 0.4123'
    """
    steps = done - initial
    eta = elapsed / steps * max(total - done, 0) if steps > 0 else float("nan")
    pct = 100 * done / total if total else 100.0

    def clock(s: float) -> str:
        return "?" if s != s else f"{int(s) // 60}:{int(s) % 60:02d}"

    extra = "".join(f", {k} {v}" for k, v in (postfix or {}).items())
    return f"{desc}: {done}/{total} ({pct:.0f}%), elapsed {clock(elapsed)}, ETA {clock(eta)}{extra}"
