"""What the benchmarks share: timing, the machine's name, and the JSON line with its command.

A benchmark runs as ``python benchmarks/NAME.py``, which puts this folder first on ``sys.path``,
so it imports these helpers as ``from _common import ...``.

- :func:`timings` times calls of a function (synchronised on a GPU), :func:`timed` takes the
  median after a warm-up call, :func:`timed_pair` times two functions alternately, and
  :func:`clocked` times one call;
- :func:`machine` names the CPU and its torch threads;
- :func:`target_instances` reads the instances of a BOP image that a benchmark scores;
- :func:`report` prints the run's JSON line and then the command that reproduces it
  (:func:`command`).
"""

from __future__ import annotations

import json
import platform
import shlex
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeVar

import torch

__all__ = [
    "clocked",
    "command",
    "machine",
    "report",
    "sync",
    "target_instances",
    "timed",
    "timed_pair",
    "timings",
]

T = TypeVar("T")


def sync(device: torch.device | str | None) -> None:
    """Wait for the work queued on ``device`` when it is a GPU; nothing elsewhere."""
    if device is not None and torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def timings(
    fn: Callable[[], T], repeats: int, *, device: torch.device | str | None = None
) -> tuple[list[float], T | None]:
    """Seconds of each of ``repeats`` calls of ``fn`` and the last call's output.

    On a GPU ``device`` the clock starts and stops on a synchronised device.
    """
    times, out = [], None
    for _ in range(repeats):
        sync(device)
        start = time.perf_counter()
        out = fn()
        sync(device)
        times.append(time.perf_counter() - start)
    return times, out


def clocked(fn: Callable[[], T], *, device: torch.device | str | None = None) -> tuple[float, T]:
    """Seconds of one call of ``fn`` and its output."""
    times, out = timings(fn, 1, device=device)
    return times[0], out  # type: ignore[return-value]


def timed(
    fn: Callable[[], T],
    repeats: int,
    *,
    device: torch.device | str | None = None,
    warmup: bool = True,
) -> tuple[float, T | None]:
    """Median seconds of ``repeats`` calls of ``fn`` (after an untimed call) and the last output."""
    if warmup:
        fn()
    times, out = timings(fn, repeats, device=device)
    return statistics.median(times), out


def timed_pair(
    ours: Callable[[], Any],
    theirs: Callable[[], Any],
    repeats: int,
    *,
    device: torch.device | str | None = None,
) -> tuple[list[float], list[float], Any, Any]:
    """Both functions warmed up, then timed alternately ``repeats`` times each (seconds).

    Alternating keeps a change of the machine's load from favouring one side; ``ours`` is
    synchronised on ``device``. Returns both lists of times and both last outputs.
    """
    out_ours, out_theirs = ours(), theirs()
    t_ours, t_theirs = [], []
    for _ in range(repeats):
        seconds, out_ours = clocked(ours, device=device)
        t_ours.append(seconds)
        seconds, out_theirs = clocked(theirs)
        t_theirs.append(seconds)
    return t_ours, t_theirs, out_ours, out_theirs


def machine() -> str:
    """The CPU architecture and torch's threads, e.g. ``x86_64, 1 torch threads``."""
    return f"{platform.machine()}, {torch.get_num_threads()} torch threads"


def target_instances(scene: Any, im_id: int, wanted: set[int]) -> tuple[Any, ...]:
    """The ground-truth instances of the ``wanted`` objects in one image of a BOP scene.

    Args:
        scene: a :class:`~poseflow.data.bop.BOPScene`.
        im_id: the image.
        wanted: the object ids to keep.

    Returns:
        ``(obj_ids, masks, poses, rgb, depth, K)``: the instances' object ids, visible masks
        ``(B, H, W)``, ground-truth poses ``(B, 4, 4)`` float32, the image ``(3, H, W)``, its
        depth ``(H, W)`` in metres and intrinsics ``(3, 3)`` float32.
    """
    gts = scene.gt_of(im_id)
    sel = [k for k, gt in enumerate(gts) if gt.obj_id in wanted]
    obj_ids = [gts[k].obj_id for k in sel]
    masks = torch.stack([scene.load_mask(im_id, k, visible=True) for k in sel])
    poses = torch.stack([torch.as_tensor(gts[k].pose, dtype=torch.float32) for k in sel])
    rgb, depth = scene.load_rgb_image(im_id), scene.load_depth_image(im_id)
    K = torch.as_tensor(scene.camera[im_id].K, dtype=torch.float32)
    return obj_ids, masks, poses, rgb, depth, K


def command(script: str, argv: Sequence[str] | None = None) -> str:
    """The command that reproduces a run: ``python benchmarks/NAME.py ARGS``.

    Args:
        script: the benchmark's file (its ``__file__``).
        argv: its arguments (default: this process's).
    """
    args = sys.argv[1:] if argv is None else list(argv)
    return shlex.join(["python", f"benchmarks/{Path(script).name}", *args])


def report(record: dict[str, Any], script: str, argv: Sequence[str] | None = None) -> None:
    """Print a run's figures as one JSON line, then ``command: ...`` (:func:`command`)."""
    print(json.dumps(record))
    print("command:", command(script, argv), flush=True)
