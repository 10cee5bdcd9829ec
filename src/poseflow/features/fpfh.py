"""FPFH in batched PyTorch: Open3D's ``compute_fpfh_feature`` and ``estimate_normals``.

:func:`compute_fpfh` gives Open3D's 33-bin FPFH histograms of every point of a padded batch of
clouds, and :func:`estimate_outward_normals` the normals it needs, oriented away from each cloud's
centroid; both run on CPU or CUDA in float64 inside, with no Open3D.
:class:`~poseflow.features.geometric.FPFHEncoder` turns the histograms into descriptors.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from poseflow._checks import check_mask, check_same, check_tensor
from poseflow.errors import ShapeError, ValueRangeError
from poseflow.geometry.neighbors import NeighborIndex

__all__ = ["check_clouds", "compute_fpfh", "estimate_outward_normals"]

#: Neighbour pairs whose features the torch FPFH computes at once (bounds its memory).
_PAIR_CHUNK = 1 << 14
#: FPFH bins per angle; the descriptor is three such histograms.
_BINS = 11


def _radius_table(radius: torch.Tensor | float, B: int, device: torch.device) -> torch.Tensor:
    """Radii as a float64 ``(B, S)`` table from a float, a ``(B,)`` or a ``(B, S)`` tensor."""
    if isinstance(radius, torch.Tensor):
        if radius.dim() == 0:
            radius = radius.reshape(1, 1).expand(B, 1)
        elif radius.dim() == 1:
            check_tensor(radius, "radius", (B,), finite=True)
            radius = radius[:, None]
        else:
            check_tensor(radius, "radius", (B, None), finite=True)
        table = radius.to(device=device, dtype=torch.float64)
    else:
        table = torch.full((B, 1), float(radius), dtype=torch.float64, device=device)
    if table.shape[1] == 0 or not bool((table > 0).all()):
        raise ValueRangeError(f"radius must be positive, got {table.tolist()}")
    return table


def check_clouds(
    points: torch.Tensor,
    normals: torch.Tensor | None,
    mask: torch.Tensor | None,
    *,
    finite_everywhere: bool = False,
) -> tuple[torch.Tensor, dict[str, int]]:
    """Validate a padded batch of clouds, its normals and its mask; fill in a missing mask.

    Args:
        points: clouds ``(B, P, 3)``.
        normals: their normals ``(B, P, 3)``, or None.
        mask: valid points ``(B, P)`` bool, or None (all valid).
        finite_everywhere: require finite points and normals on padded rows too; by default only
            the valid rows must be finite.

    Returns:
        ``(mask, sizes)``: the mask ``(B, P)`` and the named sizes ``{"B": B, "P": P}``.

    Raises:
        ShapeError: wrong shapes, dtypes or devices, a non-bool mask.
        ValueRangeError: NaN or inf points or normals (at valid rows, or anywhere with
            ``finite_everywhere``).
    """
    sizes = check_tensor(points, "points", ("B", "P", 3), finite=finite_everywhere)
    if normals is not None:
        check_tensor(normals, "normals", ("B", "P", 3), finite=finite_everywhere, sizes=sizes)
        check_same(("points", points), ("normals", normals))
    if mask is None:
        mask = torch.ones(points.shape[:2], dtype=torch.bool, device=points.device)
    else:
        check_mask(mask, "mask", ("B", "P"), sizes)
        check_same(("points", points), ("mask", mask), dtype=False)
    if not finite_everywhere:
        for name, x in (("points", points), ("normals", normals)):
            if x is not None and not bool(torch.isfinite(x[mask]).all()):
                raise ValueRangeError(f"{name} contains NaN or inf at valid points")
    return mask, sizes


def _nearest(
    points: torch.Tensor, mask: torch.Tensor, max_nn: int, max_distance: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``min(max_nn, P)`` nearest valid points of every point, as rows of the flat batch.

    Returns:
        ``(nbr, found)``: int64 ``(B * P, k)`` indices into the flattened ``(B * P)`` points,
        sorted by distance (the point itself first), and ``(B * P, k)`` bool, False for missing
        neighbours (fewer valid points, or beyond ``max_distance``).
    """
    B, P = points.shape[:2]
    k = min(max_nn, P)
    # On CPU the KD-tree beats brute force at these k even for small clouds (no full sort).
    backend = "kdtree" if points.device.type == "cpu" else "auto"
    index = NeighborIndex(points, mask, backend=backend)
    dist, idx = index.query(points, k=k, max_distance=max_distance)
    offset = (torch.arange(B, device=idx.device) * P)[:, None, None]
    return (idx + offset).reshape(B * P, k), torch.isfinite(dist).reshape(B * P, k)


