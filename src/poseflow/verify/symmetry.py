"""Near-symmetries of an object's geometry: the poses a depth-only registration confuses.

A labelled box flipped end for end, a printed can turned about its axis, a prism turned by a
third of a turn: the geometry maps (almost) onto itself, so depth and silhouette barely tell the
poses apart and only appearance can. :func:`near_symmetries` finds these transforms once per
object from its surface points, with no annotation:

1. seeds: turns about each principal axis of the points (every ``360 / turn_steps`` degrees)
   and half-turns about axes perpendicular to each principal axis (the flips), all about the
   centroid, and turns about the surface's best axis of revolution (:func:`revolution_axis`),
   which a handle or a spout moves away from the principal axes;
2. every seed is refined by ICP of the model onto itself, so a seed near a true near-symmetry
   lands on it even when that symmetry's axis is not a principal axis (a prism's flips);
3. a refined transform is kept when enough of the moved points lie on the model's surface, it is
   not (modulo the declared symmetries) the identity, and it is not a repeat of a kept one.

Declared symmetries (``models_info.json``) leave the object's look unchanged: poses that differ
by one are the same answer, so they are never returned as candidates.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Any

import torch

from poseflow._checks import check_tensor
from poseflow.errors import DegenerateInputError, ValueRangeError
from poseflow.geometry.neighbors import nearest_neighbors
from poseflow.geometry.se3 import axis_angle_to_rotation, rotation_angle_error
from poseflow.registration.icp import multi_scale_icp

__all__ = [
    "NearSymmetries",
    "box_slides",
    "box_turns",
    "near_symmetries",
    "revolution_axis",
]


@dataclass
class NearSymmetries:
    """Near-symmetry transforms of one object, most self-similar first.

    Attributes:
        transforms: ``(C, 4, 4)`` model-frame transforms ``x -> R x + t`` that map the model
            (almost) onto itself; ``pose @ transforms[c]`` is the candidate pose.
        overlap: ``(C,)`` fraction of the model's points that land on its surface.
    """

    transforms: torch.Tensor
    overlap: torch.Tensor

    def __len__(self) -> int:
        return int(self.transforms.shape[0])


def _principal_axes(points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Centroid ``(3,)`` and principal axes ``(3, 3)`` of ``points`` ``(N, 3)`` (float64, CPU).

    The axes are columns, by increasing variance.
    """
    cpu = points.detach().to("cpu", torch.float64)
    centre = cpu.mean(0)
    centred = cpu - centre
    return centre, torch.linalg.eigh(centred.T @ centred)[1]


def box_slides(points: torch.Tensor, fractions: tuple[float, ...] = (0.25, 0.5)) -> torch.Tensor:
    """Shifts of an object along its principal axes: the other starts of a global search.

    An object seen only in part (a bar half hidden behind another object) tends to be placed
    centred on the part that is seen, and ICP cannot move it along a face that slides on
    itself. Applied to a pose (``pose @ slides``), these shifts try the model at other places
    along each of its principal axes: by each fraction of its extent along that axis, either
    way (``±½`` puts the seen part at either end of the object).

    Args:
        points: surface points ``(N, 3)`` of the model, ``N >= 3``.
        fractions: the shifts, fractions of the extent, each in ``(0, 1]``.

    Returns:
        Model-frame translations ``(6 · len(fractions), 4, 4)`` in the points' dtype: for each
        principal axis (largest extent first) and fraction, the shift along it and against it.

    Example:
        >>> bar = torch.cartesian_prod(*[torch.tensor([-s, s]) for s in (0.1, 0.02, 0.01)])
        >>> box_slides(bar, (0.5,))[0, :3, 3].abs()  # half its length along its long axis
        tensor([0.1000, 0.0000, 0.0000])
    """
    check_tensor(points, "points", (None, 3), finite=True)
    if points.shape[0] < 3:
        raise ValueRangeError(f"box_slides needs at least 3 points, got {points.shape[0]}")
    if not all(0 < f <= 1 for f in fractions):
        raise ValueRangeError(f"the fractions must lie in (0, 1], got {fractions}")
    centre, axes = _principal_axes(points)
    along = (points.detach().to("cpu", torch.float64) - centre) @ axes
    extent = along.amax(0) - along.amin(0)  # (3,)
    shifts = [
        sign * f * extent[a] * axes[:, a]
        for a in (2, 1, 0)
        for f in fractions
        for sign in (1.0, -1.0)
    ]
    T = torch.eye(4, dtype=torch.float64).repeat(len(shifts), 1, 1)
    if shifts:
        T[:, :3, 3] = torch.stack(shifts)
    return T.to(dtype=points.dtype, device=points.device)


