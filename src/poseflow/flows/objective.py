"""From a batch to the training loss: what the trainer asks of a flow-matching task.

The trainer knows nothing of the data. For each step it hands an *objective* the model, the
batch (already on the device) and a :class:`StepRandom` to draw noise and times from, and gets
back the scalar loss, or ``(loss, metrics)`` with a dict of scalar tensors to log.
:class:`CFMObjective` is the conditional flow matching objective of the paper; a batch reaches
it as a :class:`FlowBatch` or anything :meth:`FlowBatch.from_any` understands, e.g. the dict
a ``DataLoader`` collates:

>>> batch = {"x_1": torch.zeros(2, 5, 3), "condition": torch.zeros(2, 5, 8),
...          "mask": torch.ones(2, 5, dtype=torch.bool)}
>>> fb = FlowBatch.from_any(batch)
>>> fb.x_1.shape, sorted(fb.cond), fb.mask.shape, fb.frozen_mask
(torch.Size([2, 5, 3]), ['condition', 'mask'], torch.Size([2, 5]), None)

For FunFlow6D a batch is ``x_1 = [Q ; T^r]`` ``(B, 2N, 3)``, the conditioning tensors, the point
``mask``, the anchor's ``frozen_mask`` and, for symmetric objects, the ``equivalents`` of ``x_1``
(see :mod:`poseflow.flows.equivalents`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import nn

from poseflow._checks import check_tensor
from poseflow.errors import ShapeError, ValueRangeError
from poseflow.flows.equivalents import nearest_equivalent
from poseflow.flows.loss import cfm_loss
from poseflow.flows.path import LinearPath, PathSample
from poseflow.flows.timesteps import TIME_SAMPLERS, sample_time

__all__ = ["CFMObjective", "DistillationObjective", "FlowBatch", "StepRandom"]


@dataclass
class FlowBatch:
    """One batch of a conditional flow-matching task.

    Attributes:
        x_1: the data states, shape ``(B, L, C)``.
        cond: keyword arguments passed to the model with ``x`` and ``t`` (e.g. ``condition``,
            ``mask``).
        mask: optional ``(B, L)`` bool, True at valid points (the loss ignores the others).
        frozen_mask: optional ``(B, L)`` bool, True at anchor points.
        equivalents: optional ``(B, K, C, C + 1)`` affine maps carrying ``x_1`` to each of the
            data states that are equally right (see :mod:`poseflow.flows.equivalents`).
    """

    x_1: torch.Tensor
    cond: dict[str, Any] = field(default_factory=dict)
    mask: torch.Tensor | None = None
    frozen_mask: torch.Tensor | None = None
    equivalents: torch.Tensor | None = None

    @classmethod
    def from_any(cls, batch: Any) -> FlowBatch:
        """Interpret a batch: a :class:`FlowBatch`, a tensor ``x_1``, or a mapping.

        A mapping must hold ``"x_1"``; ``"mask"`` and ``"frozen_mask"`` are taken as the masks
        and ``"equivalents"`` as :attr:`equivalents`; every other key, ``"mask"`` included, is
        passed to the model (the DiT takes a mask).

        Raises:
            ShapeError: the batch has none of these forms.
        """
        if isinstance(batch, FlowBatch):
            return batch
        if isinstance(batch, torch.Tensor):
            return cls(x_1=batch)
        if isinstance(batch, Mapping):
            if "x_1" not in batch:
                raise ShapeError(f"a batch mapping needs an 'x_1' entry, got keys {sorted(batch)}")
            own = ("x_1", "frozen_mask", "equivalents")
            return cls(
                x_1=batch["x_1"],
                cond={k: v for k, v in batch.items() if k not in own},
                mask=batch.get("mask"),
                frozen_mask=batch.get("frozen_mask"),
                equivalents=batch.get("equivalents"),
            )
        raise ShapeError(
            f"cannot read a flow batch from {type(batch).__name__}: "
            "give a FlowBatch, a tensor x_1, or a mapping with 'x_1'"
        )


class StepRandom:
    """The random draws of one training step, the same whatever the number of processes.

    Every rank holds a generator seeded identically for the step, draws the noise for the
    *global* batch (``world_size * B`` rows) and keeps rows ``rank, rank + world_size, ...``:
    exactly the rows that ``DistributedSampler`` gives this rank. One process with batch
    ``K * B`` therefore draws the same noise for the same samples as K processes with batch B.

    Args:
        generator: the step's generator (on the training device).
        rank: this process's rank.
        world_size: number of processes.

    Example:
        >>> one = StepRandom(torch.Generator().manual_seed(3)).randn_like(torch.zeros(4, 2, 3))
        >>> half = StepRandom(torch.Generator().manual_seed(3), rank=1, world_size=2)
        >>> torch.equal(half.randn_like(torch.zeros(2, 2, 3)), one[1::2])
        True
    """

    def __init__(self, generator: torch.Generator, *, rank: int = 0, world_size: int = 1) -> None:
        self.generator = generator
        self.rank = rank
        self.world_size = world_size

    def randn_like(self, x: torch.Tensor) -> torch.Tensor:
        """Standard normal noise shaped like ``x`` ``(B, ...)``: this rank's share of the draw."""
        shape = (x.shape[0] * self.world_size, *x.shape[1:])
        z = torch.randn(shape, generator=self.generator, dtype=x.dtype, device=x.device)
        return z[self.rank :: self.world_size]

    def time(
        self,
        batch: int,
        name: str = "uniform",
        *,
        dtype: torch.dtype | None = None,
        device: torch.device | str | None = None,
    ) -> torch.Tensor:
        """Times ``(B,)`` from the named sampler (see :func:`.timesteps.sample_time`)."""
        t = sample_time(
            batch * self.world_size,
            name,
            generator=self.generator,
            device=device if device is not None else self.generator.device,
            dtype=dtype,
        )
        return t[self.rank :: self.world_size]


