"""The conditional flow matching loss: a masked mean squared error on velocities."""

from __future__ import annotations

import torch

from poseflow._checks import check_mask, check_same, check_tensor
from poseflow.flows.path import PathSample

__all__ = ["cfm_loss"]


def cfm_loss(
    velocity: torch.Tensor,
    path_sample: PathSample,
    mask: torch.Tensor | None = None,
    frozen_mask: torch.Tensor | None = None,
    *,
    include_frozen: bool = False,
) -> torch.Tensor:
    """Mean squared error between predicted and target velocities over the points that count.

    The paper regresses ``X(1) - X(0)`` on all ``2N`` points with an MSE. A point counts when it
    is valid (``mask``) and, unless ``include_frozen``, not frozen: an anchor's velocity is zeroed
    by every sampler, so its prediction is never used and by default is not trained. The mean is
    pooled over the batch: ``sum_{b,l valid} |v - dx_t|^2 / (C * #valid)``. With no valid point at
    all the loss is exactly 0 (there is nothing to learn), never NaN.

    Args:
        velocity: predicted velocities, shape ``(B, L, C)``.
        path_sample: the :class:`~poseflow.flows.path.PathSample` whose ``dx_t`` (same shape) is
            the target.
        mask: optional ``(B, L)`` bool, True at valid (non-padding) points.
        frozen_mask: optional ``(B, L)`` bool, True at frozen (anchor) points.
        include_frozen: keep frozen points in the loss (the paper's literal loss over all points
            is ``frozen_mask=None`` or ``include_frozen=True``).

    Returns:
        The scalar loss, in the dtype of ``velocity``.

    Raises:
        ShapeError: shapes, dtypes or devices disagree.

    Example:
        >>> from poseflow.flows.path import LinearPath
        >>> x_0, x_1 = torch.zeros(1, 3, 3), torch.ones(1, 3, 3)
        >>> s = LinearPath().sample(x_0, x_1, torch.tensor([0.5]))
        >>> float(cfm_loss(torch.zeros(1, 3, 3), s))
        1.0
        >>> frozen = torch.tensor([[True, False, False]])
        >>> v = torch.ones(1, 3, 3); v[0, 1:] = 3.0
        >>> float(cfm_loss(v, s, frozen_mask=frozen)), float(cfm_loss(v, s, frozen_mask=frozen,
        ...     include_frozen=True))
        (4.0, 2.6666667461395264)
    """
    target = path_sample.dx_t
    sizes = check_tensor(velocity, "velocity", ("B", "L", "C"))
    check_tensor(target, "path_sample.dx_t", ("B", "L", "C"), sizes=sizes)
    check_same(("velocity", velocity), ("path_sample.dx_t", target), dtype=False)
    sq = (velocity - target.to(velocity.dtype)).square()
    weight = _weights(mask, frozen_mask, include_frozen, sizes, velocity)
    if weight is None:
        return sq.mean()
    total = (sq.sum(dim=-1) * weight).sum()
    count = weight.sum() * sizes["C"]
    return total / count.clamp_min(1)


def _weights(
    mask: torch.Tensor | None,
    frozen_mask: torch.Tensor | None,
    include_frozen: bool,
    sizes: dict[str, int],
    like: torch.Tensor,
) -> torch.Tensor | None:
    for name, m in (("mask", mask), ("frozen_mask", frozen_mask)):
        if m is not None:
            check_mask(m, name, ("B", "L"), sizes)
            check_same(("velocity", like), (name, m), dtype=False)
    keep = mask
    if frozen_mask is not None and not include_frozen:
        keep = ~frozen_mask if keep is None else keep & ~frozen_mask
    return None if keep is None else keep.to(like.dtype)
