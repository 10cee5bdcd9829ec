"""Read and write datasets in the BOP format (LM-O, TUD-L, IC-BIN, YCB-V, ...).

A BOP dataset is a folder ``root`` holding ``models/`` and ``models_eval/`` (PLY meshes in mm
and ``models_info.json``), the split folders (``test``, ``train_pbr``, ``test_primesense``, ...)
with one folder per scene ``{scene_id:06d}``, and optionally ``test_targets_bop19.json``. A scene
folder holds ``scene_camera.json``, ``scene_gt.json``, ``scene_gt_info.json``, ``rgb/`` (or
``gray/``), ``depth/``, ``mask/`` and ``mask_visib/``.

Units: everything returned by this module is in **metres** (depth maps, translations, diameters,
symmetry offsets); the files are in millimetres and are converted here, on read and on write.
Poses are ``(4, 4)`` model-to-camera transforms, ``x_cam = R x_model + t``. Pixel coordinates
follow the BOP/OpenCV convention: pixel ``(u, v)`` is column ``u``, row ``v`` and ``K`` maps camera
points to those integer pixel positions.

Three levels of lazy, indexable access, all usable with a :class:`torch.utils.data.DataLoader`:

- :class:`BOPScene`: the images of one scene (``scene[i]`` is an image sample);
- :class:`BOPImageDataset`: every image of a split (batch with :func:`collate_images`, which pads
  the variable number of instances);
- :class:`BOPInstanceDataset` (ground-truth instances) and :class:`BOPDetectionDataset`
  (instances given by detection/segmentation results such as the public ZebraPose masks): one
  object instance per item, collated by the default collate function.

Problems confined to one instance (an empty mask, fewer than ``min_valid_pixels`` valid depth
pixels inside the mask, NaN or zero depth) never raise: the sample's ``valid`` flag is False and a
:class:`BOPDataWarning` names the scene, image and instance, so that an evaluation loop can skip it.
Problems of the files themselves (missing files or keys, a depth map clearly stored in metres
although ``depth_scale`` declares millimetres) raise :class:`BOPFormatError` or
:class:`MissingFileError` naming the file, scene and image.
"""

from __future__ import annotations

import json
import math
import warnings
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image

from poseflow.data.rle import rle_decode
from poseflow.errors import BOPFormatError, MissingFileError, ShapeError, ValueRangeError

__all__ = [
    "BOPDataWarning",
    "BOPDataset",
    "BOPDetectionDataset",
    "BOPImageDataset",
    "BOPInstanceDataset",
    "BOPScene",
    "BOPWriter",
    "CameraInfo",
    "ContinuousSymmetry",
    "Detection",
    "GTInfo",
    "GTPose",
    "ModelInfo",
    "TestTarget",
    "collate_images",
    "compute_gt_info",
    "read_depth",
    "read_detections",
    "read_image",
    "read_mask",
    "read_models_info",
    "read_scene_camera",
    "read_scene_gt",
    "read_scene_gt_info",
    "read_test_targets",
    "write_depth",
    "write_detections",
    "write_image",
    "write_mask",
    "write_model_ply",
    "write_models_info",
    "write_scene_camera",
    "write_scene_gt",
    "write_scene_gt_info",
    "write_test_targets",
]

#: Millimetres per metre: the one conversion factor between BOP files and poseflow.
MM_PER_M = 1000.0

#: A depth map whose largest valid value is below this (in metres, after applying depth_scale) is
#: taken to have been written in metres although millimetres were declared.
_MIN_PLAUSIBLE_MAX_DEPTH_M = 0.05


class BOPDataWarning(UserWarning):
    """One instance or image is unusable (empty mask, too few valid depth pixels) and is flagged."""


# --------------------------------------------------------------------------------------------
# Records
# --------------------------------------------------------------------------------------------


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


# --------------------------------------------------------------------------------------------
# JSON readers
# --------------------------------------------------------------------------------------------


def _load_json(path: str | Path) -> Any:
    path = Path(path)
    if not path.is_file():
        raise MissingFileError(f"missing BOP file {path}")
    try:
        with path.open() as f:
            return json.load(f)
    except json.JSONDecodeError as exc:
        raise BOPFormatError(f"{path} is not valid JSON: {exc}") from exc


def _get(entry: Mapping[str, Any], key: str, where: str) -> Any:
    if not isinstance(entry, Mapping):
        raise BOPFormatError(f"{where}: expected a JSON object, got {type(entry).__name__}")
    if key not in entry:
        raise BOPFormatError(f"{where}: missing key '{key}'")
    return entry[key]


