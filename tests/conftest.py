"""Shared fixtures: devices, dtypes, tolerances and the hypothesis profile."""

from __future__ import annotations

import os

import pytest
import torch
from hypothesis import HealthCheck, settings

settings.register_profile(
    "ci",
    derandomize=True,
    deadline=None,
    max_examples=25,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.differing_executors],
)
settings.register_profile("dev", deadline=None, max_examples=50)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))

DEVICES = ["cpu"] + (["cuda:0"] if torch.cuda.is_available() else [])
DTYPES = [torch.float32, torch.float64]

#: Absolute tolerance of exact-in-theory results, keyed by dtype.
TOL = {torch.float32: 1e-4, torch.float64: 1e-9}


@pytest.fixture(params=DEVICES)
def device(request: pytest.FixtureRequest) -> torch.device:
    return torch.device(request.param)


@pytest.fixture(params=DTYPES, ids=["float32", "float64"])
def dtype(request: pytest.FixtureRequest) -> torch.dtype:
    return request.param


@pytest.fixture
def tol(dtype: torch.dtype) -> float:
    return TOL[dtype]


@pytest.fixture(scope="session")
def o3d():
    """Open3D, for tests that compare with it (skipped on machines without it, e.g. GPU hosts)."""
    return pytest.importorskip("open3d")
