"""What the verifier returns: hypotheses, and the verification of one image's instances.

Shape letters: B instances, H hypotheses per instance, G blocks of a crop.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch

from poseflow.verify.score import VerifierScore, select_significant

__all__ = ["Hypotheses", "Verification"]


@dataclass
class Hypotheses:
    """Pose hypotheses of ``B`` instances, padded to ``H`` each.

    Attributes:
        poses: model-to-camera transforms ``(B, H, 4, 4)``; hypothesis 0 is the estimate.
        mask: ``(B, H)`` bool, False for padding (a copy of the estimate).
    """

    poses: torch.Tensor
    mask: torch.Tensor


@dataclass
class Verification:
    """The outcome of :meth:`~poseflow.verify.PoseVerifier.verify` for ``B`` instances.

    Attributes:
        poses: the chosen poses ``(B, 4, 4)``: the estimate where it was kept (ICP-refined with
            ``refine_estimate``, else unchanged), else the ICP-refined candidate or searched turn
            that beat it; polished (:meth:`~poseflow.verify.PoseScorer.polish`) where the
            verifier's ``polish_levels`` is not 0, so then not equal to ``hypotheses[chosen]``.
        scores: the chosen pose's total score clipped to ``[0, 1]`` ``(B,)`` (0 where
            invalid), for ranking estimates.
        valid: ``(B,)`` bool, whether the chosen hypothesis could be scored.
        chosen: ``(B,)`` int64, the index of the chosen hypothesis in ``hypotheses`` (0: the
            estimate was kept).
        hypotheses: the finally scored hypotheses ``(B, H, 4, 4)``: the estimate (refined with
            ``refine_estimate``), then the refined candidates, then, with ``search_below`` on,
            the ``search_top_k`` refined turns and, with ``search_slides``, as many refined
            slides of :meth:`~poseflow.verify.PoseVerifier.search` (invalid where the instance
            was not searched).
        score: their scores.
        statistic: each candidate's test statistic against the estimate ``(B, H)`` (a searched
            turn's against the pose it was turned from).
    """

    poses: torch.Tensor
    scores: torch.Tensor
    valid: torch.Tensor
    chosen: torch.Tensor
    hypotheses: torch.Tensor
    score: VerifierScore
    statistic: torch.Tensor

    @classmethod
    def select(
        cls, hypotheses: torch.Tensor, score: VerifierScore, *, significance: float
    ) -> Verification:
        """The verification of scored hypotheses ``(B, H, 4, 4)``, the incumbent first.

        The incumbent is kept unless a candidate beats it significantly
        (:func:`~poseflow.verify.select_significant`).
        """
        index, stat = select_significant(score, significance=significance)
        rows = torch.arange(hypotheses.shape[0], device=hypotheses.device)
        total, valid = score.total[rows, index], score.valid[rows, index]
        return cls(
            poses=hypotheses[rows, index],
            scores=torch.where(valid, total.clamp(0, 1), 0.0),
            valid=valid,
            chosen=index,
            hypotheses=hypotheses,
            score=score,
            statistic=stat,
        )

    @classmethod
    def unscored(cls, hypotheses: torch.Tensor, blocks: int) -> Verification:
        """The verification of unscored hypotheses ``(B, H, 4, 4)``: the first kept, invalid.

        Their scores are 0, on ``blocks`` blocks each.

        Example:
            >>> out = Verification.unscored(torch.eye(4).expand(2, 3, 4, 4), 16)
            >>> out.poses.shape, out.valid.tolist(), out.score.evidence.shape
            (torch.Size([2, 4, 4]), [False, False], torch.Size([2, 3, 16]))
        """
        B, H = hypotheses.shape[:2]
        score = VerifierScore.zeros(B, H, blocks, like=hypotheses)
        return cls(
            poses=hypotheses[:, 0].clone(),
            scores=hypotheses.new_zeros(B),
            valid=torch.zeros(B, dtype=torch.bool, device=hypotheses.device),
            chosen=torch.zeros(B, dtype=torch.long, device=hypotheses.device),
            hypotheses=hypotheses.clone(),
            score=score,
            statistic=hypotheses.new_zeros(B, H),
        )

    def widened(self, k: int) -> Verification:
        """A copy with ``k`` more hypotheses per instance, unscored: the chosen pose repeated."""
        B = self.poses.shape[0]
        score = VerifierScore(*(
            torch.cat((t, t.new_zeros(B, k, *t.shape[2:])), dim=1)
            for t in (getattr(self.score, f.name) for f in fields(self.score))
        ))  # fmt: skip
        return Verification(
            self.poses.clone(), self.scores.clone(), self.valid.clone(), self.chosen.clone(),
            torch.cat((self.hypotheses, self.poses[:, None].expand(B, k, 4, 4)), dim=1),
            score, torch.cat((self.statistic, self.statistic.new_zeros(B, k)), dim=1),
        )  # fmt: skip

    def scatter(
        self,
        rows: torch.Tensor,
        part: Verification,
        *,
        column: int = 0,
        skip: int = 0,
        where: torch.Tensor | None = None,
    ) -> None:
        """Write ``part``, the verification of the instances ``rows``, into this one.

        Args:
            rows: the instances ``part`` holds ``(B',)`` int64.
            part: their verification.
            column: where ``part``'s hypotheses go in each row's.
            skip: ``part``'s hypotheses left out, its first ``skip``.
            where: ``(B',)`` bool, the instances whose choice is taken (default all); ``chosen``
                is shifted to index this verification's hypotheses.
        """
        cols = slice(column, column + part.hypotheses.shape[1] - skip)
        self.hypotheses[rows, cols] = part.hypotheses[:, skip:]
        for f in fields(part.score):
            getattr(self.score, f.name)[rows, cols] = getattr(part.score, f.name)[:, skip:]
        self.statistic[rows, cols] = part.statistic[:, skip:]
        taken = slice(None) if where is None else where
        into = rows[taken]
        self.poses[into] = part.poses[taken]
        self.scores[into] = part.scores[taken]
        self.valid[into] = part.valid[taken]
        self.chosen[into] = part.chosen[taken] + (column - skip)
