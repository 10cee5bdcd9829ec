"""Fusion: learned layers that merge per-point geometric and semantic descriptors (torch only)."""

from poseflow.fusion.attention import (
    CrossAttention,
    GatedCrossAttention,
    attend,
    key_padding_mask,
)
from poseflow.fusion.blocks import (
    FUSIONS,
    ConcatMLPFusion,
    CrossAttentionFusion,
    Fusion,
    FusionGates,
    GatedCrossAttentionFusion,
    SumFusion,
    build_fusion,
)

__all__ = [
    "FUSIONS",
    "ConcatMLPFusion",
    "CrossAttention",
    "CrossAttentionFusion",
    "Fusion",
    "FusionGates",
    "GatedCrossAttention",
    "GatedCrossAttentionFusion",
    "SumFusion",
    "attend",
    "build_fusion",
    "key_padding_mask",
]
