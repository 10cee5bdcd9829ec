"""The flow's pose proposals of one image: ``H`` sampled flows per instance, each solved for a pose.

:func:`flow_proposals` integrates the velocity net from noise ``H`` times per instance (one batch
of ``B·H`` samples), solves every sample for a pose (:func:`~poseflow.models.pose.solve_pose`),
keeps the best by the solver's score as the incumbent and, when the verifier ranks hypotheses,
the others as its candidates: the :class:`~poseflow.models.verification.Proposals` that
:meth:`FunFlow6D.verify <poseflow.models.FunFlow6D.verify>` checks.

Shape letters: ``B`` instances, ``H`` hypotheses per instance, ``N`` points per cloud.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch

from poseflow.eval.predict import PoseEstimate, invalidate_implausible
from poseflow.flows import get_sampler
from poseflow.models.config import FunFlow6DConfig
from poseflow.models.inputs import FlowInputs
from poseflow.models.network import FunFlow6DNet
from poseflow.models.objects import PreparedObject, select_objects
from poseflow.models.observe import Observation
from poseflow.models.pose import select_hypotheses, solve_pose
from poseflow.models.verification import Proposals, other_hypotheses

__all__ = ["flow_proposals", "no_proposals"]


def no_proposals(device: torch.device | str | None = None) -> Proposals:
    """The proposals of an image without instances (``B = 0``)."""
    est = PoseEstimate.empty(device=device)
    return Proposals(est, est.poses[:, None][:, :0], est.valid[:, None][:, :0])


def flow_proposals(
    net: FunFlow6DNet,
    inputs: FlowInputs,
    obs: Observation,
    objects: Mapping[int, PreparedObject],
    config: FunFlow6DConfig,
    generator: torch.Generator,
) -> Proposals:
    """Sample ``H = config.num_hypotheses`` flows per instance and solve each for a pose.

    Args:
        net: the velocity net.
        inputs: the flow inputs of the ``B`` instances.
        obs: their observation (its validity ``(B,)`` and cleaned clouds ``(B, P, 3)``).
        objects: the prepared objects, ``{obj_id: PreparedObject}``.
        config: the sampler (``solver``, ``steps``, ``anchor``, ``flow_precision``), the pose
            solver's settings and the verifier, whose ``rank_hypotheses`` keeps the other
            hypotheses as candidates.
        generator: seeds the noise and the pose solver's draws.

    Returns:
        :class:`~poseflow.models.verification.Proposals` of the ``B`` instances: the best
        hypothesis each (a pose behind the camera flagged invalid), the others ``(B, H-1, 4, 4)``
        when ranked, and the observation's cleaned clouds for the verifier's ICP.
    """
    H = config.num_hypotheses
    x_1 = net.sample(
        inputs,
        get_sampler(config.solver, steps=config.steps),
        frozen_mask=inputs.frozen_mask,
        x_frozen=inputs.anchor if config.anchor == "pinned" else None,
        generator=generator,
        num_samples=H,
        precision=config.flow_precision,
    )
    rep = inputs.repeat_interleave(H)
    dense = [o.dense_points for o in select_objects(objects, rep.obj_ids)]
    n = rep.points.shape[1] // 2
    solved = solve_pose(rep, x_1[:, n:], dense, config, generator=generator)
    est = select_hypotheses(*solved, obs.valid, H)
    est = invalidate_implausible(est)  # nothing behind the camera is verified
    rank = config.verifier is not None and config.verifier.rank_hypotheses and H > 1
    if rank:
        others, others_mask = other_hypotheses(*solved, H)
    else:
        others, others_mask = est.poses[:, None][:, :0], est.valid[:, None][:, :0]
    return Proposals(est, others, others_mask, obs.cloud, obs.cloud_mask, rank=rank)
