"""SE(3) algebra on batched homogeneous transforms.

Transforms are ``(..., 4, 4)`` tensors whose last row is ``[0, 0, 0, 1]``; points are
``(..., N, 3)``. Every function keeps the dtype and device of its inputs. Rotations from
axis-angle vectors and quaternions are kornia's (``kornia.geometry.conversions``), through
:func:`axis_angle_to_rotation` and :func:`quaternion_to_rotation`, which also take numpy arrays.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TypeVar

import numpy as np
import torch
from kornia.geometry.conversions import (
    axis_angle_to_rotation_matrix,
    quaternion_to_rotation_matrix,
)

from poseflow._checks import check_same, check_tensor
from poseflow.errors import DegenerateInputError, ShapeError, ValueRangeError

__all__ = [
    "axis_angle_to_rotation",
    "compose",
    "from_Rt",
    "inverse_transform",
    "quaternion_to_rotation",
    "random_rotation",
    "random_transform",
    "rotation_angle_error",
    "to_Rt",
    "transform_points",
    "translation_error",
]


#: A tensor in, a tensor out; a numpy array in, a numpy array out.
_ArrayT = TypeVar("_ArrayT", torch.Tensor, np.ndarray)


def axis_angle_to_rotation(axis_angle: _ArrayT, angle: _ArrayT | None = None) -> _ArrayT:
    """Rotation matrices from axis-angle vectors (kornia's ``axis_angle_to_rotation_matrix``).

    A vector is the unit rotation axis times the angle in radians; a positive angle turns
    counter-clockwise about the axis (right-hand rule), so ``(0, 0, a)`` is ``R_z(a)``. With
    ``angle`` given, ``axis_angle`` holds axes of any non-zero length and ``angle`` the angles
    (broadcast against them: one axis and ``(K,)`` angles give ``K`` rotations).

    Args:
        axis_angle: vectors, shape ``(*, 3)``: a floating tensor (on any device), or a numpy
            array, computed in float64.
        angle: angles in radians ``(*)``, or None (the vectors' lengths are the angles).

    Returns:
        Rotations ``(*, 3, 3)``: a tensor in the input's dtype and on its device, or a float64
        numpy array for a numpy input.

    Raises:
        ShapeError: the last dimension is not 3, or a tensor is not floating point.
        DegenerateInputError: ``angle`` given and an axis of zero length.

    Example:
        >>> R = axis_angle_to_rotation(torch.tensor([0.0, 0.0, math.pi / 2]))
        >>> R.round(decimals=6) + 0.0  # + 0.0: no -0. in the output
        tensor([[ 0., -1.,  0.],
                [ 1.,  0.,  0.],
                [ 0.,  0.,  1.]])
        >>> axis_angle_to_rotation(torch.tensor([0.0, 0.0, 2.0]), torch.tensor([0.0, 1.0])).shape
        torch.Size([2, 3, 3])
    """
    if angle is None:
        return _convert(axis_angle_to_rotation_matrix, axis_angle, "axis_angle", 3)
    numpy_in = not isinstance(axis_angle, torch.Tensor)
    axis = torch.tensor(np.asarray(axis_angle, dtype=np.float64)) if numpy_in else axis_angle
    check_tensor(axis, "axis", ("*", 3))
    norm = axis.norm(dim=-1, keepdim=True)
    if bool((norm == 0).any()):
        raise DegenerateInputError("rotation axes must have non-zero length")
    theta = torch.as_tensor(np.asarray(angle) if numpy_in else angle).to(axis)
    R = axis_angle_to_rotation_matrix(axis / norm * theta[..., None])
    return R.numpy() if numpy_in else R


def quaternion_to_rotation(quaternion: _ArrayT) -> _ArrayT:
    """Rotation matrices from quaternions (kornia's ``quaternion_to_rotation_matrix``).

    A quaternion is ``(w, x, y, z)``, the real part first, as in kornia. It need not have unit
    norm (it is normalised first), and ``q`` and ``-q`` give the same rotation. Tensors and numpy
    arrays are handled as by :func:`axis_angle_to_rotation`.

    Args:
        quaternion: quaternions, shape ``(*, 4)``.

    Returns:
        Rotations, shape ``(*, 3, 3)``.

    Raises:
        ShapeError: the last dimension is not 4, or a tensor is not floating point.

    Example:
        >>> quaternion_to_rotation(torch.tensor([[1.0, 0.0, 0.0, 0.0]]))[0]
        tensor([[1., 0., 0.],
                [0., 1., 0.],
                [0., 0., 1.]])
    """
    return _convert(quaternion_to_rotation_matrix, quaternion, "quaternion", 4)


def _convert(
    fn: Callable[[torch.Tensor], torch.Tensor], x: _ArrayT, name: str, size: int
) -> _ArrayT:
    """Apply a kornia conversion to a tensor, or to a numpy array in float64."""
    if isinstance(x, torch.Tensor):
        check_tensor(x, name, ("*", size))
        return fn(x)
    x64 = torch.tensor(np.asarray(x, dtype=np.float64))
    check_tensor(x64, name, ("*", size))
    return fn(x64).numpy()


def from_Rt(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Assemble homogeneous transforms from rotations and translations.

    Args:
        R: rotations, shape ``(*, 3, 3)``.
        t: translations, shape ``(*, 3)``.

    Returns:
        Transforms of shape ``(*, 4, 4)``.

    Example:
        >>> from_Rt(torch.eye(3)[None], torch.tensor([[1.0, 2.0, 3.0]]))[0, :3, 3]
        tensor([1., 2., 3.])
    """
    check_tensor(R, "R", ("*", 3, 3))
    check_tensor(t, "t", ("*", 3))
    check_same(("R", R), ("t", t))
    if R.shape[:-2] != t.shape[:-1]:
        raise ShapeError(f"R {tuple(R.shape)} and t {tuple(t.shape)} have different batch shapes")
    T = torch.zeros(*R.shape[:-2], 4, 4, dtype=R.dtype, device=R.device)
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1
    return T


def to_Rt(T: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Split transforms ``(*, 4, 4)`` into rotations ``(*, 3, 3)`` and translations ``(*, 3)``.

    Example:
        >>> R, t = to_Rt(torch.eye(4)[None])
        >>> R.shape, t.shape
        (torch.Size([1, 3, 3]), torch.Size([1, 3]))
    """
    check_tensor(T, "T", ("*", 4, 4))
    return T[..., :3, :3], T[..., :3, 3]


def transform_points(T: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply rigid transforms to point sets: ``R @ p + t`` for every point.

    Args:
        T: transforms, shape ``(B, 4, 4)`` (or any leading shape matching ``points``).
        points: points, shape ``(B, N, 3)``.

    Returns:
        Transformed points, shape ``(B, N, 3)``.

    Example:
        >>> T = from_Rt(torch.eye(3)[None], torch.ones(1, 3))
        >>> transform_points(T, torch.zeros(1, 2, 3))
        tensor([[[1., 1., 1.],
                 [1., 1., 1.]]])
    """
    check_tensor(T, "T", ("*", 4, 4))
    check_tensor(points, "points", ("*", None, 3))
    check_same(("T", T), ("points", points))
    R, t = T[..., :3, :3], T[..., :3, 3]
    return points @ R.transpose(-1, -2) + t.unsqueeze(-2)


def inverse_transform(T: torch.Tensor) -> torch.Tensor:
    """Invert rigid transforms in closed form (``R^T, -R^T t``).

    Args:
        T: rigid transforms, shape ``(*, 4, 4)``.

    Returns:
        The inverses, shape ``(*, 4, 4)``.

    Example:
        >>> T = from_Rt(torch.eye(3)[None], torch.tensor([[1.0, 0.0, 0.0]]))
        >>> inverse_transform(T)[0, :3, 3]
        tensor([-1., -0., -0.])
    """
    check_tensor(T, "T", ("*", 4, 4))
    R, t = T[..., :3, :3], T[..., :3, 3]
    Rt = R.transpose(-1, -2)
    return from_Rt(Rt, -(Rt @ t.unsqueeze(-1)).squeeze(-1))


def compose(*transforms: torch.Tensor) -> torch.Tensor:
    """Compose transforms left to right as matrices: ``compose(A, B) = A @ B`` (B applied first).

    Example:
        >>> compose(torch.eye(4)[None], torch.eye(4)[None]).shape
        torch.Size([1, 4, 4])
    """
    if not transforms:
        raise ValueRangeError("compose needs at least one transform")
    out = transforms[0]
    check_tensor(out, "transforms[0]", ("*", 4, 4))
    for i, T in enumerate(transforms[1:], 1):
        check_tensor(T, f"transforms[{i}]", ("*", 4, 4))
        check_same(("transforms[0]", out), (f"transforms[{i}]", T))
        out = out @ T
    return out


def rotation_angle_error(
    R1: torch.Tensor, R2: torch.Tensor, *, degrees: bool = True
) -> torch.Tensor:
    """Geodesic angle between rotations, ``arccos((tr(R1^T R2) - 1) / 2)``.

    Args:
        R1: rotations ``(*, 3, 3)`` (or transforms ``(*, 4, 4)``; the rotation block is used).
        R2: rotations with the same shape as ``R1``.
        degrees: return degrees (default) rather than radians.

    Returns:
        Angles of shape ``(*)`` in ``[0, 180]`` degrees (or ``[0, pi]``).

    Example:
        >>> rotation_angle_error(torch.eye(3)[None], torch.eye(3)[None])
        tensor([0.])
    """
    R1 = R1[..., :3, :3]
    R2 = R2[..., :3, :3]
    check_tensor(R1, "R1", ("*", 3, 3))
    check_tensor(R2, "R2", ("*", 3, 3))
    check_same(("R1", R1), ("R2", R2))
    cos = ((R1.transpose(-1, -2) * R2.transpose(-1, -2)).sum((-1, -2)) - 1) / 2  # tr(R1^T R2)
    # atan2 of the rotation's sine and cosine is accurate near 0 and pi, unlike arccos.
    rel = R1.transpose(-1, -2) @ R2
    skew = torch.stack(
        (
            rel[..., 2, 1] - rel[..., 1, 2],
            rel[..., 0, 2] - rel[..., 2, 0],
            rel[..., 1, 0] - rel[..., 0, 1],
        ),
        -1,
    )
    angle = torch.atan2(skew.norm(dim=-1) / 2, cos)
    return torch.rad2deg(angle) if degrees else angle


def translation_error(t1: torch.Tensor, t2: torch.Tensor) -> torch.Tensor:
    """Euclidean distance between translations ``(*, 3)`` (or those of transforms ``(*, 4, 4)``).

    Example:
        >>> translation_error(torch.zeros(1, 3), torch.tensor([[3.0, 4.0, 0.0]]))
        tensor([5.])
    """
    if t1.dim() >= 2 and t1.shape[-2:] == (4, 4):
        check_tensor(t2, "t2", ("*", 4, 4))
        t1, t2 = t1[..., :3, 3], t2[..., :3, 3]
    check_tensor(t1, "t1", ("*", 3))
    check_tensor(t2, "t2", ("*", 3))
    check_same(("t1", t1), ("t2", t2))
    return (t1 - t2).norm(dim=-1)


def random_rotation(
    B: int,
    *,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """Draw rotations uniformly on SO(3) (normalised Gaussian quaternions).

    Args:
        B: number of rotations.
        generator: optional seeded generator (on ``device``) for reproducible draws.
        dtype: output dtype.
        device: output device (defaults to the generator's, else CPU).

    Returns:
        Rotations of shape ``(B, 3, 3)`` with determinant +1.

    Example:
        >>> R = random_rotation(4, generator=torch.Generator().manual_seed(0))
        >>> torch.allclose(R @ R.transpose(1, 2), torch.eye(3).expand(4, 3, 3), atol=1e-6)
        True
    """
    if device is None:
        device = generator.device if generator is not None else "cpu"
    q = torch.randn(B, 4, generator=generator, dtype=torch.float64, device=device)
    return quaternion_to_rotation(q).to(dtype)


def random_transform(
    B: int,
    *,
    max_angle: float = math.pi,
    max_translation: float = 1.0,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """Draw rigid transforms with a bounded rotation angle and translation norm.

    Rotation axes are uniform on the sphere and angles uniform in ``[0, max_angle]``; translations
    are uniform in the ball of radius ``max_translation``.

    Returns:
        Transforms of shape ``(B, 4, 4)``.

    Example:
        >>> T = random_transform(3, max_angle=0.1, generator=torch.Generator().manual_seed(0))
        >>> angle = rotation_angle_error(T, torch.eye(4).expand(3, 4, 4), degrees=False)
        >>> bool((angle <= 0.1).all())
        True
    """
    if device is None:
        device = generator.device if generator is not None else "cpu"
    kw = {"generator": generator, "dtype": torch.float64, "device": device}
    axis = torch.randn(B, 3, **kw)
    axis = axis / axis.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    R = axis_angle_to_rotation(axis * (torch.rand(B, 1, **kw) * max_angle))
    direction = torch.randn(B, 3, **kw)
    direction = direction / direction.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    t = direction * torch.rand(B, 1, **kw).pow(1 / 3) * max_translation
    return from_Rt(R, t).to(dtype)
