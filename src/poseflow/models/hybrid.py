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

The hybrid spends more time for accuracy than FunFlow6D alone: :func:`full_grid_ranking` (what
``poseflow predict --method hybrid`` applies) scores every candidate on the verifier's full grid
rather than its coarse one, where a thin deciding part (a mug's handle) is a pixel or two wide.

Ranking both estimators' poses as candidates of one incumbent was measured too and is worse where
the flow's best-ranked hypothesis is a wrong turn: the baseline's pose then never gets its own
near-symmetric candidates (``benchmarks/LOG.md``).

Shape letters: ``B`` instances of an image.
"""

from __future__ import annotations

from dataclasses import replace

import torch

from poseflow.baselines import ClassicBaseline
from poseflow.data.frame import ImageInstances
from poseflow.errors import ValueRangeError
from poseflow.eval.predict import PoseEstimate, SeededEstimator
from poseflow.models.config import FunFlow6DConfig
from poseflow.models.funflow6d import FunFlow6D
from poseflow.models.verification import keep_better

__all__ = ["Hybrid", "full_grid_ranking"]


def full_grid_ranking(config: FunFlow6DConfig) -> FunFlow6DConfig:
    """``config`` with its verifier's coarse grid as fine as its full one.

    Every hypothesis and candidate is then scored at ``crop_size`` (about 10 % more time per
    image for the hybrid). Set it before :meth:`FunFlow6D.prepare_objects
    <poseflow.models.FunFlow6D.prepare_objects>`, which builds the verifier.

    Raises:
        ValueRangeError: ``config`` has no verifier.

    Example:
        >>> full_grid_ranking(FunFlow6DConfig.recipe("learned_small")).verifier.coarse_crop_size
        64
    """
    if config.verifier is None:
        raise ValueRangeError("full-grid ranking needs config.verifier")
    return config.with_inference({"verifier.coarse_crop_size": config.verifier.crop_size})


class Hybrid(SeededEstimator):
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

    @property
    def device(self) -> torch.device:
        """The model's device."""
        return self.model.device

    def _object_ids(self) -> list[int]:
        return sorted(self.model.objects)

    def _estimate(self, image: ImageInstances, generator: torch.Generator | None) -> PoseEstimate:
        """Both estimators' proposals of every instance, verified in one batch; the better kept.

        ``generator`` seeds the flow's noise, its sampling of the clouds and RANSAC (the
        baseline seeds each instance from its own ``seed``). The verifier's scores become the
        estimate's; an instance is valid where either estimator found a pose, and its
        agreement is that of the flow's proposals with the kept pose.
        """
        proposals = self.model.propose(image, generator=generator)
        if proposals.estimate.poses.shape[0] == 0:
            return proposals.estimate
        on_cpu = replace(image, rgb=None, depth=image.depth.cpu(), masks=image.masks.cpu())
        classic, _ = self.baseline.solve(on_cpu)
        best = keep_better(self.model.verify(proposals.with_rival(classic), image.twice()))
        return replace(best, agreement=self.model.agreement(proposals, best.poses, image.obj_ids))
