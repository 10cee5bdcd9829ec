"""The BOP pose-error functions VSD, MSSD and MSPD, vectorised over estimates.

Each function compares ``B`` estimated poses with ``B`` ground-truth poses of one object
(model-to-camera transforms in metres) and returns one error per pair, following the definitions
of the BOP toolkit (Hodan et al., "BOP Challenge 2020 on 6D Object Localization", ECCVW 2020):

- **MSSD**, the maximum symmetry-aware surface distance: the largest distance between a model
  vertex in the estimated pose and the same vertex in the GT pose composed with a symmetry, the
  minimum over the symmetry set (metres).
- **MSPD**, the maximum symmetry-aware projection distance: the same with the vertices projected
  into the image (pixels).
- **VSD**, the visible surface discrepancy: the fraction of the union of the visible surfaces in
  the two poses where the rendered distances differ by at least ``tau`` (one error per ``tau``).

MSSD and MSPD use the vertices of the evaluation model (``models_eval`` in BOP), not a sampled
surface. Thresholds and normalisation (by the diameter, by the image width) are applied by
:mod:`poseflow.eval.recall` and :mod:`poseflow.eval.evaluate`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from poseflow._checks import check_same, check_tensor
from poseflow.errors import ShapeError, ValueRangeError

__all__ = [
    "MSPD_THRESHOLDS",
    "MSSD_THRESHOLDS",
    "VSD_DELTA",
    "VSD_TAUS",
    "VSD_THRESHOLDS",
    "depth_to_distance",
    "mspd",
    "mssd",
    "project_points",
    "vsd_from_depth",
]

#: VSD visibility tolerance ``delta`` in metres (15 mm, the BOP value for all but ITODD).
VSD_DELTA = 0.015
#: VSD misalignment tolerances ``tau`` as fractions of the object diameter: 0.05, 0.10, ... 0.50.
VSD_TAUS: tuple[float, ...] = tuple(float(x) for x in np.arange(0.05, 0.51, 0.05))
#: Correctness thresholds of the VSD error: 0.05, 0.10, ... 0.50.
VSD_THRESHOLDS: tuple[float, ...] = VSD_TAUS
#: Correctness thresholds of MSSD as fractions of the object diameter: 0.05, 0.10, ... 0.50.
MSSD_THRESHOLDS: tuple[float, ...] = VSD_TAUS
#: Correctness thresholds of MSPD in pixels for a 640-pixel-wide image: 5, 10, ... 50.
MSPD_THRESHOLDS: tuple[float, ...] = tuple(float(x) for x in np.arange(5, 51, 5))

# Elements (rows x vertices) of one block of the pairwise distance computations.
_BLOCK = 1 << 22


def _check_poses(T_est: torch.Tensor, T_gt: torch.Tensor) -> int:
    sizes = check_tensor(T_est, "T_est", ("B", 4, 4), finite=True)
    check_tensor(T_gt, "T_gt", ("B", 4, 4), finite=True, sizes=sizes)
    check_same(("T_est", T_est), ("T_gt", T_gt))
    return sizes["B"]


def _check_vertices(points: torch.Tensor, T_est: torch.Tensor) -> None:
    """Check model vertices ``(N, 3)``: finite, at least one, on ``T_est``'s device and dtype."""
    check_tensor(points, "points", ("N", 3), finite=True)
    check_same(("T_est", T_est), ("points", points))
    if points.shape[0] == 0:
        raise ShapeError("points must hold at least one vertex")


def _symmetries_or_identity(symmetries: torch.Tensor | None, like: torch.Tensor) -> torch.Tensor:
    if symmetries is None:
        return torch.eye(4, dtype=like.dtype, device=like.device)[None]
    check_tensor(symmetries, "symmetries", ("S", 4, 4), finite=True)
    if symmetries.shape[0] == 0:
        raise ShapeError("symmetries must hold at least one transform (the identity)")
    return symmetries.to(dtype=like.dtype, device=like.device)


