"""One RGB-D frame from plain files: colour, metric depth, intrinsics and instance masks.

What ``poseflow estimate`` reads, for users with one camera frame and a mesh rather than a BOP
dataset tree:

- colour: any image file Pillow reads;
- depth: a 16-bit PNG (or any integer image, or ``.npy``) with ``depth_scale`` metres per unit
  (default 0.001: millimetres, as most sensors and BOP write), or a float TIFF/``.npy`` already
  in metres; the median depth must be plausible (0.1-10 m), else the error says which
  ``--depth-scale`` to set;
- intrinsics: 9 numbers (row-major), a 3x3 matrix, or a JSON file or string holding either, an
  object with ``cam_K``, ``K`` or ``fx``/``fy``/``cx``/``cy``, or a BOP ``scene_camera.json``
  (one image's entry, whose ``depth_scale`` is used when none is given); the principal point must
  lie inside the image;
- instances: mask images (non-zero = object) or a BOP detections file (COCO-RLE masks).

:class:`ImageInstances` is what every estimator and the verifier take of such a frame: the colour
image, the depth, the intrinsics and the instances' masks and object ids (:attr:`Frame.instances`).
"""

from __future__ import annotations

import json
import math
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image

from poseflow._checks import check_tensor
from poseflow._units import check_depth_units, check_intrinsics
from poseflow.errors import BOPFormatError, MissingFileError, ShapeError, ValueRangeError

__all__ = [
    "Frame",
    "ImageInstances",
    "read_color",
    "read_frame",
    "read_intrinsics",
    "read_masks",
    "read_metric_depth",
]

#: Metres per unit of an integer depth image when no scale is given (millimetres).
DEFAULT_INTEGER_DEPTH_SCALE = 0.001


@dataclass(frozen=True)
class ImageInstances:
    """The instances of one RGB-D image: the five arguments of every estimator.

    What the estimators' ``estimate(rgb, depth, K, masks, obj_ids)`` take one by one, and their
    steps and the verifier (:class:`~poseflow.verify.PoseVerifier`) take as one.

    Attributes:
        rgb: the colour image ``(3, H, W)``, uint8 or float in ``[0, 1]``, or None.
        depth: depth ``(H, W)`` in metres.
        K: intrinsics ``(3, 3)`` (as given, or checked by :meth:`checked`).
        masks: instance masks ``(B, H, W)`` bool.
        obj_ids: object id of each instance ``(B,)``.

    Example:
        >>> image = ImageInstances(None, torch.ones(4, 6), [[5, 0, 3], [0, 5, 2], [0, 0, 1]],
        ...                        torch.ones(1, 4, 6, dtype=torch.bool), [7])
        >>> checked = image.checked(torch.float32)
        >>> checked.K.dtype, checked.obj_ids.tolist()
        (torch.float32, [7])
    """

    rgb: torch.Tensor | None
    depth: torch.Tensor
    K: Any
    masks: torch.Tensor
    obj_ids: torch.Tensor | Sequence[int]

    def __iter__(self) -> Iterator[Any]:
        """The five arguments in the estimators' order: ``estimate(*image)``."""
        return iter((self.rgb, self.depth, self.K, self.masks, self.obj_ids))

    def checked(self, dtype: torch.dtype) -> ImageInstances:
        """This image with ``K`` ``(3, 3)`` in ``dtype`` and ``obj_ids`` an int64 tensor ``(B,)``.

        ``K`` is checked against the depth's size ``(H, W)`` and put on the depth's device
        (:func:`~poseflow._units.check_intrinsics`).

        Raises:
            ShapeError: a depth that is not ``(H, W)``, or ``K`` not 9 numbers.
            ValueRangeError: ``K`` is not a pinhole matrix of this image.
        """
        sizes = check_tensor(self.depth, "depth", ("H", "W"), floating=False)
        K = check_intrinsics(self.K, sizes["W"], sizes["H"], dtype=dtype, device=self.depth.device)
        return replace(
            self, K=K, obj_ids=torch.as_tensor(self.obj_ids, dtype=torch.long).reshape(-1)
        )

    def twice(self) -> ImageInstances:
        """This image with every instance twice: rows ``B + i`` repeat instance ``i``."""
        ids = torch.as_tensor(self.obj_ids).reshape(-1)
        return replace(
            self, masks=torch.cat((self.masks, self.masks)), obj_ids=torch.cat((ids, ids))
        )


