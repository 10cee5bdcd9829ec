"""CPU ICP: the compiled Procrustes solve and the early-exit loop, against torch's tensor ops."""

from __future__ import annotations

import importlib

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from poseflow.geometry.neighbors import nearest_neighbors
from poseflow.geometry.se3 import random_transform, transform_points
from poseflow.registration import icp, multi_scale_icp, procrustes
from poseflow.registration._icp_cpu import rigid_from_moments
from poseflow.registration.procrustes import is_well_posed, procrustes_moments, rigid_from_svd

FIXTURES = settings(
    suppress_health_check=[*settings().suppress_health_check, HealthCheck.function_scoped_fixture],
    max_examples=10,
)
seeds = st.integers(0, 2**31 - 1)
KINDS = ("general", "reflected", "planar", "collinear", "coincident", "few", "tiny")
WELL_POSED = ("general", "reflected", "planar")


def _pairs(kind, g, N, offset):
    """Corresponding points ``(N, 3)`` and 0/1 weights ``(N,)`` of one kind, float64."""
    f64 = {"generator": g, "dtype": torch.float64}
    src = torch.randn(N, 3, **f64)
    w = torch.ones(N, dtype=torch.float64)
    if kind == "planar":
        src[:, 2] = 0
    elif kind == "collinear":
        src = torch.randn(N, 1, **f64) * torch.randn(1, 3, **f64)
    elif kind == "coincident":  # dyadic and 2^k of them: their centroid is exact, at any offset
        src = torch.tensor([[0.5, -1.25, 2.0]], dtype=torch.float64).expand(N, 3)
        w[1 << (N.bit_length() - 1) :] = 0
    elif kind == "few":
        w[torch.randperm(N, generator=g)[: N - int(torch.randint(0, 3, (1,), generator=g))]] = 0
    T = random_transform(1, max_translation=2.0, generator=g, dtype=torch.float64)[0]
    dst = transform_points(T[None], src[None])[0] + 0.05 * torch.randn(N, 3, **f64)
    if kind == "reflected":  # the least-squares orthogonal map is a reflection: det < 0
        dst = dst * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)
    if kind == "tiny":  # an extent of a few float32 resolutions at 1e3
        src, dst = src * 1e-4, dst * 1e-4
    return src + offset, dst + offset, w


def _solve_both_ways(kinds, g, N, offset, dtype):
    """The compiled solve and torch's (SVD, :func:`is_well_posed`, :func:`rigid_from_svd`) on
    pairs of the given kinds, checked to agree; the compiled ``(T, ok)``."""
    pairs = (_pairs(kind, g, N, offset) for kind in kinds)
    src, dst, w = (torch.stack(x).to(dtype) for x in zip(*pairs))
    mu_s, mu_d, cov, _, _ = procrustes_moments(src, dst, w)
    current = random_transform(len(kinds), max_translation=1.0, generator=g, dtype=torch.float64)

    U, S, Vh = torch.linalg.svd(cov)
    ok = is_well_posed(w, mu_s, mu_d, S)
    expected = rigid_from_svd(mu_s, mu_d, U, S, Vh, ok, dtype=torch.float64)
    expected = torch.where(ok[:, None, None], expected, current)

    stats = torch.stack((w.sum(-1).double(), torch.zeros(len(kinds), dtype=torch.float64)), -1)
    T = current.numpy().copy()
    out = np.empty(len(kinds), dtype=bool)
    eps = torch.finfo(dtype).eps
    rigid_from_moments(
        torch.stack((mu_s, mu_d), 1).numpy(), cov.numpy(), stats.numpy(), eps, T, out
    )
    assert out.tolist() == ok.tolist()
    torch.testing.assert_close(torch.from_numpy(T), expected, atol=1e-9, rtol=0)
    assert (torch.linalg.det(torch.from_numpy(T[out, :3, :3])) > 0).all()  # never a reflection
    return T, out