def mssd(
    T_est: torch.Tensor,
    T_gt: torch.Tensor,
    points: torch.Tensor,
    symmetries: torch.Tensor | None = None,
) -> torch.Tensor:
    """Maximum symmetry-aware surface distance between estimated and ground-truth poses.

    ``e = min_S max_x || T_est x - T_gt S x ||`` over the model vertices ``x`` and the symmetry
    set ``S``. Computed for all pairs and symmetries at once: the squared distance of a vertex is a
    quadratic form in ``x``, so every (pair, symmetry) row is one dot product with 10 monomials of
    each vertex.

    Args:
        T_est: estimated model-to-camera poses, shape ``(B, 4, 4)``, metres.
        T_gt: ground-truth poses, shape ``(B, 4, 4)``.
        points: model vertices in the model frame, shape ``(N, 3)``.
        symmetries: the object's symmetry set, shape ``(S, 4, 4)`` (see
            :func:`poseflow.eval.symmetry.symmetry_transforms`), or None for the identity only.

    Returns:
        Errors in metres, shape ``(B,)``, in the dtype of ``T_est``.

    Raises:
        ShapeError: shapes, devices or dtypes disagree, or ``points`` is empty.
        ValueRangeError: an input holds NaN or inf.

    Example:
        >>> pts = torch.tensor([[0.1, 0.0, 0.0], [-0.1, 0.0, 0.0], [0.0, 0.05, 0.0]])
        >>> T = torch.eye(4)[None]
        >>> T2 = T.clone(); T2[0, 0, 3] = 0.02
        >>> mssd(T2, T, pts)
        tensor([0.0200])
    """
    B = _check_poses(T_est, T_gt)
    _check_vertices(points, T_est)
    S = _symmetries_or_identity(symmetries, T_est)
    # Centre the vertices so that the quadratic form is well conditioned.
    centre = points.mean(0)
    p = points - centre
    G = T_gt[:, None] @ S[None]  # (B, S, 4, 4)
    A = T_est[:, None, :3, :3] - G[..., :3, :3]  # (B, S, 3, 3)
    c = T_est[:, None, :3, 3] - G[..., :3, 3] + (A @ centre)  # (B, S, 3)
    M = A.transpose(-1, -2) @ A
    v = (A.transpose(-1, -2) @ c[..., None])[..., 0]
    W = torch.stack(
        (
            M[..., 0, 0], M[..., 1, 1], M[..., 2, 2],
            2 * M[..., 0, 1], 2 * M[..., 0, 2], 2 * M[..., 1, 2],
            2 * v[..., 0], 2 * v[..., 1], 2 * v[..., 2],
            (c * c).sum(-1),
        ),
        -1,
    ).reshape(-1, 10)  # fmt: skip
    x, y, z = p.unbind(-1)
    phi = torch.stack((x * x, y * y, z * z, x * y, x * z, y * z, x, y, z, torch.ones_like(x)), 0)
    rows = max(1, _BLOCK // p.shape[0])
    worst = torch.cat([(w @ phi).amax(-1) for w in W.split(rows)])
    return worst.clamp_min(0).sqrt().reshape(B, S.shape[0]).amin(-1)


def project_points(T: torch.Tensor, K: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Project model points into the image: ``pi(K (R x + t))``.

    Args:
        T: model-to-camera poses, shape ``(*, 4, 4)``.
        K: intrinsics, shape ``(3, 3)`` or ``(*, 3, 3)`` matching ``T``.
        points: model points, shape ``(N, 3)``.

    Returns:
        Pixel coordinates ``(u, v)``, shape ``(*, N, 2)``. A point on the camera plane (z = 0)
        projects to inf.

    Example:
        >>> T = torch.eye(4); T[2, 3] = 1.0
        >>> K = torch.tensor([[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]])
        >>> project_points(T, K, torch.tensor([[0.1, 0.0, 0.0]]))
        tensor([[60., 40.]])
    """
    X = points @ T[..., :3, :3].transpose(-1, -2) + T[..., None, :3, 3]
    uvw = X @ K.transpose(-1, -2)
    z = uvw[..., 2:]
    safe = torch.where(z == 0, torch.ones_like(z), z)
    uv = uvw[..., :2] / safe
    return torch.where(z == 0, torch.full_like(uv, float("inf")), uv)


def mspd(
    T_est: torch.Tensor,
    T_gt: torch.Tensor,
    K: torch.Tensor,
    points: torch.Tensor,
    symmetries: torch.Tensor | None = None,
) -> torch.Tensor:
    """Maximum symmetry-aware projection distance between estimated and ground-truth poses.

    ``e = min_S max_x || pi(K T_est x) - pi(K T_gt S x) ||`` in pixels.

    Args:
        T_est: estimated model-to-camera poses, shape ``(B, 4, 4)``, metres.
        T_gt: ground-truth poses, shape ``(B, 4, 4)``.
        K: camera intrinsics, shape ``(3, 3)`` or ``(B, 3, 3)``.
        points: model vertices in the model frame, shape ``(N, 3)``.
        symmetries: symmetry set ``(S, 4, 4)``, or None for the identity only.

    Returns:
        Errors in pixels, shape ``(B,)`` (inf where a vertex lies on the camera plane).

    Raises:
        ShapeError: shapes, devices or dtypes disagree, or ``points`` is empty.
        ValueRangeError: an input holds NaN or inf.

    Example:
        >>> K = torch.tensor([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
        >>> pts = torch.tensor([[0.05, 0.0, 0.0], [0.0, 0.05, 0.0]])
        >>> T = torch.eye(4)[None].clone(); T[0, 2, 3] = 1.0
        >>> T2 = T.clone(); T2[0, 0, 3] = 0.01
        >>> mspd(T2, T, K, pts)
        tensor([5.])
    """
    B = _check_poses(T_est, T_gt)
    _check_vertices(points, T_est)
    if K.dim() == 2:
        check_tensor(K, "K", (3, 3), finite=True)
        K = K.expand(B, 3, 3)
    else:
        check_tensor(K, "K", (B, 3, 3), finite=True)
    check_same(("T_est", T_est), ("K", K))
    S = _symmetries_or_identity(symmetries, T_est)
    n_sym = S.shape[0]
    ones = torch.ones(points.shape[0], 1, dtype=points.dtype, device=points.device)
    pts_h = torch.cat((points, ones), 1).T  # (4, N)
    P_est = K @ T_est[:, :3, :]  # (B, 3, 4)
    if n_sym == 1:
        return _max_projection_distance(P_est, K @ (T_gt @ S[0])[:, :3, :], pts_h)
    # Branch and bound over the symmetries: the maximum over a few extreme vertices is a lower
    # bound of the maximum over all of them; only symmetries whose bound beats the exact error of
    # the most promising one are evaluated on every vertex. The result is exact.
    P_gt = K[:, None] @ (T_gt[:, None] @ S[None])[..., :3, :]  # (B, S, 3, 4)
    probe = pts_h[:, _extreme_vertices(points)]
    bound = _max_projection_distance(
        P_est[:, None].expand(B, n_sym, 3, 4).reshape(-1, 3, 4), P_gt.reshape(-1, 3, 4), probe
    ).reshape(B, n_sym)
    best = bound.argmin(-1)
    rows = torch.arange(B, device=T_est.device)
    upper = _max_projection_distance(P_est, P_gt[rows, best], pts_h)
    b_idx, s_idx = torch.nonzero(bound < upper[:, None], as_tuple=True)
    exact = _max_projection_distance(P_est[b_idx], P_gt[b_idx, s_idx], pts_h)
    return upper.scatter_reduce(0, b_idx, exact, reduce="amin")


def _extreme_vertices(points: torch.Tensor, count: int = 64) -> torch.Tensor:
    """Indices of up to ``count`` vertices: the extremes along 26 directions, then a stride."""
    n = points.shape[0]
    if n <= count:
        return torch.arange(n, device=points.device)
    grid = torch.tensor([-1.0, 0.0, 1.0], dtype=points.dtype, device=points.device)
    dirs = torch.cartesian_prod(grid, grid, grid)
    dirs = dirs[dirs.abs().sum(-1) > 0]
    centred = points - points.mean(0)
    extremes = (centred @ dirs.T).argmax(0)
    stride = torch.linspace(0, n - 1, count, device=points.device).round().long()
    return torch.cat((extremes, stride)).unique()[:count]


def _max_projection_distance(
    P_est: torch.Tensor, P_gt: torch.Tensor, pts_h: torch.Tensor
) -> torch.Tensor:
    """Max over points of the pixel distance between two projections ``(R, 3, 4)`` each."""
    n = pts_h.shape[1]
    rows = max(1, _BLOCK // (3 * n))
    out = []
    for pe, pg in zip(P_est.split(rows), P_gt.split(rows)):
        a, b = pe @ pts_h, pg @ pts_h  # (r, 3, N)
        d = (a[:, :2] / a[:, 2:] - b[:, :2] / b[:, 2:]).square().sum(1)
        out.append(torch.nan_to_num(d, nan=float("inf")).amax(-1))
    if not out:
        return P_est.new_zeros(0)
    return torch.cat(out).sqrt()


def depth_to_distance(depth: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Convert z-depth images to distance-from-camera-centre images.

    Pixel ``(u, v)`` (column, row; integer coordinates, as the BOP toolkit uses) holds the point
    ``z ((u - cx) / fx, (v - cy) / fy, 1)``; its distance is ``z`` times the norm of that ray.
    Missing depth (0) stays 0.

    Args:
        depth: depth images, shape ``(B, H, W)`` or ``(H, W)``.
        K: intrinsics, shape ``(3, 3)`` or ``(B, 3, 3)``.

    Returns:
        Distance images with the shape of ``depth``.

    Example:
        >>> K = torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1]])
        >>> depth_to_distance(torch.ones(1, 2), K)
        tensor([[1.0000, 1.4142]])
    """
    squeeze = depth.dim() == 2
    d = depth[None] if squeeze else depth
    check_tensor(d, "depth", ("B", "H", "W"))
    Kb = K[None] if K.dim() == 2 else K
    check_tensor(Kb, "K", (None, 3, 3))
    H, W = d.shape[-2:]
    u = torch.arange(W, dtype=d.dtype, device=d.device)
    v = torch.arange(H, dtype=d.dtype, device=d.device)
    Kb = Kb.to(d)
    fx, fy = Kb[:, 0, 0, None, None], Kb[:, 1, 1, None, None]
    cx, cy = Kb[:, 0, 2, None, None], Kb[:, 1, 2, None, None]
    x = (u[None, None, :] - cx) / fx
    y = (v[None, :, None] - cy) / fy
    dist = d * torch.sqrt(x * x + y * y + 1)
    return dist[0] if squeeze else dist


def _clean_depth(depth: torch.Tensor) -> torch.Tensor:
    """Missing depth is 0; NaN, inf and negative values are read as missing too."""
    return torch.where(torch.isfinite(depth) & (depth > 0), depth, torch.zeros_like(depth))


def vsd_from_depth(
    depth_est: torch.Tensor,
    depth_gt: torch.Tensor,
    depth_test: torch.Tensor,
    K: torch.Tensor,
    diameter: torch.Tensor | float,
    *,
    delta: float = VSD_DELTA,
    taus: Sequence[float] = VSD_TAUS,
    normalized_by_diameter: bool = True,
) -> torch.Tensor:
    r"""Visible surface discrepancy from rendered and measured depth images (BOP19 visibility).

    With distance images ``D_est``, ``D_gt`` (renderings of the model in the two poses) and
    ``D_test`` (the measurement), a rendered pixel is *visible* when the model is there and either
    lies at most ``delta`` behind the measured surface or the measurement is missing there (the
    toolkit's ``bop19`` mode, which keeps shiny objects evaluable). The estimate's visible mask also
    takes every pixel visible in the GT pose where the estimate is rendered. Over the union ``U`` of
    the two visible masks, ``e = (#{p in inter: |D_gt - D_est| >= tau} + |U \ inter|) / |U|``,
    distances divided by the diameter when ``normalized_by_diameter``; ``e = 1`` for an empty
    union.

    Args:
        depth_est: z-depth of the model rendered in the estimated poses, shape ``(B, H, W)``,
            metres, 0 where the model is absent.
        depth_gt: z-depth of the model rendered in the GT poses, shape ``(B, H, W)``.
        depth_test: measured depth, shape ``(B, H, W)`` or ``(H, W)``; 0 (or NaN/inf) is missing.
        K: intrinsics of these images, shape ``(3, 3)`` or ``(B, 3, 3)`` (a crop shifts cx, cy).
        diameter: the object diameter in metres, a float or shape ``(B,)``.
        delta: visibility tolerance in metres.
        taus: misalignment tolerances (fractions of the diameter when normalised, else metres).
        normalized_by_diameter: divide the pixel distances by the diameter.

    Returns:
        Errors in ``[0, 1]``, shape ``(B, T)`` with ``T = len(taus)``.

    Raises:
        ShapeError: the images disagree in shape.
        ValueRangeError: ``delta`` or a ``tau`` is not positive, or a diameter is not positive.

    Example:
        >>> K = torch.tensor([[100.0, 0, 2], [0, 100.0, 2], [0, 0, 1]])
        >>> gt = torch.zeros(1, 4, 4); gt[0, 1:3, 1:3] = 1.0
        >>> vsd_from_depth(gt, gt, gt[0], K, 0.1, taus=[0.05])
        tensor([[0.]])
    """
    sizes = check_tensor(depth_est, "depth_est", ("B", "H", "W"))
    check_tensor(depth_gt, "depth_gt", ("B", "H", "W"), sizes=sizes)
    test = depth_test[None].expand_as(depth_gt) if depth_test.dim() == 2 else depth_test
    check_tensor(test, "depth_test", ("B", "H", "W"), sizes=sizes)
    if not delta > 0:
        raise ValueRangeError(f"delta must be positive, got {delta}")
    tau = torch.as_tensor(list(taus), dtype=depth_est.dtype, device=depth_est.device)
    if tau.numel() == 0 or not bool((tau > 0).all()):
        raise ValueRangeError(f"taus must be a non-empty list of positive values, got {taus}")
    diam = torch.as_tensor(diameter, dtype=depth_est.dtype, device=depth_est.device)
    diam = diam.expand(sizes["B"]) if diam.dim() == 0 else diam
    check_tensor(diam, "diameter", (sizes["B"],))
    if normalized_by_diameter and not bool((diam > 0).all()):
        raise ValueRangeError("diameters must be positive")
    d_est = depth_to_distance(_clean_depth(depth_est), K)
    d_gt = depth_to_distance(_clean_depth(depth_gt), K)
    d_test = depth_to_distance(_clean_depth(test.to(depth_est)), K)
    test_missing = d_test == 0
    in_est, in_gt = d_est > 0, d_gt > 0
    visib_gt = in_gt & ((d_gt - d_test <= delta) | test_missing)
    visib_est = (in_est & ((d_est - d_test <= delta) | test_missing)) | (visib_gt & in_est)
    inter = visib_gt & visib_est
    union_count = (visib_gt | visib_est).flatten(1).sum(-1)
    comp_count = union_count - inter.flatten(1).sum(-1)
    dist = (d_gt - d_est).abs()
    if normalized_by_diameter:
        dist = dist / diam[:, None, None]
    dist = torch.where(inter, dist, torch.full_like(dist, -1.0)).flatten(1)  # -1: never >= tau
    bad = torch.stack([(dist >= t).sum(-1) for t in tau], -1)  # (B, T)
    union = union_count[:, None].to(depth_est.dtype)
    err = (bad + comp_count[:, None]).to(depth_est.dtype) / union.clamp_min(1)
    return torch.where(union > 0, err, torch.ones_like(err))
