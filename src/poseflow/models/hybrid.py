"""The hybrid estimator: FunFlow6D's hypotheses and the classic baseline's pose under one verifier.

The learned flow and the geometric pipeline fail on different instances (the flow on shapes whose
local geometry decides the pose, the baseline on turns that only the print decides), and the
render-and-compare verifier tells which of their poses explains the image. :class:`Hybrid` checks
both estimators' proposals of each instance in one batched verification: the flow's ``H``
hypotheses (:meth:`FunFlow6D.propose <poseflow.models.FunFlow6D.propose>`), ranked by the
verifier, and the baseline's ICP-refined pose
(:meth:`ClassicBaseline.solve <poseflow.baselines.ClassicBaseline.solve>`) each enter as an
incumbent of their own (:meth:`Proposals.with_rival
<poseflow.models.verification.Proposals.with_rival>`), expanded with its near-symmetric
candidates, refined, tested and searched, and the pose the verifier scores higher is kept
(:func:`~poseflow.models.verification.keep_better`). The two pipelines share the image, the
observed clouds, the verifier's prepared objects and one batch of its renderings and ICP.

Ranking both estimators' poses as candidates of one incumbent was measured too and is worse where
the flow's best-ranked hypothesis is a wrong turn: the baseline's pose then never gets its own
near-symmetric candidates (``benchmarks/LOG.md``).

Shape letters: ``B`` instances of an image.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from poseflow.baselines import ClassicBaseline
from poseflow.errors import ValueRangeError
from poseflow.eval.predict import Estimator, PoseEstimate, predict_seeded, seeded_estimator
from poseflow.eval.results import PoseResults
from poseflow.models.funflow6d import FunFlow6D
from poseflow.models.verification import keep_better

__all__ = ["Hybrid"]


class Hybrid:
    """FunFlow6D and the classic baseline as one estimator, their poses chosen by one verifier.

    Args:
        model: a FunFlow6D with its objects prepared and a ``config.verifier``; its verifier
            chooses.
        baseline: the classic baseline of the same objects; its own verification is not used.

    Raises:
        ValueRangeError: no verifier in ``model.config``, or an object the model has
            prepared that the baseline has no model of.

    Example:
        >>> from poseflow.data import demo_objects  # doctest: +SKIP
        >>> hybrid = Hybrid(model, ClassicBaseline(objects))  # doctest: +SKIP
        >>> estimate = hybrid.estimate(rgb, depth, K, masks, obj_ids)  # doctest: +SKIP
    """

    def __init__(self, model: FunFlow6D, baseline: ClassicBaseline) -> None:
        if model.config.verifier is None:
            raise ValueRangeError(
                "the hybrid estimator chooses by render-and-compare verification: set "
                "config.verifier"
            )
        missing = sorted(set(model.objects) - set(baseline.models))
        if missing:
            raise ValueRangeError(f"the baseline has no model of objects {missing}")
        self.model = model
        self.baseline = baseline

    @torch.no_grad()
    def estimate(
        self,
        rgb: torch.Tensor,
        depth: torch.Tensor,
        K: torch.Tensor,
        masks: torch.Tensor,
        obj_ids: torch.Tensor | Sequence[int],
        *,
        generator: torch.Generator | None = None,
    ) -> PoseEstimate:
        """Estimate the pose of every masked instance of one RGBD image.

        Args:
            rgb: the image ``(3, H, W)``, uint8 or float in ``[0, 1]``.
            depth: depth ``(H, W)`` in metres.
            K: intrinsics ``(3, 3)``: a tensor, an array, nested lists or 9 numbers.
            masks: instance masks ``(B, H, W)`` bool (``B`` may be 0).
            obj_ids: object id of each mask ``(B,)``.
            generator: seeds the flow's noise, its sampling of the clouds and RANSAC (the
                baseline seeds each instance from its own ``seed``).

        Returns:
            The verified :class:`~poseflow.eval.predict.PoseEstimate` (float32), the verifier's
            scores; an instance is valid where either estimator found a pose.

        Raises:
            UnitsError: the masked depth spans far more or far less than the objects.
        """
        proposals = self.model.propose(rgb, depth, K, masks, obj_ids, generator=generator)
        if proposals.estimate.poses.shape[0] == 0:
            return proposals.estimate
        classic, _ = self.baseline.solve(depth.cpu(), K, masks.cpu(), obj_ids)
        both = proposals.with_rival(classic)
        ids = torch.as_tensor(obj_ids).reshape(-1)
        out = self.model.verify(
            both, rgb, depth, K, torch.cat((masks, masks)), torch.cat((ids, ids))
        )
        return keep_better(out)

    def estimator(self, *, seed: int = 0, generator: torch.Generator | None = None) -> Estimator:
        """This estimator as an :data:`~poseflow.eval.predict.Estimator` of one generator.

        See :func:`~poseflow.eval.predict.seeded_estimator`.
        """
        return seeded_estimator(self.estimate, self.model.device, seed=seed, generator=generator)

    def predict(self, dataset: str | Path | Any, *, seed: int = 0, **options: Any) -> PoseResults:
        """Estimate every target instance of a BOP split: :func:`~poseflow.eval.predict_seeded`.

        Arguments as :meth:`FunFlow6D.predict <poseflow.models.FunFlow6D.predict>`.
        """
        return predict_seeded(
            lambda generator: self.estimator(generator=generator),
            dataset,
            device=self.model.device,
            object_ids=sorted(self.model.objects),
            seed=seed,
            **options,
        )