@dataclass
class Frame:
    """One RGB-D frame and its instances.

    Attributes:
        rgb: the colour image ``(3, H, W)`` uint8.
        depth: depth ``(H, W)`` float32 in metres, 0 where missing.
        K: intrinsics ``(3, 3)`` float64.
        masks: instance masks ``(B, H, W)`` bool.
        obj_ids: object id of each instance ``(B,)`` int64.
        scores: detection score of each instance ``(B,)`` float64 (1 for given masks).
        sources: where each instance's mask came from (a file, or a detection).
        depth_scale: the metres per unit that was applied to the depth file.
    """

    rgb: torch.Tensor
    depth: torch.Tensor
    K: torch.Tensor
    masks: torch.Tensor
    obj_ids: torch.Tensor
    scores: torch.Tensor
    sources: list[str] = field(default_factory=list)
    depth_scale: float = 1.0

    @property
    def instances(self) -> ImageInstances:
        """The colour image, depth, intrinsics, masks and object ids, as the estimators take them.

        ``estimator(*frame.instances)`` estimates the frame's poses.
        """
        return ImageInstances(self.rgb, self.depth, self.K, self.masks, self.obj_ids)

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)`` in pixels."""
        return int(self.depth.shape[1]), int(self.depth.shape[0])

    def __len__(self) -> int:
        return int(self.masks.shape[0])


def _open(path: str | Path, what: str) -> np.ndarray:
    path = Path(path)
    if not path.is_file():
        raise MissingFileError(f"{what} {path} does not exist")
    if path.suffix.lower() == ".npy":
        return np.load(path, allow_pickle=False)
    try:
        with Image.open(path) as im:
            return np.asarray(im)
    except OSError as exc:
        raise BOPFormatError(f"{what} {path} is not an image Pillow can read ({exc})") from None


def read_color(path: str | Path) -> torch.Tensor:
    """Read a colour (or grey) image as ``(3, H, W)`` uint8.

    Raises:
        MissingFileError: the file does not exist.
        BOPFormatError: not an image of 1, 3 or 4 channels.

    Example:
        >>> import tempfile
        >>> p = Path(tempfile.mkdtemp()) / "c.png"
        >>> Image.fromarray(np.zeros((4, 6, 3), np.uint8)).save(p)
        >>> read_color(p).shape
        torch.Size([3, 4, 6])
    """
    arr = _open(path, "colour image")
    if arr.ndim == 2:
        arr = np.repeat(arr[..., None], 3, axis=2)
    if arr.ndim != 3 or arr.shape[2] not in (3, 4):
        raise BOPFormatError(f"{path}: expected an RGB or grey image, got shape {arr.shape}")
    if arr.dtype == np.uint16:
        arr = (arr // 257).astype(np.uint8)
    elif arr.dtype != np.uint8:
        arr = np.clip(np.round(arr.astype(np.float64) * 255.0), 0, 255).astype(np.uint8)
    return torch.from_numpy(np.array(arr[..., :3])).permute(2, 0, 1).contiguous()


def read_metric_depth(
    path: str | Path, *, depth_scale: float | None = None
) -> tuple[torch.Tensor, float]:
    """Read a depth image in metres and check that its scale is plausible.

    Args:
        path: a 16-bit PNG (or other integer image or ``.npy``), or a float image (TIFF mode
            ``F``) or ``.npy`` in metres.
        depth_scale: metres per unit of the file; default 0.001 for integer images (millimetres)
            and 1 for float images (metres).

    Returns:
        ``(depth (H, W) float32 metres with 0 where missing, the scale applied)``.

    Raises:
        MissingFileError: the file does not exist.
        BOPFormatError: not a single-channel image.
        UnitsError: the median depth is implausible (the message gives the ``--depth-scale``
            that fixes it).
        DegenerateInputError: no valid depth at all.

    Example:
        >>> import tempfile
        >>> p = Path(tempfile.mkdtemp()) / "d.png"
        >>> Image.fromarray(np.full((4, 6), 800, np.uint16)).save(p)
        >>> d, scale = read_metric_depth(p)
        >>> round(float(d[0, 0]), 3), scale
        (0.8, 0.001)
    """
    arr = _open(path, "depth image")
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    if arr.ndim != 2 or arr.dtype.kind not in "uif":
        raise BOPFormatError(
            f"{path}: a depth image must have one channel of numbers, got {arr.dtype} {arr.shape}"
        )
    if depth_scale is None:
        depth_scale = 1.0 if arr.dtype.kind == "f" else DEFAULT_INTEGER_DEPTH_SCALE
    if not (math.isfinite(depth_scale) and depth_scale > 0):
        raise ValueRangeError(f"depth_scale must be positive, got {depth_scale}")
    depth = torch.from_numpy(arr.astype(np.float64) * depth_scale).float()
    depth = torch.where(torch.isfinite(depth) & (depth > 0), depth, torch.zeros_like(depth))
    check_depth_units(depth, scale=depth_scale, api_name="depth_scale", where=f"depth {path}")
    return depth, float(depth_scale)


def _load_json_spec(spec: str | Path) -> Any:
    """JSON text, or the content of a JSON file."""
    text = str(spec).strip()
    if text[:1] in "[{":
        try:
            return json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueRangeError(f"the intrinsics {text!r} are not valid JSON: {exc}") from None
    path = Path(spec)
    if not path.is_file():
        raise MissingFileError(
            f"intrinsics file {path} does not exist (give 9 numbers, a JSON file or JSON text)"
        )
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise BOPFormatError(f"intrinsics file {path} is not valid JSON: {exc}") from None


def _camera_entry(spec: Any, im_id: int | None) -> tuple[Any, float | None, str | None]:
    """``(K as given, BOP depth_scale in mm per unit or None, its file or None)`` of a spec.

    The file is named with the image of a ``scene_camera.json``, for the messages.
    """
    data = _load_json_spec(spec) if isinstance(spec, (str, Path)) else spec
    source = None
    if isinstance(spec, (str, Path)) and str(spec).strip()[:1] not in "[{":
        source = f"intrinsics file {spec}"
    if not isinstance(data, Mapping):
        return data, None, source
    if data and all(str(k).isdigit() for k in data):  # scene_camera.json: {im_id: entry}
        ids = sorted(int(k) for k in data)
        if im_id is None:
            if len(ids) != 1:
                raise ValueRangeError(
                    f"{spec} holds the cameras of {len(ids)} images ({ids[0]} ... {ids[-1]}); "
                    "choose one with --im-id (im_id=)"
                )
            im_id = ids[0]
        entry = data.get(str(im_id), data.get(im_id))  # type: ignore[call-overload]
        if entry is None:
            raise ValueRangeError(f"{spec} has no camera of image {im_id} (images {ids})")
        data = entry
        source = None if source is None else f"{spec} (image {im_id})"
    if not isinstance(data, Mapping):
        raise BOPFormatError(f"{spec}: a camera entry must be a JSON object")
    scale = data.get("depth_scale")
    scale = float(scale) if isinstance(scale, (int, float)) else None
    for key in ("cam_K", "K"):
        if key in data:
            return data[key], scale, source
    if all(k in data for k in ("fx", "fy", "cx", "cy")):
        f = {k: data[k] for k in ("fx", "fy", "cx", "cy")}
        return [[f["fx"], 0, f["cx"]], [0, f["fy"], f["cy"]], [0, 0, 1]], scale, source
    raise BOPFormatError(f"{spec}: no cam_K, K or fx/fy/cx/cy in the camera entry")


def _check_K(K: Any, width: int, height: int, source: str | None) -> torch.Tensor:
    """:func:`check_intrinsics`; a bad ``K`` read from a file is that file's error, named."""
    try:
        return check_intrinsics(K, width, height)
    except (ShapeError, ValueRangeError) as exc:
        if source is None:  # numbers or JSON text given directly: the caller's argument
            raise
        raise BOPFormatError(f"{source}: {exc}") from None