def _array(value: Any, size: int, where: str, key: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise BOPFormatError(f"{where}: '{key}' is not numeric: {exc}") from exc
    if arr.size != size:
        raise BOPFormatError(f"{where}: '{key}' must have {size} numbers, got {arr.size}")
    if not np.isfinite(arr).all():
        raise BOPFormatError(f"{where}: '{key}' holds NaN or inf")
    return arr


def _int_keys(data: Any, path: Path) -> dict[int, Any]:
    if not isinstance(data, Mapping):
        raise BOPFormatError(f"{path}: expected a JSON object keyed by image id")
    out: dict[int, Any] = {}
    for k, v in data.items():
        try:
            out[int(k)] = v
        except ValueError as exc:
            raise BOPFormatError(f"{path}: key {k!r} is not an integer id") from exc
    return out


def _scene_of(path: Path) -> str:
    return path.parent.name


def read_scene_camera(path: str | Path) -> dict[int, CameraInfo]:
    """Read ``scene_camera.json``.

    Args:
        path: the JSON file.

    Returns:
        ``{im_id: CameraInfo}`` with translations in metres.

    Raises:
        MissingFileError: the file does not exist.
        BOPFormatError: a key is missing or malformed (the message names file, scene and image).
    """
    path = Path(path)
    out = {}
    for im_id, entry in sorted(_int_keys(_load_json(path), path).items()):
        where = f"{path} (scene {_scene_of(path)}, image {im_id})"
        K = _array(_get(entry, "cam_K", where), 9, where, "cam_K").reshape(3, 3)
        scale = float(entry.get("depth_scale", 1.0)) if isinstance(entry, Mapping) else 1.0
        if not math.isfinite(scale) or scale <= 0:
            raise BOPFormatError(f"{where}: depth_scale must be positive, got {scale}")
        R = t = None
        if "cam_R_w2c" in entry and "cam_t_w2c" in entry:
            R = _array(entry["cam_R_w2c"], 9, where, "cam_R_w2c").reshape(3, 3)
            t = _array(entry["cam_t_w2c"], 3, where, "cam_t_w2c") / MM_PER_M
        out[im_id] = CameraInfo(K=K, depth_scale=scale, R_w2c=R, t_w2c=t)
    return out


def read_scene_gt(path: str | Path) -> dict[int, list[GTPose]]:
    """Read ``scene_gt.json``.

    Returns:
        ``{im_id: [GTPose, ...]}`` in the file's instance order, poses in metres.

    Raises:
        MissingFileError: the file does not exist.
        BOPFormatError: a key is missing or malformed.
    """
    path = Path(path)
    out = {}
    for im_id, entries in sorted(_int_keys(_load_json(path), path).items()):
        if not isinstance(entries, list):
            raise BOPFormatError(f"{path} (image {im_id}): expected a list of instances")
        poses = []
        for gt_idx, entry in enumerate(entries):
            where = f"{path} (scene {_scene_of(path)}, image {im_id}, instance {gt_idx})"
            R = _array(_get(entry, "cam_R_m2c", where), 9, where, "cam_R_m2c").reshape(3, 3)
            t = _array(_get(entry, "cam_t_m2c", where), 3, where, "cam_t_m2c") / MM_PER_M
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, t
            poses.append(GTPose(obj_id=int(_get(entry, "obj_id", where)), pose=T))
        out[im_id] = poses
    return out


def read_scene_gt_info(path: str | Path) -> dict[int, list[GTInfo]]:
    """Read ``scene_gt_info.json``.

    Returns:
        ``{im_id: [GTInfo, ...]}`` aligned with :func:`read_scene_gt`.

    Raises:
        MissingFileError: the file does not exist.
        BOPFormatError: a key is missing or malformed.
    """
    path = Path(path)
    out = {}
    for im_id, entries in sorted(_int_keys(_load_json(path), path).items()):
        if not isinstance(entries, list):
            raise BOPFormatError(f"{path} (image {im_id}): expected a list of instances")
        infos = []
        for gt_idx, e in enumerate(entries):
            where = f"{path} (scene {_scene_of(path)}, image {im_id}, instance {gt_idx})"

            def box(key: str, e: Any = e, where: str = where) -> tuple[int, int, int, int]:
                a = _array(_get(e, key, where), 4, where, key).astype(int)
                return (int(a[0]), int(a[1]), int(a[2]), int(a[3]))

            infos.append(
                GTInfo(
                    bbox_obj=box("bbox_obj"),
                    bbox_visib=box("bbox_visib"),
                    px_count_all=int(_get(e, "px_count_all", where)),
                    px_count_valid=int(_get(e, "px_count_valid", where)),
                    px_count_visib=int(_get(e, "px_count_visib", where)),
                    visib_fract=float(_get(e, "visib_fract", where)),
                )
            )
        out[im_id] = infos
    return out


def read_models_info(path: str | Path) -> dict[int, ModelInfo]:
    """Read ``models_info.json`` (diameter, bounding box, symmetries), converted to metres.

    Example:
        >>> import json, tempfile, pathlib
        >>> p = pathlib.Path(tempfile.mkdtemp()) / "models_info.json"
        >>> _ = p.write_text(json.dumps({"1": {"diameter": 102.1, "min_x": -37.9, "min_y": -38.8,
        ...     "min_z": -45.9, "size_x": 75.9, "size_y": 77.6, "size_z": 91.8}}))
        >>> read_models_info(p)[1].diameter
        0.1021
    """
    path = Path(path)
    out = {}
    for obj_id, e in sorted(_int_keys(_load_json(path), path).items()):
        where = f"{path} (obj {obj_id})"
        diameter = float(_get(e, "diameter", where)) / MM_PER_M
        min_xyz = np.array([float(e.get(f"min_{a}", 0.0)) for a in "xyz"]) / MM_PER_M
        size_xyz = np.array([float(e.get(f"size_{a}", 0.0)) for a in "xyz"]) / MM_PER_M
        discrete = []
        for s in e.get("symmetries_discrete", []):
            T = _array(s, 16, where, "symmetries_discrete").reshape(4, 4).copy()
            T[:3, 3] /= MM_PER_M
            discrete.append(T)
        continuous = []
        for s in e.get("symmetries_continuous", []):
            axis = _array(_get(s, "axis", where), 3, where, "axis")
            norm = np.linalg.norm(axis)
            if norm == 0:
                raise BOPFormatError(f"{where}: a continuous symmetry has a zero axis")
            offset = _array(s.get("offset", [0, 0, 0]), 3, where, "offset") / MM_PER_M
            continuous.append(ContinuousSymmetry(axis=axis / norm, offset=offset))
        out[obj_id] = ModelInfo(
            diameter=diameter,
            min_xyz=min_xyz,
            size_xyz=size_xyz,
            symmetries_discrete=tuple(discrete),
            symmetries_continuous=tuple(continuous),
        )
    return out


def read_test_targets(path: str | Path) -> list[TestTarget]:
    """Read ``test_targets_bop19.json`` (a list of ``scene_id, im_id, obj_id, inst_count``)."""
    path = Path(path)
    data = _load_json(path)
    if not isinstance(data, list):
        raise BOPFormatError(f"{path}: expected a JSON list of targets")
    out = []
    for i, e in enumerate(data):
        where = f"{path} (entry {i})"
        out.append(
            TestTarget(
                scene_id=int(_get(e, "scene_id", where)),
                im_id=int(_get(e, "im_id", where)),
                obj_id=int(_get(e, "obj_id", where)),
                inst_count=int(_get(e, "inst_count", where)),
            )
        )
    return out


def read_detections(path: str | Path) -> list[Detection]:
    """Read detection/segmentation results in the BOP format.

    The file is a JSON list of ``{scene_id, image_id, category_id, score, bbox, segmentation,
    time}`` where ``segmentation`` is a COCO RLE, compressed (string ``counts``) or not (list).
    Masks are decoded lazily by :meth:`Detection.mask`.

    Raises:
        MissingFileError: the file does not exist.
        BOPFormatError: an entry lacks a key (the message gives its index, scene and image).
    """
    path = Path(path)
    data = _load_json(path)
    if not isinstance(data, list):
        raise BOPFormatError(f"{path}: expected a JSON list of detections")
    out = []
    for i, e in enumerate(data):
        where = f"{path} (entry {i})"
        scene_id = int(_get(e, "scene_id", where))
        im_id = int(_get(e, "image_id", where))
        where = f"{path} (entry {i}, scene {scene_id}, image {im_id})"
        seg = e.get("segmentation")
        if seg is not None and not (isinstance(seg, Mapping) and "counts" in seg and "size" in seg):
            raise BOPFormatError(f"{where}: segmentation must be a COCO RLE with counts and size")
        bbox = _array(e.get("bbox", [0, 0, 0, 0]), 4, where, "bbox")
        out.append(
            Detection(
                scene_id=scene_id,
                im_id=im_id,
                obj_id=int(_get(e, "category_id", where)),
                score=float(_get(e, "score", where)),
                bbox=(float(bbox[0]), float(bbox[1]), float(bbox[2]), float(bbox[3])),
                segmentation=seg,
                time=float(e.get("time", -1.0)),
            )
        )
    return out


# --------------------------------------------------------------------------------------------
# Images
# --------------------------------------------------------------------------------------------


def read_image(path: str | Path) -> torch.Tensor:
    """Read an RGB or grey image as float ``(3, H, W)`` in ``[0, 1]`` (grey is repeated).

    Raises:
        MissingFileError: the file does not exist.
    """
    path = Path(path)
    if not path.is_file():
        raise MissingFileError(f"missing image {path}")
    with Image.open(path) as im:
        arr = np.asarray(im)
    if arr.ndim == 2:
        arr = np.repeat(arr[..., None], 3, axis=2)
    if arr.ndim != 3 or arr.shape[2] not in (3, 4):
        raise BOPFormatError(f"{path}: expected an RGB or grey image, got shape {arr.shape}")
    scale = 65535.0 if arr.dtype == np.uint16 else 255.0
    img = torch.from_numpy(arr[..., :3].astype(np.float32) / scale)
    return img.permute(2, 0, 1).contiguous()


def read_depth(
    path: str | Path, depth_scale: float = 1.0, *, check_units: bool = True
) -> torch.Tensor:
    """Read a BOP depth PNG (uint16, ``value * depth_scale`` = mm) as metres ``(H, W)`` float32.

    Missing measurements are 0.

    Args:
        path: the PNG file.
        depth_scale: millimetres per unit, from ``scene_camera.json``.
        check_units: raise when the depth is clearly in metres although mm were declared (every
            valid value below 5 cm after scaling).

    Raises:
        MissingFileError: the file does not exist.
        BOPFormatError: not a single-channel 16-bit image, or clearly wrong units.
    """
    path = Path(path)
    if not path.is_file():
        raise MissingFileError(f"missing depth map {path}")
    with Image.open(path) as im:
        arr = np.asarray(im)
    if arr.ndim != 2 or arr.dtype.kind not in "ui":
        raise BOPFormatError(
            f"{path}: a depth map must be a single-channel 16-bit PNG, got {arr.dtype} {arr.shape}"
        )
    depth = arr.astype(np.float32) * np.float32(depth_scale / MM_PER_M)
    if check_units:
        valid = depth[depth > 0]
        if valid.size and float(valid.max()) < _MIN_PLAUSIBLE_MAX_DEPTH_M:
            raise BOPFormatError(
                f"{path}: depth looks like metres, not millimetres: the largest value is "
                f"{int(arr.max())} units x depth_scale {depth_scale} = "
                f"{valid.max() * 1000:.2f} mm; "
                "write depth in mm (or fix depth_scale in scene_camera.json)"
            )
    return torch.from_numpy(depth)


def read_mask(path: str | Path) -> torch.Tensor:
    """Read a BOP mask PNG as bool ``(H, W)`` (non-zero = object)."""
    path = Path(path)
    if not path.is_file():
        raise MissingFileError(f"missing mask {path}")
    with Image.open(path) as im:
        arr = np.asarray(im)
    if arr.ndim == 3:
        arr = arr[..., 0]
    return torch.from_numpy(arr > 0)


def _np(x: Any, dtype: Any = None) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=dtype)


