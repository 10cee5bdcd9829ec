"""RANSAC-Procrustes: recovery under noise and outliers, batch independence, early stopping."""

from __future__ import annotations

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from poseflow.errors import ShapeError, ValueRangeError
from poseflow.geometry.se3 import random_transform, rotation_angle_error, transform_points
from poseflow.registration import RANSACProcrustes, RegistrationResult, ransac_procrustes

FIXTURES = settings(
    suppress_health_check=[*settings().suppress_health_check, HealthCheck.function_scoped_fixture],
    max_examples=10,
)
seeds = st.integers(0, 2**31 - 1)


def _pairs(seed, B, N, outliers, noise, extent=0.2):
    """Pairs on an anisotropic cloud of the given extent; ``outliers`` of them random."""
    g = torch.Generator().manual_seed(seed)
    src = (torch.rand(B, N, 3, generator=g, dtype=torch.float64) - 0.5) * torch.tensor(
        [1.0, 0.6, 0.3], dtype=torch.float64
    ) * extent + torch.tensor([0.0, 0.0, 0.8], dtype=torch.float64)
    T = random_transform(B, max_translation=0.5, generator=g, dtype=torch.float64)
    dst = transform_points(T, src) + noise * torch.randn(B, N, 3, generator=g, dtype=torch.float64)
    k = round(outliers * N)
    wrong = torch.zeros(B, N, dtype=torch.bool)
    wrong[torch.arange(B)[:, None], torch.rand(B, N, generator=g).argsort(-1)[:, :k]] = True
    junk = transform_points(T, src[:, torch.randperm(N, generator=g)])
    dst = torch.where(wrong[..., None], junk, dst)
    return src, dst, T, wrong, g


def _errors(est, T, src):
    """Rotation error (degrees) and the error at the cloud's centre (the pose's translation
    error in the cloud's frame)."""
    est = est.double().cpu()
    rot = rotation_angle_error(est, T)
    centre = src.double().cpu().mean(1, keepdim=True)
    trans = (transform_points(est, centre) - transform_points(T, centre)).norm(dim=-1)[:, 0]
    return rot, trans


@FIXTURES
@given(seed=seeds, outliers=st.floats(0.0, 0.6), noise=st.floats(0.0, 0.002))
def test_recovers_pose_with_noise_and_outliers(seed, outliers, noise, device, dtype):
    extent = 0.2
    src, dst, T, wrong, _ = _pairs(seed, 3, 300, outliers, noise, extent)
    g = torch.Generator(device=device).manual_seed(seed)
    result = ransac_procrustes(
        src.to(device, dtype),
        dst.to(device, dtype),
        max_correspondence_distance=max(4 * noise, 1e-3) * 3**0.5,
        generator=g,
    )
    assert isinstance(result, RegistrationResult) and len(result) == 3
    assert result.transformation.dtype == dtype and result.valid.all()
    rot, trans = _errors(result.transformation, T, src)
    assert (rot < 1.0).all(), rot
    assert (trans < 0.01 * extent).all(), trans
    # The true pairs are found, and fitness counts them among all (valid) pairs.
    inliers = result.inliers.cpu()
    assert (inliers & ~wrong).sum() >= 0.95 * (~wrong).sum()
    torch.testing.assert_close(result.fitness.cpu().double(), inliers.double().mean(-1))
    assert torch.isfinite(result.inlier_rmse).all()


@FIXTURES
@given(seed=seeds, confidence=st.sampled_from([0.99, 0.999, 1.0]))
def test_batched_equals_per_instance_under_same_seed(seed, confidence, device, dtype):
    src, dst, _, _, g = _pairs(seed, 4, 120, 0.5, 0.001)
    mask = torch.rand(4, 120, generator=g) < 0.85
    mask[1] = True
    kw = {"max_correspondence_distance": 0.005, "max_iterations": 300, "confidence": confidence}
    src, dst, mask = src.to(device, dtype), dst.to(device, dtype), mask.to(device)

    def gen():
        return torch.Generator(device=device).manual_seed(seed)

    batched = ransac_procrustes(src, dst, mask, generator=gen(), **kw)
    for b in range(4):
        single = ransac_procrustes(src[b : b + 1], dst[b : b + 1], mask[b : b + 1],
                                   generator=gen(), **kw)  # fmt: skip
        atol = 1e-4 if dtype == torch.float32 else 1e-10
        torch.testing.assert_close(single.transformation[0], batched.transformation[b], atol=atol,
                                   rtol=0)  # fmt: skip
        assert single.num_iterations[0] == batched.num_iterations[b]
        assert (single.inliers[0] != batched.inliers[b]).sum() <= 1  # a pair on the threshold


def test_early_stop_and_full_run():
    src, dst, *_ = _pairs(0, 2, 200, 0.0, 0.0005)
    kw = {"max_correspondence_distance": 0.005, "max_iterations": 500}
    early = ransac_procrustes(
        src, dst, confidence=0.999, generator=torch.Generator().manual_seed(0), **kw
    )
    full = ransac_procrustes(
        src, dst, confidence=1.0, generator=torch.Generator().manual_seed(0), **kw
    )
    assert (early.num_iterations <= 5).all()  # all pairs are inliers: one sample suffices
    assert (full.num_iterations == 500).all()
    torch.testing.assert_close(early.transformation, full.transformation)
    # 50% outliers: log(0.001) / log(1 - 0.5^3) = 51.7 hypotheses are needed.
    src, dst, *_ = _pairs(1, 1, 400, 0.5, 0.0005)
    mid = ransac_procrustes(src, dst, generator=torch.Generator().manual_seed(0), **kw)
    assert 40 <= mid.num_iterations.item() <= 60


