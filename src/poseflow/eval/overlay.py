"""Qualitative pictures: object models rendered in their estimated poses over the input image.

As in the paper's qualitative figure, the input image is turned to grey and every model is drawn
in its *estimated* pose in colour (shaded by its surface orientation, so that its shape reads);
ground-truth poses, when given, are outlined in a second colour on top, so that misalignment shows
as a gap between the coloured surface and the outline.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch.nn import functional as F

from poseflow.errors import ShapeError, ValueRangeError
from poseflow.render.raycast import Renderer

__all__ = ["ESTIMATE_COLOR", "GT_COLOR", "overlay_poses", "write_overlay"]

#: Colour of the models in their estimated poses (azure, as in the paper).
ESTIMATE_COLOR = (30, 144, 255)
#: Colour of the ground-truth outlines.
GT_COLOR = (50, 220, 50)


def _as_image(image: torch.Tensor | np.ndarray) -> torch.Tensor:
    """An ``(H, W, 3)`` uint8 tensor from ``(H, W, 3)``/``(H, W)`` uint8 or ``(3, H, W)`` float."""
    x = torch.as_tensor(np.asarray(image) if not isinstance(image, torch.Tensor) else image)
    x = x.detach().cpu()
    if x.dim() == 3 and x.shape[0] in (1, 3) and x.shape[-1] not in (1, 3):
        x = x.permute(1, 2, 0)  # channels first
    if x.dim() == 2:
        x = x[..., None]
    if x.dim() != 3 or x.shape[-1] not in (1, 3):
        raise ShapeError(f"image must be (H, W, 3), (H, W) or (3, H, W), got {tuple(x.shape)}")
    if x.is_floating_point():
        x = (x.clamp(0, 1) * 255 + 0.5).to(torch.uint8)
    elif x.dtype != torch.uint8:
        raise ShapeError(f"an integer image must be uint8, got {x.dtype}")
    return x.expand(*x.shape[:2], 3) if x.shape[-1] == 1 else x


def _outline(mask: torch.Tensor, width: int) -> torch.Tensor:
    """Pixels of ``mask`` (``(H, W)`` bool) within ``width`` pixels of its border."""
    m = mask[None, None].float()
    eroded = -F.max_pool2d(-m, 2 * width + 1, stride=1, padding=width)
    return mask & ~(eroded[0, 0] > 0.5)


def overlay_poses(
    image: torch.Tensor | np.ndarray,
    K: torch.Tensor | np.ndarray,
    meshes: Sequence[Any],
    poses: torch.Tensor | np.ndarray,
    *,
    object_ids: Sequence[int] | None = None,
    gt_poses: torch.Tensor | np.ndarray | None = None,
    gt_object_ids: Sequence[int] | None = None,
    alpha: float = 0.7,
    color: tuple[int, int, int] = ESTIMATE_COLOR,
    gt_color: tuple[int, int, int] = GT_COLOR,
    outline_width: int = 2,
    renderer: Renderer | None = None,
) -> torch.Tensor:
    """Draw models in estimated poses (filled) and GT poses (outlined) over a grey image.

    Args:
        image: the input image, ``(H, W, 3)`` or ``(H, W)`` uint8, or ``(3, H, W)`` float in
            ``[0, 1]`` (a BOP sample's ``rgb``).
        K: intrinsics ``(3, 3)``.
        meshes: the object meshes in metres (anything :class:`~poseflow.render.Renderer` takes).
        poses: estimated model-to-camera poses ``(n, 4, 4)``.
        object_ids: index into ``meshes`` of each pose (default ``0 .. n-1``).
        gt_poses: ground-truth poses ``(m, 4, 4)``, or None.
        gt_object_ids: index into ``meshes`` of each GT pose (default ``0 .. m-1``).
        alpha: opacity of the rendered models.
        color: RGB of the estimates.
        gt_color: RGB of the ground-truth outlines.
        outline_width: outline thickness in pixels.
        renderer: a :class:`~poseflow.render.Renderer` built on ``meshes``, to reuse across calls.

    Returns:
        The picture, ``(H, W, 3)`` uint8.

    Raises:
        ShapeError: bad image or pose shapes.
        ValueRangeError: ``alpha`` outside ``[0, 1]`` or ``outline_width < 1``.

    Example:
        >>> import open3d as o3d
        >>> box = o3d.geometry.TriangleMesh.create_box(0.1, 0.1, 0.1).translate((-0.05,) * 3)
        >>> K = torch.tensor([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]])
        >>> T = torch.eye(4)[None].clone(); T[0, 2, 3] = 0.5
        >>> pic = overlay_poses(torch.full((48, 64, 3), 200, dtype=torch.uint8), K, [box], T,
        ...                     gt_poses=T)
        >>> pic.shape, pic.dtype, pic[0, 0].tolist()
        (torch.Size([48, 64, 3]), torch.uint8, [200, 200, 200])
    """
    if not 0.0 <= alpha <= 1.0:
        raise ValueRangeError(f"alpha must lie in [0, 1], got {alpha}")
    if outline_width < 1:
        raise ValueRangeError(f"outline_width must be >= 1, got {outline_width}")
    img = _as_image(image).to(torch.float32)
    H, W = img.shape[:2]
    grey = (img @ torch.tensor([0.299, 0.587, 0.114]))[..., None].expand(H, W, 3)
    out = grey.clone()
    ren = renderer if renderer is not None else Renderer(meshes)
    T = torch.as_tensor(poses).reshape(-1, 4, 4)
    if T.shape[0]:
        ids = list(range(T.shape[0])) if object_ids is None else list(object_ids)
        r = ren.render(T, K, W, H, object_ids=ids, rgb=False)
        hit = r.instance >= 0
        # Headlight shading from the camera-facing normals: |n_z| is 1 facing the camera.
        shade = (0.35 + 0.65 * r.normals[..., 2].abs()).clamp(0, 1)[..., None]
        paint = torch.tensor(color, dtype=torch.float32) * shade
        out = torch.where(hit[..., None], (1 - alpha) * grey + alpha * paint, out)
    if gt_poses is not None:
        G = torch.as_tensor(gt_poses).reshape(-1, 4, 4)
        if G.shape[0]:
            gids = list(range(G.shape[0])) if gt_object_ids is None else list(gt_object_ids)
            r = ren.render(G, K, W, H, object_ids=gids, rgb=False)
            edge = torch.zeros(H, W, dtype=torch.bool)
            for m in r.masks_full:
                edge |= _outline(m, outline_width)
            out = torch.where(edge[..., None], torch.tensor(gt_color, dtype=torch.float32), out)
    return out.round().clamp(0, 255).to(torch.uint8)


def write_overlay(path: str | os.PathLike[str], *args: Any, **kwargs: Any) -> torch.Tensor:
    """:func:`overlay_poses`, then write the picture as a PNG at ``path``; returns the picture.

    Example:
        >>> import tempfile, pathlib, open3d as o3d
        >>> from PIL import Image
        >>> box = o3d.geometry.TriangleMesh.create_box(0.1, 0.1, 0.1)
        >>> K = torch.tensor([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]])
        >>> T = torch.eye(4)[None].clone(); T[0, 2, 3] = 0.5
        >>> path = pathlib.Path(tempfile.mkdtemp()) / "overlay.png"
        >>> _ = write_overlay(path, torch.zeros(48, 64, 3, dtype=torch.uint8), K, [box], T)
        >>> Image.open(path).size
        (64, 48)
    """
    from PIL import Image

    pic = overlay_poses(*args, **kwargs)
    Image.fromarray(pic.numpy()).save(path)
    return pic
