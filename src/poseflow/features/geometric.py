"""Geometric encoders Φ: per-point descriptors of a point cloud's local 3D structure.

Every encoder follows :class:`GeometricEncoder`: ``encode(points, normals, mask, diameter)`` maps a
padded batch of clouds ``(B, P, 3)`` to descriptors ``(B, P, D)``; padded rows (``mask`` False)
come back as zeros. Encoders are frozen: no gradients, no training.

- :class:`FPFHEncoder`: multi-scale FPFH at radii given as fractions of the object diameter (the
  paper's two scales, 30 % and 40 %), concatenated and L2-normalised. Weight-free, the offline
  default. It runs :func:`compute_fpfh`, Open3D's FPFH computed in batched PyTorch (CPU or CUDA, no
  Open3D needed), or Open3D itself cloud by cloud (by default on CPU, where it is faster);
  :func:`estimate_outward_normals` gives the normals of :func:`open3d_normals` in PyTorch.
- :class:`~poseflow.features.gedi.GeDiEncoder`: GeDi's architecture in plain PyTorch (own module).
- :class:`TorchScriptEncoder` and :class:`CallableEncoder`: adapters that plug in any per-point
  encoder (dGeDi exported to TorchScript, a user's function).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np
import torch

from poseflow._checks import check_mask, check_same, check_tensor
from poseflow.errors import DegenerateInputError, MissingWeightsError, ShapeError, ValueRangeError
from poseflow.geometry.neighbors import NeighborIndex

__all__ = [
    "CallableEncoder",
    "FPFHEncoder",
    "GeometricEncoder",
    "TorchScriptEncoder",
    "check_geometric_inputs",
    "compute_fpfh",
    "estimate_outward_normals",
    "open3d_normals",
]

#: Neighbour pairs whose features the torch FPFH computes at once (bounds its memory).
_PAIR_CHUNK = 1 << 14
#: FPFH bins per angle; the descriptor is three such histograms.
_BINS = 11


@runtime_checkable
class GeometricEncoder(Protocol):
    """What the pipeline needs from a geometric encoder.

    Attributes:
        dim: the descriptor size ``D``.
    """

    dim: int

    def encode(
        self,
        points: torch.Tensor,
        normals: torch.Tensor | None,
        mask: torch.Tensor | None,
        diameter: torch.Tensor | float,
    ) -> torch.Tensor:
        """Describe every point: ``(B, P, 3)`` points → ``(B, P, D)`` descriptors."""
        ...


def check_geometric_inputs(
    points: torch.Tensor,
    normals: torch.Tensor | None,
    mask: torch.Tensor | None,
    diameter: torch.Tensor | float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Validate the encoder inputs and return ``(mask (B, P), diameter (B,))`` filled in.

    Args:
        points: clouds, shape ``(B, P, 3)``, finite.
        normals: unit normals, shape ``(B, P, 3)``, or None.
        mask: valid points, shape ``(B, P)`` bool, or None (all valid).
        diameter: object diameter in metres, a float or a tensor of shape ``(B,)``.

    Returns:
        The mask ``(B, P)`` and the diameters ``(B,)`` on the points' device and dtype.

    Raises:
        ShapeError: on a shape, dtype or device mismatch.
        ValueRangeError: non-finite points or a diameter that is not positive.
        DegenerateInputError: a cloud with fewer than 3 valid points.

    Example:
        >>> m, d = check_geometric_inputs(torch.rand(2, 5, 3), None, None, 0.1)
        >>> m.shape, d.shape
        (torch.Size([2, 5]), torch.Size([2]))
    """
    sizes = check_tensor(points, "points", ("B", "P", 3), finite=True)
    if normals is not None:
        check_tensor(normals, "normals", ("B", "P", 3), finite=True, sizes=sizes)
        check_same(("points", points), ("normals", normals))
    if mask is None:
        mask = torch.ones(points.shape[:2], dtype=torch.bool, device=points.device)
    else:
        check_mask(mask, "mask", ("B", "P"), sizes)
        check_same(("points", points), ("mask", mask), dtype=False)
    if isinstance(diameter, torch.Tensor):
        if diameter.dim() == 0:
            diameter = diameter.expand(sizes["B"])
        check_tensor(diameter, "diameter", ("B",), finite=True, sizes=sizes)
        diameter = diameter.to(device=points.device, dtype=points.dtype)
    else:
        diameter = torch.full(
            (sizes["B"],), float(diameter), dtype=points.dtype, device=points.device
        )
    if not bool((diameter > 0).all()):
        raise ValueRangeError(f"diameter must be positive, got {diameter.tolist()}")
    counts = mask.sum(dim=1)
    if bool((counts < 3).any()):
        raise DegenerateInputError(
            f"every cloud needs at least 3 valid points, got counts {counts.tolist()}"
        )
    return mask, diameter


