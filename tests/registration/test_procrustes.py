"""Weighted Procrustes: exact recovery, equivariance, reflections, scaling, degeneracy, gradient."""

from __future__ import annotations

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from poseflow.errors import ShapeError, ValueRangeError
from poseflow.geometry.se3 import compose, inverse_transform, random_transform, transform_points
from poseflow.registration import Procrustes, procrustes

FIXTURES = settings(
    suppress_health_check=[*settings().suppress_health_check, HealthCheck.function_scoped_fixture]
)
seeds = st.integers(0, 2**31 - 1)


def _problem(seed, B, N, dtype, device):
    g = torch.Generator().manual_seed(seed)
    T = random_transform(B, max_translation=3.0, generator=g, dtype=torch.float64)
    src = torch.randn(B, N, 3, generator=g, dtype=torch.float64) + torch.randn(
        B, 1, 3, generator=g, dtype=torch.float64
    )
    dst = transform_points(T, src)
    return src.to(device, dtype), dst.to(device, dtype), T.to(device, dtype), g


@FIXTURES
@given(seed=seeds, B=st.integers(1, 4), N=st.integers(3, 200), weighted=st.booleans())
def test_recovers_any_rigid_transform_exactly(seed, B, N, weighted, device, dtype, tol):
    src, dst, T, g = _problem(seed, B, N, dtype, device)
    weights = None
    if weighted:
        weights = torch.rand(B, N, generator=g, dtype=torch.float64).to(device, dtype) + 0.1
    est, valid = procrustes(src, dst, weights)
    assert valid.all()
    assert est.shape == (B, 4, 4) and est.dtype == dtype and est.device.type == device.type
    torch.testing.assert_close(est, T, atol=100 * tol, rtol=0)
    det = torch.linalg.det(est[:, :3, :3].double())
    torch.testing.assert_close(det, torch.ones_like(det), atol=1e-5, rtol=0)


@FIXTURES
@given(seed=seeds, N=st.integers(10, 100))
def test_zero_weights_and_masked_pairs_are_ignored(seed, N, device, dtype, tol):
    src, dst, T, g = _problem(seed, 2, N, dtype, device)
    bad = torch.rand(2, N, generator=g) < 0.3
    bad[:, :3] = False  # at least three good pairs
    bad = bad.to(device)
    corrupted = torch.where(bad[..., None], dst + 5.0, dst)
    weights = (~bad).to(dtype)
    torch.testing.assert_close(
        procrustes(src, corrupted, weights).transformation, T, atol=100 * tol, rtol=0
    )
    nan = torch.where(bad[..., None], torch.nan, corrupted)
    torch.testing.assert_close(
        procrustes(src, nan, mask=~bad).transformation, T, atol=100 * tol, rtol=0
    )


@FIXTURES
@given(seed=seeds, N=st.integers(3, 80))
def test_equivariant_to_rigid_changes_of_both_inputs(seed, N, device, dtype, tol):
    g = torch.Generator().manual_seed(seed)
    src = torch.randn(1, N, 3, generator=g, dtype=torch.float64)
    dst = torch.randn(1, N, 3, generator=g, dtype=torch.float64)  # no exact solution
    A = random_transform(1, max_translation=2.0, generator=g, dtype=torch.float64)
    C = random_transform(1, max_translation=2.0, generator=g, dtype=torch.float64)
    w = torch.rand(1, N, generator=g, dtype=torch.float64) + 0.1
    args = [x.to(device, dtype) for x in (src, dst, A, C, w)]
    src, dst, A, C, w = args
    base = procrustes(src, dst, w).transformation
    moved = procrustes(transform_points(A, src), transform_points(C, dst), w).transformation
    expected = compose(C, base, inverse_transform(A))
    atol = 1e-3 if dtype == torch.float32 else 1e-9
    torch.testing.assert_close(moved, expected, atol=atol, rtol=0)


def test_reflection_is_never_returned():
    g = torch.Generator().manual_seed(0)
    src = torch.randn(4, 50, 3, generator=g, dtype=torch.float64)
    mirrored = src * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)
    est = procrustes(src, mirrored).transformation
    det = torch.linalg.det(est[:, :3, :3])
    torch.testing.assert_close(det, torch.ones(4, dtype=torch.float64))


@FIXTURES
@given(seed=seeds, scale=st.floats(0.1, 10.0))
def test_with_scaling_recovers_similarity(seed, scale, dtype, tol):
    src, _, T, _ = _problem(seed, 3, 40, torch.float64, "cpu")
    dst = scale * (src @ T[:, :3, :3].transpose(1, 2)) + T[:, None, :3, 3]
    est = procrustes(src.to(dtype), dst.to(dtype), with_scaling=True).transformation
    expected = T.clone()
    expected[:, :3, :3] *= scale
    torch.testing.assert_close(est.double(), expected, atol=1000 * tol * scale, rtol=0)
    solver = Procrustes(with_scaling=True)
    assert torch.equal(solver(src.to(dtype), dst.to(dtype)).transformation, est)


