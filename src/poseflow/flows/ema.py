"""Exponential moving average of a model's weights."""

from __future__ import annotations

import copy

import torch
from torch import nn

from poseflow.errors import ValueRangeError

__all__ = ["EMA"]


class EMA:
    """Keep ``shadow <- d * shadow + (1 - d) * weights`` after every optimiser step.

    The shadow is a frozen deep copy of the model (``.module``, in eval mode), usable directly
    for validation and sampling. With ``warmup`` the decay used at update ``n`` (0-based) is
    ``min(decay, (1 + n) / (10 + n))``, so the average does not stay anchored to the random
    initial weights. Floating-point buffers are averaged like parameters; other buffers (counters)
    are copied.

    Args:
        model: the model to track (not a DDP wrapper: pass ``ddp.module``).
        decay: the long-run decay in ``[0, 1]``.
        warmup: ramp the decay up over the first updates.

    Example:
        >>> net = torch.nn.Linear(2, 1)
        >>> ema = EMA(net, decay=0.5, warmup=False)
        >>> with torch.no_grad():
        ...     _ = net.weight.add_(2.0)
        >>> ema.update(net)
        >>> torch.allclose(ema.module.weight, net.weight - 1.0)
        True
    """

    def __init__(self, model: nn.Module, *, decay: float = 0.999, warmup: bool = True) -> None:
        if not 0.0 <= decay <= 1.0:
            raise ValueRangeError(f"decay must be in [0, 1], got {decay}")
        self.decay = float(decay)
        self.warmup = bool(warmup)
        self.num_updates = 0
        self.module = copy.deepcopy(model).eval().requires_grad_(False)

    def decay_at(self, update: int) -> float:
        """The decay applied at update number ``update`` (0-based)."""
        if not self.warmup:
            return self.decay
        return min(self.decay, (1 + update) / (10 + update))

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        """Fold the current weights of ``model`` into the average."""
        weight = 1.0 - self.decay_at(self.num_updates)
        pairs = [
            *zip(self.module.parameters(), model.parameters(), strict=True),
            *zip(self.module.buffers(), model.buffers(), strict=True),
        ]
        for target, value in pairs:
            if target.is_floating_point():
                target.lerp_(value.detach().to(target.dtype), weight)
            else:
                target.copy_(value.detach())
        self.num_updates += 1

    def state_dict(self) -> dict[str, torch.Tensor]:
        """The averaged weights, keyed like ``model.state_dict()``."""
        return self.module.state_dict()

    def load_state_dict(self, state: dict[str, torch.Tensor], *, num_updates: int) -> None:
        """Restore averaged weights and the update counter (used by the decay warm-up)."""
        self.module.load_state_dict(state)
        self.num_updates = int(num_updates)