def _cross(
    a: Sequence[torch.Tensor], b: Sequence[torch.Tensor]
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Cross product of vectors given as three coordinate planes."""
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _dot(a: Sequence[torch.Tensor], b: Sequence[torch.Tensor]) -> torch.Tensor:
    """Dot product of vectors given as three coordinate planes."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _pair_bins(
    p1: Sequence[torch.Tensor],
    n1: Sequence[torch.Tensor],
    p2: Sequence[torch.Tensor],
    n2: Sequence[torch.Tensor],
) -> tuple[torch.Tensor, torch.Tensor]:
    """Histogram bins of Open3D's pair feature of ``(p1, n1)`` and ``(p2, n2)``.

    With ``d = p2 - p1``, the pair is reordered so that the source normal makes the smaller angle
    with ``d`` (ties keep the order); the Darboux frame ``u = n1'``, ``v = d' x u / |d' x u|``,
    ``w = u x v`` gives ``atan2(w.n2', u.n2')``, ``v.n2'`` and the cosine of the source normal
    with ``d``. Coincident points and ``d`` parallel to ``u`` give zeros. Each value is binned into
    11 equal bins of ``[-pi, pi]`` or ``[-1, 1]``, clamped to the ends. Every vector is handled as
    three coordinate planes, which keeps each operation a flat, contiguous one.

    Args:
        p1: source points as three coordinate planes, each ``(N,)``.
        n1: their normals, likewise.
        p2: the other points, likewise.
        n2: their normals, likewise.

    Returns:
        ``(bins, d2)``: int64 ``(N, 3)``, the bins of the three values offset by 0, 11 and 22
        (indices into the 33 bins), and the squared distances ``(N,)``.
    """
    n1, n2 = tuple(n1), tuple(n2)
    d = tuple(p2[i] - p1[i] for i in range(3))
    d2 = _dot(d, d)
    length = d2.sqrt()
    a1, a2 = _dot(n1, d) / length, _dot(n2, d) / length
    swap = torch.acos(a1.abs()) > torch.acos(a2.abs())
    u = tuple(torch.where(swap, n2[i], n1[i]) for i in range(3))
    t = tuple(torch.where(swap, n1[i], n2[i]) for i in range(3))
    v = _cross(tuple(torch.where(swap, -d[i], d[i]) for i in range(3)), u)
    v_norm = _dot(v, v).sqrt()
    ok = v_norm > 0  # also False for coincident points
    v = tuple(c / v_norm for c in v)
    w = _cross(u, v)
    zero = torch.zeros((), dtype=d2.dtype, device=d2.device)
    angle = torch.where(ok, torch.atan2(_dot(w, t), _dot(u, t)), zero)
    cos_v = torch.where(ok, _dot(v, t), zero)
    cos_d = torch.where(ok, torch.where(swap, -a2, a1), zero)
    bins = (
        (_BINS * (angle + math.pi) / (2 * math.pi)).clamp_(0, _BINS - 1).long(),
        (_BINS * (cos_v + 1.0) * 0.5).clamp_(0, _BINS - 1).long() + _BINS,
        (_BINS * (cos_d + 1.0) * 0.5).clamp_(0, _BINS - 1).long() + 2 * _BINS,
    )
    return torch.stack(bins, dim=-1), d2