def open3d_normals(points: np.ndarray, radius: float, *, max_nn: int = 30) -> np.ndarray:
    """Estimate unit normals with Open3D, oriented away from the cloud's centroid.

    Orienting away from the centroid gives a query model and an observed partial view the same
    (outward) convention, which FPFH needs: its angles change when a normal flips.

    Args:
        points: one cloud, shape ``(P, 3)``, float64.
        radius: neighbourhood radius in metres.
        max_nn: neighbours used at most.

    Returns:
        Normals of shape ``(P, 3)``, float64.

    Example:
        >>> import numpy as np
        >>> pts = np.random.default_rng(0).normal(size=(200, 3))
        >>> pts /= np.linalg.norm(pts, axis=1, keepdims=True)
        >>> n = open3d_normals(pts, 0.5)
        >>> bool((np.sum(n * pts, axis=1) > 0.9).mean() > 0.9)
        True
    """
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points)))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=max_nn))
    normals = np.asarray(pcd.normals).copy()
    outward = points - points.mean(axis=0, keepdims=True)
    flip = np.sum(normals * outward, axis=1) < 0
    normals[flip] *= -1
    return normals


@functools.cache
def _open3d_available() -> bool:
    """Whether Open3D imports (it needs system libraries that a machine may lack)."""
    try:
        import open3d  # noqa: F401
    except (ImportError, OSError):
        return False
    return True


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


def _check_cloud(
    points: torch.Tensor, normals: torch.Tensor | None, mask: torch.Tensor | None
) -> torch.Tensor:
    """Validate ``(B, P, 3)`` points (and normals) finite at valid rows; return the mask."""
    sizes = check_tensor(points, "points", ("B", "P", 3))
    if normals is not None:
        check_tensor(normals, "normals", ("B", "P", 3), sizes=sizes)
        check_same(("points", points), ("normals", normals))
    if mask is None:
        mask = torch.ones(points.shape[:2], dtype=torch.bool, device=points.device)
    else:
        check_mask(mask, "mask", ("B", "P"), sizes)
        check_same(("points", points), ("mask", mask), dtype=False)
    for name, x in (("points", points), ("normals", normals)):
        if x is not None and not bool(torch.isfinite(x[mask]).all()):
            raise ValueRangeError(f"{name} contains NaN or inf at valid points")
    return mask


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
    float64 rounding (ties aside, see :class:`FPFHEncoder`). The work is done in float64 (bins
    are discontinuous: float32 rounding would move pairs between bins); the neighbour search is
    :class:`~poseflow.geometry.NeighborIndex`. Not differentiable.

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
    mask = _check_cloud(points, normals, mask)
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
    """Unit normals as :func:`open3d_normals` gives them, batched, in PyTorch.

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
        >>> g = torch.Generator().manual_seed(0)
        >>> pts = torch.nn.functional.normalize(torch.randn(1, 500, 3, generator=g), dim=-1)
        >>> n = estimate_outward_normals(pts, radius=0.3)
        >>> bool(((n * pts).sum(-1) > 0.95).all())
        True
    """
    mask = _check_cloud(points, None, mask)
    if isinstance(max_nn, bool) or not isinstance(max_nn, int) or max_nn < 3:
        raise ValueRangeError(f"max_nn must be an integer >= 3, got {max_nn!r}")
    if isinstance(radius, torch.Tensor) and radius.dim() > 1:
        raise ShapeError(f"radius must be a float or have shape (B,), got {tuple(radius.shape)}")
    radii = _radius_table(radius, points.shape[0], points.device)
    pts = torch.where(mask[..., None], points, 0).to(torch.float64)
    return _outward_normals64(pts, mask, radii, max_nn).to(points.dtype)


