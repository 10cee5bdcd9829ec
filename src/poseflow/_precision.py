"""The arithmetic a network runs in: named precisions and the autocast they mean.

``"fp32"`` is the network's own dtype, ``"bf16"`` / ``"fp16"`` run its matrix products under
:func:`torch.autocast` in that dtype (normalisations, softmax statistics and the state a sampler
integrates stay float32), and ``"auto"`` is ``"bf16"`` where the device computes it natively,
else ``"fp32"``: a CUDA GPU with bfloat16 support, or a CPU with AVX-512 BF16 or AMX
instructions. Elsewhere bfloat16 products would be emulated, slower than float32. Shared by the
velocity network (:mod:`poseflow.flows` re-exports it), the appearance encoders at inference and
the surface embedding's training.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch

from poseflow.errors import ValueRangeError

__all__ = ["PRECISIONS", "autocast_dtype", "native_bfloat16", "precision_autocast"]

#: The named precisions and the autocast dtype each stands for (None: no autocast).
PRECISIONS: dict[str, torch.dtype | None] = {
    "fp32": None,
    "bf16": torch.bfloat16,
    "fp16": torch.float16,
}


def native_bfloat16(device: torch.device | str) -> bool:
    """Whether ``device`` multiplies bfloat16 matrices in hardware.

    Example:
        >>> native_bfloat16("meta")
        False
    """
    device = torch.device(device)
    if device.type == "cuda":
        return torch.cuda.is_available() and torch.cuda.is_bf16_supported()
    if device.type == "cpu":
        checks = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")
        return any(bool(getattr(torch.cpu, name, lambda: False)()) for name in checks)
    return False


def autocast_dtype(precision: str, device: torch.device | str) -> torch.dtype | None:
    """The autocast dtype of ``precision`` on ``device`` (None: the network's own dtype).

    Args:
        precision: ``"fp32"``, ``"bf16"``, ``"fp16"`` or ``"auto"``.
        device: where the network runs.

    Raises:
        ValueRangeError: an unknown name.

    Example:
        >>> autocast_dtype("bf16", "cpu"), autocast_dtype("fp32", "cpu")
        (torch.bfloat16, None)
    """
    if precision == "auto":
        return torch.bfloat16 if native_bfloat16(device) else None
    if precision not in PRECISIONS:
        raise ValueRangeError(
            f"precision must be one of {', '.join(sorted([*PRECISIONS, 'auto']))}, "
            f"got {precision!r}"
        )
    return PRECISIONS[precision]


@contextlib.contextmanager
def precision_autocast(precision: str, device: torch.device | str) -> Iterator[None]:
    """Run the block in ``precision`` on ``device`` (see :func:`autocast_dtype`).

    Example:
        >>> with precision_autocast("bf16", "cpu"):
        ...     (torch.ones(2, 2) @ torch.ones(2, 2)).dtype
        torch.bfloat16
    """
    dtype = autocast_dtype(precision, device)
    if dtype is None:
        yield
        return
    with torch.autocast(device_type=torch.device(device).type, dtype=dtype):
        yield