def write_image(path: str | Path, rgb: torch.Tensor | np.ndarray) -> None:
    """Write an image given as float ``(3, H, W)`` in ``[0, 1]`` or uint8 ``(H, W, 3)``.

    The format follows the extension (``.png`` lossless, ``.jpg`` quality 95).
    """
    arr = _np(rgb)
    if arr.ndim == 3 and arr.shape[0] in (1, 3) and arr.shape[2] not in (1, 3):
        arr = np.moveaxis(arr, 0, 2)
    if arr.dtype != np.uint8:
        arr = np.clip(np.round(arr.astype(np.float64) * 255.0), 0, 255).astype(np.uint8)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    jpg = path.suffix.lower() in (".jpg", ".jpeg")
    kwargs = {"quality": 95} if jpg else {"compress_level": 3}
    Image.fromarray(arr).save(path, **kwargs)


def write_depth(
    path: str | Path, depth: torch.Tensor | np.ndarray, depth_scale: float = 1.0
) -> None:
    """Write a depth map in metres ``(H, W)`` as a BOP uint16 PNG (``value * depth_scale`` = mm).

    Non-finite and non-positive depths are written as 0 (missing).

    Raises:
        ValueRangeError: a depth does not fit in 16 bits at this ``depth_scale``.
    """
    d = _np(depth, np.float64)
    if d.ndim != 2:
        raise ShapeError(f"depth must have shape (H, W), got {d.shape}")
    units = np.where(np.isfinite(d) & (d > 0), d * MM_PER_M / depth_scale, 0.0)
    if units.max(initial=0.0) > 65535:
        raise ValueRangeError(
            f"depth up to {d[np.isfinite(d)].max():.3f} m does not fit in 16 bits with "
            f"depth_scale {depth_scale} mm; use a larger depth_scale"
        )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # level 3: noisy depth barely compresses further, and level 6 takes 5x longer
    Image.fromarray(np.round(units).astype(np.uint16)).save(path, compress_level=3)


def write_mask(path: str | Path, mask: torch.Tensor | np.ndarray) -> None:
    """Write a bool mask ``(H, W)`` as a BOP 8-bit PNG (255 = object)."""
    m = _np(mask).astype(bool)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray((m * 255).astype(np.uint8)).save(path)


# --------------------------------------------------------------------------------------------
# JSON writers
# --------------------------------------------------------------------------------------------


def _dump(path: str | Path, data: Any) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w") as f:
        json.dump(data, f, indent=2)
        f.write("\n")


def _floats(a: Any) -> list[float]:
    return [float(v) for v in _np(a, np.float64).reshape(-1)]


def write_scene_camera(path: str | Path, cameras: Mapping[int, CameraInfo]) -> None:
    """Write ``scene_camera.json`` from ``{im_id: CameraInfo}`` (metres in, mm in the file)."""
    data = {}
    for im_id, cam in sorted(cameras.items()):
        e: dict[str, Any] = {"cam_K": _floats(cam.K), "depth_scale": float(cam.depth_scale)}
        if cam.R_w2c is not None and cam.t_w2c is not None:
            e["cam_R_w2c"] = _floats(cam.R_w2c)
            e["cam_t_w2c"] = _floats(_np(cam.t_w2c, np.float64) * MM_PER_M)
        data[str(im_id)] = e
    _dump(path, data)


def write_scene_gt(path: str | Path, gts: Mapping[int, Sequence[GTPose]]) -> None:
    """Write ``scene_gt.json`` from ``{im_id: [GTPose, ...]}`` (poses in metres)."""
    data = {}
    for im_id, poses in sorted(gts.items()):
        entries = []
        for gt in poses:
            T = _np(gt.pose, np.float64)
            entries.append(
                {
                    "cam_R_m2c": _floats(T[:3, :3]),
                    "cam_t_m2c": _floats(T[:3, 3] * MM_PER_M),
                    "obj_id": int(gt.obj_id),
                }
            )
        data[str(im_id)] = entries
    _dump(path, data)


def write_scene_gt_info(path: str | Path, infos: Mapping[int, Sequence[GTInfo]]) -> None:
    """Write ``scene_gt_info.json`` from ``{im_id: [GTInfo, ...]}``."""
    data = {
        str(im_id): [
            {
                "bbox_obj": list(i.bbox_obj),
                "bbox_visib": list(i.bbox_visib),
                "px_count_all": int(i.px_count_all),
                "px_count_valid": int(i.px_count_valid),
                "px_count_visib": int(i.px_count_visib),
                "visib_fract": float(i.visib_fract),
            }
            for i in entries
        ]
        for im_id, entries in sorted(infos.items())
    }
    _dump(path, data)


def write_models_info(path: str | Path, infos: Mapping[int, ModelInfo]) -> None:
    """Write ``models_info.json`` from ``{obj_id: ModelInfo}`` (metres in, mm in the file)."""
    data = {}
    for obj_id, info in sorted(infos.items()):
        e: dict[str, Any] = {"diameter": float(info.diameter * MM_PER_M)}
        for a, lo, size in zip(
            "xyz", _np(info.min_xyz, np.float64), _np(info.size_xyz, np.float64)
        ):
            e[f"min_{a}"] = float(lo * MM_PER_M)
            e[f"size_{a}"] = float(size * MM_PER_M)
        if info.symmetries_discrete:
            syms = []
            for S in info.symmetries_discrete:
                S = _np(S, np.float64).copy()
                S[:3, 3] *= MM_PER_M
                syms.append(_floats(S))
            e["symmetries_discrete"] = syms
        if info.symmetries_continuous:
            e["symmetries_continuous"] = [
                {"axis": _floats(s.axis), "offset": _floats(_np(s.offset, np.float64) * MM_PER_M)}
                for s in info.symmetries_continuous
            ]
        data[str(obj_id)] = e
    _dump(path, data)