def box_turns(points: torch.Tensor, *, min_angle: float = 5.0) -> torch.Tensor:
    """The turns that map a box about the points onto itself: the starts of a global search.

    The 23 proper rotations of a cube other than the identity (the quarter and half turns
    about its axes and the turns about its diagonals), taken about the points' centroid, in
    two frames: the model's own axes (a mesh's designer usually aligns them with the object)
    and the points' principal axes; a principal-frame turn within ``min_angle`` degrees of a
    model-frame one is dropped. Applied to a pose (``pose @ turns``) they cover every
    orientation coarsely (the 24 of one frame leave no rotation farther than about 63 degrees)
    and hold the object's flips exactly.

    Args:
        points: surface points ``(N, 3)`` of the model, ``N >= 3``.
        min_angle: turns of the two frames closer than this are one.

    Returns:
        Model-frame transforms ``(T, 4, 4)`` in the points' dtype, ``23 <= T <= 46``, the
        model frame's first.

    Example:
        >>> box = torch.cartesian_prod(*[torch.tensor([-s, s]) for s in (3.0, 2.0, 1.0)])
        >>> len(box_turns(box))  # its principal axes are the model's: one frame
        23
        >>> turn = axis_angle_to_rotation(torch.tensor([1.0, 2, 3]), torch.tensor(0.5))
        >>> len(box_turns(box @ turn))
        46
    """
    check_tensor(points, "points", (None, 3), finite=True)
    if points.shape[0] < 3:
        raise ValueRangeError(f"box_turns needs at least 3 points, got {points.shape[0]}")
    dtype, device = points.dtype, points.device
    centre, axes = _principal_axes(points)
    axes = axes * torch.linalg.det(axes)  # a proper frame: columns are the principal axes
    cube = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            G = torch.zeros(3, 3, dtype=torch.float64)
            G[range(3), perm] = torch.tensor(signs, dtype=torch.float64)
            if torch.linalg.det(G) > 0 and not torch.equal(G, torch.eye(3, dtype=G.dtype)):
                cube.append(G)
    own = torch.stack(cube)  # (23, 3, 3)
    principal = axes @ own @ axes.T
    near = rotation_angle_error(principal[:, None], own[None]).amin(1) < min_angle
    R = torch.cat((own, principal[~near]))
    T = torch.eye(4, dtype=torch.float64).repeat(len(R), 1, 1)
    T[:, :3, :3] = R
    T[:, :3, 3] = centre - R @ centre
    return T.to(dtype=dtype, device=device)


def near_symmetries(
    points: torch.Tensor,
    normals: torch.Tensor,
    diameter: float,
    *,
    surface: torch.Tensor | None = None,
    declared: torch.Tensor | None = None,
    turn_steps: int = 12,
    min_overlap: float = 0.6,
    overlap_distance: float = 0.03,
    min_angle: float = 15.0,
    max_candidates: int = 12,
    icp_distances: tuple[float, ...] = (0.1, 0.05, 0.02),
    icp_iterations: int = 30,
    icp_relative_rmse: float = 1e-6,
) -> NearSymmetries:
    """Find the transforms that map an object's surface (almost) onto itself.

    Args:
        points: surface points of the model ``(N, 3)``, spread evenly (they are moved).
        normals: unit surface normals at ``points`` ``(N, 3)`` (for the axis of revolution).
        diameter: the object's diameter in the points' unit.
        surface: a denser sampling of the surface ``(M, 3)`` the moved points are matched to;
            ``points`` by default.
        declared: declared symmetries ``(S, 4, 4)`` (identity included or not); candidates equal
            to one of them up to ``min_angle``, or equal to each other modulo them, are dropped.
        turn_steps: seeds every ``360 / turn_steps`` degrees (see the module docstring).
        min_overlap: keep a transform when at least this fraction of the moved points lies
            within ``overlap_distance * diameter`` of the surface.
        overlap_distance: see ``min_overlap``, as a fraction of the diameter.
        min_angle: degrees; closer transforms count as the same.
        max_candidates: keep at most this many, the most self-similar.
        icp_distances: self-ICP correspondence distances, fractions of the diameter.
        icp_iterations: self-ICP iterations per scale, at most.
        icp_relative_rmse: a scale of self-ICP stops once its inlier RMSE changes by less than
            this (a fraction of the diameter) and its inlier count no longer changes.

    Returns:
        :class:`NearSymmetries` in the points' dtype and device.

    Raises:
        ShapeError: wrong shapes.
        DegenerateInputError: fewer than 4 points.
        ValueRangeError: a non-positive diameter or step count.

    Example:
        >>> import open3d as o3d
        >>> from poseflow.data.objects import ObjectModel
        >>> box = o3d.geometry.TriangleMesh.create_box(0.1, 0.06, 0.03)
        >>> m = ObjectModel.from_mesh(box, num_points=1024, dtype=torch.float64)
        >>> found = near_symmetries(m.points, m.normals, m.diameter, min_overlap=0.9)
        >>> len(found), [round(a) for a in rotation_angle_error(
        ...     torch.eye(3, dtype=torch.float64), found.transforms[:, :3, :3]).tolist()]
        (3, [180, 180, 180])
    """
    sizes = check_tensor(points, "points", ("N", 3), finite=True)
    check_tensor(normals, "normals", ("N", 3), finite=True, sizes=sizes)
    if points.shape[0] < 4:
        raise DegenerateInputError(f"need at least 4 points, got {points.shape[0]}")
    if not diameter > 0:
        raise ValueRangeError(f"diameter must be positive, got {diameter}")
    if isinstance(turn_steps, bool) or not isinstance(turn_steps, int) or turn_steps < 2:
        raise ValueRangeError(f"turn_steps must be an int >= 2, got {turn_steps!r}")
    dtype, device = points.dtype, points.device
    surface = points if surface is None else surface
    check_tensor(surface, "surface", ("M", 3), finite=True)
    seeds = _seeds(points, normals, turn_steps)  # (K, 4, 4)
    icp = {
        "max_correspondence_distances": [f * diameter for f in icp_distances],
        "max_iterations": icp_iterations,
        "relative_rmse": icp_relative_rmse * diameter,
    }
    T, overlap = _self_overlap(points, surface, seeds, overlap_distance * diameter, icp)
    sym = torch.eye(4, dtype=dtype, device=device)[None]
    if declared is not None:
        check_tensor(declared, "declared", ("S", 4, 4), finite=True)
        sym = torch.cat((sym, declared.to(dtype=dtype, device=device)))
    idx = _distinct(T, overlap, sym, min_overlap, min_angle, max_candidates)
    return NearSymmetries(transforms=T[idx], overlap=overlap[idx])


