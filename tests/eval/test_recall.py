from __future__ import annotations

import pytest
import torch

from poseflow.errors import ShapeError, ValueRangeError
from poseflow.eval.recall import Target, assign, match, targets_from_gt

TH = [0.05, 0.1, 0.2]


def _errors(a, table):
    """Pair errors from a dict {(estimate index, gt id): error}; missing pairs are inf."""
    _, _, _, est, gt = a.pairs()
    return torch.tensor([table.get((int(e), int(g)), float("inf")) for e, g in zip(est, gt)])


def test_exact_estimates_give_full_recall():
    gts = {(1, 0): [(5, 1.0), (7, 0.5)], (1, 1): [(5, 0.9)]}
    targets = targets_from_gt(gts)
    a = assign(targets, gts, [1, 1, 1], [0, 0, 1], [5, 7, 5], [1.0, 1.0, 1.0])
    r = match(a, torch.zeros(len(a.pairs()[0])), TH)
    assert r.num_targets == 3
    torch.testing.assert_close(r.recall, torch.ones(1, 3, dtype=torch.float64))
    assert r.average == 1.0 and r.per_object_targets == {5: 2, 7: 1}


def test_threshold_is_strict():
    gts = {(1, 0): [(5, 1.0)]}
    a = assign(targets_from_gt(gts), gts, [1], [0], [5], [1.0])
    r = match(a, torch.tensor([0.1]), TH)
    torch.testing.assert_close(r.recall, torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64))


def test_ties_in_score_keep_file_order():
    gts = {(1, 0): [(5, 1.0)]}
    targets = [Target(1, 0, 5, 1)]
    # Two estimates with the same score: only the first in file order is evaluated.
    a = assign(targets, gts, [1, 1], [0, 0], [5, 5], [0.5, 0.5])
    assert a.est_index.tolist() == [[0]]
    wrong_first = match(a, _errors(a, {(0, 0): 1.0, (1, 0): 0.0}), TH)
    assert wrong_first.average == 0.0
    b = assign(targets, gts, [1, 1], [0, 0], [5, 5], [0.5, 0.5000001])
    assert b.est_index.tolist() == [[1]]
    assert match(b, _errors(b, {(0, 0): 1.0, (1, 0): 0.0}), TH).average == 1.0


def test_missing_estimates_count_as_misses():
    gts = {(1, 0): [(5, 1.0)], (1, 1): [(5, 1.0)], (1, 2): [(6, 1.0)]}
    targets = targets_from_gt(gts)
    a = assign(targets, gts, [1], [1], [5], [0.3])
    r = match(a, torch.zeros(1), TH)
    assert r.num_targets == 3
    torch.testing.assert_close(r.recall, torch.full((1, 3), 1 / 3, dtype=torch.float64))
    assert r.per_object[6].sum() == 0.0
    torch.testing.assert_close(r.per_object[5], torch.full((1, 3), 0.5, dtype=torch.float64))


def test_estimates_for_non_targets_are_ignored():
    gts = {(1, 0): [(5, 1.0), (9, 0.02)]}
    targets = targets_from_gt(gts)  # object 9 is too occluded to be a target
    assert targets == [Target(1, 0, 5, 1)]
    # Estimates of another image, another scene and the non-target object are dropped.
    a = assign(targets, gts, [1, 1, 2, 1], [0, 7, 0, 0], [5, 5, 5, 9], [0.1, 0.9, 0.9, 0.9])
    assert a.est_index.tolist() == [[0]]
    assert match(a, torch.zeros(1), TH).average == 1.0


def test_top_inst_count_by_score():
    gts = {(1, 0): [(5, 1.0), (5, 0.8)]}
    a = assign(targets_from_gt(gts), gts, [1, 1, 1], [0, 0, 0], [5, 5, 5], [0.1, 0.9, 0.5])
    assert a.est_index.tolist() == [[1, 2]]  # the two best, in decreasing score
    assert a.gt_index.tolist() == [[0, 1]]


