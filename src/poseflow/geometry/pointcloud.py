"""Point-cloud primitives: statistical outlier removal and exact diameters; re-exports the rest.

Batched clouds of different sizes are padded to a common length with a ``(B, N)`` bool mask
(True = valid). Padded points hold zeros. The other primitives live in their own modules and are
importable from here too: back-projection and projection (:mod:`poseflow.geometry.projection`),
crops (:mod:`poseflow.geometry.crops`), subsampling (:mod:`poseflow.geometry.sampling`) and
normals (:mod:`poseflow.geometry.normals`).
"""

from __future__ import annotations

import numpy as np
import torch

from poseflow._checks import check_mask, check_tensor
from poseflow.errors import ValueRangeError
from poseflow.geometry.crops import crop_box_around, crop_resize, crop_to_pixels, pixels_to_crop
from poseflow.geometry.neighbors import NeighborIndex
from poseflow.geometry.normals import estimate_normals
from poseflow.geometry.projection import BackprojectedCloud, backproject_depth, project_points
from poseflow.geometry.sampling import farthest_point_sample, voxel_downsample

__all__ = [
    "BackprojectedCloud",
    "backproject_depth",
    "cloud_diameter",
    "crop_box_around",
    "crop_resize",
    "crop_to_pixels",
    "estimate_normals",
    "farthest_point_sample",
    "pixels_to_crop",
    "project_points",
    "remove_statistical_outliers",
    "voxel_downsample",
]


def remove_statistical_outliers(
    points: torch.Tensor,
    mask: torch.Tensor | None = None,
    *,
    k: int = 20,
    std_ratio: float = 2.0,
) -> torch.Tensor:
    """Flag points whose mean distance to their neighbours is unusually large.

    Open3D's ``remove_statistical_outlier``: for every valid point the mean distance ``d`` to
    its ``k`` nearest valid neighbours (itself included) is computed; a point is kept when
    ``d <= mean(d) + std_ratio * std(d)`` over its cloud (sample standard deviation).

    Args:
        points: clouds ``(B, N, 3)``.
        mask: ``(B, N)`` bool validity.
        k: neighbourhood size (at least 2).
        std_ratio: threshold in standard deviations.

    Returns:
        The new validity mask ``(B, N)`` bool (a subset of ``mask``).

    Example:
        >>> pts = torch.zeros(1, 50, 3); pts[0, :, 0] = torch.linspace(0, 1, 50); pts[0, -1] = 9.0
        >>> remove_statistical_outliers(pts, k=5)[0].nonzero().flatten()[-1].item()
        48
    """
    sizes = check_tensor(points, "points", ("B", "N", 3))
    B, N = sizes["B"], sizes["N"]
    if isinstance(k, bool) or not isinstance(k, int) or k < 2:
        raise ValueRangeError(f"k must be an integer >= 2, got {k!r}")
    if not std_ratio > 0:
        raise ValueRangeError(f"std_ratio must be positive, got {std_ratio}")
    if mask is None:
        mask = torch.ones(B, N, dtype=torch.bool, device=points.device)
    check_mask(mask, "mask", ("B", "N"), sizes)
    if N == 0:
        return mask.clone()
    dist, _ = NeighborIndex(points, mask).neighbors_of_valid_points(min(k, N))
    found = torch.isfinite(dist)
    d = torch.where(found, dist, 0.0).to(torch.float64).sum(-1) / found.sum(-1).clamp(min=1)
    n = mask.sum(1).to(torch.float64)
    mean = (d * mask).sum(1) / n.clamp(min=1)
    var = (((d - mean[:, None]) * mask).square()).sum(1) / (n - 1).clamp(min=1)
    thresh = mean + std_ratio * var.sqrt()
    return mask & (d <= thresh[:, None])


def cloud_diameter(
    points: torch.Tensor, mask: torch.Tensor | None = None, *, chunk: int = 4096
) -> torch.Tensor:
    """Largest distance between two valid points of each cloud (exact).

    Points that cannot be an end of a longer pair than a cheap lower bound are pruned first
    (a point ``p`` with ``|p - c| + max_q |q - c| < bound`` for the centroid ``c``), then those
    inside the convex hull of the rest (the ends of a longest pair lie on it), then the
    remaining pairs are checked in chunks of ``chunk`` rows.

    Args:
        points: clouds ``(B, N, 3)``.
        mask: ``(B, N)`` bool validity.
        chunk: rows of the pairwise-distance block computed at once.

    Returns:
        Diameters ``(B,)`` in the points' dtype (0 for clouds with fewer than 2 valid points).

    Example:
        >>> cloud_diameter(torch.tensor([[[0.0, 0, 0], [3.0, 4.0, 0], [1.0, 1.0, 0]]]))
        tensor([5.])
    """
    sizes = check_tensor(points, "points", ("B", "N", 3))
    B, N = sizes["B"], sizes["N"]
    if mask is None:
        mask = torch.ones(B, N, dtype=torch.bool, device=points.device)
    check_mask(mask, "mask", ("B", "N"), sizes)
    if not bool(torch.isfinite(points[mask]).all()):
        raise ValueRangeError("valid points contain NaN or inf")
    out = torch.zeros(B, dtype=points.dtype, device=points.device)
    for b in range(B):
        p = points[b][mask[b]].to(torch.float64)
        if p.shape[0] < 2:
            continue
        c = p.mean(0)
        r = (p - c).norm(dim=1)
        a = p[(p - p[r.argmax()]).norm(dim=1).argmax()]
        bound = (p - a).norm(dim=1).max()
        cand = _hull_points(p[r >= bound - r.max()])
        best = bound
        for s in range(0, cand.shape[0], chunk):
            best = torch.maximum(best, torch.cdist(cand[s : s + chunk], cand).max())
        out[b] = best.to(points.dtype)
    return out


def _hull_points(points: torch.Tensor) -> torch.Tensor:
    """The points ``(M, 3)`` of ``points`` ``(P, 3)`` on their convex hull, or all of them.

    Qhull's vertices and the points it found coplanar with a facet; every point when the cloud
    is small or flat (no full-dimensional hull).
    """
    if points.shape[0] < 64:
        return points
    from scipy.spatial import ConvexHull, QhullError

    try:
        hull = ConvexHull(points.cpu().numpy(), qhull_options="Qc")
    except (QhullError, ValueError):
        return points
    keep = np.union1d(hull.vertices, hull.coplanar[:, 0])
    return points[torch.from_numpy(keep).to(points.device)]
