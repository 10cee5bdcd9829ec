"""Square image crops around clouds, resampled to a fixed size, and their pixel coordinates.

Boxes are ``(x0, y0, x1, y1)`` in continuous image coordinates, where the pixel ``(u, v)``
covers ``[u - 0.5, u + 0.5] x [v - 0.5, v + 0.5]`` (:mod:`poseflow.geometry.projection`).
"""

from __future__ import annotations

import torch

from poseflow._checks import check_mask, check_same, check_tensor
from poseflow.errors import DegenerateInputError, ValueRangeError
from poseflow.geometry.projection import project_points

__all__ = ["crop_box_around", "crop_resize", "crop_to_pixels", "pixels_to_crop"]


def crop_box_around(
    points: torch.Tensor,
    K: torch.Tensor,
    mask: torch.Tensor | None = None,
    *,
    margin: float = 1.1,
    min_size: float = 16.0,
) -> torch.Tensor:
    """The square image crop centred on the projection of each cloud's barycentre.

    This is the target crop of FunFlow6D's appearance encoder. The side is the smallest square
    (centred on the barycentre's projection) containing the projections of all valid points,
    times ``margin``, and at least ``min_size`` pixels. The box may extend beyond the image;
    :func:`crop_resize` fills the outside with zeros.

    Args:
        points: camera-frame clouds ``(B, N, 3)``.
        K: intrinsics ``(B, 3, 3)`` or ``(3, 3)``.
        mask: ``(B, N)`` bool validity; each cloud needs at least one valid point.
        margin: scale factor applied to the tight side length (>= 1 keeps every point inside).
        min_size: smallest side in pixels.

    Returns:
        Boxes ``(B, 4)`` as ``(x0, y0, x1, y1)`` in continuous pixel coordinates (pixel ``u``
        spans ``[u - 0.5, u + 0.5]``), with ``x1 - x0 == y1 - y0``.

    Raises:
        DegenerateInputError: a cloud has no valid point.

    Example:
        >>> K = torch.tensor([[100.0, 0.0, 50.0], [0.0, 100.0, 50.0], [0.0, 0.0, 1.0]])
        >>> pts = torch.tensor([[[-0.1, 0.0, 1.0], [0.1, 0.0, 1.0]]])
        >>> crop_box_around(pts, K, margin=1.0)  # pixels 40 and 60 lie inside
        tensor([[39.5000, 39.5000, 60.5000, 60.5000]])
    """
    sizes = check_tensor(points, "points", ("B", "N", 3))
    B = sizes["B"]
    if mask is None:
        mask = torch.ones(B, sizes["N"], dtype=torch.bool, device=points.device)
    check_mask(mask, "mask", ("B", "N"), sizes)
    if not margin > 0 or not min_size >= 0:
        raise ValueRangeError(f"need margin > 0 and min_size >= 0, got {margin}, {min_size}")
    count = mask.sum(1)
    if bool((count == 0).any()):
        bad = torch.nonzero(count == 0).flatten().tolist()
        raise DegenerateInputError(f"cannot crop around empty clouds (batch items {bad})")
    w = mask.to(points.dtype).unsqueeze(-1)
    centre = (points * w).sum(1) / count.to(points.dtype).unsqueeze(-1)
    c_uv = project_points(centre.unsqueeze(1), K).squeeze(1)
    uv = project_points(points, K, mask)
    reach = (uv - c_uv.unsqueeze(1)).abs().amax(-1).masked_fill(~mask, 0.0).amax(1)
    # +0.5: the box must cover the whole extreme pixels, not only their centres.
    half = torch.clamp((reach + 0.5) * margin, min=min_size / 2)
    return torch.cat([c_uv - half.unsqueeze(-1), c_uv + half.unsqueeze(-1)], dim=-1)


def _box_check(box: torch.Tensor, B: int) -> None:
    check_tensor(box, "box", (B, 4), finite=True)
    if bool(((box[:, 2] <= box[:, 0]) | (box[:, 3] <= box[:, 1])).any()):
        raise ValueRangeError("boxes need x1 > x0 and y1 > y0")


