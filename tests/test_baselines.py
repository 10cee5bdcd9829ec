from __future__ import annotations

import pytest
import torch

from poseflow.baselines import ClassicBaseline
from poseflow.data.demo_objects import demo_objects
from poseflow.data.synthetic import generate_dataset
from poseflow.errors import ShapeError, ValueRangeError
from poseflow.eval.evaluate import evaluate_bop
from poseflow.eval.results import read_results, write_results
from poseflow.eval.timing import StageTimer


@pytest.fixture(scope="module")
def bracket():
    return demo_objects(num_points=1024, names=("bracket",))[0]


def test_bad_inputs(bracket):
    with pytest.raises(ValueRangeError):
        ClassicBaseline({})
    with pytest.raises(ValueRangeError):
        ClassicBaseline({3: bracket}, restarts=0)
    baseline = ClassicBaseline({3: bracket}, num_views=4)
    K = torch.eye(3, dtype=torch.float64)
    depth = torch.zeros(8, 8)
    masks = torch.zeros(1, 8, 8, dtype=torch.bool)
    with pytest.raises(ValueRangeError):
        baseline.estimate(depth, K, masks, [7])
    with pytest.raises(ValueRangeError):
        baseline.estimate(depth, K, masks, [3, 3])
    with pytest.raises(ShapeError):
        baseline.estimate(depth, K, torch.zeros(1, 8, 9, dtype=torch.bool), [3])


def test_empty_mask_is_invalid_not_nan(bracket):
    baseline = ClassicBaseline({3: bracket}, num_views=4)
    K = torch.tensor([[100.0, 0, 4], [0, 100.0, 4], [0, 0, 1]], dtype=torch.float64)
    est = baseline.estimate(torch.full((8, 8), 0.5), K, torch.zeros(1, 8, 8, dtype=torch.bool), [3])
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
    assert {"geometric_encoder", "ransac", "icp", "other"} <= set(stages)
