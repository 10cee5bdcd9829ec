"""Poses of one frame: ``poseflow.eval.frame``."""

from __future__ import annotations

import json

import pytest
import torch

from poseflow.data.frame import Frame
from poseflow.errors import ShapeError, UnitsError
from poseflow.eval.frame import estimate_frame, write_poses_json
from poseflow.eval.predict import PoseEstimate

H, W = 12, 16


def _frame(n: int, depth: float = 0.6) -> Frame:
    masks = torch.zeros(n, H, W, dtype=torch.bool)
    masks[:, 2:8, 3:9] = True
    K = torch.tensor([[20.0, 0, 7.5], [0, 20.0, 5.5], [0, 0, 1]], dtype=torch.float64)
    return Frame(
        torch.zeros(3, H, W, dtype=torch.uint8), torch.full((H, W), depth), K, masks,
        torch.arange(1, n + 1), torch.ones(n, dtype=torch.float64),
        [f"mask{i}.png" for i in range(n)],
    )  # fmt: skip


class _Fixed:
    """An estimator returning fixed poses; counts its calls."""

    def __init__(self, z, valid):
        self.calls = 0
        n = len(z)
        self.poses = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
        self.poses[:, 2, 3] = torch.tensor(z, dtype=torch.float64)
        self.valid = torch.tensor(valid)

    def __call__(self, rgb, depth, K, masks, obj_ids):
        self.calls += 1
        assert masks.shape[0] == len(obj_ids)
        return PoseEstimate(self.poses, torch.full((len(obj_ids),), 0.7), self.valid)


def test_a_pose_behind_the_camera_is_never_valid():
    est = _Fixed([0.6, -0.6, 0.0, float("nan")], [True, True, True, True])
    out = estimate_frame(est, _frame(4))
    assert out.valid.tolist() == [True, False, False, False]
    assert out.scores.tolist() == pytest.approx([0.7, 0.0, 0.0, 0.0])
    assert "behind the camera" in out.notes[1] and "not finite" in out.notes[3]
    assert out.sources == ["mask0.png", "mask1.png", "mask2.png", "mask3.png"]


def test_a_pose_the_estimator_already_rejected_keeps_its_reason():
    out = estimate_frame(_Fixed([-0.6, 0.0], [False, False]), _frame(2))
    assert out.valid.tolist() == [False, False]
    assert "behind the camera (t_z = -0.6 m)" in out.notes[0]
    assert out.notes[1].startswith("no pose found")  # the identity of no estimate


def test_zero_instances_give_an_empty_result_without_calling_the_estimator():
    est = _Fixed([], [])
    out = estimate_frame(est, _frame(0))
    assert len(out) == 0 and out.poses.shape == (0, 4, 4) and est.calls == 0


def test_an_object_larger_than_its_distance_is_a_unit_mix_up():
    est = _Fixed([0.6], [True])
    estimate_frame(est, _frame(1), diameters={1: 0.2})
    with pytest.raises(UnitsError, match=r"object 1 \(mask0\.png\) has a diameter of 150 m"):
        estimate_frame(est, _frame(1), diameters={1: 150.0})  # a mesh in mm, depth in m
    assert est.calls == 1


def test_wrong_number_of_poses_is_an_error():
    with pytest.raises(ShapeError):
        estimate_frame(_Fixed([0.6], [True]), _frame(2))


def test_poses_json_has_metres_millimetres_score_and_validity(tmp_path):
    out = estimate_frame(_Fixed([0.6, -0.2], [True, True]), _frame(2))
    write_poses_json(tmp_path / "p.json", out, meta={"method": "fixed"})
    data = json.loads((tmp_path / "p.json").read_text())
    first, second = data["poses"]
    assert first["t_m"] == [0.0, 0.0, 0.6] and first["t_mm"] == pytest.approx([0.0, 0.0, 600.0])
    assert first["R"] == torch.eye(3).tolist() and first["valid"]
    assert first["score"] == pytest.approx(0.7)
    assert not second["valid"] and second["score"] == 0.0 and "behind" in second["note"]
    assert data["method"] == "fixed" and data["seconds"] >= 0


def test_depth_a_thousand_times_too_small_stops_before_the_estimator():
    masks = torch.zeros(2, 120, 160, dtype=torch.bool)
    masks[0, 10:40, 10:40] = True
    masks[1, 50:80, 60:90] = True
    K = torch.tensor([[600.0, 0, 80], [0, 600.0, 60], [0, 0, 1]], dtype=torch.float64)
    frame = Frame(
        torch.zeros(3, 120, 160, dtype=torch.uint8), torch.full((120, 160), 0.8), K, masks,
        torch.tensor([1, 2]), torch.ones(2, dtype=torch.float64), depth_scale=0.001,
    )  # fmt: skip
    est = _Fixed([0.8, 0.8], [True, True])
    assert estimate_frame(est, frame, diameters={1: 0.05, 2: 0.06}).valid.all()
    frame.depth = frame.depth / 1000  # metres divided by 1000 once more
    with pytest.raises(UnitsError, match=r"1000 times too small\? set depth_scale=1;"):
        estimate_frame(est, frame, diameters={1: 0.05, 2: 0.06})
    assert est.calls == 1
