"""Plausibility checks of units and intrinsics: the magnitudes that reveal a mix-up.

poseflow works in metres. A depth image in millimetres read as metres, a mesh in millimetres
loaded without its scale, or a transposed intrinsic matrix do not fail by themselves: they give
empty datasets, objects behind the camera and poses flagged valid. These checks stop such input
early with a :class:`~poseflow.errors.UnitsError` (or :class:`~poseflow.errors.ValueRangeError`
for intrinsics) whose message names the option that fixes it.

The plausible ranges: a median scene depth of 0.1 to 10 m (:data:`DEPTH_RANGE`), an object
diameter of 5 mm to 5 m (:data:`DIAMETER_RANGE`), an object no larger than twice its
distance to the camera, and masked depth whose back-projected extent agrees with the objects'
diameters (:data:`EXTENT_RATIO_RANGE`, :func:`check_depth_extent`).
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
    "EXTENT_RATIO_RANGE",
    "NEAR_DEPTH",
    "check_depth_extent",
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

#: Plausible ratio of the extent of a masked, back-projected depth to the object's diameter
#: (:func:`check_depth_extent`): the typical instance of an image may span at most 3 diameters
#: (no visible part is larger than its object), and the largest must span at least a twentieth
#: of one, or a third of one where the masked depth is nearer than :data:`NEAR_DEPTH`. The lower
#: bounds are looser because a visible part can be much smaller than its object: an instance
#: 10 % visible, one compact patch, spans 0.09 (a thin clamp's) to 0.35 of its diameter.
EXTENT_RATIO_RANGE: tuple[float, float] = (0.05, 3.0)

#: Below this median depth (metres) of the masked pixels, the largest extent ratio must reach a
#: third (:func:`check_depth_extent`): a depth ten times too small puts a scene 1-3 m away here.
NEAR_DEPTH: float = 0.3


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


def _implausible(what: str, value: float, bounds: tuple[float, float], advice: str) -> UnitsError:
    """``what`` of ``value`` m lies outside ``bounds`` (metres): the error, with ``advice``."""
    low, high = bounds
    return UnitsError(f"{what} of {value:g} m, outside the plausible {low:g}-{high:g} m: {advice}")


def _check_range(
    value: float,
    bounds: tuple[float, float],
    typical: float,
    what: str,
    guesses: tuple[str, str],
    scale_name: str,
    scale: float,
    api_name: str | None,
) -> None:
    """Raise the UnitsError of a ``value`` (metres) that is not finite or outside ``bounds``.

    Its message says ``what`` had the value, the likely mix-up (``guesses``: below, above the
    bounds) and the scale that brings the value nearest ``typical`` (:func:`_suggest`).
    """
    low, high = bounds
    if math.isfinite(value) and low <= value <= high:
        return
    fix = _fix(scale_name, scale, _suggest(value, low, high, scale, typical), api_name)
    raise _implausible(what, value, bounds, guesses[value > high] + fix)


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
    guesses = ("metres read as millimetres? ", "millimetres read as metres? ")
    what = f"{where} has a median depth"
    _check_range(median, DEPTH_RANGE, 1.0, what, guesses, scale_name, scale, api_name)
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
    guesses = ("", "is the mesh in millimetres? ")
    what = f"{where} has a diameter"
    _check_range(diameter, DIAMETER_RANGE, 0.1, what, guesses, scale_name, scale, api_name)
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


def _extent(points: torch.Tensor) -> float:
    """Twice the 90th percentile of the distances of ``points`` ``(N, 3)`` to their median point.

    Rotation-invariant and robust to the flying pixels and stray background pixels of a mask's
    border (up to a tenth of the points); about the diameter for a fully visible object.
    """
    if points.shape[0] > 20000:  # evenly thinned: the percentile barely moves
        points = points[:: (points.shape[0] + 19999) // 20000]
    centre = points.median(dim=0).values
    return 2.0 * float(torch.quantile((points - centre).norm(dim=1), 0.9))


def check_depth_extent(
    depth: torch.Tensor,
    K: Any,
    masks: torch.Tensor,
    diameters: Sequence[float] | torch.Tensor,
    *,
    min_points: int = 50,
    where: str = "the depth image",
    scale_name: str | None = None,
    scale: float = 1.0,
    api_name: str | None = None,
) -> torch.Tensor:
    """Check that the depth inside each mask spans about as much as its object.

    Each mask's valid depth, clamped to half the object's diameter around its median (so that
    the far background a loose mask takes in does not count), is back-projected and its robust
    extent (twice the 90th percentile of the distances to the median point) compared with the
    object's diameter: a depth in the wrong unit scales every extent by one factor (10 for
    0.1 mm read as millimetres), while its median alone can still look plausible. Judged on the
    instances with at least ``min_points`` valid pixels, the depth is too large when the median
    ratio exceeds 3, too small when even the largest is below 1/20, or below 1/3 with the masked
    depth nearer than :data:`NEAR_DEPTH` (:data:`EXTENT_RATIO_RANGE` says why).

    Args:
        depth: depth ``(H, W)``, metres; 0 or NaN where missing.
        K: intrinsics ``(3, 3)`` (tensor, array or nested lists; checked elsewhere).
        masks: instance masks ``(B, H, W)`` bool.
        diameters: the diameter of each instance's object ``(B,)``, metres.
        min_points: an instance with fewer valid depth pixels is not judged.
        where: what the depth is (a file, a scene and image), for the message.
        scale_name: the option or argument that sets the depth's scale (``--depth-scale``,
            ``depth_scale=``), for the message; None: the message asks for depth in metres.
        scale: the scale that was applied (the message suggests a corrected one).
        api_name: the Python argument that sets the scale too, when ``scale_name`` is an option.

    Returns:
        The ratio of extent to diameter of each instance ``(B,)`` float64, NaN where not judged.

    Raises:
        ShapeError: masks and depth of different sizes, or not one diameter per mask.
        UnitsError: the extents disagree with the diameters beyond :data:`EXTENT_RATIO_RANGE`;
            the message gives the likely factor and the scale that fixes it.

    Example:
        >>> K = torch.tensor([[500.0, 0, 32], [0, 500, 32], [0, 0, 1]])
        >>> masks = torch.zeros(1, 64, 64, dtype=torch.bool); masks[0, 20:44, 20:44] = True
        >>> depth = torch.full((64, 64), 2.0)  # 24 px at 2 m: about 0.1 m across
        >>> round(float(check_depth_extent(depth, K, masks, [0.12])[0]), 1)
        0.9
        >>> try:
        ...     check_depth_extent(10 * depth, K, masks, [0.12], scale_name="--depth-scale",
        ...                        scale=0.001)
        ... except UnitsError as e:
        ...     print(str(e).split("? ")[-1])
        set --depth-scale 0.0001; it is 0.001
    """
    d = torch.as_tensor(depth)
    if d.dim() != 2 or masks.dim() != 3 or tuple(masks.shape[1:]) != tuple(d.shape):
        raise ShapeError(
            f"{where}: masks {tuple(masks.shape)} must be (B, H, W) of the depth's {tuple(d.shape)}"
        )
    diam = torch.as_tensor(diameters, dtype=torch.float64).reshape(-1).cpu()
    B = masks.shape[0]
    if diam.numel() != B:
        raise ShapeError(f"{where}: {B} masks but {diam.numel()} diameters")
    if B == 0:
        return torch.full((B,), float("nan"), dtype=torch.float64)
    valid = torch.isfinite(d) & (d > 0)
    ratios = _extent_ratios(d, valid, K, masks, diam, min_points)
    judged = ratios[torch.isfinite(ratios)]
    if judged.numel() == 0:
        return ratios
    low, high = EXTENT_RATIO_RANGE
    if float(judged.max()) < 1.0 / high and low <= float(judged.max()):
        inside = masks[torch.isfinite(ratios).to(masks.device)].any(dim=0).to(d.device) & valid
        if float(d[inside].median()) < NEAR_DEPTH:
            low = 1.0 / high
    if float(judged.median()) > high or float(judged.max()) < low:
        raise _extent_error(judged, low, where, scale_name, scale, api_name)
    return ratios


def _extent_ratios(
    d: torch.Tensor,
    valid: torch.Tensor,
    K: Any,
    masks: torch.Tensor,
    diameters: torch.Tensor,
    min_points: int,
) -> torch.Tensor:
    """Extent over diameter ``(B,)`` float64 of each mask's valid depth, NaN where not judged.

    ``d`` ``(H, W)`` is the depth, ``valid`` ``(H, W)`` its finite positive pixels; an instance
    with fewer than ``min_points`` of them, or without a positive diameter, is not judged.
    """
    ratios = torch.full((masks.shape[0],), float("nan"), dtype=torch.float64)
    Kt = torch.as_tensor(_nested_floats(K), dtype=torch.float64).reshape(3, 3)
    fx, fy, cx, cy = (float(Kt[0, 0]), float(Kt[1, 1]), float(Kt[0, 2]), float(Kt[1, 2]))
    for i in range(masks.shape[0]):
        v, u = torch.nonzero(masks[i].to(d.device) & valid, as_tuple=True)
        if v.numel() < min_points or not (math.isfinite(diameters[i]) and diameters[i] > 0):
            continue
        z = d[v, u].double()
        # depth within half a diameter of the median: the background a loose mask takes in
        # (far behind the object) must not count as the object's extent; a depth in the
        # wrong unit still scales the lateral extent by its factor
        middle, half = float(z.median()), float(diameters[i]) / 2
        z = z.clamp(middle - half, middle + half)
        pts = torch.stack([(u.double() - cx) * z / fx, (v.double() - cy) * z / fy, z], dim=1)
        ratios[i] = _extent(pts) / float(diameters[i])
    return ratios


def _extent_error(
    judged: torch.Tensor,
    low: float,
    where: str,
    scale_name: str | None,
    scale: float,
    api_name: str | None,
) -> UnitsError:
    """The error for judged extent ratios ``(n,)`` too large (median) or below ``low`` (max)."""
    n = judged.numel()
    of = "one instance" if n == 1 else f"{n} instances"
    typical, largest = float(judged.median()), float(judged.max())
    if typical > EXTENT_RATIO_RANGE[1]:
        factor = 10.0 ** max(1, round(math.log10(typical)))
        spans = f"{typical:.3g} times" + (" (the median)" if n > 1 else "")
        why = "more than a visible part of an object can (unless the masks are of other objects)"
        size = "large"
    else:
        factor = 10.0 ** min(-1, round(math.log10(largest)))
        spans = f"at most {largest:.3g} times"
        why = "far less than the visible part of an object does"
        size = "small"
    if scale_name is None:
        fix = f"multiply the depth by {1.0 / factor:g} (poseflow takes depth in metres)"
    else:
        fix = _fix(scale_name, scale, scale / factor, api_name)
    return UnitsError(
        f"{where}: the depth inside the masks spans {spans} the objects' diameters ({of}), "
        f"{why}: is the depth {max(factor, 1.0 / factor):g} times too {size}? {fix}"
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
        ValueRangeError: non-finite entries, all zeros, a non-positive focal length, a last row
            other than ``[0, 0, 1]``, or a principal point outside the image (a transposed
            ``K``, or ``K`` of another resolution).

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
    if not bool(t.any()):
        raise ValueRangeError(f"{name} is all zeros")
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
