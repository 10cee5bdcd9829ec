"""The positional encoder ``Ξ`` of FunFlow6D's conditioning signal ``C = [F | P]``.

Shape letters: ``B`` batch, ``L`` points (``2N`` for ``[Q ; T]``), ``K`` frequencies.

Per point the encoder reads a 10-dimensional input: the point's coordinates ``p``, its surface
normal ``n``, the coordinates ``x₀`` of its counterpart in the noise sample ``X(0)``, and a flag
that is 1 for target points and 0 for query points. Each geometric attribute (``p``, ``n``,
``x₀``) gets its own NeRF-style sinusoidal embedding
``γ(a) = [a, sin(2⁰πa), cos(2⁰πa), …, sin(2^{K−1}πa), cos(2^{K−1}πa)]``; learned point-wise
features (a linear layer with GELU over the whole 10-dim input, the only place where the flag
enters) are concatenated to them, and a linear layer projects the result to ``d_P`` channels.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from poseflow._checks import check_mask, check_same, check_tensor
from poseflow.errors import ValueRangeError

__all__ = ["PointPositionalEncoder", "nerf_embedding"]


def nerf_embedding(a: torch.Tensor, num_frequencies: int) -> torch.Tensor:
    """NeRF's sinusoidal embedding ``[a, sin(2^k π a), cos(2^k π a)]`` for ``k < K``.

    Args:
        a: values, shape ``(*, A)``.
        num_frequencies: ``K``, the number of octaves.

    Returns:
        ``(*, A · (1 + 2K))`` in ``a``'s dtype: the input, then octave by octave the sines of
        all ``A`` channels followed by their cosines.

    Example:
        >>> nerf_embedding(torch.tensor([[0.25]]), 1)
        tensor([[0.2500, 0.7071, 0.7071]])
        >>> nerf_embedding(torch.zeros(4, 3), 10).shape
        torch.Size([4, 63])
    """
    k = torch.arange(num_frequencies, dtype=a.dtype, device=a.device)
    angles = a[..., None, :] * (math.pi * 2.0**k)[:, None]  # (*, K, A)
    waves = torch.cat([torch.sin(angles), torch.cos(angles)], dim=-1)  # (*, K, 2A)
    return torch.cat([a, waves.flatten(-2)], dim=-1)


class PointPositionalEncoder(nn.Module):
    """Encode per-point geometry and cloud membership into ``d_P`` channels (the paper's ``Ξ``).

    Args:
        out_dim: output channels ``d_P``.
        num_frequencies: octaves ``K`` of each sinusoidal embedding (NeRF's 10 for positions; the
            paper does not give a value). Frequencies reach ``2^{K−1}π`` per unit, so inputs should
            be in roughly unit scale.
        feature_dim: channels of the learned point-wise features.

    Example:
        >>> enc = PointPositionalEncoder(32)
        >>> p, n, x0 = torch.randn(2, 6, 3), torch.randn(2, 6, 3), torch.randn(2, 6, 3)
        >>> flag = torch.tensor([[False] * 3 + [True] * 3] * 2)
        >>> enc(p, n, x0, flag).shape
        torch.Size([2, 6, 32])
    """

    def __init__(self, out_dim: int = 64, *, num_frequencies: int = 10, feature_dim: int = 64):
        super().__init__()
        if out_dim <= 0 or num_frequencies < 0 or feature_dim <= 0:
            raise ValueRangeError(
                "out_dim and feature_dim must be positive and num_frequencies non-negative, got "
                f"{out_dim}, {feature_dim} and {num_frequencies}"
            )
        self.out_dim = out_dim
        self.num_frequencies = num_frequencies
        self.features = nn.Sequential(nn.Linear(10, feature_dim), nn.GELU())
        self.proj = nn.Linear(3 * 3 * (1 + 2 * num_frequencies) + feature_dim, out_dim)

    def forward(
        self,
        points: torch.Tensor,
        normals: torch.Tensor,
        noise: torch.Tensor,
        is_target: torch.Tensor,
    ) -> torch.Tensor:
        """Encode every point.

        Args:
            points: coordinates ``p``, shape ``(B, L, 3)``.
            normals: unit surface normals ``n``, shape ``(B, L, 3)``.
            noise: each point's counterpart ``x₀`` in the noise sample ``X(0)``, ``(B, L, 3)``.
            is_target: ``(B, L)`` bool, True for target points and False for query points.

        Returns:
            ``(B, L, d_P)`` in the inputs' dtype.

        Raises:
            ShapeError: shapes, dtypes or devices that do not match.
        """
        sizes = check_tensor(points, "points", ("B", "L", 3))
        check_tensor(normals, "normals", ("B", "L", 3), sizes=sizes)
        check_tensor(noise, "noise", ("B", "L", 3), sizes=sizes)
        check_mask(is_target, "is_target", ("B", "L"), sizes)
        check_same(("points", points), ("normals", normals), ("noise", noise))
        check_same(("points", points), ("is_target", is_target), dtype=False)
        flag = is_target[..., None].to(points.dtype)
        raw = torch.cat([points, normals, noise, flag], dim=-1)
        k = self.num_frequencies
        parts = [nerf_embedding(a, k) for a in (points, normals, noise)]
        return self.proj(torch.cat([*parts, self.features(raw)], dim=-1))