def read_intrinsics(
    spec: Any, width: int, height: int, *, im_id: int | None = None
) -> torch.Tensor:
    """Read and check pinhole intrinsics.

    Args:
        spec: 9 numbers (row-major) or a 3x3 matrix (list, array, tensor); or a JSON file or
            JSON text holding one, an object with ``cam_K``, ``K`` or ``fx``/``fy``/``cx``/``cy``,
            or a BOP ``scene_camera.json`` (keyed by image id).
        width: image width, pixels.
        height: image height, pixels.
        im_id: the image of a ``scene_camera.json`` (needed when it holds several).

    Returns:
        ``K`` ``(3, 3)`` float64.

    Raises:
        MissingFileError: a named file does not exist.
        ShapeError: not 9 numbers.
        ValueRangeError: malformed JSON text, a missing image, or implausible intrinsics (a
            principal point outside the image, as a transposed ``K`` gives).
        BOPFormatError: a file holding implausible intrinsics (named, with the image of a
            ``scene_camera.json``), or malformed JSON in a file.

    Example:
        >>> read_intrinsics('{"fx": 500, "fy": 500, "cx": 320, "cy": 240}', 640, 480)[0].tolist()
        [500.0, 0.0, 320.0]
    """
    K, _, source = _camera_entry(spec, im_id)
    return _check_K(K, width, height, source)


