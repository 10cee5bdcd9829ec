from __future__ import annotations

import pytest
import torch

from poseflow.baselines import (
    BASELINE_VERIFIER,
    BaselineConfig,
    ClassicBaseline,
    verify_estimates,
)
from poseflow.data import ImageInstances
from poseflow.data.demo_objects import demo_objects
from poseflow.data.synthetic import generate_dataset
from poseflow.errors import ShapeError, ValueRangeError
from poseflow.eval.evaluate import evaluate_bop
from poseflow.eval.predict import PoseEstimate
from poseflow.eval.results import read_results, write_results
from poseflow.eval.timing import StageTimer
from poseflow.geometry.se3 import axis_angle_to_rotation, rotation_angle_error, translation_error
from poseflow.render import Light, Renderer
from poseflow.verify import PoseVerifier, VerifierConfig

#: A verifier light enough for tests.
LIGHT = VerifierConfig(num_points=2048, crop_size=48, coarse_crop_size=24, turn_steps=4)


@pytest.fixture(scope="module")
def bracket():
    return demo_objects(num_points=1024, names=("bracket",))[0]


@pytest.fixture(scope="module")
def labelled_box():
    return demo_objects(num_points=1024, names=("labelled_box",))[0]


def test_bad_inputs(bracket):
    with pytest.raises(ValueRangeError):
        ClassicBaseline({})
    with pytest.raises(ValueRangeError):
        ClassicBaseline({3: bracket}, restarts=0)
    with pytest.raises(ValueRangeError, match="unknown BaselineConfig field 'verification'"):
        ClassicBaseline({3: bracket}, verification=False)  # the old name: verifier=None
    with pytest.raises(ValueRangeError, match="unknown VerifierConfig field 'crop'"):
        ClassicBaseline({3: bracket}, verifier={"crop": 32})
    with pytest.raises(ValueRangeError, match="verifier must be a VerifierConfig"):
        ClassicBaseline({3: bracket}, verifier=32)
    assert ClassicBaseline({3: bracket}, verifier={"crop_size": 32}).verifier.config.crop_size == 32
    baseline = ClassicBaseline({3: bracket}, num_views=4)
    K = torch.tensor([[100.0, 0, 4], [0, 100.0, 4], [0, 0, 1]], dtype=torch.float64)
    depth = torch.zeros(8, 8)
    masks = torch.zeros(1, 8, 8, dtype=torch.bool)
    with pytest.raises(ValueRangeError, match="no model"):
        baseline.estimate(None, depth, K, masks, [7])
    with pytest.raises(ValueRangeError, match="object ids"):
        baseline.estimate(None, depth, K, masks, [3, 3])
    with pytest.raises(ShapeError):
        baseline.estimate(None, depth, K, torch.zeros(1, 8, 9, dtype=torch.bool), [3])
    for bad in (torch.eye(2), [[100.0, 0], [0, 100.0]], [1.0] * 8):
        with pytest.raises(ShapeError, match="K must be 9 numbers"):
            baseline.estimate(None, depth, bad, masks, [3])
    with pytest.raises(ValueRangeError, match="transposed"):
        baseline.estimate(None, depth, K.T, masks, [3])


def test_baseline_config_merges_changes_and_round_trips(bracket):
    config = BaselineConfig(restarts=4, icp_distances=[0.1, 0.02])
    assert config.icp_distances == (0.1, 0.02) and config.verifier == BASELINE_VERIFIER
    assert BaselineConfig.from_dict(config.to_dict()) == config
    baseline = ClassicBaseline({3: bracket}, config, verifier={"rank_top_k": 4}, seed=2)
    assert baseline.config.restarts == 4 and baseline.config.seed == 2
    assert baseline.verifier.config == VerifierConfig(refine_estimate=False, rank_top_k=4)
    merged = ClassicBaseline({3: bracket}, verifier={"crop_size": 32}).config.verifier
    assert merged.crop_size == 32 and merged.refine_estimate is False  # merged, not reset
    assert ClassicBaseline({3: bracket}, config, verifier=None).config.verifier is None
    for bad in ({"voxel_size": 0}, {"icp_distances": ()}, {"restarts": 0}):
        with pytest.raises(ValueRangeError):
            BaselineConfig(**bad)
    with pytest.raises(ValueRangeError, match="config must be a BaselineConfig"):
        ClassicBaseline({3: bracket}, {"restarts": 4})