def pixels_to_crop(pixels: torch.Tensor, box: torch.Tensor, size: int) -> torch.Tensor:
    """Map image pixel coordinates to the pixel coordinates of a crop resized to ``size``.

    The crop of ``box`` resampled to ``size x size`` pixels (as :func:`crop_resize` does) has
    pixel ``i`` covering image coordinates ``[x0 + i s, x0 + (i + 1) s]``, ``s = (x1 - x0) / size``.

    Args:
        pixels: image coordinates ``(u, v)``, ``(B, N, 2)`` (integer pixels or float).
        box: crop boxes ``(B, 4)`` from :func:`crop_box_around`.
        size: side of the resized crop in pixels.

    Returns:
        Crop coordinates ``(B, N, 2)`` in the crop's own pixel-centre convention, in the box's
        dtype; round them to index a crop-resolution feature map.

    Example:
        >>> box = torch.tensor([[-0.5, -0.5, 9.5, 9.5]])
        >>> pixels_to_crop(torch.tensor([[[0, 0], [9, 9]]]), box, 5)
        tensor([[[-0.2500, -0.2500],
                 [ 4.2500,  4.2500]]])
    """
    sizes = check_tensor(pixels, "pixels", ("B", "N", 2), floating=False)
    _box_check(box, sizes["B"])
    scale = (box[:, 2:] - box[:, :2]) / size
    return (pixels.to(box.dtype) - box[:, None, :2]) / scale[:, None] - 0.5


def crop_to_pixels(coords: torch.Tensor, box: torch.Tensor, size: int) -> torch.Tensor:
    """Inverse of :func:`pixels_to_crop`: crop pixel coordinates to image coordinates.

    Example:
        >>> box = torch.tensor([[-0.5, -0.5, 9.5, 9.5]])
        >>> crop_to_pixels(torch.tensor([[[-0.25, 4.25]]]), box, 5)
        tensor([[[0., 9.]]])
    """
    sizes = check_tensor(coords, "coords", ("B", "N", 2))
    _box_check(box, sizes["B"])
    scale = (box[:, 2:] - box[:, :2]) / size
    return (coords + 0.5) * scale[:, None] + box[:, None, :2]


def crop_resize(
    images: torch.Tensor, box: torch.Tensor, size: int, *, mode: str = "bilinear"
) -> torch.Tensor:
    """Crop boxes out of images and resample them to ``size x size`` (zeros outside the image).

    Consistent with :func:`pixels_to_crop`: crop pixel ``(i, j)`` samples image point
    ``crop_to_pixels((i, j))``.

    Args:
        images: ``(B, C, H, W)`` floating images.
        box: ``(B, 4)`` boxes ``(x0, y0, x1, y1)``.
        size: output side in pixels.
        mode: ``"bilinear"`` or ``"nearest"`` (``torch.nn.functional.grid_sample`` modes).

    Returns:
        Crops ``(B, C, size, size)``.

    Example:
        >>> img = torch.arange(16.0).reshape(1, 1, 4, 4)
        >>> crop_resize(img, torch.tensor([[1.5, 1.5, 3.5, 3.5]]), 2)
        tensor([[[[10., 11.],
                  [14., 15.]]]])
    """
    sizes = check_tensor(images, "images", ("B", None, "H", "W"))
    _box_check(box, sizes["B"])
    check_same(("images", images), ("box", box))
    if size < 1:
        raise ValueRangeError(f"size must be >= 1, got {size}")
    H, W = sizes["H"], sizes["W"]
    i = torch.arange(size, dtype=box.dtype, device=box.device)
    scale = (box[:, 2:] - box[:, :2]) / size  # (B, 2)
    xs = (i[None] + 0.5) * scale[:, :1] + box[:, :1]  # (B, size) image u of crop columns
    ys = (i[None] + 0.5) * scale[:, 1:] + box[:, 1:2]
    gx = (xs + 0.5) / W * 2 - 1  # grid_sample, align_corners=False: pixel u at (2u + 1) / W - 1
    gy = (ys + 0.5) / H * 2 - 1
    grid = torch.stack(
        [gx[:, None, :].expand(-1, size, -1), gy[:, :, None].expand(-1, -1, size)], dim=-1
    )
    return torch.nn.functional.grid_sample(
        images, grid, mode=mode, padding_mode="zeros", align_corners=False
    )