def write_test_targets(path: str | Path, targets: Iterable[TestTarget]) -> None:
    """Write ``test_targets_bop19.json``."""
    _dump(
        path,
        [
            {
                "im_id": t.im_id,
                "inst_count": t.inst_count,
                "obj_id": t.obj_id,
                "scene_id": t.scene_id,
            }
            for t in targets
        ],
    )


def write_detections(path: str | Path, detections: Iterable[Detection]) -> None:
    """Write detection/segmentation results in the BOP format (see :func:`read_detections`)."""
    _dump(
        path,
        [
            {
                "scene_id": d.scene_id,
                "image_id": d.im_id,
                "category_id": d.obj_id,
                "score": d.score,
                "bbox": list(d.bbox),
                "segmentation": dict(d.segmentation) if d.segmentation is not None else None,
                "time": d.time,
            }
            for d in detections
        ],
    )


def write_model_ply(
    path: str | Path,
    vertices: torch.Tensor | np.ndarray,
    faces: torch.Tensor | np.ndarray,
    *,
    normals: torch.Tensor | np.ndarray | None = None,
    colors: torch.Tensor | np.ndarray | None = None,
    uvs: torch.Tensor | np.ndarray | None = None,
    texture_file: str | None = None,
) -> None:
    """Write a triangle mesh as a binary BOP model PLY (vertices given in metres, written in mm).

    Args:
        path: output ``.ply``.
        vertices: ``(V, 3)`` positions in metres.
        faces: ``(F, 3)`` vertex indices.
        normals: optional ``(V, 3)`` unit normals.
        colors: optional ``(V, 3)`` colours in ``[0, 1]``.
        uvs: optional ``(V, 2)`` texture coordinates, written as ``texture_u``/``texture_v`` with
            ``v`` measured from the bottom row of the texture image (the PLY/OpenGL convention).
        texture_file: name of the texture image next to the PLY (a ``comment TextureFile`` line).
    """
    v = _np(vertices, np.float64)
    f = _np(faces, np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise ShapeError(f"vertices must be (V, 3) and faces (F, 3), got {v.shape} and {f.shape}")
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise ValueRangeError("faces index vertices out of range")
    props: list[tuple[str, str]] = [("x", "f4"), ("y", "f4"), ("z", "f4")]
    cols: list[np.ndarray] = [v * MM_PER_M]
    if normals is not None:
        props += [("nx", "f4"), ("ny", "f4"), ("nz", "f4")]
        cols.append(_np(normals, np.float64).reshape(len(v), 3))
    if colors is not None:
        props += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        c = _np(colors, np.float64).reshape(len(v), 3)
        cols.append(np.clip(np.round(c * 255), 0, 255))
    if uvs is not None:
        props += [("texture_u", "f4"), ("texture_v", "f4")]
        cols.append(_np(uvs, np.float64).reshape(len(v), 2))
    vdtype = np.dtype([(n, "<" + t) for n, t in props])
    vrec = np.empty(len(v), dtype=vdtype)
    flat = np.concatenate(cols, axis=1)
    for i, (n, _) in enumerate(props):
        vrec[n] = flat[:, i]
    frec = np.empty(len(f), dtype=np.dtype([("n", "u1"), ("idx", "<i4", (3,))]))
    frec["n"] = 3
    frec["idx"] = f
    ply_types = {"f4": "float", "u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0"]
    if texture_file is not None:
        header.append(f"comment TextureFile {texture_file}")
    header.append(f"element vertex {len(v)}")
    header += [f"property {ply_types[t]} {n}" for n, t in props]
    header += [f"element face {len(f)}", "property list uchar int vertex_indices", "end_header"]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as out:
        out.write(("\n".join(header) + "\n").encode("ascii"))
        out.write(vrec.tobytes())
        out.write(frec.tobytes())


def _bbox(mask: np.ndarray) -> tuple[int, int, int, int]:
    ys, xs = np.nonzero(mask)
    if ys.size == 0:
        return (-1, -1, -1, -1)
    x0, y0 = int(xs.min()), int(ys.min())
    return (x0, y0, int(xs.max()) - x0 + 1, int(ys.max()) - y0 + 1)


def compute_gt_info(
    mask: torch.Tensor | np.ndarray,
    mask_visib: torch.Tensor | np.ndarray,
    depth: torch.Tensor | np.ndarray | None = None,
) -> GTInfo:
    """Compute an instance's ``scene_gt_info`` entry from its full and visible masks.

    ``visib_fract = px_count_visib / px_count_all`` (0 when the full mask is empty); pixels are
    counted inside the image. ``px_count_valid`` counts full-mask pixels with a measured depth.

    Args:
        mask: full silhouette ``(H, W)`` bool.
        mask_visib: visible part ``(H, W)`` bool.
        depth: optional depth ``(H, W)`` (metres, 0 = missing); without it every pixel is valid.

    Example:
        >>> m = torch.zeros(4, 4, dtype=torch.bool); m[1:3, 1:3] = True
        >>> v = m.clone(); v[1, 1] = False
        >>> compute_gt_info(m, v).visib_fract
        0.75
    """
    m = _np(mask).astype(bool)
    mv = _np(mask_visib).astype(bool)
    if m.shape != mv.shape:
        raise ShapeError(f"mask {m.shape} and mask_visib {mv.shape} differ in shape")
    n_all, n_vis = int(m.sum()), int(mv.sum())
    if depth is None:
        n_valid = n_all
    else:
        d = _np(depth, np.float64)
        n_valid = int((m & np.isfinite(d) & (d > 0)).sum())
    return GTInfo(
        bbox_obj=_bbox(m),
        bbox_visib=_bbox(mv),
        px_count_all=n_all,
        px_count_valid=n_valid,
        px_count_visib=n_vis,
        visib_fract=n_vis / n_all if n_all else 0.0,
    )


# --------------------------------------------------------------------------------------------
# Lazy readers
# --------------------------------------------------------------------------------------------


def _find_first(paths: Iterable[Path]) -> Path | None:
    for p in paths:
        if p.is_file():
            return p
    return None


def _validity(
    mask: torch.Tensor, depth: torch.Tensor | None, min_valid_pixels: int, what: str
) -> tuple[bool, int]:
    """Count valid depth pixels in a mask; warn and return False when too few."""
    if depth is None:
        n = int(mask.sum())
    else:
        n = int((mask & torch.isfinite(depth) & (depth > 0)).sum())
    if int(mask.sum()) == 0:
        warnings.warn(f"{what}: empty mask; instance flagged invalid", BOPDataWarning, stacklevel=3)
        return False, n
    if n < min_valid_pixels:
        warnings.warn(
            f"{what}: only {n} pixels of the mask have a valid (finite, non-zero) depth, fewer "
            f"than min_valid_pixels={min_valid_pixels}; instance flagged invalid",
            BOPDataWarning,
            stacklevel=3,
        )
        return False, n
    return True, n


class BOPScene(torch.utils.data.Dataset):
    """One scene folder, read lazily; ``scene[i]`` is the sample of its ``i``-th image.

    Args:
        path: the scene folder (``.../test/000002``).
        load_rgb: include ``rgb`` in samples.
        load_depth: include ``depth`` in samples.
        load_masks: include ``masks`` and ``masks_visib`` in samples (needs ``mask/`` and
            ``mask_visib/``).
        min_valid_pixels: an instance whose visible mask holds fewer valid depth pixels is flagged
            invalid (``valid`` False) with a :class:`BOPDataWarning`.
        check_depth_units: raise when a depth map is clearly in metres (see :func:`read_depth`).
        dtype: floating dtype of the returned tensors.

    Image samples are dicts with ``scene_id``, ``im_id`` (int), ``K`` ``(3, 3)``, ``rgb``
    ``(3, H, W)`` in ``[0, 1]``, ``depth`` ``(H, W)`` metres (0 = missing), ``obj_ids`` ``(n,)``,
    ``poses`` ``(n, 4, 4)`` model-to-camera in metres, ``visib_fract`` ``(n,)``, ``masks`` and
    ``masks_visib`` ``(n, H, W)`` bool, and ``valid`` ``(n,)`` bool.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        load_rgb: bool = True,
        load_depth: bool = True,
        load_masks: bool = True,
        min_valid_pixels: int = 16,
        check_depth_units: bool = True,
        dtype: torch.dtype = torch.float32,
    ) -> None:
        self.path = Path(path)
        if not self.path.is_dir():
            raise MissingFileError(f"missing BOP scene folder {self.path}")
        try:
            self.scene_id = int(self.path.name)
        except ValueError as exc:
            raise BOPFormatError(f"{self.path}: a scene folder is named by its id") from exc
        self.load_rgb = load_rgb
        self.load_depth = load_depth
        self.load_masks = load_masks
        self.min_valid_pixels = min_valid_pixels
        self.check_depth_units = check_depth_units
        self.dtype = dtype

    @cached_property
    def camera(self) -> dict[int, CameraInfo]:
        """``{im_id: CameraInfo}`` from ``scene_camera.json``."""
        return read_scene_camera(self.path / "scene_camera.json")

    @cached_property
    def gt(self) -> dict[int, list[GTPose]]:
        """``{im_id: [GTPose]}`` from ``scene_gt.json``; empty when the file is absent."""
        p = self.path / "scene_gt.json"
        return read_scene_gt(p) if p.is_file() else {}

    @cached_property
    def gt_info(self) -> dict[int, list[GTInfo]]:
        """``{im_id: [GTInfo]}`` from ``scene_gt_info.json``; empty when the file is absent."""
        p = self.path / "scene_gt_info.json"
        return read_scene_gt_info(p) if p.is_file() else {}

    @property
    def im_ids(self) -> list[int]:
        """Sorted image ids of the scene (the keys of ``scene_camera.json``)."""
        return sorted(self.camera)

    def __len__(self) -> int:
        return len(self.camera)

    def __getitem__(self, index: int) -> dict[str, Any]:
        ids = self.im_ids
        if not -len(ids) <= index < len(ids):
            raise IndexError(f"scene {self.scene_id} has {len(ids)} images, index {index}")
        return self.image_sample(ids[index])

    def _where(self, im_id: int, gt_idx: int | None = None) -> str:
        s = f"scene {self.scene_id} image {im_id}"
        return s if gt_idx is None else f"{s} instance {gt_idx}"

    def _cam(self, im_id: int) -> CameraInfo:
        if im_id not in self.camera:
            raise BOPFormatError(
                f"{self.path / 'scene_camera.json'}: no entry for {self._where(im_id)}"
            )
        return self.camera[im_id]

    def gt_of(self, im_id: int) -> list[GTPose]:
        """Ground-truth instances of an image (raises when the scene has GT but not this image)."""
        if not self.gt:
            return []
        if im_id not in self.gt:
            raise BOPFormatError(
                f"{self.path / 'scene_gt.json'}: no entry for {self._where(im_id)}"
            )
        return self.gt[im_id]

    def rgb_path(self, im_id: int) -> Path:
        """Path of the colour (or grey) image of ``im_id``."""
        name = f"{im_id:06d}"
        p = _find_first(
            self.path / folder / f"{name}{ext}"
            for folder in ("rgb", "gray")
            for ext in (".png", ".jpg", ".jpeg", ".tif")
        )
        if p is None:
            raise MissingFileError(
                f"missing image for {self._where(im_id)}: no {name}.png/.jpg in "
                f"{self.path / 'rgb'} or {self.path / 'gray'}"
            )
        return p

    def depth_path(self, im_id: int) -> Path:
        """Path of the depth PNG of ``im_id``."""
        p = _find_first(self.path / "depth" / f"{im_id:06d}{e}" for e in (".png", ".tif"))
        if p is None:
            want = self.path / "depth" / f"{im_id:06d}.png"
            raise MissingFileError(f"missing depth for {self._where(im_id)}: {want}")
        return p

    def mask_path(self, im_id: int, gt_idx: int, *, visible: bool = True) -> Path:
        """Path of the (visible) mask PNG of instance ``gt_idx`` of ``im_id``."""
        folder = "mask_visib" if visible else "mask"
        return self.path / folder / f"{im_id:06d}_{gt_idx:06d}.png"

    def load_rgb_image(self, im_id: int) -> torch.Tensor:
        """Colour image ``(3, H, W)`` in ``[0, 1]``."""
        return read_image(self.rgb_path(im_id)).to(self.dtype)

    def load_depth_image(self, im_id: int) -> torch.Tensor:
        """Depth ``(H, W)`` in metres (0 = missing)."""
        cam = self._cam(im_id)
        return read_depth(
            self.depth_path(im_id), cam.depth_scale, check_units=self.check_depth_units
        ).to(self.dtype)

    def load_mask(self, im_id: int, gt_idx: int, *, visible: bool = True) -> torch.Tensor:
        """Mask ``(H, W)`` bool of instance ``gt_idx``."""
        p = self.mask_path(im_id, gt_idx, visible=visible)
        if not p.is_file():
            raise MissingFileError(f"missing mask for {self._where(im_id, gt_idx)}: {p}")
        return read_mask(p)

    def image_sample(self, im_id: int) -> dict[str, Any]:
        """The sample of image ``im_id`` (see the class docstring for its keys)."""
        cam = self._cam(im_id)
        gts = self.gt_of(im_id)
        infos = self.gt_info.get(im_id, [])
        n = len(gts)
        out: dict[str, Any] = {
            "scene_id": self.scene_id,
            "im_id": im_id,
            "K": torch.as_tensor(cam.K, dtype=self.dtype),
            "obj_ids": torch.tensor([g.obj_id for g in gts], dtype=torch.long),
            "poses": torch.as_tensor(
                np.stack([g.pose for g in gts]) if n else np.zeros((0, 4, 4)), dtype=self.dtype
            ),
        }
        depth = self.load_depth_image(im_id) if self.load_depth else None
        if self.load_rgb:
            out["rgb"] = self.load_rgb_image(im_id)
        if depth is not None:
            out["depth"] = depth
        valid = torch.ones(n, dtype=torch.bool)
        if self.load_masks:
            masks = [self.load_mask(im_id, i, visible=False) for i in range(n)]
            visib = [self.load_mask(im_id, i, visible=True) for i in range(n)]
            shape = depth.shape if depth is not None else (masks[0].shape if n else (0, 0))
            out["masks"] = torch.stack(masks) if n else torch.zeros(0, *shape, dtype=torch.bool)
            out["masks_visib"] = torch.stack(visib) if n else torch.zeros_like(out["masks"])
            for i, m in enumerate(visib):
                valid[i], _ = _validity(m, depth, self.min_valid_pixels, self._where(im_id, i))
        if infos and len(infos) != n:
            raise BOPFormatError(
                f"{self.path / 'scene_gt_info.json'}: {self._where(im_id)} has {len(infos)} "
                f"entries but scene_gt.json has {n}"
            )
        out["visib_fract"] = torch.tensor(
            [i.visib_fract for i in infos] if infos else [1.0] * n, dtype=self.dtype
        )
        out["valid"] = valid
        return out


def collate_images(batch: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Collate image samples with different instance counts, padding to the largest.

    Per-instance entries (``obj_ids``, ``poses``, ``visib_fract``, ``masks``, ``masks_visib``,
    ``valid``) are padded along a new instance dimension ``n_max`` (``obj_ids`` with -1, poses with
    the identity, ``valid`` with False) and ``instance_mask`` ``(B, n_max)`` says which entries are
    real; everything else is stacked by :func:`torch.utils.data.default_collate`.

    Example:
        >>> a = {"im_id": 0, "obj_ids": torch.tensor([1, 2]), "poses": torch.eye(4).repeat(2, 1, 1),
        ...      "valid": torch.tensor([True, True])}
        >>> b = {"im_id": 1, "obj_ids": torch.tensor([5]), "poses": torch.eye(4)[None],
        ...      "valid": torch.tensor([True])}
        >>> out = collate_images([a, b])
        >>> out["obj_ids"].tolist(), out["instance_mask"].tolist()
        ([[1, 2], [5, -1]], [[True, True], [True, False]])
    """
    per_instance = {"obj_ids", "poses", "visib_fract", "masks", "masks_visib", "valid"}
    counts = [len(s["obj_ids"]) for s in batch]
    n_max = max(counts, default=0)
    out = torch.utils.data.default_collate(
        [{k: v for k, v in s.items() if k not in per_instance} for s in batch]
    )
    for key in per_instance & set(batch[0]):
        items = [s[key] for s in batch]
        first = items[0]
        pad_shape = (len(batch), n_max, *first.shape[1:])
        if key == "obj_ids":
            padded = torch.full(pad_shape, -1, dtype=first.dtype)
        elif key == "poses":
            padded = torch.eye(4, dtype=first.dtype).expand(pad_shape).clone()
        else:
            padded = torch.zeros(pad_shape, dtype=first.dtype)
        for b, x in enumerate(items):
            padded[b, : len(x)] = x
        out[key] = padded
    out["instance_mask"] = torch.arange(n_max)[None] < torch.tensor(counts)[:, None]
    return out


class BOPDataset:
    """A BOP dataset folder: scenes of one split, object models and targets, all read lazily.

    Args:
        root: the dataset folder (holding ``models/`` and the split folders).
        split: split folder name, e.g. ``"test"``, ``"train_pbr"``, ``"test_primesense"``.
        **scene_kwargs: passed to every :class:`BOPScene` (``load_rgb``, ``min_valid_pixels``, ...).

    Raises:
        MissingFileError: ``root`` or the split folder does not exist.

    Example:
        >>> import tempfile
        >>> root = tempfile.mkdtemp()
        >>> with BOPWriter(root, "test") as w:
        ...     w.add_image(1, 0, K=torch.eye(3), depth=torch.full((4, 5), 0.5))
        >>> ds = BOPDataset(root, "test", load_rgb=False, load_masks=False)
        >>> ds.scene_ids, ds.scene(1)[0]["depth"].shape
        ([1], torch.Size([4, 5]))
    """

    def __init__(self, root: str | Path, split: str = "test", **scene_kwargs: Any) -> None:
        self.root = Path(root)
        self.split = split
        self.split_path = self.root / split
        if not self.split_path.is_dir():
            raise MissingFileError(f"missing BOP split folder {self.split_path}")
        self.scene_kwargs = scene_kwargs
        self._scenes: dict[int, BOPScene] = {}

    @cached_property
    def scene_ids(self) -> list[int]:
        """Sorted ids of the scene folders of the split."""
        return sorted(
            int(p.name) for p in self.split_path.iterdir() if p.is_dir() and p.name.isdigit()
        )

    def scene(self, scene_id: int) -> BOPScene:
        """The :class:`BOPScene` of ``scene_id`` (cached)."""
        if scene_id not in self._scenes:
            self._scenes[scene_id] = BOPScene(
                self.split_path / f"{scene_id:06d}", **self.scene_kwargs
            )
        return self._scenes[scene_id]

    def models_info(self, *, eval_models: bool = False) -> dict[int, ModelInfo]:
        """``models_info.json`` of ``models/`` (or ``models_eval/``), in metres."""
        folder = "models_eval" if eval_models else "models"
        return read_models_info(self.root / folder / "models_info.json")

    def model_path(self, obj_id: int, *, eval_models: bool = False) -> Path:
        """Path of the PLY of ``obj_id`` (``models_eval/`` is what BOP evaluation uses)."""
        folder = "models_eval" if eval_models else "models"
        p = self.root / folder / f"obj_{obj_id:06d}.ply"
        if not p.is_file():
            raise MissingFileError(f"missing model of obj {obj_id}: {p}")
        return p

    def test_targets(self, name: str = "test_targets_bop19.json") -> list[TestTarget]:
        """Targets of the BOP challenge (``test_targets_bop19.json`` in ``root``)."""
        return read_test_targets(self.root / name)


def _image_index(
    dataset: BOPDataset, scene_ids: Sequence[int] | None, targets: Sequence[TestTarget] | None
) -> list[tuple[int, int]]:
    if targets is not None:
        keys = sorted({(t.scene_id, t.im_id) for t in targets})
        return [k for k in keys if scene_ids is None or k[0] in scene_ids]
    ids = dataset.scene_ids if scene_ids is None else list(scene_ids)
    return [(s, i) for s in ids for i in dataset.scene(s).im_ids]


def _targets(root: Path, targets: bool | str | Path | Sequence[TestTarget] | None) -> Any:
    if targets is None or targets is False:
        return None
    if targets is True:
        return read_test_targets(root / "test_targets_bop19.json")
    if isinstance(targets, (str, Path)):
        p = Path(targets)
        return read_test_targets(p if p.is_absolute() or p.exists() else root / p)
    return list(targets)


class BOPImageDataset(torch.utils.data.Dataset):
    """Every image of a BOP split (optionally only those named by the test targets).

    Batch with ``DataLoader(ds, collate_fn=collate_images)``.

    Args:
        root: dataset folder.
        split: split folder name.
        scene_ids: restrict to these scenes.
        targets: ``True`` for ``test_targets_bop19.json``, a path, or a list of
            :class:`TestTarget`: keep only the images they name.
        **scene_kwargs: see :class:`BOPScene`.
    """

    def __init__(
        self,
        root: str | Path,
        split: str = "test",
        *,
        scene_ids: Sequence[int] | None = None,
        targets: bool | str | Path | Sequence[TestTarget] | None = None,
        **scene_kwargs: Any,
    ) -> None:
        self.dataset = BOPDataset(root, split, **scene_kwargs)
        self.index = _image_index(self.dataset, scene_ids, _targets(self.dataset.root, targets))

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, i: int) -> dict[str, Any]:
        scene_id, im_id = self.index[i]
        return self.dataset.scene(scene_id).image_sample(im_id)