def test_intrinsics_as_lists_or_arrays_and_no_masks(bracket):
    baseline = ClassicBaseline({3: bracket}, num_views=4)
    K = torch.tensor([[100.0, 0, 4], [0, 100.0, 4], [0, 0, 1]], dtype=torch.float64)
    depth, masks = torch.full((8, 8), 0.5), torch.ones(1, 8, 8, dtype=torch.bool)
    ref = baseline.estimate(None, depth, K, masks, [3])
    for same in (K.tolist(), K.numpy(), K.reshape(9).tolist()):
        est = baseline.estimate(None, depth, same, masks, [3])
        assert torch.equal(est.poses, ref.poses) and torch.equal(est.valid, ref.valid)
    est = baseline.estimate(None, depth, K.tolist(), masks[:0], [])
    assert est.poses.shape == (0, 4, 4) and est.scores.shape == est.valid.shape == (0,)


def test_a_pose_behind_the_camera_is_never_valid(bracket, monkeypatch):
    baseline = ClassicBaseline({3: bracket}, num_views=4, verifier=None)
    behind = torch.eye(4, dtype=torch.float64)
    behind[2, 3] = -0.5  # depth in the wrong unit can put the object there

    def estimate_one(depth, K, mask, obj_id, i):
        pose = behind.clone()
        pose[2, 3] *= -1 if i == 0 else 1
        return pose, 0.8, torch.zeros(0, 3)

    monkeypatch.setattr(baseline, "_estimate_one", estimate_one)
    K = torch.tensor([[100.0, 0, 4], [0, 100.0, 4], [0, 0, 1]], dtype=torch.float64)
    est = baseline.estimate(
        None, torch.full((8, 8), 0.5), K, torch.ones(2, 8, 8, dtype=torch.bool), [3, 3]
    )
    assert est.valid.tolist() == [True, False] and est.scores.tolist() == [0.8, 0.0]


def test_empty_mask_is_invalid_not_nan(bracket):
    baseline = ClassicBaseline({3: bracket}, num_views=4)
    K = torch.tensor([[100.0, 0, 4], [0, 100.0, 4], [0, 0, 1]], dtype=torch.float64)
    depth, masks = torch.full((8, 8), 0.5), torch.zeros(1, 8, 8, dtype=torch.bool)
    est = baseline.estimate(None, depth, K, masks, [3])
    assert est.valid.tolist() == [False]
    assert torch.equal(est.poses[0], torch.eye(4, dtype=torch.float64))
    assert est.scores.tolist() == [0.0]


@pytest.mark.slow
def test_baseline_recovers_poses_through_csv_and_eval(bracket, tmp_path):
    """Little occlusion, geometry-distinct object: the classic pipeline reaches AR >= 0.8."""
    root = generate_dataset(
        tmp_path / "bop",
        {3: bracket},
        num_train_images=0,
        num_test_images=6,
        images_per_scene=2,
        objects_per_image=1,
        distractors_per_image=0,
        clutter=0.15,
        width=320,
        height=240,
        progress=False,
    )
    timer = StageTimer()
    results = ClassicBaseline({3: bracket}).predict(root, timer=timer)
    assert len(results) == 6
    assert bool((results.times > 0).all())
    csv = tmp_path / "classic_synthetic-test.csv"
    write_results(csv, results)
    report = evaluate_bop(root, read_results(csv))
    assert report["AR"] >= 0.8, report
    stages = timer.breakdown()["stages_ms"]
    named = {"lifting", "geometric_encoder", "matching", "ransac", "icp", "verification"}
    assert named <= set(stages)
    assert stages.get("other", 0.0) < 0.05 * sum(stages.values())  # every step has a stage


def test_verification_picks_the_printed_side_of_a_labelled_box(labelled_box):
    K = torch.tensor([[320.0, 0, 79.5], [0, 320.0, 59.5], [0, 0, 1]])
    pose = torch.eye(4)
    pose[:3, :3] = axis_angle_to_rotation(torch.tensor([1.0, 0.3, 0.0]), torch.tensor(0.45))
    pose[2, 3] = 0.55
    light = Light(direction=(0.3, -0.4, -1.0), ambient=0.4, diffuse=0.6)
    out = Renderer([labelled_box.mesh]).render(pose[None], K, 160, 120, light=light)
    rgb = out.rgb.permute(2, 0, 1).contiguous()  # uint8, as BOP images are read
    args = (rgb, out.depth, K, out.masks_visible, [1])
    on = ClassicBaseline({1: labelled_box}, num_views=6, restarts=4, verifier=LIGHT)
    timer = StageTimer()
    with timer.active():
        verified = on.estimate(*args)
    assert timer.counts["verification"] == 1
    assert bool(verified.valid[0])
    assert float(rotation_angle_error(verified.poses, pose[None].double())[0]) < 3.0
    assert float(translation_error(verified.poses, pose[None].double())[0]) < 0.003
    off = ClassicBaseline({1: labelled_box}, num_views=6, restarts=4, verifier=None)
    plain = off.estimate(*args)
    # depth alone settles on the box turned end for end (seed 0)
    assert float(rotation_angle_error(plain.poses, pose[None].double())[0]) > 150
    # the score is the verifier's render-and-compare score, not ICP fitness
    assert 0 < float(verified.scores[0]) <= 1
    assert abs(float(verified.scores[0]) - float(plain.scores[0])) > 1e-3


