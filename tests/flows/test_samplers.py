"""ODE samplers: exactness, convergence order, anchors, conditioning, autograd, validation."""

from __future__ import annotations

import itertools
import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from poseflow.errors import ShapeError, ValueRangeError
from poseflow.flows.protocols import VelocityModel
from poseflow.flows.samplers import (
    SAMPLERS,
    EulerSampler,
    RK4Sampler,
    get_sampler,
    initial_noise,
    sample,
)

METHODS = sorted(SAMPLERS)
ORDERS = {"euler": 1, "midpoint": 2, "heun": 2, "rk4": 4}


def _noise(seed: int, shape=(2, 5, 3), dtype=torch.float64, device="cpu") -> torch.Tensor:
    return torch.randn(shape, generator=torch.Generator().manual_seed(seed), dtype=dtype).to(device)


class Constant:
    def __init__(self, c: torch.Tensor) -> None:
        self.c = c

    def __call__(self, *, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return self.c.to(x).expand_as(x)


class Linear:
    """dx/dt = x A^T: x(1) = x(0) expm(A)^T."""

    def __init__(self, A: torch.Tensor) -> None:
        self.A = A

    def __call__(self, *, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return x @ self.A.T.to(x)


def _linear_field(seed: int = 0) -> Linear:
    g = torch.Generator().manual_seed(seed)
    return Linear(torch.randn(3, 3, generator=g, dtype=torch.float64) * 0.8)


def test_all_documented_solvers_exist() -> None:
    assert set(METHODS) == set(ORDERS)
    for name, order in ORDERS.items():
        assert SAMPLERS[name].order == order


@given(seed=st.integers(0, 2**31 - 1), steps=st.integers(1, 12))
@settings(max_examples=15)
def test_constant_velocity_is_exact(seed: int, steps: int) -> None:
    x_0 = _noise(seed)
    c = _noise(seed + 1, (1, 1, 3))
    for name in METHODS:
        out = sample(Constant(c), x_0, steps=steps, method=name)
        assert torch.allclose(out, x_0 + c, atol=1e-12), name


def test_constant_velocity_dtype_device(dtype: torch.dtype, device: torch.device, tol) -> None:
    x_0 = _noise(0, dtype=dtype, device=device)
    c = torch.tensor([0.5, -1.0, 2.0], dtype=dtype, device=device)
    out = EulerSampler(steps=7).sample(Constant(c), x_0)
    assert out.dtype == dtype and out.device.type == device.type
    assert torch.allclose(out, x_0 + c, atol=tol)


@pytest.mark.parametrize("method", METHODS)
def test_linear_field_converges_with_the_promised_order(method: str) -> None:
    field = _linear_field()
    x_0 = _noise(0)
    exact = x_0 @ torch.linalg.matrix_exp(field.A).T
    base = {1: 32, 2: 16, 4: 8}[ORDERS[method]]
    errors = [
        float((sample(field, x_0, steps=k, method=method) - exact).abs().max())
        for k in (base, 2 * base, 4 * base)
    ]
    for coarse, fine in itertools.pairwise(errors):
        observed = math.log2(coarse / fine)
        assert abs(observed - ORDERS[method]) < 0.25, (method, errors)
    assert errors[-1] < {1: 5e-2, 2: 1e-4, 4: 1e-8}[ORDERS[method]]


def test_time_argument_is_the_step_start() -> None:
    # dx/dt = 2t integrates to 1; Euler sees t = 0, dt, ..., 1 - dt, hence (K - 1) / K.
    def ramp(*, x, t):
        assert t.shape == (x.shape[0],) and t.dtype == x.dtype
        return (2 * t)[:, None, None].expand_as(x)

    x_0 = torch.zeros(2, 3, 3, dtype=torch.float64)
    for k in (1, 4, 10):
        assert torch.allclose(sample(ramp, x_0, steps=k), x_0 + (k - 1) / k)
    for name in ("midpoint", "heun", "rk4"):  # exact for a linear-in-t field
        assert torch.allclose(sample(ramp, x_0, steps=3, method=name), x_0 + 1.0)


def test_cubic_in_time_is_exact_with_rk4() -> None:
    def cubic(*, x, t):
        return (4 * t**3)[:, None, None].expand_as(x)

    x_0 = torch.zeros(1, 2, 3, dtype=torch.float64)
    assert torch.allclose(RK4Sampler(steps=2).sample(cubic, x_0), x_0 + 1.0, atol=1e-14)


@pytest.mark.parametrize("method", METHODS)
def test_frozen_points_never_move(method: str, dtype: torch.dtype, device: torch.device) -> None:
    x_0 = _noise(2, (3, 6, 3), dtype=dtype, device=device)
    frozen = torch.zeros(3, 6, dtype=torch.bool, device=device)
    frozen[:, :2] = True
    frozen[2, 5] = True
    field = _linear_field(1)
    traj = sample(field, x_0, steps=4, method=method, frozen_mask=frozen, return_trajectory=True)
    assert traj.shape == (5, 3, 6, 3)
    for state in traj:
        assert torch.equal(state[frozen], x_0[frozen])
    # free points are unaffected by freezing others only through the model; with a point-wise
    # field they follow the unfrozen solution exactly
    free = sample(field, x_0, steps=4, method=method)
    assert torch.allclose(traj[-1][~frozen], free[~frozen])


def test_x_frozen_pins_the_anchor_and_leaves_x0_untouched() -> None:
    x_0 = _noise(3, (2, 4, 3))
    x_0_copy = x_0.clone()
    anchor = _noise(4, (2, 4, 3))
    frozen = torch.tensor([[True, True, False, False], [True, False, False, False]])
    seen = []

    def model(*, x, t, x_noise):
        seen.append(x_noise)
        return torch.ones_like(x)

    out = sample(model, x_0, steps=3, frozen_mask=frozen, x_frozen=anchor, x_noise=x_0)
    assert torch.equal(out[frozen], anchor[frozen])
    assert torch.allclose(out[~frozen], x_0[~frozen] + 1)
    assert torch.equal(x_0, x_0_copy)
    assert all(s is x_0 for s in seen)


def test_conditioning_keywords_pass_through() -> None:
    calls = []

    class DiTLike(torch.nn.Module):
        def forward(self, x, t, *, condition, mask=None):
            calls.append((condition, mask))
            return torch.zeros_like(x) + condition.mean(-1, keepdim=True)

    x_0 = _noise(5, (2, 4, 3))
    cond = _noise(6, (2, 4, 8))
    mask = torch.ones(2, 4, dtype=torch.bool)
    model = DiTLike()
    assert isinstance(model, VelocityModel)
    sampler = get_sampler("heun", steps=3)
    out = sampler.sample(model, x_0, condition=cond, mask=mask)
    assert len(calls) == sampler.nfe == 6
    assert all(c is cond and m is mask for c, m in calls)
    assert torch.allclose(out, x_0 + cond.mean(-1, keepdim=True))


def test_trajectory_endpoints() -> None:
    x_0 = _noise(7)
    traj = sample(_linear_field(), x_0, steps=6, method="midpoint", return_trajectory=True)
    assert traj.shape == (7, *x_0.shape)
    assert torch.equal(traj[0], x_0)
    assert torch.equal(traj[-1], sample(_linear_field(), x_0, steps=6, method="midpoint"))


def test_no_autograd_unless_asked() -> None:
    net = torch.nn.Linear(3, 3).double()

    def model(*, x, t):
        return net(x)

    x_0 = _noise(8)
    assert not sample(model, x_0, steps=3).requires_grad
    out = sample(model, x_0, steps=3, method="rk4", enable_grad=True)
    assert out.requires_grad
    out.sum().backward()
    assert net.weight.grad is not None and net.weight.grad.abs().sum() > 0


def test_generate_is_seeded(device: torch.device) -> None:
    g = lambda: torch.Generator(device=device).manual_seed(11)  # noqa: E731
    sampler = EulerSampler(steps=3)
    a = sampler.generate(Constant(torch.zeros(3)), (2, 5, 3), generator=g(), dtype=torch.float64)
    b = initial_noise((2, 5, 3), generator=g(), dtype=torch.float64)
    assert torch.equal(a, b)
    assert a.device.type == device.type and a.dtype == torch.float64


def test_bad_input_raises() -> None:
    x_0 = _noise(9)
    zero = Constant(torch.zeros(3))
    with pytest.raises(ValueRangeError):
        EulerSampler(steps=0)
    with pytest.raises(ValueRangeError):
        get_sampler("dopri5")
    with pytest.raises(ShapeError):
        sample(zero, x_0[0])
    with pytest.raises(ShapeError):
        sample(zero, x_0, frozen_mask=torch.zeros(2, 4, dtype=torch.bool))
    with pytest.raises(ShapeError):
        sample(zero, x_0, x_frozen=x_0)
    with pytest.raises(ShapeError):
        sample(lambda *, x, t: x[..., :2], x_0)
    with pytest.raises(ValueRangeError):
        sample(lambda *, x, t: torch.full_like(x, float("nan")), x_0)
