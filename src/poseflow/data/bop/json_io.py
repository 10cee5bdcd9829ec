"""Read and write the JSON files of a BOP dataset (millimetres in the files, metres in poseflow)."""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from poseflow.data._arrays import as_numpy
from poseflow.data.bop.records import (
    MM_PER_M,
    CameraInfo,
    ContinuousSymmetry,
    Detection,
    GTInfo,
    GTPose,
    ModelInfo,
    TestTarget,
)
from poseflow.errors import BOPFormatError, MissingFileError

__all__ = [
    "read_detections",
    "read_models_info",
    "read_scene_camera",
    "read_scene_gt",
    "read_scene_gt_info",
    "read_test_targets",
    "write_detections",
    "write_models_info",
    "write_scene_camera",
    "write_scene_gt",
    "write_scene_gt_info",
    "write_test_targets",
]

#: A record read from one instance's JSON entry.
_Record = TypeVar("_Record")


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


def _per_entry(path: Path, what: str, parse: Callable[[Any, str], _Record]) -> list[_Record]:
    """``[parse(entry, where), ...]`` of a file holding a JSON list of ``what``.

    ``where`` names the file and the entry's index, for the parser's error messages.
    """
    data = _load_json(path)
    if not isinstance(data, list):
        raise BOPFormatError(f"{path}: expected a JSON list of {what}")
    return [parse(e, f"{path} (entry {i})") for i, e in enumerate(data)]


def _per_instance(path: Path, parse: Callable[[Any, str], _Record]) -> dict[int, list[_Record]]:
    """``{im_id: [parse(entry, where), ...]}`` of a file holding a list of instances per image.

    ``where`` names the file, scene, image and instance, for the parser's error messages.
    """
    out = {}
    for im_id, entries in sorted(_int_keys(_load_json(path), path).items()):
        if not isinstance(entries, list):
            raise BOPFormatError(f"{path} (image {im_id}): expected a list of instances")
        out[im_id] = [
            parse(entry, f"{path} (scene {_scene_of(path)}, image {im_id}, instance {gt_idx})")
            for gt_idx, entry in enumerate(entries)
        ]
    return out


def read_scene_camera(path: str | Path) -> dict[int, CameraInfo]:
    """Read ``scene_camera.json``.

    Args:
        path: the JSON file.

    Returns:
        ``{im_id: CameraInfo}`` with translations in metres.

    Raises:
        MissingFileError: the file does not exist.
        BOPFormatError: a key is missing or malformed, or ``cam_K`` is not a pinhole matrix
            (zero, transposed); the message names file, scene and image.
    """
    path = Path(path)
    out = {}
    for im_id, entry in sorted(_int_keys(_load_json(path), path).items()):
        where = f"{path} (scene {_scene_of(path)}, image {im_id})"
        K = _array(_get(entry, "cam_K", where), 9, where, "cam_K").reshape(3, 3)
        if not K.any() or K[2].tolist() != [0.0, 0.0, 1.0] or not (K[0, 0] > 0 and K[1, 1] > 0):
            raise BOPFormatError(
                f"{where}: cam_K {K.reshape(-1).tolist()} is not a pinhole matrix (positive "
                "fx and fy, last row 0 0 1, row-major): is it transposed, or zero?"
            )
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
    return _per_instance(Path(path), _gt_pose)


def _gt_pose(entry: Any, where: str) -> GTPose:
    R = _array(_get(entry, "cam_R_m2c", where), 9, where, "cam_R_m2c").reshape(3, 3)
    t = _array(_get(entry, "cam_t_m2c", where), 3, where, "cam_t_m2c") / MM_PER_M
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return GTPose(obj_id=int(_get(entry, "obj_id", where)), pose=T)


def read_scene_gt_info(path: str | Path) -> dict[int, list[GTInfo]]:
    """Read ``scene_gt_info.json``.

    Returns:
        ``{im_id: [GTInfo, ...]}`` aligned with :func:`read_scene_gt`.

    Raises:
        MissingFileError: the file does not exist.
        BOPFormatError: a key is missing or malformed.
    """
    return _per_instance(Path(path), _gt_info)


def _gt_info(e: Any, where: str) -> GTInfo:
    return GTInfo(
        bbox_obj=_box(e, "bbox_obj", where),
        bbox_visib=_box(e, "bbox_visib", where),
        px_count_all=int(_get(e, "px_count_all", where)),
        px_count_valid=int(_get(e, "px_count_valid", where)),
        px_count_visib=int(_get(e, "px_count_visib", where)),
        visib_fract=float(_get(e, "visib_fract", where)),
    )


