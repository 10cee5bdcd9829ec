"""Fusion of per-point geometric and semantic descriptors into one descriptor per point.

Shape letters: ``B`` batch, ``P`` points, ``D`` channels.

Every block here has the same call, so that a configuration string picks one
(:func:`build_fusion`)::

    fused = block(geometric, semantic, mask)                       # (B, P, D)
    fused, gates = block(geometric, semantic, mask, return_gates=True)

Both inputs are L2-normalised along the channels inside the block (the paper's ``G`` and ``S``
are L2-normalised) and every output is L2-normalised too. Rows of padded points (``mask`` False)
are zero in the output, and padding never changes the output at valid points.

The blocks, from the paper's fusion ablation:

- :class:`GatedCrossAttentionFusion` (``"gated"``): FunFlow6D's bidirectional gated
  cross-attention, then concatenation, a two-layer GELU MLP, LayerNorm and L2 normalisation.
- :class:`CrossAttentionFusion` (``"cross"``): the same without the sigmoid gates.
- :class:`ConcatMLPFusion` (``"concat_mlp"``): no attention; concatenation and the MLP only.
- :class:`SumFusion` (``"sum"``): the point-wise sum of Flose; no parameters.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from poseflow._checks import check_mask, check_same, check_tensor
from poseflow.errors import ValueRangeError
from poseflow.fusion.attention import CrossAttention, GatedCrossAttention

__all__ = [
    "FUSIONS",
    "ConcatMLPFusion",
    "CrossAttentionFusion",
    "Fusion",
    "FusionGates",
    "GatedCrossAttentionFusion",
    "SumFusion",
    "build_fusion",
]


class FusionGates(NamedTuple):
    """Per-point, per-channel gates of :class:`GatedCrossAttentionFusion`, each ``(B, P, D)``.

    Attributes:
        geometric: gate of the branch whose queries are the geometric stream (G → S): how much
            of what the geometric stream gathers from the semantic one it lets through.
        semantic: gate of the branch whose queries are the semantic stream (S → G).
    """

    geometric: torch.Tensor
    semantic: torch.Tensor


FusionOutput = torch.Tensor | tuple[torch.Tensor, FusionGates | None]


class Fusion(nn.Module, ABC):
    """Base class of the fusion blocks: input checks, normalisation and masking.

    A subclass implements :meth:`_fuse` on the L2-normalised streams; :meth:`forward` checks the
    inputs, normalises the result and zeroes padded points, so every block has the same call.

    Args:
        dim: channels ``D`` of both streams and of the output.
    """

    def __init__(self, dim: int) -> None:
        super().__init__()
        if dim <= 0:
            raise ValueRangeError(f"dim must be positive, got {dim}")
        self.dim = dim

    def forward(
        self,
        geometric: torch.Tensor,
        semantic: torch.Tensor,
        mask: torch.Tensor | None = None,
        *,
        return_gates: bool = False,
    ) -> FusionOutput:
        """Fuse the two streams.

        Args:
            geometric: geometric descriptors ``G``, shape ``(B, P, D)``.
            semantic: semantic descriptors ``S``, shape ``(B, P, D)``, point ``i`` of both
                describing the same 3-D point.
            mask: ``(B, P)`` bool, True for valid points; None means all valid.
            return_gates: also return the gates (a :class:`FusionGates` for the gated block,
                None for the others).

        Returns:
            Fused, L2-normalised descriptors ``(B, P, D)`` (zero at padded points), or the pair
            ``(fused, gates)`` when ``return_gates`` is True.

        Raises:
            ShapeError: shapes, dtypes or devices that do not match.
        """
        sizes = check_tensor(geometric, "geometric", ("B", "P", self.dim))
        check_tensor(semantic, "semantic", ("B", "P", self.dim), sizes=sizes)
        check_same(("geometric", geometric), ("semantic", semantic))
        if mask is not None:
            check_mask(mask, "mask", ("B", "P"), sizes)
            check_same(("geometric", geometric), ("mask", mask), dtype=False)
        g = F.normalize(geometric, dim=-1)
        s = F.normalize(semantic, dim=-1)
        fused, gates = self._fuse(g, s, mask)
        fused = F.normalize(fused, dim=-1)
        if mask is not None:
            fused = fused * mask[..., None].to(fused.dtype)
        if return_gates:
            return fused, gates
        return fused

    @abstractmethod
    def _fuse(
        self, g: torch.Tensor, s: torch.Tensor, mask: torch.Tensor | None
    ) -> tuple[torch.Tensor, FusionGates | None]:
        """Fuse normalised ``(B, P, D)`` streams; return the unnormalised result and the gates."""


class _MLPHead(nn.Module):
    """``LN(MLP([G̃ | S̃]))``: two linear layers with GELU from ``2D`` channels back to ``D``."""

    def __init__(self, dim: int, hidden_dim: int | None) -> None:
        super().__init__()
        hidden = 2 * dim if hidden_dim is None else hidden_dim
        if hidden <= 0:
            raise ValueRangeError(f"hidden_dim must be positive, got {hidden}")
        self.mlp = nn.Sequential(nn.Linear(2 * dim, hidden), nn.GELU(), nn.Linear(hidden, dim))
        self.norm = nn.LayerNorm(dim)

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return self.norm(self.mlp(torch.cat([a, b], dim=-1)))


class SumFusion(Fusion):
    """Point-wise sum of the normalised streams, ``F = norm(G + S)`` (Flose's fusion).

    Args:
        dim: channels ``D``.

    Example:
        >>> g = torch.tensor([[[1.0, 0.0]]])
        >>> SumFusion(2)(g, torch.tensor([[[0.0, 2.0]]]))
        tensor([[[0.7071, 0.7071]]])
    """

    def __init__(self, dim: int = 64) -> None:
        super().__init__(dim)

    def _fuse(
        self, g: torch.Tensor, s: torch.Tensor, mask: torch.Tensor | None
    ) -> tuple[torch.Tensor, None]:
        return g + s, None


class ConcatMLPFusion(Fusion):
    """Concatenation and MLP without attention, ``F = norm(LN(MLP([G | S])))``.

    Args:
        dim: channels ``D``.
        hidden_dim: width of the MLP's hidden layer (default ``2·D``; the paper does not give it).

    Example:
        >>> fused = ConcatMLPFusion(8)(torch.randn(2, 5, 8), torch.randn(2, 5, 8))
        >>> fused.norm(dim=-1).allclose(torch.ones(2, 5))
        True
    """

    def __init__(self, dim: int = 64, *, hidden_dim: int | None = None) -> None:
        super().__init__(dim)
        self.head = _MLPHead(dim, hidden_dim)

    def _fuse(
        self, g: torch.Tensor, s: torch.Tensor, mask: torch.Tensor | None
    ) -> tuple[torch.Tensor, None]:
        return self.head(g, s), None


class _BidirectionalFusion(Fusion):
    """Two cross-attention branches (G → S and S → G), concatenation, MLP, LN, L2 norm."""

    attention: type[CrossAttention] = CrossAttention

    def __init__(
        self,
        dim: int = 64,
        *,
        num_heads: int = 4,
        dropout: float = 0.1,
        hidden_dim: int | None = None,
    ) -> None:
        super().__init__(dim)
        self.geometric_branch = self.attention(dim, num_heads=num_heads, dropout=dropout)
        self.semantic_branch = self.attention(dim, num_heads=num_heads, dropout=dropout)
        self.head = _MLPHead(dim, hidden_dim)

    def _fuse(
        self, g: torch.Tensor, s: torch.Tensor, mask: torch.Tensor | None
    ) -> tuple[torch.Tensor, FusionGates | None]:
        g_out, g_gate = self.geometric_branch(g, s, kv_mask=mask, q_mask=mask, return_gate=True)
        s_out, s_gate = self.semantic_branch(s, g, kv_mask=mask, q_mask=mask, return_gate=True)
        gates = None if g_gate is None or s_gate is None else FusionGates(g_gate, s_gate)
        return self.head(g_out, s_out), gates


class CrossAttentionFusion(_BidirectionalFusion):
    """Bidirectional, ungated cross-attention fusion (the ablation's "standard cross-attention").

    Identical to :class:`GatedCrossAttentionFusion` with the sigmoid gates removed: each branch
    is a :class:`~poseflow.fusion.attention.CrossAttention`.

    Args:
        dim: channels ``D`` (paper: 64).
        num_heads: attention heads per branch (paper: 4).
        dropout: dropout after each branch's output projection (paper: 0.1).
        hidden_dim: width of the MLP's hidden layer (default ``2·D``).

    Example:
        >>> block = CrossAttentionFusion(8, num_heads=2).eval()
        >>> block(torch.randn(2, 5, 8), torch.randn(2, 5, 8)).shape
        torch.Size([2, 5, 8])
    """

    attention = CrossAttention


class GatedCrossAttentionFusion(_BidirectionalFusion):
    """FunFlow6D's bidirectional gated cross-attention fusion.

    ``G̃ = GCA(G, S)``, ``S̃ = GCA(S, G)`` (each a
    :class:`~poseflow.fusion.attention.GatedCrossAttention` over all valid points, with its own
    weights), then ``F = norm(LN(MLP([G̃ | S̃])))`` with a two-layer GELU MLP from ``2D`` to ``D``.
    The gates start at exactly 0.5 (see :class:`~poseflow.fusion.attention.GatedCrossAttention`
    for what is initialised how); ``return_gates=True`` exposes them per point and channel, e.g.
    ``gates.geometric.mean(-1)`` maps which points let appearance into the geometric stream.

    Args:
        dim: channels ``D`` (paper: 64).
        num_heads: attention heads per branch (paper: 4, so ``D_h = 16``).
        dropout: dropout after each branch's output projection (paper: 0.1).
        hidden_dim: width of the MLP's hidden layer (default ``2·D``; the paper does not give it).

    Example:
        >>> block = GatedCrossAttentionFusion(8, num_heads=2).eval()
        >>> mask = torch.tensor([[True, True, True, False]])
        >>> g, s = torch.randn(1, 4, 8), torch.randn(1, 4, 8)
        >>> fused, gates = block(g, s, mask, return_gates=True)
        >>> fused.shape, fused[0, 3].abs().sum().item(), gates.geometric[0, 0, 0].item()
        (torch.Size([1, 4, 8]), 0.0, 0.5)
    """

    attention = GatedCrossAttention


#: The fusion blocks by configuration name.
FUSIONS: dict[str, type[Fusion]] = {
    "gated": GatedCrossAttentionFusion,
    "cross": CrossAttentionFusion,
    "concat_mlp": ConcatMLPFusion,
    "sum": SumFusion,
}


def build_fusion(name: str, **kwargs: Any) -> Fusion:
    """Build a fusion block by name.

    Args:
        name: one of ``"gated"``, ``"cross"``, ``"concat_mlp"``, ``"sum"``.
        **kwargs: the block's own arguments (``dim`` for all; ``num_heads``, ``dropout`` and
            ``hidden_dim`` for the attention blocks; ``hidden_dim`` for ``"concat_mlp"``).

    Returns:
        The block, called as ``block(geometric, semantic, mask, *, return_gates=False)``.

    Raises:
        ValueRangeError: an unknown name.

    Example:
        >>> type(build_fusion("gated", dim=32)).__name__
        'GatedCrossAttentionFusion'
    """
    try:
        cls = FUSIONS[name]
    except KeyError:
        raise ValueRangeError(
            f"unknown fusion {name!r}; choose one of {', '.join(sorted(FUSIONS))}"
        ) from None
    return cls(**kwargs)