class CFMObjective:
    """The conditional flow matching loss of a batch (the paper's training step).

    Draws ``x_0 ~ N(0, I)`` and ``t`` from the time sampler, builds ``x_t`` on the path, asks the
    model for the velocity, ``model(x=x_t, t=t, **cond)``, and returns :func:`cfm_loss` against
    ``x_1 - x_0``. The model's output is cast to the dtype of ``x_1`` before the loss, so the loss
    stays in full precision under autocast. A batch with :attr:`FlowBatch.equivalents` is trained
    towards the equivalent of ``x_1`` nearest ``x_0``
    (:func:`~poseflow.flows.equivalents.nearest_equivalent`).

    Args:
        path: the probability path (default :class:`~poseflow.flows.path.LinearPath`).
        time_sampler: name of the training-time distribution; ``"uniform"`` is the paper's.
        include_frozen: keep anchor points in the loss (see :func:`cfm_loss`).
        pin_frozen: hold anchor points at their clean coordinates along the path
            (``x_t = x_1``, ``dx_t = 0``); sample such a model with ``x_frozen``. The paper's
            equation interpolates every point (``False``).
        noise_kwarg: if set, ``x_0`` is also passed to the model under this keyword (FunFlow6D's
            positional encoder reads each point's noise coordinates).

    Example:
        >>> class Zero(torch.nn.Module):
        ...     def forward(self, *, x, t):
        ...         return torch.zeros_like(x)
        >>> rng = StepRandom(torch.Generator().manual_seed(0))
        >>> loss = CFMObjective()(Zero(), torch.zeros(8, 16, 3), rng)
        >>> 0.5 < float(loss) < 1.5  # E|x_1 - x_0|^2 / C = 1 for x_1 = 0
        True
    """

    def __init__(
        self,
        *,
        path: LinearPath | None = None,
        time_sampler: str = "uniform",
        include_frozen: bool = False,
        pin_frozen: bool = False,
        noise_kwarg: str | None = None,
    ) -> None:
        if time_sampler not in TIME_SAMPLERS:
            raise ValueRangeError(
                f"unknown time sampler {time_sampler!r}; choose from {sorted(TIME_SAMPLERS)}"
            )
        self.path = path if path is not None else LinearPath()
        self.time_sampler = time_sampler
        self.include_frozen = include_frozen
        self.pin_frozen = pin_frozen
        self.noise_kwarg = noise_kwarg

    def __call__(self, model: nn.Module, batch: Any, rng: StepRandom) -> torch.Tensor:
        """Return the scalar loss of one batch."""
        fb = FlowBatch.from_any(batch)
        x_1 = fb.x_1
        check_tensor(x_1, "x_1", ("B", "L", "C"))
        x_0 = rng.randn_like(x_1)
        if fb.equivalents is not None:
            x_1 = nearest_equivalent(
                x_0, x_1, fb.equivalents.to(x_1), mask=fb.mask, frozen_mask=fb.frozen_mask
            )
        t = rng.time(x_1.shape[0], self.time_sampler, dtype=x_1.dtype, device=x_1.device)
        frozen = fb.frozen_mask if self.pin_frozen else None
        ps = self.path.sample(x_0, x_1, t, frozen_mask=frozen)
        cond = dict(fb.cond)
        if self.noise_kwarg is not None:
            cond[self.noise_kwarg] = x_0
        velocity = model(x=ps.x_t, t=ps.t, **cond)
        if not isinstance(velocity, torch.Tensor):
            raise ShapeError(f"the model must return a tensor, got {type(velocity).__name__}")
        return cfm_loss(
            velocity.to(x_1.dtype),
            ps,
            fb.mask,
            fb.frozen_mask,
            include_frozen=self.include_frozen,
        )


