"""Plausibility checks of units and intrinsics (``poseflow._units``)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from poseflow._units import (
    check_depth_units,
    check_diameter_units,
    check_intrinsics,
    check_size_against_depth,
    in_front_of_camera,
)
from poseflow.errors import DegenerateInputError, ShapeError, UnitsError, ValueRangeError

K = [[572.4, 0.0, 325.3], [0.0, 573.6, 242.0], [0.0, 0.0, 1.0]]


def test_depth_in_millimetres_read_as_metres_names_the_scale_to_set():
    depth = torch.full((8, 8), 812.0)
    depth[0] = 0.0  # missing pixels do not count
    with pytest.raises(UnitsError, match=r"--depth-scale 0\.001"):
        check_depth_units(depth)
    with pytest.raises(UnitsError, match=r"depth_scale=0\.001"):
        check_depth_units(depth, scale_name="depth_scale=")


def test_depth_divided_by_1000_twice_names_the_scale_to_set():
    with pytest.raises(
        UnitsError, match=r"metres read as millimetres\? set --depth-scale 1; it is 0\.001"
    ):
        check_depth_units(torch.full((4, 4), 0.0008), scale=0.001)


def test_plausible_depth_returns_its_median_and_empty_depth_is_degenerate():
    assert check_depth_units(torch.tensor([[0.0, 0.5], [0.7, 0.9]])) == pytest.approx(0.7)
    with pytest.raises(DegenerateInputError):
        check_depth_units(torch.zeros(3, 3))


@pytest.mark.parametrize(("diameter", "fix"), [(155.0, "0.001"), (0.000155, "1000")])
def test_implausible_diameters_name_the_mesh_scale(diameter, fix):
    with pytest.raises(UnitsError, match=f"--mesh-scale {fix}"):
        check_diameter_units(diameter)
    assert check_diameter_units(0.155) == 0.155


def test_an_object_holding_the_camera_is_a_unit_mix_up():
    check_size_against_depth(0.2, 0.5)
    with pytest.raises(UnitsError, match="not in the same unit"):
        check_size_against_depth(1.5, 0.5)


@pytest.mark.parametrize("form", ["list", "flat", "array", "tensor"])
def test_intrinsics_accept_lists_arrays_and_tensors(form):
    value = {
        "list": K,
        "flat": [x for row in K for x in row],
        "array": np.array(K),
        "tensor": torch.tensor(K, dtype=torch.float32),
    }[form]
    out = check_intrinsics(value, 640, 480)
    assert out.dtype == torch.float64 and out.shape == (3, 3)
    assert out[0, 2].item() == pytest.approx(325.3)


def test_transposed_or_foreign_intrinsics_are_rejected():
    with pytest.raises(ValueRangeError, match="transposed"):
        check_intrinsics(np.array(K).T, 640, 480)
    with pytest.raises(ValueRangeError, match="outside the 320x240 image"):
        check_intrinsics(K, 320, 240)  # K of a 640x480 camera
    with pytest.raises(ValueRangeError, match="focal"):
        check_intrinsics([[-500.0, 0, 320], [0, 500, 240], [0, 0, 1]], 640, 480)
    with pytest.raises(ShapeError):
        check_intrinsics([1.0, 2.0, 3.0], 640, 480)
    with pytest.raises(ShapeError):
        check_intrinsics("572.4 0 325", 640, 480)


def test_a_pose_behind_the_camera_is_never_in_front():
    T = torch.eye(4, dtype=torch.float64).repeat(4, 1, 1)
    T[:, 2, 3] = torch.tensor([0.8, 0.0, -0.8, float("nan")], dtype=torch.float64)
    assert in_front_of_camera(T).tolist() == [True, False, False, False]
