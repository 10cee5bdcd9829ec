"""What ``valid`` means: rules fitted on calibration poses, applied, reported, stored."""

from __future__ import annotations

import json
import math

import hypothesis.strategies as st
import open3d as o3d
import pytest
import torch
from hypothesis import given, settings

from poseflow.data.objects import ObjectModel
from poseflow.data.synthetic import generate_dataset
from poseflow.errors import CheckpointError, ValueRangeError
from poseflow.eval.evaluate import gt_results
from poseflow.eval.frame import FramePoses
from poseflow.eval.results import PoseResults
from poseflow.eval.validity import (
    ValidityRule,
    apply_validity,
    estimate_errors,
    mesh_key,
    plot_reliability,
    read_validity,
    validity_report,
    write_validity,
)


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(st.integers(1, 3), st.floats(0, 1, allow_nan=False), st.booleans()),
        min_size=1,
        max_size=60,
    ),
    st.sampled_from([0.8, 0.9, 0.95]),
)
def test_fitted_rule_reaches_its_precision_on_its_own_poses(rows, precision):
    obj_ids = [r[0] for r in rows]
    scores = torch.tensor([r[1] for r in rows], dtype=torch.float64)
    errors = torch.tensor([0.02 if r[2] else 0.5 for r in rows], dtype=torch.float64)
    rule = ValidityRule.fit("funflow6d", scores, errors, obj_ids, precision=precision)
    valid, notes = rule.decide(scores, obj_ids)
    for obj in set(obj_ids):
        rows_o = torch.tensor([o == obj for o in obj_ids])
        marked = valid & rows_o
        right = int((marked & (errors < 0.1)).sum())
        # Jeffreys' posterior mean of the precision reaches it: a margin on the fitted poses
        assert right + 0.5 >= precision * (int(marked.sum()) + 1) or not bool(marked.any())
        threshold = rule.thresholds[obj]
        if math.isinf(threshold):
            assert not bool(marked.any())
        else:  # the threshold is one of the object's scores, and everything from it is valid
            assert bool((marked == (rows_o & (scores >= threshold))).all())
    assert all(bool(n) != bool(v) for n, v in zip(notes, valid.tolist()))


def test_fit_takes_the_lowest_precise_score_per_object():
    scores = [0.9, 0.8, 0.7, 0.6, 0.5] * 8 + [0.9, 0.1] * 10
    errors = [0.01, 0.02, 0.03, 0.5, 0.04] * 8 + [0.5, 0.01] * 10
    obj_ids = [1] * 40 + [2] * 20
    rule = ValidityRule.fit("baseline", scores, errors, obj_ids)
    # object 1: from 0.6 down a fifth are wrong; object 2: its best scores are all wrong
    assert rule.thresholds == {1: 0.7, 2: math.inf}
    assert rule.counts == {1: (40, 32), 2: (20, 10)}
    valid, notes = rule.decide(torch.tensor([0.75, 0.65, 0.99]), [1, 1, 2])
    assert valid.tolist() == [True, False, False]
    assert "below 0.700" in notes[1] and "no score made poses of obj 2 right" in notes[2]
    unknown, why = rule.decide(torch.tensor([0.99]), [7])
    assert not unknown[0] and "obj 7 was not calibrated" in why[0]


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"precision": 1.0}, "precision"),
        ({"precision": 0.0}, "precision"),
        ({"tolerance": 0.0}, "tolerance"),
    ],
)
def test_fit_refuses_settings_out_of_range(kwargs, message):
    with pytest.raises(ValueRangeError, match=message):
        ValidityRule.fit("funflow6d", [0.5], [0.0], [1], **kwargs)


def test_fit_refuses_columns_of_different_lengths():
    with pytest.raises(ValueRangeError, match="differ in length"):
        ValidityRule.fit("funflow6d", [0.5, 0.6], [0.0], [1])


