"""The hybrid estimator: FunFlow6D's hypotheses and the classic baseline's pose, one verifier."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from poseflow.baselines import ClassicBaseline
from poseflow.errors import UnitsError, ValueRangeError
from poseflow.eval.predict import PoseEstimate
from poseflow.eval.timing import StageTimer
from poseflow.geometry.se3 import rotation_angle_error, translation_error
from poseflow.models import FunFlow6D, Hybrid, Proposals


@pytest.fixture(scope="module")
def baseline(box):
    return ClassicBaseline({1: box}, num_views=8, restarts=4, verification=False)


@pytest.fixture(scope="module")
def hybrid(tiny_model, baseline):
    model = FunFlow6D(tiny_model.config.replace(num_hypotheses=2))
    model.objects, model.verifier = tiny_model.objects, tiny_model.verifier
    return Hybrid(model, baseline)


def _args(scene):
    return scene["rgb"], scene["depth"], scene["K"], scene["masks"], [1, 1]


def test_the_verifier_keeps_the_baseline_pose_where_the_flow_is_lost(hybrid, baseline, scene):
    """The untrained flow's poses are noise, the baseline's the box up to its geometric flip; the
    verifier finds the baseline's pose in the pool and turns it by the print."""
    flow = hybrid.model.estimate(*_args(scene))
    classic, _ = baseline.solve(scene["depth"], scene["K"], scene["masks"], [1, 1])
    timer = StageTimer(synchronize=False)
    with timer.active():
        out = hybrid.estimate(*_args(scene))
    assert timer.counts["verification"] >= 1 and timer.counts["icp"] >= 1  # both ran
    truth = scene["poses"]
    assert classic.valid.all() and out.valid.all()
    assert (rotation_angle_error(classic.poses.float(), truth) > 175).any()  # flipped
    assert (rotation_angle_error(flow.poses, truth) > 5).any()  # the flow alone is lost
    assert (rotation_angle_error(out.poses, truth) < 5).all()
    assert (
        translation_error(out.poses, truth)[1] < 0.005
    )  # the first slides along the box, as in the baseline's pose
    assert out.poses.dtype == torch.float32 and ((out.scores > 0) & (out.scores <= 1)).all()


def test_the_same_call_gives_the_same_poses(hybrid, scene):
    a, b = hybrid.estimate(*_args(scene)), hybrid.estimate(*_args(scene))
    assert torch.equal(a.poses, b.poses) and torch.equal(a.scores, b.scores)


def test_no_instances_give_an_empty_estimate(hybrid, scene):
    empty = scene["masks"][:0]
    out = hybrid.estimate(scene["rgb"], scene["depth"], scene["K"], empty, [])
    assert out.poses.shape == (0, 4, 4) and out.valid.shape == (0,)


def test_the_hybrid_needs_verification_and_every_object(tiny_model, box):
    unverified = FunFlow6D(tiny_model.config.replace(verification=False))
    unverified.objects = tiny_model.objects
    with pytest.raises(ValueRangeError, match="verification"):
        Hybrid(unverified, ClassicBaseline({1: box}, num_views=2, verification=False))
    with pytest.raises(ValueRangeError, match=r"no model of objects \[1\]"):
        Hybrid(tiny_model, ClassicBaseline({2: box}, num_views=2, verification=False))


def test_a_funflow6d_estimate_without_a_generator_is_seeded(tiny_model, scene):
    a, b = tiny_model.estimate(*_args(scene)), tiny_model.estimate(*_args(scene))
    assert torch.equal(a.poses, b.poses)


@given(
    st.lists(st.booleans(), min_size=1, max_size=6),
    st.lists(st.booleans(), min_size=6, max_size=6),
    st.integers(0, 3),
    st.sampled_from([torch.float32, torch.float64]),
)
def test_pooling_keeps_every_valid_pose_and_verifies_a_valid_one(inc_valid, other_valid, E, dtype):
    B = len(inc_valid)
    g = torch.Generator().manual_seed(B * 7 + E)
    pose = lambda *s: torch.randn(*s, 4, 4, generator=g, dtype=dtype)  # noqa: E731
    est = PoseEstimate(pose(B), torch.rand(B, generator=g, dtype=dtype), torch.tensor(inc_valid))
    others, others_mask = pose(B, E), torch.rand(B, E, generator=g) < 0.5
    other_ok = torch.tensor(other_valid[:B])
    other = PoseEstimate(pose(B).double(), torch.rand(B, generator=g).double(), other_ok)
    pooled = Proposals(est, others, others_mask).pooled(other)
    assert pooled.rank and pooled.others.shape == (B, E + 1, 4, 4)
    assert pooled.estimate.poses.dtype == dtype and pooled.others.dtype == dtype
    assert torch.equal(pooled.estimate.valid, est.valid | other_ok)
    assert torch.equal(pooled.others[:, :E], others) and torch.equal(
        pooled.others_mask[:, :E], others_mask
    )
    for i in range(B):  # the two poses of an instance are the incumbent and the last candidate
        pair = {pooled.estimate.poses[i].sum().item(), pooled.others[i, E].sum().item()}
        assert pair == {est.poses[i].sum().item(), other.poses[i].to(dtype).sum().item()}
        if other_ok[i] and not est.valid[i]:  # a valid pose is verified, not the invalid one
            assert torch.equal(pooled.estimate.poses[i], other.poses[i].to(dtype))
            assert not pooled.others_mask[i, E]
        else:
            assert torch.equal(pooled.estimate.poses[i], est.poses[i])
            assert bool(pooled.others_mask[i, E]) == bool(other_ok[i])


@pytest.mark.parametrize("factor", [1000.0, 0.001])
def test_a_depth_in_the_wrong_unit_is_a_units_error_for_every_estimator(
    tiny_model, hybrid, baseline, scene, factor
):
    """Depth in millimetres passed as metres (or the reverse) is never estimated."""
    rgb, depth, K, masks, ids = _args(scene)
    for estimate in (
        tiny_model.estimate,
        hybrid.estimate,
        lambda *a: baseline.estimate(*a[1:], rgb=a[0]),
    ):
        with pytest.raises(UnitsError, match="depth"):
            estimate(rgb, depth * factor, K, masks, ids)
