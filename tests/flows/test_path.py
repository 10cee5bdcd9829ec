"""LinearPath: interpolation, velocity, anchors, validation."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from poseflow.errors import ShapeError
from poseflow.flows.path import LinearPath, PathSample


def _pair(seed: int, shape: tuple[int, ...], dtype: torch.dtype, device: torch.device):
    g = torch.Generator().manual_seed(seed)
    x_0 = torch.randn(shape, generator=g, dtype=dtype).to(device)
    x_1 = torch.randn(shape, generator=g, dtype=dtype).to(device)
    t = torch.rand(shape[0], generator=g, dtype=dtype).to(device)
    return x_0, x_1, t


@given(seed=st.integers(0, 2**31 - 1), b=st.integers(1, 4), n=st.integers(1, 9))
def test_endpoints_and_constant_velocity(seed: int, b: int, n: int) -> None:
    for dtype in (torch.float32, torch.float64):
        x_0, x_1, t = _pair(seed, (b, n, 3), dtype, torch.device("cpu"))
        path = LinearPath()
        s0 = path.sample(x_0, x_1, torch.zeros(b, dtype=dtype))
        s1 = path.sample(x_0, x_1, torch.ones(b, dtype=dtype))
        assert torch.equal(s0.x_t, x_0)
        assert torch.equal(s1.x_t, x_1)
        st_ = path.sample(x_0, x_1, t)
        # x_t is on the segment: x_t = x_0 + t (x_1 - x_0), and dx_t is its derivative
        tol = 1e-5 if dtype == torch.float32 else 1e-12
        expected = x_0 + t[:, None, None] * (x_1 - x_0)
        assert torch.allclose(st_.x_t, expected, atol=tol)
        assert torch.equal(st_.dx_t, x_1 - x_0)
        assert torch.equal(st_.t, t)


def test_finite_difference_matches_velocity(dtype: torch.dtype, device: torch.device) -> None:
    x_0, x_1, t = _pair(0, (3, 7, 3), dtype, device)
    t = t.clamp(0.1, 0.9)
    h = 1e-3
    path = LinearPath()
    fd = (path.sample(x_0, x_1, t + h).x_t - path.sample(x_0, x_1, t - h).x_t) / (2 * h)
    s = path.sample(x_0, x_1, t)
    tol = 2e-3 if dtype == torch.float32 else 1e-9
    assert torch.allclose(fd, s.dx_t, atol=tol)
    assert s.x_t.dtype == dtype and s.x_t.device.type == device.type


def test_batched_equals_per_item(dtype: torch.dtype) -> None:
    x_0, x_1, t = _pair(1, (4, 5, 3), dtype, torch.device("cpu"))
    path = LinearPath()
    batched = path.sample(x_0, x_1, t)
    for i in range(4):
        one = path.sample(x_0[i : i + 1], x_1[i : i + 1], t[i : i + 1])
        assert torch.equal(one.x_t[0], batched.x_t[i])


def test_other_ranks_broadcast() -> None:
    x_0, x_1, t = _pair(2, (2, 4, 5, 6), torch.float64, torch.device("cpu"))
    s = LinearPath().sample(x_0, x_1, t)
    assert s.x_t.shape == (2, 4, 5, 6)
    assert torch.allclose(s.x_t[1], x_0[1] + t[1] * (x_1[1] - x_0[1]))


def test_frozen_points_are_pinned_to_data(dtype: torch.dtype, device: torch.device) -> None:
    x_0, x_1, t = _pair(3, (2, 6, 3), dtype, device)
    frozen = torch.zeros(2, 6, dtype=torch.bool, device=device)
    frozen[:, :2] = True
    s = LinearPath().sample(x_0, x_1, t, frozen_mask=frozen)
    assert torch.equal(s.x_t[:, :2], x_1[:, :2])
    assert torch.count_nonzero(s.dx_t[:, :2]) == 0
    free = LinearPath().sample(x_0, x_1, t)
    assert torch.equal(s.x_t[:, 2:], free.x_t[:, 2:])
    assert torch.equal(s.dx_t[:, 2:], free.dx_t[:, 2:])


def test_gradients_flow_to_data() -> None:
    x_0, x_1, t = _pair(4, (2, 3, 3), torch.float64, torch.device("cpu"))
    x_1.requires_grad_(True)
    s = LinearPath().sample(x_0, x_1, t)
    s.x_t.sum().backward()
    assert torch.allclose(x_1.grad, t[:, None, None].expand(2, 3, 3))


def test_path_sample_is_immutable() -> None:
    s = PathSample(torch.zeros(1), torch.zeros(1), torch.zeros(1))
    with pytest.raises(AttributeError):
        s.x_t = torch.ones(1)  # type: ignore[misc]


@pytest.mark.parametrize(
    ("x_1_shape", "t_shape", "frozen_shape"),
    [((2, 5, 2), (2,), None), ((2, 5, 3), (3,), None), ((2, 5, 3), (2,), (2, 4))],
)
def test_bad_shapes_raise(x_1_shape, t_shape, frozen_shape) -> None:
    frozen = None if frozen_shape is None else torch.zeros(frozen_shape, dtype=torch.bool)
    with pytest.raises(ShapeError):
        LinearPath().sample(
            torch.zeros(2, 5, 3), torch.zeros(x_1_shape), torch.zeros(t_shape), frozen_mask=frozen
        )


def test_dtype_mismatch_and_float_mask_raise() -> None:
    with pytest.raises(ShapeError):
        LinearPath().sample(torch.zeros(2, 5, 3), torch.zeros(2, 5, 3).double(), torch.zeros(2))
    with pytest.raises(ShapeError):
        LinearPath().sample(
            torch.zeros(2, 5, 3),
            torch.zeros(2, 5, 3),
            torch.zeros(2),
            frozen_mask=torch.zeros(2, 5),
        )
