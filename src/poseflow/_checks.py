"""The one place where tensor arguments are validated.

Every public function of poseflow checks its tensor inputs through :func:`check_tensor` (shape,
dtype family, device, finiteness) and :func:`check_same` (device and dtype agreement), so error
messages read the same everywhere.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from poseflow.errors import ShapeError, ValueRangeError

__all__ = ["check_mask", "check_same", "check_tensor"]

Dim = int | str | None


def check_tensor(
    x: object,
    name: str,
    shape: Sequence[Dim],
    *,
    floating: bool = True,
    finite: bool = False,
    sizes: dict[str, int] | None = None,
) -> dict[str, int]:
    """Check that ``x`` is a tensor of the given shape pattern.

    Args:
        x: the object to check.
        name: the argument's name, used in messages.
        shape: one entry per dimension: an int (exact size), a letter (a named size that must agree
            with earlier uses of the same letter, including those in ``sizes``) or ``None`` (any).
            A leading ``"*"`` accepts any number of leading dimensions.
        floating: require a floating-point dtype.
        finite: require every entry to be finite (no NaN or inf).
        sizes: named sizes already bound by earlier checks; updated in place and returned.

    Returns:
        The dict of named sizes, so that several checks can share letters.

    Raises:
        ShapeError: wrong type, rank, size or dtype family.
        ValueRangeError: ``finite`` was asked and ``x`` holds NaN or inf.

    Example:
        >>> s = check_tensor(torch.zeros(2, 5, 3), "points", ("B", "N", 3))
        >>> s["B"], s["N"]
        (2, 5)
    """
    sizes = {} if sizes is None else sizes
    if not isinstance(x, torch.Tensor):
        raise ShapeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    pattern = list(shape)
    dims = list(x.shape)
    if pattern and pattern[0] == "*":
        pattern = pattern[1:]
        if len(dims) < len(pattern):
            raise ShapeError(f"{name} must have at least {len(pattern)} dims, got {tuple(x.shape)}")
        dims = dims[len(dims) - len(pattern) :]
    elif len(dims) != len(pattern):
        raise ShapeError(
            f"{name} must have shape {_fmt(shape)}, got {tuple(x.shape)} ({x.dim()} dims)"
        )
    for want, got in zip(pattern, dims):
        if want is None:
            continue
        if isinstance(want, int):
            if got != want:
                raise ShapeError(f"{name} must have shape {_fmt(shape)}, got {tuple(x.shape)}")
        else:
            bound = sizes.setdefault(want, got)
            if bound != got:
                raise ShapeError(
                    f"{name} must have shape {_fmt(shape)} with {want}={bound}, "
                    f"got {tuple(x.shape)}"
                )
    if floating and not x.is_floating_point():
        raise ShapeError(f"{name} must be a floating-point tensor, got {x.dtype}")
    if finite and x.numel() and not bool(torch.isfinite(x).all()):
        raise ValueRangeError(f"{name} contains NaN or inf")
    return sizes


def check_mask(mask: object, name: str, shape: Sequence[Dim], sizes: dict[str, int]) -> None:
    """Check that ``mask`` is a bool tensor of the given shape pattern (True means valid).

    Example:
        >>> check_mask(torch.ones(2, 5, dtype=torch.bool), "mask", ("B", "N"), {"B": 2, "N": 5})
    """
    check_tensor(mask, name, shape, floating=False, sizes=sizes)
    if mask.dtype != torch.bool:  # type: ignore[union-attr]
        raise ShapeError(f"{name} must be a bool tensor, got {mask.dtype}")  # type: ignore[union-attr]


def check_same(*named: tuple[str, torch.Tensor], dtype: bool = True) -> None:
    """Check that tensors share one device (and one dtype, unless ``dtype=False``).

    Under autocast on the tensors' device, floating-point dtypes may differ (mixed precision
    mixes them by design).

    Example:
        >>> check_same(("a", torch.zeros(1)), ("b", torch.ones(1)))
    """
    first_name, first = named[0]
    mixed = torch.is_autocast_enabled(first.device.type)
    for other_name, other in named[1:]:
        if other.device != first.device:
            raise ShapeError(
                f"{other_name} is on {other.device} but {first_name} is on {first.device}"
            )
        if mixed and other.is_floating_point() and first.is_floating_point():
            continue
        if dtype and other.dtype != first.dtype:
            raise ShapeError(
                f"{other_name} has dtype {other.dtype} but {first_name} has {first.dtype}"
            )


def _fmt(shape: Sequence[Dim]) -> str:
    return "(" + ", ".join("?" if d is None else str(d) for d in shape) + ")"
