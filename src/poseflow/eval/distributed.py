"""Prediction split over the processes of a ``torchrun`` job: shards, failures, one merged result.

``torchrun --nproc_per_node=K`` (on one machine, or on several with ``--nnodes``) starts K
processes with ``WORLD_SIZE``, ``RANK``, ``LOCAL_RANK``, ``MASTER_ADDR`` and ``MASTER_PORT`` in
their environment. :func:`join_ranks` reads them and joins the process group (``gloo`` on the
CPU, ``nccl`` on CUDA); without them it returns None and nothing here is used.

Each rank then takes its share of the images (:meth:`Ranks.shard`, balanced by the number of
instances: :func:`shard_images`), estimates them on its own device and hands the outcome to
:meth:`Ranks.run`, which brings every rank's :class:`PredictionPart` to rank 0. Rank 0 merges
them (:func:`merge_parts`: the results in the order of one process, :func:`merge_results`; the
stage timers summed, :func:`merge_timers`) and only then writes anything.

A rank that fails tells the others through the job's key-value store; they stop after the
image they are estimating (:meth:`Ranks.check_peers`), and every rank raises
:class:`~poseflow.errors.RankFailedError` naming the failed rank and its error, so that the
whole job exits non-zero and no output is written.

The merged results equal those of one process when the estimate of an image does not depend on
the images estimated before it in the same process: the classic baseline seeds every instance
itself, and a generator shared over images is reseeded per image with :func:`image_seed`.
"""

from __future__ import annotations

import hashlib
import heapq
import logging
import os
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import timedelta
from types import TracebackType
from typing import Any, TypeVar

import torch
import torch.distributed as dist

from poseflow._env import env_int
from poseflow.errors import PoseflowError, RankFailedError, ValueRangeError
from poseflow.eval.recall import Target
from poseflow.eval.results import PoseResults
from poseflow.eval.timing import StageTimer

__all__ = [
    "LAUNCH_VARIABLES",
    "WAIT_TIMEOUT",
    "PredictionPart",
    "Ranks",
    "image_seed",
    "join_ranks",
    "merge_parts",
    "merge_results",
    "merge_timers",
    "shard_images",
]

