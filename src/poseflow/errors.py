"""Exceptions raised by poseflow.

Every error is a :class:`PoseflowError`; the subclasses are also builtin exceptions so that code
catching ``ValueError`` or ``ImportError`` keeps working.
"""

from __future__ import annotations

__all__ = [
    "BOPFormatError",
    "CheckpointError",
    "DegenerateInputError",
    "MeshFormatError",
    "MissingDependencyError",
    "MissingFileError",
    "MissingSystemLibraryError",
    "MissingWeightsError",
    "NotWritableError",
    "OutputExistsError",
    "PoseflowError",
    "RankFailedError",
    "ResultsFormatError",
    "ShapeError",
    "UnitsError",
    "UsageError",
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
    """A dependency is not installed; the message names the extra (or command) that installs it."""

    def __init__(
        self, package: str, extra: str | None, purpose: str = "", *, install: str | None = None
    ) -> None:
        why = f" for {purpose}" if purpose else ""
        fix = install if install is not None else f"pip install 'poseflow[{extra}]'"
        super().__init__(f"{package} is needed{why} but is not installed: {fix}")


class MissingSystemLibraryError(PoseflowError, ImportError):
    """A system library that a dependency loads is missing; the message names the apt package.

    Args:
        package: the Python package that failed to import (``open3d``).
        library: the shared library it could not load (``libGL.so.1``), or ``""`` when unknown.
        apt_packages: the Debian/Ubuntu packages that provide it.
        purpose: what the package is needed for.
    """

    def __init__(self, package: str, library: str, apt_packages: str, purpose: str = "") -> None:
        why = f" (needed for {purpose})" if purpose else ""
        what = f"the system library {library}" if library else "a system library"
        super().__init__(
            f"{package} cannot be imported{why}: {what} is missing; install it with "
            f"`sudo apt-get install {apt_packages}` (or your system's equivalent)"
        )


class MissingWeightsError(PoseflowError, FileNotFoundError):
    """Pretrained weights were requested but are not available locally."""


class MissingFileError(PoseflowError, FileNotFoundError):
    """A file or folder that a dataset or model format requires is missing."""


class CheckpointError(PoseflowError, ValueError):
    """A checkpoint, cache or configuration file is truncated, corrupt or of the wrong type."""


class NotWritableError(PoseflowError, PermissionError):
    """An output path cannot be written (checked before any work is done)."""


class UnitsError(ValueRangeError):
    """Values whose magnitude shows a unit mix-up (millimetres read as metres, or the reverse).

    The message says which option or argument sets the scale.
    """


class UsageError(ValueRangeError):
    """A command-line option is invalid, missing or conflicts with another (exit code 2)."""


class OutputExistsError(PoseflowError, FileExistsError):
    """An output file or folder exists and overwriting it was not asked for."""


class RankFailedError(PoseflowError, RuntimeError):
    """A process of a job split over several processes failed; the message names its rank and why.

    Raised on every rank of the job, so that all of them stop with a non-zero exit.
    """


class BOPFormatError(PoseflowError, ValueError):
    """A BOP file is malformed: a missing key, a wrong type or shape, or implausible units."""


class ResultsFormatError(BOPFormatError, ValueRangeError):
    """A BOP results file is malformed: a bad header, field, number or rotation (file and line)."""


class MeshFormatError(DegenerateInputError):
    """A mesh file is missing, malformed or uses a feature that is not supported."""