class FPFHEncoder:
    """Multi-scale FPFH descriptors, concatenated and L2-normalised.

    Each scale is Open3D's 33-bin FPFH histogram with a hybrid search of radius
    ``fraction * diameter`` and at most ``max_nn`` neighbours; the scales are concatenated
    (``D = 33 * len(radius_fractions)``) and each row is L2-normalised. Two backends give the
    same descriptors to float64 rounding, except where Open3D's own result hangs on rounding
    (neighbours at exactly equal distances; two neighbours whose normals are equal up to
    rounding, as estimated normals on a flat face can be):

    - ``"torch"``: :func:`compute_fpfh`, the whole padded batch at once on the input's device
      (CPU or CUDA), float64 inside; the scales share one neighbour search. Needs no Open3D.
    - ``"open3d"``: Open3D's ``compute_fpfh_feature``, cloud by cloud, on the CPU in float64.
    - ``"auto"`` (default): ``"open3d"`` for CPU inputs, ``"torch"`` for any other device or
      when Open3D cannot be imported. On one CPU thread Open3D is the faster of the two (the
      torch backend takes 1.2 to 1.9 times as long for 8 clouds of 64 to 256 points and for one
      of 2,000; ``benchmarks/features.py`` prints the ratio).

    The result has the input's device and dtype.

    Args:
        radius_fractions: FPFH radii as fractions of the object diameter (paper: 0.30 and 0.40).
        max_nn: neighbours per FPFH query at most (bounds the cost on dense clouds).
        normal_radius_fraction: normal-estimation radius as a fraction of the diameter, used when
            ``encode`` gets no normals (at most 30 neighbours, turned away from the centroid:
            :func:`estimate_outward_normals`, or :func:`open3d_normals` with ``"open3d"``).
        backend: ``"auto"``, ``"torch"`` or ``"open3d"``.

    Example:
        >>> enc = FPFHEncoder()
        >>> pts = torch.rand(2, 300, 3, generator=torch.Generator().manual_seed(0)) * 0.1
        >>> f = enc.encode(pts, None, None, 0.17)
        >>> f.shape, enc.dim
        (torch.Size([2, 300, 66]), 66)
        >>> bool(torch.allclose(f.norm(dim=-1), torch.ones(2, 300), atol=1e-5))
        True
    """

    def __init__(
        self,
        *,
        radius_fractions: Sequence[float] = (0.30, 0.40),
        max_nn: int = 100,
        normal_radius_fraction: float = 0.05,
        backend: str = "auto",
    ) -> None:
        if not radius_fractions or any(r <= 0 for r in radius_fractions):
            raise ValueRangeError(f"radius_fractions must be positive, got {radius_fractions}")
        if max_nn < 3:
            raise ValueRangeError(f"max_nn must be at least 3, got {max_nn}")
        if backend not in ("auto", "torch", "open3d"):
            raise ValueRangeError(f"backend must be 'auto', 'torch' or 'open3d', got {backend!r}")
        self.radius_fractions = tuple(float(r) for r in radius_fractions)
        self.max_nn = int(max_nn)
        self.normal_radius_fraction = float(normal_radius_fraction)
        self.backend = backend
        self.dim = 33 * len(self.radius_fractions)

    def __repr__(self) -> str:
        return (
            f"FPFHEncoder(radius_fractions={self.radius_fractions}, max_nn={self.max_nn}, "
            f"backend={self.backend!r})"
        )

    @torch.no_grad()
    def encode(
        self,
        points: torch.Tensor,
        normals: torch.Tensor | None,
        mask: torch.Tensor | None,
        diameter: torch.Tensor | float,
    ) -> torch.Tensor:
        """Describe every valid point of every cloud.

        Args:
            points: clouds, shape ``(B, P, 3)`` in metres.
            normals: unit normals ``(B, P, 3)`` oriented outward, or None to estimate them
                (hybrid radius search, turned away from each cloud's centroid).
            mask: valid points ``(B, P)`` bool, or None.
            diameter: object diameter(s) in metres, float or ``(B,)``.

        Returns:
            Descriptors of shape ``(B, P, 33 * len(radius_fractions))``, unit norm on valid rows
            (a point with an empty neighbourhood gets a zero histogram), zero on padded rows.
        """
        mask, diameter = check_geometric_inputs(points, normals, mask, diameter)
        backend = self.backend
        if backend == "auto":
            on_cpu = points.device.type == "cpu"
            backend = "open3d" if on_cpu and _open3d_available() else "torch"
        if backend == "torch":
            out = self._encode_torch(points, normals, mask, diameter)
        else:
            out = self._encode_open3d(points, normals, mask, diameter)
        out = torch.nn.functional.normalize(out, dim=-1)
        return out.to(device=points.device, dtype=points.dtype)

    def _encode_torch(
        self,
        points: torch.Tensor,
        normals: torch.Tensor | None,
        mask: torch.Tensor,
        diameter: torch.Tensor,
    ) -> torch.Tensor:
        """Raw float64 histograms ``(B, P, D)`` by :func:`compute_fpfh`."""
        keep = mask[..., None]
        pts = torch.where(keep, points, 0).to(torch.float64)
        diameter = diameter.to(torch.float64)[:, None]
        if normals is None:
            radius = self.normal_radius_fraction * diameter
            nrm = _outward_normals64(pts, mask, radius, 30)
        else:
            nrm = torch.where(keep, normals, 0).to(torch.float64)
        fractions = torch.tensor(self.radius_fractions, dtype=torch.float64, device=pts.device)
        return _fpfh64(pts, nrm, mask, diameter * fractions, self.max_nn)

    def _encode_open3d(
        self,
        points: torch.Tensor,
        normals: torch.Tensor | None,
        mask: torch.Tensor,
        diameter: torch.Tensor,
    ) -> torch.Tensor:
        """Raw float64 CPU histograms ``(B, P, D)`` by Open3D, cloud by cloud."""
        import open3d as o3d

        out = torch.zeros(*points.shape[:2], self.dim, dtype=torch.float64)
        pts_np = points.detach().cpu().double().numpy()
        nrm_np = None if normals is None else normals.detach().cpu().double().numpy()
        mask_np = mask.cpu().numpy()
        for b in range(points.shape[0]):
            valid = mask_np[b]
            pts = np.ascontiguousarray(pts_np[b][valid])
            d = float(diameter[b])
            if nrm_np is None:
                nrm = open3d_normals(pts, self.normal_radius_fraction * d)
            else:
                nrm = np.ascontiguousarray(nrm_np[b][valid])
            pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
            pcd.normals = o3d.utility.Vector3dVector(nrm)
            scales = []
            for fraction in self.radius_fractions:
                param = o3d.geometry.KDTreeSearchParamHybrid(
                    radius=fraction * d, max_nn=self.max_nn
                )
                fpfh = o3d.pipelines.registration.compute_fpfh_feature(pcd, param)
                scales.append(np.asarray(fpfh.data).T)
            out[b, torch.from_numpy(valid)] = torch.from_numpy(np.concatenate(scales, axis=1))
        return out