def _fpfh64(
    points: torch.Tensor,
    normals: torch.Tensor,
    mask: torch.Tensor,
    radii: torch.Tensor,
    max_nn: int,
) -> torch.Tensor:
    """Unchecked :func:`compute_fpfh` on float64 inputs with radii ``(B, S)``: ``(B, P, S*33)``."""
    B, P = points.shape[:2]
    S, D, BP = radii.shape[1], 3 * _BINS, B * P
    nbr, found = _nearest(points, mask, max_nn, float(radii.max()))
    rows = mask.reshape(-1).nonzero().squeeze(1)  # valid points, as indices into the flat batch
    R = len(rows)
    # Every (point, neighbour) pair within the largest radius, grouped by point in neighbour
    # order; the first neighbour, the point itself, is skipped as Open3D does.
    found = found.index_select(0, rows)[:, 1:]
    dst = nbr.index_select(0, rows)[:, 1:][found]
    per_row = found.sum(1)
    pair_row = torch.repeat_interleave(torch.arange(R, device=rows.device), per_row)
    src = rows.index_select(0, pair_row)
    N = len(src)
    if N == 0:  # no point has a neighbour: every histogram is zero
        return points.new_zeros(B, P, S * D)

    # Pair bins (shared by the scales) and exact squared distances, a chunk of pairs at a time;
    # coordinates as separate planes, so that every gather and operation is a flat one.
    coords = points.reshape(BP, 3).T.contiguous()
    dirs = normals.reshape(BP, 3).T.contiguous()
    bins = torch.empty(N, 3, dtype=torch.long, device=points.device)
    d2 = torch.empty(N, dtype=points.dtype, device=points.device)
    for start in range(0, N, _PAIR_CHUNK):
        i, j = src[start : start + _PAIR_CHUNK], dst[start : start + _PAIR_CHUNK]
        bins[start : start + _PAIR_CHUNK], d2[start : start + _PAIR_CHUNK] = _pair_bins(
            *([x[c].index_select(0, k) for c in range(3)] for k in (i, j) for x in (coords, dirs))
        )

    # Open3D's hybrid search keeps the neighbours with d2 < radius ** 2.
    bound = radii.square().repeat_interleave(P, dim=0).index_select(0, rows)  # (R, S)
    within = (d2 < bound.index_select(0, pair_row).T).to(points.dtype)  # (S, N)
    count = points.new_zeros(S, R).index_add_(1, pair_row, within)  # neighbours but itself
    incr = torch.where(count > 0, 100.0 / count.clamp(min=1), 0.0)

    # SPFH: every pair within a scale's radius adds incr to its three bins.
    weight = (within * incr.index_select(1, pair_row)).repeat_interleave(3, dim=1)  # (S, 3 N)
    spfh = points.new_zeros(S, BP * D).index_add_(1, (src[:, None] * D + bins).reshape(-1), weight)
    spfh = spfh.reshape(S, BP, D)

    # FPFH: the neighbours' SPFH weighted by 1 / d2, each 11-bin block scaled to 100, plus own.
    nonzero = d2 != 0
    inv_d2 = torch.where(nonzero, 1.0 / torch.where(nonzero, d2, 1.0), 0.0)
    offsets = torch.cumsum(per_row, 0) - per_row
    shift = torch.arange(S, device=src.device)[:, None]
    summed = torch.nn.functional.embedding_bag(
        (dst + shift * BP).reshape(-1),
        spfh.reshape(S * BP, D),
        (offsets + shift * N).reshape(-1),
        per_sample_weights=(within * inv_d2).reshape(-1),
        mode="sum",
    ).reshape(S, R, 3, _BINS)
    total = summed.sum(-1, keepdim=True)
    norm = torch.where(total != 0, 100.0 / torch.where(total != 0, total, 1.0), 0.0)
    fpfh = (summed * norm).reshape(S, R, D) + spfh.index_select(1, rows)
    out = points.new_zeros(BP, S, D).index_copy_(0, rows, fpfh.transpose(0, 1))
    return out.reshape(B, P, S * D)


def compute_fpfh(
    points: torch.Tensor,
    normals: torch.Tensor,
    mask: torch.Tensor | None = None,
    *,
    radius: torch.Tensor | float,
    max_nn: int = 100,
) -> torch.Tensor:
    """Open3D's FPFH histograms of every point, batched, in PyTorch.

    Reproduces ``open3d.pipelines.registration.compute_fpfh_feature`` with
    ``KDTreeSearchParamHybrid(radius, max_nn)``: the neighbourhood of a point is its ``max_nn``
    nearest valid points closer than ``radius`` (itself included, first). Its SPFH histograms the
    three angles of the pair feature with each further neighbour into 11 bins apiece, each pair
    adding ``100 / (n - 1)``; its FPFH sums the neighbours' SPFH weighted by one over their
    squared distance (coincident points skipped), scales each 11-bin block to sum to 100 and adds
    the point's own SPFH. A point without neighbours gets zeros. The result equals Open3D's to
    float64 rounding (ties aside, see :class:`~poseflow.features.geometric.FPFHEncoder`). The work
    is done in float64 (bins are discontinuous: float32 rounding would move pairs between bins);
    the neighbour search is :class:`~poseflow.geometry.NeighborIndex`. Not differentiable.

    Args:
        points: clouds ``(B, P, 3)``, finite at valid rows.
        normals: unit normals ``(B, P, 3)``; FPFH's angles change sign when a normal flips, so
            orient them consistently (e.g. :func:`estimate_outward_normals`).
        mask: valid points ``(B, P)`` bool, or None (all valid).
        radius: search radius: a float, one per cloud ``(B,)``, or ``S`` per cloud ``(B, S)``
            (the scales share one neighbour search).
        max_nn: neighbours per point at most, itself included (at least 2).

    Returns:
        Histograms ``(B, P, 33 * S)`` in the points' dtype, scale after scale, each in Open3D's
        units (every 11-bin block of a point with neighbours sums to 200); zero at padded rows.

    Raises:
        ShapeError: wrong shapes, dtypes or devices.
        ValueRangeError: NaN or inf at valid points, a radius that is not positive, ``max_nn < 2``.

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> pts = torch.nn.functional.normalize(torch.randn(1, 200, 3, generator=g), dim=-1)
        >>> f = compute_fpfh(pts, pts, radius=0.5, max_nn=30)
        >>> f.shape, f[0, 0, :11].sum().item()
        (torch.Size([1, 200, 33]), 200.0)
    """
    mask, _ = check_clouds(points, normals, mask)
    if isinstance(max_nn, bool) or not isinstance(max_nn, int) or max_nn < 2:
        raise ValueRangeError(f"max_nn must be an integer >= 2, got {max_nn!r}")
    radii = _radius_table(radius, points.shape[0], points.device)
    keep = mask[..., None]
    pts = torch.where(keep, points, 0).to(torch.float64)
    nrm = torch.where(keep, normals, 0).to(torch.float64)
    return _fpfh64(pts, nrm, mask, radii, max_nn).to(points.dtype)


