"""ICP: basin of convergence on half-cropped clouds, coarse-to-fine, Open3D agreement, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from poseflow.errors import ShapeError, ValueRangeError
from poseflow.geometry.se3 import (
    compose,
    from_Rt,
    inverse_transform,
    random_transform,
    rotation_angle_error,
    transform_points,
    translation_error,
)
from poseflow.registration import ICP, MultiScaleICP, icp, multi_scale_icp

FIXTURES = settings(
    suppress_health_check=[*settings().suppress_health_check, HealthCheck.function_scoped_fixture],
    max_examples=6,
)
seeds = st.integers(0, 2**31 - 1)


def _bumpy_clouds(seed, B, M=2000):
    """Model clouds of bumpy, elongated, asymmetric surfaces and half-cropped observations.

    Returns the models ``(B, M, 3)``, the observations (all model points moved by the true
    poses) with the mask of the half facing a random view, the poses and the models' extents.
    """
    g = torch.Generator().manual_seed(seed)
    kw = {"generator": g, "dtype": torch.float64}
    w = torch.randn(B, 6, 3, **kw)
    w = w / w.norm(dim=-1, keepdim=True) * (2 + 3 * torch.rand(B, 6, 1, **kw))
    a = 0.1 + 0.15 * torch.rand(B, 1, 6, **kw)
    phi = 2 * math.pi * torch.rand(B, 1, 6, **kw)
    u = torch.randn(B, M, 3, **kw)
    u = u / u.norm(dim=-1, keepdim=True)
    r = 1 + (a * torch.sin(u @ w.transpose(1, 2) + phi)).sum(-1, keepdim=True)
    model = 0.1 * u * torch.tensor([1.0, 0.7, 0.5], dtype=torch.float64) * r  # metres
    view = torch.randn(B, 1, 3, **kw)
    half = (model * view).sum(-1) > 0
    pose = random_transform(B, max_translation=1.0, **kw)
    extent = (model.amax(1) - model.amin(1)).norm(dim=-1)
    return model, transform_points(pose, model), half, pose, extent, g


def _perturbed(truth, extent, angle_deg, translation, g):
    """``truth`` composed with rotations of exactly ``angle_deg`` about random axes (through the
    object's origin) and translations of ``translation * extent``."""
    B = truth.shape[0]
    axis = torch.randn(B, 3, generator=g, dtype=torch.float64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    K = torch.zeros(B, 3, 3, dtype=torch.float64)
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    K = K - K.transpose(1, 2)
    theta = math.radians(angle_deg)
    R = torch.eye(3, dtype=torch.float64) + math.sin(theta) * K + (1 - math.cos(theta)) * K @ K
    d = torch.randn(B, 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=-1, keepdim=True) * translation * extent[:, None]
    return compose(from_Rt(R, d), truth)


def _converged(T, pose, extent):
    """Exact recovery: the source is a subset of the target's points."""
    T = T.double().cpu()
    rot = rotation_angle_error(T, inverse_transform(pose))
    trans = translation_error(inverse_transform(T), pose) / extent
    return (rot < 0.05) & (trans < 1e-3)


@FIXTURES
@given(seed=seeds, angle=st.floats(0.0, 15.0), translation=st.floats(0.0, 0.1))
def test_converges_from_15_degrees_and_10_percent_on_half_clouds(
    seed, angle, translation, device, dtype
):
    model, obs, half, pose, extent, g = _bumpy_clouds(seed, 4)
    init = _perturbed(inverse_transform(pose), extent, angle, translation, g)
    result = icp(
        obs.to(device, dtype),
        model.to(device, dtype),
        init.to(device, dtype),
        max_correspondence_distance=0.2 * extent.mean().item(),
        max_iterations=100,
        source_mask=half.to(device),
    )
    assert result.transformation.dtype == dtype and result.valid.all()
    assert _converged(result.transformation, pose, extent).all()
    assert (result.fitness > 0.99).all() and not (result.inliers.cpu() & ~half).any()


@pytest.mark.slow
def test_coarse_to_fine_widens_the_basin():
    model, obs, half, pose, extent, g = _bumpy_clouds(7, 16)
    init = _perturbed(inverse_transform(pose), extent, 40.0, 0.25, g)
    size = extent.mean().item()
    kw = {"source_mask": half, "max_iterations": 100}
    fine = icp(obs, model, init, max_correspondence_distance=0.05 * size, **kw)
    coarse = icp(obs, model, init, max_correspondence_distance=0.2 * size, **kw)
    multi = multi_scale_icp(
        obs, model, init, max_correspondence_distances=[0.5 * size, 0.2 * size, 0.05 * size], **kw
    )
    counts = [int(_converged(r.transformation, pose, extent).sum()) for r in (fine, coarse, multi)]
    assert counts[2] >= counts[1] and counts[2] >= counts[0] + 6, counts
    assert (multi.num_iterations >= fine.num_iterations.clamp_max(1)).all()


@pytest.mark.parametrize("M", [40, 1500])  # brute-force and KD-tree searches
def test_matches_open3d_registration_icp(M):
    o3d = pytest.importorskip("open3d")
    reg = o3d.pipelines.registration
    model, obs, half, pose, extent, g = _bumpy_clouds(3, 3, M)
    obs = obs + 0.001 * torch.randn(obs.shape, generator=g, dtype=torch.float64)
    init = _perturbed(inverse_transform(pose), extent, 8.0, 0.05, g)
    distance = 0.05 * extent.mean().item()
    ours = icp(obs, model, init, max_correspondence_distance=distance, source_mask=half)
    for b in range(3):
        src, tgt = o3d.geometry.PointCloud(), o3d.geometry.PointCloud()
        src.points = o3d.utility.Vector3dVector(obs[b][half[b]].numpy())
        tgt.points = o3d.utility.Vector3dVector(model[b].numpy())
        theirs = reg.registration_icp(src, tgt, distance, init[b].numpy(),
                                      reg.TransformationEstimationPointToPoint(),
                                      reg.ICPConvergenceCriteria(1e-6, 1e-6, 30))  # fmt: skip
        np.testing.assert_allclose(ours.transformation[b].numpy(), theirs.transformation, atol=1e-6)
        assert ours.fitness[b].item() == pytest.approx(theirs.fitness, abs=1e-3)
        assert ours.inlier_rmse[b].item() == pytest.approx(theirs.inlier_rmse, rel=1e-3, abs=1e-7)


@FIXTURES
@given(seed=seeds)
def test_batched_equals_per_instance(seed, dtype):
    model, obs, half, pose, extent, g = _bumpy_clouds(seed, 3, 600)
    init = _perturbed(inverse_transform(pose), extent, 10.0, 0.05, g).to(dtype)
    model, obs = model.to(dtype), obs.to(dtype)
    target_mask = torch.rand(3, 600, generator=g) < 0.9
    kw = {"max_correspondence_distances": [0.3, 0.1, 0.03], "max_iterations": [10, 20, 30]}
    batched = multi_scale_icp(obs, model, init, source_mask=half, target_mask=target_mask, **kw)
    for b in range(3):
        one = multi_scale_icp(
            obs[b : b + 1],
            model[b : b + 1],
            init[b : b + 1],
            source_mask=half[b : b + 1],
            target_mask=target_mask[b : b + 1],
            **kw,
        )
        torch.testing.assert_close(one.transformation[0], batched.transformation[b])
        assert one.num_iterations[0] == batched.num_iterations[b]
        assert torch.equal(one.inliers[0], batched.inliers[b])


def test_masked_points_may_hold_nan_and_identity_init():
    model, obs, half, pose, _, _ = _bumpy_clouds(1, 2, 500)
    obs = torch.where(half[..., None], obs, torch.nan)
    target = model.clone()
    target_mask = torch.ones(2, 500, dtype=torch.bool)
    target[:, :10], target_mask[:, :10] = torch.inf, False
    init = inverse_transform(pose)
    result = ICP(max_correspondence_distance=0.02)(
        obs, target, init, source_mask=half, target_mask=target_mask
    )
    assert result.valid.all() and torch.isfinite(result.transformation).all()
    torch.testing.assert_close(result.fitness, result.inliers.sum(-1) / half.sum(-1).double())
    # Without init, the identity is the start: here far from the target, so nothing matches.
    far = icp(obs, target, source_mask=half, target_mask=target_mask,
              max_correspondence_distance=0.01)  # fmt: skip
    assert not far.valid.any()


def test_hopeless_instances_get_identity():
    line = torch.linspace(0, 1, 50, dtype=torch.float64)[None, :, None] * torch.tensor(
        [1.0, 0.5, 0.2], dtype=torch.float64
    )
    g = torch.Generator().manual_seed(0)
    good = torch.randn(1, 50, 3, generator=g, dtype=torch.float64)
    source = torch.cat((good, line, good + 100.0))  # ok, collinear, nothing in range
    target = torch.cat((good + 0.01, line + 0.01, good))
    result = icp(source, target, max_correspondence_distance=0.1)
    assert result.valid.tolist() == [True, False, False]
    eye = torch.eye(4, dtype=torch.float64)
    for b in (1, 2):
        assert torch.equal(result.transformation[b], eye)
        assert result.fitness[b] == 0 and result.inlier_rmse[b] == 0 and not result.inliers[b].any()
    torch.testing.assert_close(
        result.transformation[0, :3, 3], torch.full((3,), 0.01, dtype=torch.float64)
    )


def test_an_empty_target_gives_invalid_instances_not_an_error():
    """No target point at all (M = 0) is reported like a target mask that is all False."""
    g = torch.Generator().manual_seed(0)
    source = torch.rand(2, 50, 3, generator=g, dtype=torch.float64)
    for target, target_mask in (
        (torch.zeros(2, 0, 3, dtype=torch.float64), None),
        (source + 0.01, torch.zeros(2, 50, dtype=torch.bool)),
    ):
        for run in (
            lambda t, m: icp(source, t, max_correspondence_distance=0.1, target_mask=m),
            lambda t, m: multi_scale_icp(
                source, t, max_correspondence_distances=[0.2, 0.1], target_mask=m
            ),
        ):
            result = run(target, target_mask)
            assert result.valid.tolist() == [False, False]
            assert torch.equal(
                result.transformation, torch.eye(4, dtype=torch.float64).expand(2, 4, 4)
            )
            assert result.fitness.eq(0).all() and not result.inliers.any()
    # one instance empty, the other solved as it would be alone
    mask = torch.tensor([[True] * 50, [False] * 50])
    both = icp(source, source + 0.01, max_correspondence_distance=0.1, target_mask=mask)
    alone = icp(source[:1], source[:1] + 0.01, max_correspondence_distance=0.1)
    assert both.valid.tolist() == [True, False]
    torch.testing.assert_close(both.transformation[:1], alone.transformation)


@FIXTURES
@given(seed=seeds, offset=st.floats(1.0, 1e4))
def test_far_from_the_origin_in_float32(seed, offset, device):
    """Float32 clouds kilometres away converge as near the origin (the degeneracy test judges
    the clouds' extent, not their distance from the origin)."""
    model, obs, half, pose, extent, g = _bumpy_clouds(seed, 1, 500)
    init = _perturbed(inverse_transform(pose), extent, 3.0, 0.01, g)
    shift = torch.eye(4, dtype=torch.float64)
    shift[:3, 3] = (
        torch.nn.functional.normalize(torch.randn(3, generator=g, dtype=torch.float64), dim=0)
        * offset
    )
    far_obs = transform_points(shift, obs)
    far_model = transform_points(shift, model)
    far_init = compose(shift, compose(init, inverse_transform(shift)))
    kw = {"max_correspondence_distance": 0.1 * float(extent.max())}
    near = icp(obs.float(), model.float(), init.float(), source_mask=half, **kw)
    far = icp(
        far_obs.float().to(device),
        far_model.float().to(device),
        far_init.float().to(device),
        source_mask=half.to(device),
        **kw,
    )
    assert near.valid.item() and far.valid.item()
    truth = compose(shift, compose(inverse_transform(pose), inverse_transform(shift)))
    rot = rotation_angle_error(far.transformation.cpu().double(), truth)
    assert rot.item() < 1.0  # degrees
    resolution = torch.finfo(torch.float32).eps * offset
    moved = transform_points(far.transformation.cpu().double(), far_obs)
    err = (moved - transform_points(truth, far_obs))[half].norm(dim=-1).median().item()
    assert err < 0.05 * float(extent.max()) + 50 * resolution


def test_solver_classes_and_stopping():
    model, obs, half, pose, extent, g = _bumpy_clouds(2, 2, 400)
    init = _perturbed(inverse_transform(pose), extent, 5.0, 0.02, g)
    solver = ICP(max_correspondence_distance=0.05, max_iterations=3)
    capped = solver(obs, model, init, source_mask=half)
    assert (capped.num_iterations == 3).all() and "max_iterations=3" in repr(solver)
    full = icp(obs, model, init, max_correspondence_distance=0.05, source_mask=half)
    assert (full.num_iterations < 30).all()  # converged before the cap
    multi = MultiScaleICP(max_correspondence_distances=[0.05])(obs, model, init, source_mask=half)
    assert torch.equal(multi.transformation, full.transformation)


def test_bad_inputs():
    x = torch.rand(2, 10, 3)
    with pytest.raises(ShapeError):
        icp(x, torch.rand(3, 10, 3), max_correspondence_distance=0.1)
    with pytest.raises(ShapeError):
        icp(x, x.double(), max_correspondence_distance=0.1)
    with pytest.raises(ShapeError):
        icp(x, x, torch.eye(4).expand(3, 4, 4), max_correspondence_distance=0.1)
    with pytest.raises(ShapeError):
        icp(x, x, source_mask=torch.ones(2, 9, dtype=torch.bool), max_correspondence_distance=0.1)
    with pytest.raises(ShapeError):
        icp(x, x, target_mask=torch.ones(2, 10), max_correspondence_distance=0.1)
    with pytest.raises(ValueRangeError):
        icp(x.clone().fill_(float("nan")), x, max_correspondence_distance=0.1)
    with pytest.raises(ValueRangeError):
        icp(x, x, torch.full((2, 4, 4), float("nan")), max_correspondence_distance=0.1)
    for bad in ({"max_correspondence_distance": -1.0},
                {"max_correspondence_distance": 0.1, "max_iterations": 0},
                {"max_correspondence_distance": 0.1, "relative_rmse": -1.0}):  # fmt: skip
        with pytest.raises(ValueRangeError):
            icp(x, x, **bad)
    for bad in ({"max_correspondence_distances": []},
                {"max_correspondence_distances": [0.1, 0.2]},
                {"max_correspondence_distances": [0.2, 0.1], "max_iterations": [5]}):  # fmt: skip
        with pytest.raises(ValueRangeError):
            multi_scale_icp(x, x, **bad)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fixed_masked_steps_equal_the_early_exit_loop(device, dtype):
    # The CUDA path (fixed masked steps, graph-captured there) against the CPU loop whose batch
    # shrinks as instances stop; one hopeless instance (no pairs) and one masked half included.
    from poseflow.registration._icp_loop import ICPProblem, Scale, run_scale, run_scale_fixed

    model, obs, half, pose, extent, g = _bumpy_clouds(3, 4, M=400)
    init = _perturbed(inverse_transform(pose), extent, 8.0, 0.05, g)
    init[3, :3, 3] += 10.0  # nothing within reach
    src, tgt = obs.to(dtype), model.to(dtype)
    mask = half.clone()
    cpu = ICPProblem.make(src, tgt, init.to(dtype), mask, None)
    scale = Scale(0.03, 30, 1e-6, 1e-6)
    ref = run_scale(cpu, cpu.init, scale)
    on = ICPProblem.make(
        src.to(device), tgt.to(device), init.to(device, dtype), mask.to(device), None
    )
    out = run_scale_fixed(on, on.init, scale, capture=device.type == "cuda")
    tol = 1e-4 if dtype == torch.float32 else 1e-9
    assert torch.equal(out.valid.cpu(), ref.valid) and not bool(ref.valid[3])
    assert torch.equal(out.iterations.cpu(), ref.iterations)
    assert torch.allclose(out.T.cpu(), ref.T, atol=tol)
    assert torch.allclose(out.fitness.cpu(), ref.fitness, atol=tol)
    assert int(ref.iterations[:3].min()) >= 2  # the steps did something
