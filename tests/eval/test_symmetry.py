from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from poseflow.errors import DegenerateInputError, ShapeError, ValueRangeError
from poseflow.eval.symmetry import (
    discretize_continuous_symmetry,
    symmetries_from_model_info,
    symmetry_transforms,
)
from poseflow.geometry.se3 import axis_angle_to_rotation


def test_one_axis_and_angles_give_rotations(dtype):
    R = axis_angle_to_rotation(
        torch.tensor([1.0, 2.0, 3.0], dtype=dtype), torch.linspace(0, 6, 7, dtype=dtype)
    )
    eye = torch.eye(3, dtype=dtype).expand(7, 3, 3)
    torch.testing.assert_close(R @ R.transpose(1, 2), eye)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(7, dtype=dtype))
    # The axis is fixed by every rotation.
    a = torch.tensor([1.0, 2.0, 3.0], dtype=dtype)
    torch.testing.assert_close(R @ a, a.expand(7, 3))


@pytest.mark.parametrize(("dtype", "tol"), [(torch.float32, 2e-6), (torch.float64, 1e-12)])
@given(seed=st.integers(0, 2**31 - 1), K=st.integers(1, 6), length=st.sampled_from([1e-3, 1, 50]))
def test_one_axis_and_angles_match_scipy(dtype, tol, seed, K, length):
    g = torch.Generator().manual_seed(seed)
    axis = torch.randn(3, generator=g, dtype=torch.float64)
    axis = axis / axis.norm() * length  # any length: normalised here
    angles = (2 * torch.rand(K, generator=g, dtype=torch.float64) - 1) * 2 * math.pi
    R = axis_angle_to_rotation(axis.to(dtype), angles.to(dtype))
    assert R.dtype == dtype and R.shape == (K, 3, 3)
    unit = (axis / axis.norm()).numpy()
    expected = Rotation.from_rotvec(angles.numpy()[:, None] * unit).as_matrix()
    assert (R.double() - torch.from_numpy(expected)).abs().max() <= tol


def test_one_axis_and_no_angles():
    R = axis_angle_to_rotation(torch.tensor([0.0, 0.0, 1.0]), torch.zeros(0))
    assert R.shape == (0, 3, 3)
    with pytest.raises(DegenerateInputError):
        axis_angle_to_rotation(torch.zeros(3), torch.zeros(2))


def test_discretisation_count_and_offset():
    axis = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    offset = torch.tensor([0.1, 0.0, 0.0], dtype=torch.float64)
    S = discretize_continuous_symmetry(axis, offset)
    assert S.shape == (math.ceil(math.pi / 0.01), 4, 4) == (315, 4, 4)
    torch.testing.assert_close(S[0], torch.eye(4, dtype=torch.float64))
    # The offset point lies on the axis: every sample fixes it.
    p = torch.cat((offset, torch.ones(1, dtype=torch.float64)))
    torch.testing.assert_close(S @ p, p.expand(315, 4))
    # Consecutive samples are one step of 2 pi / 315 apart.
    step = 2 * math.pi / 315
    torch.testing.assert_close(
        S[1, :3, :3], axis_angle_to_rotation(axis, torch.tensor([step], dtype=torch.float64))[0]
    )
    assert discretize_continuous_symmetry(axis, offset, max_sym_disc_step=0.5).shape[0] == 7


def test_symmetry_transforms_product_order():
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))  # 180 deg about x
    axis, offset = torch.tensor([0.0, 0.0, 1.0]), torch.zeros(3)
    S = symmetry_transforms(flip[None], [(axis, offset)], max_sym_disc_step=0.5)
    C = discretize_continuous_symmetry(axis.double(), offset.double(), max_sym_disc_step=0.5)
    assert S.shape == (2 * 7, 4, 4)
    torch.testing.assert_close(S[:7], C)
    torch.testing.assert_close(S[7:], C @ flip)


def test_identity_only_without_symmetries(dtype):
    S = symmetry_transforms(dtype=dtype)
    assert S.dtype == dtype
    torch.testing.assert_close(S, torch.eye(4, dtype=dtype)[None])


def test_model_info_converts_millimetres():
    info = {
        "diameter": 100.0,
        "symmetries_discrete": [[-1, 0, 0, 10, 0, -1, 0, 20, 0, 0, 1, 0, 0, 0, 0, 1]],
    }
    S = symmetries_from_model_info(info)
    assert S.shape == (2, 4, 4)
    torch.testing.assert_close(S[1, :3, 3], torch.tensor([0.01, 0.02, 0.0], dtype=torch.float64))
    cont = symmetries_from_model_info(
        {"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 50]}]},
        max_sym_disc_step=0.5,
    )
    p = torch.tensor([0.0, 0.0, 0.05, 1.0], dtype=torch.float64)
    torch.testing.assert_close(cont @ p, p.expand(7, 4))


def test_bad_symmetries_raise():
    with pytest.raises(ShapeError):
        symmetries_from_model_info({"symmetries_discrete": [[1, 0, 0]]})
    with pytest.raises(ValueRangeError):
        discretize_continuous_symmetry(torch.zeros(3), torch.zeros(3))
    with pytest.raises(ValueRangeError):
        discretize_continuous_symmetry(
            torch.tensor([0.0, 0, 1]), torch.zeros(3), max_sym_disc_step=0
        )


def test_agrees_with_the_data_package():
    from poseflow.data.objects import discretize_symmetries

    flip = torch.diag(torch.tensor([-1.0, 1.0, -1.0, 1.0], dtype=torch.float64))
    flip[:3, 3] = torch.tensor([0.0, 0.01, 0.0], dtype=torch.float64)
    axis, offset = torch.tensor([0.0, 1.0, 0.0]), torch.tensor([0.0, 0.0, 0.02])
    ours = symmetry_transforms(flip[None], [(axis, offset)], max_sym_disc_step=0.1)
    theirs = discretize_symmetries(
        [flip.numpy()], [(axis.double().numpy(), offset.double().numpy())], max_sym_disc_step=0.1
    )
    torch.testing.assert_close(ours, torch.from_numpy(theirs))
