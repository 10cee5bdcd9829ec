"""poseflow: 6D object pose estimation from RGBD images, and the parts FunFlow6D is built from.

Subpackages are imported on first use (``poseflow.registration``, ``poseflow.flows``, ...), so
``import poseflow`` stays cheap and a user who needs only the fusion layer never loads Open3D.
:func:`set_num_threads` sets the threads of every CPU pool poseflow uses (torch, numba, BLAS,
Open3D's ray casting); :func:`num_threads` does so for a ``with`` block.
"""

from __future__ import annotations

import importlib
from typing import Any

from poseflow import errors
from poseflow._threads import get_num_threads, num_threads, set_num_threads
from poseflow.errors import PoseflowError

__version__ = "0.1.0"

_SUBPACKAGES = (
    "geometry",
    "registration",
    "render",
    "data",
    "features",
    "fusion",
    "flows",
    "eval",
    "verify",
    "detect",
    "models",
    "baselines",
    "assets",
    "cli",
)

__all__ = [
    "PoseflowError",
    "__version__",
    "errors",
    "get_num_threads",
    "num_threads",
    "set_num_threads",
    *_SUBPACKAGES,
]


def __getattr__(name: str) -> Any:
    if name in _SUBPACKAGES:
        return importlib.import_module(f"poseflow.{name}")
    raise AttributeError(f"module 'poseflow' has no attribute {name!r}")
