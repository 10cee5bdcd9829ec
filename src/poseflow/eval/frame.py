"""Poses of one RGB-D frame: run any estimator, vet its poses, write them as JSON.

:func:`estimate_frame` is what ``poseflow estimate`` does with a
:class:`~poseflow.data.frame.Frame`: it checks that each object's size agrees with its depth
(a mesh and a depth image in different units give themselves away), runs an
:data:`~poseflow.eval.predict.Estimator` (FunFlow6D's or the classic baseline's) on all
instances at once, and flags as invalid every pose that puts the object behind the camera
(``t_z <= 0``) or is not finite. :func:`write_poses_json` writes the result with ``R``, ``t`` in
metres and millimetres, the score and the validity of each instance.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import torch

from poseflow._units import check_depth_extent, check_size_against_depth, in_front_of_camera
from poseflow.data.frame import Frame
from poseflow.errors import ShapeError
from poseflow.eval.predict import Estimator, PoseEstimate, invalidate_implausible

__all__ = ["FramePoses", "estimate_frame", "write_poses_json"]


@dataclass
class FramePoses:
    """The estimates of the instances of one frame.

    Attributes:
        obj_ids: object of each instance ``(B,)`` int64.
        poses: model-to-camera transforms ``(B, 4, 4)`` float64, metres.
        scores: confidences ``(B,)`` float64 (0 where invalid).
        valid: ``(B,)`` bool.
        notes: why each invalid instance is invalid (empty for valid ones).
        sources: where each instance's mask came from.
        seconds: wall-clock time of the estimator call.
        agreement: ``(B,)`` float64, the share of the estimator's hypotheses that agree with
            each pose (:class:`~poseflow.eval.predict.PoseEstimate`), or None.
    """

    obj_ids: torch.Tensor
    poses: torch.Tensor
    scores: torch.Tensor
    valid: torch.Tensor
    notes: list[str] = field(default_factory=list)
    sources: list[str] = field(default_factory=list)
    seconds: float = 0.0
    agreement: torch.Tensor | None = None

    def __len__(self) -> int:
        return int(self.obj_ids.shape[0])

    def to_json(self) -> list[dict[str, Any]]:
        """One JSON object per instance.

        Keys: ``obj_id``, ``R`` (3x3 rows), ``t_m``, ``t_mm``, ``score``, ``valid``, ``note``
        and ``source``, and ``agreement`` where the estimator gives one.
        """
        out = []
        for i in range(len(self)):
            T = self.poses[i]
            extra = {} if self.agreement is None else {"agreement": float(self.agreement[i])}
            out.append(
                {
                    "obj_id": int(self.obj_ids[i]),
                    "R": T[:3, :3].tolist(),
                    "t_m": T[:3, 3].tolist(),
                    "t_mm": (1000.0 * T[:3, 3]).tolist(),
                    "score": float(self.scores[i]),
                    "valid": bool(self.valid[i]),
                    "note": self.notes[i] if i < len(self.notes) else "",
                    "source": self.sources[i] if i < len(self.sources) else "",
                    **extra,
                }
            )
        return out


def estimate_frame(
    estimator: Estimator,
    frame: Frame,
    *,
    diameters: Mapping[int, float] | None = None,
) -> FramePoses:
    """Estimate the pose of every instance of a frame and vet the poses.

    Args:
        estimator: any :data:`~poseflow.eval.predict.Estimator`, e.g. ``model.estimator()`` of
            a FunFlow6D model whose objects are prepared, or ``ClassicBaseline(...).estimator()``.
        frame: the frame (:func:`~poseflow.data.frame.read_frame`).
        diameters: ``{obj_id: diameter in metres}``; when given, the depth inside the masks
            must span about as much as the objects (:func:`~poseflow._units.check_depth_extent`:
            a depth off by a power of ten gives itself away), and each object must be no larger
            than twice the median depth of its mask (else the units of the mesh and the depth
            differ).

    Returns:
        :class:`FramePoses`; a pose behind the camera or not finite is never valid.

    Raises:
        UnitsError: an object's size disagrees with its depth (the message gives the
            ``depth_scale=`` of :func:`~poseflow.data.frame.read_frame` that fixes it).
        ShapeError: the estimator returned the wrong number of poses.

    Example:
        >>> from poseflow.eval.predict import PoseEstimate
        >>> T = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1); T[0, 2, 3] = 0.6
        >>> T[1, 2, 3] = -0.6  # behind the camera
        >>> fake = lambda rgb, depth, K, masks, ids: PoseEstimate(
        ...     T, torch.ones(2, dtype=torch.float64), torch.ones(2, dtype=torch.bool))
        >>> frame = Frame(torch.zeros(3, 4, 4, dtype=torch.uint8), torch.full((4, 4), 0.6),
        ...               torch.eye(3), torch.ones(2, 4, 4, dtype=torch.bool),
        ...               torch.tensor([1, 1]), torch.ones(2))
        >>> out = estimate_frame(fake, frame)
        >>> out.valid.tolist(), out.notes[1]
        ([True, False], 'the pose puts the object behind the camera (t_z = -0.6 m)')
    """
    B = len(frame)
    if B == 0:
        z = torch.zeros(0, dtype=torch.float64)
        return FramePoses(
            torch.zeros(0, dtype=torch.long),
            torch.zeros(0, 4, 4, dtype=torch.float64),
            z,
            torch.zeros(0, dtype=torch.bool),
        )
    if diameters is not None:
        _check_units(frame, diameters)
    start = time.perf_counter()
    est = estimator(frame.rgb, frame.depth, frame.K, frame.masks, frame.obj_ids)
    seconds = time.perf_counter() - start
    poses = est.poses.detach().to("cpu", torch.float64)
    if poses.shape != (B, 4, 4):
        raise ShapeError(f"the estimator returned poses of shape {tuple(poses.shape)} for {B}")
    found = est.valid.detach().cpu().bool()
    checked = invalidate_implausible(
        PoseEstimate(poses, est.scores.detach().to("cpu", torch.float64), found)
    )
    return FramePoses(
        frame.obj_ids.clone(),
        poses,
        checked.scores,
        checked.valid,
        _notes(poses, found),
        list(frame.sources),
        seconds,
        None if est.agreement is None else est.agreement.detach().to("cpu", torch.float64),
    )


def _check_units(frame: Frame, diameters: Mapping[int, float]) -> None:
    """Check the frame's masked depth against its objects' diameters (``{obj_id: metres}``).

    Raises:
        UnitsError: the depth inside the masks spans far more or less than the objects, or an
            object is larger than twice the median depth of its mask.
    """
    check_depth_extent(
        frame.depth,
        frame.K,
        frame.masks,
        [float(diameters.get(int(o), float("nan"))) for o in frame.obj_ids.tolist()],
        where="the frame's depth",
        scale_name="depth_scale=",
        scale=frame.depth_scale,
    )
    for i in range(len(frame)):
        obj = int(frame.obj_ids[i])
        d = frame.depth[frame.masks[i]]
        d = d[torch.isfinite(d) & (d > 0)]
        if obj in diameters and d.numel():
            check_size_against_depth(
                float(diameters[obj]),
                float(d.median()),
                where=f"object {obj} ({frame.sources[i] if i < len(frame.sources) else i})",
            )


def _notes(poses: torch.Tensor, found: torch.Tensor) -> list[str]:
    """Why each pose ``(B, 4, 4)`` is invalid ('' if valid), given the estimator's ``found``."""
    finite = torch.isfinite(poses).flatten(1).all(1)
    z = poses[:, 2, 3]
    # an estimator that applied the rule itself returns a rejected pose flagged invalid
    behind = finite & ~in_front_of_camera(poses) & (found | (z < 0))
    notes = []
    for i in range(poses.shape[0]):
        if bool(behind[i]):
            notes.append(f"the pose puts the object behind the camera (t_z = {float(z[i]):g} m)")
        elif not bool(found[i]):
            notes.append("no pose found (too few depth points or no consensus)")
        elif not bool(finite[i]):
            notes.append("the pose is not finite")
        else:
            notes.append("")
    return notes


