"""From the flow's prediction to poses: correspondences, RANSAC-Procrustes, ICP and the score.

The flow predicts, for every observed target point ``T`` (normalised, see
:mod:`poseflow.models.inputs`), its canonical position ``T̂``. :func:`solve_pose` registers ``T``
onto ``T̂`` (RANSAC-Procrustes, or one Procrustes), refines the transform by coarse-to-fine ICP
of ``T`` onto the object's dense surface cloud (:func:`dense_targets`), scores it
(:func:`agreement_score`) and undoes the normalisation; :func:`select_hypotheses` keeps each
instance's best-scoring hypothesis and turns it into the model-to-camera pose. The stages are
reported to the active timer as ``ransac`` and ``icp``.

Distances: a fraction ``f`` of the diameter is ``2f`` in normalised units (``s = d / 2``).

Shape letters: ``B`` rows (instances × hypotheses), ``N`` target points, ``Nd`` dense model
points, ``H`` hypotheses per instance.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from poseflow.eval.predict import PoseEstimate
from poseflow.eval.timing import stage
from poseflow.geometry.neighbors import nearest_neighbors
from poseflow.geometry.se3 import from_Rt, inverse_transform, transform_points
from poseflow.models.config import FunFlow6DConfig
from poseflow.models.inputs import FlowInputs
from poseflow.registration import multi_scale_icp, procrustes, ransac_procrustes

__all__ = ["agreement_score", "dense_targets", "select_hypotheses", "solve_pose"]


def agreement_score(
    source: torch.Tensor,
    mask: torch.Tensor,
    transform: torch.Tensor,
    dense: torch.Tensor,
    dense_mask: torch.Tensor,
    *,
    max_distance: float,
) -> torch.Tensor:
    """Fraction of the valid source points that land within ``max_distance`` of the target.

    Args:
        source: the observed clouds ``(B, N, 3)``.
        mask: their valid points ``(B, N)``.
        transform: source-to-target transforms ``(B, 4, 4)``.
        dense: the target clouds (model surfaces) ``(B, Nd, 3)``.
        dense_mask: their valid points ``(B, Nd)``.
        max_distance: the inlier distance, in the clouds' unit.

    Returns:
        Scores in ``[0, 1]`` ``(B,)`` (0 for a source without valid points).

    Example:
        >>> pts = torch.rand(1, 10, 3)
        >>> ok = torch.ones(1, 10, dtype=torch.bool)
        >>> float(agreement_score(pts, ok, torch.eye(4)[None], pts, ok, max_distance=1e-6))
        1.0
    """
    moved = transform_points(transform, source)
    dist, _ = nearest_neighbors(moved, dense, k=1, reference_mask=dense_mask)
    close = (dist[..., 0] <= max_distance) & mask
    return close.sum(1) / mask.sum(1).clamp_min(1)


def dense_targets(
    clouds: Sequence[torch.Tensor], scale: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The ICP targets: each row's dense model cloud, normalised by its scale and padded.

    Args:
        clouds: ``B`` dense model clouds ``(Nd_b, 3)``, metres.
        scale: the half diameter of each row's object ``(B,)``.

    Returns:
        ``(dense, dense_mask)``: ``(B, max Nd_b, 3)`` in ``scale``'s dtype and device, and the
        padding mask ``(B, max Nd_b)``.
    """
    dev, dt = scale.device, scale.dtype
    size = max(len(c) for c in clouds)
    dense = torch.zeros(len(clouds), size, 3, dtype=dt, device=dev)
    dense_mask = torch.zeros(len(clouds), size, dtype=torch.bool, device=dev)
    for b, c in enumerate(clouds):
        dense[b, : len(c)] = c.to(dev, dt) / scale[b]
        dense_mask[b, : len(c)] = True
    return dense, dense_mask


def solve_pose(
    inputs: FlowInputs,
    predicted: torch.Tensor,
    dense_clouds: Sequence[torch.Tensor],
    config: FunFlow6DConfig,
    *,
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Register each observed target onto its predicted canonical position, refine and score.

    Args:
        inputs: the flow inputs of the rows (``points``, ``mask``, ``scale``, ``centroid``).
        predicted: the flow's target half ``T̂ / s`` ``(B, N, 3)``.
        dense_clouds: each row's dense model cloud (metres), the ICP target.
        config: ``pose_solver``, ``ransac_iterations``, ``ransac_distance``,
            ``icp_distances`` and ``icp_iterations``.
        generator: seeds RANSAC.

    Returns:
        ``(transform, score, valid)``: camera-to-canonical transforms ``(B, 4, 4)`` in metres,
        scores ``(B,)`` (RANSAC fitness times :func:`agreement_score`) and validity ``(B,)``.
    """
    n = predicted.shape[1]
    source = inputs.points[:, n:]
    mask = inputs.mask[:, n:]
    scale, centroid = inputs.scale, inputs.centroid
    with stage("ransac"):
        if config.pose_solver == "ransac":
            rr = ransac_procrustes(
                source,
                predicted,
                mask,
                max_correspondence_distance=2 * config.ransac_distance,
                max_iterations=config.ransac_iterations,
                generator=generator,
            )
            T, score, ok = rr.transformation, rr.fitness, rr.valid
        else:
            T, ok = procrustes(source, predicted, mask=mask)
            score = torch.ones(len(T), dtype=T.dtype, device=T.device)
    dense, dense_mask = dense_targets(dense_clouds, scale)
    if config.icp_distances:
        with stage("icp"):
            ir = multi_scale_icp(
                source,
                dense,
                T,
                max_correspondence_distances=[2 * f for f in config.icp_distances],
                max_iterations=config.icp_iterations,
                source_mask=mask,
                target_mask=dense_mask,
            )
            T = torch.where(ir.valid[:, None, None], ir.transformation, T)
    score = score * agreement_score(
        source, mask, T, dense, dense_mask, max_distance=2 * config.ransac_distance
    )
    # Undo the normalisation: canonical = R (x - c) + s t'  =>  t = s t' - R c.
    R, t = T[:, :3, :3], T[:, :3, 3]
    t = scale[:, None] * t - (R @ centroid[..., None]).squeeze(-1)
    return from_Rt(R, t), score, ok


def select_hypotheses(
    transform: torch.Tensor,
    score: torch.Tensor,
    valid: torch.Tensor,
    observed: torch.Tensor,
    num_hypotheses: int,
) -> PoseEstimate:
    """Keep each instance's best-scoring hypothesis, as a model-to-camera pose.

    Args:
        transform: camera-to-canonical transforms ``(B·H, 4, 4)``, the ``H`` hypotheses of an
            instance in consecutive rows.
        score: their scores ``(B·H,)``.
        valid: their validity ``(B·H,)``.
        observed: instances with enough observed points ``(B,)``.
        num_hypotheses: ``H``.

    Returns:
        The :class:`~poseflow.eval.predict.PoseEstimate` of the ``B`` instances (identity pose
        and zero score where invalid).
    """
    H = num_hypotheses
    B = len(transform) // H
    dev, dt = transform.device, transform.dtype
    best = score.reshape(B, H).argmax(dim=1) + torch.arange(B, device=dev) * H
    transform, score, ok = transform[best], score[best], valid[best]
    ok = ok & observed.to(dev)
    poses = inverse_transform(transform)
    eye = torch.eye(4, dtype=dt, device=dev).expand(B, 4, 4)
    poses = torch.where(ok[:, None, None], poses, eye)
    return PoseEstimate(poses, torch.where(ok, score, torch.zeros_like(score)), ok)