def test_rules_round_trip_through_the_model_folder(tmp_path):
    counts = {1: (9, 8), 2: (3, 0)}
    a = ValidityRule("funflow6d", 0.1, 0.95, {1: 0.4, 2: math.inf}, {1: "k1"}, counts)
    b = ValidityRule("hybrid", 0.1, 0.9, {1: 0.3}, {}, {1: (5, 5)})
    assert read_validity(tmp_path, "funflow6d") is None  # no file yet
    write_validity(tmp_path, a)
    path = write_validity(tmp_path, b)
    assert json.loads(path.read_text())["methods"]["funflow6d"]["objects"]["2"]["threshold"] is None
    assert read_validity(tmp_path, "funflow6d") == a
    assert read_validity(tmp_path, "hybrid") == b
    assert read_validity(tmp_path, "baseline") is None
    path.write_text("[1, 2]")
    with pytest.raises(CheckpointError, match="is not a validity file"):
        read_validity(tmp_path, "funflow6d")


def test_a_rule_knows_only_the_meshes_it_was_fitted_on():
    box = o3d.geometry.TriangleMesh.create_box(0.1, 0.2, 0.3)
    key = mesh_key(ObjectModel.from_mesh(box, num_points=16))
    other = mesh_key(ObjectModel.from_mesh(box.scale(0.5, [0, 0, 0]), num_points=16))
    assert key != other
    rule = ValidityRule("funflow6d", 0.1, 0.95, {1: 0.4}, {1: key}, {1: (9, 9)})
    same, _ = rule.decide(torch.tensor([0.9]), [1], {1: key})
    changed, notes = rule.decide(torch.tensor([0.9]), [1], {1: other})
    assert same.tolist() == [True] and changed.tolist() == [False]
    assert "is not the one calibrated" in notes[0]


def test_apply_keeps_earlier_reasons_and_says_what_valid_means():
    T = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1)
    poses = FramePoses(
        torch.tensor([1, 1, 1]), T, torch.tensor([0.9, 0.3, 0.0], dtype=torch.float64),
        torch.tensor([True, True, False]), ["", "", "no pose: too few points"],
    )  # fmt: skip
    unchanged, meaning = apply_validity(poses, None)
    assert unchanged is poses and "not calibrated" in meaning
    rule = ValidityRule("funflow6d", 0.1, 0.95, {1: 0.5}, {}, {1: (20, 19)})
    out, meaning = apply_validity(poses, rule)
    assert out.valid.tolist() == [True, False, False]
    assert out.notes[0] == "" and "below 0.500" in out.notes[1]
    assert out.notes[2] == "no pose: too few points"
    assert "precision of 95%" in meaning


def test_report_counts_precision_and_recall_per_object():
    valid = torch.tensor([True, True, False, True, False])
    errors = torch.tensor([0.01, 0.3, 0.05, 0.02, math.inf], dtype=torch.float64)
    report = validity_report(valid, errors, [1, 1, 1, 2, 2])
    assert (report["precision"], report["recall"]) == (2 / 3, 2 / 3)
    assert report["per_object"]["1"]["precision"] == 0.5
    assert report["per_object"]["2"] == {
        "precision": 1.0, "recall": 1.0, "poses": 2, "right": 1, "valid": 1, "valid_right": 1
    }  # fmt: skip
    nothing = validity_report(torch.zeros(2, dtype=torch.bool), torch.ones(2), [1, 1])
    assert nothing["precision"] == 1.0 and nothing["recall"] == 1.0


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    box = o3d.geometry.TriangleMesh.create_box(0.08, 0.06, 0.04).translate((-0.04, -0.03, -0.02))
    return generate_dataset(
        tmp_path_factory.mktemp("validity"), [box, box.scale(0.7, [0, 0, 0])],
        num_train_images=0, num_test_images=2, objects_per_image=2, width=64, height=48,
        progress=False,
    )  # fmt: skip


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_errors_are_zero_for_the_truth_and_grow_with_a_shift(scene, dtype):
    truth = gt_results(scene)
    zeros = torch.zeros(len(truth.scores), dtype=torch.float64)
    assert torch.equal(estimate_errors(scene, truth), zeros)
    shifted = truth.poses.to(dtype).clone()
    shifted[:, 0, 3] += 0.01  # 1 cm: MSSD 1 cm
    moved = PoseResults.from_columns(
        truth.scene_ids, truth.im_ids, truth.obj_ids, truth.scores, shifted
    )
    errors = estimate_errors(scene, moved)
    from poseflow.eval.evaluate import _open, load_eval_models

    models = load_eval_models(_open(scene, "test"), [1, 2])
    expected = torch.tensor([0.01 / models[int(o)].diameter for o in truth.obj_ids.tolist()])
    assert torch.allclose(errors, expected.double(), atol=1e-5)


