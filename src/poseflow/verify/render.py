"""Z-buffered point rendering into square crops, and the matching crops of an observed image.

Shape letters: B instances, H hypotheses per instance, N model points, C colour channels,
S the side of the square crop, Hi x Wi the image.

A crop is a square box ``(x0, y0, x1, y1)`` of the image in continuous pixel coordinates (image
pixel ``u`` covers ``[u - 0.5, u + 0.5]``, the convention of :mod:`poseflow.geometry.pointcloud`),
resampled to ``S x S`` pixels: crop pixel ``i`` covers image coordinates
``[x0 + i s, x0 + (i + 1) s]`` with ``s = (x1 - x0) / S``, exactly as
:func:`~poseflow.geometry.pointcloud.crop_resize`. :func:`crop_intrinsics` gives the pinhole
intrinsics of that grid, so a point projects into the crop with the same formula as into the
image.

:func:`render_points` draws a model's coloured surface points at many poses at once: every point
is moved, culled when it faces away from the camera, projected to its nearest crop pixel and
z-buffered, by one ``scatter_reduce`` over all ``B x H`` renderings on any device, or on the
CPU by a compiled kernel with the same answers (:mod:`poseflow.verify._splat_cpu`).
Each pixel takes the depth of its nearest point and the mean colour of the points on that front
surface. Two fixes make points behave like a surface: a pixel whose depth lies far behind the
nearest depth of its 3 x 3 neighbourhood shows a back surface through a gap between samples and is
dropped, and an empty pixel most of whose 8 neighbours are covered is filled with their mean
(repeated, so that gaps a few pixels wide close).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from poseflow._checks import check_mask, check_same, check_tensor
from poseflow.errors import ShapeError, ValueRangeError

__all__ = [
    "ObservedCrops",
    "PointRendering",
    "box_sum",
    "crop_intrinsics",
    "crop_observation",
    "render_points",
]


@dataclass
class PointRendering:
    """Renderings of ``B x H`` hypotheses on ``S x S`` crops.

    Attributes:
        depth: z-depth in metres ``(B, H, S, S)``, 0 where nothing was drawn.
        mask: ``(B, H, S, S)`` bool, True where the object was drawn.
        color: mean colour of the front surface ``(B, H, C, S, S)``, 0 where nothing was drawn.
    """

    depth: torch.Tensor
    mask: torch.Tensor
    color: torch.Tensor


@dataclass
class ObservedCrops:
    """The observation resampled to the crops of :func:`crop_observation`.

    Attributes:
        depth: metres ``(B, S, S)``, 0 where missing or outside the image.
        mask: the instance masks ``(B, S, S)`` bool.
        color: colour ``(B, 3, S, S)`` (area-averaged), or None when no image was given.
    """

    depth: torch.Tensor
    mask: torch.Tensor
    color: torch.Tensor | None


def crop_intrinsics(K: torch.Tensor, boxes: torch.Tensor, size: int) -> torch.Tensor:
    """Pinhole intrinsics of square crops resampled to ``size x size`` pixels.

    A point that projects to image coordinates ``(u, v)`` with ``K`` projects to crop
    coordinates ``((u - x0) / s - 0.5, (v - y0) / s - 0.5)`` with the result, ``s`` the crop's
    pixel size in image pixels: the mapping of
    :func:`~poseflow.geometry.pointcloud.pixels_to_crop`.

    Args:
        K: intrinsics ``(B, 3, 3)`` or ``(3, 3)``.
        boxes: square boxes ``(B, 4)`` as ``(x0, y0, x1, y1)``, ``x1 - x0 == y1 - y0 > 0``.
        size: side ``S`` of the crop in pixels.

    Returns:
        Intrinsics ``(B, 3, 3)`` in the boxes' dtype.

    Raises:
        ShapeError: wrong shapes or devices.
        ValueRangeError: an empty box or ``size < 1``.

    Example:
        >>> K = torch.tensor([[100.0, 0.0, 50.0], [0.0, 100.0, 40.0], [0.0, 0.0, 1.0]])
        >>> crop_intrinsics(K, torch.tensor([[9.5, 9.5, 29.5, 29.5]]), 10)[0]
        tensor([[50.0000,  0.0000, 19.7500],
                [ 0.0000, 50.0000, 14.7500],
                [ 0.0000,  0.0000,  1.0000]])
    """
    sizes = check_tensor(boxes, "boxes", ("B", 4), finite=True)
    B = sizes["B"]
    Kb = K.unsqueeze(0).expand(B, 3, 3) if K.dim() == 2 else K
    check_tensor(Kb, "K", ("B", 3, 3), finite=True, sizes=sizes)
    check_same(("boxes", boxes), ("K", Kb), dtype=False)
    if isinstance(size, bool) or not isinstance(size, int) or size < 1:
        raise ValueRangeError(f"size must be an int >= 1, got {size!r}")
    side = boxes[:, 2] - boxes[:, 0]
    if bool((side <= 0).any()) or bool(((boxes[:, 3] - boxes[:, 1]) <= 0).any()):
        raise ValueRangeError("crop boxes must have positive sides")
    s = (side / size)[:, None]
    out = Kb.to(boxes.dtype).clone()
    out[:, :2, :3] = Kb[:, :2, :3].to(boxes.dtype) / s[:, :, None]
    out[:, 0, 2] = (Kb[:, 0, 2].to(boxes.dtype) - boxes[:, 0]) / s[:, 0] - 0.5
    out[:, 1, 2] = (Kb[:, 1, 2].to(boxes.dtype) - boxes[:, 1]) / s[:, 0] - 0.5
    return out


def render_points(
    points: torch.Tensor,
    normals: torch.Tensor,
    colors: torch.Tensor,
    poses: torch.Tensor,
    K: torch.Tensor,
    size: int,
    *,
    point_mask: torch.Tensor | None = None,
    surface_tolerance: torch.Tensor | float,
    occlusion_tolerance: torch.Tensor | float,
    fill_passes: int = 3,
) -> PointRendering:
    """Z-buffer a batch of coloured point clouds into square crops at ``H`` poses each.

    Args:
        points: surface points in the model frame ``(B, N, 3)``.
        normals: outward unit normals at ``points`` ``(B, N, 3)``; points whose normal faces away
            from the camera are not drawn.
        colors: colour (or any per-point value) of ``points`` ``(B, N, C)``.
        poses: model-to-camera transforms ``(B, H, 4, 4)``.
        K: intrinsics of the crops ``(B, 3, 3)`` (see :func:`crop_intrinsics`).
        size: side ``S`` of the crops in pixels.
        point_mask: ``(B, N)`` bool, True for real points (clouds of different sizes are padded).
        surface_tolerance: points within this depth (metres) of a pixel's nearest point are on
            its front surface and averaged into its colour; a float or ``(B,)``.
        occlusion_tolerance: a pixel deeper than the nearest depth of its 3 x 3 neighbourhood by
            more than this (metres) is dropped as a back surface seen through a gap; a float or
            ``(B,)``.
        fill_passes: rounds of filling empty pixels most of whose neighbours are drawn; each
            round closes gaps one pixel wider (thin-walled objects, whose samples are shared by
            an inner and an outer surface, leave gaps up to about 3 pixels wide).

    Returns:
        A :class:`PointRendering` in the dtype of ``points``.

    Raises:
        ShapeError: wrong shapes, dtypes or devices.
        ValueRangeError: NaN or inf in the inputs, ``size < 1``.

    Example:
        >>> pts = torch.tensor([[[0.0, 0.0, 0.0], [0.0, 0.0, 0.1]]])
        >>> nrm = torch.tensor([[[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]]])
        >>> col = torch.tensor([[[1.0], [0.5]]])
        >>> pose = torch.eye(4).expand(1, 1, 4, 4).clone(); pose[..., 2, 3] = 1.0
        >>> K = torch.tensor([[[10.0, 0.0, 1.0], [0.0, 10.0, 1.0], [0.0, 0.0, 1.0]]])
        >>> out = render_points(pts, nrm, col, pose, K, 3, surface_tolerance=0.01,
        ...                     occlusion_tolerance=0.05)
        >>> out.depth[0, 0, 1, 1].item(), out.color[0, 0, 0, 1, 1].item(), int(out.mask.sum())
        (1.0, 1.0, 1)
    """
    sizes = check_tensor(points, "points", ("B", "N", 3), finite=True)
    check_tensor(normals, "normals", ("B", "N", 3), finite=True, sizes=sizes)
    check_tensor(colors, "colors", ("B", "N", "C"), finite=True, sizes=sizes)
    check_tensor(poses, "poses", ("B", "H", 4, 4), finite=True, sizes=sizes)
    check_tensor(K, "K", ("B", 3, 3), finite=True, sizes=sizes)
    check_same(("points", points), ("normals", normals), ("colors", colors), ("poses", poses))
    check_same(("points", points), ("K", K))
    if point_mask is not None:
        check_mask(point_mask, "point_mask", ("B", "N"), sizes)
        check_same(("points", points), ("point_mask", point_mask), dtype=False)
    if isinstance(size, bool) or not isinstance(size, int) or size < 1:
        raise ValueRangeError(f"size must be an int >= 1, got {size!r}")
    if isinstance(fill_passes, bool) or not isinstance(fill_passes, int) or fill_passes < 0:
        raise ValueRangeError(f"fill_passes must be an int >= 0, got {fill_passes!r}")
    B, H, S = sizes["B"], sizes["H"], size
    surface = _per_instance(surface_tolerance, B, points, "surface_tolerance")
    occlusion = _per_instance(occlusion_tolerance, B, points, "occlusion_tolerance")
    R, t = poses[..., :3, :3], poses[..., :3, 3]
    # the compiled CPU kernels give the tensor versions' answers, bit for bit, faster
    compiled = runs_compiled(points)
    splat = _splat_compiled if compiled else _splat_tensors
    close_gaps = _close_gaps_compiled if compiled else _close_gaps_tensors
    zbuf, csum, ccount = splat(points, normals, colors, R, t, K, S, point_mask, surface)
    return close_gaps(zbuf, csum, ccount, occlusion, H, S, fill_passes)


def _splat_tensors(
    points: torch.Tensor,
    normals: torch.Tensor,
    colors: torch.Tensor,
    R: torch.Tensor,
    t: torch.Tensor,
    K: torch.Tensor,
    S: int,
    point_mask: torch.Tensor | None,
    surface: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Project the points into the crops: the z-buffer and each pixel's front surface.

    Tensor operations (any device), one scatter over all renderings.

    Returns:
        The z-buffer ``(B H S S,)`` (inf where empty), and the colour sums ``(B H S S, C)`` and
        counts ``(B H S S,)`` of the points within ``surface`` of each pixel's nearest.
    """
    (B, N, C), H = colors.shape, R.shape[1]
    dtype, device = points.dtype, points.device
    cam, keep, u, v = _camera(points, normals, R, t, K)
    z = cam[..., 2]
    if point_mask is not None:
        keep &= point_mask[:, None]
    keep &= (u >= 0) & (u < S) & (v >= 0) & (v < S)
    bh, n = keep.reshape(B * H, N).nonzero(as_tuple=True)
    zk = z.reshape(B * H, N)[bh, n]
    pix = bh * (S * S) + v.reshape(B * H, N)[bh, n].long() * S + u.reshape(B * H, N)[bh, n].long()
    zbuf = torch.full((B * H * S * S,), math.inf, dtype=dtype, device=device)
    zbuf = zbuf.scatter_reduce(0, pix, zk, reduce="amin", include_self=True)
    b_of = torch.div(bh, H, rounding_mode="floor")
    front = zk <= zbuf[pix] + surface[b_of]
    col = colors[b_of[front], n[front]]  # (P, C)
    csum = torch.zeros(B * H * S * S, C, dtype=dtype, device=device)
    csum.index_add_(0, pix[front], col)
    ccount = torch.zeros(B * H * S * S, dtype=dtype, device=device)
    ccount.index_add_(0, pix[front], torch.ones_like(zk[front]))
    return zbuf, csum, ccount