def test_greedy_matching_by_score():
    """The best-scored estimate takes its closest GT, even if that leaves another unmatched."""
    gts = {(1, 0): [(5, 1.0), (5, 0.9)]}
    a = assign(targets_from_gt(gts), gts, [1, 1], [0, 0], [5, 5], [0.9, 0.5])
    errs = _errors(a, {(0, 0): 0.03, (0, 1): 0.04, (1, 0): 0.045})
    r = match(a, errs, TH)
    # Estimate 0 matches GT 0; estimate 1 only fits GT 0, already taken: 1 of 2 found.
    torch.testing.assert_close(r.recall, torch.full((1, 3), 0.5, dtype=torch.float64))
    # With the scores swapped estimate 1 goes first, takes GT 0, and estimate 0 takes GT 1.
    b = assign(targets_from_gt(gts), gts, [1, 1], [0, 0], [5, 5], [0.5, 0.9])
    r = match(b, _errors(b, {(0, 0): 0.03, (0, 1): 0.04, (1, 0): 0.045}), TH)
    torch.testing.assert_close(r.recall, torch.tensor([[1.0, 1.0, 1.0]], dtype=torch.float64))


def test_only_most_visible_instances_are_valid():
    gts = {(1, 0): [(5, 0.3), (5, 0.9)]}
    a = assign([Target(1, 0, 5, 1)], gts, [1], [0], [5], [1.0])
    assert a.gt_valid.tolist() == [[False, True]]
    assert a.num_targets == 1
    # Matching the less visible instance does not count, and it is not a candidate at all.
    r = match(a, _errors(a, {(0, 0): 0.0, (0, 1): 0.15}), TH)
    torch.testing.assert_close(r.recall, torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64))


def test_recall_is_pooled_over_targets_not_averaged_per_object():
    gts = {(1, i): [(5, 1.0)] for i in range(3)}
    gts[(1, 3)] = [(6, 1.0)]
    a = assign(targets_from_gt(gts), gts, [1, 1, 1, 1], [0, 1, 2, 3], [5, 5, 5, 6], [1.0] * 4)
    r = match(a, _errors(a, {(0, 0): 0.0, (1, 0): 0.0, (2, 0): 0.0, (3, 0): 9.0}), TH)
    assert r.average == pytest.approx(0.75)
    assert (r.object_average(5) + r.object_average(6)) / 2 == pytest.approx(0.5)


def test_variants_are_matched_independently():
    gts = {(1, 0): [(5, 1.0)]}
    a = assign(targets_from_gt(gts), gts, [1], [0], [5], [1.0])
    r = match(a, torch.tensor([[0.01, 0.5]]), TH)
    torch.testing.assert_close(
        r.recall, torch.tensor([[1.0, 1.0, 1.0], [0.0, 0.0, 0.0]], dtype=torch.float64)
    )


def test_no_targets_gives_zero_recall():
    a = assign([], {}, [], [], [], [])
    r = match(a, torch.zeros(0), TH)
    assert r.num_targets == 0 and r.average == 0.0


def test_bad_inputs_raise():
    gts = {(1, 0): [(5, 1.0)]}
    a = assign(targets_from_gt(gts), gts, [1], [0], [5], [1.0])
    with pytest.raises(ValueRangeError):
        match(a, torch.tensor([float("nan")]), TH)
    with pytest.raises(ShapeError):
        match(a, torch.zeros(2), TH)
    with pytest.raises(ValueRangeError):
        assign([Target(2, 0, 5, 1)], gts, [], [], [], [])
    with pytest.raises(ValueRangeError):
        assign([Target(1, 0, 5, 0)], gts, [], [], [], [])
    with pytest.raises(ShapeError):
        assign([Target(1, 0, 5, 1)], gts, [1, 1], [0], [5], [1.0])