def _outward_normals64(
    points: torch.Tensor, mask: torch.Tensor, radius: torch.Tensor, max_nn: int
) -> torch.Tensor:
    """Unchecked :func:`estimate_outward_normals` on float64 points, radius ``(B, 1)``."""
    B, P = points.shape[:2]
    nbr, found = _nearest(points, mask, max_nn, float(radius.max()))
    k = int(found.sum(1).max())  # missing neighbours come last
    nbr, found = nbr[:, :k], found[:, :k].reshape(B, P, k)
    nbr = points.reshape(B * P, 3)[nbr.reshape(-1)].reshape(B, P, k, 3)
    d2 = (nbr - points[:, :, None]).square().sum(-1)
    w = (found & (d2 < radius.square()[:, :, None])).to(points.dtype)[..., None]
    count = w.sum(2)
    mean = (nbr * w).sum(2) / count.clamp(min=1)
    dev = (nbr - mean[:, :, None]) * w
    cov = (dev[..., :, None] * dev[..., None, :]).sum(2)  # (B, P, 3, 3), no tiny matmuls
    normals = torch.linalg.eigh(cov)[1][..., 0]
    flat = (count.squeeze(-1) < 3) | (cov == 0).flatten(-2).all(-1)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=points.dtype, device=points.device)
    normals = torch.where(flat[..., None], up, normals)
    m = mask[..., None].to(points.dtype)
    centroid = (points * m).sum(1, keepdim=True) / m.sum(1, keepdim=True).clamp(min=1)
    flip = ((points - centroid) * normals).sum(-1, keepdim=True) < 0
    return torch.where(mask[..., None], torch.where(flip, -normals, normals), 0.0)


def estimate_outward_normals(
    points: torch.Tensor,
    mask: torch.Tensor | None = None,
    *,
    radius: torch.Tensor | float,
    max_nn: int = 30,
) -> torch.Tensor:
    """Unit normals as Open3D estimates them, batched, in PyTorch.

    The PyTorch counterpart of :func:`~poseflow.features.geometric.open3d_normals`:
    Open3D's ``estimate_normals`` with ``KDTreeSearchParamHybrid(radius, max_nn)``: the normal of
    a point is the smallest-eigenvalue eigenvector of the covariance of its ``max_nn`` nearest
    valid points closer than ``radius`` (itself included), ``(0, 0, 1)`` when fewer than 3 are
    found; then it is turned away from its cloud's centroid. The covariance is taken about the
    neighbourhood mean in float64 (Open3D uses one-pass moments), so the two agree to rounding
    wherever the smallest eigenvalue is well separated.

    Args:
        points: clouds ``(B, P, 3)``, finite at valid rows.
        mask: valid points ``(B, P)`` bool, or None (all valid).
        radius: neighbourhood radius, a float or one per cloud ``(B,)``.
        max_nn: neighbours per point at most (at least 3).

    Returns:
        Normals ``(B, P, 3)`` in the points' dtype; zero at padded rows.

    Raises:
        ShapeError: wrong shapes, dtypes or devices.
        ValueRangeError: NaN or inf at valid points, a radius that is not positive, ``max_nn < 3``.

    Example:
        >>> sphere = torch.randn(1, 500, 3, generator=torch.Generator().manual_seed(0))
        >>> sphere = sphere / sphere.norm(dim=-1, keepdim=True)
        >>> n = estimate_outward_normals(sphere, radius=0.3)  # the normals point outward
        >>> bool(((n * sphere).sum(-1) > 0.95).all())
        True
    """
    mask, _ = check_clouds(points, None, mask)
    if isinstance(max_nn, bool) or not isinstance(max_nn, int) or max_nn < 3:
        raise ValueRangeError(f"max_nn must be an integer >= 3, got {max_nn!r}")
    if isinstance(radius, torch.Tensor) and radius.dim() > 1:
        raise ShapeError(f"radius must be a float or have shape (B,), got {tuple(radius.shape)}")
    radii = _radius_table(radius, points.shape[0], points.device)
    pts = torch.where(mask[..., None], points, 0).to(torch.float64)
    return _outward_normals64(pts, mask, radii, max_nn).to(points.dtype)
