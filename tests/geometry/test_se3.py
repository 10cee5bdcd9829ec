"""SE(3) toolkit: round trips, inverse, composition, sampling, angle errors against scipy."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from poseflow.errors import PoseflowError, ShapeError, ValueRangeError
from poseflow.geometry.se3 import (
    compose,
    from_Rt,
    inverse_transform,
    random_rotation,
    random_transform,
    rotation_angle_error,
    to_Rt,
    transform_points,
    translation_error,
)

# The device/dtype fixtures hold plain values, so reusing them across examples is safe.
FIXTURES = settings(
    suppress_health_check=[*settings().suppress_health_check, HealthCheck.function_scoped_fixture]
)
seeds = st.integers(0, 2**31 - 1)


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


@FIXTURES
@given(seed=seeds, B=st.integers(1, 6))
def test_from_to_Rt_round_trip(seed, B, device, dtype):
    g = _gen(seed)
    R = random_rotation(B, generator=g, dtype=dtype).to(device)
    t = torch.randn(B, 3, generator=g, dtype=dtype).to(device)
    T = from_Rt(R, t)
    assert T.dtype == dtype and T.device.type == device.type and T.shape == (B, 4, 4)
    R2, t2 = to_Rt(T)
    assert torch.equal(R2, R) and torch.equal(t2, t)
    assert torch.equal(T[:, 3], torch.tensor([0, 0, 0, 1], dtype=dtype, device=device).expand(B, 4))


@FIXTURES
@given(seed=seeds, B=st.integers(1, 5), N=st.integers(0, 20))
def test_transform_points_matches_R_x_plus_t(seed, B, N, device, dtype, tol):
    g = _gen(seed)
    T = random_transform(B, generator=g, dtype=torch.float64)
    x = torch.randn(B, N, 3, generator=g, dtype=torch.float64)
    expected = torch.einsum("bij,bnj->bni", T[:, :3, :3], x) + T[:, None, :3, 3]
    got = transform_points(T.to(device, dtype), x.to(device, dtype))
    assert got.dtype == dtype and got.shape == (B, N, 3)
    torch.testing.assert_close(got.cpu().double(), expected, atol=10 * tol, rtol=0)


@FIXTURES
@given(seed=seeds, B=st.integers(1, 5))
def test_inverse_and_compose(seed, B, device, dtype, tol):
    g = _gen(seed)
    A = random_transform(B, max_translation=2.0, generator=g, dtype=dtype).to(device)
    C = random_transform(B, max_translation=2.0, generator=g, dtype=dtype).to(device)
    eye = torch.eye(4, dtype=dtype, device=device).expand(B, 4, 4)
    torch.testing.assert_close(compose(A, inverse_transform(A)), eye, atol=10 * tol, rtol=0)
    torch.testing.assert_close(compose(inverse_transform(A), A), eye, atol=10 * tol, rtol=0)
    torch.testing.assert_close(inverse_transform(inverse_transform(A)), A, atol=10 * tol, rtol=0)
    # compose(A, C) applies C first, then A.
    x = torch.randn(B, 7, 3, generator=g, dtype=dtype).to(device)
    torch.testing.assert_close(
        transform_points(compose(A, C), x),
        transform_points(A, transform_points(C, x)),
        atol=20 * tol,
        rtol=0,
    )
    torch.testing.assert_close(compose(A, C, A), A @ C @ A)


def test_random_rotation_is_uniform_on_so3():
    R = random_rotation(20000, generator=_gen(0), dtype=torch.float64)
    eye = torch.eye(3, dtype=torch.float64).expand_as(R)
    torch.testing.assert_close(R @ R.transpose(1, 2), eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(20000, dtype=torch.float64))
    # Haar measure: E[R] = 0, and the angle has density (1 - cos a) / pi, mean pi/2 + 2/pi.
    assert R.mean(0).abs().max() < 0.02
    angle = rotation_angle_error(R, eye, degrees=False)
    assert abs(angle.mean().item() - (math.pi / 2 + 2 / math.pi)) < 0.02
    # Each image of a fixed axis is uniform on the sphere: its z coordinate is uniform in [-1, 1].
    z = R[:, 2, 2]
    hist = torch.histc(z, bins=10, min=-1, max=1) / len(z)
    assert (hist - 0.1).abs().max() < 0.015


def test_random_rotation_follows_generator_and_dtype():
    a = random_rotation(3, generator=_gen(5), dtype=torch.float64)
    b = random_rotation(3, generator=_gen(5), dtype=torch.float64)
    assert torch.equal(a, b)
    assert random_rotation(2, generator=_gen(5)).dtype == torch.float32


@given(seed=seeds, max_angle=st.floats(0.0, math.pi), max_translation=st.floats(0.0, 5.0))
def test_random_transform_respects_bounds(seed, max_angle, max_translation):
    T = random_transform(
        16,
        max_angle=max_angle,
        max_translation=max_translation,
        generator=_gen(seed),
        dtype=torch.float64,
    )
    eye = torch.eye(4, dtype=torch.float64).expand(16, 4, 4)
    assert (rotation_angle_error(T, eye, degrees=False) <= max_angle + 1e-9).all()
    assert (T[:, :3, 3].norm(dim=-1) <= max_translation + 1e-9).all()
    torch.testing.assert_close(torch.linalg.det(T[:, :3, :3]), torch.ones(16, dtype=torch.float64))


@FIXTURES
@given(seed=seeds, near=st.sampled_from(["any", "zero", "pi"]))
def test_rotation_angle_error_matches_scipy(seed, near, dtype):
    g = _gen(seed)
    R1 = random_rotation(8, generator=g, dtype=torch.float64)
    if near == "any":
        R2 = random_rotation(8, generator=g, dtype=torch.float64)
    else:
        angle = math.pi - 1e-4 if near == "pi" else 1e-4
        axis = torch.randn(8, 3, generator=g, dtype=torch.float64)
        rotvec = axis / axis.norm(dim=-1, keepdim=True) * angle
        delta = torch.from_numpy(Rotation.from_rotvec(rotvec.numpy()).as_matrix())
        R2 = R1 @ delta
    expected = Rotation.from_matrix((R1.transpose(1, 2) @ R2).numpy()).magnitude()
    got = rotation_angle_error(R1.to(dtype), R2.to(dtype), degrees=False)
    assert got.dtype == dtype
    atol = 1e-3 if dtype == torch.float32 else 1e-9
    np.testing.assert_allclose(got.double().numpy(), expected, atol=atol)
    np.testing.assert_allclose(
        rotation_angle_error(R1, R2).numpy(), np.degrees(expected), atol=1e-7
    )
    # Symmetric, and works on 4x4 transforms.
    torch.testing.assert_close(rotation_angle_error(R2, R1), rotation_angle_error(R1, R2))
    T1 = from_Rt(R1, torch.zeros(8, 3, dtype=torch.float64))
    T2 = from_Rt(R2, torch.ones(8, 3, dtype=torch.float64))
    torch.testing.assert_close(rotation_angle_error(T1, T2), rotation_angle_error(R1, R2))


def test_translation_error():
    t1 = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    t2 = torch.tensor([[3.0, 4.0, 0.0], [1.0, 1.0, 1.0]])
    assert translation_error(t1, t2).tolist() == [5.0, 0.0]
    T1 = from_Rt(torch.eye(3).expand(2, 3, 3), t1)
    T2 = from_Rt(torch.eye(3).expand(2, 3, 3), t2)
    assert translation_error(T1, T2).tolist() == [5.0, 0.0]


def test_bad_inputs_raise_poseflow_errors():
    with pytest.raises(ShapeError):
        from_Rt(torch.eye(3)[None], torch.zeros(2, 3))
    with pytest.raises(ShapeError):
        from_Rt(torch.eye(3)[None], torch.zeros(1, 4))
    with pytest.raises(ShapeError):
        from_Rt(torch.eye(3)[None], torch.zeros(1, 3, dtype=torch.float64))
    with pytest.raises(ShapeError):
        transform_points(torch.eye(4)[None], torch.zeros(1, 5, 2))
    with pytest.raises(ShapeError):
        inverse_transform(torch.eye(3)[None])
    with pytest.raises(ValueRangeError):
        compose()
    with pytest.raises(ShapeError):
        rotation_angle_error(torch.eye(3)[None], torch.eye(3, dtype=torch.float64)[None])
    with pytest.raises(ShapeError):
        translation_error(torch.eye(4)[None], torch.zeros(1, 3))
    with pytest.raises(PoseflowError):
        to_Rt(torch.zeros(2, 3))
