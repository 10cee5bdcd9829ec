"""The one place where tensor arguments are validated.

Every public function of poseflow checks its tensor inputs through :func:`check_tensor` (shape,
dtype family, device, finiteness) and :func:`check_same` (device and dtype agreement), so error
messages read the same everywhere.
"""

from __future__ import annotations

import dataclasses
import numbers
import types
import typing
from collections.abc import Mapping, Sequence

import torch

from poseflow.errors import ShapeError, ValueRangeError

__all__ = ["check_field_types", "check_mask", "check_same", "check_tensor"]

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
    if finite and x.numel() and not bool(torch.isfinite(_one_copy(x)).all()):
        raise ValueRangeError(f"{name} contains NaN or inf")
    return sizes


def _one_copy(x: torch.Tensor) -> torch.Tensor:
    """``x`` without the repeats of an ``expand``: one index along every dimension of stride 0.

    An image expanded to ``B`` instances is then checked once, not ``B`` times.
    """
    if all(x.stride()):
        return x
    return x[tuple(slice(None) if st else slice(0, 1) for st in x.stride())]


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


def check_field_types(config: object) -> None:
    """Check every field of a configuration dataclass against its annotated type, once.

    Understood: ``int`` (not a bool), ``float`` (any real number but a bool), ``bool``, ``str``,
    ``tuple[X, ...]`` (a list or tuple of ``X``), ``Literal[...]``, ``X | None`` and nested
    dataclasses (an instance, or a mapping that ``__post_init__`` turns into one). Other
    annotations are left to the class's own checks.

    Args:
        config: a dataclass instance (typically from its ``__post_init__``).

    Raises:
        ValueRangeError: a field holds a value of another type; the message names the class,
            the field, the expected type and the value (what ``--set num_points=abc`` gives).

    Example:
        >>> @dataclasses.dataclass
        ... class C:
        ...     steps: int = 1
        >>> check_field_types(C(steps=4))
        >>> try:
        ...     check_field_types(C(steps="abc"))
        ... except ValueRangeError as e:
        ...     print(e)
        C.steps must be an int, got 'abc' (str)
    """
    cls = type(config)
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(config):  # type: ignore[arg-type]
        value = getattr(config, f.name)
        expected = hints.get(f.name)
        if expected is not None and not _matches(value, expected):
            raise ValueRangeError(
                f"{cls.__name__}.{f.name} must be {_describe(expected)}, got {value!r} "
                f"({type(value).__name__})"
            )


def _matches(value: object, expected: object) -> bool:
    """Whether ``value`` is of the annotated type ``expected`` (see :func:`check_field_types`)."""
    origin, args = typing.get_origin(expected), typing.get_args(expected)
    if expected is typing.Any:
        return True
    if origin in (typing.Union, types.UnionType):
        return any(_matches(value, a) for a in args)
    if expected is type(None):
        return value is None
    if origin is typing.Literal:
        return any(value == a and type(value) is type(a) for a in args)
    if expected is bool:
        return isinstance(value, bool)
    if expected is int:
        return isinstance(value, numbers.Integral) and not isinstance(value, bool)
    if expected is float:
        return isinstance(value, numbers.Real) and not isinstance(value, bool)
    if expected is str:
        return isinstance(value, str)
    if origin is tuple:
        if not isinstance(value, (tuple, list)):
            return False
        if len(args) == 2 and args[1] is Ellipsis:
            return all(_matches(v, args[0]) for v in value)
        return len(args) == len(value) and all(_matches(v, a) for v, a in zip(value, args))
    if isinstance(expected, type) and dataclasses.is_dataclass(expected):
        return isinstance(value, (expected, Mapping))
    return True  # an annotation this check does not understand: the class checks it


def _describe(expected: object) -> str:
    """``expected`` in words: ``an int``, ``a list of numbers``, ``one of 'a', 'b'``."""
    origin, args = typing.get_origin(expected), typing.get_args(expected)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_describe(a) for a in args)
    if expected is type(None):
        return "null"
    if origin is typing.Literal:
        return "one of " + ", ".join(repr(a) for a in args)
    if origin is tuple:
        return "a list of " + _describe(args[0]).split(" ", 1)[-1] + "s"
    names = {bool: "true or false", int: "an int", float: "a number", str: "a string"}
    if expected in names:
        return names[expected]  # type: ignore[index]
    return f"a {getattr(expected, '__name__', expected)} (or a JSON object of its fields)"
