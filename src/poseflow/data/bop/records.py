"""BOP records: the dataclasses that the JSON files and datasets of a BOP split hold, in metres."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from poseflow.data.rle import rle_decode
from poseflow.errors import BOPFormatError, ValueRangeError

__all__ = [
    "MM_PER_M",
    "BOPDataWarning",
    "CameraInfo",
    "ContinuousSymmetry",
    "Detection",
    "GTInfo",
    "GTPose",
    "ModelInfo",
    "TestTarget",
]

#: Millimetres per metre: the one conversion factor between BOP files and poseflow.
MM_PER_M = 1000.0


class BOPDataWarning(UserWarning):
    """One instance or image is unusable (empty mask, too few valid depth pixels) and is flagged."""


@dataclass(frozen=True)
class CameraInfo:
    """Camera of one image (``scene_camera.json``).

    Attributes:
        K: intrinsics, ``(3, 3)`` float64, pixels.
        depth_scale: millimetres per unit of the depth PNG (BOP's ``depth_scale``).
        R_w2c: optional world-to-camera rotation ``(3, 3)``.
        t_w2c: optional world-to-camera translation ``(3,)`` in metres.
    """

    K: np.ndarray
    depth_scale: float = 1.0
    R_w2c: np.ndarray | None = None
    t_w2c: np.ndarray | None = None


@dataclass(frozen=True)
class GTPose:
    """One ground-truth instance (``scene_gt.json``): object id and model-to-camera pose in metres.

    Attributes:
        obj_id: object id.
        pose: ``(4, 4)`` float64 model-to-camera transform, translation in metres.
    """

    obj_id: int
    pose: np.ndarray


@dataclass(frozen=True)
class GTInfo:
    """Visibility statistics of one ground-truth instance (``scene_gt_info.json``).

    Boxes are ``(x, y, w, h)`` in pixels, ``(-1, -1, -1, -1)`` when empty.
    """

    bbox_obj: tuple[int, int, int, int]
    bbox_visib: tuple[int, int, int, int]
    px_count_all: int
    px_count_valid: int
    px_count_visib: int
    visib_fract: float


@dataclass(frozen=True)
class ContinuousSymmetry:
    """A continuous rotational symmetry: unit ``axis`` ``(3,)`` through ``offset`` ``(3,)`` (m)."""

    axis: np.ndarray
    offset: np.ndarray


@dataclass(frozen=True)
class ModelInfo:
    """One object's entry of ``models_info.json``, in metres.

    Attributes:
        diameter: largest distance between two model vertices (metres).
        min_xyz: ``(3,)`` lower corner of the model's bounding box (metres).
        size_xyz: ``(3,)`` extent of the bounding box (metres).
        symmetries_discrete: ``(4, 4)`` transforms, translation in metres.
        symmetries_continuous: rotational symmetries.
    """

    diameter: float
    min_xyz: np.ndarray
    size_xyz: np.ndarray
    symmetries_discrete: tuple[np.ndarray, ...] = ()
    symmetries_continuous: tuple[ContinuousSymmetry, ...] = ()


@dataclass(frozen=True)
class TestTarget:
    """One entry of ``test_targets_bop19.json``: estimate ``inst_count`` poses of ``obj_id``."""

    __test__ = False  # not a pytest test class despite the name

    scene_id: int
    im_id: int
    obj_id: int
    inst_count: int


@dataclass(frozen=True)
class Detection:
    """One detection/segmentation result in the BOP format.

    Attributes:
        scene_id: scene id.
        im_id: image id (``image_id`` in the file).
        obj_id: object id (``category_id`` in the file).
        score: confidence.
        bbox: ``(x, y, w, h)`` in pixels.
        segmentation: COCO RLE (compressed or not), or None for box-only detections.
        time: run time reported for the image, seconds (-1 when absent).
    """

    scene_id: int
    im_id: int
    obj_id: int
    score: float
    bbox: tuple[float, float, float, float]
    segmentation: Mapping[str, Any] | None = field(default=None, repr=False)
    time: float = -1.0

    def mask(self) -> torch.Tensor:
        """Decode the segmentation to a bool mask ``(H, W)``.

        Raises:
            BOPFormatError: the detection carries no segmentation or its RLE is malformed.
        """
        if self.segmentation is None:
            raise BOPFormatError(
                f"detection of obj {self.obj_id} in scene {self.scene_id} image {self.im_id} "
                "has no segmentation"
            )
        try:
            return rle_decode(self.segmentation)
        except ValueRangeError as exc:
            raise BOPFormatError(
                f"detection of obj {self.obj_id} in scene {self.scene_id} image {self.im_id}: {exc}"
            ) from exc
