"""Equivalent data states: train against the one nearest the noise.

When several end states are equally right (the canonical coordinates of a symmetric object under
each of its symmetries, for instance), regressing towards one fixed choice asks the network for a
discontinuous function of its input: two views that look the same get different targets. Given
the affine maps ``x -> A_k x + b_k`` that carry ``x_1`` to each of its ``K`` equivalents, the
objective instead pairs the noise ``x_0`` with the equivalent nearest to it (a per-sample optimal
coupling, as in equivariant flow matching). The choice depends on ``x_1`` only through the set of
its equivalents, so every member of a symmetry group gives the same loss.

Maps are stored as ``(B, K, C, C + 1)`` (``[A | b]``) and act on the free points only: frozen
(anchor) points keep their coordinates. A batch whose objects have fewer equivalents than ``K``
pads with the identity, which changes nothing (an equivalent repeated is not a new choice).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from poseflow._checks import check_mask, check_same, check_tensor
from poseflow.errors import ShapeError

__all__ = ["apply_equivalents", "identity_maps", "nearest_equivalent", "pad_maps"]


def identity_maps(
    batch: int, count: int, channels: int, *, dtype: torch.dtype = torch.float32
) -> torch.Tensor:
    """``count`` identity maps per sample, ``(batch, count, channels, channels + 1)``.

    Example:
        >>> identity_maps(2, 1, 3)[0, 0]
        tensor([[1., 0., 0., 0.],
                [0., 1., 0., 0.],
                [0., 0., 1., 0.]])
    """
    eye = torch.eye(channels, channels + 1, dtype=dtype)
    return eye.expand(batch, count, channels, channels + 1).clone()


def pad_maps(maps: Sequence[torch.Tensor], *, dtype: torch.dtype) -> torch.Tensor:
    """Stack each sample's maps ``(K_i, C, C + 1)`` into ``(B, max K_i, C, C + 1)``.

    Samples with fewer maps are padded with the identity.

    Example:
        >>> eye = identity_maps(1, 1, 3)[0]  # (1, 3, 4)
        >>> flip = torch.tensor([[[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 0]]])
        >>> out = pad_maps([eye, torch.cat([eye, flip])], dtype=torch.float64)
        >>> out.shape, torch.equal(out[0, 1], out[0, 0])
        (torch.Size([2, 2, 3, 4]), True)
    """
    channels = maps[0].shape[-2]
    out = identity_maps(len(maps), max(len(m) for m in maps), channels, dtype=dtype)
    for b, m in enumerate(maps):
        out[b, : len(m)] = m.to(dtype)
    return out


def apply_equivalents(
    x_1: torch.Tensor, maps: torch.Tensor, frozen_mask: torch.Tensor | None = None
) -> torch.Tensor:
    """Every equivalent of ``x_1``: ``A_k x + b_k`` at the free points, ``x`` at frozen ones.

    Args:
        x_1: data states ``(B, L, C)``.
        maps: ``(B, K, C, C + 1)`` affine maps ``[A | b]``.
        frozen_mask: optional ``(B, L)`` bool, True at points the maps leave alone.

    Returns:
        ``(B, K, L, C)``.

    Raises:
        ShapeError: shapes, dtypes or devices disagree.
    """
    sizes = check_tensor(x_1, "x_1", ("B", "L", "C"))
    if (
        maps.dim() != 4
        or maps.shape[0] != sizes["B"]
        or maps.shape[2:]
        != (
            sizes["C"],
            sizes["C"] + 1,
        )
    ):
        raise ShapeError(
            f"maps must be (B, K, C, C + 1) = ({sizes['B']}, K, {sizes['C']}, {sizes['C'] + 1}), "
            f"got {tuple(maps.shape)}"
        )
    check_same(("x_1", x_1), ("maps", maps))
    A, b = maps[..., :-1], maps[..., -1]
    out = torch.einsum("bkij,blj->bkli", A, x_1) + b[:, :, None, :]
    if frozen_mask is not None:
        check_mask(frozen_mask, "frozen_mask", ("B", "L"), sizes)
        out = torch.where(frozen_mask[:, None, :, None], x_1[:, None], out)
    return out


def nearest_equivalent(
    x_0: torch.Tensor,
    x_1: torch.Tensor,
    maps: torch.Tensor,
    *,
    mask: torch.Tensor | None = None,
    frozen_mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """The equivalent of each ``x_1`` nearest ``x_0`` over the valid free points.

    Ties go to the first map, so identity-padded maps never move a sample whose own ``x_1`` is
    among the nearest.

    Args:
        x_0: noise states ``(B, L, C)``.
        x_1: data states, same shape.
        maps: ``(B, K, C, C + 1)`` affine maps (see the module docstring).
        mask: optional ``(B, L)`` bool, True at valid points (the others do not count).
        frozen_mask: optional ``(B, L)`` bool, True at anchor points (kept, not counted).

    Returns:
        The chosen data states ``(B, L, C)``.

    Raises:
        ShapeError: shapes, dtypes or devices disagree.

    Example:
        >>> flip = torch.tensor([[[[-1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, 1, 0]]]])
        >>> maps = torch.cat([identity_maps(1, 1, 3), flip], 1)
        >>> x_1 = torch.tensor([[[1.0, 0, 0]]])
        >>> nearest_equivalent(-x_1, x_1, maps)
        tensor([[[-1.,  0.,  0.]]])
    """
    if x_0.shape != x_1.shape:
        raise ShapeError(f"x_0 has shape {tuple(x_0.shape)} but x_1 has {tuple(x_1.shape)}")
    check_same(("x_0", x_0), ("x_1", x_1))
    candidates = apply_equivalents(x_1, maps, frozen_mask)  # (B, K, L, C)
    keep = torch.ones(x_1.shape[:2], dtype=torch.bool, device=x_1.device)
    if mask is not None:
        check_mask(mask, "mask", ("B", "L"), {"B": x_1.shape[0], "L": x_1.shape[1]})
        keep = keep & mask
    if frozen_mask is not None:
        keep = keep & ~frozen_mask
    cost = ((candidates - x_0[:, None]).square().sum(-1) * keep[:, None].to(x_1.dtype)).sum(-1)
    best = cost.argmin(dim=1)  # first minimum on ties
    return candidates[torch.arange(len(best), device=best.device), best]
