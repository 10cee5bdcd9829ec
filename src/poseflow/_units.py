"""Plausibility checks of units and intrinsics: the magnitudes that reveal a mix-up.

poseflow works in metres. A depth image in millimetres read as metres, a mesh in millimetres
loaded without its scale, or a transposed intrinsic matrix do not fail by themselves: they give
empty datasets, objects behind the camera and poses flagged valid. These checks stop such input
early with a :class:`~poseflow.errors.UnitsError` (or :class:`~poseflow.errors.ValueRangeError`
for intrinsics) whose message names the option that fixes it.

The plausible ranges: a median scene depth of 0.1 to 10 m (:data:`DEPTH_RANGE`), an object
diameter of 5 mm to 5 m (:data:`DIAMETER_RANGE`), and an object no larger than twice its
distance to the camera.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch

from poseflow.errors import DegenerateInputError, ShapeError, UnitsError, ValueRangeError

__all__ = [
    "DEPTH_RANGE",
    "DIAMETER_RANGE",
    "check_depth_units",
    "check_diameter_units",
    "check_intrinsics",
    "check_size_against_depth",
    "in_front_of_camera",
]

#: Plausible median depth of the valid pixels of an image, metres.
DEPTH_RANGE: tuple[float, float] = (0.1, 10.0)

#: Plausible object diameter, metres.
DIAMETER_RANGE: tuple[float, float] = (0.005, 5.0)


def _suggest(value: float, low: float, high: float, scale: float, typical: float) -> float | None:
    """The scale (a power of ten times ``scale``) that brings ``value`` into ``[low, high]``.

    Of several, the one that brings it nearest ``typical`` (the usual magnitude), so that depth
    in units of 0.1 mm is not taken for millimetres of a scene 8 m away.
    """
    factors = [10.0**k for k in range(-6, 7) if k != 0 and low <= value * 10.0**k <= high]
    if not factors or not value > 0:
        return None
    best = min(factors, key=lambda f: abs(math.log10(value * f / typical)))
    return scale * best


def _fix(name: str, scale: float, suggested: float | None, api_name: str | None = None) -> str:
    """How to fix the scale: ``set --flag VALUE`` (``name=VALUE`` when ``name`` ends in ``=``)."""
    if suggested is None:
        return f"check the units and {name.rstrip('=')}"
    value = f"{suggested:g}"
    fix = f"set {name}{value}" if name.endswith("=") else f"set {name} {value}"
    if api_name is not None:
        fix += f" ({api_name}={value} in Python)"
    return fix + ("" if scale == 1.0 else f"; it is {scale:g}")


def check_depth_units(
    depth: torch.Tensor,
    *,
    scale_name: str = "--depth-scale",
    scale: float = 1.0,
    where: str = "the depth image",
    api_name: str | None = None,
) -> float:
    """Check that a depth image is in metres; returns the median of its valid pixels.

    Args:
        depth: depth ``(H, W)`` (or any shape) after scaling, metres; 0 marks missing pixels.
        scale_name: the option that sets the scale (``--depth-scale``, or ``depth_scale=``
            for a Python argument), for the message.
        scale: the scale that was applied (the message suggests a corrected one).
        where: what the depth is, for the message.
        api_name: the Python argument that sets the scale too, when ``scale_name`` is an option.

    Returns:
        The median valid depth in metres.

    Raises:
        DegenerateInputError: no pixel holds a finite positive depth.
        UnitsError: the median depth lies outside :data:`DEPTH_RANGE`.

    Example:
        >>> check_depth_units(torch.full((4, 4), 0.75))
        0.75
        >>> try:
        ...     check_depth_units(torch.full((4, 4), 800.0))
        ... except UnitsError as e:
        ...     print(str(e).split("? ")[-1])
        set --depth-scale 0.001
    """
    d = torch.as_tensor(depth)
    valid = d[torch.isfinite(d) & (d > 0)]
    if valid.numel() == 0:
        raise DegenerateInputError(f"{where} holds no valid (finite, positive) depth")
    median = float(valid.float().median())
    low, high = DEPTH_RANGE
    if not low <= median <= high:
        guess = "millimetres read as metres? " if median > high else "metres read as millimetres? "
        suggested = _suggest(median, low, high, scale, 1.0)
        raise UnitsError(
            f"{where} has a median depth of {median:g} m, outside the plausible {low:g}-{high:g} "
            f"m: {guess}{_fix(scale_name, scale, suggested, api_name)}"
        )
    return median


def check_diameter_units(
    diameter: float,
    *,
    scale_name: str = "--mesh-scale",
    scale: float = 1.0,
    where: str = "the object",
    api_name: str | None = None,
) -> float:
    """Check that an object's diameter (metres) is plausible; returns it.

    Args:
        diameter: the diameter after scaling, metres.
        scale_name: the option that sets the mesh scale (``--mesh-scale``, or ``scale=`` for a
            Python argument), for the message.
        scale: the scale that was applied.
        where: the object's name or file, for the message.
        api_name: the Python argument that sets the scale too, when ``scale_name`` is an option.

    Returns:
        ``diameter``.

    Raises:
        UnitsError: the diameter lies outside :data:`DIAMETER_RANGE`.

    Example:
        >>> check_diameter_units(0.155)
        0.155
        >>> try:
        ...     check_diameter_units(155.0, where="mesh.ply")
        ... except UnitsError as e:
        ...     print(str(e).split("? ")[-1])
        set --mesh-scale 0.001
    """
    low, high = DIAMETER_RANGE
    if not (math.isfinite(diameter) and low <= diameter <= high):
        guess = "is the mesh in millimetres? " if diameter > high else ""
        suggested = _suggest(diameter, low, high, scale, 0.1)
        raise UnitsError(
            f"{where} has a diameter of {diameter:g} m, outside the plausible {low:g}-{high:g} "
            f"m: {guess}{_fix(scale_name, scale, suggested, api_name)}"
        )
    return diameter


def check_size_against_depth(
    diameter: float,
    depth: float,
    *,
    where: str = "the object",
    hint: str = "check --depth-scale and --mesh-scale",
) -> None:
    """Check that an object is no larger than twice its distance to the camera.

    Each of depth and diameter can look plausible alone while one is off by a factor that
    still keeps it in range (a mesh in centimetres read with a millimetre scale); an object
    that would hold the camera inside it gives that away.

    Args:
        diameter: the object's diameter, metres.
        depth: the median depth of its pixels, metres.
        where: the object's name, for the message.
        hint: what to check, for the message.

    Raises:
        UnitsError: ``diameter > 2 * depth``.

    Example:
        >>> check_size_against_depth(0.2, 0.8)
        >>> try:
        ...     check_size_against_depth(2.0, 0.5)
        ... except UnitsError as e:
        ...     print(str(e).split(": ")[0])
        the object has a diameter of 2 m but lies 0.5 m from the camera
    """
    if diameter > 2.0 * depth:
        raise UnitsError(
            f"{where} has a diameter of {diameter:g} m but lies {depth:g} m from the camera: the "
            f"depth and the mesh are not in the same unit; {hint}"
        )


def check_intrinsics(
    K: Any,
    width: int,
    height: int,
    *,
    name: str = "K",
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """Check and convert a pinhole intrinsic matrix.

    Accepts a ``(3, 3)`` tensor, array or nested list, or 9 numbers in row-major order.

    Args:
        K: the intrinsics.
        width: image width, pixels.
        height: image height, pixels.
        name: the argument's name, for messages.
        dtype: dtype of the returned tensor.
        device: device of the returned tensor (default: ``K``'s, or the CPU).

    Returns:
        ``K`` as a ``(3, 3)`` tensor.

    Raises:
        ShapeError: not 9 numbers.
        ValueRangeError: non-finite entries, a non-positive focal length, a last row other than
            ``[0, 0, 1]``, or a principal point outside the image (a transposed ``K``, or ``K``
            of another resolution).

    Example:
        >>> K = [[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]
        >>> check_intrinsics(K, 640, 480).shape
        torch.Size([3, 3])
        >>> try:
        ...     check_intrinsics(torch.tensor(K).T, 640, 480)
        ... except ValueRangeError as e:
        ...     print(e)
        K's last row must be [0, 0, 1], got [320.0, 240.0, 1.0]: is K transposed?
    """
    if isinstance(K, torch.Tensor):
        t = K.detach().to(dtype=dtype, device=device if device is not None else K.device)
    else:
        try:
            t = torch.as_tensor(_nested_floats(K), dtype=dtype, device=device)
        except (TypeError, ValueError) as exc:
            raise ShapeError(f"{name} must be 9 numbers or a 3x3 matrix: {exc}") from None
    if t.numel() != 9:
        raise ShapeError(f"{name} must be 9 numbers or a 3x3 matrix, got shape {tuple(t.shape)}")
    t = t.reshape(3, 3)
    if not bool(torch.isfinite(t).all()):
        raise ValueRangeError(f"{name} holds NaN or inf")
    row = [float(x) for x in t[2]]
    if row != [0.0, 0.0, 1.0]:
        raise ValueRangeError(f"{name}'s last row must be [0, 0, 1], got {row}: is K transposed?")
    fx, fy, cx, cy = (float(t[0, 0]), float(t[1, 1]), float(t[0, 2]), float(t[1, 2]))
    if not (fx > 0 and fy > 0):
        raise ValueRangeError(f"{name}'s focal lengths must be positive, got fx={fx}, fy={fy}")
    if not (0 < cx < width and 0 < cy < height):
        raise ValueRangeError(
            f"{name}'s principal point ({cx:g}, {cy:g}) lies outside the {width}x{height} image: "
            "is K transposed, or given for another resolution?"
        )
    return t


def _nested_floats(K: Any) -> Any:
    """``K`` (array, nested sequences of numbers) as nested Python floats."""
    if hasattr(K, "tolist"):
        K = K.tolist()
    if isinstance(K, (str, bytes)):
        raise TypeError(f"got the string {K!r}")
    if isinstance(K, Sequence):
        return [_nested_floats(x) for x in K]
    if isinstance(K, bool):
        raise TypeError(f"got {K!r}")
    return float(K)


def in_front_of_camera(poses: torch.Tensor, *, min_z: float = 0.0) -> torch.Tensor:
    """Whether each pose puts the object's origin in front of the camera (``t_z > min_z``).

    A pose with ``t_z <= 0`` is never a valid estimate: the object would be behind the camera.

    Args:
        poses: model-to-camera transforms ``(B, 4, 4)``, metres.
        min_z: the smallest accepted depth of the origin, metres.

    Returns:
        ``(B,)`` bool.

    Example:
        >>> T = torch.eye(4).repeat(2, 1, 1); T[0, 2, 3] = 0.7; T[1, 2, 3] = -0.7
        >>> in_front_of_camera(T).tolist()
        [True, False]
    """
    if not isinstance(poses, torch.Tensor) or poses.dim() != 3 or poses.shape[-2:] != (4, 4):
        raise ShapeError("poses must be a (B, 4, 4) tensor")
    z = poses[:, 2, 3]
    return torch.isfinite(z) & (z > min_z)
