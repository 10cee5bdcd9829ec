"""Point-cloud subsampling that returns indices: voxel grids and farthest-point sampling.

Indices, not new points, keep every per-point attribute (pixel, colour, feature) attached.
"""

from __future__ import annotations

import numpy as np
import torch

from poseflow._checks import check_mask, check_tensor
from poseflow.errors import ValueRangeError

__all__ = ["farthest_point_sample", "voxel_downsample"]


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


def _valid_mask(
    points: torch.Tensor, mask: torch.Tensor | None, sizes: dict[str, int]
) -> torch.Tensor:
    """The checked mask ``(B, N)`` of ``points`` ``(B, N, 3)`` (all True when None).

    Raises:
        ShapeError: ``mask`` is not a ``(B, N)`` bool tensor.
        ValueRangeError: a point under the mask is NaN or inf.
    """
    if mask is None:
        mask = torch.ones(sizes["B"], sizes["N"], dtype=torch.bool, device=points.device)
    check_mask(mask, "mask", ("B", "N"), sizes)
    if not bool(torch.isfinite(points[mask]).all()):
        raise ValueRangeError("valid points contain NaN or inf")
    return mask


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
    mask = _valid_mask(points, mask, sizes)
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
    mask = _valid_mask(points, mask, sizes)
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
