"""Learning-rate schedule of the trainer: linear warm-up, then cosine decay."""

from __future__ import annotations

import math

from poseflow.errors import ValueRangeError

__all__ = ["warmup_cosine_lr"]


def warmup_cosine_lr(
    step: int,
    *,
    base_lr: float,
    total_steps: int,
    warmup_steps: int = 0,
    min_lr: float = 0.0,
) -> float:
    """Learning rate of optimiser step ``step`` (0-based) under warm-up + cosine decay.

    Steps ``0 .. warmup_steps - 1`` ramp linearly up to ``base_lr`` (step ``i`` uses
    ``base_lr * (i + 1) / warmup_steps``); the remaining steps follow a half cosine from
    ``base_lr`` down to ``min_lr``, reached after ``total_steps`` steps. The schedule is a pure
    function of the step, so resuming needs no scheduler state.

    Args:
        step: the optimiser step about to be taken, ``>= 0``.
        base_lr: peak learning rate.
        total_steps: length of the schedule (>= 1).
        warmup_steps: length of the linear warm-up (>= 0).
        min_lr: final learning rate.

    Returns:
        The learning rate.

    Example:
        >>> [round(warmup_cosine_lr(s, base_lr=1.0, total_steps=6, warmup_steps=2), 3)
        ...  for s in range(7)]
        [0.5, 1.0, 1.0, 0.854, 0.5, 0.146, 0.0]
    """
    if step < 0 or total_steps < 1 or warmup_steps < 0:
        raise ValueRangeError(
            f"need step >= 0, total_steps >= 1, warmup_steps >= 0; "
            f"got {step}, {total_steps}, {warmup_steps}"
        )
    if step < warmup_steps:
        return base_lr * (step + 1) / warmup_steps
    span = max(1, total_steps - warmup_steps)
    progress = min(1.0, (step - warmup_steps) / span)
    return min_lr + (base_lr - min_lr) * 0.5 * (1.0 + math.cos(math.pi * progress))
