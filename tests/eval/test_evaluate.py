from __future__ import annotations

import json
import math
import shutil

import numpy as np
import open3d as o3d
import pytest
import torch

from poseflow.data.bop import BOPDataset, BOPDataWarning
from poseflow.data.objects import ObjectModel
from poseflow.data.synthetic import generate_dataset
from poseflow.errors import ValueRangeError
from poseflow.eval.evaluate import closest_results, evaluate_bop, gt_results, load_eval_models
from poseflow.eval.recall import Target
from poseflow.eval.results import PoseResults, write_results

BOX, CAN = 1, 2


def _rot(axis: str, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    R = {"x": [[1, 0, 0], [0, c, -s], [0, s, c]], "z": [[c, -s, 0], [s, c, 0], [0, 0, 1]]}[axis]
    T = np.eye(4)
    T[:3, :3] = R
    return T


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    box = o3d.geometry.TriangleMesh.create_box(0.08, 0.06, 0.04).translate((-0.04, -0.03, -0.02))
    can = o3d.geometry.TriangleMesh.create_cylinder(radius=0.03, height=0.1, resolution=32)
    flip_x = _rot("x", math.pi)
    objects = {
        BOX: ObjectModel.from_mesh(box, num_points=64),  # declared asymmetric
        CAN: ObjectModel.from_mesh(
            can,
            num_points=64,
            symmetries_discrete=[flip_x],
            symmetries_continuous=[(np.array([0.0, 0.0, 1.0]), np.zeros(3))],
        ),
    }
    root = tmp_path_factory.mktemp("bop")
    generate_dataset(
        root,
        objects,
        num_train_images=0,
        num_test_images=4,
        images_per_scene=2,
        objects_per_image=2,
        distractors_per_image=0,
        clutter=0.2,
        width=200,
        height=150,
        progress=False,
    )
    return root


def _with_poses(res: PoseResults, poses: torch.Tensor) -> PoseResults:
    return PoseResults(res.scene_ids, res.im_ids, res.obj_ids, res.scores, poses, res.times)


def test_exact_gt_scores_one(dataset):
    report = evaluate_bop(dataset, gt_results(dataset))
    assert report["AR"] == report["AR_VSD"] == report["AR_MSSD"] == report["AR_MSPD"] == 1.0
    assert set(report["per_object"]) == {str(BOX), str(CAN)}
    assert all(v["AR"] == 1.0 for v in report["per_object"].values())
    assert report["num_targets"] == sum(v["num_targets"] for v in report["per_object"].values())
    assert len(report["per_threshold"]["vsd"]["recall"]) == 10
    assert len(report["per_threshold"]["mspd"]["thresholds"]) == 10
    json.dumps(report)  # serialisable


def test_symmetric_equivalents_score_one(dataset):
    res = gt_results(dataset)
    poses = res.poses.clone()
    is_can = res.obj_ids == CAN
    # A rotation about the can's axis by a multiple of its facet angle, then the flip: same shape.
    sym = torch.from_numpy(_rot("z", 5 * 2 * math.pi / 32) @ _rot("x", math.pi))
    poses[is_can] = poses[is_can] @ sym
    report = evaluate_bop(dataset, _with_poses(res, poses))
    assert report["per_object"][str(CAN)]["AR_MSSD"] == 1.0
    assert report["per_object"][str(CAN)]["AR_MSPD"] == 1.0
    assert report["per_object"][str(CAN)]["AR_VSD"] == 1.0


def test_flip_correct_for_symmetric_not_for_asymmetric(dataset):
    res = gt_results(dataset)
    flip = torch.from_numpy(_rot("x", math.pi))
    report = evaluate_bop(dataset, _with_poses(res, res.poses @ flip), metrics=("mssd", "mspd"))
    assert report["per_object"][str(CAN)]["AR"] == 1.0
    # The box's flip moves its corners by about 0.07 m, 0.65 of its diameter: never correct.
    assert report["per_object"][str(BOX)]["AR_MSSD"] == 0.0
    assert report["per_object"][str(BOX)]["AR_MSPD"] < 0.5
    assert "AR_VSD" not in report and report["metrics"] == ["mssd", "mspd"]


def test_pose_off_by_0_6_diameters_scores_zero_on_mssd(dataset):
    res = gt_results(dataset)
    models = load_eval_models(BOPDataset(dataset), [BOX, CAN])
    poses = res.poses.clone()
    for i, o in enumerate(res.obj_ids.tolist()):
        poses[i, 0, 3] += 0.6 * models[o].diameter
    report = evaluate_bop(dataset, _with_poses(res, poses), metrics=("mssd",))
    assert report["AR_MSSD"] == 0.0 and report["AR"] == 0.0
    assert all(r == 0.0 for r in report["per_threshold"]["mssd"]["recall"])


def test_missing_estimates_and_non_target_images(dataset):
    res = gt_results(dataset)
    keep = torch.arange(len(res)) % 2 == 0
    half = PoseResults(
        *(
            getattr(res, f)[keep]
            for f in ("scene_ids", "im_ids", "obj_ids", "scores", "poses", "times")
        )
    )
    extra = PoseResults.from_columns(
        [99, 0], [0, 77], [BOX, BOX], [1.0, 1.0], torch.eye(4).repeat(2, 1, 1)
    )
    with pytest.warns(BOPDataWarning, match=r"2 results rows name images .*scene 0 image 77"):
        report = evaluate_bop(dataset, PoseResults.concat([half, extra]), metrics=("mssd", "mspd"))
    full = evaluate_bop(dataset, res, metrics=("mssd",))
    n = full["num_targets"]
    found = int(keep.sum())  # the GT results hold exactly one estimate per target instance here
    assert report["num_targets"] == n
    assert report["AR_MSSD"] == pytest.approx(found / n)
    assert report["num_estimates"] == found + 2 and report["num_evaluated"] == found


def test_ties_keep_file_order(dataset):
    res = gt_results(dataset)
    wrong = res.poses.clone()
    wrong[:, :3, 3] += 1.0
    # Wrong copies first with the same score: they are the ones evaluated.
    both = PoseResults.concat([_with_poses(res, wrong), res])
    assert evaluate_bop(dataset, both, metrics=("mssd",))["AR"] == 0.0
    both = PoseResults.concat([res, _with_poses(res, wrong)])
    assert evaluate_bop(dataset, both, metrics=("mssd",))["AR"] == 1.0


def test_csv_path_and_derived_targets(dataset, tmp_path):
    res = gt_results(dataset)
    csv = tmp_path / "gt_synthetic-test.csv"
    write_results(csv, res)
    copy = tmp_path / "copy"
    shutil.copytree(dataset, copy)
    (copy / "test_targets_bop19.json").unlink()
    a = evaluate_bop(dataset, csv, metrics=("mssd",))
    b = evaluate_bop(copy, csv, metrics=("mssd",))
    assert a["num_targets"] == b["num_targets"] and b["AR"] == 1.0
    only = evaluate_bop(dataset, csv, metrics=("mssd",), targets=[Target(0, 0, BOX, 1)])
    assert only["num_targets"] == 1 and list(only["per_object"]) == [str(BOX)]


def test_unknown_metric_raises(dataset):
    with pytest.raises(ValueRangeError):
        evaluate_bop(dataset, gt_results(dataset), metrics=("add",))


def test_gt_results_raise_no_warning(dataset):
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert evaluate_bop(dataset, gt_results(dataset), metrics=("mssd",))["AR"] == 1.0


def test_rows_of_unknown_objects_are_counted_in_a_warning(dataset):
    res = gt_results(dataset)
    stray = PoseResults.from_columns(
        [0, 0, 0], [0, 0, 0], [7, 7, 9], [1.0] * 3, torch.eye(4).repeat(3, 1, 1)
    )
    with pytest.warns(BOPDataWarning, match=r"3 results rows name objects .* \(7, 9\)"):
        report = evaluate_bop(dataset, PoseResults.concat([res, stray]), metrics=("mssd",))
    assert report["AR"] == 1.0


def test_translations_in_metres_are_reported(dataset, tmp_path):
    res = gt_results(dataset)
    poses = res.poses.clone()
    poses[:, :3, 3] /= 1000.0  # t written in metres where the file holds millimetres
    write_results(tmp_path / "m.csv", _with_poses(res, poses))
    with pytest.warns(BOPDataWarning, match="was t written in metres"):
        report = evaluate_bop(dataset, tmp_path / "m.csv", metrics=("mssd",))
    assert report["AR"] == 0.0


def _shifted(res: PoseResults, which: torch.Tensor, by: float) -> PoseResults:
    """``res`` with the rows ``which`` moved by ``by`` metres along x."""
    poses = res.poses.clone()
    poses[which, 0, 3] += by
    return _with_poses(res, poses)


def _groups(res: PoseResults, obj_id: int) -> int:
    """How many images ``res`` has estimates of ``obj_id`` in."""
    rows = res.obj_ids == obj_id
    return len(set(zip(res.scene_ids[rows].tolist(), res.im_ids[rows].tolist())))


def test_closest_results_takes_each_objects_better_estimator(dataset):
    truth = gt_results(dataset)
    box = truth.obj_ids == BOX
    good_box = _shifted(truth, ~box, 0.03)  # the box right, the can 3 cm off
    good_can = _shifted(truth, box, 0.03)
    chosen, counts = closest_results(dataset, [good_box, good_can])
    report = evaluate_bop(dataset, chosen, metrics=("mssd", "mspd"))
    alone = [evaluate_bop(dataset, r, metrics=("mssd", "mspd"))["AR"] for r in (good_box, good_can)]
    assert report["AR"] == 1.0 and max(alone) < 1.0
    n_box, n_can = _groups(truth, BOX), _groups(truth, CAN)
    assert counts == [n_box, n_can]
    assert len(chosen) == len(truth) and bool((chosen.times == -1).all())


def test_closest_results_ties_go_first_and_missing_rows_count_as_misses(dataset):
    truth = gt_results(dataset)
    _, counts = closest_results(dataset, [truth, truth])
    assert counts[1] == 0
    box = truth.obj_ids == BOX
    only_cans = PoseResults(*(getattr(truth, f)[~box] for f in ("scene_ids", "im_ids",
                            "obj_ids", "scores", "poses", "times")))  # fmt: skip
    near = _shifted(truth, torch.ones_like(box), 0.002)  # every estimate 2 mm off
    chosen, counts = closest_results(dataset, [only_cans, near])
    assert counts == [_groups(truth, CAN), _groups(truth, BOX)]
    assert int((chosen.obj_ids == BOX).sum()) == int(box.sum())


def test_closest_results_needs_two(dataset):
    with pytest.raises(ValueRangeError, match="two or more"):
        closest_results(dataset, [gt_results(dataset)])