def test_errors_of_an_object_without_a_model_are_refused(scene):
    truth = gt_results(scene)
    wrong = PoseResults.from_columns(
        truth.scene_ids[:1], truth.im_ids[:1], torch.tensor([99]), truth.scores[:1],
        truth.poses[:1],
    )  # fmt: skip
    with pytest.raises(ValueRangeError, match="object 99 has no entry"):
        estimate_errors(scene, wrong)


def test_reliability_picture_is_written(tmp_path):
    rule = ValidityRule("funflow6d", 0.1, 0.95, {1: 0.5, 2: math.inf})
    s, e = torch.rand(20), torch.rand(20)
    o = torch.tensor([1, 2] * 10)
    panels = {"funflow6d": (s, e, o, rule), "baseline": (s, e, o, None)}
    path = plot_reliability(tmp_path / "r.png", panels)
    assert path.stat().st_size > 1000 and path.read_bytes()[:4] == b"\x89PNG"


def test_agreement_separates_what_the_score_cannot():
    # half the poses are wrong at every score; only the wrong ones have little agreement
    scores = torch.linspace(0.3, 0.9, 40, dtype=torch.float64)
    right = torch.arange(40) % 2 == 0
    errors = torch.where(right, 0.02, 0.4).double()
    agreement = torch.where(right, 0.5, 0.1).double()
    without = ValidityRule.fit("funflow6d", scores, errors, [5] * 40)
    assert math.isinf(without.thresholds[5]) and without.agreements == {}
    rule = ValidityRule.fit("funflow6d", scores, errors, [5] * 40, agreement=agreement)
    assert rule.agreements == {5: 0.5} and rule.thresholds[5] == pytest.approx(0.3)
    valid, notes = rule.decide(scores, [5] * 40, agreement=agreement)
    assert torch.equal(valid, right)
    assert "agree with the pose too little (10%" in notes[1]
    unknown, why = rule.decide(scores[:1], [5])  # no agreement given: not valid
    assert not unknown[0] and "(unknown;" in why[0]
    again = ValidityRule.from_json("funflow6d", json.loads(json.dumps(rule.to_json())))
    assert again == rule


def test_agreement_must_match_the_poses():
    with pytest.raises(ValueRangeError, match="agreement has 1 entries for 2 poses"):
        ValidityRule.fit("funflow6d", [0.5, 0.6], [0.0, 0.0], [1, 1], agreement=[0.5])


def test_frame_poses_write_their_agreement():
    T = torch.eye(4, dtype=torch.float64)[None]
    poses = FramePoses(torch.tensor([1]), T, torch.ones(1), torch.ones(1).bool(), [""])
    assert "agreement" not in poses.to_json()[0]
    poses.agreement = torch.tensor([0.25], dtype=torch.float64)
    assert poses.to_json()[0]["agreement"] == 0.25


def test_reliability_picture_without_matplotlib_names_the_extra(tmp_path, monkeypatch):
    import sys

    from poseflow.errors import MissingDependencyError

    monkeypatch.setitem(sys.modules, "matplotlib", None)  # an import of it fails
    panels = {"baseline": (torch.rand(2), torch.rand(2), torch.tensor([1, 1]), None)}
    with pytest.raises(MissingDependencyError, match=r"poseflow\[viz\]"):
        plot_reliability(tmp_path / "r.png", panels)
    assert not (tmp_path / "r.png").exists()