def runs_compiled(x: torch.Tensor) -> bool:
    """Whether the compiled CPU kernels take ``x``: a CPU tensor of float32 or float64."""
    return x.device.type == "cpu" and x.dtype in (torch.float32, torch.float64)


def numpy_scalar(value: float, dtype: torch.dtype) -> np.generic:
    """``value`` as a numpy scalar of ``dtype``, the type a compiled kernel computes in.

    Example:
        >>> numpy_scalar(0.1, torch.float32).dtype
        dtype('float32')
    """
    return np.dtype(str(dtype).removeprefix("torch.")).type(value)


#: Points nearer to the camera than this (metres) are not drawn.
_NEAREST_DEPTH = 1e-6


def _camera(
    points: torch.Tensor, normals: torch.Tensor, R: torch.Tensor, t: torch.Tensor, K: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Points in the camera ``(B, H, N, 3)``, whether they face it in front of it, their pixels.

    Every product and sum is written out in the order the compiled kernel
    (:mod:`poseflow.verify._splat_cpu`) evaluates it, so that both give the same pixels.
    """

    def turned(vectors: torch.Tensor) -> torch.Tensor:  # R v, (B, H, N, 3)
        x, y, z = (vectors[:, None, :, i, None] for i in range(3))
        return x * R[:, :, None, :, 0] + y * R[:, :, None, :, 1] + z * R[:, :, None, :, 2]

    cam = turned(points) + t[:, :, None]
    m = turned(normals)
    x, y, z = cam.unbind(-1)
    shown = (m[..., 0] * x + m[..., 1] * y + m[..., 2] * z < 0) & (z > _NEAREST_DEPTH)
    k = K[:, None, None]
    zs = torch.where(shown, z, torch.ones_like(z))
    u = torch.round((x * k[..., 0, 0] + y * k[..., 0, 1] + z * k[..., 0, 2]) / zs)
    v = torch.round((x * k[..., 1, 0] + y * k[..., 1, 1] + z * k[..., 1, 2]) / zs)
    return cam, shown, u, v


def _splat_compiled(
    points: torch.Tensor,
    normals: torch.Tensor,
    colors: torch.Tensor,
    R: torch.Tensor,
    t: torch.Tensor,
    K: torch.Tensor,
    S: int,
    point_mask: torch.Tensor | None,
    surface: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`_splat_tensors`'s buffers by the compiled CPU kernel (float32 or float64)."""
    from poseflow.verify._splat_cpu import splat_kernel

    (B, N, C), H = colors.shape, R.shape[1]
    dtype = points.dtype
    if point_mask is None:
        point_mask = torch.ones(B, N, dtype=torch.bool)
    zbuf = torch.full((B * H * S * S,), math.inf, dtype=dtype)
    csum = torch.zeros(B * H * S * S, C, dtype=dtype)
    ccount = torch.zeros(B * H * S * S, dtype=dtype)
    arrays = (points, normals, colors, R, t, K, point_mask, surface)
    near = numpy_scalar(_NEAREST_DEPTH, dtype)
    splat_kernel(
        *(a.detach().contiguous().numpy() for a in arrays), near, S,
        zbuf.numpy(), csum.numpy(), ccount.numpy(),
    )  # fmt: skip
    return zbuf, csum, ccount


def _close_gaps_compiled(
    zbuf: torch.Tensor,
    csum: torch.Tensor,
    ccount: torch.Tensor,
    occlusion: torch.Tensor,
    H: int,
    S: int,
    fill_passes: int,
) -> PointRendering:
    """:func:`_close_gaps_tensors` by the compiled CPU kernel (float32 or float64)."""
    from poseflow.verify._splat_cpu import close_gaps_kernel

    B, C, dtype = occlusion.shape[0], csum.shape[1], zbuf.dtype
    depth = torch.zeros(B * H, S, S, dtype=dtype)
    color = torch.zeros(B * H, C, S, S, dtype=dtype)
    drawn = torch.zeros(B * H, S, S, dtype=torch.bool)
    close_gaps_kernel(
        zbuf.reshape(B * H, S, S).numpy(), csum.reshape(B * H, S, S, C).numpy(),
        ccount.reshape(B * H, S, S).numpy(), occlusion.repeat_interleave(H).contiguous().numpy(),
        fill_passes, depth.numpy(), color.numpy(), drawn.numpy(),
    )  # fmt: skip
    return PointRendering(
        depth=depth.reshape(B, H, S, S),
        mask=drawn.reshape(B, H, S, S),
        color=color.reshape(B, H, C, S, S),
    )


def _close_gaps_tensors(
    zbuf: torch.Tensor,
    csum: torch.Tensor,
    ccount: torch.Tensor,
    occlusion: torch.Tensor,
    H: int,
    S: int,
    fill_passes: int,
) -> PointRendering:
    """The rendering of the splat's buffers ``(B H S S, ...)``, its gaps closed (any device).

    Back surfaces seen through gaps between samples are dropped, and the pixels that fell between
    samples filled.
    """
    B, C, dtype = occlusion.shape[0], csum.shape[1], zbuf.dtype
    zimg = zbuf.reshape(B * H, 1, S, S)
    drawn = torch.isfinite(zimg)
    # Back surfaces seen through gaps between samples: far behind a neighbour's nearest depth.
    near = -F.max_pool2d(-zimg, 3, stride=1, padding=1)
    occl = occlusion.repeat_interleave(H)[:, None, None, None]
    drawn &= zimg <= near + occl
    color = (csum / ccount.clamp_min(1)[:, None]).reshape(B * H, S, S, C).permute(0, 3, 1, 2)
    depth = torch.where(drawn, zimg, torch.zeros_like(zimg))
    color = torch.where(drawn, color, torch.zeros_like(color))
    # Fill pixels that fell between samples: empty, with at least 5 of their 8 neighbours drawn.
    stacked = torch.cat((depth, color), dim=1)
    for _ in range(fill_passes):
        w = drawn.to(dtype)
        count = box_sum(w, 3) - w
        hole = ~drawn & (count >= 5)
        sums = box_sum(stacked, 3)
        stacked = torch.where(hole, sums / count.clamp_min(1), stacked)
        drawn = drawn | hole
    return PointRendering(
        depth=stacked[:, 0].reshape(B, H, S, S),
        mask=drawn[:, 0].reshape(B, H, S, S),
        color=stacked[:, 1:].reshape(B, H, C, S, S),
    )


def crop_observation(
    depth: torch.Tensor,
    masks: torch.Tensor,
    boxes: torch.Tensor,
    size: int,
    rgb: torch.Tensor | None = None,
    *,
    max_supersampling: int = 4,
) -> ObservedCrops:
    """Resample an observed image to square crops, one per instance.

    Depth and masks take the image pixel nearest to each crop pixel's centre (no mixing of
    missing and valid depth); colour is the mean of ``f x f`` bilinear samples per crop pixel,
    ``f`` the crop's pixel size in image pixels rounded up (at most ``max_supersampling``), so a
    crop that shrinks the image averages it instead of aliasing.

    Args:
        depth: depth in metres ``(Hi, Wi)``, 0 or NaN where missing.
        masks: instance masks ``(B, Hi, Wi)`` bool.
        boxes: square crop boxes ``(B, 4)``, ``(x0, y0, x1, y1)`` in image pixel coordinates.
        size: side ``S`` of the crops.
        rgb: optional colour image ``(3, Hi, Wi)``, float in ``[0, 1]`` or uint8.
        max_supersampling: cap on ``f``.

    Returns:
        :class:`ObservedCrops` in the boxes' dtype; outside the image depth is 0 and masks are
        False.

    Raises:
        ShapeError: wrong shapes or devices.
        ValueRangeError: ``size < 1`` or an empty box.

    Example:
        >>> depth = torch.arange(16.0).reshape(4, 4)
        >>> masks = torch.ones(1, 4, 4, dtype=torch.bool)
        >>> crops = crop_observation(depth, masks, torch.tensor([[1.5, 1.5, 3.5, 3.5]]), 2)
        >>> crops.depth
        tensor([[[10., 11.],
                 [14., 15.]]])
    """
    sizes = check_tensor(depth, "depth", ("Hi", "Wi"))
    check_mask(masks, "masks", ("B", "Hi", "Wi"), sizes)
    check_tensor(boxes, "boxes", ("B", 4), finite=True, sizes=sizes)
    check_same(("boxes", boxes), ("depth", depth), ("masks", masks), dtype=False)
    if isinstance(size, bool) or not isinstance(size, int) or size < 1:
        raise ValueRangeError(f"size must be an int >= 1, got {size!r}")
    if bool(((boxes[:, 2] <= boxes[:, 0]) | (boxes[:, 3] <= boxes[:, 1])).any()):
        raise ValueRangeError("crop boxes must have positive sides")
    Hi, Wi, B, S = sizes["Hi"], sizes["Wi"], sizes["B"], size
    dtype = boxes.dtype
    i = torch.arange(S, dtype=dtype, device=boxes.device)
    step = (boxes[:, 2:] - boxes[:, :2]) / S  # (B, 2)
    us = boxes[:, None, 0] + (i[None] + 0.5) * step[:, None, 0]  # (B, S) image u of columns
    vs = boxes[:, None, 1] + (i[None] + 0.5) * step[:, None, 1]
    ui, vi = torch.floor(us + 0.5).long(), torch.floor(vs + 0.5).long()
    inside = ((vi >= 0) & (vi < Hi))[:, :, None] & ((ui >= 0) & (ui < Wi))[:, None, :]
    rows, cols = vi.clamp(0, Hi - 1)[:, :, None], ui.clamp(0, Wi - 1)[:, None, :]
    d = torch.nan_to_num(depth, nan=0.0, posinf=0.0, neginf=0.0).to(dtype)
    dc = torch.where(inside, d[rows, cols], torch.zeros((), dtype=dtype, device=d.device))
    bidx = torch.arange(B, device=masks.device)[:, None, None]
    mc = inside & masks[bidx, rows, cols]
    color = None
    if rgb is not None:
        check_tensor(rgb, "rgb", (3, "Hi", "Wi"), floating=False, sizes=sizes)
        check_same(("boxes", boxes), ("rgb", rgb), dtype=False)
        color = _crop_color(rgb, boxes, S, max_supersampling)
    return ObservedCrops(depth=dc, mask=mc, color=color)


def _crop_color(
    rgb: torch.Tensor, boxes: torch.Tensor, S: int, max_supersampling: int
) -> torch.Tensor:
    """The colour of :func:`crop_observation`'s crops ``(B, 3, S, S)``, supersampled."""
    (_, Hi, Wi), B, dtype = rgb.shape, boxes.shape[0], boxes.dtype
    step = (boxes[:, 2:] - boxes[:, :2]) / S  # (B, 2)
    img = rgb.to(dtype) / 255.0 if not rgb.is_floating_point() else rgb.to(dtype)
    f = int(min(max_supersampling, max(1, math.ceil(float(step.max())))))
    j = torch.arange(S * f, dtype=dtype, device=boxes.device)
    sub = step / f
    gu = boxes[:, None, 0] + (j[None] + 0.5) * sub[:, None, 0]  # (B, S f)
    gv = boxes[:, None, 1] + (j[None] + 0.5) * sub[:, None, 1]
    gx = (gu + 0.5) / Wi * 2 - 1  # grid_sample, align_corners=False
    gy = (gv + 0.5) / Hi * 2 - 1
    grid = torch.stack(
        (gx[:, None, :].expand(-1, S * f, -1), gy[:, :, None].expand(-1, -1, S * f)), -1
    )
    samples = F.grid_sample(
        img[None], grid.reshape(1, B * S * f, S * f, 2), align_corners=False
    )  # (1, 3, B S f, S f)
    samples = samples.reshape(3, B, S * f, S * f).transpose(0, 1)
    return F.avg_pool2d(samples, f) if f > 1 else samples


def box_sum(images: torch.Tensor, window: int) -> torch.Tensor:
    """Sums over the ``window x window`` neighbourhood of every pixel, zeros outside the image.

    Separable shifted additions: exact, and several times faster on the CPU than ``avg_pool2d``
    or a convolution with a box kernel at the sizes the verifier uses.

    Args:
        images: ``(*, S0, S1)`` images.
        window: odd window side.

    Returns:
        ``(*, S0, S1)`` sums.

    Example:
        >>> box_sum(torch.ones(1, 3, 4), 3)
        tensor([[[4., 6., 6., 4.],
                 [6., 9., 9., 6.],
                 [4., 6., 6., 4.]]])
    """
    if isinstance(window, bool) or not isinstance(window, int) or window < 1 or window % 2 == 0:
        raise ValueRangeError(f"window must be an odd int >= 1, got {window!r}")
    S0, S1 = images.shape[-2:]
    p = window // 2
    padded = F.pad(images, (p, p, p, p))
    rows = padded[..., :, :S1].clone()
    for j in range(1, window):
        rows += padded[..., :, j : j + S1]
    out = rows[..., :S0, :].clone()
    for j in range(1, window):
        out += rows[..., j : j + S0, :]
    return out


def _per_instance(
    value: torch.Tensor | float, B: int, like: torch.Tensor, name: str
) -> torch.Tensor:
    """A float or ``(B,)`` tensor as a ``(B,)`` tensor like ``like``."""
    out = torch.as_tensor(value, dtype=like.dtype, device=like.device)
    if out.dim() == 0:
        out = out.expand(B)
    if out.shape != (B,):
        raise ShapeError(f"{name} must be a float or have shape ({B},), got {tuple(out.shape)}")
    if not bool(torch.isfinite(out).all()) or bool((out < 0).any()):
        raise ValueRangeError(f"{name} must be finite and >= 0")
    return out