def read_masks(paths: Sequence[str | Path], width: int, height: int) -> torch.Tensor:
    """Read instance masks (non-zero pixels are the object) as ``(B, H, W)`` bool.

    Raises:
        MissingFileError: a file does not exist.
        ShapeError: a mask's size differs from the image's.
        DegenerateInputError: a mask is empty.
    """
    from poseflow.errors import DegenerateInputError

    out = []
    for p in paths:
        arr = _open(p, "mask")
        if arr.ndim == 3:
            arr = arr[..., :3].max(axis=2)
        if arr.shape != (height, width):
            raise ShapeError(
                f"mask {p} is {arr.shape[1]}x{arr.shape[0]}, the image {width}x{height}"
            )
        m = torch.from_numpy(arr > 0)
        if not bool(m.any()):
            raise DegenerateInputError(f"mask {p} is empty (no non-zero pixel)")
        _check_not_labels(arr, p)
        out.append(m)
    if not out:
        return torch.zeros(0, height, width, dtype=torch.bool)
    return torch.stack(out)


def _check_not_labels(arr: np.ndarray, path: str | Path) -> None:
    """Refuse a label image (several instances, one value each) given as one instance's mask.

    A binary mask has one non-zero value, give or take anti-aliased edges (thin bands); a label
    image has two or more values that each fill solid regions (pixels whose four neighbours
    share their value).

    Raises:
        DegenerateInputError: the image looks like a label image.
    """
    from poseflow.errors import DegenerateInputError

    inner = arr[1:-1, 1:-1]
    solid = (inner > 0) & (inner == arr[:-2, 1:-1]) & (inner == arr[2:, 1:-1])
    solid &= (inner == arr[1:-1, :-2]) & (inner == arr[1:-1, 2:])
    values, counts = np.unique(inner[solid], return_counts=True)
    large = values[counts >= 4]
    if len(large) >= 2:
        shown = ", ".join(str(int(v)) for v in large[:6]) + (", ..." if len(large) > 6 else "")
        raise DegenerateInputError(
            f"mask {path} holds {len(large)} labels ({shown}): a label image, not one instance's "
            "mask; give one binary PNG per instance (non-zero = the object), e.g. save "
            "(labels == value) for each value"
        )


def _detections_of(
    path: str | Path,
    scene_id: int | None,
    im_id: int | None,
    score_threshold: float,
    size: tuple[int, int],
) -> tuple[torch.Tensor, list[int], list[float], list[str]]:
    from poseflow.data.bop import read_detections

    dets = read_detections(path)
    images = sorted({(d.scene_id, d.im_id) for d in dets})
    if scene_id is None and im_id is None:
        if len(images) > 1:
            raise ValueRangeError(
                f"{path} holds detections of {len(images)} images; choose one with --scene-id "
                "and --im-id (scene_id=, im_id=)"
            )
    kept = [
        d
        for d in dets
        if (scene_id is None or d.scene_id == scene_id)
        and (im_id is None or d.im_id == im_id)
        and d.score >= score_threshold
    ]
    width, height = size
    masks, ids, scores, sources = [], [], [], []
    for k, d in enumerate(kept):
        m = d.mask()
        if tuple(m.shape) != (height, width):
            raise ShapeError(
                f"{path}: the mask of detection {k} (obj {d.obj_id}) is {m.shape[1]}x"
                f"{m.shape[0]}, the image {width}x{height}"
            )
        masks.append(m.bool())
        ids.append(d.obj_id)
        scores.append(d.score)
        sources.append(f"{Path(path).name}: scene {d.scene_id} image {d.im_id} obj {d.obj_id}")
    stacked = torch.stack(masks) if masks else torch.zeros(0, height, width, dtype=torch.bool)
    return stacked, ids, scores, sources


def _camera_depth_scale(depth_scale: float | None, bop_scale: float, source: str | None) -> float:
    """The depth scale to use, metres per unit, given a BOP camera entry's (mm per unit).

    The given ``depth_scale`` wins, with a warning (to the caller of :func:`read_frame`) when it
    disagrees with the camera's.
    """
    from_camera = bop_scale / 1000.0  # BOP: millimetres per unit, poseflow: metres
    if depth_scale is None:
        return from_camera
    if not math.isclose(depth_scale, from_camera, rel_tol=1e-6):
        warnings.warn(
            f"depth_scale {depth_scale:g} (m per unit, --depth-scale) overrides the "
            f"depth_scale {bop_scale:g} (mm per unit, i.e. {from_camera:g} m) of "
            f"{source or 'the camera entry'}; omit it to use the camera's",
            stacklevel=3,
        )
    return depth_scale