def _instance_sample(
    scene: BOPScene,
    im_id: int,
    mask: torch.Tensor,
    what: str,
) -> dict[str, Any]:
    cam = scene._cam(im_id)
    out: dict[str, Any] = {
        "scene_id": scene.scene_id,
        "im_id": im_id,
        "K": torch.as_tensor(cam.K, dtype=scene.dtype),
    }
    depth = scene.load_depth_image(im_id) if scene.load_depth else None
    if scene.load_rgb:
        out["rgb"] = scene.load_rgb_image(im_id)
    if depth is not None:
        out["depth"] = depth
        if depth.shape != mask.shape:
            warnings.warn(
                f"{what}: mask {tuple(mask.shape)} and depth {tuple(depth.shape)} differ in size; "
                "instance flagged invalid",
                BOPDataWarning,
                stacklevel=3,
            )
            out["mask"] = torch.zeros(depth.shape, dtype=torch.bool)
            out["valid"], out["num_valid_pixels"] = False, 0
            return out
    out["mask"] = mask
    out["valid"], out["num_valid_pixels"] = _validity(mask, depth, scene.min_valid_pixels, what)
    return out


class BOPInstanceDataset(torch.utils.data.Dataset):
    """Every ground-truth object instance of a BOP split, one per item.

    Items are dicts with ``scene_id``, ``im_id``, ``gt_idx``, ``obj_id`` (int), ``K`` ``(3, 3)``,
    ``rgb`` ``(3, H, W)``, ``depth`` ``(H, W)`` metres, ``mask`` ``(H, W)`` bool (the visible
    mask), ``mask_full`` ``(H, W)``, ``pose`` ``(4, 4)`` model-to-camera in metres,
    ``visib_fract``, ``valid`` (bool) and ``num_valid_pixels``. An item whose mask is empty or holds
    fewer than ``min_valid_pixels`` valid depth pixels has ``valid`` False (with a warning).

    Args:
        root: dataset folder.
        split: split folder name.
        scene_ids: restrict to these scenes.
        obj_ids: restrict to these objects.
        targets: keep only instances of the (image, object) pairs of the test targets (see
            :class:`BOPImageDataset`).
        min_visib_fract: skip instances less visible than this (needs ``scene_gt_info.json``);
            decided from the JSON, without reading images.
        **scene_kwargs: see :class:`BOPScene`.
    """

    def __init__(
        self,
        root: str | Path,
        split: str = "test",
        *,
        scene_ids: Sequence[int] | None = None,
        obj_ids: Sequence[int] | None = None,
        targets: bool | str | Path | Sequence[TestTarget] | None = None,
        min_visib_fract: float = 0.0,
        **scene_kwargs: Any,
    ) -> None:
        self.dataset = BOPDataset(root, split, **scene_kwargs)
        tg = _targets(self.dataset.root, targets)
        wanted = None if tg is None else {(t.scene_id, t.im_id, t.obj_id) for t in tg}
        self.index: list[tuple[int, int, int]] = []
        for scene_id, im_id in _image_index(self.dataset, scene_ids, tg):
            scene = self.dataset.scene(scene_id)
            infos = scene.gt_info.get(im_id, [])
            for gt_idx, g in enumerate(scene.gt_of(im_id)):
                if obj_ids is not None and g.obj_id not in obj_ids:
                    continue
                if wanted is not None and (scene_id, im_id, g.obj_id) not in wanted:
                    continue
                if min_visib_fract > 0 and infos and infos[gt_idx].visib_fract < min_visib_fract:
                    continue
                self.index.append((scene_id, im_id, gt_idx))

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, i: int) -> dict[str, Any]:
        scene_id, im_id, gt_idx = self.index[i]
        scene = self.dataset.scene(scene_id)
        gt = scene.gt_of(im_id)[gt_idx]
        mask = scene.load_mask(im_id, gt_idx, visible=True)
        out = _instance_sample(scene, im_id, mask, scene._where(im_id, gt_idx))
        out["mask_full"] = scene.load_mask(im_id, gt_idx, visible=False)
        infos = scene.gt_info.get(im_id, [])
        out["gt_idx"] = gt_idx
        out["obj_id"] = gt.obj_id
        out["pose"] = torch.as_tensor(gt.pose, dtype=scene.dtype)
        out["visib_fract"] = float(infos[gt_idx].visib_fract) if infos else 1.0
        return out