def _self_overlap(
    points: torch.Tensor,
    surface: torch.Tensor,
    seeds: torch.Tensor,
    distance: float,
    icp: dict[str, Any],
) -> tuple[torch.Tensor, torch.Tensor]:
    """The seeds ``(K, 4, 4)`` refined by ICP of the points onto the surface, and their overlap.

    The overlap ``(K,)`` is the fraction of the moved points within ``distance`` of the surface.
    """
    K = seeds.shape[0]
    refined = multi_scale_icp(
        points[None].expand(K, -1, -1), surface[None].expand(K, -1, -1), seeds, **icp
    )
    T = torch.where(refined.valid[:, None, None], refined.transformation, seeds)
    moved = points[None] @ T[:, :3, :3].transpose(1, 2) + T[:, None, :3, 3]
    dist, _ = nearest_neighbors(moved, surface[None].expand(K, -1, -1))
    return T, (dist[..., 0] <= distance).to(points.dtype).mean(-1)


def _distinct(
    T: torch.Tensor,
    overlap: torch.Tensor,
    sym: torch.Tensor,
    min_overlap: float,
    min_angle: float,
    max_candidates: int,
) -> torch.Tensor:
    """The transforms ``T`` ``(K, 4, 4)`` kept as candidates, most overlapping first ``(C,)``.

    Each overlaps at least ``min_overlap``, is no declared symmetry ``sym`` ``(S, 4, 4)`` (the
    identity included) and no kept one times a declared symmetry, up to ``min_angle``.
    """
    order = torch.argsort(overlap, descending=True, stable=True)
    kept: list[int] = []
    for k in order.tolist():
        if float(overlap[k]) < min_overlap or len(kept) >= max_candidates:
            break
        # equal to the identity modulo a declared symmetry: the same answer, not a candidate
        if float(rotation_angle_error(sym[:, :3, :3], T[k, :3, :3]).min()) < min_angle:
            continue
        if kept:
            # T_k ~ T_j S for a kept j and a declared S: the same candidate
            prev = T[kept][:, None, :3, :3] @ sym[None, :, :3, :3]  # (J, S, 3, 3)
            if float(rotation_angle_error(prev, T[k, :3, :3]).min()) < min_angle:
                continue
        kept.append(k)
    return torch.tensor(kept, dtype=torch.long, device=T.device)


