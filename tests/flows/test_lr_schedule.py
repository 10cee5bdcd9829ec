"""Warm-up + cosine learning-rate schedule."""

from __future__ import annotations

import itertools
import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from poseflow.errors import ValueRangeError
from poseflow.flows.schedule import warmup_cosine_lr


@given(total=st.integers(1, 500), warm=st.integers(0, 100), lo=st.floats(0, 0.5))
def test_shape_of_the_schedule(total: int, warm: int, lo: float) -> None:
    lrs = [
        warmup_cosine_lr(s, base_lr=1.0, total_steps=total, warmup_steps=warm, min_lr=lo)
        for s in range(total + 5)
    ]
    ramp, tail = lrs[:warm], lrs[warm:]
    assert all(0.0 < x <= 1.0 for x in ramp)
    assert all(a < b for a, b in itertools.pairwise(ramp))
    assert all(lo - 1e-12 <= x <= 1.0 + 1e-12 for x in tail)
    assert all(a >= b - 1e-12 for a, b in itertools.pairwise(tail))
    if warm < total:
        assert lrs[warm] == pytest.approx(1.0)
        assert lrs[-1] == pytest.approx(lo)


def test_cosine_midpoint() -> None:
    lr = warmup_cosine_lr(60, base_lr=2.0, total_steps=110, warmup_steps=10, min_lr=0.0)
    assert lr == pytest.approx(2.0 * 0.5 * (1 + math.cos(math.pi * 0.5)))


def test_bad_arguments() -> None:
    with pytest.raises(ValueRangeError):
        warmup_cosine_lr(-1, base_lr=1.0, total_steps=10)
    with pytest.raises(ValueRangeError):
        warmup_cosine_lr(0, base_lr=1.0, total_steps=0)