@FIXTURES
@given(
    seed=seeds,
    kinds=st.lists(st.sampled_from(KINDS), min_size=1, max_size=6),
    N=st.integers(4, 40),
    offset=st.sampled_from([0.0, 1.0, 1e3]),
)
def test_compiled_solve_equals_torch(seed, kinds, N, offset, dtype):
    g = torch.Generator().manual_seed(seed)
    _, ok = _solve_both_ways(kinds, g, N, offset, dtype)
    for kind, solved in zip(kinds, ok):
        assert (kind in WELL_POSED and N >= 10) <= solved <= (kind in (*WELL_POSED, "tiny"))


@pytest.mark.parametrize("offset", [0.0, 1e3])
def test_compiled_solve_rejects_degenerate_pairs(offset, dtype):
    # Collinear (up to the points' rounding), coincident, fewer than 3 pairs; a cloud of extent
    # 1e-4 is a point in float32 at 1e3 (a few units in the last place) but not in float64.
    g = torch.Generator().manual_seed(0)
    _, ok = _solve_both_ways(KINDS, g, 16, offset, dtype)
    tiny = dtype == torch.float64 or offset == 0
    assert ok.tolist() == [True, True, True, False, False, False, tiny]


def test_compiled_solve_keeps_the_transform_where_moments_are_not_finite():
    mu = np.zeros((2, 2, 3))
    cov = np.stack((np.diag([3.0, 2.0, 1.0]), np.diag([np.inf, 2.0, 1.0])))
    stats = np.array([[10.0, 0.0], [10.0, 0.0]])
    T = np.stack((np.eye(4), 2 * np.eye(4)))
    ok = np.empty(2, dtype=bool)
    rigid_from_moments(mu, cov, stats, float(np.finfo(np.float64).eps), T, ok)
    assert ok.tolist() == [True, False]
    assert np.array_equal(T[0], np.eye(4)) and np.array_equal(T[1], 2 * np.eye(4))


def _clouds(seed, dtype, B=4, N=300, M=900):
    """Targets ``(B, M, 3)``, noisy sources ``(B, N, 3)`` taken from them and their masks, and
    initial transforms near the truth. The first instance is noise-free and starts at the truth
    (it stops after one step), the last one starts out of reach."""
    g = torch.Generator().manual_seed(seed)
    f64 = {"generator": g, "dtype": torch.float64}
    target = torch.rand(B, M, 3, **f64) * torch.tensor([1.0, 0.6, 0.3], dtype=torch.float64)
    pick = torch.randint(0, M, (B, N), generator=g)
    source = target.gather(1, pick[..., None].expand(-1, -1, 3))
    source = source + 0.003 * torch.randn(B, N, 3, **f64)
    init = random_transform(
        B, max_translation=0.04, max_angle=0.15, generator=g, dtype=torch.float64
    )
    init[-1, :3, 3] += 10.0
    source_mask = torch.rand(B, N, generator=g) < 0.9
    target_mask = torch.rand(B, M, generator=g) < 0.95
    source[0], init[0], target_mask[0] = target[0, pick[0]], torch.eye(4), True
    return source.to(dtype), target.to(dtype), init.to(dtype), source_mask, target_mask


def _nearest_pairs(source, target, T, target_mask, source_mask, distance):
    """The brute-force nearest target point of every moved source point and the pairs in range,
    in float64 (as ICP moves and pairs points)."""
    source, target, T = source.double(), target.double(), T.double()
    moved = transform_points(T, source)
    dist, idx = nearest_neighbors(moved, target, reference_mask=target_mask)
    matched = target.gather(1, idx.expand(-1, -1, 3))
    return matched, (dist[..., 0] <= distance) & source_mask, dist[..., 0]