def write_poses_json(
    path: str | os.PathLike[str], poses: FramePoses, *, meta: Mapping[str, Any] | None = None
) -> None:
    """Write the poses of a frame as JSON: ``{"poses": [...], **meta}``.

    Each pose is an object with ``obj_id``, ``R`` (rows of the rotation, model to camera),
    ``t_m`` and ``t_mm`` (the translation in metres and millimetres), ``score``, ``valid``,
    ``note`` (why it is invalid) and ``source`` (its mask).

    Example:
        >>> import tempfile, pathlib
        >>> p = pathlib.Path(tempfile.mkdtemp()) / "poses.json"
        >>> T = torch.eye(4, dtype=torch.float64)[None].clone(); T[0, 2, 3] = 0.5
        >>> fp = FramePoses(torch.tensor([1]), T, torch.ones(1, dtype=torch.float64),
        ...                 torch.ones(1, dtype=torch.bool))
        >>> write_poses_json(p, fp, meta={"method": "baseline"})
        >>> data = json.loads(p.read_text())
        >>> data["poses"][0]["t_mm"], data["method"]
        ([0.0, 0.0, 500.0], 'baseline')
    """
    data = {"poses": poses.to_json(), "seconds": poses.seconds, **dict(meta or {})}
    with open(path, "w", encoding="utf-8") as f:
        json.dump(data, f, indent=1)
        f.write("\n")
