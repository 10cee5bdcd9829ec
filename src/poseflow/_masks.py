"""Attention masks shared by the fusion layers and the DiT (both torch-only packages)."""

from __future__ import annotations

import torch

__all__ = ["key_padding_mask"]


def key_padding_mask(mask: torch.Tensor) -> torch.Tensor:
    """Turn a validity mask into an SDPA key mask that never masks a whole row.

    A batch item whose points are all padding would leave its attention rows with no key, which
    some SDPA kernels answer with NaN. Such items get every key unmasked instead; their outputs
    are padding anyway and are zeroed by the callers.

    Args:
        mask: ``(B, S)`` bool, True for valid points.

    Returns:
        ``(B, 1, 1, S)`` bool, broadcastable against SDPA's ``(B, H, P, S)`` scores.

    Example:
        >>> key_padding_mask(torch.tensor([[True, False], [False, False]]))[:, 0, 0]
        tensor([[ True, False],
                [ True,  True]])
    """
    keep = mask | ~mask.any(dim=-1, keepdim=True)
    return keep[:, None, None, :]
