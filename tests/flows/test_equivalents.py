"""Equivalent data states: the objective trains towards the one nearest the noise."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from poseflow.errors import ShapeError
from poseflow.flows import (
    CFMObjective,
    StepRandom,
    apply_equivalents,
    identity_maps,
    nearest_equivalent,
)
from poseflow.geometry.se3 import random_rotation

DTYPES = [torch.float32, torch.float64]


def _rotation_maps(count: int, generator: torch.Generator, dtype: torch.dtype) -> torch.Tensor:
    """``(1, count, 3, 4)``: the identity then ``count - 1`` random rigid maps."""
    R = random_rotation(count - 1, generator=generator, dtype=dtype)
    b = torch.randn(count - 1, 3, 1, generator=generator, dtype=dtype)
    rigid = torch.cat([R, b], dim=2)
    return torch.cat([identity_maps(1, 1, 3, dtype=dtype)[0], rigid])[None]


@settings(deadline=None, max_examples=30)
@given(st.integers(0, 2**31 - 1), st.integers(1, 6), st.sampled_from(DTYPES))
def test_the_chosen_equivalent_is_the_nearest_over_valid_free_points(seed, count, dtype):
    g = torch.Generator().manual_seed(seed)
    B, L = 3, 10
    maps = torch.cat([_rotation_maps(count, g, dtype) for _ in range(B)])
    x_0 = torch.randn(B, L, 3, generator=g, dtype=dtype)
    x_1 = torch.randn(B, L, 3, generator=g, dtype=dtype)
    mask = torch.rand(B, L, generator=g) > 0.2
    frozen = torch.zeros(B, L, dtype=torch.bool)
    frozen[:, :3] = True
    chosen = nearest_equivalent(x_0, x_1, maps, mask=mask, frozen_mask=frozen)
    assert chosen.dtype == dtype and chosen.shape == x_1.shape
    assert torch.equal(chosen[frozen], x_1[frozen])  # the anchor is never moved
    every = apply_equivalents(x_1, maps, frozen)
    keep = (mask & ~frozen)[:, None, :, None]
    cost = ((every - x_0[:, None]).square() * keep).sum((2, 3))
    own = ((chosen - x_0).square() * keep[:, 0]).sum((1, 2))
    assert torch.allclose(own, cost.min(dim=1).values, rtol=1e-5, atol=1e-6)


@given(st.integers(0, 2**31 - 1), st.sampled_from(DTYPES))
def test_identity_maps_change_nothing(seed, dtype):
    g = torch.Generator().manual_seed(seed)
    x_0, x_1 = torch.randn(2, 2, 5, 3, generator=g, dtype=dtype)
    assert torch.equal(nearest_equivalent(x_0, x_1, identity_maps(2, 4, 3, dtype=dtype)), x_1)


def _group_c4(dtype: torch.dtype) -> torch.Tensor:
    """The four turns about an axis parallel to z by multiples of 90°: ``(4, 3, 4)``."""
    out = []
    for c, s in ((1, 0), (0, 1), (-1, 0), (0, -1)):
        R = torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=dtype)
        axis = torch.tensor([0.3, -0.2, 0.0], dtype=dtype)  # a point of the axis
        out.append(torch.cat([R, (axis - R @ axis)[:, None]], dim=1))
    return torch.stack(out)


class _Zero(torch.nn.Module):
    def forward(self, *, x, t, mask=None):
        return torch.zeros_like(x)


class _Linear(torch.nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.w = torch.nn.Parameter(torch.tensor(0.7))

    def forward(self, *, x, t, mask=None):
        return self.w * x + t[:, None, None]


@pytest.mark.parametrize("dtype", DTYPES)
def test_a_symmetric_ground_truth_costs_the_same_loss_as_the_one_it_equals(dtype):
    g = torch.Generator().manual_seed(0)
    group = _group_c4(dtype)
    x_1 = torch.randn(4, 12, 3, generator=g, dtype=dtype)
    frozen = torch.zeros(4, 12, dtype=torch.bool)
    frozen[:, :6] = True
    maps = group.expand(4, -1, -1, -1)
    turned = apply_equivalents(x_1, maps, frozen)[:, 2]  # each ground truth turned by 180°
    objective = CFMObjective()

    def loss(data, with_maps, model):
        batch = {"x_1": data, "frozen_mask": frozen}
        if with_maps:
            batch["equivalents"] = maps
        return objective(model, batch, StepRandom(torch.Generator().manual_seed(5)))

    linear = _Linear()
    assert torch.allclose(loss(x_1, True, linear), loss(turned, True, linear), rtol=1e-6)
    assert not torch.allclose(loss(x_1, False, linear), loss(turned, False, linear))
    # With a zero velocity the loss is the distance from the noise: never larger when aligned.
    assert loss(x_1, True, _Zero()) < loss(x_1, False, _Zero())


def test_bad_maps_are_shape_errors():
    x = torch.zeros(2, 5, 3)
    with pytest.raises(ShapeError, match="maps must be"):
        nearest_equivalent(x, x, torch.zeros(2, 1, 3, 3))
    with pytest.raises(ShapeError, match="x_0 has shape"):
        nearest_equivalent(torch.zeros(2, 4, 3), x, identity_maps(2, 1, 3))
