"""BOP 2019 recall: targets, top-k estimates, greedy matching, recall pooled over targets.

The protocol, as the BOP toolkit implements it for the 6D localisation task:

1. **Targets** are ``(scene_id, im_id, obj_id, inst_count)`` records (``test_targets_bop19.json``),
   or, when a dataset has no such file, the objects with at least one instance of visible fraction
   >= 0.1 in an image, ``inst_count`` being the number of such instances (:func:`targets_from_gt`).
2. For each target, only the ``inst_count`` estimates of that object in that image with the highest
   scores are evaluated (:func:`assign`); estimates of other images or objects are ignored. Ties in
   score keep the order of the results file (a stable sort, as in the toolkit).
3. The ``inst_count`` most visible GT instances of the object are *valid*; the others can be neither
   matched nor missed.
4. In order of decreasing score, each estimate is matched to the valid, still unmatched GT instance
   with the lowest error, provided that error is strictly below the threshold (:func:`match`).
5. Recall = matched valid instances / valid instances, pooled over all targets of the dataset (not
   averaged per object); it is computed for every threshold (and every VSD ``tau``) and the average
   recall is its mean.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch

from poseflow._checks import check_tensor
from poseflow.errors import ShapeError, ValueRangeError

__all__ = ["Assignment", "Recall", "Target", "assign", "match", "targets_from_gt"]

#: Minimum visible fraction of a GT instance for it to become a target (BOP 2019).
VISIB_MIN = 0.1

ImageKey = tuple[int, int]


@dataclass(frozen=True)
class Target:
    """One estimation target: ``inst_count`` instances of ``obj_id`` to find in one image."""

    scene_id: int
    im_id: int
    obj_id: int
    inst_count: int


def targets_from_gt(
    gts: Mapping[ImageKey, Sequence[tuple[int, float]]], *, visib_min: float = VISIB_MIN
) -> list[Target]:
    """Derive targets from GT visibility, as BOP does when writing ``test_targets_bop19.json``.

    Args:
        gts: for each ``(scene_id, im_id)``, its GT instances as ``(obj_id, visib_fract)`` pairs in
            ``scene_gt.json`` order.
        visib_min: minimum visible fraction of a counted instance.

    Returns:
        Targets sorted by scene, image and object; objects without a visible enough instance in an
        image are no target there.

    Example:
        >>> targets = targets_from_gt({(1, 0): [(5, 0.9), (5, 0.05), (7, 0.3)]})
        >>> [(t.obj_id, t.inst_count) for t in targets]
        [(5, 1), (7, 1)]
    """
    out = []
    for (scene_id, im_id), inst in sorted(gts.items()):
        counts: dict[int, int] = defaultdict(int)
        for obj_id, visib in inst:
            if visib >= visib_min:
                counts[int(obj_id)] += 1
        out.extend(Target(int(scene_id), int(im_id), o, n) for o, n in sorted(counts.items()))
    return out


@dataclass
class Assignment:
    """Which estimates are compared with which GT instances, one row per target.

    Attributes:
        targets: the ``R`` targets.
        est_index: indices into the estimate list, in decreasing score, shape ``(R, E)``, -1 pads.
        gt_index: GT instance ids (positions in the image's ``scene_gt`` list) of the target's
            object, shape ``(R, G)``, -1 pads.
        gt_valid: which of those instances count (the ``inst_count`` most visible), ``(R, G)``.
    """

    targets: list[Target]
    est_index: torch.Tensor
    gt_index: torch.Tensor
    gt_valid: torch.Tensor

    @property
    def num_targets(self) -> int:
        """Number of valid GT instances: the denominator of the recall."""
        return int(self.gt_valid.sum())

    def pairs(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Every (estimate, GT instance) pair whose error is needed.

        Returns:
            ``(row, e, g, est, gt)``, each of shape ``(P,)``: the target row, the estimate's rank
            and the GT's column in the padded layout, the estimate's index in the input list and
            the GT instance id.
        """
        both = (self.est_index >= 0)[:, :, None] & (self.gt_index >= 0)[:, None, :]
        row, e, g = torch.nonzero(both, as_tuple=True)
        return row, e, g, self.est_index[row, e], self.gt_index[row, g]


def assign(
    targets: Sequence[Target],
    gts: Mapping[ImageKey, Sequence[tuple[int, float]]],
    est_scene_ids: Sequence[int] | torch.Tensor,
    est_im_ids: Sequence[int] | torch.Tensor,
    est_obj_ids: Sequence[int] | torch.Tensor,
    est_scores: Sequence[float] | torch.Tensor,
) -> Assignment:
    """Select the top ``inst_count`` estimates of every target and its valid GT instances.

    Args:
        targets: the estimation targets.
        gts: for each ``(scene_id, im_id)``, its GT instances as ``(obj_id, visib_fract)`` pairs in
            ``scene_gt.json`` order (the position is the GT id).
        est_scene_ids: scene of each estimate, length ``E``.
        est_im_ids: image of each estimate.
        est_obj_ids: object of each estimate.
        est_scores: confidence of each estimate.

    Returns:
        The :class:`Assignment`.

    Raises:
        ShapeError: the estimate columns differ in length.
        ValueRangeError: a target's image is missing from ``gts`` or its ``inst_count`` is < 1.

    Example:
        >>> a = assign([Target(1, 0, 5, 1)], {(1, 0): [(5, 0.8)]}, [1, 1, 2], [0, 0, 0], [5, 5, 5],
        ...            [0.2, 0.9, 1.0])
        >>> a.est_index, a.gt_index, a.gt_valid
        (tensor([[1]]), tensor([[0]]), tensor([[True]]))
    """
    cols = [torch.as_tensor(c).reshape(-1) for c in (est_scene_ids, est_im_ids, est_obj_ids)]
    scores = torch.as_tensor(est_scores, dtype=torch.float64).reshape(-1)
    if any(c.numel() != scores.numel() for c in cols):
        raise ShapeError("estimate scene, image, object and score columns must have one length")
    groups: dict[tuple[int, int, int], list[int]] = defaultdict(list)
    # Stable sort by decreasing score: ties keep the order of the results file.
    order = torch.sort(scores, descending=True, stable=True).indices.tolist()
    keys = torch.stack([c.long() for c in cols], 1).tolist() if scores.numel() else []
    for i in order:
        groups[tuple(keys[i])].append(i)  # type: ignore[index]
    est_rows, gt_rows, valid_rows = [], [], []
    for t in targets:
        if t.inst_count < 1:
            raise ValueRangeError(f"target {t} must have inst_count >= 1")
        inst = gts.get((t.scene_id, t.im_id))
        if inst is None:
            raise ValueRangeError(f"no ground truth for scene {t.scene_id}, image {t.im_id}")
        est_rows.append(groups.get((t.scene_id, t.im_id, t.obj_id), [])[: t.inst_count])
        ids = [g for g, (obj, _) in enumerate(inst) if int(obj) == t.obj_id]
        by_visib = sorted(ids, key=lambda g: -float(inst[g][1]))  # stable: ties by GT id
        chosen = set(by_visib[: t.inst_count])
        gt_rows.append(ids)
        valid_rows.append([g in chosen for g in ids])
    return Assignment(
        targets=list(targets),
        est_index=_pad(est_rows, -1, torch.long),
        gt_index=_pad(gt_rows, -1, torch.long),
        gt_valid=_pad(valid_rows, False, torch.bool),
    )


def _pad(rows: list[list], fill: object, dtype: torch.dtype) -> torch.Tensor:
    width = max((len(r) for r in rows), default=0)
    out = torch.full((len(rows), width), fill, dtype=dtype)  # type: ignore[arg-type]
    for i, r in enumerate(rows):
        if r:
            out[i, : len(r)] = torch.tensor(r, dtype=dtype)
    return out


@dataclass
class Recall:
    """Recall of one error function at every threshold (and every variant, e.g. VSD's ``tau``).

    Attributes:
        thresholds: correctness thresholds, shape ``(Th,)``.
        recall: pooled recall, shape ``(V, Th)`` (``V`` variants of the error).
        true_positives: matched valid GT instances, shape ``(V, Th)``.
        num_targets: valid GT instances over all targets.
        per_object: object id -> recall of that object's targets, shape ``(V, Th)``.
        per_object_targets: object id -> its number of valid GT instances.
    """

    thresholds: torch.Tensor
    recall: torch.Tensor
    true_positives: torch.Tensor
    num_targets: int
    per_object: dict[int, torch.Tensor]
    per_object_targets: dict[int, int]

    @property
    def average(self) -> float:
        """Average recall: the mean over thresholds and variants."""
        return float(self.recall.mean())

    def object_average(self, obj_id: int) -> float:
        """Average recall of one object's targets."""
        return float(self.per_object[obj_id].mean())


def match(
    assignment: Assignment,
    pair_errors: torch.Tensor,
    thresholds: Sequence[float] | torch.Tensor,
) -> Recall:
    """Greedy matching in order of decreasing score, for all thresholds and variants at once.

    Args:
        assignment: from :func:`assign`.
        pair_errors: errors of the pairs listed by :meth:`Assignment.pairs`, shape ``(P, V)`` (or
            ``(P,)`` for one variant), already normalised (MSSD by the diameter, MSPD to a 640 px
            width); inf is allowed and never correct.
        thresholds: correctness thresholds; an error is correct when strictly below.

    Returns:
        The :class:`Recall`.

    Raises:
        ShapeError: ``pair_errors`` does not have one row per pair.
        ValueRangeError: an error is NaN.

    Example:
        >>> a = assign([Target(1, 0, 5, 1)], {(1, 0): [(5, 0.8)]}, [1], [0], [5], [1.0])
        >>> match(a, torch.tensor([0.12]), [0.1, 0.2]).recall.tolist()
        [[0.0, 1.0]]
    """
    row, e, g, _, _ = assignment.pairs()
    errs = pair_errors[:, None] if pair_errors.dim() == 1 else pair_errors
    check_tensor(errs, "pair_errors", (row.numel(), "V"))
    if bool(errs.isnan().any()):
        raise ValueRangeError("pair_errors contains NaN")
    th = torch.as_tensor(thresholds, dtype=torch.float64).reshape(-1)
    R, E = assignment.est_index.shape
    G = assignment.gt_index.shape[1]
    V = errs.shape[1]
    full = torch.full((R, E, G, V), float("inf"), dtype=torch.float64)
    full[row, e, g] = errs.detach().to("cpu", torch.float64)
    valid = assignment.gt_valid[:, None, None, :]  # (R, 1, 1, G)
    matched = torch.zeros(R, V, th.numel(), G, dtype=torch.bool)
    for rank in range(E):
        cur = full[:, rank].transpose(1, 2)[:, :, None, :]  # (R, V, 1, G)
        cand = valid & ~matched & (cur < th[None, None, :, None])
        best = torch.where(cand, cur, torch.full_like(cur, float("inf"))).argmin(-1, keepdim=True)
        hit = cand.any(-1, keepdim=True)
        matched |= torch.zeros_like(matched).scatter_(-1, best, hit)
    tp_rows = (matched & valid).sum(-1)  # (R, V, Th)
    n_rows = assignment.gt_valid.sum(-1)  # (R,)
    obj = torch.tensor([t.obj_id for t in assignment.targets], dtype=torch.long)
    per_object, per_object_targets = {}, {}
    for o in sorted(set(obj.tolist())):
        sel = obj == o
        n = int(n_rows[sel].sum())
        per_object_targets[o] = n
        per_object[o] = _ratio(tp_rows[sel].sum(0), n)
    tp = tp_rows.sum(0)
    total = int(n_rows.sum())
    return Recall(th, _ratio(tp, total), tp, total, per_object, per_object_targets)


def _ratio(tp: torch.Tensor, n: int) -> torch.Tensor:
    """Recall, 0 when there are no targets (as the toolkit)."""
    return tp.to(torch.float64) / n if n > 0 else torch.zeros(tp.shape, dtype=torch.float64)
