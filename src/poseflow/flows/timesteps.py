"""Training-time distributions of the flow time ``t`` in ``[0, 1]``, selectable by name.

- ``"uniform"``: ``t ~ U[0, 1)``, the paper's choice.
- ``"logit_normal"``: ``t = sigmoid(u)``, ``u ~ N(mean, std)``; concentrates training on middle
  times, where the velocity is hardest to predict (Esser et al., 2024).
- ``"u_shaped"``: density proportional to ``cosh(a (2t - 1))``; concentrates training near both
  ends, where trajectories start and where fine detail is placed (Rectified Point Flow's default).

Every sampler draws from an optional ``torch.Generator`` on the output device, so a seeded
generator gives the same times on every call.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

from poseflow.errors import ValueRangeError

__all__ = [
    "TIME_SAMPLERS",
    "logit_normal_time",
    "sample_time",
    "u_shaped_time",
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


def logit_normal_time(
    batch: int,
    *,
    mean: float = 0.0,
    std: float = 1.0,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> torch.Tensor:
    """Draw ``t = sigmoid(u)`` with ``u ~ N(mean, std^2)``.

    Args:
        batch: number of times B.
        mean: mean of the underlying normal.
        std: standard deviation of the underlying normal (> 0).
        generator: optional random generator (on ``device``).
        device: output device (default: the generator's, else CPU).
        dtype: floating output dtype.

    Returns:
        Times in ``(0, 1)``, shape ``(B,)``.

    Example:
        >>> t = logit_normal_time(1000, generator=torch.Generator().manual_seed(0))
        >>> abs(float(t.mean()) - 0.5) < 0.02
        True
    """
    if not std > 0:
        raise ValueRangeError(f"std must be > 0, got {std}")
    device = _device(generator, device)
    u = torch.randn(_size(batch), generator=generator, device=device, dtype=dtype)
    return torch.sigmoid(u * std + mean)


def u_shaped_time(
    batch: int,
    *,
    a: float = 4.0,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> torch.Tensor:
    """Draw ``t`` with density proportional to ``cosh(a (2t - 1))`` (heavier near 0 and 1).

    Inverse-CDF sampling: with ``s = 2t - 1`` the CDF is
    ``(sinh(a s) + sinh(a)) / (2 sinh(a))``, so ``s = asinh((2u - 1) sinh(a)) / a`` for uniform u.

    Args:
        batch: number of times B.
        a: sharpness (> 0); larger puts more mass near the ends.
        generator: optional random generator (on ``device``).
        device: output device (default: the generator's, else CPU).
        dtype: floating output dtype.

    Returns:
        Times in ``[0, 1]``, shape ``(B,)``.

    Example:
        >>> t = u_shaped_time(2000, generator=torch.Generator().manual_seed(0))
        >>> bool(((t < 0.1) | (t > 0.9)).float().mean() > 0.4)
        True
    """
    if not a > 0:
        raise ValueRangeError(f"a must be > 0, got {a}")
    device = _device(generator, device)
    u = torch.rand(_size(batch), generator=generator, device=device, dtype=dtype)
    s = torch.asinh((2 * u - 1) * math.sinh(a)) / a
    return ((s + 1) / 2).clamp(0, 1)


#: The time samplers by name; each is called as ``fn(B, generator=, device=, dtype=)``.
TIME_SAMPLERS: dict[str, Callable[..., torch.Tensor]] = {
    "uniform": uniform_time,
    "logit_normal": logit_normal_time,
    "u_shaped": u_shaped_time,
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
        name: ``"uniform"`` (the paper), ``"logit_normal"`` or ``"u_shaped"``, each with its
            default parameters (call the functions directly to change them).
        generator: optional random generator (on ``device``).
        device: output device (default: the generator's, else CPU).
        dtype: floating output dtype.

    Returns:
        Times in ``[0, 1]``, shape ``(B,)``.

    Raises:
        ValueRangeError: unknown name or negative batch.

    Example:
        >>> sample_time(3, "logit_normal", dtype=torch.float64).dtype
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
