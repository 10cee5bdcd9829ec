"""What a velocity model is: anything callable as ``model(x=x_t, t=t, **cond)``.

Samplers and the trainer call the model with keyword arguments only: the state ``x`` of shape
``(B, L, C)``, the times ``t`` of shape ``(B,)``, and whatever conditioning the model takes
(for the FunFlow6D DiT: ``condition=(B, L, D)`` and ``mask=(B, L)``), passed through untouched.
The returned velocity has the shape of ``x``. An ``nn.Module`` whose ``forward`` accepts these
keywords satisfies the protocol, as does a plain function.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import torch

__all__ = ["VelocityModel"]


@runtime_checkable
class VelocityModel(Protocol):
    """A time-dependent, conditional velocity field ``v(x, t | cond)``.

    Example:
        >>> def drift(*, x, t, shift):
        ...     return shift.expand_as(x)
        >>> isinstance(drift, VelocityModel)
        True
        >>> drift(x=torch.zeros(2, 4, 3), t=torch.zeros(2), shift=torch.ones(3)).shape
        torch.Size([2, 4, 3])
    """

    def __call__(self, *, x: torch.Tensor, t: torch.Tensor, **cond: Any) -> torch.Tensor:
        """Return the velocity at states ``x`` ``(B, L, C)`` and times ``t`` ``(B,)``."""
        ...
