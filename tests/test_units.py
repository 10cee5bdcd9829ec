"""Plausibility checks of units and intrinsics (``poseflow._units``)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from poseflow._units import (
    check_depth_extent,
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


def _scene(depth_m: float = 0.8, size: int = 30, n: int = 2):
    """``(depth, K, masks)``: ``n`` squares of ``size`` px at ``depth_m``, each ~0.1 m across."""
    K = torch.tensor([[600.0, 0, 80], [0, 600.0, 60], [0, 0, 1]], dtype=torch.float64)
    depth = torch.full((120, 160), depth_m)
    masks = torch.zeros(n, 120, 160, dtype=torch.bool)
    for i in range(n):
        masks[i, 10:10 + size, 10 + 50 * i:10 + 50 * i + size] = True  # fmt: skip
    return depth, K, masks


def test_depth_extent_agrees_with_the_diameter_and_returns_each_ratio():
    depth, K, masks = _scene()
    ratios = check_depth_extent(depth, K, masks, [0.05, 0.04])
    assert ratios.shape == (2,) and ratios.dtype == torch.float64
    side = 30 * 0.8 / 600  # 4 cm squares
    assert ratios[0].item() == pytest.approx(side * 1.2 / 0.05, rel=0.15)
    assert ratios[1].item() == pytest.approx(ratios[0].item() * 0.05 / 0.04)


@pytest.mark.parametrize(
    ("factor", "fix"),
    [(10.0, r"10 times too large\? set --depth-scale 0\.0001"),
     (1000.0, r"1000 times too large\? set --depth-scale 1e-06"),
     (0.001, r"1000 times too small\? set --depth-scale 1;")],
)  # fmt: skip
def test_depth_off_by_a_power_of_ten_names_the_factor_and_the_scale(factor, fix):
    depth, K, masks = _scene()
    with pytest.raises(UnitsError, match=fix):
        check_depth_extent(
            depth * factor, K, masks, [0.05, 0.05], scale_name="--depth-scale", scale=0.001
        )


def test_depth_off_without_a_scale_asks_for_metres():
    depth, K, masks = _scene()
    with pytest.raises(UnitsError, match=r"multiply the depth by 1000 \(poseflow takes depth in"):
        check_depth_extent(depth / 1000, K, masks, [0.05, 0.05], where="depth.png")


def test_depth_ten_times_too_small_is_caught_where_it_is_also_implausibly_near():
    depth, K, masks = _scene(depth_m=0.8, size=60, n=1)  # 8 cm squares of an 8 cm object
    check_depth_extent(depth, K, masks, [0.08])
    with pytest.raises(UnitsError, match="10 times too small"):
        check_depth_extent(depth / 10, K, masks, [0.08])  # 8 cm away


def test_heavily_occluded_or_thin_instances_do_not_trip_the_extent_check():
    # a tenth of the object visible: about a third of its diameter, at a plausible depth
    depth, K, masks = _scene(depth_m=0.8, size=15, n=1)
    assert check_depth_extent(depth, K, masks, [0.08])[0] < 1 / 3
    # a thin object seen end-on, alone: a twentieth of its length, 1.5 m away
    depth, K, masks = _scene(depth_m=1.5, size=8, n=1)
    assert check_depth_extent(depth, K, masks, [0.3])[0] > 0.05
    # one occluded instance among others that show their whole object
    depth, K, masks = _scene()
    masks[1] = False
    masks[1, 20:28, 60:68] = True
    assert check_depth_extent(depth, K, masks, [0.05, 0.1])[1] < 1 / 3


def test_one_stray_mask_does_not_make_the_depth_look_too_large():
    depth, K, masks = _scene(n=3)
    masks[2, :, :] = True  # a mask spilling over the whole image
    ratios = check_depth_extent(depth, K, masks, [0.05, 0.05, 0.05])
    assert ratios[2] > 3 and ratios[0] < 3  # the median of the three judges
    with pytest.raises(UnitsError, match="masks are of other objects"):
        check_depth_extent(depth, K, masks[2:], [0.05])


def test_masks_spilling_onto_a_far_background_do_not_look_like_a_unit_error():
    depth, K, masks = _scene(n=3)
    wall = torch.full_like(depth, 2.5)
    depth = torch.where(masks.any(0), depth, wall)  # the squares 1.7 m in front of a wall
    loose = torch.nn.functional.max_pool2d(masks[None].float(), 11, 1, 5)[0] > 0  # dilated 5 px
    ratios = check_depth_extent(depth, K, loose, [0.05, 0.05, 0.05])
    assert (ratios < 2).all()  # the wall 34 diameters behind counts half a diameter at most
    with pytest.raises(UnitsError, match="10 times too large"):
        check_depth_extent(depth * 10, K, loose, [0.05, 0.05, 0.05])


def test_instances_with_few_points_or_unknown_diameters_are_not_judged():
    depth, K, masks = _scene()
    small = torch.zeros_like(masks)
    small[:, 10:15, 10:15] = True  # 25 pixels
    assert torch.isnan(check_depth_extent(depth * 1000, K, small, [0.05, 0.05])).all()
    out = check_depth_extent(depth, K, masks, [float("nan"), 0.05])
    assert torch.isnan(out[0]) and torch.isfinite(out[1])
    assert check_depth_extent(depth, K, masks[:0], []).shape == (0,)
    with pytest.raises(ShapeError, match="2 masks but 1 diameters"):
        check_depth_extent(depth, K, masks, [0.05])
    with pytest.raises(ShapeError):
        check_depth_extent(depth[:50], K, masks, [0.05, 0.05])