class BOPDetectionDataset(torch.utils.data.Dataset):
    """Instances given by detection/segmentation results (e.g. public ZebraPose/CNOS masks).

    Items are dicts with ``scene_id``, ``im_id``, ``det_idx``, ``obj_id``, ``score``, ``bbox``
    ``(4,)`` ``(x, y, w, h)``, ``K``, ``rgb``, ``depth``, ``mask`` (the decoded segmentation,
    ``(H, W)`` bool), ``valid`` and ``num_valid_pixels``. A detection whose mask is empty, has the
    wrong size or covers too few valid depth pixels is flagged invalid (with a warning).

    Args:
        root: dataset folder.
        split: split folder name.
        detections: a results file path or a list of :class:`Detection`.
        score_threshold: drop detections scoring below this.
        targets: keep only detections of (image, object) pairs in the test targets, at most
            ``inst_count`` per pair (the best scoring), as the BOP challenge does.
        **scene_kwargs: see :class:`BOPScene`.

    Raises:
        BOPFormatError: a detection names a scene or image the split does not have.
    """

    def __init__(
        self,
        root: str | Path,
        split: str,
        detections: str | Path | Sequence[Detection],
        *,
        score_threshold: float = 0.0,
        targets: bool | str | Path | Sequence[TestTarget] | None = None,
        **scene_kwargs: Any,
    ) -> None:
        self.dataset = BOPDataset(root, split, **scene_kwargs)
        dets = read_detections(detections) if isinstance(detections, (str, Path)) else detections
        dets = [d for d in dets if d.score >= score_threshold]
        tg = _targets(self.dataset.root, targets)
        if tg is not None:
            budget = {(t.scene_id, t.im_id, t.obj_id): t.inst_count for t in tg}
            kept = []
            for d in sorted(dets, key=lambda d: -d.score):
                key = (d.scene_id, d.im_id, d.obj_id)
                if budget.get(key, 0) > 0:
                    budget[key] -= 1
                    kept.append(d)
            dets = kept
        scenes = set(self.dataset.scene_ids)
        for d in dets:
            if d.scene_id not in scenes:
                raise BOPFormatError(
                    f"detection of obj {d.obj_id} names scene {d.scene_id} image {d.im_id}, but "
                    f"{self.dataset.split_path} has no scene {d.scene_id}"
                )
            if d.im_id not in self.dataset.scene(d.scene_id).camera:
                raise BOPFormatError(
                    f"detection of obj {d.obj_id} names scene {d.scene_id} image {d.im_id}, which "
                    "is not in its scene_camera.json"
                )
        self.detections = sorted(dets, key=lambda d: (d.scene_id, d.im_id, -d.score))

    def __len__(self) -> int:
        return len(self.detections)

    def __getitem__(self, i: int) -> dict[str, Any]:
        d = self.detections[i]
        scene = self.dataset.scene(d.scene_id)
        what = f"scene {d.scene_id} image {d.im_id} detection {i} (obj {d.obj_id})"
        try:
            mask = d.mask()
        except BOPFormatError as exc:
            warnings.warn(f"{exc}; instance flagged invalid", BOPDataWarning, stacklevel=2)
            mask = torch.zeros(0, 0, dtype=torch.bool)
        out = _instance_sample(scene, d.im_id, mask, what)
        out["det_idx"] = i
        out["obj_id"] = d.obj_id
        out["score"] = float(d.score)
        out["bbox"] = torch.tensor(d.bbox, dtype=scene.dtype)
        return out