@pytest.mark.parametrize("polish", [0, 4])
def test_a_kept_estimate_comes_back_polished_or_at_full_precision(labelled_box, polish):
    K = torch.tensor([[320.0, 0, 79.5], [0, 320.0, 59.5], [0, 0, 1]])
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, :3] = axis_angle_to_rotation(
        torch.tensor([1.0, 0.3, 0.0]), torch.tensor(0.45)
    ).double()
    pose[2, 3] = 0.55
    light = Light(direction=(0.3, -0.4, -1.0), ambient=0.4, diffuse=0.6)
    out = Renderer([labelled_box.mesh]).render(pose[None].float(), K, 160, 120, light=light)
    image = ImageInstances(out.rgb.permute(2, 0, 1), out.depth, K, out.masks_visible, [1])
    off = pose.clone()
    off[0, 3] += 0.006  # the baseline's verifier keeps its estimate unrefined (refine_estimate)
    verifier = PoseVerifier(
        VerifierConfig(**{**LIGHT.to_dict(), "refine_estimate": False, "polish_levels": polish})
    )
    verifier.prepare(1, labelled_box)
    cloud, mask = verifier.observed_cloud(out.depth, K, out.masks_visible)
    estimate = PoseEstimate(off[None], torch.ones(1, dtype=torch.float64), torch.tensor([True]))
    verified = verify_estimates(verifier, image, estimate, [cloud[0][mask[0]]])
    if polish:  # the polish is what comes back, not the estimate it started from
        assert float(translation_error(verified.poses, pose[None])[0]) < 0.003
    else:
        assert torch.equal(verified.poses, estimate.poses)  # float64, as it was


def test_baseline_with_verification_on_a_generated_scene(labelled_box, tmp_path):
    root = generate_dataset(
        tmp_path / "bop", {1: labelled_box}, num_train_images=0, num_test_images=1,
        objects_per_image=1, distractors_per_image=0, clutter=0.15, width=240, height=180,
        progress=False,
    )  # fmt: skip
    results, stages = {}, {}
    for verify in (True, False):
        timer = StageTimer()
        verifier = LIGHT if verify else None
        baseline = ClassicBaseline({1: labelled_box}, num_views=6, restarts=4, verifier=verifier)
        results[verify] = baseline.predict(root, timer=timer)
        stages[verify] = set(timer.breakdown()["stages_ms"])
    assert "verification" in stages[True] and "verification" not in stages[False]
    assert len(results[True]) == len(results[False]) == 1
    assert 0 < float(results[True].scores[0]) <= 1
    assert float(results[True].scores[0]) != float(results[False].scores[0])


def test_estimate_takes_the_estimators_arguments_in_their_order(bracket):
    """rgb first, as FunFlow6D and Hybrid take it; keyword calls of the old order still work."""
    import inspect

    from poseflow.models import FunFlow6D, Hybrid

    first = ["rgb", "depth", "K", "masks", "obj_ids"]
    for estimate in (ClassicBaseline.estimate, FunFlow6D.estimate, Hybrid.estimate):
        assert list(inspect.signature(estimate).parameters)[1:6] == first
    baseline = ClassicBaseline({3: bracket}, num_views=4, verifier=None)
    assert baseline.estimator() == baseline.estimate
    K = torch.tensor([[100.0, 0, 4], [0, 100.0, 4], [0, 0, 1]], dtype=torch.float64)
    depth, masks = torch.full((8, 8), 0.5), torch.ones(1, 8, 8, dtype=torch.bool)
    by_name = baseline.estimate(depth=depth, K=K, masks=masks, obj_ids=[3], rgb=None)
    assert torch.equal(by_name.poses, baseline.estimate(None, depth, K, masks, [3]).poses)
