"""Exceptions raised by poseflow.

Every error is a :class:`PoseflowError`; the subclasses are also builtin exceptions so that code
catching ``ValueError`` or ``ImportError`` keeps working.
"""

from __future__ import annotations

__all__ = [
    "BOPFormatError",
    "DegenerateInputError",
    "MeshFormatError",
    "MissingDependencyError",
    "MissingFileError",
    "MissingWeightsError",
    "PoseflowError",
    "ShapeError",
    "ValueRangeError",
]


class PoseflowError(Exception):
    """Base class of every exception raised by poseflow."""


class ShapeError(PoseflowError, ValueError):
    """A tensor has the wrong shape, dtype or device for the call."""


class ValueRangeError(PoseflowError, ValueError):
    """An argument or tensor holds a value outside its allowed range (NaN, inf, negative size)."""


class DegenerateInputError(PoseflowError, ValueError):
    """Input is well-formed but carries too little information (too few points, collinear)."""


class MissingDependencyError(PoseflowError, ImportError):
    """An optional dependency is not installed; the message names the extra that installs it."""

    def __init__(self, package: str, extra: str, purpose: str = "") -> None:
        why = f" for {purpose}" if purpose else ""
        super().__init__(
            f"{package} is needed{why} but is not installed: pip install 'poseflow[{extra}]'"
        )


class MissingWeightsError(PoseflowError, FileNotFoundError):
    """Pretrained weights were requested but are not available locally."""


class MissingFileError(PoseflowError, FileNotFoundError):
    """A file or folder that a dataset or model format requires is missing."""


class BOPFormatError(PoseflowError, ValueError):
    """A BOP file is malformed: a missing key, a wrong type or shape, or implausible units."""


class MeshFormatError(DegenerateInputError):
    """A mesh file is missing, malformed or uses a feature that is not supported."""
