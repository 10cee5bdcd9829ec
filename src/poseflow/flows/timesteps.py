"""Training-time distributions of the flow time ``t`` in ``[0, 1]``, selectable by name.

- ``"uniform"``: ``t ~ U[0, 1)``, the paper's choice.

A new distribution is one function of the same signature added to :data:`TIME_SAMPLERS` (the
logit-normal and U-shaped ones, never measured here, were removed: ``benchmarks/LOG.md``,
2026-12-07). Every sampler draws from an optional ``torch.Generator`` on the output device, so a
seeded generator gives the same times on every call.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from poseflow.errors import ValueRangeError

__all__ = [
    "TIME_SAMPLERS",
    "sample_time",
    "uniform_time",
]


def uniform_time(
    batch: int,
    *,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> torch.Tensor:
    """Draw ``t ~ U[0, 1)``, the paper's schedule.

    Args:
        batch: number of times B.
        generator: optional random generator (on ``device``).
        device: output device (default: the generator's, else CPU).
        dtype: floating output dtype (default: torch's default dtype).

    Returns:
        Times of shape ``(B,)``.

    Example:
        >>> t = uniform_time(4, generator=torch.Generator().manual_seed(0))
        >>> t.shape, bool(((t >= 0) & (t < 1)).all())
        (torch.Size([4]), True)
    """
    device = _device(generator, device)
    return torch.rand(_size(batch), generator=generator, device=device, dtype=dtype)


#: The time samplers by name; each is called as ``fn(B, generator=, device=, dtype=)``.
TIME_SAMPLERS: dict[str, Callable[..., torch.Tensor]] = {
    "uniform": uniform_time,
}


def sample_time(
    batch: int,
    name: str = "uniform",
    *,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> torch.Tensor:
    """Draw ``B`` training times from the named distribution (see :data:`TIME_SAMPLERS`).

    Args:
        batch: number of times B.
        name: a name of :data:`TIME_SAMPLERS`: ``"uniform"`` (the paper's).
        generator: optional random generator (on ``device``).
        device: output device (default: the generator's, else CPU).
        dtype: floating output dtype.

    Returns:
        Times in ``[0, 1]``, shape ``(B,)``.

    Raises:
        ValueRangeError: unknown name or negative batch.

    Example:
        >>> sample_time(3, "uniform", dtype=torch.float64).dtype
        torch.float64
    """
    if name not in TIME_SAMPLERS:
        raise ValueRangeError(f"unknown time sampler {name!r}; choose from {sorted(TIME_SAMPLERS)}")
    return TIME_SAMPLERS[name](batch, generator=generator, device=device, dtype=dtype)


def _size(batch: int) -> tuple[int]:
    if batch < 0:
        raise ValueRangeError(f"batch must be >= 0, got {batch}")
    return (int(batch),)


def _device(
    generator: torch.Generator | None, device: torch.device | str | None
) -> torch.device | str | None:
    if device is None and generator is not None:
        return generator.device
    return device