class CallableEncoder:
    """Adapt any function ``f(points, normals, mask, diameter) -> (B, P, D)`` to the protocol.

    The output is checked (shape, finiteness), padded rows are zeroed, and the result is moved to
    the input's device and dtype, so a user's encoder behaves like the built-in ones.

    Args:
        fn: the per-point encoder.
        dim: its descriptor size ``D``.
        normalize: L2-normalise every descriptor.

    Example:
        >>> fn = lambda p, n, m, d: torch.cat([p, p.norm(dim=-1, keepdim=True)], -1)
        >>> enc = CallableEncoder(fn, 4)
        >>> enc.encode(torch.rand(1, 10, 3), None, None, 1.0).shape
        torch.Size([1, 10, 4])
    """

    def __init__(
        self,
        fn: Callable[..., torch.Tensor],
        dim: int,
        *,
        normalize: bool = False,
    ) -> None:
        if dim <= 0:
            raise ValueRangeError(f"dim must be positive, got {dim}")
        self.fn = fn
        self.dim = int(dim)
        self.normalize = normalize

    @torch.no_grad()
    def encode(
        self,
        points: torch.Tensor,
        normals: torch.Tensor | None,
        mask: torch.Tensor | None,
        diameter: torch.Tensor | float,
    ) -> torch.Tensor:
        """Run the wrapped encoder; see :class:`GeometricEncoder`.

        Raises:
            ShapeError: the wrapped encoder returned the wrong shape.
            ValueRangeError: it returned NaN or inf on a valid point.
        """
        mask, diameter = check_geometric_inputs(points, normals, mask, diameter)
        out = self.fn(points, normals, mask, diameter)
        if not isinstance(out, torch.Tensor) or tuple(out.shape) != (*points.shape[:2], self.dim):
            got = tuple(out.shape) if isinstance(out, torch.Tensor) else type(out).__name__
            raise ShapeError(f"encoder returned {got}, expected {(*points.shape[:2], self.dim)}")
        out = out.to(device=points.device, dtype=points.dtype)
        out = torch.where(mask[..., None], out, torch.zeros((), dtype=out.dtype, device=out.device))
        if not bool(torch.isfinite(out).all()):
            raise ValueRangeError("encoder returned NaN or inf descriptors")
        if self.normalize:
            out = torch.nn.functional.normalize(out, dim=-1)
        return out