class DistillationObjective:
    """Train a one-step sampler: one Euler step of the model lands where the teacher's solver does.

    Draws ``x_0 ~ N(0, I)`` as :class:`CFMObjective` does, integrates the frozen ``teacher``
    from it with ``sampler`` (e.g. one midpoint step, two teacher calls), and regresses the
    model's velocity at ``t = 0`` on ``X_teacher(1) - x_0``: afterwards
    ``x_0 + model(x_0, 0)`` approximates the teacher's sample from the same noise, at one model
    call instead of ``sampler.evaluations``. The loss is :func:`cfm_loss` over the points that
    count, in the dtype of ``x_1``; the teacher runs without gradients, outside any autocast.

    Args:
        teacher: the trained velocity model, called as ``teacher(x=x_t, t=t, **cond)``.
        sampler: the teacher's solver (:func:`~poseflow.flows.samplers.get_sampler`).
        include_frozen: keep anchor points in the loss (see :func:`cfm_loss`).
        pin_frozen: anchor points start at their clean coordinates (``x_frozen = x_1``), as
            for a model trained with ``CFMObjective(pin_frozen=True)``.
        noise_kwarg: if set, ``x_0`` is also passed to both models under this keyword.

    Example:
        >>> from poseflow.flows.samplers import get_sampler
        >>> class Drift(torch.nn.Module):  # teacher: constant velocity 2
        ...     def forward(self, *, x, t):
        ...         return torch.full_like(x, 2.0)
        >>> rng = StepRandom(torch.Generator().manual_seed(0))
        >>> objective = DistillationObjective(Drift(), get_sampler("midpoint", steps=1))
        >>> float(objective(Drift(), torch.zeros(4, 5, 3), rng)) < 1e-12  # the student agrees
        True
    """

    def __init__(
        self,
        teacher: nn.Module,
        sampler: Any,
        *,
        include_frozen: bool = False,
        pin_frozen: bool = False,
        noise_kwarg: str | None = None,
    ) -> None:
        self.teacher = teacher
        self.sampler = sampler
        self.include_frozen = include_frozen
        self.pin_frozen = pin_frozen
        self.noise_kwarg = noise_kwarg

    def __call__(self, model: nn.Module, batch: Any, rng: StepRandom) -> torch.Tensor:
        """Return the scalar loss of one batch."""
        fb = FlowBatch.from_any(batch)
        x_1 = fb.x_1
        check_tensor(x_1, "x_1", ("B", "L", "C"))
        x_0 = rng.randn_like(x_1)
        cond = dict(fb.cond)
        if self.noise_kwarg is not None:
            cond[self.noise_kwarg] = x_0
        pinned = self.pin_frozen and fb.frozen_mask is not None

        def teacher(*, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
            return self.teacher(x=x, t=t, **cond)

        with torch.autocast(x_1.device.type, enabled=False):
            end = self.sampler.sample(
                teacher, x_0, frozen_mask=fb.frozen_mask, x_frozen=x_1 if pinned else None
            )
        start = torch.where(fb.frozen_mask[..., None], x_1, x_0) if pinned else x_0
        t = torch.zeros(x_1.shape[0], dtype=x_1.dtype, device=x_1.device)
        velocity = model(x=start, t=t, **cond)
        if not isinstance(velocity, torch.Tensor):
            raise ShapeError(f"the model must return a tensor, got {type(velocity).__name__}")
        return cfm_loss(
            velocity.to(x_1.dtype),
            PathSample(x_t=start, dx_t=end - start, t=t),
            fb.mask,
            fb.frozen_mask,
            include_frozen=self.include_frozen,
        )
