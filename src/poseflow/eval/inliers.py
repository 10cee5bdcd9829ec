"""The correspondence-inlier metric of the paper's feature-discriminativity analysis.

Correspondences between the object model ``Q`` and the observed target ``T`` are the mutual
nearest neighbours in feature space; a correspondence is an inlier when its two points lie within
``threshold × diameter`` (3 % in the paper) once the target is brought into the model's canonical
frame by the ground-truth pose. The paper reports the average number of inliers. For a symmetric
object every symmetric equivalent of the ground truth is as true: with ``equivalents`` the count
is that of the equivalent pose that confirms the most correspondences (one pose for all of them).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch.nn import functional as F

from poseflow._checks import check_mask, check_same, check_tensor
from poseflow.errors import ValueRangeError

__all__ = ["InlierResult", "correspondence_inliers", "mutual_nearest_neighbors"]

_CHUNK_ELEMENTS = 1 << 22


@dataclass
class InlierResult:
    """Outcome of :func:`correspondence_inliers`, one entry per instance.

    Attributes:
        num_inliers: inlier correspondences, shape ``(B,)`` long.
        num_matches: mutual-nearest-neighbour correspondences, shape ``(B,)`` long.
        inlier_ratio: ``num_inliers / num_matches`` (0 where there is no match), shape ``(B,)``.
        match: for every target point, the index of its mutual nearest query point or -1,
            shape ``(B, M)`` long.
        inlier: which target points form an inlier correspondence, shape ``(B, M)`` bool.
    """

    num_inliers: torch.Tensor
    num_matches: torch.Tensor
    inlier_ratio: torch.Tensor
    match: torch.Tensor
    inlier: torch.Tensor


def _feature_distances(a: torch.Tensor, b: torch.Tensor, metric: str) -> torch.Tensor:
    if metric == "cosine":
        return 1.0 - F.normalize(a, dim=-1) @ F.normalize(b, dim=-1).transpose(-1, -2)
    return torch.cdist(a, b)


def mutual_nearest_neighbors(
    feat_a: torch.Tensor,
    feat_b: torch.Tensor,
    *,
    mask_a: torch.Tensor | None = None,
    mask_b: torch.Tensor | None = None,
    metric: str = "euclidean",
) -> torch.Tensor:
    """Mutual nearest neighbours between two batched feature sets.

    Args:
        feat_a: features ``(B, N, D)``.
        feat_b: features ``(B, M, D)``.
        mask_a: valid rows of ``feat_a`` ``(B, N)`` bool, or None.
        mask_b: valid rows of ``feat_b`` ``(B, M)`` bool, or None.
        metric: ``"euclidean"`` or ``"cosine"``.

    Returns:
        For every row of ``feat_b``, the index of its mutual nearest row of ``feat_a``, or -1;
        shape ``(B, M)`` long.

    Example:
        >>> a = torch.tensor([[[0.0, 0.0], [1.0, 0.0], [5.0, 5.0]]])
        >>> b = torch.tensor([[[0.9, 0.1], [0.1, 0.0], [0.2, 0.0]]])
        >>> mutual_nearest_neighbors(a, b)
        tensor([[ 1,  0, -1]])
    """
    if metric not in ("euclidean", "cosine"):
        raise ValueRangeError(f"metric must be 'euclidean' or 'cosine', got {metric!r}")
    sizes = check_tensor(feat_a, "feat_a", ("B", "N", "D"), finite=True)
    check_tensor(feat_b, "feat_b", ("B", "M", "D"), finite=True, sizes=sizes)
    check_same(("feat_a", feat_a), ("feat_b", feat_b))
    B, N, M = sizes["B"], sizes["N"], sizes["M"]
    if mask_a is None:
        mask_a = torch.ones(B, N, dtype=torch.bool, device=feat_a.device)
    if mask_b is None:
        mask_b = torch.ones(B, M, dtype=torch.bool, device=feat_a.device)
    check_mask(mask_a, "mask_a", ("B", "N"), sizes)
    check_mask(mask_b, "mask_b", ("B", "M"), sizes)
    inf = torch.tensor(float("inf"), dtype=feat_a.dtype, device=feat_a.device)
    best_b2a = torch.full((B, M), -1, dtype=torch.long, device=feat_a.device)
    min_a2b = torch.full((B, N), float("inf"), dtype=feat_a.dtype, device=feat_a.device)
    arg_a2b = torch.zeros(B, N, dtype=torch.long, device=feat_a.device)
    step = max(1, _CHUNK_ELEMENTS // max(1, N * B))
    for start in range(0, M, step):
        stop = min(M, start + step)
        d = _feature_distances(feat_b[:, start:stop], feat_a, metric)  # (B, m, N)
        d = torch.where(mask_a[:, None, :] & mask_b[:, start:stop, None], d, inf)
        best_b2a[:, start:stop] = d.argmin(dim=2)
        vals, args = d.min(dim=1)
        better = vals < min_a2b
        min_a2b = torch.where(better, vals, min_a2b)
        arg_a2b = torch.where(better, args + start, arg_a2b)
    back = arg_a2b.gather(1, best_b2a.clamp_min(0))
    rows = torch.arange(M, device=feat_a.device)[None]
    has_a = mask_a.any(dim=1, keepdim=True)
    mutual = (back == rows) & mask_b & has_a
    return torch.where(mutual, best_b2a, torch.full_like(best_b2a, -1))


def correspondence_inliers(
    feat_q: torch.Tensor,
    feat_t: torch.Tensor,
    q_points: torch.Tensor,
    t_points_canonical: torch.Tensor,
    diameter: torch.Tensor | float,
    threshold: float = 0.03,
    *,
    q_mask: torch.Tensor | None = None,
    t_mask: torch.Tensor | None = None,
    metric: str = "euclidean",
    equivalents: torch.Tensor | None = None,
) -> InlierResult:
    """Count the mutual-nearest-neighbour correspondences that the ground truth confirms.

    Args:
        feat_q: query (model) features ``(B, N, D)`` or ``(N, D)``.
        feat_t: target (scene) features ``(B, M, D)`` or ``(M, D)``.
        q_points: query points in the model frame ``(B, N, 3)`` or ``(N, 3)``.
        t_points_canonical: target points mapped into the model frame by the inverse GT pose,
            ``(B, M, 3)`` or ``(M, 3)``.
        diameter: object diameter(s), float or ``(B,)``, in the points' unit.
        threshold: inlier distance as a fraction of the diameter (paper: 0.03).
        q_mask: valid query points ``(B, N)``, or None.
        t_mask: valid target points ``(B, M)``, or None.
        metric: feature distance, ``"euclidean"`` (default) or ``"cosine"``.
        equivalents: maps ``[R | b]`` of the target's canonical points to their symmetric
            equivalents ``(B, K, 3, 4)`` or ``(K, 3, 4)``, the identity among them
            (:func:`~poseflow.models.inputs.equivalent_maps`, identity-padded); the inliers are
            those of the map that confirms the most. None: the ground truth as given.

    Returns:
        An :class:`InlierResult`; for unbatched input every field loses its leading dimension.

    Raises:
        ShapeError: shapes, dtypes or devices disagree.
        ValueRangeError: non-finite values, a non-positive diameter or threshold.

    Example:
        >>> q = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
        >>> feats = torch.eye(3)
        >>> r = correspondence_inliers(feats, feats[[1, 0, 2]], q, q + 0.01, 1.0, 0.03)
        >>> int(r.num_matches), int(r.num_inliers)
        (3, 1)
    """
    batched = feat_q.dim() == 3
    if not batched:
        feat_q, feat_t, q_points, t_points_canonical = (
            x.unsqueeze(0) for x in (feat_q, feat_t, q_points, t_points_canonical)
        )
        q_mask = None if q_mask is None else q_mask.unsqueeze(0)
        t_mask = None if t_mask is None else t_mask.unsqueeze(0)
        equivalents = None if equivalents is None else equivalents.unsqueeze(0)
    sizes = check_tensor(feat_q, "feat_q", ("B", "N", "D"), finite=True)
    check_tensor(feat_t, "feat_t", ("B", "M", "D"), finite=True, sizes=sizes)
    check_tensor(q_points, "q_points", ("B", "N", 3), finite=True, sizes=sizes)
    check_tensor(t_points_canonical, "t_points_canonical", ("B", "M", 3), finite=True, sizes=sizes)
    check_same(("q_points", q_points), ("t_points_canonical", t_points_canonical))
    check_same(("feat_q", feat_q), ("q_points", q_points), dtype=False)
    if equivalents is None:
        equivalents = torch.eye(3, 4, dtype=q_points.dtype, device=q_points.device)[None, None]
        equivalents = equivalents.expand(sizes["B"], 1, 3, 4)
    check_tensor(equivalents, "equivalents", ("B", "K", 3, 4), finite=True, sizes=sizes)
    check_same(("q_points", q_points), ("equivalents", equivalents))
    if threshold <= 0:
        raise ValueRangeError(f"threshold must be positive, got {threshold}")
    if isinstance(diameter, torch.Tensor):
        diam = diameter.to(device=q_points.device, dtype=q_points.dtype).reshape(-1)
        diam = diam.expand(sizes["B"]) if diam.numel() == 1 else diam
        check_tensor(diam, "diameter", ("B",), finite=True, sizes=sizes)
    else:
        diam = torch.full(
            (sizes["B"],), float(diameter), dtype=q_points.dtype, device=q_points.device
        )
    if not bool((diam > 0).all()):
        raise ValueRangeError(f"diameter must be positive, got {diam.tolist()}")
    match = mutual_nearest_neighbors(feat_q, feat_t, mask_a=q_mask, mask_b=t_mask, metric=metric)
    matched = match >= 0
    partner = q_points.gather(1, match.clamp_min(0)[..., None].expand(-1, -1, 3))
    # the target's canonical points under every equivalent ground truth (B, K, M, 3)
    alt = t_points_canonical[:, None] @ equivalents[..., :3].transpose(-1, -2)
    alt = alt + equivalents[..., None, :, 3]
    dist = (partner[:, None] - alt).norm(dim=-1)
    confirmed = matched[:, None] & (dist < threshold * diam[:, None, None])  # (B, K, M)
    best = confirmed.sum(dim=2).argmax(dim=1)
    inlier = confirmed[torch.arange(len(best), device=best.device), best]
    num_matches = matched.sum(dim=1)
    num_inliers = inlier.sum(dim=1)
    ratio = num_inliers.to(q_points.dtype) / num_matches.clamp_min(1).to(q_points.dtype)
    result = InlierResult(num_inliers, num_matches, ratio, match, inlier)
    if not batched:
        result = InlierResult(*(getattr(result, f)[0] for f in result.__dataclass_fields__))
    return result
