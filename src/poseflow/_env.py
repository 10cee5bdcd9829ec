"""Reading the launcher's environment (``torchrun`` sets ``WORLD_SIZE``, ``RANK``, ...)."""

from __future__ import annotations

import os

from poseflow.errors import ValueRangeError

__all__ = ["env_int"]


def env_int(name: str, default: int) -> int:
    """The integer value of environment variable ``name``, or ``default`` when unset or empty.

    Raises:
        ValueRangeError: the variable is set to something that is not an integer.

    Example:
        >>> env_int("POSEFLOW_SURELY_UNSET", 3)
        3
    """
    raw = os.environ.get(name)
    if raw is None or raw == "":
        return default
    try:
        return int(raw)
    except ValueError as exc:
        raise ValueRangeError(f"environment variable {name}={raw!r} is not an integer") from exc
