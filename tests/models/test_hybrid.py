"""The hybrid estimator: FunFlow6D's hypotheses and the classic baseline's pose, one verifier."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from poseflow.baselines import ClassicBaseline
from poseflow.data import ImageInstances
from poseflow.errors import UnitsError, ValueRangeError
from poseflow.eval.predict import PoseEstimate
from poseflow.eval.timing import StageTimer
from poseflow.geometry.se3 import rotation_angle_error, translation_error
from poseflow.models import FunFlow6D, Hybrid, Proposals, full_grid_ranking, keep_better


@pytest.fixture(scope="module")
def baseline(box):
    return ClassicBaseline({1: box}, num_views=8, restarts=4, verifier=None)


@pytest.fixture(scope="module")
def hybrid(tiny_model, baseline):
    model = FunFlow6D(tiny_model.config.replace(num_hypotheses=2))
    model.objects, model.verifier = tiny_model.objects, tiny_model.verifier
    return Hybrid(model, baseline)


def _args(scene):
    return scene["rgb"], scene["depth"], scene["K"], scene["masks"], [1, 1]


class _FlippingBaseline(ClassicBaseline):
    """The baseline with its first pose replaced by the truth half-turned about the box's long
    axis: the geometric flip that only the print decides, made exact (where the baseline itself
    lands after its flip depends on the machine's rounding)."""

    truth: torch.Tensor

    def solve(self, image):
        est, clouds = super().solve(image)
        poses = est.poses.clone()
        poses[0] = self.truth[0].to(poses) @ torch.diag(torch.tensor([1.0, -1, -1, 1])).to(poses)
        return PoseEstimate(poses, est.scores, est.valid), clouds


def test_the_verifier_keeps_the_baseline_pose_where_the_flow_is_lost(hybrid, box, scene):
    """The untrained flow's poses are noise, the baseline's the box up to its geometric flip; the
    verifier finds the baseline's pose in the pool and turns it by the print."""
    baseline = _FlippingBaseline({1: box}, num_views=8, restarts=4, verifier=None)
    baseline.truth = scene["poses"]
    flipping = Hybrid(hybrid.model, baseline)
    flow = hybrid.model.estimate(*_args(scene))
    classic, _ = baseline.solve(ImageInstances(*_args(scene)))
    timer = StageTimer(synchronize=False)
    with timer.active():
        out = flipping.estimate(*_args(scene))
    assert timer.counts["verification"] >= 1 and timer.counts["icp"] >= 1  # both ran
    truth = scene["poses"]
    assert classic.valid.all() and out.valid.all()
    assert (rotation_angle_error(classic.poses.float(), truth) > 175).any()  # flipped
    assert (rotation_angle_error(flow.poses, truth) > 5).any()  # the flow alone is lost
    assert (rotation_angle_error(out.poses, truth) < 5).all()
    assert (translation_error(out.poses, truth) < 0.005).all()
    assert out.poses.dtype == torch.float32 and ((out.scores > 0) & (out.scores <= 1)).all()
    assert out.agreement.shape == (2,) and ((out.agreement >= 0) & (out.agreement <= 1)).all()


def test_the_same_call_gives_the_same_poses(hybrid, scene):
    a, b = hybrid.estimate(*_args(scene)), hybrid.estimate(*_args(scene))
    assert torch.equal(a.poses, b.poses) and torch.equal(a.scores, b.scores)


def test_no_instances_give_an_empty_estimate(hybrid, scene):
    empty = scene["masks"][:0]
    out = hybrid.estimate(scene["rgb"], scene["depth"], scene["K"], empty, [])
    assert out.poses.shape == (0, 4, 4) and out.valid.shape == (0,)


def test_the_hybrid_needs_verification_and_every_object(tiny_model, box):
    unverified = FunFlow6D(tiny_model.config.replace(verifier=None))
    unverified.objects = tiny_model.objects
    with pytest.raises(ValueRangeError, match="verification"):
        Hybrid(unverified, ClassicBaseline({1: box}, num_views=2, verifier=None))
    with pytest.raises(ValueRangeError, match=r"no model of objects \[1\]"):
        Hybrid(tiny_model, ClassicBaseline({2: box}, num_views=2, verifier=None))


def test_full_grid_ranking_scores_every_candidate_at_the_full_crop(tiny_model):
    cfg = tiny_model.config.with_inference(
        {"verifier.crop_size": 48, "verifier.coarse_crop_size": 16}
    )
    ranked = full_grid_ranking(cfg)
    assert ranked.verifier.coarse_crop_size == 48 == ranked.verifier.crop_size
    assert ranked.replace(verifier=cfg.verifier) == cfg  # nothing else changes
    with pytest.raises(ValueRangeError, match=r"needs config\.verifier"):
        full_grid_ranking(cfg.replace(verifier=None))


def test_a_funflow6d_estimate_without_a_generator_is_seeded(tiny_model, scene):
    a, b = tiny_model.estimate(*_args(scene)), tiny_model.estimate(*_args(scene))
    assert torch.equal(a.poses, b.poses)


@given(
    st.lists(st.booleans(), min_size=1, max_size=6),
    st.lists(st.booleans(), min_size=6, max_size=6),
    st.integers(0, 3),
    st.sampled_from([torch.float32, torch.float64]),
    st.booleans(),
)
def test_a_rival_is_verified_on_its_own_row_and_the_better_score_is_kept(
    first_valid, second_valid, E, dtype, rank
):
    B = len(first_valid)
    g = torch.Generator().manual_seed(B * 7 + E)
    pose = lambda *s: torch.randn(*s, 4, 4, generator=g, dtype=dtype)  # noqa: E731
    est = PoseEstimate(pose(B), torch.rand(B, generator=g, dtype=dtype), torch.tensor(first_valid))
    others, others_mask = pose(B, E), torch.rand(B, E, generator=g) < 0.5
    cloud, cloud_mask = torch.rand(B, 5, 3, generator=g), torch.rand(B, 5, generator=g) < 0.5
    second_ok = torch.tensor(second_valid[:B])
    other = PoseEstimate(pose(B).double(), torch.rand(B, generator=g).double(), second_ok)
    both = Proposals(est, others, others_mask, cloud, cloud_mask, rank=rank).with_rival(other)
    assert both.rank == rank and both.others.shape == (2 * B, E, 4, 4)
    assert both.estimate.poses.dtype == dtype and both.others.dtype == dtype
    assert torch.equal(both.estimate.poses[B:], other.poses.to(dtype))
    assert torch.equal(both.estimate.valid, torch.cat((est.valid, second_ok)))
    assert torch.equal(both.others[:B], others) and torch.equal(both.others_mask[:B], others_mask)
    assert not both.others_mask[B:].any()  # the rival's rows have no other candidates
    assert torch.equal(both.observed, torch.cat((cloud, cloud)))
    assert torch.equal(both.observed_mask, torch.cat((cloud_mask, cloud_mask)))
    kept = keep_better(both.estimate)
    assert torch.equal(kept.valid, est.valid | second_ok)
    for i in range(B):
        s1, s2 = est.scores[i].item(), other.scores[i].item()
        second_wins = second_ok[i] and (not est.valid[i] or s2 > s1)
        winner = both.estimate.poses[B + i] if second_wins else est.poses[i]
        assert torch.equal(kept.poses[i], winner)
        assert kept.scores[i].item() == pytest.approx(s2 if second_wins else s1)


@pytest.mark.parametrize("factor", [1000.0, 0.001])
def test_a_depth_in_the_wrong_unit_is_a_units_error_for_every_estimator(
    tiny_model, hybrid, baseline, scene, factor
):
    """Depth in millimetres passed as metres (or the reverse) is never estimated."""
    rgb, depth, K, masks, ids = _args(scene)
    for estimate in (tiny_model.estimate, hybrid.estimate, baseline.estimate):
        with pytest.raises(UnitsError, match="depth"):
            estimate(rgb, depth * factor, K, masks, ids)


def test_predict_gives_an_image_the_same_poses_whatever_came_before(hybrid, tmp_path):
    from poseflow.data.bop import BOPDataset
    from poseflow.data.synthetic import generate_dataset
    from poseflow.eval.recall import Target

    root = generate_dataset(
        tmp_path / "ds", num_train_images=0, num_test_images=2, width=160, height=120,
        seed=5, progress=False,
    )  # fmt: skip
    scene = BOPDataset(root, "test").scene(0)
    last = max(scene.im_ids)
    count = sum(gt.obj_id == 1 for gt in scene.gt_of(last))
    both = hybrid.predict(root, seed=3, max_images=2)
    alone = hybrid.predict(root, seed=3, targets=[Target(0, last, 1, count)])
    rows = (both.scene_ids == 0) & (both.im_ids == last)
    assert len(alone) == int(rows.sum()) > 0 and bool((~rows).any())
    assert torch.equal(alone.poses, both.poses[rows]) and torch.equal(
        alone.scores, both.scores[rows]
    )
