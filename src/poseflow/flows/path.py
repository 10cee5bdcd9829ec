"""The probability path of conditional flow matching: straight lines from noise to data.

FunFlow6D (section "Conditional flow matching") interpolates a Gaussian noise state ``X(0)`` and
the clean state ``X(1)`` linearly, ``X(t) = (1 - t) X(0) + t X(1)``, so the velocity along the
path is the constant ``X(1) - X(0)``: the rectified-flow / optimal-transport path.

Frozen points (an anchor, such as the query cloud ``Q`` of FunFlow6D) can be pinned at their clean
coordinates for the whole path, ``X(t) = X(1)`` and ``dX/dt = 0`` there: this is the training-time
counterpart of the samplers' zeroed anchor velocity when they are given ``x_frozen``
(see :mod:`poseflow.flows.samplers` for the two anchor conventions).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from poseflow._checks import check_mask, check_same, check_tensor
from poseflow.errors import ShapeError

__all__ = ["LinearPath", "PathSample"]


@dataclass(frozen=True)
class PathSample:
    """A point on the probability path and the velocity that the model must regress there.

    Attributes:
        x_t: the interpolated state, shape ``(B, L, C)`` (any ``(B, *)`` for the plain path).
        dx_t: the target velocity ``d x_t / dt``, same shape as ``x_t``.
        t: the times, shape ``(B,)``.
    """

    x_t: torch.Tensor
    dx_t: torch.Tensor
    t: torch.Tensor


class LinearPath:
    """Straight path ``x_t = (1 - t) x_0 + t x_1`` with constant velocity ``x_1 - x_0``.

    ``x_0`` is the noise end (``t = 0``) and ``x_1`` the data end (``t = 1``), as in the paper.

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> x_0, x_1 = torch.randn(2, 4, 3, generator=g), torch.randn(2, 4, 3, generator=g)
        >>> s = LinearPath().sample(x_0, x_1, torch.tensor([0.0, 1.0]))
        >>> torch.equal(s.x_t[0], x_0[0]), torch.equal(s.x_t[1], x_1[1])
        (True, True)
        >>> torch.allclose(s.dx_t, x_1 - x_0)
        True
    """

    def sample(
        self,
        x_0: torch.Tensor,
        x_1: torch.Tensor,
        t: torch.Tensor,
        *,
        frozen_mask: torch.Tensor | None = None,
    ) -> PathSample:
        """Sample the path at times ``t``.

        Args:
            x_0: noise states, shape ``(B, L, C)`` (or any ``(B, *)`` without ``frozen_mask``).
            x_1: data states, same shape, dtype and device as ``x_0``.
            t: times in ``[0, 1]``, shape ``(B,)``, broadcast over all other dimensions.
            frozen_mask: optional ``(B, L)`` bool, True at points pinned to their clean coordinates
                (``x_t = x_1`` and ``dx_t = 0`` there, for every ``t``). ``None`` (the paper's
                equation) interpolates every point.

        Returns:
            A :class:`PathSample` with ``x_t`` and ``dx_t`` shaped like ``x_0`` and ``t``.

        Raises:
            ShapeError: shapes, dtypes or devices disagree.
        """
        check_tensor(x_0, "x_0", ("*", None))
        if x_0.dim() < 2:
            raise ShapeError(f"x_0 must have a batch and at least one more dim, got {x_0.shape}")
        if x_1.shape != x_0.shape:
            raise ShapeError(f"x_1 has shape {tuple(x_1.shape)} but x_0 has {tuple(x_0.shape)}")
        check_tensor(t, "t", (x_0.shape[0],))
        check_same(("x_0", x_0), ("x_1", x_1), ("t", t))
        tb = t.reshape(-1, *([1] * (x_0.dim() - 1)))
        x_t = torch.lerp(x_0, x_1, tb)
        dx_t = x_1 - x_0
        if frozen_mask is not None:
            if x_0.dim() != 3:
                raise ShapeError(f"frozen_mask needs (B, L, C) states, got {tuple(x_0.shape)}")
            check_mask(
                frozen_mask, "frozen_mask", ("B", "L"), {"B": x_0.shape[0], "L": x_0.shape[1]}
            )
            check_same(("x_0", x_0), ("frozen_mask", frozen_mask), dtype=False)
            f = frozen_mask.unsqueeze(-1)
            x_t = torch.where(f, x_1, x_t)
            dx_t = dx_t.masked_fill(f, 0)
        return PathSample(x_t=x_t, dx_t=dx_t, t=t)
