"""COCO run-length encoding of binary masks, as used by BOP detection and segmentation results.

A mask of shape ``(H, W)`` is flattened in column-major (Fortran) order and stored as the lengths
of alternating runs, starting with a run of zeros (which may be empty). The *uncompressed* form
keeps the run lengths as a JSON list; the *compressed* form packs them into an ASCII string: from
the fourth run on, each length is replaced by its difference with the length two runs earlier, and
every value is written as little-endian groups of 5 bits, one character (offset 48) per group, bit
``0x20`` meaning "another group follows" and bit ``0x10`` of the last group carrying the sign.

Both forms are decoded here without pycocotools.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch

from poseflow.errors import ShapeError, ValueRangeError

__all__ = ["rle_area", "rle_decode", "rle_encode"]


def rle_decode(rle: Mapping[str, Any]) -> torch.Tensor:
    """Decode a COCO RLE (compressed string or uncompressed list of counts) to a mask.

    Args:
        rle: a mapping with ``size`` = ``[H, W]`` and ``counts``, either a list of run lengths or
            the compressed ASCII string (``str`` or ``bytes``).

    Returns:
        Bool mask of shape ``(H, W)``, True inside the object.

    Raises:
        ValueRangeError: missing keys, malformed counts, or run lengths that do not sum to
            ``H * W``.

    Example:
        >>> rle_decode({"size": [2, 3], "counts": [1, 2, 3]}).int()
        tensor([[0, 1, 0],
                [1, 0, 0]], dtype=torch.int32)
        >>> rle_decode({"size": [2, 3], "counts": "015"}).int()
        tensor([[1, 0, 0],
                [0, 0, 0]], dtype=torch.int32)
    """
    if not isinstance(rle, Mapping) or "size" not in rle or "counts" not in rle:
        raise ValueRangeError("an RLE must be a mapping with keys 'size' and 'counts'")
    size = rle["size"]
    if not isinstance(size, Sequence) or len(size) != 2 or any(int(s) < 0 for s in size):
        raise ValueRangeError(f"RLE size must be [H, W] with non-negative entries, got {size!r}")
    h, w = int(size[0]), int(size[1])
    counts = rle["counts"]
    if isinstance(counts, bytes):
        counts = counts.decode("ascii")
    runs = _string_to_counts(counts) if isinstance(counts, str) else _check_counts(counts)
    if int(runs.sum()) != h * w:
        raise ValueRangeError(
            f"RLE run lengths sum to {int(runs.sum())} but size {h}x{w} needs {h * w}"
        )
    values = (np.arange(runs.size) % 2).astype(bool)
    flat = np.repeat(values, runs)
    return torch.from_numpy(np.ascontiguousarray(flat.reshape(w, h).T))


def rle_encode(mask: torch.Tensor | np.ndarray, *, compressed: bool = True) -> dict[str, Any]:
    """Encode a binary mask as a COCO RLE.

    Args:
        mask: mask of shape ``(H, W)``; non-zero entries are inside.
        compressed: write ``counts`` as the compressed ASCII string (as pycocotools and the BOP
            results do) rather than a list of run lengths.

    Returns:
        ``{"size": [H, W], "counts": str | list[int]}``, JSON-serialisable.

    Example:
        >>> m = torch.tensor([[0, 1, 0], [1, 0, 0]], dtype=torch.bool)
        >>> rle_encode(m, compressed=False)
        {'size': [2, 3], 'counts': [1, 2, 3]}
        >>> bool((rle_decode(rle_encode(m)) == m).all())
        True
    """
    arr = mask.detach().cpu().numpy() if isinstance(mask, torch.Tensor) else np.asarray(mask)
    if arr.ndim != 2:
        raise ShapeError(f"mask must have shape (H, W), got {arr.shape}")
    h, w = arr.shape
    flat = arr.astype(bool).ravel(order="F")
    change = np.flatnonzero(flat[1:] != flat[:-1]) + 1
    bounds = np.concatenate(([0], change, [flat.size]))
    runs = np.diff(bounds)
    if flat.size and flat[0]:
        runs = np.concatenate(([0], runs))
    counts: str | list[int] = (
        _counts_to_string(runs) if compressed else [int(r) for r in runs.tolist()]
    )
    return {"size": [int(h), int(w)], "counts": counts}


def rle_area(rle: Mapping[str, Any]) -> int:
    """Number of foreground pixels of a COCO RLE, without decoding the mask.

    Example:
        >>> rle_area({"size": [2, 3], "counts": [1, 2, 3]})
        2
    """
    counts = rle["counts"]
    if isinstance(counts, bytes):
        counts = counts.decode("ascii")
    runs = _string_to_counts(counts) if isinstance(counts, str) else _check_counts(counts)
    return int(runs[1::2].sum())


def _check_counts(counts: object) -> np.ndarray:
    try:
        runs = np.asarray(counts, dtype=np.int64)
    except (TypeError, ValueError) as exc:
        raise ValueRangeError(f"RLE counts must be a list of integers: {exc}") from exc
    if runs.ndim != 1 or (runs < 0).any():
        raise ValueRangeError("RLE counts must be a flat list of non-negative integers")
    return runs


def _string_to_counts(s: str) -> np.ndarray:
    out: list[int] = []
    p, n = 0, len(s)
    while p < n:
        x, k, more = 0, 0, True
        while more:
            if p >= n:
                raise ValueRangeError("compressed RLE string ends inside a value")
            c = ord(s[p]) - 48
            if not 0 <= c < 64:
                raise ValueRangeError(f"compressed RLE string has an invalid character {s[p]!r}")
            x |= (c & 0x1F) << (5 * k)
            more = bool(c & 0x20)
            p += 1
            k += 1
            if not more and c & 0x10:
                x -= 1 << (5 * k)
        if len(out) > 2:
            x += out[-2]
        out.append(x)
    return _check_counts(out)


def _counts_to_string(runs: np.ndarray) -> str:
    chars: list[str] = []
    values = [int(r) for r in runs.tolist()]
    for i, r in enumerate(values):
        x = r - values[i - 2] if i > 2 else r
        more = True
        while more:
            c = x & 0x1F
            x >>= 5
            more = x != -1 if c & 0x10 else x != 0
            if more:
                c |= 0x20
            chars.append(chr(c + 48))
    return "".join(chars)