# --------------------------------------------------------------------------------------------
# Writer
# --------------------------------------------------------------------------------------------


class BOPWriter:
    """Write images and annotations of one split in the BOP format.

    Images are written at once; the scene JSON files (``scene_camera``, ``scene_gt``,
    ``scene_gt_info``) are accumulated and written by :meth:`flush` (called on leaving a ``with``
    block). Existing JSON entries of a scene are kept, so a split can be written in several runs.

    Args:
        root: dataset folder.
        split: split folder name.
        image_ext: ``".png"`` or ``".jpg"`` for colour images.
        depth_scale: default millimetres per depth unit (0.1 keeps 0.1 mm resolution up to 6.5 m).

    Example:
        >>> import tempfile
        >>> root = tempfile.mkdtemp()
        >>> with BOPWriter(root, "test") as w:
        ...     w.add_image(3, 7, K=torch.eye(3), depth=torch.full((4, 5), 0.5),
        ...                 obj_ids=[2], poses=torch.eye(4)[None],
        ...                 masks=torch.ones(1, 4, 5, dtype=torch.bool),
        ...                 masks_visib=torch.ones(1, 4, 5, dtype=torch.bool))
        >>> read_scene_gt(f"{root}/test/000003/scene_gt.json")[7][0].obj_id
        2
    """

    def __init__(
        self,
        root: str | Path,
        split: str,
        *,
        image_ext: str = ".png",
        depth_scale: float = 0.1,
    ) -> None:
        if image_ext not in (".png", ".jpg"):
            raise ValueRangeError(f"image_ext must be '.png' or '.jpg', got {image_ext!r}")
        if not depth_scale > 0:
            raise ValueRangeError(f"depth_scale must be positive, got {depth_scale}")
        self.root = Path(root)
        self.split_path = self.root / split
        self.image_ext = image_ext
        self.depth_scale = depth_scale
        self._camera: dict[int, dict[int, CameraInfo]] = {}
        self._gt: dict[int, dict[int, list[GTPose]]] = {}
        self._gt_info: dict[int, dict[int, list[GTInfo]]] = {}

    def scene_path(self, scene_id: int) -> Path:
        """Folder of ``scene_id``."""
        return self.split_path / f"{scene_id:06d}"

    def add_image(
        self,
        scene_id: int,
        im_id: int,
        *,
        K: torch.Tensor | np.ndarray,
        rgb: torch.Tensor | np.ndarray | None = None,
        depth: torch.Tensor | np.ndarray | None = None,
        obj_ids: Sequence[int] | torch.Tensor = (),
        poses: torch.Tensor | np.ndarray | None = None,
        masks: torch.Tensor | np.ndarray | None = None,
        masks_visib: torch.Tensor | np.ndarray | None = None,
        depth_scale: float | None = None,
        R_w2c: torch.Tensor | np.ndarray | None = None,
        t_w2c: torch.Tensor | np.ndarray | None = None,
    ) -> None:
        """Write one image with its instances.

        Args:
            scene_id: scene id.
            im_id: image id.
            K: intrinsics ``(3, 3)``.
            rgb: colour image, float ``(3, H, W)`` in ``[0, 1]`` or uint8 ``(H, W, 3)``.
            depth: depth ``(H, W)`` in metres (0 or NaN = missing).
            obj_ids: object id of each instance, ``n`` of them.
            poses: ``(n, 4, 4)`` model-to-camera, metres.
            masks: ``(n, H, W)`` full silhouettes (``mask/``).
            masks_visib: ``(n, H, W)`` visible parts (``mask_visib/``).
            depth_scale: millimetres per depth unit for this image (default: the writer's).
            R_w2c: optional world-to-camera rotation ``(3, 3)``.
            t_w2c: optional world-to-camera translation ``(3,)``, metres.

        ``scene_gt_info`` is computed from the masks (and depth) when both mask stacks are given.
        """
        ids = [int(o) for o in (obj_ids.tolist() if isinstance(obj_ids, torch.Tensor) else obj_ids)]
        n = len(ids)
        P = np.zeros((0, 4, 4)) if poses is None else _np(poses, np.float64).reshape(-1, 4, 4)
        if len(P) != n:
            raise ShapeError(f"{n} obj_ids but {len(P)} poses for scene {scene_id} image {im_id}")
        for name, m in (("masks", masks), ("masks_visib", masks_visib)):
            if m is not None and len(m) != n:
                raise ShapeError(
                    f"{n} obj_ids but {len(m)} {name} for scene {scene_id} image {im_id}"
                )
        scale = self.depth_scale if depth_scale is None else depth_scale
        sp = self.scene_path(scene_id)
        name = f"{im_id:06d}"
        if rgb is not None:
            write_image(sp / "rgb" / f"{name}{self.image_ext}", rgb)
        if depth is not None:
            write_depth(sp / "depth" / f"{name}.png", depth, scale)
        for i in range(n):
            if masks is not None:
                write_mask(sp / "mask" / f"{name}_{i:06d}.png", masks[i])
            if masks_visib is not None:
                write_mask(sp / "mask_visib" / f"{name}_{i:06d}.png", masks_visib[i])
        self._camera.setdefault(scene_id, {})[im_id] = CameraInfo(
            K=_np(K, np.float64).reshape(3, 3),
            depth_scale=float(scale),
            R_w2c=None if R_w2c is None else _np(R_w2c, np.float64).reshape(3, 3),
            t_w2c=None if t_w2c is None else _np(t_w2c, np.float64).reshape(3),
        )
        self._gt.setdefault(scene_id, {})[im_id] = [GTPose(o, T) for o, T in zip(ids, P)]
        if masks is not None and masks_visib is not None:
            d = None if depth is None else _np(depth, np.float64)
            self._gt_info.setdefault(scene_id, {})[im_id] = [
                compute_gt_info(masks[i], masks_visib[i], d) for i in range(n)
            ]

    def flush(self) -> None:
        """Write (merging with existing files) the scene JSON files accumulated so far."""
        for scene_id in sorted(set(self._camera) | set(self._gt) | set(self._gt_info)):
            sp = self.scene_path(scene_id)
            for fname, reader, writer, store in (
                ("scene_camera.json", read_scene_camera, write_scene_camera, self._camera),
                ("scene_gt.json", read_scene_gt, write_scene_gt, self._gt),
                ("scene_gt_info.json", read_scene_gt_info, write_scene_gt_info, self._gt_info),
            ):
                new = store.get(scene_id)
                if not new:
                    continue
                p = sp / fname
                merged: dict[int, Any] = dict(reader(p)) if p.is_file() else {}
                merged.update(new)
                writer(p, merged)
        self._camera.clear()
        self._gt.clear()
        self._gt_info.clear()

    def __enter__(self) -> BOPWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.flush()
