"""Time samplers: support, distribution (Kolmogorov-Smirnov against the analytic CDF), seeding."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st
from scipy import stats

from poseflow.errors import ValueRangeError
from poseflow.flows.timesteps import TIME_SAMPLERS, sample_time

#: The analytic CDF of each sampler.
_CDFS = {"uniform": lambda t: t}


def test_every_sampler_has_a_cdf() -> None:
    assert set(TIME_SAMPLERS) == set(_CDFS)


@pytest.mark.parametrize("name", sorted(TIME_SAMPLERS))
def test_distribution_matches_cdf(name: str) -> None:
    t = sample_time(4000, name, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    assert t.shape == (4000,)
    assert bool(((t >= 0) & (t <= 1)).all())
    result = stats.kstest(t.numpy(), _CDFS[name])
    assert result.pvalue > 1e-3, result


@pytest.mark.parametrize("name", sorted(TIME_SAMPLERS))
def test_wrong_cdf_is_rejected(name: str) -> None:
    # the KS check above has power: t**2 (density 1 / (2 sqrt(t))) is rejected
    t = sample_time(4000, name, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    assert stats.kstest(t.numpy() ** 2, _CDFS[name]).pvalue < 1e-6


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


def test_bad_arguments_raise() -> None:
    with pytest.raises(ValueRangeError, match="uniform"):
        sample_time(4, "logit_normal")  # removed, never measured
    with pytest.raises(ValueRangeError):
        sample_time(-1)
