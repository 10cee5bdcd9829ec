"""Render-and-compare verification of FunFlow6D's poses, prepared per object and run per image.

The :class:`~poseflow.verify.PoseVerifier` is training-free: :func:`prepare_verification` gives
it every object (surface samples with colour and the near-symmetries, cached on disk beside the
object's other prepared data, in an entry keyed by the mesh and the verifier's fingerprint),
and :func:`verify_estimate` checks the poses of one image after the best hypothesis of each
instance was selected (optionally by the verifier itself,
:meth:`~poseflow.verify.PoseVerifier.rank_hypotheses`): each pose is expanded with its object's
near-symmetric candidates (and, optionally, the instance's other hypotheses,
:func:`other_hypotheses`), the best candidates are refined by ICP of the observed cloud, all are
rendered and compared with the image, and a candidate replaces the pose only where it explains
the image clearly better. The verifier's
score becomes the estimate's score. The stage is reported to the active timer as
``verification``.

Shape letters: ``B`` instances, ``H`` hypotheses per instance, ``N`` observed points.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path

import torch

from poseflow._progress import progress as progress_loop
from poseflow.data.frame import ImageInstances
from poseflow.data.objects import ObjectModel
from poseflow.errors import ValueRangeError
from poseflow.eval.predict import PoseEstimate
from poseflow.eval.timing import stage
from poseflow.geometry.se3 import inverse_transform
from poseflow.verify import PoseVerifier

__all__ = [
    "AGREEMENT_TOLERANCE",
    "Proposals",
    "keep_better",
    "other_hypotheses",
    "prepare_verification",
    "rank_estimate",
    "verify_estimate",
    "verify_proposals",
]


#: A proposal agrees with a pose within this fraction of the object's diameter (BOP's tightest
#: useful MSSD threshold): :meth:`Proposals.agreement`.
AGREEMENT_TOLERANCE = 0.1


@dataclass(frozen=True)
class Proposals:
    """The poses an image's verification chooses among, one row per instance.

    Attributes:
        estimate: each instance's incumbent pose ``(B, 4, 4)`` with its score and validity.
        others: more candidate poses of each instance ``(B, E, 4, 4)`` (``E`` may be 0).
        others_mask: ``(B, E)`` bool, False where a candidate is padding or invalid.
        observed: the observed clouds ``(B, N, 3)`` (camera frame, metres) the verifier's ICP
            registers; None lifts them from the depth.
        observed_mask: ``(B, N)`` bool, their valid points (None with ``observed``).
        rank: whether the verifier ranks the incumbent and ``others`` on its coarse score first
            (:meth:`~poseflow.verify.PoseVerifier.rank_hypotheses`) instead of keeping the
            incumbent as it is.

    Example:
        >>> est = PoseEstimate(torch.eye(4)[None], torch.ones(1), torch.tensor([False]))
        >>> other = PoseEstimate(torch.eye(4)[None] * 2, torch.ones(1) / 2, torch.tensor([True]))
        >>> p = Proposals(est, torch.zeros(1, 0, 4, 4), torch.zeros(1, 0, dtype=torch.bool))
        >>> both = p.with_rival(other)  # instance 0 twice: its own pose, then the rival's
        >>> both.estimate.valid.tolist(), keep_better(both.estimate).scores.tolist()
        ([False, True], [0.5])
    """

    estimate: PoseEstimate
    others: torch.Tensor
    others_mask: torch.Tensor
    observed: torch.Tensor | None = None
    observed_mask: torch.Tensor | None = None
    rank: bool = False

    def agreement(
        self,
        poses: torch.Tensor,
        points: torch.Tensor,
        diameters: torch.Tensor,
        *,
        tolerance: float = AGREEMENT_TOLERANCE,
    ) -> torch.Tensor:
        """``(B,)`` the share of each instance's proposals that agree with its pose ``(B, 4, 4)``.

        A proposal (the incumbent or a valid other) agrees when no point of the object moves
        by ``tolerance`` times its diameter or more between it and the pose (the MSSD without
        symmetries): with proposals drawn from the flow's posterior, the share estimates how
        sure the model is of the pose; a symmetric object's share is spread over its
        symmetric poses, which calibration (:class:`~poseflow.eval.ValidityRule`) takes into
        account per object.

        Args:
            poses: the instances' final poses ``(B, 4, 4)``.
            points: each instance's object surface points ``(B, N, 3)``, canonical frame.
            diameters: each instance's object diameter ``(B,)``.
            tolerance: the fraction of the diameter.

        Returns:
            ``(B,)`` float in ``[0, 1]`` (0 for an instance without a valid proposal).

        Example:
            >>> turned = torch.eye(4); turned[:3, :3] = torch.diag(torch.tensor([-1.0, -1, 1]))
            >>> est = PoseEstimate(torch.eye(4)[None], torch.ones(1), torch.ones(1).bool())
            >>> p = Proposals(est, torch.stack([torch.eye(4), turned])[None],
            ...               torch.ones(1, 2, dtype=torch.bool))
            >>> box = torch.tensor([[[0.05, 0.02, 0.0], [-0.05, -0.02, 0.0]]])
            >>> p.agreement(torch.eye(4)[None], box, torch.tensor([0.1])).mul(3).tolist()
            [2.0]
        """
        hyps = torch.cat((self.estimate.poses[:, None], self.others), 1).to(poses.dtype)
        mask = torch.cat((self.estimate.valid[:, None], self.others_mask), 1)
        p = points.to(poses)[:, None]  # (B, 1, N, 3)
        moved = p @ hyps[..., :3, :3].transpose(-1, -2) + hyps[..., None, :3, 3]  # (B, H, N, 3)
        final = p @ poses[:, None, :3, :3].transpose(-1, -2) + poses[:, None, None, :3, 3]
        reach = (moved - final).norm(dim=-1).amax(-1)  # (B, H)
        near = (reach < tolerance * diameters.to(poses)[:, None]) & mask
        return near.sum(1).to(poses.dtype) / mask.sum(1).clamp_min(1).to(poses.dtype)

    def with_rival(self, other: PoseEstimate) -> Proposals:
        """These ``B`` instances followed by the same ``B`` instances proposed by ``other``.

        Rows ``B + i`` hold ``other``'s pose of instance ``i`` as their incumbent, without
        other candidates (padding), so that one verification checks both estimators' poses,
        each with its own near-symmetric candidates, refinement and search; the caller keeps,
        per instance, the row the verifier scores higher (:func:`keep_better`).

        Args:
            other: another estimate of the same ``B`` instances (any float dtype).

        Returns:
            :class:`Proposals` of ``2B`` rows (the observed clouds repeated).
        """
        est = self.estimate
        dev, dt = est.poses.device, est.poses.dtype
        B, E = self.others.shape[:2]
        rival = PoseEstimate(
            other.poses.to(device=dev, dtype=dt),
            other.scores.to(device=dev, dtype=est.scores.dtype),
            other.valid.to(dev),
        )
        twice = lambda t: None if t is None else torch.cat((t, t))  # noqa: E731
        return Proposals(
            PoseEstimate(
                torch.cat((est.poses, rival.poses)),
                torch.cat((est.scores, rival.scores)),
                torch.cat((est.valid, rival.valid)),
            ),
            torch.cat((self.others, est.poses[:, None].expand(B, E, 4, 4))),
            torch.cat((self.others_mask, torch.zeros_like(self.others_mask))),
            twice(self.observed),
            twice(self.observed_mask),
            rank=self.rank,
        )


def keep_better(verified: PoseEstimate) -> PoseEstimate:
    """Per instance, the better of rows ``i`` and ``B + i`` of a :meth:`Proposals.with_rival`.

    The higher verifier score wins (the first row on a tie); an invalid row never does.

    Args:
        verified: the verified estimate of ``2B`` rows.

    Returns:
        The :class:`~poseflow.eval.predict.PoseEstimate` of the ``B`` instances.
    """
    B = len(verified.valid) // 2
    first = PoseEstimate(verified.poses[:B], verified.scores[:B], verified.valid[:B])
    second = PoseEstimate(verified.poses[B:], verified.scores[B:], verified.valid[B:])
    take = second.valid & (~first.valid | (second.scores > first.scores))
    return PoseEstimate(
        torch.where(take[:, None, None], second.poses, first.poses),
        torch.where(take, second.scores, first.scores),
        first.valid | second.valid,
    )


def prepare_verification(
    verifier: PoseVerifier,
    models: Mapping[int, ObjectModel],
    *,
    cache_dir: str | Path | None = None,
    progress: bool = True,
) -> None:
    """Prepare every object for ``verifier``, through the on-disk cache.

    An object the verifier already holds under the same id is prepared again from ``models``
    (or read from the cache), so that it always matches the mesh given last.

    Args:
        verifier: the verifier.
        models: ``{obj_id: ObjectModel}`` (metres, with colours).
        cache_dir: the prepared objects' folder (shared with
            :func:`~poseflow.models.objects.prepare_objects`: the verifier's entries
            ``obj_XXXXXX/<key>/`` of :func:`~poseflow.verify.cached_verifier_object` sit beside
            the objects' own); None keeps them in memory only. A cache folder that cannot be
            written gives a warning.
        progress: show a progress bar.
    """
    items = sorted(models.items())
    for obj_id, model in progress_loop(
        items, total=len(items), desc="prepare verifier", enabled=progress
    ):
        verifier.objects.pop(int(obj_id), None)
        verifier.prepare(obj_id, model, cache_dir=cache_dir)


def other_hypotheses(
    transform: torch.Tensor, score: torch.Tensor, valid: torch.Tensor, num_hypotheses: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """The hypotheses of each instance that the selection did not keep, as verifier candidates.

    Args:
        transform: camera-to-canonical transforms ``(B·H, 4, 4)`` of
            :func:`~poseflow.models.pose.solve_pose`, an instance's ``H`` rows consecutive.
        score: their scores ``(B·H,)``; the best of each instance is the one left out.
        valid: their validity ``(B·H,)``.
        num_hypotheses: ``H``.

    Returns:
        ``(poses (B, H-1, 4, 4), mask (B, H-1))``: model-to-camera poses, mask False where a
        hypothesis is invalid (its pose is then the identity).

    Example:
        >>> T = torch.eye(4).repeat(4, 1, 1); T[:, 0, 3] = torch.arange(1.0, 5.0)  # x = 1..4
        >>> poses, mask = other_hypotheses(T, torch.tensor([0.1, 0.9, 0.5, 0.2]),
        ...                                torch.tensor([True, True, True, False]), 2)
        >>> (-poses[:, 0, 0, 3]).tolist(), mask[:, 0].tolist()  # rows 0 and 3 (invalid: identity)
        ([1.0, 0.0], [True, False])
    """
    H = num_hypotheses
    B = len(transform) // H
    dev = transform.device
    best = score.reshape(B, H).argmax(dim=1)
    column = torch.arange(H, device=dev).expand(B, H)
    others = column[column != best[:, None]].reshape(B, H - 1)
    rows = others + torch.arange(B, device=dev)[:, None] * H
    ok = valid[rows] & torch.isfinite(transform[rows]).flatten(-2).all(-1)
    eye = torch.eye(4, dtype=transform.dtype, device=dev)
    poses = inverse_transform(torch.where(ok[..., None, None], transform[rows], eye))
    return poses, ok


def rank_estimate(
    verifier: PoseVerifier,
    estimate: PoseEstimate,
    extra: torch.Tensor,
    extra_mask: torch.Tensor,
    image: ImageInstances,
) -> tuple[PoseEstimate, torch.Tensor, torch.Tensor]:
    """Make each instance's best hypothesis by the verifier's score its estimate.

    :meth:`PoseVerifier.rank_hypotheses <poseflow.verify.PoseVerifier.rank_hypotheses>` of the
    estimate's poses and validity.

    Args:
        verifier: a verifier with every object of the image prepared.
        estimate: the estimator's choice ``(B, 4, 4)`` with its validity.
        extra: the other hypotheses ``(B, E, 4, 4)`` (:func:`other_hypotheses`).
        extra_mask: ``(B, E)`` bool.
        image: the image ``(3, Hi, Wi)``, depth ``(Hi, Wi)``, ``K`` ``(3, 3)``, and the ``B``
            instances' masks ``(B, Hi, Wi)`` and object ids ``(B,)``.

    Returns:
        ``(estimate, extra, extra_mask)`` with each instance's best hypothesis swapped into
        the estimate (an instance whose estimate is invalid is left as it is); the estimate's
        scores and validity are kept.
    """
    ranked = verifier.rank_hypotheses(
        image, estimate.poses, extra=extra, extra_mask=extra_mask, estimated=estimate.valid
    )
    chosen = PoseEstimate(ranked.poses[:, 0], estimate.scores, estimate.valid)
    return chosen, ranked.poses[:, 1:], ranked.mask[:, 1:]


def verify_estimate(
    verifier: PoseVerifier,
    estimate: PoseEstimate,
    image: ImageInstances,
    observed: torch.Tensor | None,
    observed_mask: torch.Tensor | None,
    *,
    extra: torch.Tensor | None = None,
    extra_mask: torch.Tensor | None = None,
) -> PoseEstimate:
    """Verify the poses of one image's instances; the verifier's score becomes their score.

    Args:
        verifier: a verifier with every object of the image prepared.
        estimate: the selected poses ``(B, 4, 4)``, scores and validity of the instances.
        image: the image ``(3, Hi, Wi)`` (uint8 or float in ``[0, 1]``), depth ``(Hi, Wi)`` in
            metres, ``K`` ``(3, 3)``, and the ``B`` instances' masks ``(B, Hi, Wi)`` bool and
            object ids ``(B,)``.
        observed: the observed clouds ``(B, N, 3)``, camera frame, metres (ICP's source; the
            verifier thins them to ``max_observed_points``); None lifts them from the depth.
        observed_mask: ``(B, N)`` bool, their valid points.
        extra: more candidates per instance ``(B, E, 4, 4)`` (e.g. :func:`other_hypotheses`).
        extra_mask: ``(B, E)`` bool for ``extra``.

    Returns:
        A :class:`~poseflow.eval.predict.PoseEstimate`: the verified poses, the verifier's
        scores in ``[0, 1]`` (0 where it could not score the pose) and the estimate's validity
        (instances without a pose are not verified).

    Raises:
        ValueRangeError: an object the verifier has not prepared.
    """
    ids = [int(o) for o in torch.as_tensor(image.obj_ids).reshape(-1).tolist()]
    missing = sorted(set(ids) - set(verifier.objects))
    if missing:
        raise ValueRangeError(
            f"objects {missing} are not prepared for verification; call prepare_objects with "
            "verification on (or turn verification off)"
        )
    with stage("verification"):
        out = verifier.verify(
            replace(image, obj_ids=ids), estimate.poses, (observed, observed_mask),
            extra=extra, extra_mask=extra_mask, estimated=estimate.valid,
        )  # fmt: skip
    return PoseEstimate(out.poses, out.scores.to(estimate.scores.dtype), estimate.valid)


def verify_proposals(
    verifier: PoseVerifier, proposals: Proposals, image: ImageInstances
) -> PoseEstimate:
    """Choose and verify each instance's pose among its proposals, in one verification.

    With ``proposals.rank`` (and candidates to rank), :func:`rank_estimate` makes the best
    proposal by the verifier's score the incumbent first; then :func:`verify_estimate`
    checks it against its near-symmetric candidates and the other proposals.

    Args:
        verifier: a verifier with every object of the image prepared.
        proposals: the instances' :class:`Proposals`.
        image: the image and its ``B`` instances.

    Returns:
        The verified :class:`~poseflow.eval.predict.PoseEstimate`.
    """
    est, extra, extra_mask = proposals.estimate, proposals.others, proposals.others_mask
    if extra.shape[1] == 0:
        extra = extra_mask = None
    elif proposals.rank:
        with stage("verification"):
            est, extra, extra_mask = rank_estimate(verifier, est, extra, extra_mask, image)
    return verify_estimate(
        verifier, est, image, proposals.observed, proposals.observed_mask,
        extra=extra, extra_mask=extra_mask,
    )  # fmt: skip