def test_instances_that_reached_the_confidence_draw_no_more(monkeypatch):
    """An easy instance beside a hard one is not solved for the hard one's hypotheses."""
    import poseflow.registration.ransac as ransac

    solved = torch.zeros(2, dtype=torch.long)
    original = ransac._hypotheses

    def counting(src, dst, samples):
        if samples.shape[0] == 2:
            solved.add_(samples.shape[1])
        else:  # only the hard instance is still drawing
            solved[1] += samples.shape[1]
        return original(src, dst, samples)

    monkeypatch.setattr(ransac, "_hypotheses", counting)
    easy, easy_dst, *_ = _pairs(0, 1, 200, 0.0, 0.0005)
    hard, hard_dst, *_ = _pairs(1, 1, 200, 0.9, 0.0005)
    src, dst = torch.cat([easy, hard]), torch.cat([easy_dst, hard_dst])
    kw = {"max_correspondence_distance": 0.005, "max_iterations": 1000}
    batched = ransac_procrustes(src, dst, generator=torch.Generator().manual_seed(0), **kw)
    assert batched.num_iterations[1] == 1000
    assert solved[1] >= 1000  # every hypothesis of the hard instance, plus the final fit
    assert solved[0] <= 64 + 1  # the first chunk and the final fit
    alone = ransac_procrustes(easy, easy_dst, generator=torch.Generator().manual_seed(0), **kw)
    torch.testing.assert_close(alone.transformation[0], batched.transformation[0])


def test_masked_pairs_are_ignored_and_may_hold_nan():
    src, dst, T, _, g = _pairs(2, 2, 200, 0.3, 0.0005)
    mask = torch.rand(2, 200, generator=g) < 0.7
    dst = torch.where(mask[..., None], dst, torch.nan)
    result = ransac_procrustes(src, dst, mask, max_correspondence_distance=0.004,
                               generator=torch.Generator().manual_seed(0))  # fmt: skip
    rot, _ = _errors(result.transformation, T, src)
    assert (rot < 1).all() and not (result.inliers & ~mask).any()
    torch.testing.assert_close(result.fitness, result.inliers.sum(-1) / mask.sum(-1).double())


def test_hopeless_instances_are_flagged_with_identity():
    g = torch.Generator().manual_seed(0)
    good_src, good_dst, *_ = _pairs(3, 1, 50, 0.0, 0.0)
    line = torch.linspace(0, 1, 50, dtype=torch.float64)[None, :, None] * torch.tensor(
        [1.0, 2.0, 0.5], dtype=torch.float64
    )
    noise = torch.randn(2, 50, 3, generator=g, dtype=torch.float64)  # no consensus at 1e-6
    src = torch.cat((good_src, line, noise[:1], good_src))
    dst = torch.cat((good_dst, line + 1.0, noise[1:], good_dst))
    mask = torch.ones(4, 50, dtype=torch.bool)
    mask[3, 2:] = False  # two valid pairs
    result = ransac_procrustes(src, dst, mask, max_correspondence_distance=1e-6, max_iterations=200,
                               generator=torch.Generator().manual_seed(0))  # fmt: skip
    assert result.valid.tolist() == [True, False, False, False]
    eye = torch.eye(4, dtype=torch.float64)
    for b in (1, 2, 3):
        assert torch.equal(result.transformation[b], eye)
        assert result.fitness[b] == 0 and result.inlier_rmse[b] == 0 and not result.inliers[b].any()
    for field in (result.transformation, result.fitness, result.inlier_rmse):
        assert torch.isfinite(field).all()
    empty = ransac_procrustes(torch.zeros(2, 0, 3), torch.zeros(2, 0, 3),
                              max_correspondence_distance=0.1)  # fmt: skip
    assert not empty.valid.any() and empty.inliers.shape == (2, 0)


def test_solver_class_matches_function():
    src, dst, *_ = _pairs(4, 2, 100, 0.3, 0.001)
    solver = RANSACProcrustes(max_correspondence_distance=0.005, max_iterations=100)
    a = solver(src, dst, generator=torch.Generator().manual_seed(1))
    b = ransac_procrustes(src, dst, max_correspondence_distance=0.005, max_iterations=100,
                          generator=torch.Generator().manual_seed(1))  # fmt: skip
    assert torch.equal(a.transformation, b.transformation)
    assert "max_iterations=100" in repr(solver)


def test_bad_inputs():
    x = torch.rand(2, 10, 3)
    with pytest.raises(ShapeError):
        ransac_procrustes(x, torch.rand(2, 11, 3), max_correspondence_distance=0.1)
    with pytest.raises(ShapeError):
        ransac_procrustes(x, x.double(), max_correspondence_distance=0.1)
    with pytest.raises(ShapeError):
        ransac_procrustes(x, x, torch.ones(2, 10), max_correspondence_distance=0.1)
    with pytest.raises(ValueRangeError):
        ransac_procrustes(x.clone().fill_(float("inf")), x, max_correspondence_distance=0.1)
    for bad in (
        {"max_correspondence_distance": 0.0},
        {"max_correspondence_distance": float("nan")},
        {"max_correspondence_distance": 0.1, "sample_size": 2},
        {"max_correspondence_distance": 0.1, "max_iterations": 0},
        {"max_correspondence_distance": 0.1, "confidence": 0.0},
        {"max_correspondence_distance": 0.1, "confidence": 1.5},
    ):
        with pytest.raises(ValueRangeError):
            ransac_procrustes(x, x, **bad)