@FIXTURES
@given(seed=seeds)
def test_every_step_is_procrustes_on_the_nearest_pairs(seed, dtype, tol):
    # Against torch's Procrustes on brute-force pairs: runs capped at k = 1, 2, ... iterations
    # retrace the first k steps of a longer run.
    source, target, init, source_mask, target_mask = _clouds(seed, dtype)
    distance = 0.05
    kw = {
        "source_mask": source_mask,
        "target_mask": target_mask,
        "relative_fitness": 0.01,
        "relative_rmse": 1e-4,
    }
    before, iterations = init, torch.zeros(len(init), dtype=torch.int64)
    for k in range(1, 9):
        run = icp(
            source, target, init, max_correspondence_distance=distance, max_iterations=k, **kw
        )
        matched, inliers, dist = _nearest_pairs(
            source, target, before, target_mask, source_mask, distance
        )
        stepped = run.num_iterations == k
        assert bool((stepped | (run.num_iterations == iterations)).all())
        expected = procrustes(source.double(), matched, mask=inliers).transformation
        expected = torch.where(stepped[:, None, None], expected, before.double())
        good = run.valid
        assert run.transformation.dtype == dtype
        torch.testing.assert_close(
            run.transformation[good].double(), expected[good], atol=tol, rtol=0
        )
        # The record is measured at the final transforms.
        _, inliers, dist = _nearest_pairs(
            source, target, run.transformation, target_mask, source_mask, distance
        )
        assert torch.equal(run.inliers[good], inliers[good])
        count = inliers.sum(-1)
        torch.testing.assert_close(
            run.fitness,
            torch.where(good, count.to(dtype) / source_mask.sum(-1).to(dtype), 0).to(dtype),
        )
        rmse = (torch.where(inliers, dist, 0).square().sum(-1) / count.clamp_min(1)).sqrt()
        torch.testing.assert_close(
            run.inlier_rmse, torch.where(good, rmse, 0).to(dtype), atol=tol, rtol=0
        )
        before, iterations = run.transformation, run.num_iterations
    assert run.valid.tolist() == [True, True, True, False]
    assert int(iterations[0]) == 1 and int(iterations[1:3].max()) >= 3


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("seed", range(4))
def test_multi_scale_equals_the_fixed_masked_steps(seed, dtype, monkeypatch):
    # The loop whose batch shrinks against the fixed masked steps of tensor ops (the CUDA path),
    # here on the CPU: the same iterations, early exits and results.
    module = importlib.import_module("poseflow.registration.icp")
    source, target, init, source_mask, target_mask = _clouds(seed, dtype, B=6)
    kw = {
        "max_correspondence_distances": (0.1, 0.05, 0.02),
        "max_iterations": 20,
        "source_mask": source_mask,
        "target_mask": target_mask,
    }
    ours = multi_scale_icp(source, target, init, **kw)
    monkeypatch.setattr(
        module, "_scale", lambda p, T, s: module.run_scale_fixed(p, T, s, capture=False)
    )
    fixed = multi_scale_icp(source, target, init, **kw)
    assert torch.equal(ours.num_iterations, fixed.num_iterations)
    assert torch.equal(ours.valid, fixed.valid) and torch.equal(ours.inliers, fixed.inliers)
    assert ours.transformation.dtype == ours.fitness.dtype == ours.inlier_rmse.dtype == dtype
    atol = 1e-6 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(ours.transformation, fixed.transformation, atol=atol, rtol=0)
    torch.testing.assert_close(ours.fitness, fixed.fitness, atol=0, rtol=0)
    torch.testing.assert_close(ours.inlier_rmse, fixed.inlier_rmse, atol=atol, rtol=0)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_runs_in_its_dtype(dtype):
    g = torch.Generator().manual_seed(0)
    cloud = torch.rand(2, 400, 3, generator=g)
    result = icp(cloud.to(dtype), (cloud + 0.02).to(dtype), max_correspondence_distance=0.1)
    assert result.valid.all() and result.transformation.dtype == result.fitness.dtype == dtype
    torch.testing.assert_close(
        result.transformation[:, :3, 3].float(), torch.full((2, 3), 0.02), atol=2e-3, rtol=0
    )
