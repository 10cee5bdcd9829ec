"""Flow inputs: the tensors of ``[Q ; T]`` that sampling, training and pose solving share.

Coordinates. Every cloud enters the flow divided by its object's half diameter ``s = d / 2``:
the query ``Q`` in its canonical frame, the observed target ``T`` centred on its barycentre
``c``. The flow carries ``(T - c) / s`` to ``T̂ / s`` with ``T̂ ≈ Tʳ = Rᵀ (T - t)`` and the pose
solvers work in the same unit, so one threshold (a fraction of the diameter) serves all objects.

Semantic features. The raw appearance features of the target and the query's multi-view bank go
through the object's fitted reducer (:func:`reduce_appearance`); instances of one object are
reduced together. The time is reported as the ``reducer`` stage of the active timer.

Shape letters: ``B`` instances, ``N`` points per cloud (``2N`` tokens ``[Q ; T]``), ``Dg`` /
``Ds`` geometric / semantic channels, ``G`` raw appearance channels.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from poseflow._checks import check_tensor
from poseflow.errors import ValueRangeError
from poseflow.eval.timing import stage
from poseflow.models.network import NetInputs
from poseflow.models.objects import PreparedObject
from poseflow.models.observe import Observation

__all__ = [
    "OPTIONAL_TRAINING_FIELDS",
    "TRAINING_FIELDS",
    "FlowInputs",
    "equivalent_maps",
    "reduce_appearance",
]


@dataclass(kw_only=True)
class FlowInputs(NetInputs):
    """The network's inputs for ``[Q ; T]`` and what sampling, training and pose solving add.

    The network's part is a :class:`~poseflow.models.network.NetInputs`; everything is
    normalised as the module docstring says.

    Attributes:
        mask: ``(B, 2N)`` bool, True at valid points (every query point; the target's valid ones).
        frozen_mask: ``(B, 2N)`` bool, True at the query's points (the anchor the flow keeps).
        anchor: ``[Q ; 0]`` ``(B, 2N, 3)``: where the anchor sits when it is pinned.
        scale: half diameter ``s`` of each instance's object ``(B,)``, metres.
        centroid: barycentre ``c`` of each observed target ``(B, 3)``, camera frame, metres.
        obj_ids: object of each instance ``(B,)``.
        x_1: the flow's end state ``[Q ; Tʳ / s]`` ``(B, 2N, 3)`` when poses are given
            (training), else None.

    The other attributes (``geometric``, ``semantic``, ``points``, ``normals``) are those of
    :class:`~poseflow.models.network.NetInputs`.
    """

    mask: torch.Tensor
    frozen_mask: torch.Tensor
    anchor: torch.Tensor
    scale: torch.Tensor
    centroid: torch.Tensor
    obj_ids: torch.Tensor
    x_1: torch.Tensor | None = None

    @classmethod
    def from_observation(
        cls,
        obs: Observation,
        objects: Sequence[PreparedObject],
        poses: torch.Tensor | None = None,
        *,
        query_pooling: str = "mean",
    ) -> FlowInputs:
        """Pair every observed target with its object's query cloud.

        Args:
            obs: the observation.
            objects: the prepared object of every instance (``B``).
            poses: ground-truth model-to-camera poses ``(B, 4, 4)`` (training only): fills
                :attr:`x_1`.
            query_pooling: the appearance encoder's ``query_pooling`` (see
                :func:`reduce_appearance`).

        Returns:
            The flow inputs, on the observation's device and dtype.
        """
        B, n = obs.points.shape[:2]
        dev, dt = obs.points.device, obs.points.dtype
        scale = torch.tensor([o.diameter / 2 for o in objects], dtype=dt, device=dev)
        mask_t = obs.mask & obs.valid[:, None]
        w = mask_t.to(dt)[..., None]
        centroid = (obs.points * w).sum(1) / w.sum(1).clamp_min(1.0)
        q_pts = torch.stack([o.points for o in objects]).to(dev, dt)
        q_nrm = torch.stack([o.normals for o in objects]).to(dev, dt)
        t_pts = (obs.points - centroid[:, None]) / scale[:, None, None]
        q_n = q_pts / scale[:, None, None]
        semantic = geometric = None  # (query, target) descriptors of each stream
        if obs.appearance is not None:
            with stage("reducer"):
                semantic = reduce_appearance(
                    objects, obs.appearance, mask_t, query_pooling=query_pooling
                )
        if obs.geometric is not None:
            geometric_q = torch.stack([o.geometric for o in objects])  # type: ignore[misc]
            geometric = (geometric_q.to(dev, dt), obs.geometric)
        # A stream without an encoder is fed the other one's descriptors.
        geometric, semantic = geometric or semantic, semantic or geometric
        if geometric is None or semantic is None:
            raise ValueRangeError("an observation needs geometric or appearance features")
        ones = torch.ones(B, n, dtype=torch.bool, device=dev)
        x_1 = None
        if poses is not None:
            check_tensor(poses, "poses", (B, 4, 4))
            R, t = poses[:, :3, :3].to(dt), poses[:, :3, 3].to(dt)
            t_canon = (obs.points - t[:, None]) @ R  # Rᵀ (T - t), row-vector form
            x_1 = torch.cat([q_n, t_canon / scale[:, None, None]], 1)
        return cls(
            geometric=torch.cat(geometric, 1),
            semantic=torch.cat(semantic, 1),
            points=torch.cat([q_n, t_pts], 1),
            normals=torch.cat([q_nrm, obs.normals], 1),
            mask=torch.cat([ones, mask_t], 1),
            frozen_mask=torch.cat([ones, ~ones], 1),
            anchor=torch.cat([q_n, torch.zeros_like(t_pts)], 1),
            scale=scale,
            centroid=centroid,
            obj_ids=obs.obj_ids.to(dev),
            x_1=x_1,
        )


#: The tensors a training set keeps per instance: the flow's end state and anchor mask, under
#: the names :class:`~poseflow.flows.FlowBatch` reads, and the network's inputs.
TRAINING_FIELDS: tuple[str, ...] = ("x_1", "frozen_mask", *NetInputs.field_names())

#: What a training set keeps when some object is symmetric: the maps from each instance's
#: ``x_1`` to its symmetric equivalents ``(I, K, 3, 4)`` (see :func:`equivalent_maps`).
OPTIONAL_TRAINING_FIELDS: tuple[str, ...] = ("equivalents",)


def equivalent_maps(symmetries: torch.Tensor, scale: float) -> torch.Tensor:
    """The maps that carry a target's flow end state to its symmetric equivalents.

    For a model symmetry ``S = (R_s, t_s)`` the pose ``P S`` shows the object as ``P`` does, and
    the target's canonical points become ``S⁻¹ Tʳ``; in the flow's unit (``/ s``) that is
    ``x ↦ R_sᵀ x − R_sᵀ t_s / s``, stored as ``[R_sᵀ | −R_sᵀ t_s / s]`` for
    :func:`~poseflow.flows.equivalents.nearest_equivalent`.

    Args:
        symmetries: the object's symmetries ``(S, 4, 4)``, metres, the identity among them
            (:attr:`~poseflow.data.objects.ObjectModel.symmetries`).
        scale: the object's half diameter ``s``, metres.

    Returns:
        ``(S, 3, 4)`` in the dtype of ``symmetries``.

    Example:
        >>> flip = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0]))
        >>> flip[2, 3] = 0.02
        >>> m = equivalent_maps(torch.stack([torch.eye(4), flip]), 0.05)[1]
        >>> m[:, :3].diagonal().tolist(), [round(v, 4) + 0.0 for v in m[:, 3].tolist()]
        ([1.0, -1.0, -1.0], [0.0, 0.0, 0.4])
    """
    check_tensor(symmetries, "symmetries", ("S", 4, 4))
    if not scale > 0:
        raise ValueRangeError(f"scale must be positive, got {scale}")
    Rt = symmetries[:, :3, :3].transpose(1, 2)
    b = -(Rt @ symmetries[:, :3, 3:]) / scale
    return torch.cat([Rt, b], dim=2)


def reduce_appearance(
    objects: Sequence[PreparedObject],
    appearance: torch.Tensor,
    mask: torch.Tensor,
    *,
    query_pooling: str = "mean",
) -> tuple[torch.Tensor, torch.Tensor]:
    """Reduced appearance features of the query and the target of every instance.

    Instances of the same object go through its bank and reducer together.

    Args:
        objects: the prepared object of every instance (``B``), each with a bank and a reducer.
        appearance: raw target features ``(B, N, G)``.
        mask: valid target points ``(B, N)``; an instance without any uses all its points.
        query_pooling: ``"mean"``: the query's features are its bank's view average;
            ``"select"``: the bank's views that match each target are kept (see
            :meth:`~poseflow.features.QueryFeatureBank.select`).

    Returns:
        ``(semantic_q, semantic_t)``, each ``(B, N, Ds)``.
    """
    mask = mask | ~mask.any(dim=1, keepdim=True)
    rows, reduced_q, reduced_t = [], [], []
    for obj in {id(o): o for o in objects}.values():
        idx = torch.tensor([b for b, o in enumerate(objects) if o is obj], device=appearance.device)
        feats_t, m = appearance[idx], mask[idx]
        bank, reducer = obj.bank, obj.reducer
        if bank is None or reducer is None:
            raise ValueRangeError(
                "appearance features need objects prepared with an appearance encoder"
            )
        if query_pooling == "select":
            feats_q = bank.select(feats_t, m)
        else:
            feats_q = bank.pooled().to(feats_t).expand(len(idx), -1, -1)
        reduced_q.append(reducer.transform(feats_q.to(feats_t)))
        reduced_t.append(reducer.transform(feats_t, m))
        rows.append(idx)
    order = torch.cat(rows).argsort()  # back to the instances' order
    return torch.cat(reduced_q)[order], torch.cat(reduced_t)[order]