def revolution_axis(
    points: torch.Tensor, normals: torch.Tensor, *, iterations: int = 5
) -> tuple[torch.Tensor, torch.Tensor]:
    """The line that the surface normals meet best: the axis of a surface of revolution.

    On a surface of revolution every normal line meets the axis. Writing the axis in Plücker
    coordinates (unit direction ``a``, moment ``m``), the normal line through ``p`` with
    direction ``n`` meets it when ``a . (p x n) + m . n = 0``; the axis minimising the sum of
    squares of these residuals is an eigenvector of a 3 x 3 matrix (Pottmann and Randrup's
    line-geometry fit). All normals through one point (a sphere) leave the axis undefined.
    Iteratively reweighted (Cauchy weights scaled by the median residual), so
    that a handle or a label's relief does not pull the axis.

    Args:
        points: surface points ``(N, 3)``.
        normals: unit normals at the points ``(N, 3)``.
        iterations: reweighting rounds.

    Returns:
        ``(direction (3,), point (3,))``: a unit direction and the axis point closest to the
        origin, in float64.

    Raises:
        ShapeError: wrong shapes.
        DegenerateInputError: the normals do not span 3-D (a plane), so no axis is defined.

    Example:
        >>> t = torch.linspace(0, 2 * math.pi, 200, dtype=torch.float64)[:-1]
        >>> ring = torch.stack((torch.cos(t), torch.sin(t), torch.zeros_like(t)), -1)
        >>> pts = torch.cat((ring + torch.tensor([0.0, 0.0, 0.5]), ring * 0.5)) + 3.0
        >>> nrm = torch.cat((ring, ring - torch.tensor([0.0, 0.0, 0.5])))  # a cylinder, a cone
        >>> a, c = revolution_axis(pts, torch.nn.functional.normalize(nrm, dim=-1))
        >>> a.abs().round(decimals=6).tolist(), c.round(decimals=6).abs().tolist()
        ([0.0, 0.0, 1.0], [3.0, 3.0, 0.0])
    """
    sizes = check_tensor(points, "points", ("N", 3), finite=True)
    check_tensor(normals, "normals", ("N", 3), finite=True, sizes=sizes)
    p, n = points.to(torch.float64), normals.to(torch.float64)
    pn = torch.linalg.cross(p, n)
    w = torch.ones(p.shape[0], dtype=torch.float64, device=p.device)
    a = m = None
    for _ in range(max(1, iterations)):
        A = (pn * w[:, None]).T @ pn
        Bm = (pn * w[:, None]).T @ n
        C = (n * w[:, None]).T @ n
        if float(torch.linalg.eigvalsh(C)[0]) <= 1e-9 * float(C.trace()):
            raise DegenerateInputError("the normals do not span 3-D: no axis of revolution")
        Cinv_Bt = torch.linalg.solve(C, Bm.T)
        schur = A - Bm @ Cinv_Bt
        _, vecs = torch.linalg.eigh((schur + schur.T) / 2)
        a = vecs[:, 0]
        m = -Cinv_Bt @ a
        r = (pn @ a + n @ m).abs()
        scale = r.median().clamp_min(1e-12)
        w = 1 / (1 + (r / (2 * scale)).square())
    return a, torch.linalg.cross(a, m)


def _seeds(points: torch.Tensor, normals: torch.Tensor, turn_steps: int) -> torch.Tensor:
    """Seed transforms ``(K, 4, 4)`` of the near-symmetry search.

    Turns about the principal axes and the axis of revolution; half-turns (flips) about axes
    perpendicular to the principal axes, through the centroid.
    """
    dtype, device = points.dtype, points.device
    centre = points.mean(0)
    cov = (points - centre).T @ (points - centre) / points.shape[0]
    _, axes = torch.linalg.eigh(cov.to(torch.float64))
    axes = axes.to(dtype).T  # rows: principal axes
    step = 2 * math.pi / turn_steps
    turn_angles = torch.arange(1, turn_steps, dtype=dtype, device=device) * step
    flip_angles = torch.arange(0, (turn_steps + 1) // 2, dtype=dtype, device=device) * step
    axis_list, angle_list = [], []
    for i in range(3):
        a = axes[i]
        b, c = axes[(i + 1) % 3], axes[(i + 2) % 3]
        axis_list.append(a.expand(turn_angles.shape[0], 3))
        angle_list.append(turn_angles)
        perp = torch.cos(flip_angles)[:, None] * b + torch.sin(flip_angles)[:, None] * c
        axis_list.append(perp)
        angle_list.append(torch.full_like(flip_angles, math.pi))
    pivots = [centre.expand(sum(a.shape[0] for a in axis_list), 3)]
    try:
        direction, on_axis = revolution_axis(points, normals)
    except DegenerateInputError:  # flat: the principal axes already hold its turns
        pass
    else:
        axis_list.append(direction.to(dtype).expand(turn_angles.shape[0], 3))
        angle_list.append(turn_angles)
        # pivot on the axis, at the foot of the centroid
        foot = on_axis + ((centre.to(torch.float64) - on_axis) @ direction) * direction
        pivots.append(foot.to(dtype).expand(turn_angles.shape[0], 3))
    R = axis_angle_to_rotation(torch.cat(axis_list), torch.cat(angle_list))
    pivot = torch.cat(pivots)
    T = torch.eye(4, dtype=dtype, device=device).repeat(R.shape[0], 1, 1)
    T[:, :3, :3] = R
    T[:, :3, 3] = pivot - (R @ pivot[:, :, None])[..., 0]
    return T