def _ids_of_masks(obj_ids: Sequence[int] | int | None, n: int) -> list[int]:
    """One object id per mask: 1 by default, one id for all, or one each."""
    if obj_ids is None:
        ids = [1] * n
    elif isinstance(obj_ids, int):
        ids = [obj_ids] * n
    else:
        ids = [int(o) for o in obj_ids]
        if len(ids) == 1:
            ids = ids * n
    if len(ids) != n:
        raise ShapeError(f"got {n} masks but {len(ids)} object ids")
    return ids


def read_frame(
    rgb: str | Path,
    depth: str | Path,
    K: Any,
    *,
    masks: Sequence[str | Path] = (),
    obj_ids: Sequence[int] | int | None = None,
    detections: str | Path | None = None,
    depth_scale: float | None = None,
    scene_id: int | None = None,
    im_id: int | None = None,
    score_threshold: float = 0.0,
    detector: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], Any] | None = None,
) -> Frame:
    """Read one RGB-D frame and its instances from files, with every check of this module.

    Args:
        rgb: the colour image.
        depth: the depth image (see :func:`read_metric_depth`).
        K: the intrinsics (see :func:`read_intrinsics`); the ``depth_scale`` of a BOP camera
            entry is used when ``depth_scale`` is None.
        masks: mask images, one per instance.
        obj_ids: the object id of each mask (one id for all); default 1.
        detections: a BOP detections file instead of (or besides) ``masks``.
        depth_scale: metres per unit of the depth file (see :func:`read_metric_depth`).
        scene_id: the scene of the detections (and nothing else).
        im_id: the image of the detections and of a ``scene_camera.json``.
        score_threshold: detections scoring below it are dropped.
        detector: finds the instances when no masks or detections are given: called as
            ``detector(rgb (3, H, W) uint8, depth (H, W) metres, K (3, 3))``, it returns an object
            with ``masks (B, H, W)``, ``obj_ids (B,)`` and ``scores (B,)`` (a
            :class:`~poseflow.detect.Detector`'s ``detect``).

    Returns:
        The :class:`Frame` (``B`` may be 0 when the detections hold none for the image).

    Warns:
        UserWarning: ``depth_scale`` disagrees with the ``depth_scale`` of the BOP camera entry
            (which is millimetres per unit: BOP's 0.1 is ``depth_scale=0.0001``); the given one
            is used.

    Raises:
        ShapeError: the images differ in size (both files are named), or ``obj_ids`` does not
            match ``masks``.
        UnitsError: implausible depth (the message gives the ``depth_scale`` to set).
        ValueRangeError: implausible intrinsics given as numbers, or no instance source given.
        BOPFormatError: implausible intrinsics in a file (named, with the image id).
    """
    if not masks and detections is None and detector is None:
        raise ValueRangeError("give the instances: mask images, a detections file or a detector")
    color = read_color(rgb)
    raw_K, bop_scale, source = _camera_entry(K, im_id)
    if bop_scale is not None:
        depth_scale = _camera_depth_scale(depth_scale, bop_scale, source)
    d, scale = read_metric_depth(depth, depth_scale=depth_scale)
    if tuple(color.shape[1:]) != tuple(d.shape):
        raise ShapeError(
            f"the colour image {rgb} is {color.shape[2]}x{color.shape[1]}, the depth image "
            f"{depth} {d.shape[1]}x{d.shape[0]}: they must be registered to the same pixels"
        )
    height, width = d.shape
    intrinsics = _check_K(raw_K, width, height, source)
    m = read_masks(list(masks), width, height)
    ids = _ids_of_masks(obj_ids, len(m))
    scores = [1.0] * len(m)
    sources = [str(p) for p in masks]
    if detections is not None:
        dm, dids, dscores, dsrc = _detections_of(
            detections, scene_id, im_id, score_threshold, (width, height)
        )
        m = torch.cat([m, dm])
        ids, scores, sources = ids + dids, scores + dscores, sources + dsrc
    if detector is not None and not masks and detections is None:
        found = detector(color, d, intrinsics.float())
        kept = found.scores >= score_threshold
        m = found.masks[kept].bool()
        ids = [int(o) for o in found.obj_ids[kept].tolist()]
        scores = [float(x) for x in found.scores[kept].tolist()]
        sources = [f"detector, score {x:.2f}" for x in scores]
    return Frame(
        rgb=color,
        depth=d,
        K=intrinsics,
        masks=m,
        obj_ids=torch.tensor(ids, dtype=torch.long),
        scores=torch.tensor(scores, dtype=torch.float64),
        sources=sources,
        depth_scale=scale,
    )
