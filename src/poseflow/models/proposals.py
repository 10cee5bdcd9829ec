"""The flow's pose proposals of one image: ``H`` sampled flows per instance, each solved for a pose.

:func:`flow_proposals` integrates the velocity net from noise ``H`` times per instance (one batch
of ``B·H`` samples), solves every sample for a pose (:func:`~poseflow.models.pose.solve_pose`),
keeps the best by the solver's score as the incumbent and, when the verifier ranks hypotheses,
the others as its candidates: the :class:`~poseflow.models.verification.Proposals` that
:meth:`FunFlow6D.verify <poseflow.models.FunFlow6D.verify>` checks. With a surface embedding as
the appearance encoder, its own matches (:func:`surface_match_positions`) are one more
hypothesis of each instance, solved alongside the flow's: the embedding and the flow fail on
different instances, and the verifier tells which pose explains the image.

Shape letters: ``B`` instances, ``H`` hypotheses per instance, ``N`` points per cloud, ``Nd``
dense surface points.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch
from torch.nn.utils.rnn import pad_sequence

from poseflow.errors import ValueRangeError
from poseflow.eval.predict import PoseEstimate, invalidate_implausible
from poseflow.eval.timing import stage
from poseflow.features import match_surface
from poseflow.flows import get_sampler
from poseflow.models.config import FunFlow6DConfig
from poseflow.models.inputs import FlowInputs
from poseflow.models.network import FunFlow6DNet
from poseflow.models.objects import PreparedObject, select_objects
from poseflow.models.observe import Observation
from poseflow.models.pose import dense_targets, select_hypotheses, solve_pose
from poseflow.models.verification import Proposals, other_hypotheses

__all__ = ["flow_proposals", "has_surface_keys", "no_proposals", "surface_match_positions"]


def no_proposals(device: torch.device | str | None = None) -> Proposals:
    """The proposals of an image without instances (``B = 0``)."""
    est = PoseEstimate.empty(device=device)
    return Proposals(est, est.poses[:, None][:, :0], est.valid[:, None][:, :0])


def surface_match_positions(
    obs: Observation, objects: Sequence[PreparedObject], scale: torch.Tensor
) -> torch.Tensor:
    """Each target point's canonical position by the surface embedding's best key match.

    Args:
        obs: the observation; its ``appearance`` ``(B, N, G)`` are the embedding's queries.
        objects: the prepared object of every instance (``B``), with their ``dense_keys``.
        scale: the half diameter ``s`` of every instance's object ``(B,)``.

    Returns:
        ``(B, N, 3)``: the dense surface point (model frame) whose key matches each target
        point best, divided by ``s`` (the flow's ``T̂ / s``).

    Raises:
        ValueRangeError: the observation has no appearance features or an object has no keys
            (its appearance encoder is not a surface embedding).
    """
    if not has_surface_keys(obs, objects):
        raise ValueRangeError(
            "surface matches need a surface embedding as the appearance encoder "
            "(appearance_encoder='surface:FOLDER')"
        )
    points, key_mask = dense_targets([o.dense_points for o in objects], scale)
    keys = pad_sequence([o.dense_keys for o in objects], batch_first=True)  # type: ignore[misc]
    index, _ = match_surface(obs.appearance, keys.to(scale.device), key_mask)  # type: ignore[arg-type]
    return torch.gather(points, 1, index[..., None].expand(-1, -1, 3))


def has_surface_keys(obs: Observation, objects: Sequence[PreparedObject]) -> bool:
    """Whether every instance can be matched to its object's surface keys (a surface embedding)."""
    return obs.appearance is not None and all(o.dense_keys is not None for o in objects)


def flow_proposals(
    net: FunFlow6DNet,
    inputs: FlowInputs,
    obs: Observation,
    objects: Mapping[int, PreparedObject],
    config: FunFlow6DConfig,
    generator: torch.Generator,
) -> Proposals:
    """Sample ``H = config.num_hypotheses`` flows per instance and solve each for a pose.

    With ``config.match_hypothesis`` and a surface embedding's keys on the objects, the
    embedding's matches (:func:`surface_match_positions`) are solved as an ``H+1``-th
    hypothesis of each instance.

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
        (``(B, H, 4, 4)`` with the match hypothesis) when ranked, and the observation's cleaned
        clouds for the verifier's ICP.
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
    B, n = inputs.points.shape[0], inputs.points.shape[1] // 2
    predicted = x_1[:, n:].reshape(B, H, n, 3)
    prepared = select_objects(objects, inputs.obj_ids)
    if config.match_hypothesis and has_surface_keys(obs, prepared):
        with stage("matching"):
            matched = surface_match_positions(obs, prepared, inputs.scale)
        predicted = torch.cat([predicted, matched[:, None].to(predicted)], 1)
    rows = predicted.shape[1]  # hypotheses per instance
    rep = inputs.repeat_interleave(rows)
    dense = [o.dense_points for o in prepared for _ in range(rows)]
    solved = solve_pose(rep, predicted.flatten(0, 1), dense, config, generator=generator)
    est = select_hypotheses(*solved, obs.valid, rows)
    est = invalidate_implausible(est)  # nothing behind the camera is verified
    rank = config.verifier is not None and config.verifier.rank_hypotheses and rows > 1
    if rank:
        others, others_mask = other_hypotheses(*solved, rows)
    else:
        others, others_mask = est.poses[:, None][:, :0], est.valid[:, None][:, :0]
    return Proposals(est, others, others_mask, obs.cloud, obs.cloud_mask, rank=rank)
