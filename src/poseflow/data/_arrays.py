"""Array-likes (tensors or numpy arrays) as numpy arrays, for the readers and writers of files."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

__all__ = ["as_numpy"]


def as_numpy(x: Any, dtype: Any = None) -> np.ndarray:
    """``x`` (a tensor on any device, a numpy array or a nested sequence) as a numpy array.

    Args:
        x: the values; a tensor is detached and copied to the CPU.
        dtype: the numpy dtype of the result, or None to keep ``x``'s.

    Returns:
        The array, of ``x``'s shape.

    Example:
        >>> as_numpy(torch.ones(2), np.float64)
        array([1., 1.])
    """
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=dtype)