#: The environment variables that ``torchrun`` sets in every process it starts (and that a job
#: started by other means must set): ``WORLD_SIZE`` above 1 asks for a split run.
LAUNCH_VARIABLES = ("WORLD_SIZE", "RANK", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")

#: How long a rank that finished its share waits for the others (and for the rendezvous).
WAIT_TIMEOUT = timedelta(hours=6)

LOG = logging.getLogger(__name__)

T = TypeVar("T")

Image = tuple[int, int]


def image_seed(seed: int, scene_id: int, im_id: int) -> int:
    """The seed of one image's random draws: a hash of the run's seed and the image's ids.

    Reseeding a generator with it before each image makes the image's estimate independent of
    which images were estimated before it, and in which process.

    Args:
        seed: the run's seed.
        scene_id: the image's scene.
        im_id: the image.

    Returns:
        A seed in ``[0, 2**63)``.

    Example:
        >>> image_seed(0, 1, 2) == image_seed(0, 1, 2), image_seed(0, 1, 2) == image_seed(0, 2, 1)
        (True, False)
        >>> g = torch.Generator().manual_seed(image_seed(0, 1, 2))
    """
    text = f"{int(seed)}/{int(scene_id)}/{int(im_id)}".encode()
    return int.from_bytes(hashlib.blake2b(text, digest_size=8).digest(), "little") >> 1


def shard_images(
    images: Sequence[Image], world_size: int, *, weights: Sequence[float] | None = None
) -> list[list[Image]]:
    """Split images over ranks so that each rank's total weight is about the same.

    Greedy longest-processing-time assignment: the heaviest image first, each to the rank with
    the smallest total so far (the lowest rank on ties), so that no rank carries more than the
    mean plus one image's weight. With equal weights the images go round-robin in sorted order.

    Args:
        images: ``(scene_id, im_id)`` of each image, no repeats.
        world_size: number of ranks ``K >= 1``.
        weights: the cost of each image (e.g. its number of instances), ``>= 0``; default 1.

    Returns:
        ``K`` lists, one per rank, each sorted; together they hold every image once.

    Raises:
        ValueRangeError: ``world_size < 1``, repeated images, or weights of the wrong length,
            negative or not finite.

    Example:
        >>> shard_images([(0, 0), (0, 1), (0, 2), (0, 3)], 2)
        [[(0, 0), (0, 2)], [(0, 1), (0, 3)]]
        >>> shard_images([(0, 0), (0, 1), (0, 2)], 2, weights=[5, 2, 2])
        [[(0, 0)], [(0, 1), (0, 2)]]
    """
    if world_size < 1:
        raise ValueRangeError(f"world_size must be at least 1, got {world_size}")
    keys = [(int(s), int(i)) for s, i in images]
    if len(set(keys)) != len(keys):
        raise ValueRangeError("images must not repeat")
    w = [1.0] * len(keys) if weights is None else [float(x) for x in weights]
    if len(w) != len(keys):
        raise ValueRangeError(f"{len(w)} weights for {len(keys)} images")
    if not all(0.0 <= x < float("inf") for x in w):
        raise ValueRangeError("weights must be finite and non-negative")
    loads = [(0.0, r) for r in range(world_size)]  # a heap of (total weight, rank)
    shards: list[list[Image]] = [[] for _ in range(world_size)]
    for k in sorted(range(len(keys)), key=lambda k: (-w[k], keys[k])):
        load, r = heapq.heappop(loads)
        shards[r].append(keys[k])
        heapq.heappush(loads, (load + w[k], r))
    return [sorted(s) for s in shards]


@dataclass
class PredictionPart:
    """What one rank predicted, or (merged by :func:`merge_parts`) the whole run.

    Attributes:
        results: the estimates, ``E`` rows.
        timer: the stage timer of the images.
        instances: instances given to the estimator (valid or not).
        devices: the device of each rank, in rank order (one entry for one rank).
        images: images estimated by each rank, in rank order.
        config: the estimator's configuration, if it has one (merged: rank 0's).
    """

    results: PoseResults
    timer: StageTimer
    instances: int = 0
    devices: list[str] = field(default_factory=list)
    images: list[int] = field(default_factory=list)
    config: dict[str, Any] | None = None


def merge_results(parts: Sequence[PoseResults]) -> PoseResults:
    """Concatenate the results of disjoint image sets in the order one process writes them.

    The rows are sorted by scene and image, keeping each image's rows in their own order (the
    estimator's): the rows of one process walking the images in sorted order.

    Args:
        parts: results whose images do not overlap (one set per rank).

    Returns:
        The merged :class:`~poseflow.eval.results.PoseResults`.

    Raises:
        ValueRangeError: an image has rows in two parts.

    Example:
        >>> T = torch.eye(4)[None]
        >>> a = PoseResults.from_columns([0, 0], [2, 2], [7, 5], [0.5, 0.6], T.repeat(2, 1, 1), 1.0)
        >>> b = PoseResults.from_columns([0], [1], [3], [0.9], T, 2.0)
        >>> merge_results([a, b]).obj_ids.tolist()
        [3, 7, 5]
    """
    owner: dict[Image, int] = {}
    for n, part in enumerate(parts):
        for key in set(zip(part.scene_ids.tolist(), part.im_ids.tolist())):
            if owner.setdefault(key, n) != n:
                raise ValueRangeError(
                    f"scene {key[0]} image {key[1]} has results in parts {owner[key]} and {n}"
                )
    merged = PoseResults.concat(parts)
    order = torch.sort(merged.im_ids, stable=True).indices
    order = order[torch.sort(merged.scene_ids[order], stable=True).indices]
    return PoseResults(
        merged.scene_ids[order],
        merged.im_ids[order],
        merged.obj_ids[order],
        merged.scores[order],
        merged.poses[order],
        merged.times[order],
    )


def merge_timers(timers: Sequence[StageTimer]) -> StageTimer:
    """One timer holding the images and stage times of several (one per rank).

    Totals, counts and images add up, so that the merged :meth:`StageTimer.breakdown` is the mean
    per image over every rank's images.

    Raises:
        ValueRangeError: no timer, or timers that exclude different stages.

    Example:
        >>> a, b = StageTimer(), StageTimer()
        >>> a.totals, a.counts, a.num_images = {"icp": 0.3}, {"icp": 2}, 2
        >>> b.totals, b.counts, b.num_images = {"icp": 0.1, "ransac": 0.2}, {"icp": 1}, 1
        >>> m = merge_timers([a, b])
        >>> m.num_images, round(m.breakdown()["stages_ms"]["icp"], 6)
        (3, 133.333333)
    """
    if not timers:
        raise ValueRangeError("no timer to merge")
    first = timers[0]
    if any(t.excluded != first.excluded for t in timers):
        raise ValueRangeError("the timers exclude different stages")
    out = StageTimer(synchronize=first.synchronize, excluded=first.excluded, clock=first.clock)
    for t in timers:
        out.add(t)
    return out


def merge_parts(parts: Sequence[PredictionPart]) -> PredictionPart:
    """Merge the parts of the ranks, given in rank order, into the part of the whole run.

    Example:
        >>> T = torch.eye(4)[None]
        >>> one = PredictionPart(PoseResults.from_columns([0], [1], [3], [0.9], T, 2.0),
        ...                      StageTimer(), 1, ["cpu"], [1], {"steps": 5})
        >>> two = PredictionPart(PoseResults.empty(), StageTimer(), 2, ["cpu"], [1])
        >>> m = merge_parts([one, two])
        >>> len(m.results), m.instances, m.devices, m.images, m.config
        (1, 3, ['cpu', 'cpu'], [1, 1], {'steps': 5})
    """
    if not parts:
        raise ValueRangeError("no part to merge")
    return PredictionPart(
        results=merge_results([p.results for p in parts]),
        timer=merge_timers([p.timer for p in parts]),
        instances=sum(p.instances for p in parts),
        devices=[d for p in parts for d in p.devices],
        images=[n for p in parts for n in p.images],
        config=parts[0].config,
    )


class _Stopped(RankFailedError):
    """Raised by :meth:`Ranks.check_peers`: another rank failed, this one stops."""


class Ranks:
    """This process's place in a split prediction, and the collectives that finish it.

    Built by :func:`join_ranks`; use it as a context manager (or call :meth:`close`) so that the
    process group it created is destroyed at the end.

    Attributes:
        rank: global rank, ``0 .. world_size - 1``.
        world_size: number of processes ``K``.
        local_rank: rank on this machine (selects the GPU).
        device: the device this rank estimates on.
        backend: the default process group's backend.
        threads: torch's CPU threads in this process.
    """

    def __init__(
        self,
        *,
        rank: int,
        world_size: int,
        local_rank: int,
        device: torch.device,
        backend: str,
        group: Any = None,
        store: Any = None,
        owns_group: bool = False,
    ) -> None:
        self.rank = rank
        self.world_size = world_size
        self.local_rank = local_rank
        self.device = device
        self.backend = backend
        self.threads = torch.get_num_threads()
        self._group = group  # a gloo group for the (CPU) objects of the bookkeeping
        self._store = store  # None: failures are learnt at the end only
        self._round = 0  # the number of finished runs: each has its own failure key
        self._owns_group = owns_group

    @property
    def is_main(self) -> bool:
        """True on rank 0, the rank that merges and writes."""
        return self.rank == 0

    def __repr__(self) -> str:
        return (
            f"Ranks(rank={self.rank}, world_size={self.world_size}, device={self.device}, "
            f"backend={self.backend!r}, threads={self.threads})"
        )

    def shard(self, images: Sequence[Image], weights: Sequence[float] | None = None) -> list[Image]:
        """This rank's share of ``images`` (:func:`shard_images`).

        Every rank must pass the same images and weights.
        """
        return shard_images(images, self.world_size, weights=weights)[self.rank]

    def shard_targets(self, targets: Sequence[Target]) -> list[Target]:
        """The targets of this rank's share of their images.

        Each image weighs the number of instances it asks for; every rank must pass the same
        targets.
        """
        weights: dict[Image, int] = {}
        for t in targets:
            key = (t.scene_id, t.im_id)
            weights[key] = weights.get(key, 0) + t.inst_count
        mine = set(self.shard(list(weights), list(weights.values())))
        return [t for t in targets if (t.scene_id, t.im_id) in mine]

    def check_peers(self) -> None:
        """Raise :class:`~poseflow.errors.RankFailedError` if another rank has failed.

        Cheap (one look-up in the job's store): call it between images.
        """
        if self._store is not None and self._store.check([self._failure_key]):
            what = self._store.get(self._failure_key).decode()
            raise _Stopped(f"rank {self.rank} of {self.world_size} stopped: {what}")

    @property
    def _failure_key(self) -> str:
        return f"{self._round}/failed"

    def run(
        self, work: Callable[[], PredictionPart], finish: Callable[[PredictionPart], T]
    ) -> T | None:
        """Run this rank's ``work``, bring every rank's part to rank 0, and ``finish`` there.

        Every rank calls it. ``work`` estimates this rank's share (calling :meth:`check_peers`
        between images); an exception in it is reported to the other ranks at once. When all
        ranks succeeded, rank 0 merges the parts in rank order (:func:`merge_parts`) and calls
        ``finish`` on the merged part (e.g. to write the results); its success or failure is
        then shared with every rank. After a failure the ranks stay in step: the next call
        starts afresh.

        Args:
            work: returns this rank's :class:`PredictionPart`.
            finish: called on rank 0 only, with the merged part.

        Returns:
            ``finish``'s value on rank 0, None on the other ranks.

        Raises:
            RankFailedError: on every rank, when one failed (in ``work``, or rank 0 in
                ``finish``); the message names the failed rank(s) and the error.
        """
        status: tuple[str, str]
        part: PredictionPart | None = None
        try:
            part = work()
            status = ("ok", "")
        except _Stopped as exc:
            status = ("stopped", str(exc))
        except Exception as exc:
            cause = _describe(exc)
            if self._store is not None:
                text = f"rank {self.rank} of {self.world_size} failed: {cause}"
                self._store.set(self._failure_key, text)
            status = ("failed", cause)
        statuses: list[Any] = [None] * self.world_size
        dist.all_gather_object(statuses, status, group=self._group)
        self._round += 1  # every rank is past this run's work: the next run starts clean
        failed = [(r, s[1]) for r, s in enumerate(statuses) if s[0] == "failed"]
        if failed:
            text = "; ".join(f"rank {r} of {self.world_size} failed: {c}" for r, c in failed)
            if all(r != self.rank for r, _ in failed):
                text = f"rank {self.rank} of {self.world_size} stopped: {text}"
            raise RankFailedError(text)
        parts: list[Any] | None = [None] * self.world_size if self.is_main else None
        dist.gather_object(part, parts, dst=0, group=self._group)
        result: T | None = None
        outcome: list[str | None] = [None]
        if self.is_main:
            try:
                result = finish(merge_parts(parts))  # type: ignore[arg-type]
            except Exception as exc:
                outcome[0] = _describe(exc)
        dist.broadcast_object_list(outcome, src=0, group=self._group)
        if outcome[0] is not None:
            text = f"rank 0 of {self.world_size} failed: {outcome[0]}"
            if not self.is_main:
                text = f"rank {self.rank} of {self.world_size} stopped: {text}"
            raise RankFailedError(text)
        return result

    def close(self) -> None:
        """Destroy the process group, if :func:`join_ranks` created it."""
        if self._owns_group and dist.is_initialized():
            dist.destroy_process_group()
        self._owns_group = False

    def __enter__(self) -> Ranks:
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


def join_ranks(device: torch.device | str, *, timeout: timedelta = WAIT_TIMEOUT) -> Ranks | None:
    """Join the ``torchrun`` job the environment describes, or return None for a single process.

    The default process group is initialised with ``nccl`` when ``device`` is a GPU and ``gloo``
    otherwise (the results travel through a ``gloo`` group either way). On the CPU this process
    keeps at most its share of the machine's cores as torch threads (the cores divided by
    ``LOCAL_WORLD_SIZE``; ``torchrun`` itself sets ``OMP_NUM_THREADS=1`` unless it is set).
    An already initialised default group is used as it is (and left in place by
    :meth:`Ranks.close`); a failure is then learnt at the end of the work rather than at once.

    Args:
        device: this process's device, e.g. ``cuda:LOCAL_RANK`` or ``cpu``.
        timeout: how long to wait for the other ranks, at the rendezvous and at the end.

    Returns:
        The :class:`Ranks`, or None when ``WORLD_SIZE`` is unset or 1.

    Raises:
        ValueRangeError: ``WORLD_SIZE`` above 1 while another of :data:`LAUNCH_VARIABLES` is
            missing, or malformed ranks.

    Example:
        >>> import os
        >>> "WORLD_SIZE" in os.environ or join_ranks("cpu") is None
        True
    """
    world = env_int("WORLD_SIZE", 1)
    if world <= 1:
        return None
    missing = [v for v in LAUNCH_VARIABLES if not os.environ.get(v)]
    if missing:
        raise ValueRangeError(
            f"WORLD_SIZE={world} but {', '.join(missing)} not set: start the job with torchrun"
        )
    rank, local_rank = env_int("RANK", 0), env_int("LOCAL_RANK", 0)
    if not 0 <= rank < world:
        raise ValueRangeError(f"RANK={rank} is outside 0..{world - 1}")
    device = torch.device(device)
    if device.type == "cuda":
        torch.cuda.set_device(device)
    else:
        share = max(1, _cores() // max(1, env_int("LOCAL_WORLD_SIZE", world)))
        torch.set_num_threads(min(torch.get_num_threads(), share))
    if dist.is_initialized():
        backend = str(dist.get_backend())
        group = None if backend == "gloo" else dist.new_group(backend="gloo", timeout=timeout)
        return Ranks(
            rank=dist.get_rank(),
            world_size=dist.get_world_size(),
            local_rank=local_rank,
            device=device,
            backend=backend,
            group=group,
        )
    store, rank, world = next(dist.rendezvous("env://", rank, world, timeout=timeout))
    store.set_timeout(timeout)
    backend = "nccl" if device.type == "cuda" else "gloo"
    dist.init_process_group(
        backend,
        store=dist.PrefixStore("default_pg", store),  # as init_process_group("env://") does
        rank=rank,
        world_size=world,
        timeout=timeout if backend == "gloo" else None,
    )
    group = None if backend == "gloo" else dist.new_group(backend="gloo", timeout=timeout)
    attempt = os.environ.get("TORCHELASTIC_RESTART_COUNT", "0")
    return Ranks(
        rank=rank,
        world_size=world,
        local_rank=local_rank,
        device=device,
        backend=backend,
        group=group,
        store=dist.PrefixStore(f"poseflow_predict/{attempt}", store),
        owns_group=True,
    )


def _describe(exc: BaseException) -> str:
    """The error as one line.

    An unexpected one (neither a poseflow nor an OS error) is also logged with its traceback,
    which the line alone would lose.
    """
    if isinstance(exc, (PoseflowError, OSError)):
        return str(exc) or type(exc).__name__
    LOG.error("%s", "".join(traceback.format_exception(exc)).rstrip())
    return f"{type(exc).__name__}: {exc}"


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1
