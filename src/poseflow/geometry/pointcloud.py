"""Point-cloud primitives: depth back-projection, projection, crops, downsampling, normals.

Batched clouds of different sizes are padded to a common length with a ``(B, N)`` bool mask
(True = valid). Padded points hold zeros.

Pixel convention (the OpenCV / BOP back-projection convention): the integer pixel ``(u, v)``
(column ``u``, row ``v``) is the *centre* of that pixel and back-projects to
``z * K^-1 [u, v, 1]^T``; :func:`project_points` is its exact inverse. A pixel covers
``[u - 0.5, u + 0.5] x [v - 0.5, v + 0.5]`` in continuous image coordinates, the coordinates
in which crop boxes are given. ``poseflow.render`` casts its rays through the same points.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch

from poseflow._checks import check_mask, check_same, check_tensor
from poseflow.errors import DegenerateInputError, ShapeError, ValueRangeError
from poseflow.geometry.neighbors import nearest_neighbors

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
    B, H, W = sizes["B"], sizes["H"], sizes["W"]
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
    flat = depth.reshape(B, H * W)  # a view, also for a depth map expanded over instances
    # gather depth only where the (sparse) masks are set; never materialise B full depth maps
    source = mask.reshape(B, H * W) if mask is not None else torch.ones_like(flat, dtype=torch.bool)
    b_idx, p_idx = source.nonzero(as_tuple=True)
    zz = flat[b_idx, p_idx].to(dtype) * depth_scale
    ok = torch.isfinite(zz) & (zz > 0)
    b_idx, p_idx, zz = b_idx[ok], p_idx[ok], zz[ok]
    counts = torch.bincount(b_idx, minlength=B)
    if max_points is not None and bool((counts > max_points).any()):
        r = torch.rand(b_idx.numel(), generator=generator, dtype=torch.float64, device=device)
        order = torch.argsort(b_idx.to(torch.float64) + r)  # by image, then at random
        rank = (
            torch.arange(order.numel(), device=device)
            - (torch.cumsum(counts, 0) - counts)[b_idx[order]]
        )
        chosen = torch.sort(order[rank < max_points]).values  # back to raster order
        b_idx, p_idx, zz = b_idx[chosen], p_idx[chosen], zz[chosen]
        counts = torch.bincount(b_idx, minlength=B)
    M = int(counts.max()) if B else 0
    starts = torch.cumsum(counts, 0) - counts
    slot = torch.arange(b_idx.numel(), device=device) - starts[b_idx]
    u = p_idx % W
    v = torch.div(p_idx, W, rounding_mode="floor")
    Ki = Kb[b_idx]
    fx, fy, cx, cy, s = Ki[:, 0, 0], Ki[:, 1, 1], Ki[:, 0, 2], Ki[:, 1, 2], Ki[:, 0, 1]
    y = (v.to(dtype) - cy) / fy
    x = (u.to(dtype) - cx - s * y) / fx
    points = torch.zeros(B, M, 3, dtype=dtype, device=device)
    points[b_idx, slot] = torch.stack([x * zz, y * zz, zz], dim=1)
    pixels = torch.zeros(B, M, 2, dtype=torch.long, device=device)
    pixels[b_idx, slot] = torch.stack([u, v], dim=1)
    out_mask = torch.arange(M, device=device).unsqueeze(0) < counts.unsqueeze(1)
    return BackprojectedCloud(points, out_mask, pixels)


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


def crop_box_around(
    points: torch.Tensor,
    K: torch.Tensor,
    mask: torch.Tensor | None = None,
    *,
    margin: float = 1.1,
    min_size: float = 16.0,
) -> torch.Tensor:
    """The square image crop centred on the projection of each cloud's barycentre.

    This is the target crop of FunFlow6D's appearance encoder. The side is the smallest square
    (centred on the barycentre's projection) containing the projections of all valid points,
    times ``margin``, and at least ``min_size`` pixels. The box may extend beyond the image;
    :func:`crop_resize` fills the outside with zeros.

    Args:
        points: camera-frame clouds ``(B, N, 3)``.
        K: intrinsics ``(B, 3, 3)`` or ``(3, 3)``.
        mask: ``(B, N)`` bool validity; each cloud needs at least one valid point.
        margin: scale factor applied to the tight side length (>= 1 keeps every point inside).
        min_size: smallest side in pixels.

    Returns:
        Boxes ``(B, 4)`` as ``(x0, y0, x1, y1)`` in continuous pixel coordinates (pixel ``u``
        spans ``[u - 0.5, u + 0.5]``), with ``x1 - x0 == y1 - y0``.

    Raises:
        DegenerateInputError: a cloud has no valid point.

    Example:
        >>> K = torch.tensor([[100.0, 0.0, 50.0], [0.0, 100.0, 50.0], [0.0, 0.0, 1.0]])
        >>> pts = torch.tensor([[[-0.1, 0.0, 1.0], [0.1, 0.0, 1.0]]])
        >>> crop_box_around(pts, K, margin=1.0)  # pixels 40 and 60 lie inside
        tensor([[39.5000, 39.5000, 60.5000, 60.5000]])
    """
    sizes = check_tensor(points, "points", ("B", "N", 3))
    B = sizes["B"]
    if mask is None:
        mask = torch.ones(B, sizes["N"], dtype=torch.bool, device=points.device)
    check_mask(mask, "mask", ("B", "N"), sizes)
    if not margin > 0 or not min_size >= 0:
        raise ValueRangeError(f"need margin > 0 and min_size >= 0, got {margin}, {min_size}")
    count = mask.sum(1)
    if bool((count == 0).any()):
        bad = torch.nonzero(count == 0).flatten().tolist()
        raise DegenerateInputError(f"cannot crop around empty clouds (batch items {bad})")
    w = mask.to(points.dtype).unsqueeze(-1)
    centre = (points * w).sum(1) / count.to(points.dtype).unsqueeze(-1)
    Kb = _expand_K(K, B)
    c_uv = project_points(centre.unsqueeze(1), Kb).squeeze(1)
    uv = project_points(points, Kb, mask)
    reach = (uv - c_uv.unsqueeze(1)).abs().amax(-1).masked_fill(~mask, 0.0).amax(1)
    # +0.5: the box must cover the whole extreme pixels, not only their centres.
    half = torch.clamp((reach + 0.5) * margin, min=min_size / 2)
    return torch.cat([c_uv - half.unsqueeze(-1), c_uv + half.unsqueeze(-1)], dim=-1)


def _box_check(box: torch.Tensor, B: int) -> None:
    check_tensor(box, "box", (B, 4), finite=True)
    if bool(((box[:, 2] <= box[:, 0]) | (box[:, 3] <= box[:, 1])).any()):
        raise ValueRangeError("boxes need x1 > x0 and y1 > y0")


def pixels_to_crop(pixels: torch.Tensor, box: torch.Tensor, size: int) -> torch.Tensor:
    """Map image pixel coordinates to the pixel coordinates of a crop resized to ``size``.

    The crop of ``box`` resampled to ``size x size`` pixels (as :func:`crop_resize` does) has
    pixel ``i`` covering image coordinates ``[x0 + i s, x0 + (i + 1) s]``, ``s = (x1 - x0) / size``.

    Args:
        pixels: image coordinates ``(u, v)``, ``(B, N, 2)`` (integer pixels or float).
        box: crop boxes ``(B, 4)`` from :func:`crop_box_around`.
        size: side of the resized crop in pixels.

    Returns:
        Crop coordinates ``(B, N, 2)`` in the crop's own pixel-centre convention, in the box's
        dtype; round them to index a crop-resolution feature map.

    Example:
        >>> box = torch.tensor([[-0.5, -0.5, 9.5, 9.5]])
        >>> pixels_to_crop(torch.tensor([[[0, 0], [9, 9]]]), box, 5)
        tensor([[[-0.2500, -0.2500],
                 [ 4.2500,  4.2500]]])
    """
    sizes = check_tensor(pixels, "pixels", ("B", "N", 2), floating=False)
    _box_check(box, sizes["B"])
    scale = (box[:, 2:] - box[:, :2]) / size
    return (pixels.to(box.dtype) - box[:, None, :2]) / scale[:, None] - 0.5


def crop_to_pixels(coords: torch.Tensor, box: torch.Tensor, size: int) -> torch.Tensor:
    """Inverse of :func:`pixels_to_crop`: crop pixel coordinates to image coordinates.

    Example:
        >>> box = torch.tensor([[-0.5, -0.5, 9.5, 9.5]])
        >>> crop_to_pixels(torch.tensor([[[-0.25, 4.25]]]), box, 5)
        tensor([[[0., 9.]]])
    """
    sizes = check_tensor(coords, "coords", ("B", "N", 2))
    _box_check(box, sizes["B"])
    scale = (box[:, 2:] - box[:, :2]) / size
    return (coords + 0.5) * scale[:, None] + box[:, None, :2]


def crop_resize(
    images: torch.Tensor, box: torch.Tensor, size: int, *, mode: str = "bilinear"
) -> torch.Tensor:
    """Crop boxes out of images and resample them to ``size x size`` (zeros outside the image).

    Consistent with :func:`pixels_to_crop`: crop pixel ``(i, j)`` samples image point
    ``crop_to_pixels((i, j))``.

    Args:
        images: ``(B, C, H, W)`` floating images.
        box: ``(B, 4)`` boxes ``(x0, y0, x1, y1)``.
        size: output side in pixels.
        mode: ``"bilinear"`` or ``"nearest"`` (``torch.nn.functional.grid_sample`` modes).

    Returns:
        Crops ``(B, C, size, size)``.

    Example:
        >>> img = torch.arange(16.0).reshape(1, 1, 4, 4)
        >>> crop_resize(img, torch.tensor([[1.5, 1.5, 3.5, 3.5]]), 2)
        tensor([[[[10., 11.],
                  [14., 15.]]]])
    """
    sizes = check_tensor(images, "images", ("B", None, "H", "W"))
    _box_check(box, sizes["B"])
    check_same(("images", images), ("box", box))
    if size < 1:
        raise ValueRangeError(f"size must be >= 1, got {size}")
    H, W = sizes["H"], sizes["W"]
    i = torch.arange(size, dtype=box.dtype, device=box.device)
    scale = (box[:, 2:] - box[:, :2]) / size  # (B, 2)
    xs = (i[None] + 0.5) * scale[:, :1] + box[:, :1]  # (B, size) image u of crop columns
    ys = (i[None] + 0.5) * scale[:, 1:] + box[:, 1:2]
    gx = (xs + 0.5) / W * 2 - 1  # grid_sample, align_corners=False: pixel u at (2u + 1) / W - 1
    gy = (ys + 0.5) / H * 2 - 1
    grid = torch.stack(
        [gx[:, None, :].expand(-1, size, -1), gy[:, :, None].expand(-1, -1, size)], dim=-1
    )
    return torch.nn.functional.grid_sample(
        images, grid, mode=mode, padding_mode="zeros", align_corners=False
    )


def _lexicographic_codes(keys: torch.Tensor) -> torch.Tensor:
    """One int64 per row of integer ``keys`` ``(M, K)`` that orders as the rows do.

    Sorting these codes sorts the rows lexicographically, and equal rows get equal codes, so one
    1-D :func:`torch.unique` replaces ``torch.unique(keys, dim=0)`` (several times faster). Rows
    whose extents do not fit in 63 bits keep the row-wise unique's order through their ranks.
    """
    low = keys.min(0).values
    span = keys.max(0).values - low + 1
    if float(torch.prod(span.double())) >= 2.0**62:
        _, ranks = torch.unique(keys, dim=0, return_inverse=True)
        return ranks
    code = torch.zeros(len(keys), dtype=torch.long, device=keys.device)
    for column, size in zip((keys - low).unbind(1), span.tolist()):
        code = code * size + column
    return code


def voxel_downsample(
    points: torch.Tensor, voxel_size: float, mask: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Keep one point per occupied voxel: the one closest to the voxel's centroid.

    Returning indices (not centroids) keeps every per-point attribute (pixel, colour, feature)
    attached. Voxels are the cells of a grid of side ``voxel_size`` anchored at the origin.

    Args:
        points: clouds ``(B, N, 3)``.
        voxel_size: grid cell side in metres, > 0.
        mask: ``(B, N)`` bool validity.

    Returns:
        ``(idx, valid)``: ``idx (B, M)`` int64 indices into ``N`` of the kept points, grouped by
        voxel in lexicographic voxel order, and ``valid (B, M)`` bool; ``M`` is the largest
        number of occupied voxels in the batch. Invalid slots hold index 0.

    Example:
        >>> pts = torch.tensor([[[0.01, 0.0, 0.0], [0.02, 0.0, 0.0], [0.31, 0.0, 0.0]]])
        >>> voxel_downsample(pts, 0.1)
        (tensor([[0, 2]]), tensor([[True, True]]))
    """
    sizes = check_tensor(points, "points", ("B", "N", 3))
    B, N = sizes["B"], sizes["N"]
    device = points.device
    if not voxel_size > 0:
        raise ValueRangeError(f"voxel_size must be positive, got {voxel_size}")
    if mask is None:
        mask = torch.ones(B, N, dtype=torch.bool, device=device)
    check_mask(mask, "mask", ("B", "N"), sizes)
    if not bool(torch.isfinite(points[mask]).all()):
        raise ValueRangeError("valid points contain NaN or inf")
    b_idx, n_idx = mask.nonzero(as_tuple=True)
    if b_idx.numel() == 0:
        empty = torch.zeros(B, 0, dtype=torch.long, device=device)
        return empty, empty.bool()
    p = points[b_idx, n_idx]
    cell = torch.floor(p / voxel_size).long()
    keys = torch.cat([b_idx[:, None], cell], dim=1)
    _, inverse = torch.unique(_lexicographic_codes(keys), return_inverse=True)
    V = int(inverse.max()) + 1
    ones = torch.ones(p.shape[0], dtype=p.dtype, device=device)
    count = torch.zeros(V, dtype=p.dtype, device=device).index_add_(0, inverse, ones)
    centroid = torch.zeros(V, 3, dtype=p.dtype, device=device).index_add_(0, inverse, p)
    centroid = centroid / count[:, None]
    dist = (p - centroid[inverse]).square().sum(1)
    best = torch.full((V,), torch.inf, dtype=p.dtype, device=device)
    best = best.scatter_reduce(0, inverse, dist, reduce="amin")
    cand = torch.where(dist == best[inverse], n_idx, torch.full_like(n_idx, N))
    chosen = torch.full((V,), N, dtype=torch.long, device=device)
    chosen = chosen.scatter_reduce(0, inverse, cand, reduce="amin")
    vb = torch.zeros(V, dtype=torch.long, device=device).scatter_(0, inverse, b_idx)  # batch
    per_batch = torch.bincount(vb, minlength=B)
    M = int(per_batch.max())
    starts = torch.cumsum(per_batch, 0) - per_batch
    slot = torch.arange(V, device=device) - starts[vb]
    idx = torch.zeros(B, M, dtype=torch.long, device=device)
    idx[vb, slot] = chosen
    valid = torch.arange(M, device=device)[None] < per_batch[:, None]
    return idx, valid


def farthest_point_sample(
    points: torch.Tensor,
    M: int,
    mask: torch.Tensor | None = None,
    *,
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Farthest-point sampling of ``M`` points per cloud, batched.

    Starts from a valid point drawn with ``generator`` (the first valid point when None), then
    repeatedly adds the valid point farthest from those already chosen (the one of smallest
    index among equally far points).

    float32 and float64 clouds on the CPU go through a compiled kernel (numba; see
    ``poseflow.geometry._fps_cpu``) that skips the parts of a cloud a new sample cannot change;
    other devices and dtypes run a loop of batched tensor ops over the samples. Both give the
    same indices. The kernel is compiled on its first use in an environment (seconds, once per
    dtype) and cached on disk.

    Args:
        points: clouds ``(B, N, 3)``.
        M: number of samples per cloud.
        mask: ``(B, N)`` bool validity.
        generator: seeded generator for the start point (deterministic given the seed).

    Returns:
        ``(idx, valid)``: ``idx (B, M)`` int64 indices into ``N`` and ``valid (B, M)`` bool.
        A cloud with ``n < M`` valid points has its ``n`` points in the first ``n`` slots (all
        distinct) and ``valid`` False after them (their index repeats a chosen one).

    Example:
        >>> pts = torch.tensor([[[0.0, 0, 0], [0.1, 0, 0], [1.0, 0, 0], [0.5, 0, 0]]])
        >>> farthest_point_sample(pts, 3)
        (tensor([[0, 2, 3]]), tensor([[True, True, True]]))
    """
    sizes = check_tensor(points, "points", ("B", "N", 3))
    B, N = sizes["B"], sizes["N"]
    device = points.device
    if isinstance(M, bool) or not isinstance(M, int) or M < 1:
        raise ValueRangeError(f"M must be a positive integer, got {M!r}")
    if mask is None:
        mask = torch.ones(B, N, dtype=torch.bool, device=device)
    check_mask(mask, "mask", ("B", "N"), sizes)
    if not bool(torch.isfinite(points[mask]).all()):
        raise ValueRangeError("valid points contain NaN or inf")
    count = mask.sum(1)
    if N == 0:
        empty = torch.zeros(B, M, dtype=torch.long, device=device)
        return empty, empty.bool()
    pts = torch.where(mask.unsqueeze(-1), points, torch.zeros_like(points))
    if generator is None:
        cur = mask.to(torch.int8).argmax(1)
    else:
        r = torch.rand(B, N, generator=generator, device=generator.device).to(device)
        cur = r.masked_fill(~mask, -1.0).argmax(1)
    if device.type == "cpu" and points.dtype in (torch.float32, torch.float64):
        idx = _fps_compiled(pts.detach(), mask, cur, M)
    else:
        idx = _fps_loop(pts.detach(), mask, cur, M)
    valid = torch.arange(M, device=device)[None] < count[:, None]
    # slots past a cloud's size repeat its first sample, so gathering stays well defined
    idx = torch.where(valid, idx, idx[:, :1])
    return idx, valid


def _fps_compiled(
    pts: torch.Tensor, mask: torch.Tensor, start: torch.Tensor, M: int
) -> torch.Tensor:
    """:func:`_fps_loop`'s indices from the compiled CPU kernel (``poseflow.geometry._fps_cpu``).

    Args:
        pts: CPU clouds ``(B, N, 3)``, float32 or float64, zero at masked points.
        mask: ``(B, N)`` bool validity.
        start: ``(B,)`` int64 first sample of each cloud.
        M: number of samples.

    Returns:
        ``(B, M)`` int64 indices, equal to :func:`_fps_loop`'s.
    """
    from poseflow.geometry._fps_cpu import fps_kernel

    x, y, z = (pts[..., c].contiguous().numpy() for c in range(3))
    idx = np.zeros((pts.shape[0], M), dtype=np.int64)
    fps_kernel(x, y, z, mask.contiguous().numpy(), start.contiguous().numpy(), idx)
    return torch.from_numpy(idx)


def _fps_loop(pts: torch.Tensor, mask: torch.Tensor, start: torch.Tensor, M: int) -> torch.Tensor:
    """Farthest-point sampling as a loop of batched tensor ops over the samples (any device).

    Args:
        pts: clouds ``(B, N, 3)``, zero at masked points.
        mask: ``(B, N)`` bool validity.
        start: ``(B,)`` int64 first sample of each cloud.
        M: number of samples.

    Returns:
        ``(B, M)`` int64 indices in the order they were chosen; once a cloud's valid points are
        all chosen, its further slots hold 0.
    """
    B, N = mask.shape
    device = pts.device
    idx = torch.zeros(B, M, dtype=torch.long, device=device)
    cur = start
    # One coordinate at a time with in-place ops: this loop is memory-bound, and avoiding
    # (B, N, 3) temporaries makes it several times faster than the vectorised form.
    x, y, z = (pts[..., c].contiguous() for c in range(3))
    dist = torch.full((B, N), torch.inf, dtype=pts.dtype, device=device)
    dist = dist.masked_fill(~mask, -1.0)
    d, tmp = torch.empty_like(x), torch.empty_like(x)
    rows = torch.arange(B, device=device)
    for i in range(M):
        idx[:, i] = cur
        dist[rows, cur] = -1.0
        torch.sub(x, x[rows, cur].unsqueeze(1), out=d)
        d.mul_(d)
        torch.sub(y, y[rows, cur].unsqueeze(1), out=tmp)
        d.addcmul_(tmp, tmp)
        torch.sub(z, z[rows, cur].unsqueeze(1), out=tmp)
        d.addcmul_(tmp, tmp)
        torch.minimum(dist, d, out=dist)
        cur = dist.argmax(1)
    return idx


def estimate_normals(
    points: torch.Tensor,
    mask: torch.Tensor | None = None,
    *,
    k: int = 30,
    viewpoint: torch.Tensor | tuple[float, float, float] | None = (0.0, 0.0, 0.0),
) -> torch.Tensor:
    """Unit normals by PCA over each point's ``k`` nearest valid neighbours (itself included).

    The normal is the eigenvector of the neighbourhood covariance with the smallest eigenvalue,
    turned to face ``viewpoint`` (the camera centre by default, right for camera-frame clouds).

    Args:
        points: clouds ``(B, N, 3)``.
        mask: ``(B, N)`` bool validity.
        k: neighbourhood size (at least 3).
        viewpoint: point ``(3,)`` or ``(B, 3)`` the normals should face, or None to leave the
            sign as the eigen-solver returns it.

    Returns:
        Normals ``(B, N, 3)``; zero at masked points and at points with fewer than 3 valid
        neighbours.

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> pts = torch.rand(1, 200, 3, generator=g) * torch.tensor([1.0, 1.0, 0.0]) + 2.0
        >>> n = estimate_normals(pts, k=10)
        >>> bool(torch.allclose(n[0, :, 2], torch.full((200,), -1.0), atol=1e-5))
        True
    """
    sizes = check_tensor(points, "points", ("B", "N", 3))
    B, N = sizes["B"], sizes["N"]
    if isinstance(k, bool) or not isinstance(k, int) or k < 3:
        raise ValueRangeError(f"k must be an integer >= 3, got {k!r}")
    if mask is not None:
        check_mask(mask, "mask", ("B", "N"), sizes)
    pts = points if mask is None else torch.where(mask.unsqueeze(-1), points, 0.0)
    if N == 0:
        return torch.zeros_like(points)
    dist, nn = nearest_neighbors(pts, pts, k=min(k, N), reference_mask=mask)
    found = torch.isfinite(dist)
    # one flat index_select (a gather with an expanded index is several times slower)
    rows = nn + N * torch.arange(B, device=nn.device).reshape(B, 1, 1)
    nbr64 = pts.to(torch.float64).reshape(B * N, 3)[rows.reshape(-1)].reshape(B, N, -1, 3)
    w = found.to(torch.float64).unsqueeze(-1)
    cnt = w.sum(2)
    mean = (nbr64 * w).sum(2) / cnt.clamp(min=1)
    dev = (nbr64 - mean.unsqueeze(2)) * w
    cov = dev.transpose(-1, -2) @ dev
    normals = _smallest_eigenvector(cov)
    ok = cnt.squeeze(-1) >= 3
    if mask is not None:
        ok &= mask
    if viewpoint is not None:
        vp = torch.as_tensor(viewpoint, dtype=torch.float64, device=points.device)
        vp = vp.reshape(-1, 1, 3) if vp.dim() == 2 else vp.reshape(1, 1, 3)
        flip = ((vp - pts.to(torch.float64)) * normals).sum(-1) < 0
        normals = torch.where(flip.unsqueeze(-1), -normals, normals)
    normals = torch.where(ok.unsqueeze(-1), normals, 0.0)
    return normals.to(points.dtype)


def _smallest_eigenvector(A: torch.Tensor) -> torch.Tensor:
    """Unit eigenvectors of the smallest eigenvalue of symmetric 3 x 3 matrices, in closed form.

    Eberly's non-iterative solver ("A Robust Eigensolver for 3 x 3 Symmetric Matrices", Geometric
    Tools, 2014; Open3D's normals use it too): the eigenvalues from the trigonometric solution of
    the characteristic cubic of the matrix scaled to entries in ``[-1, 1]``; the eigenvector of
    the eigenvalue farther from the other two from cross products of rows of ``A - lambda I``,
    the middle one in that vector's orthogonal complement, the third their cross product. Where
    the smallest eigenvalue is repeated, any unit vector of its eigenspace is an answer.
    Elementwise tensor work only, an order of magnitude faster than ``torch.linalg.eigh`` on
    many small matrices.

    Args:
        A: symmetric matrices ``(..., 3, 3)``.

    Returns:
        Unit vectors ``(..., 3)``, ``A v = lambda_min v``; ``(0, 0, 1)`` for multiples of the
        identity (zero included).
    """
    scale = A.abs().amax((-1, -2), keepdim=True)
    A = A / torch.where(scale > 0, scale, 1.0)
    a00, a01, a02 = A[..., 0, 0], A[..., 0, 1], A[..., 0, 2]
    a11, a12, a22 = A[..., 1, 1], A[..., 1, 2], A[..., 2, 2]
    q = (a00 + a11 + a22) / 3
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p = ((b00**2 + b11**2 + b22**2 + 2 * (a01**2 + a02**2 + a12**2)) / 6).sqrt()
    round_ = p > 0  # False: A is a multiple of the identity, every vector an eigenvector
    p_safe = torch.where(round_, p, 1.0)
    c00 = b11 * b22 - a12 * a12
    c01 = a01 * b22 - a12 * a02
    c02 = a01 * a12 - b11 * a02
    half_det = ((b00 * c00 - a01 * c01 + a02 * c02) / p_safe**3 / 2).clamp(-1.0, 1.0)
    angle = torch.acos(half_det) / 3
    beta = torch.stack(  # ascending: 2 cos(angle + 2 pi / 3) <= middle <= 2 cos(angle)
        (2 * torch.cos(angle + 2 * math.pi / 3), torch.zeros_like(angle), 2 * torch.cos(angle)),
        dim=-1,
    )
    beta[..., 1] = -(beta[..., 0] + beta[..., 2])
    lam = q.unsqueeze(-1) + p.unsqueeze(-1) * beta  # (..., 3) ascending
    # The eigenvalue farther from the other two: the largest when half_det >= 0, else the least.
    far_is_top = half_det >= 0
    far = _eigenvector_by_cross(A, torch.where(far_is_top, lam[..., 2], lam[..., 0]))
    mid = _middle_eigenvector(A, far, lam[..., 1])
    third = torch.linalg.cross(mid, far)  # for far = top: the smallest's; else unused
    v = torch.where(far_is_top.unsqueeze(-1), third, far)
    v = v / v.norm(dim=-1, keepdim=True)
    z_axis = torch.tensor([0.0, 0.0, 1.0], dtype=A.dtype, device=A.device)
    return torch.where(round_.unsqueeze(-1), v, z_axis)


def _eigenvector_by_cross(A: torch.Tensor, lam: torch.Tensor) -> torch.Tensor:
    """Unit null vector of ``A - lam I`` (rank 2): the longest cross product of two rows."""
    M = A - lam[..., None, None] * torch.eye(3, dtype=A.dtype, device=A.device)
    r0, r1, r2 = M[..., 0, :], M[..., 1, :], M[..., 2, :]
    crosses = torch.stack(
        (torch.linalg.cross(r0, r1), torch.linalg.cross(r0, r2), torch.linalg.cross(r1, r2)), -2
    )
    sq = crosses.square().sum(-1)  # (..., 3)
    best = sq.argmax(-1, keepdim=True)
    pick = crosses.gather(-2, best.unsqueeze(-1).expand(*best.shape, 3)).squeeze(-2)
    length = sq.gather(-1, best).sqrt()
    return pick / torch.where(length > 0, length, 1.0)


def _middle_eigenvector(A: torch.Tensor, w: torch.Tensor, lam: torch.Tensor) -> torch.Tensor:
    """Unit eigenvector of ``lam`` orthogonal to the unit eigenvector ``w`` (Eberly's method).

    ``A`` restricted to the plane orthogonal to ``w`` is a symmetric 2 x 2 matrix in a basis
    ``(u, v)`` of that plane; the eigenvector is the null vector of that matrix less ``lam``.
    """
    w0, w1, w2 = w[..., 0], w[..., 1], w[..., 2]
    zero = torch.zeros_like(w0)
    first = w0.abs() > w1.abs()
    u = torch.where(
        first.unsqueeze(-1),
        torch.stack((-w2, zero, w0), -1),
        torch.stack((zero, w2, -w1), -1),
    )
    u = u / u.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(A.dtype).tiny)
    v = torch.linalg.cross(w, u)
    Au, Av = (A @ u.unsqueeze(-1)).squeeze(-1), (A @ v.unsqueeze(-1)).squeeze(-1)
    m00 = (u * Au).sum(-1) - lam
    m01 = (u * Av).sum(-1)
    m11 = (v * Av).sum(-1) - lam
    # The null vector of [[m00, m01], [m01, m11]] from its larger row, (m01, -m00) or (m11, -m01).
    use_first = m00.abs() >= m11.abs()
    x = torch.where(use_first, m01, m11)
    y = torch.where(use_first, -m00, -m01)
    length = (x * x + y * y).sqrt()
    degenerate = length == 0  # lam is a double eigenvalue in that plane: any vector of it
    x = torch.where(degenerate, 1.0, x / torch.where(degenerate, 1.0, length))
    y = torch.where(degenerate, 0.0, y / torch.where(degenerate, 1.0, length))
    return x.unsqueeze(-1) * u + y.unsqueeze(-1) * v


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
    pts = torch.where(mask.unsqueeze(-1), points, 0.0)
    dist, _ = nearest_neighbors(pts, pts, k=min(k, N), reference_mask=mask)
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
    (a point ``p`` with ``|p - c| + max_q |q - c| < bound`` for the centroid ``c``), then the
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
        cand = p[r >= bound - r.max()]
        best = bound
        for s in range(0, cand.shape[0], chunk):
            best = torch.maximum(best, torch.cdist(cand[s : s + chunk], cand).max())
        out[b] = best.to(points.dtype)
    return out
