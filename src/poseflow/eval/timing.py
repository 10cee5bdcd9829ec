"""Per-image stage timing: the paper's inference-time breakdown.

A :class:`StageTimer` accumulates wall-clock time per named stage. Stages nest: time spent in an
inner stage is charged to the inner stage only (the flow network's forward pass inside the Euler
integration loop counts as ``flow_net``, the rest of the loop as ``integration``). Inside
:meth:`StageTimer.image`, time not covered by any stage is charged to ``other``. When CUDA is in
use the timer synchronises the device at every stage boundary, so that asynchronous kernels are
charged to the stage that launched them.

The breakdown reports the mean milliseconds per image of every stage and its share of the total;
``segmentation`` is recorded but excluded from the total, as in the paper (masks are an input).

Timing is a context the caller sets, not an argument the pipeline carries: inside
``with timer.active():`` the parts of the pipeline report to ``timer`` through the module function
:func:`stage` (and :func:`timed` for a callable such as the flow network); outside any active
timer both are no-ops, so the parts cost nothing to time when nobody is timing them.
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from contextvars import ContextVar
from typing import Any, TypeVar

import torch

from poseflow.errors import MissingDependencyError, ValueRangeError

__all__ = ["EXCLUDED_STAGES", "STAGES", "StageTimer", "active_timer", "stage", "timed"]

#: The paper's stages in display order (segmentation first, then the pipeline, then the rest),
#: with ``verification`` (render-and-compare checking of the chosen poses) after ICP.
STAGES: tuple[str, ...] = (
    "segmentation",
    "lifting",
    "appearance_encoder",
    "reducer",
    "geometric_encoder",
    "matching",
    "flow_inputs",
    "fusion",
    "flow_net",
    "integration",
    "ransac",
    "icp",
    "verification",
    "other",
)

#: Stages recorded but left out of the total (the paper excludes instance segmentation).
EXCLUDED_STAGES: tuple[str, ...] = ("segmentation",)

F = TypeVar("F", bound=Callable[..., Any])


class StageTimer:
    """Accumulate exclusive wall-clock time per stage, per image.

    Args:
        synchronize: call ``torch.cuda.synchronize()`` at stage boundaries; None (default) does so
            whenever CUDA is available and initialised.
        excluded: stages left out of the per-image total.
        clock: a monotonic clock in seconds (for tests).

    Example:
        >>> timer = StageTimer()
        >>> with timer.image():
        ...     with timer.stage("ransac"):
        ...         pass
        >>> timer.num_images, sorted(timer.breakdown()["stages_ms"])
        (1, ['other', 'ransac'])
    """

    def __init__(
        self,
        *,
        synchronize: bool | None = None,
        excluded: tuple[str, ...] = EXCLUDED_STAGES,
        clock: Callable[[], float] = time.perf_counter,
    ) -> None:
        self.synchronize = synchronize
        self.excluded = tuple(excluded)
        self.clock = clock
        self.totals: dict[str, float] = {}
        self.counts: dict[str, int] = {}
        self.num_images = 0
        self._stack: list[str] = []
        self._last = 0.0

    def _sync(self) -> None:
        want = self.synchronize
        if want is None:
            want = torch.cuda.is_available() and torch.cuda.is_initialized()
        if want:
            torch.cuda.synchronize()

    def _charge_until_now(self) -> float:
        """Charge the time since the last boundary to the innermost open stage; return now."""
        self._sync()
        now = self.clock()
        if self._stack:
            name = self._stack[-1]
            self.totals[name] = self.totals.get(name, 0.0) + (now - self._last)
        self._last = now
        return now

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        """Time a block as stage ``name`` (exclusive of nested stages).

        Raises:
            ValueRangeError: ``name`` is empty.
        """
        if not name:
            raise ValueRangeError("a stage needs a name")
        self._charge_until_now()
        self._stack.append(name)
        self.counts[name] = self.counts.get(name, 0) + 1
        try:
            yield
        finally:
            self._charge_until_now()
            self._stack.pop()

    @contextmanager
    def image(self) -> Iterator[None]:
        """Delimit the processing of one image; uncovered time inside is charged to ``other``."""
        self._charge_until_now()
        self._stack.append("other")
        try:
            yield
        finally:
            self._charge_until_now()
            self._stack.pop()
        self.num_images += 1

    @contextmanager
    def active(self) -> Iterator[StageTimer]:
        """Make this the timer that :func:`stage` and :func:`timed` report to, inside the block.

        Example:
            >>> timer = StageTimer()
            >>> with timer.active():
            ...     with stage("icp"):
            ...         pass
            >>> with stage("icp"):  # no timer active: nothing recorded
            ...     pass
            >>> timer.counts
            {'icp': 1}
        """
        token = _ACTIVE.set(self)
        try:
            yield self
        finally:
            _ACTIVE.reset(token)

    def wrap(self, name: str) -> Callable[[F], F]:
        """Decorator timing every call of a function as stage ``name``.

        Example:
            >>> timer = StageTimer()
            >>> @timer.wrap("icp")
            ... def refine(x):
            ...     return x + 1
            >>> refine(1), timer.counts["icp"]
            (2, 1)
        """

        def deco(fn: F) -> F:
            @functools.wraps(fn)
            def inner(*args: Any, **kwargs: Any) -> Any:
                with self.stage(name):
                    return fn(*args, **kwargs)

            return inner  # type: ignore[return-value]

        return deco

    def reset(self) -> None:
        """Forget everything recorded."""
        self.totals.clear()
        self.counts.clear()
        self.num_images = 0

    def add(self, other: StageTimer) -> None:
        """Add the images and stage times another timer recorded (e.g. in another process).

        Example:
            >>> a, b = StageTimer(), StageTimer()
            >>> a.totals, a.counts, a.num_images = {"icp": 0.3}, {"icp": 2}, 2
            >>> b.totals, b.counts, b.num_images = {"icp": 0.1}, {"icp": 1}, 1
            >>> a.add(b); a.totals, a.counts, a.num_images
            ({'icp': 0.4}, {'icp': 3}, 3)
        """
        for name, seconds in other.totals.items():
            self.totals[name] = self.totals.get(name, 0.0) + seconds
        for name, count in other.counts.items():
            self.counts[name] = self.counts.get(name, 0) + count
        self.num_images += other.num_images

    def breakdown(self) -> dict[str, Any]:
        """Mean milliseconds per image of each stage, their shares and the total.

        Returns:
            ``{"num_images", "stages_ms", "percent", "total_ms", "excluded_ms"}``; per-image means
            divide by the number of images (by 1 if no :meth:`image` block was closed). Stages
            appear in :data:`STAGES` order, then any others alphabetically.
        """
        n = max(self.num_images, 1)
        known = [s for s in STAGES if s in self.totals]
        extra = sorted(s for s in self.totals if s not in STAGES)
        stages_ms = {s: 1000.0 * self.totals[s] / n for s in known + extra}
        included = {s: v for s, v in stages_ms.items() if s not in self.excluded}
        total = sum(included.values())
        percent = {s: (100.0 * v / total if total > 0 else 0.0) for s, v in included.items()}
        return {
            "num_images": self.num_images,
            "stages_ms": stages_ms,
            "percent": percent,
            "total_ms": total,
            "excluded_ms": {s: v for s, v in stages_ms.items() if s in self.excluded},
        }

    def to_json(self, path: str | os.PathLike[str]) -> dict[str, Any]:
        """Write :meth:`breakdown` as JSON and return it."""
        data = self.breakdown()
        with open(path, "w", encoding="utf-8") as f:
            json.dump(data, f, indent=2)
        return data

    def plot(
        self, path: str | os.PathLike[str], *, kind: str = "bar", title: str | None = None
    ) -> None:
        """Draw the breakdown as a PNG chart (:meth:`figure`) at ``path``.

        Args:
            path: output PNG path.
            kind: ``"bar"`` (default) or ``"pie"``.
            title: what was timed (e.g. the method's name), put before the total in the title.

        Raises:
            ValueRangeError: unknown ``kind``, or nothing was recorded.
            MissingDependencyError: matplotlib is not installed.
        """
        self.figure(kind=kind, title=title).savefig(path)

    def figure(self, *, kind: str = "bar", title: str | None = None) -> Any:
        """The breakdown as a matplotlib ``Figure`` in which every stage is named with its figures.

        ``"bar"`` (default): one horizontal bar per stage, longest first, each labelled with its
        milliseconds per image and its share of the total; ``other`` (time inside an image that
        no stage covered) is named as such, and excluded stages (``segmentation``) are drawn
        hatched below the others, marked as left out of the total. ``"pie"``: the shares, with
        the names and figures in a legend beside the pie rather than on the slices.

        Args:
            kind: ``"bar"`` or ``"pie"``.
            title: what was timed (e.g. the method's name), put before the total in the title.

        Returns:
            A ``matplotlib.figure.Figure`` (no pyplot state; ``savefig`` writes it).

        Raises:
            ValueRangeError: unknown ``kind``, or nothing was recorded.
            MissingDependencyError: matplotlib is not installed.
        """
        if kind not in ("pie", "bar"):
            raise ValueRangeError(f"kind must be 'pie' or 'bar', got {kind!r}")
        data = self.breakdown()
        ms = {s: v for s, v in data["stages_ms"].items() if s not in self.excluded}
        if not ms or data["total_ms"] <= 0:
            raise ValueRangeError("no stage time recorded: nothing to plot")
        try:
            from matplotlib.figure import Figure
        except ImportError as exc:
            raise MissingDependencyError("matplotlib", "viz", "timing plots") from exc
        order = sorted(ms, key=lambda s: -ms[s])
        excluded = [s for s in data["excluded_ms"] if data["excluded_ms"][s] > 0]

        def name(s: str) -> str:
            text = s.replace("_", " ")
            return f"{text} (not in any stage)" if s == "other" else text

        n_bars = len(order) + len(excluded)
        height = max(4.5, 0.45 * n_bars + 1.5) if kind == "bar" else 4.5
        fig = Figure(figsize=(7, height), dpi=100)  # no pyplot: no global state, no GUI backend
        ax = fig.subplots()
        if kind == "pie":
            values = [ms[s] for s in order]
            wedges, _ = ax.pie(values, startangle=90, counterclock=False)
            labels = [f"{name(s)}: {ms[s]:.1f} ms ({data['percent'][s]:.1f}%)" for s in order]
            ax.legend(wedges, labels, loc="center left", bbox_to_anchor=(1.0, 0.5), fontsize=8)
            ax.axis("equal")
        else:
            names = [name(s) for s in order] + [f"{name(s)} (not in total)" for s in excluded]
            values = [ms[s] for s in order] + [data["excluded_ms"][s] for s in excluded]
            y = list(range(n_bars))
            bars = ax.barh(y, values, color="tab:blue")
            for bar in list(bars)[len(order) :]:
                bar.set_color("lightgrey")
                bar.set_hatch("//")
                bar.set_edgecolor("grey")
            texts = [f"{ms[s]:.1f} ms  {data['percent'][s]:.1f}%" for s in order]
            texts += [f"{data['excluded_ms'][s]:.1f} ms" for s in excluded]
            for yi, v, text in zip(y, values, texts):
                ax.text(v, yi, f" {text}", va="center", fontsize=8)
            ax.set_yticks(y, names)
            ax.invert_yaxis()  # longest on top
            ax.set_xlim(0, 1.35 * max(values))
            ax.set_xlabel("ms per image")
        what = f"{title}: " if title else ""
        n = data["num_images"]
        ax.set_title(
            f"{what}{data['total_ms']:.1f} ms per image ({n} image{'' if n == 1 else 's'})",
            fontsize=10,
        )
        fig.tight_layout()
        return fig


_ACTIVE: ContextVar[StageTimer | None] = ContextVar("poseflow_active_stage_timer", default=None)


def active_timer() -> StageTimer | None:
    """The timer made active by :meth:`StageTimer.active` around this call, or None."""
    return _ACTIVE.get()


def stage(name: str) -> AbstractContextManager[Any]:
    """Time a block as stage ``name`` on the active timer; a no-op when none is active.

    Args:
        name: the stage (see :data:`STAGES`).

    Returns:
        A context manager.
    """
    timer = _ACTIVE.get()
    return contextlib.nullcontext() if timer is None else timer.stage(name)


def timed(name: str, fn: F) -> F:
    """``fn`` with each call charged to stage ``name`` of the timer active at call time.

    Args:
        name: the stage (e.g. ``"flow_net"`` for the velocity network inside the sampler).
        fn: any callable.

    Returns:
        A callable with ``fn``'s signature and result.

    Example:
        >>> timer = StageTimer()
        >>> double = timed("flow_net", lambda x: 2 * x)
        >>> with timer.active():
        ...     double(1), double(2)
        (2, 4)
        >>> timer.counts
        {'flow_net': 2}
    """

    def call(*args: Any, **kwargs: Any) -> Any:
        with stage(name):
            return fn(*args, **kwargs)

    # Names and docstring only: a module's ``__dict__`` (its parameters) must not be copied.
    return functools.update_wrapper(call, fn, updated=())  # type: ignore[return-value]
