"""cfm_loss: closed forms, masks, anchors, gradients, validation."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from poseflow.errors import ShapeError
from poseflow.flows.loss import cfm_loss
from poseflow.flows.path import LinearPath


def _case(seed: int, b: int, n: int, dtype=torch.float64, device="cpu"):
    g = torch.Generator().manual_seed(seed)
    x_0 = torch.randn(b, n, 3, generator=g, dtype=dtype)
    x_1 = torch.randn(b, n, 3, generator=g, dtype=dtype)
    t = torch.rand(b, generator=g, dtype=dtype)
    v = torch.randn(b, n, 3, generator=g, dtype=dtype)
    mask = torch.rand(b, n, generator=g) < 0.7
    frozen = torch.rand(b, n, generator=g) < 0.3
    s = LinearPath().sample(x_0.to(device), x_1.to(device), t.to(device))
    return v.to(device), s, mask.to(device), frozen.to(device)


@given(seed=st.integers(0, 2**31 - 1), b=st.integers(1, 4), n=st.integers(1, 12))
def test_matches_reference_mse(seed: int, b: int, n: int) -> None:
    v, s, mask, frozen = _case(seed, b, n)
    assert torch.allclose(cfm_loss(v, s), torch.nn.functional.mse_loss(v, s.dx_t))
    keep = mask & ~frozen
    if keep.any():
        ref = torch.nn.functional.mse_loss(v[keep], s.dx_t[keep])
        assert torch.allclose(cfm_loss(v, s, mask, frozen), ref)
    else:
        assert float(cfm_loss(v, s, mask, frozen)) == 0.0
    if mask.any():
        ref = torch.nn.functional.mse_loss(v[mask], s.dx_t[mask])
        assert torch.allclose(cfm_loss(v, s, mask, frozen, include_frozen=True), ref)
        assert torch.allclose(cfm_loss(v, s, mask), ref)


def test_zero_at_the_target(dtype: torch.dtype, device: torch.device) -> None:
    _, s, mask, frozen = _case(0, 3, 8, dtype, device)
    loss = cfm_loss(s.dx_t.clone(), s, mask, frozen)
    assert float(loss) == 0.0
    assert loss.dtype == dtype and loss.device.type == device.type


def test_gradient_only_on_counted_points() -> None:
    v, s, mask, frozen = _case(1, 2, 10)
    mask[0, 0], frozen[0, 0] = True, False
    mask[0, 1], frozen[0, 1] = True, True
    mask[0, 2] = False
    v.requires_grad_(True)
    cfm_loss(v, s, mask, frozen).backward()
    counted = mask & ~frozen
    assert torch.count_nonzero(v.grad[~counted]) == 0
    assert torch.count_nonzero(v.grad[0, 0]) == 3
    # closed form: d/dv mean |v - u|^2 = 2 (v - u) / (3 * count)
    expected = 2 * (v - s.dx_t) / (3 * counted.sum()) * counted[..., None]
    assert torch.allclose(v.grad, expected.detach())


def test_gradcheck() -> None:
    v, s, mask, frozen = _case(2, 2, 5)
    v.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda v: cfm_loss(v, s, mask, frozen), (v,))


def test_padding_does_not_change_the_loss() -> None:
    v, s, _, _ = _case(3, 2, 6)
    pad = torch.full((2, 3, 3), 1e3, dtype=v.dtype)
    v_pad = torch.cat([v, pad], 1)
    s_pad = LinearPath().sample(
        torch.cat([s.x_t, pad], 1) * 0, torch.cat([s.dx_t, -pad], 1), torch.ones(2, dtype=v.dtype)
    )
    mask = torch.zeros(2, 9, dtype=torch.bool)
    mask[:, :6] = True
    assert torch.allclose(cfm_loss(v_pad, s_pad, mask), cfm_loss(v, s))


def test_low_precision_velocity_is_compared_in_its_dtype() -> None:
    v, s, _, _ = _case(4, 2, 4, dtype=torch.float32)
    loss = cfm_loss(v.to(torch.bfloat16), s)
    assert loss.dtype == torch.bfloat16
    assert torch.isfinite(loss)


def test_bad_input_raises() -> None:
    v, s, mask, frozen = _case(5, 2, 4)
    with pytest.raises(ShapeError):
        cfm_loss(v[:, :3], s)
    with pytest.raises(ShapeError):
        cfm_loss(v, s, mask.float())
    with pytest.raises(ShapeError):
        cfm_loss(v, s, frozen_mask=frozen[:, :3], include_frozen=True)
    with pytest.raises(ShapeError):
        cfm_loss(v[0], s)
