"""Depth back-projection and projection between camera-frame points and pixels.

Pixel convention (the OpenCV / BOP back-projection convention): the integer pixel ``(u, v)``
(column ``u``, row ``v``) is the *centre* of that pixel and back-projects to
``z * K^-1 [u, v, 1]^T``; :func:`project_points` is its exact inverse. A pixel covers
``[u - 0.5, u + 0.5] x [v - 0.5, v + 0.5]`` in continuous image coordinates, the coordinates
in which crop boxes are given (:mod:`poseflow.geometry.crops`). ``poseflow.render`` casts its
rays through the same points.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from poseflow._checks import check_mask, check_same, check_tensor
from poseflow.errors import ShapeError, ValueRangeError

__all__ = ["BackprojectedCloud", "backproject_depth", "project_points"]


class BackprojectedCloud(NamedTuple):
    """Points lifted from a depth map, padded, with the pixel each came from.

    Attributes:
        points: camera-frame points in metres, ``(B, M, 3)``; zeros where not valid.
        mask: ``(B, M)`` bool, True for real points.
        pixels: ``(B, M, 2)`` int64 ``(u, v)`` = (column, row) of each point's pixel; zeros where
            not valid. ``image[b, :, v, u]`` is the colour of ``points[b, m]``.
    """

    points: torch.Tensor
    mask: torch.Tensor
    pixels: torch.Tensor


def _expand_K(K: torch.Tensor, B: int, name: str = "K") -> torch.Tensor:
    if K.dim() == 2:
        check_tensor(K, name, (3, 3), finite=True)
        return K.unsqueeze(0).expand(B, 3, 3)
    check_tensor(K, name, (B, 3, 3), finite=True)
    return K


def backproject_depth(
    depth: torch.Tensor,
    K: torch.Tensor,
    mask: torch.Tensor | None = None,
    *,
    depth_scale: float = 1.0,
    max_points: int | None = None,
    generator: torch.Generator | None = None,
) -> BackprojectedCloud:
    """Lift the valid pixels of depth maps to camera-frame points, keeping their pixels.

    A pixel is used when it is inside ``mask`` and its depth is finite and positive. Points come
    in raster order (row by row). ``M`` is the largest number of points in the batch (or
    ``max_points``); shorter clouds are padded.

    Args:
        depth: depth maps ``(B, H, W)``, float or integer (e.g. BOP's uint16 PNG values).
        K: intrinsics ``(B, 3, 3)`` or ``(3, 3)``, floating; the output dtype is ``K``'s.
        mask: ``(B, H, W)`` bool instance masks, or None for every pixel.
        depth_scale: factor turning depth values into metres. For a BOP depth PNG this is
            ``scene_camera['depth_scale'] / 1000`` (BOP values times depth_scale are mm).
        max_points: keep at most this many points per image, drawn uniformly at random without
            replacement (with ``generator``) and returned in raster order.
        generator: seeded generator for the ``max_points`` subsampling.

    Returns:
        A :class:`BackprojectedCloud` ``(points (B, M, 3), mask (B, M), pixels (B, M, 2))``.

    Raises:
        ShapeError: wrong shapes, dtypes or devices.
        ValueRangeError: non-positive ``depth_scale`` or ``max_points``, non-finite ``K``.

    Example:
        >>> K = torch.tensor([[100.0, 0.0, 1.0], [0.0, 100.0, 1.0], [0.0, 0.0, 1.0]])
        >>> depth = torch.zeros(1, 2, 3); depth[0, 1, 2] = 2.0
        >>> cloud = backproject_depth(depth, K)
        >>> cloud.points, cloud.pixels
        (tensor([[[0.0200, 0.0000, 2.0000]]]), tensor([[[2, 1]]]))
    """
    sizes = check_tensor(depth, "depth", ("B", "H", "W"), floating=False)
    B, W = sizes["B"], sizes["W"]
    if not K.is_floating_point():
        raise ShapeError(f"K must be a floating-point tensor, got {K.dtype}")
    Kb = _expand_K(K, B)
    check_same(("depth", depth), ("K", Kb), dtype=False)
    if mask is not None:
        check_mask(mask, "mask", ("B", "H", "W"), sizes)
        check_same(("depth", depth), ("mask", mask), dtype=False)
    if not depth_scale > 0:
        raise ValueRangeError(f"depth_scale must be positive, got {depth_scale}")
    if max_points is not None and (isinstance(max_points, bool) or max_points < 1):
        raise ValueRangeError(f"max_points must be a positive integer, got {max_points!r}")
    dtype, device = Kb.dtype, depth.device
    b_idx, p_idx, z = _valid_depths(depth, mask, dtype, depth_scale)
    counts = torch.bincount(b_idx, minlength=B)
    if max_points is not None and bool((counts > max_points).any()):
        chosen = _random_subset(b_idx, counts, max_points, generator)
        b_idx, p_idx, z = b_idx[chosen], p_idx[chosen], z[chosen]
        counts = torch.bincount(b_idx, minlength=B)
    M = int(counts.max()) if B else 0
    slot = torch.arange(b_idx.numel(), device=device) - (torch.cumsum(counts, 0) - counts)[b_idx]
    u = p_idx % W
    v = torch.div(p_idx, W, rounding_mode="floor")
    points = torch.zeros(B, M, 3, dtype=dtype, device=device)
    points[b_idx, slot] = _lift(u, v, z, Kb[b_idx])
    pixels = torch.zeros(B, M, 2, dtype=torch.long, device=device)
    pixels[b_idx, slot] = torch.stack([u, v], dim=1)
    out_mask = torch.arange(M, device=device).unsqueeze(0) < counts.unsqueeze(1)
    return BackprojectedCloud(points, out_mask, pixels)


def _valid_depths(
    depth: torch.Tensor, mask: torch.Tensor | None, dtype: torch.dtype, depth_scale: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Image ``(P,)``, flat pixel index ``(P,)`` and depth in metres ``(P,)`` of each usable pixel.

    Usable: inside ``mask`` (``(B, H, W)`` or None) with a finite positive depth; raster order.
    """
    flat = depth.flatten(1)  # a view, also for a depth map expanded over instances
    # gather depth only where the (sparse) masks are set; never materialise B full depth maps
    source = mask.flatten(1) if mask is not None else torch.ones_like(flat, dtype=torch.bool)
    b_idx, p_idx = source.nonzero(as_tuple=True)
    z = flat[b_idx, p_idx].to(dtype) * depth_scale
    ok = torch.isfinite(z) & (z > 0)
    return b_idx[ok], p_idx[ok], z[ok]


def _random_subset(
    b_idx: torch.Tensor, counts: torch.Tensor, max_points: int, generator: torch.Generator | None
) -> torch.Tensor:
    """Positions of at most ``max_points`` entries per image, drawn uniformly, in raster order.

    ``b_idx`` ``(P,)`` holds each entry's image in ascending order, ``counts`` ``(B,)`` the
    entries of each image.
    """
    device = b_idx.device
    r = torch.rand(b_idx.numel(), generator=generator, dtype=torch.float64, device=device)
    order = torch.argsort(b_idx.to(torch.float64) + r)  # by image, then at random
    starts = torch.cumsum(counts, 0) - counts
    rank = torch.arange(order.numel(), device=device) - starts[b_idx[order]]
    return torch.sort(order[rank < max_points]).values  # back to raster order


def _lift(u: torch.Tensor, v: torch.Tensor, z: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Camera-frame points ``(P, 3)`` of pixels ``(u, v)`` ``(P,)`` at depths ``z`` ``(P,)``.

    ``K`` ``(P, 3, 3)`` holds each pixel's intrinsics (skew included); the dtype is ``K``'s.
    """
    fx, fy, cx, cy, s = K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], K[:, 0, 1]
    y = (v.to(K.dtype) - cy) / fy
    x = (u.to(K.dtype) - cx - s * y) / fx
    return torch.stack([x * z, y * z, z], dim=1)


def project_points(
    points: torch.Tensor, K: torch.Tensor, mask: torch.Tensor | None = None
) -> torch.Tensor:
    """Project camera-frame points to pixel coordinates (inverse of :func:`backproject_depth`).

    Args:
        points: points ``(B, N, 3)`` with positive z at valid entries.
        K: intrinsics ``(B, 3, 3)`` or ``(3, 3)``.
        mask: optional ``(B, N)`` bool; masked-out points project to ``(0, 0)``.

    Returns:
        ``(u, v)`` pixel coordinates, ``(B, N, 2)``, in the pixel-centre convention.

    Raises:
        ShapeError: wrong shapes, dtypes or devices.
        ValueRangeError: a valid point has ``z <= 0`` or is not finite.

    Example:
        >>> K = torch.tensor([[100.0, 0.0, 1.0], [0.0, 100.0, 1.0], [0.0, 0.0, 1.0]])
        >>> project_points(torch.tensor([[[0.02, 0.0, 2.0]]]), K)
        tensor([[[2., 1.]]])
    """
    sizes = check_tensor(points, "points", ("B", "N", 3))
    Kb = _expand_K(K, sizes["B"])
    check_same(("points", points), ("K", Kb))
    if mask is not None:
        check_mask(mask, "mask", ("B", "N"), sizes)
        points = torch.where(mask.unsqueeze(-1), points, torch.ones_like(points))
    if points.numel() and not bool(torch.isfinite(points).all()):
        raise ValueRangeError("points contain NaN or inf")
    if points.numel() and not bool((points[..., 2] > 0).all()):
        raise ValueRangeError("cannot project points with z <= 0 (behind the camera)")
    p = points @ Kb.transpose(1, 2)
    uv = p[..., :2] / p[..., 2:3]
    if mask is not None:
        uv = uv.masked_fill(~mask.unsqueeze(-1), 0.0)
    return uv