def test_degenerate_instances_get_identity_never_nan():
    g = torch.Generator().manual_seed(0)
    good = torch.randn(1, 6, 3, generator=g, dtype=torch.float64)
    line = torch.linspace(0, 1, 6, dtype=torch.float64)[None, :, None] * torch.tensor(
        [1.0, 2.0, 3.0], dtype=torch.float64
    )
    point = torch.ones(1, 6, 3, dtype=torch.float64) * 0.3
    src = torch.cat((good, line, point, good))
    dst = src + 1.0
    weights = torch.ones(4, 6, dtype=torch.float64)
    weights[3, 2:] = 0  # only two weighted pairs left
    est, valid = procrustes(src, dst, weights)
    assert valid.tolist() == [True, False, False, False]
    assert torch.isfinite(est).all()
    eye = torch.eye(4, dtype=torch.float64)
    for b in (1, 2, 3):
        assert torch.equal(est[b], eye)
    torch.testing.assert_close(est[0, :3, 3], torch.ones(3, dtype=torch.float64))
    zero = procrustes(src, dst, torch.zeros(4, 6, dtype=torch.float64))
    assert torch.equal(zero.transformation, eye.expand(4, 4, 4)) and not zero.valid.any()


@FIXTURES
@given(
    seed=seeds,
    offset=st.floats(1.0, 1e4),
    extent=st.sampled_from([0.05, 0.2, 1.0]),
    angle=st.floats(0.0, 3.1),
)
def test_far_from_the_origin_is_solved_like_near_it(seed, offset, extent, angle, device, dtype):
    """A cloud kilometres away in float32 is judged by its extent, not its distance from the
    origin: solved and valid, with errors at the resolution of its coordinates; collinear and
    coincident ones there are still flagged."""
    g = torch.Generator().manual_seed(seed)
    local = torch.randn(1, 60, 3, generator=g, dtype=torch.float64) * extent
    direction = torch.nn.functional.normalize(
        torch.randn(3, generator=g, dtype=torch.float64), dim=0
    )
    where = direction * offset
    T = random_transform(1, max_angle=angle, max_translation=0.5, generator=g, dtype=torch.float64)
    T[0, :3, 3] += where - T[0, :3, :3] @ where  # rotate about the cloud, far from the origin
    src = (local + where).to(dtype)
    dst = transform_points(T, src.to(torch.float64)).to(dtype)
    est, valid = procrustes(src.to(device), dst.to(device))
    assert valid.item()
    resolution = torch.finfo(dtype).eps * offset  # one unit in the last place, about
    moved = transform_points(est.cpu().to(torch.float64), src.to(torch.float64))
    err = (moved - dst.to(torch.float64)).norm(dim=-1).max().item()
    assert err <= 50 * resolution + 1e-9
    line = where + torch.linspace(-1, 1, 60, dtype=torch.float64)[:, None] * direction * extent
    coincident = where.expand(60, 3)
    for bad in (line, coincident):
        bad = bad[None].to(dtype).to(device)
        assert not procrustes(bad, bad + 0.25).valid.item()


def test_result_record_unpacks_and_the_class_agrees():
    src = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]]).expand(2, 4, 3)
    result = procrustes(src, src + 1, mask=torch.tensor([[True] * 4, [True, True, False, False]]))
    T, valid = result
    assert valid.tolist() == [True, False] and T is result.transformation
    assert torch.equal(T[1], torch.eye(4))
    assert torch.equal(Procrustes()(src, src + 1).transformation, procrustes(src, src + 1)[0])


def test_gradcheck_float64():
    g = torch.Generator().manual_seed(0)
    src = torch.randn(2, 6, 3, generator=g, dtype=torch.float64, requires_grad=True)
    dst = torch.randn(2, 6, 3, generator=g, dtype=torch.float64, requires_grad=True)
    w = (torch.rand(2, 6, generator=g, dtype=torch.float64) + 0.5).requires_grad_()
    assert torch.autograd.gradcheck(
        lambda a, b, c: procrustes(a, b, c).transformation, (src, dst, w)
    )
    assert torch.autograd.gradcheck(
        lambda a, b, c: procrustes(a, b, c, with_scaling=True).transformation, (src, dst, w)
    )


def test_degenerate_instance_gets_zero_gradient_not_nan():
    g = torch.Generator().manual_seed(0)
    src = torch.randn(2, 5, 3, generator=g, dtype=torch.float64)
    src[1] = torch.linspace(0, 1, 5, dtype=torch.float64)[:, None]  # collinear (and symmetric)
    src.requires_grad_()
    dst = (src.detach() + 0.5).requires_grad_()
    procrustes(src, dst).transformation.sum().backward()
    assert torch.isfinite(src.grad).all() and torch.isfinite(dst.grad).all()
    assert (src.grad[1] == 0).all()


def test_bad_inputs():
    x = torch.rand(2, 5, 3)
    with pytest.raises(ShapeError):
        procrustes(x, torch.rand(2, 6, 3))
    with pytest.raises(ShapeError):
        procrustes(x, torch.rand(3, 5, 3))
    with pytest.raises(ShapeError):
        procrustes(x, x.double())
    with pytest.raises(ShapeError):
        procrustes(x, x, torch.ones(2, 4))
    with pytest.raises(ShapeError):
        procrustes(x, x, mask=torch.ones(2, 5))
    with pytest.raises(ShapeError):
        procrustes(x[..., :2], x[..., :2])
    with pytest.raises(ValueRangeError):
        procrustes(x, x, -torch.ones(2, 5))
    with pytest.raises(ValueRangeError):
        procrustes(x.clone().fill_(float("nan")), x)
    with pytest.raises(ValueRangeError):
        procrustes(x, x, torch.full((2, 5), float("inf")))