class TorchScriptEncoder(CallableEncoder):
    """Load a TorchScript per-point encoder (e.g. dGeDi exported with ``torch.jit.save``).

    The scripted module is called as ``module(points, normals, mask, diameter)`` with
    ``normals`` replaced by zeros when None, and must return ``(B, P, D)``; it runs on the device of
    the points it receives (``map_location`` picks where it is loaded).

    Args:
        path: the ``.pt`` file written by ``torch.jit.save``.
        dim: the descriptor size ``D``.
        normalize: L2-normalise every descriptor.
        map_location: device to load the module on.

    Raises:
        MissingWeightsError: ``path`` does not exist.

    Example:
        >>> import tempfile, os
        >>> class Toy(torch.nn.Module):
        ...     def forward(self, p, n, m, d):
        ...         return torch.cat([p, n], -1)
        >>> path = os.path.join(tempfile.mkdtemp(), "toy.pt")
        >>> torch.jit.save(torch.jit.script(Toy()), path)
        >>> TorchScriptEncoder(path, 6).encode(torch.rand(1, 8, 3), None, None, 1.0).shape
        torch.Size([1, 8, 6])
    """

    def __init__(
        self,
        path: str | Path,
        dim: int,
        *,
        normalize: bool = False,
        map_location: str | torch.device = "cpu",
    ) -> None:
        path = Path(path)
        if not path.is_file():
            raise MissingWeightsError(
                f"no TorchScript encoder at {path}: export one with "
                "torch.jit.save(torch.jit.script(model), path) and pass that path"
            )
        self.module = torch.jit.load(str(path), map_location=map_location).eval()

        def call(points, normals, mask, diameter):
            if normals is None:
                normals = torch.zeros_like(points)
            return self.module(points, normals, mask, diameter)

        super().__init__(call, dim, normalize=normalize)
