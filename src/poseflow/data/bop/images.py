"""Read and write the images of a BOP scene: colour, depth (millimetres in the PNG) and masks."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from PIL import Image

from poseflow.data._arrays import as_numpy
from poseflow.data.bop.records import MM_PER_M
from poseflow.errors import BOPFormatError, MissingFileError, ShapeError, ValueRangeError

__all__ = ["read_depth", "read_image", "read_mask", "write_depth", "write_image", "write_mask"]

#: A depth map whose largest valid value is below this (in metres, after applying depth_scale) is
#: taken to have been written in metres although millimetres were declared.
_MIN_PLAUSIBLE_MAX_DEPTH_M = 0.05


def read_image(path: str | Path) -> torch.Tensor:
    """Read an RGB or grey image as float ``(3, H, W)`` in ``[0, 1]`` (grey is repeated).

    Raises:
        MissingFileError: the file does not exist.
    """
    path = Path(path)
    arr = _read_array(path, "image")
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
    arr = _read_array(path, "depth map")
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
    arr = _read_array(Path(path), "mask")
    if arr.ndim == 3:
        arr = arr[..., 0]
    return torch.from_numpy(arr > 0)


def _read_array(path: Path, what: str) -> np.ndarray:
    """The pixels of an image file; ``what`` names it in the error for a missing file."""
    if not path.is_file():
        raise MissingFileError(f"missing {what} {path}")
    with Image.open(path) as im:
        return np.asarray(im)


def write_image(path: str | Path, rgb: torch.Tensor | np.ndarray) -> None:
    """Write an image given as float ``(3, H, W)`` in ``[0, 1]`` or uint8 ``(H, W, 3)``.

    The format follows the extension (``.png`` lossless, ``.jpg`` quality 95).
    """
    arr = as_numpy(rgb)
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
    d = as_numpy(depth, np.float64)
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
    m = as_numpy(mask).astype(bool)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray((m * 255).astype(np.uint8)).save(path)