def _box(entry: Any, key: str, where: str) -> tuple[int, int, int, int]:
    a = _array(_get(entry, key, where), 4, where, key).astype(int)
    return (int(a[0]), int(a[1]), int(a[2]), int(a[3]))


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
    return _per_entry(Path(path), "targets", _test_target)


def _test_target(e: Any, where: str) -> TestTarget:
    return TestTarget(
        scene_id=int(_get(e, "scene_id", where)),
        im_id=int(_get(e, "im_id", where)),
        obj_id=int(_get(e, "obj_id", where)),
        inst_count=int(_get(e, "inst_count", where)),
    )


def read_detections(path: str | Path) -> list[Detection]:
    """Read detection/segmentation results in the BOP format.

    The file is a JSON list of ``{scene_id, image_id, category_id, score, bbox, segmentation,
    time}`` where ``segmentation`` is a COCO RLE, compressed (string ``counts``) or not (list).
    Masks are decoded lazily by :meth:`Detection.mask`.

    Raises:
        MissingFileError: the file does not exist.
        BOPFormatError: an entry lacks a key or holds a value that is not a number (the message
            gives its index, scene and image).
    """
    return _per_entry(Path(path), "detections", _detection)


def _number(e: Any, key: str, where: str, kind: type = float, default: Any = None) -> Any:
    """``kind(e[key])`` (``default`` when absent and given), or an error naming the entry."""
    value = _get(e, key, where) if default is None or key in e else default
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise BOPFormatError(f"{where}: '{key}' must be a number, got {value!r}")
    if kind is int and float(value) != int(value):
        raise BOPFormatError(f"{where}: '{key}' must be an integer, got {value!r}")
    out = kind(value)
    if not math.isfinite(out):
        raise BOPFormatError(f"{where}: '{key}' must be finite, got {value!r}")
    return out


def _detection(e: Any, where: str) -> Detection:
    scene_id = _number(e, "scene_id", where, int)
    im_id = _number(e, "image_id", where, int)
    where = where.removesuffix(")") + f", scene {scene_id}, image {im_id})"
    seg = e.get("segmentation")
    if seg is not None and not (isinstance(seg, Mapping) and "counts" in seg and "size" in seg):
        raise BOPFormatError(f"{where}: segmentation must be a COCO RLE with counts and size")
    bbox = _array(e.get("bbox", [0, 0, 0, 0]), 4, where, "bbox")
    return Detection(
        scene_id=scene_id,
        im_id=im_id,
        obj_id=_number(e, "category_id", where, int),
        score=_number(e, "score", where),
        bbox=(float(bbox[0]), float(bbox[1]), float(bbox[2]), float(bbox[3])),
        segmentation=seg,
        time=_number(e, "time", where, default=-1.0),
    )


def _dump(path: str | Path, data: Any) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w") as f:
        json.dump(data, f, indent=2)
        f.write("\n")


def _floats(a: Any) -> list[float]:
    return [float(v) for v in as_numpy(a, np.float64).reshape(-1)]


def write_scene_camera(path: str | Path, cameras: Mapping[int, CameraInfo]) -> None:
    """Write ``scene_camera.json`` from ``{im_id: CameraInfo}`` (metres in, mm in the file)."""
    data = {}
    for im_id, cam in sorted(cameras.items()):
        e: dict[str, Any] = {"cam_K": _floats(cam.K), "depth_scale": float(cam.depth_scale)}
        if cam.R_w2c is not None and cam.t_w2c is not None:
            e["cam_R_w2c"] = _floats(cam.R_w2c)
            e["cam_t_w2c"] = _floats(as_numpy(cam.t_w2c, np.float64) * MM_PER_M)
        data[str(im_id)] = e
    _dump(path, data)


def write_scene_gt(path: str | Path, gts: Mapping[int, Sequence[GTPose]]) -> None:
    """Write ``scene_gt.json`` from ``{im_id: [GTPose, ...]}`` (poses in metres)."""
    data = {}
    for im_id, poses in sorted(gts.items()):
        entries = []
        for gt in poses:
            T = as_numpy(gt.pose, np.float64)
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
            "xyz", as_numpy(info.min_xyz, np.float64), as_numpy(info.size_xyz, np.float64)
        ):
            e[f"min_{a}"] = float(lo * MM_PER_M)
            e[f"size_{a}"] = float(size * MM_PER_M)
        if info.symmetries_discrete:
            syms = []
            for S in info.symmetries_discrete:
                S = as_numpy(S, np.float64).copy()
                S[:3, 3] *= MM_PER_M
                syms.append(_floats(S))
            e["symmetries_discrete"] = syms
        if info.symmetries_continuous:
            e["symmetries_continuous"] = [
                {
                    "axis": _floats(s.axis),
                    "offset": _floats(as_numpy(s.offset, np.float64) * MM_PER_M),
                }
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
