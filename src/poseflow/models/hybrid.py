"""The hybrid estimator: FunFlow6D's hypotheses and the classic baseline's pose under one verifier.

The learned flow and the geometric pipeline fail on different instances (the flow on shapes whose
local geometry decides the pose, the baseline on turns that only the print decides), and the
render-and-compare verifier tells which of their poses explains the image. :class:`Hybrid` pools
both estimators' proposals of each instance into one verification: the flow's ``H`` hypotheses
(:meth:`FunFlow6D.propose <poseflow.models.FunFlow6D.propose>`) and the baseline's ICP-refined
pose (:meth:`ClassicBaseline.solve <poseflow.baselines.ClassicBaseline.solve>`) are ranked by the
verifier's coarse score, the best is expanded with its near-symmetric candidates, refined and
tested, exactly as FunFlow6D's own hypotheses are; the two pipelines share the image, the
verifier's prepared objects, its crops, renderings and ICP.

Shape letters: ``B`` instances of an image.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from poseflow.baselines import ClassicBaseline
from poseflow.errors import ValueRangeError
from poseflow.eval.predict import Estimator, PoseEstimate, on_device
from poseflow.eval.results import PoseResults
from poseflow.eval.timing import StageTimer
from poseflow.models.funflow6d import FunFlow6D, predict_seeded

__all__ = ["Hybrid"]


class Hybrid:
    """FunFlow6D and the classic baseline as one estimator, their poses chosen by one verifier.

    Args:
        model: a FunFlow6D with its objects prepared and ``config.verification`` on; its
            verifier (``config.verifier``) chooses.
        baseline: the classic baseline of the same objects; its own verification is not used.

    Raises:
        ValueRangeError: verification off in ``model.config``, or an object the model has
            prepared that the baseline has no model of.

    Example:
        >>> from poseflow.data import demo_objects  # doctest: +SKIP
        >>> hybrid = Hybrid(model, ClassicBaseline(objects))  # doctest: +SKIP
        >>> estimate = hybrid.estimate(rgb, depth, K, masks, obj_ids)  # doctest: +SKIP
    """

    def __init__(self, model: FunFlow6D, baseline: ClassicBaseline) -> None:
        if not model.config.verification:
            raise ValueRangeError(
                "the hybrid estimator chooses by render-and-compare verification: turn "
                "config.verification on"
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
        """
        proposals = self.model.propose(rgb, depth, K, masks, obj_ids, generator=generator)
        if proposals.estimate.poses.shape[0] == 0:
            return proposals.estimate
        classic, _ = self.baseline.solve(depth.cpu(), K, masks.cpu(), obj_ids)
        pooled = proposals.pooled(classic)
        return self.model.verify(pooled, rgb, depth, K, masks, obj_ids)

    def estimator(self, *, seed: int = 0, generator: torch.Generator | None = None) -> Estimator:
        """This estimator as an :data:`~poseflow.eval.predict.Estimator` of one generator.

        See :meth:`FunFlow6D.estimator <poseflow.models.FunFlow6D.estimator>`.
        """
        device = next(self.model.net.parameters()).device
        if generator is None:
            generator = torch.Generator(device=device).manual_seed(seed)
        return on_device(functools.partial(self.estimate, generator=generator), device)

    def predict(
        self,
        dataset: str | Path | Any,
        *,
        split: str = "test",
        targets: Sequence[Any] | None = None,
        detections: Sequence[Any] | None = None,
        max_images: int | None = None,
        seed: int = 0,
        timer: StageTimer | None = None,
        progress: bool = False,
    ) -> PoseResults:
        """Estimate every target instance of a BOP split.

        Arguments as :meth:`FunFlow6D.predict <poseflow.models.FunFlow6D.predict>`.
        """
        return predict_seeded(
            lambda generator: self.estimator(generator=generator),
            next(self.model.net.parameters()).device,
            dataset,
            object_ids=sorted(self.model.objects),
            split=split,
            targets=targets,
            detections=detections,
            max_images=max_images,
            seed=seed,
            timer=timer,
            progress=progress,
        )
