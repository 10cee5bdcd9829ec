"""Time samplers: support, distribution (Kolmogorov-Smirnov against the analytic CDF), seeding."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st
from scipy import stats

from poseflow.errors import ValueRangeError
from poseflow.flows.timesteps import (
    TIME_SAMPLERS,
    logit_normal_time,
    sample_time,
    u_shaped_time,
)


def _cdf(name: str):
    if name == "uniform":
        return lambda t: t
    if name == "logit_normal":
        return lambda t: stats.norm.cdf(torch.logit(torch.as_tensor(t)).numpy())
    a = 4.0
    return lambda t: (
        (torch.sinh(a * (2 * torch.as_tensor(t) - 1)).numpy() + math.sinh(a)) / (2 * math.sinh(a))
    )


@pytest.mark.parametrize("name", sorted(TIME_SAMPLERS))
def test_distribution_matches_cdf(name: str) -> None:
    t = sample_time(4000, name, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    assert t.shape == (4000,)
    assert bool(((t >= 0) & (t <= 1)).all())
    result = stats.kstest(t.numpy(), _cdf(name))
    assert result.pvalue > 1e-3, result


@pytest.mark.parametrize("name", sorted(TIME_SAMPLERS))
def test_wrong_cdf_is_rejected(name: str) -> None:
    # the KS check above has power: each sampler is far from the other two
    t = sample_time(4000, name, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    for other in sorted(TIME_SAMPLERS):
        if other != name:
            assert stats.kstest(t.numpy(), _cdf(other)).pvalue < 1e-6


@given(seed=st.integers(0, 2**31 - 1), b=st.integers(0, 50))
def test_seeded_and_shaped(seed: int, b: int) -> None:
    for name in TIME_SAMPLERS:
        a = sample_time(b, name, generator=torch.Generator().manual_seed(seed))
        c = sample_time(b, name, generator=torch.Generator().manual_seed(seed))
        assert a.shape == (b,)
        assert torch.equal(a, c)


def test_dtype_and_device(dtype: torch.dtype, device: torch.device) -> None:
    g = torch.Generator(device=device).manual_seed(0)
    for name in TIME_SAMPLERS:
        t = sample_time(8, name, generator=g, dtype=dtype)
        assert t.dtype == dtype and t.device.type == device.type


def test_shapes_of_the_alternatives() -> None:
    g = torch.Generator().manual_seed(0)
    mid = lambda t: float(((t > 0.25) & (t < 0.75)).double().mean())  # noqa: E731
    assert mid(logit_normal_time(5000, generator=g)) > 0.6  # mass in the middle
    assert mid(u_shaped_time(5000, generator=g)) < 0.3  # mass at the ends
    wider = logit_normal_time(5000, std=3.0, generator=g)
    assert mid(wider) < mid(logit_normal_time(5000, generator=g))


def test_bad_arguments_raise() -> None:
    with pytest.raises(ValueRangeError):
        sample_time(4, "beta")
    with pytest.raises(ValueRangeError):
        sample_time(-1)
    with pytest.raises(ValueRangeError):
        logit_normal_time(4, std=0.0)
    with pytest.raises(ValueRangeError):
        u_shaped_time(4, a=-1.0)
