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
    axis_angle_to_rotation,
    compose,
    from_Rt,
    inverse_transform,
    quaternion_to_rotation,
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


#: Largest entry-wise difference allowed between kornia's conversions and the formulas they replace.
CONVERSION_TOL = {torch.float32: 2e-6, torch.float64: 1e-12}


def _rodrigues(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """``I + sin(a) K + (1 - cos(a)) K^2`` for unit axes ``(B, 3)`` and angles ``(B,)``."""
    K = torch.zeros(*axis.shape, 3, dtype=axis.dtype)
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    K = K - K.transpose(1, 2)
    s, c = torch.sin(angle)[:, None, None], torch.cos(angle)[:, None, None]
    return torch.eye(3, dtype=axis.dtype) + s * K + (1 - c) * (K @ K)


def _quaternion_formula(q: torch.Tensor) -> torch.Tensor:
    """The rotation of unit quaternions ``(w, x, y, z)`` ``(B, 4)``, written out entry by entry."""
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        (
            1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
            2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
            2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
        ),
        -1,
    ).reshape(-1, 3, 3)  # fmt: skip


def _unit_axes(g: torch.Generator, B: int) -> torch.Tensor:
    return torch.nn.functional.normalize(
        torch.randn(B, 3, generator=g, dtype=torch.float64), dim=-1
    )


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


@FIXTURES
@given(
    seed=seeds,
    B=st.integers(1, 8),
    max_angle=st.sampled_from([1e-7, 1e-3, 0.1, 1.0, math.pi, 3 * math.pi]),
)
def test_axis_angle_to_rotation_matches_rodrigues(seed, B, max_angle, device, dtype):
    g = _gen(seed)
    axis = _unit_axes(g, B)
    angle = (2 * torch.rand(B, generator=g, dtype=torch.float64) - 1) * max_angle
    expected = _rodrigues(axis, angle)
    got = axis_angle_to_rotation((angle[:, None] * axis).to(device, dtype))
    assert got.dtype == dtype and got.device.type == device.type and got.shape == (B, 3, 3)
    assert (got.cpu().double() - expected).abs().max() <= CONVERSION_TOL[dtype]
    # A numpy array is converted in float64 and comes back as one.
    got_np = axis_angle_to_rotation((angle[:, None] * axis).numpy())
    assert isinstance(got_np, np.ndarray) and got_np.dtype == np.float64
    assert np.abs(got_np - expected.numpy()).max() <= CONVERSION_TOL[torch.float64]


@FIXTURES
@given(seed=seeds, B=st.integers(1, 8), scale=st.sampled_from([1e-3, 1.0, 1e3]))
def test_quaternion_to_rotation_matches_formula_and_scipy(seed, B, scale, device, dtype):
    g = _gen(seed)
    q = torch.randn(B, 4, generator=g, dtype=torch.float64)
    unit = q / q.norm(dim=-1, keepdim=True)
    expected = _quaternion_formula(unit)
    got = quaternion_to_rotation((scale * q).to(device, dtype))  # any norm: normalised first
    assert got.dtype == dtype and got.device.type == device.type and got.shape == (B, 3, 3)
    assert (got.cpu().double() - expected).abs().max() <= CONVERSION_TOL[dtype]
    assert torch.equal(quaternion_to_rotation(-q), quaternion_to_rotation(q))
    # (w, x, y, z), real part first: scipy takes (x, y, z, w).
    scipy = Rotation.from_quat(unit[:, [1, 2, 3, 0]].numpy()).as_matrix()
    assert np.abs(quaternion_to_rotation(q.numpy()) - scipy).max() <= 1e-12


@given(seed=seeds, B=st.integers(1, 8))
def test_quaternion_and_axis_angle_agree(seed, B):
    g = _gen(seed)
    axis = _unit_axes(g, B)
    angle = torch.rand(B, generator=g, dtype=torch.float64) * 2 * math.pi
    half = angle[:, None] / 2
    q = torch.cat((torch.cos(half), torch.sin(half) * axis), -1)
    torch.testing.assert_close(
        quaternion_to_rotation(q), axis_angle_to_rotation(angle[:, None] * axis), atol=1e-12, rtol=0
    )
    # Right-hand rule: a quarter turn about +z takes +x to +y.
    R = axis_angle_to_rotation(torch.tensor([0.0, 0.0, math.pi / 2], dtype=torch.float64))
    torch.testing.assert_close(
        R @ torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64),
        torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64),
    )


def test_rotation_conversions_are_differentiable():
    g = _gen(3)
    v = torch.randn(4, 3, generator=g, dtype=torch.float64, requires_grad=True)
    q = torch.randn(4, 4, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(axis_angle_to_rotation, (v,))
    assert torch.autograd.gradcheck(quaternion_to_rotation, (q,))


def test_rotation_conversions_reject_bad_shapes():
    with pytest.raises(ShapeError):
        axis_angle_to_rotation(torch.zeros(2, 4))
    with pytest.raises(ShapeError):
        axis_angle_to_rotation(np.zeros(2))
    with pytest.raises(ShapeError):
        quaternion_to_rotation(torch.zeros(3))
    with pytest.raises(ShapeError):
        quaternion_to_rotation(torch.zeros(2, 4, dtype=torch.int64))


@given(seed=seeds, B=st.integers(1, 8))
def test_random_rotation_is_the_quaternion_formula_of_its_draws(seed, B):
    q = torch.randn(B, 4, generator=_gen(seed), dtype=torch.float64)
    expected = _quaternion_formula(q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12))
    assert torch.equal(random_rotation(B, generator=_gen(seed), dtype=torch.float64), expected)


@given(seed=seeds, B=st.integers(1, 8), max_angle=st.floats(0.0, math.pi))
def test_random_transform_rotation_is_rodrigues_of_its_draws(seed, B, max_angle):
    g = _gen(seed)
    axis = torch.randn(B, 3, generator=g, dtype=torch.float64)
    axis = axis / axis.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    angle = torch.rand(B, generator=g, dtype=torch.float64) * max_angle
    T = random_transform(B, max_angle=max_angle, generator=_gen(seed), dtype=torch.float64)
    assert (T[:, :3, :3] - _rodrigues(axis, angle)).abs().max() <= CONVERSION_TOL[torch.float64]


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
