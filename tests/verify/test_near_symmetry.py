"""Tests of the near-symmetry search and its rotation helpers."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from poseflow.data.objects import ObjectModel
from poseflow.errors import DegenerateInputError, ValueRangeError
from poseflow.geometry.se3 import axis_angle_to_rotation, random_rotation, rotation_angle_error
from poseflow.render.mesh import TexturedMesh
from poseflow.verify import (
    box_slides,
    box_turns,
    near_symmetries,
    revolution_axis,
)


def box_model(size=(0.1, 0.06, 0.03), **kw: object) -> ObjectModel:
    import open3d as o3d

    box = o3d.geometry.TriangleMesh.create_box(*size)
    box.translate([-s / 2 for s in size])
    return ObjectModel.from_mesh(box, num_points=1024, dtype=torch.float64, **kw)


def cylinder_model(radius: float = 0.03, height: float = 0.1) -> ObjectModel:
    import open3d as o3d

    cyl = o3d.geometry.TriangleMesh.create_cylinder(radius, height, resolution=96)
    return ObjectModel.from_mesh(cyl, num_points=1024, dtype=torch.float64)


def l_block_model() -> ObjectModel:
    """Two boxes in an L with a knob: no rotation maps it onto itself."""
    import open3d as o3d

    a = o3d.geometry.TriangleMesh.create_box(0.08, 0.02, 0.02)
    b = o3d.geometry.TriangleMesh.create_box(0.02, 0.05, 0.02)
    c = o3d.geometry.TriangleMesh.create_box(0.01, 0.01, 0.03).translate((0.06, 0.0, 0.02))
    return ObjectModel.from_mesh(a + b + c, num_points=1024, dtype=torch.float64)


def angles(found) -> list[float]:
    eye = torch.eye(3, dtype=found.transforms.dtype)
    return rotation_angle_error(eye, found.transforms[:, :3, :3]).tolist()


@given(seed=st.integers(0, 2**31 - 1), double=st.booleans())
def test_axis_angle_is_a_rotation_by_that_angle(seed: int, double: bool) -> None:
    dtype = torch.float64 if double else torch.float32
    g = torch.Generator().manual_seed(seed)
    axis = torch.randn(5, 3, generator=g, dtype=dtype)
    angle = torch.rand(5, generator=g, dtype=dtype) * math.pi
    R = axis_angle_to_rotation(axis, angle)
    eye = torch.eye(3, dtype=dtype).expand(5, 3, 3)
    tol = 1e-5 if not double else 1e-12
    torch.testing.assert_close(R @ R.transpose(1, 2), eye, atol=tol, rtol=0)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(5, dtype=dtype), atol=tol, rtol=0)
    torch.testing.assert_close((R @ axis[..., None])[..., 0], axis, atol=10 * tol, rtol=0)
    got = rotation_angle_error(eye, R)
    torch.testing.assert_close(got, torch.rad2deg(angle), atol=0.05 if not double else 1e-6, rtol=0)


def test_zero_axis_raises() -> None:
    with pytest.raises(DegenerateInputError):
        axis_angle_to_rotation(torch.zeros(3), torch.tensor(1.0))


@given(seed=st.integers(0, 2**31 - 1), outliers=st.floats(0.0, 0.15))
def test_revolution_axis_of_a_moved_cone_with_a_handle(seed: int, outliers: float) -> None:
    g = torch.Generator().manual_seed(seed)
    n = 600
    t = torch.rand(n, generator=g, dtype=torch.float64) * 2 * math.pi
    h = torch.rand(n, generator=g, dtype=torch.float64)
    r = 0.05 + 0.02 * h  # a cone: radius grows with height
    pts = torch.stack((r * torch.cos(t), r * torch.sin(t), 0.1 * h), -1)
    nrm = torch.stack((torch.cos(t), torch.sin(t), torch.full_like(t, -0.2)), -1)
    k = int(outliers * n)  # a "handle": points whose normals ignore the axis
    nrm[:k] = torch.randn(k, 3, generator=g, dtype=torch.float64)
    nrm = torch.nn.functional.normalize(nrm, dim=-1)
    R = random_rotation(1, generator=g, dtype=torch.float64)[0]
    shift = torch.randn(3, generator=g, dtype=torch.float64) * 0.2
    a, c = revolution_axis(pts @ R.T + shift, nrm @ R.T)
    assert abs(float(a @ R[:, 2])) > math.cos(math.radians(2.0))
    # the axis passes through the moved origin
    off = (shift - c) - ((shift - c) @ a) * a
    assert float(off.norm()) < 3e-3


def test_revolution_axis_of_a_sphere_is_undefined() -> None:
    nrm = torch.eye(3, dtype=torch.float64)
    with pytest.raises(DegenerateInputError):
        revolution_axis(torch.zeros(3, 3, dtype=torch.float64), nrm[:, :1].expand(3, 3))


def test_box_has_its_three_half_turns() -> None:
    m = box_model()
    found = near_symmetries(m.points, m.normals, m.diameter, min_overlap=0.9)
    assert len(found) == 3
    assert all(a > 179 for a in angles(found))
    assert (found.overlap > 0.97).all()
    # each is one of the box's exact half-turns about its centre
    exact = [torch.diag(torch.tensor(d, dtype=torch.float64)) for d in
             ([1.0, -1.0, -1.0], [-1.0, 1.0, -1.0], [-1.0, -1.0, 1.0])]  # fmt: skip
    for T in found.transforms:
        assert min(float(rotation_angle_error(E, T[:3, :3])) for E in exact) < 1.0
        assert float(T[:3, 3].norm()) < 0.01 * m.diameter


def test_declared_symmetries_are_not_candidates() -> None:
    declared = np.eye(4)
    declared[:3, :3] = np.diag([-1.0, -1.0, 1.0])  # the half-turn about z
    m = box_model(symmetries_discrete=[declared])
    found = near_symmetries(m.points, m.normals, m.diameter, declared=m.symmetries, min_overlap=0.9)
    # the half-turns about x and y are equal to each other modulo the declared one
    assert len(found) == 1
    R = found.transforms[0, :3, :3]
    assert not torch.allclose(R, torch.as_tensor(declared[:3, :3]), atol=0.1)


def test_cylinder_turns_about_its_axis() -> None:
    m = cylinder_model()
    found = near_symmetries(m.points, m.normals, m.diameter, min_overlap=0.9, max_candidates=30)
    axis = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    turns = [T for T in found.transforms if float((T[:3, :3] @ axis) @ axis) > 0.99]
    # every 30 degrees about the axis, kept apart by at least 15 degrees
    assert len(turns) == 11
    flips = len(found) - len(turns)
    assert flips >= 1  # upside down


def test_asymmetric_block_has_no_near_symmetry() -> None:
    m = l_block_model()
    assert len(near_symmetries(m.points, m.normals, m.diameter, min_overlap=0.8)) == 0


def test_flat_object_uses_its_principal_axes() -> None:
    v = np.array([[0, 0, 0], [0.1, 0, 0], [0.1, 0.04, 0], [0, 0.04, 0.0]])
    quad = TexturedMesh(v, np.array([[0, 1, 2], [0, 2, 3]]))
    m = ObjectModel.from_mesh(quad, num_points=512, dtype=torch.float64)
    found = near_symmetries(m.points, m.normals, m.diameter, min_overlap=0.9)
    assert len(found) == 3  # the rectangle's three half-turns; no axis of revolution


def _cube_group(R: torch.Tensor) -> None:
    """``R`` ``(23, 3, 3)`` with the identity: the 24 signed permutations, closed under ``@``."""
    assert torch.allclose(R.abs().sum(-1), torch.ones(23, 3, dtype=R.dtype), atol=1e-3)
    group = torch.cat((torch.eye(3, dtype=R.dtype)[None], R.round()))
    keys = {tuple(m.flatten().tolist()) for m in group}
    assert len(keys) == 24
    assert all(tuple((a @ b).flatten().tolist()) in keys for a in group for b in group)


def _turned_cloud(
    seed: int, draw: Any, count: int, extents: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """``count`` float64 points ``draw(count, 3) * extents``, turned by a random ``R0`` and moved.

    Returns ``(points (count, 3), R0 (3, 3))``: the cloud's box axes are ``R0``'s columns.
    """
    g = torch.Generator().manual_seed(seed)
    R0 = random_rotation(1, generator=g, dtype=torch.float64)[0]
    local = draw(count, 3, generator=g, dtype=torch.float64) * extents
    return local @ R0.T + torch.randn(3, generator=g, dtype=torch.float64), R0


@given(seed=st.integers(0, 2**31 - 1), double=st.booleans(), size=st.floats(0.3, 1.0))
def test_box_turns_are_the_cube_groups_of_the_model_and_principal_frames(
    seed: int, double: bool, size: float
) -> None:
    dtype = torch.float64 if double else torch.float32
    extents = torch.tensor([size, 1.7 * size, 3.0 * size], dtype=torch.float64)  # distinct
    points = _turned_cloud(seed, torch.randn, 400, extents)[0].to(dtype)
    T = box_turns(points)
    assert T.dtype == dtype and 23 <= len(T) <= 46
    T = T.double()
    R = T[:, :3, :3]
    tol = 1e-4 if double else 1e-3
    eye = torch.eye(3, dtype=torch.float64).expand(len(T), 3, 3)
    torch.testing.assert_close(R @ R.transpose(1, 2), eye, atol=tol, rtol=0)
    # each keeps the centroid
    centre = points.double().mean(0)
    torch.testing.assert_close(R @ centre + T[:, :3, 3], centre.expand(len(T), 3),
                               atol=10 * tol, rtol=0)  # fmt: skip
    _cube_group(R[:23])  # the model frame's turns
    # the rest are the principal frame's, none within 5 degrees of a model-frame turn
    _, axes = torch.linalg.eigh(torch.cov(points.double().T))
    principal = axes.T @ R[23:] @ axes
    assert torch.allclose(principal.abs().sum(-1), torch.ones_like(principal[..., 0]), atol=1e-3)
    assert bool((rotation_angle_error(R[23:, None], R[None, :23]) >= 5.0).all())
    # a box on the model's axes has one frame only
    corners = torch.cartesian_prod(*[torch.stack((-e, e)) for e in extents]).to(dtype)
    assert len(box_turns(corners)) == 23


def test_box_turns_need_three_points() -> None:
    with pytest.raises(ValueRangeError, match="at least 3"):
        box_turns(torch.zeros(2, 3))


@given(seed=st.integers(0, 2**31 - 1), double=st.booleans(), size=st.floats(0.02, 1.0))
def test_box_slides_shift_along_the_principal_axes_by_fractions_of_the_extent(
    seed: int, double: bool, size: float
) -> None:
    dtype = torch.float64 if double else torch.float32
    extents = torch.tensor([3.0 * size, size, 1.7 * size], dtype=torch.float64)  # distinct
    uniform = lambda *shape, **kw: torch.rand(*shape, **kw) - 0.5  # noqa: E731
    points, R0 = _turned_cloud(seed, uniform, 600, extents)
    points = points.to(dtype)
    T = box_slides(points, (0.25, 0.5))
    assert T.dtype == dtype and T.shape == (12, 4, 4)
    T = T.double()
    eye = torch.eye(3, dtype=torch.float64).expand(12, 3, 3)
    assert torch.equal(T[:, :3, :3], eye) and torch.equal(
        T[:, 3], torch.eye(4)[3].double().expand(12, 4)
    )
    shift = T[:, :3, 3].reshape(3, 2, 2, 3)  # (axis, fraction, sign, xyz)
    torch.testing.assert_close(shift[:, :, 0], -shift[:, :, 1])  # either way
    torch.testing.assert_close(shift[:, 1], 2 * shift[:, 0], atol=1e-6 * size, rtol=1e-4)
    # along the principal axes, largest extent first, by the extent of the points along them
    centred = points.double() - points.double().mean(0)
    directions = []
    for a, axis in enumerate((0, 2, 1)):  # the sample's axes: near the box's (a few degrees)
        step = shift[a, 1, 0]  # half the extent
        direction = step / step.norm()
        assert (direction @ R0[:, axis]).abs() > math.cos(math.radians(8))
        along = centred @ direction
        tol = 1e-6 if double else 1e-3
        torch.testing.assert_close(step.norm(), (along.max() - along.min()) / 2, rtol=tol, atol=0)
        directions.append(direction)
    D = torch.stack(directions)
    torch.testing.assert_close(D @ D.T, torch.eye(3, dtype=torch.float64), atol=1e-4, rtol=0)
    assert box_slides(points, ()).shape == (0, 4, 4)


def test_box_slides_check_their_arguments() -> None:
    with pytest.raises(ValueRangeError, match="at least 3"):
        box_slides(torch.zeros(2, 3))
    for bad in ((0.0,), (1.5,), (-0.25,)):
        with pytest.raises(ValueRangeError, match="fractions"):
            box_slides(torch.randn(10, 3), bad)
