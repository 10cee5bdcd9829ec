"""Qualitative pictures that explain themselves: estimated poses outlined over the input image.

The input image is turned to grey and every model is drawn in its *estimated* pose as a coloured
outline of its visible silhouette over a light tint (shaded by the surface orientation, so that
its shape reads, and translucent, so that the object underneath stays visible), one colour per
estimate; an invalid estimate gets a dashed outline and no tint. Ground-truth poses, when given,
are outlined in a second colour just *outside* their silhouettes, so that a good estimate shows
as two touching bands and misalignment as a gap between them. A legend in the corner that hides
the fewest objects names the method and, per estimate, its colour, object, score and validity
(drawn with Pillow, a dependency of poseflow; left out when the picture is too small for it).
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
from torch.nn import functional as F

from poseflow._progress import progress as progress_loop
from poseflow._workers import map_forked
from poseflow.errors import ShapeError, ValueRangeError
from poseflow.render.raycast import Renderer

__all__ = [
    "ESTIMATE_COLOR",
    "ESTIMATE_COLORS",
    "GT_COLOR",
    "as_uint8_image",
    "overlay_poses",
    "write_overlay",
    "write_result_overlays",
]

#: Colour of the first estimate (azure, as in the paper).
ESTIMATE_COLOR = (30, 144, 255)
#: Colours of the estimates, in turn (no green: that is the ground truth's).
ESTIMATE_COLORS: tuple[tuple[int, int, int], ...] = (
    ESTIMATE_COLOR,
    (255, 140, 0),
    (230, 40, 160),
    (255, 220, 0),
    (150, 90, 255),
    (0, 215, 215),
    (220, 30, 30),
    (255, 160, 200),
)
#: Colour of the ground-truth outlines.
GT_COLOR = (50, 220, 50)


def as_uint8_image(image: torch.Tensor | np.ndarray) -> torch.Tensor:
    """An ``(H, W, 3)`` uint8 CPU tensor from ``(H, W, 3)``/``(H, W)`` uint8 or ``(3, H, W)`` float.

    Args:
        image: ``(H, W, 3)``, ``(H, W, 1)`` or ``(H, W)`` uint8, or ``(3, H, W)``/``(1, H, W)``
            float in ``[0, 1]`` (a BOP sample's ``rgb``), tensor or array.

    Returns:
        The image, ``(H, W, 3)`` uint8.

    Raises:
        ShapeError: another shape, or an integer image that is not uint8.

    Example:
        >>> as_uint8_image(torch.ones(3, 2, 4)).shape
        torch.Size([2, 4, 3])
    """
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


def _outline(mask: torch.Tensor, width: int, *, outside: bool = False) -> torch.Tensor:
    """The band of ``width`` pixels along the border of ``mask`` (``(H, W)`` bool).

    Inside the mask by default; ``outside`` puts it just outside.
    """
    m = mask[None, None].float()
    if outside:
        grown = F.max_pool2d(m, 2 * width + 1, stride=1, padding=width)
        return (grown[0, 0] > 0.5) & ~mask
    eroded = -F.max_pool2d(-m, 2 * width + 1, stride=1, padding=width)
    return mask & ~(eroded[0, 0] > 0.5)


def _dashes(H: int, W: int, period: int = 8) -> torch.Tensor:
    """``(H, W)`` bool: diagonal stripes, True on half of each period (dashed outlines)."""
    v, u = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    return ((u + v) // (period // 2)) % 2 == 0


def _font(size: int) -> Any:
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)  # scalable with FreeType (Pillow >= 10.1)
    except (TypeError, ValueError, OSError, ImportError):
        return ImageFont.load_default()


def _draw_legend(
    picture: torch.Tensor,
    entries: Sequence[tuple[tuple[int, int, int] | None, str, bool]],
    covered: torch.Tensor,
) -> torch.Tensor:
    """Draw a legend box (swatch and text per entry) in the least covered corner.

    The box may take half of the picture's height and 60 % of its width: a legend too large is
    drawn in a smaller font (down to 7 px), then its lines are shortened (ending in ``...``) and
    the last ones folded into ``+ N more``; it is never left out.

    Args:
        picture: ``(H, W, 3)`` uint8.
        entries: ``(colour or None for a title line, text, dashed)`` per line.
        covered: ``(H, W)`` bool, pixels the box should avoid (the drawn objects).

    Returns:
        The picture with the legend.
    """
    from PIL import Image, ImageDraw

    H, W = picture.shape[:2]
    if not entries:
        return picture
    probe = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    size = max(10, round(H / 40))
    while True:
        font = _font(size)
        pad, gap, swatch = max(3, size // 3), max(2, size // 4), size
        line = size + gap
        width = _line_width(probe, font, swatch + gap)
        fits = max(width(c, t) for c, t, _ in entries) + 2 * pad <= 0.6 * W
        if (fits and len(entries) * line - gap + 2 * pad <= H // 2) or size <= 7:
            break
        size -= 1
    rows = max(1, (H // 2 - 2 * pad + gap) // line)
    if len(entries) > rows:
        entries = [*entries[: rows - 1], (None, f"+ {len(entries) - rows + 1} more", False)]
    entries = [(c, _shorten(t, lambda t, c=c: width(c, t) + 2 * pad <= 0.6 * W), d)
               for c, t, d in entries]  # fmt: skip
    box_w = min(max(width(c, t) for c, t, _ in entries) + 2 * pad, W)
    box_h = min(len(entries) * line - gap + 2 * pad, H)
    corners = [(pad, pad), (W - box_w - pad, pad), (pad, H - box_h - pad),
               (W - box_w - pad, H - box_h - pad)]  # fmt: skip
    x0, y0 = min(
        corners,
        key=lambda c: int(covered[max(c[1], 0) : c[1] + box_h, max(c[0], 0) : c[0] + box_w].sum()),
    )
    x0, y0 = max(x0, 0), max(y0, 0)
    img = Image.fromarray(picture.numpy()).convert("RGBA")
    layer = Image.new("RGBA", img.size, (0, 0, 0, 0))
    draw = ImageDraw.Draw(layer)
    draw.rectangle([x0, y0, x0 + box_w - 1, y0 + box_h - 1], fill=(0, 0, 0, 170))
    for k, (colour, text, dashed) in enumerate(entries):
        y = y0 + pad + k * line
        x = x0 + pad
        if colour is not None:
            draw.rectangle([x, y, x + swatch - 1, y + swatch - 1], outline=(*colour, 255), width=2)
            if not dashed:
                draw.rectangle([x + 3, y + 3, x + swatch - 4, y + swatch - 4], fill=(*colour, 255))
            x += swatch + gap
        draw.text((x, y), text, fill=(255, 255, 255, 255), font=font)
    out = Image.alpha_composite(img, layer).convert("RGB")
    return torch.from_numpy(np.array(out))


def _line_width(probe: Any, font: Any, swatch: int) -> Any:
    """``width(colour, text)``: pixels of a legend line (its swatch when it has a colour)."""

    def width(colour: Any, text: str) -> int:
        box = probe.textbbox((0, 0), text, font=font)
        return int(box[2] - box[0]) + (swatch if colour is not None else 0)

    return width


def _shorten(text: str, fits: Any) -> str:
    """``text``, or its longest start ending in ``...`` for which ``fits(text)`` holds.

    Example:
        >>> _shorten("FunFlow6D (runs/mine/model)", lambda t: len(t) <= 12)
        'FunFlow6D...'
    """
    if fits(text):
        return text
    for n in range(len(text) - 1, 0, -1):
        if fits(text[:n].rstrip() + "..."):
            return text[:n].rstrip() + "..."
    return "..."


def _per_pose(values: Any, n: int, what: str) -> list[Any] | None:
    if values is None:
        return None
    if isinstance(values, torch.Tensor):
        values = values.detach().cpu()
    out = np.asarray(values).reshape(-1).tolist()
    if len(out) != n:
        raise ShapeError(f"{what} must hold one entry per pose ({n}), got {len(out)}")
    return out


def overlay_poses(
    image: torch.Tensor | np.ndarray,
    K: torch.Tensor | np.ndarray,
    meshes: Sequence[Any],
    poses: torch.Tensor | np.ndarray,
    *,
    object_ids: Sequence[int] | None = None,
    gt_poses: torch.Tensor | np.ndarray | None = None,
    gt_object_ids: Sequence[int] | None = None,
    alpha: float = 0.3,
    color: tuple[int, int, int] | None = None,
    gt_color: tuple[int, int, int] = GT_COLOR,
    outline_width: int = 2,
    renderer: Renderer | None = None,
    method: str | None = None,
    scores: Sequence[float] | torch.Tensor | None = None,
    valid: Sequence[bool] | torch.Tensor | None = None,
    mesh_names: Sequence[str] | None = None,
    legend: bool = True,
    axes: bool = True,
    notes: Sequence[str] = (),
) -> torch.Tensor:
    """Outline models in estimated poses (and GT poses) over a grey image, with a legend.

    Estimates (colours :data:`ESTIMATE_COLORS` in turn) are tinted and outlined inside their
    visible silhouettes, invalid ones dashed and not tinted, each with its model axes (a turn
    that keeps the silhouette shows in them); the ground truth is outlined just outside. The
    legend takes at most half the height and 60 % of the width (smaller font, shortened lines).

    Args:
        image: the image, ``(H, W, 3)`` or ``(H, W)`` uint8, or ``(3, H, W)`` float in ``[0, 1]``.
        K: intrinsics ``(3, 3)``.
        meshes: the object meshes in metres (anything :class:`~poseflow.render.Renderer` takes).
        poses: estimated model-to-camera poses ``(n, 4, 4)``; a non-finite one is listed, not drawn.
        object_ids: index into ``meshes`` of each pose (default ``0 .. n-1``).
        gt_poses: ground-truth poses ``(m, 4, 4)``, or None.
        gt_object_ids: index into ``meshes`` of each GT pose (default ``0 .. m-1``).
        alpha: opacity of the tint of the estimated models (1: solid colour).
        color: one RGB for every estimate; None (default) gives each its own.
        gt_color: RGB of the ground-truth outlines.
        outline_width: outline thickness in pixels.
        renderer: a :class:`~poseflow.render.Renderer` built on ``meshes``, to reuse across calls.
        method: the name of the method, the legend's title.
        scores: the confidence of each pose ``(n,)``, shown in the legend.
        valid: the validity of each pose ``(n,)`` (default: all valid).
        mesh_names: each mesh's name in the legend (default ``mesh 0``, ``mesh 1``, ...).
        legend: draw the legend.
        axes: draw each estimate's model axes.
        notes: more lines at the end of the legend (e.g. the objects a detector did not find).

    Returns:
        The picture, ``(H, W, 3)`` uint8.

    Raises:
        ShapeError: bad image or pose shapes, or ``scores``/``valid`` not one per pose.
        ValueRangeError: ``alpha`` outside ``[0, 1]`` or ``outline_width < 1``.

    Example:
        >>> import open3d as o3d
        >>> box = o3d.geometry.TriangleMesh.create_box(0.1, 0.1, 0.1).translate((-0.05,) * 3)
        >>> K = torch.tensor([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]])
        >>> T = torch.eye(4)[None].clone(); T[0, 2, 3] = 0.5
        >>> pic = overlay_poses(torch.full((48, 64, 3), 200, dtype=torch.uint8), K, [box], T,
        ...                     gt_poses=T, method="FunFlow6D", scores=[0.9])
        >>> pic.shape, pic.dtype, pic[0, 0].tolist()
        (torch.Size([48, 64, 3]), torch.uint8, [200, 200, 200])
    """
    if not 0.0 <= alpha <= 1.0:
        raise ValueRangeError(f"alpha must lie in [0, 1], got {alpha}")
    if outline_width < 1:
        raise ValueRangeError(f"outline_width must be >= 1, got {outline_width}")
    grey = _grey(image)
    H, W = grey.shape[:2]
    ren = renderer if renderer is not None else Renderer(meshes)
    est = _Estimates.of(poses, object_ids, scores, valid, color)
    out, edges, covered_by = _tint_estimates(grey, ren, K, est, alpha, outline_width)
    covered = covered_by.any(dim=0)
    gt = _gt_outline(ren, K, gt_poses, gt_object_ids, outline_width, H, W)
    if gt is not None:
        edges.insert(0, (gt[0], gt_color))
        covered |= gt[1]
    pic = _paint(out, edges)
    if axes:
        pic = _draw_axes(pic, K, est, covered_by)
    if not legend or (est.poses.shape[0] == 0 and gt is None and not notes):
        return pic
    entries = _legend_entries(est, method, mesh_names, None if gt is None else gt_color, axes)
    entries += [(None, note, False) for note in notes]
    return _draw_legend(pic, entries, covered)


def _grey(image: torch.Tensor | np.ndarray) -> torch.Tensor:
    """The image in grey, ``(H, W, 3)`` float32 in ``[0, 255]``."""
    img = as_uint8_image(image).to(torch.float32)
    H, W = img.shape[:2]
    return (img @ torch.tensor([0.299, 0.587, 0.114]))[..., None].expand(H, W, 3)


def _paint(
    picture: torch.Tensor, edges: Sequence[tuple[torch.Tensor, tuple[int, int, int]]]
) -> torch.Tensor:
    """Paint each outline ``(edge (H, W), colour)`` in turn; the picture as ``(H, W, 3)`` uint8."""
    for edge, c in edges:
        picture = torch.where(edge[..., None], torch.tensor(c, dtype=torch.float32), picture)
    return picture.round().clamp(0, 255).to(torch.uint8)


class _Estimates(NamedTuple):
    """The ``n`` estimates of a picture and what the legend says of each."""

    poses: torch.Tensor  # (n, 4, 4), model to camera; not finite: listed, not drawn
    ids: list[int]  # the mesh of each
    colours: list[tuple[int, int, int]]
    valid: list[bool]
    scores: list[float] | None

    @classmethod
    def of(
        cls,
        poses: torch.Tensor | np.ndarray,
        object_ids: Sequence[int] | None,
        scores: Sequence[float] | torch.Tensor | None,
        valid: Sequence[bool] | torch.Tensor | None,
        color: tuple[int, int, int] | None,
    ) -> _Estimates:
        """The estimates of :func:`overlay_poses`'s arguments, checked to be one per pose."""
        T = torch.as_tensor(poses).reshape(-1, 4, 4)
        n = T.shape[0]
        ids = list(range(n)) if object_ids is None else [int(i) for i in object_ids]
        score_list = _per_pose(scores, n, "scores")
        valid_list = [bool(v) for v in _per_pose(valid, n, "valid") or [True] * n]
        colours = [color or ESTIMATE_COLORS[i % len(ESTIMATE_COLORS)] for i in range(n)]
        return cls(T, ids, colours, valid_list, score_list)


def _tint_estimates(
    grey: torch.Tensor, renderer: Renderer, K: Any, est: _Estimates, alpha: float, width: int
) -> tuple[torch.Tensor, list[tuple[torch.Tensor, tuple[int, int, int]]], torch.Tensor]:
    """The estimates drawn on the grey picture ``(H, W, 3)``: tinted surfaces (valid ones only).

    Returns the tinted picture ``(H, W, 3)`` float, the outlines to draw ``[(edge (H, W),
    colour)]`` (dashed for invalid estimates) and the pixels each estimate covers ``(n, H, W)``
    (none for one that is not drawn).
    """
    H, W = grey.shape[:2]
    out = grey.clone()
    covered = torch.zeros(len(est.colours), H, W, dtype=torch.bool)
    edges: list[tuple[torch.Tensor, tuple[int, int, int]]] = []
    drawn = [i for i in range(len(est.colours)) if bool(torch.isfinite(est.poses[i]).all())]
    if not drawn:
        return out, edges, covered
    r = renderer.render(est.poses[drawn], K, W, H, object_ids=[est.ids[i] for i in drawn])
    # Headlight shading from the camera-facing normals: |n_z| is 1 facing the camera. The
    # model's own brightness, relative to its mean over the estimate, modulates the tint, so
    # that a print or label shows where the estimate puts it (a turn keeping the silhouette
    # shows); a model of one colour keeps the estimate's colour.
    shade = (0.35 + 0.65 * r.normals[..., 2].abs()).clamp(0, 1)[..., None]
    own = r.rgb.float() @ torch.tensor([0.299, 0.587, 0.114])  # (H, W) luminance
    dashes = _dashes(H, W)
    for i, visible in zip(drawn, r.masks_visible):
        c = torch.tensor(est.colours[i], dtype=torch.float32)
        covered[i] = visible
        if est.valid[i]:
            mean = own[visible].mean().clamp_min(1.0) if bool(visible.any()) else 1.0
            detail = (own / mean).clamp(0.25, 1.75)[..., None]
            tint = ((1 - alpha) * grey + alpha * c * shade * detail).clamp(0, 255)
            out = torch.where(visible[..., None], tint, out)
            edges.append((_outline(visible, width), est.colours[i]))
        else:
            edges.append((_outline(visible, width) & dashes, est.colours[i]))
    return out, edges, covered


#: Colours of a pose's x, y and z axes (:func:`_draw_axes`).
AXIS_COLORS: tuple[tuple[int, int, int], ...] = ((235, 40, 40), (40, 210, 70), (60, 110, 255))


def _draw_axes(
    picture: torch.Tensor, K: Any, est: _Estimates, covered: torch.Tensor
) -> torch.Tensor:
    """Each drawn estimate's model axes (x red, y green, z blue) from its model origin.

    A silhouette hides a turn that maps the shape onto itself (a box or a can turned by 180°);
    the axes show it. Each axis is as long, in the image, as the root of the estimate's visible
    area (in 3D: that length at the model origin's depth).

    Args:
        picture: ``(H, W, 3)`` uint8.
        K: intrinsics ``(3, 3)``.
        est: the estimates.
        covered: the pixels each estimate covers ``(n, H, W)``.

    Returns:
        The picture with the axes ``(H, W, 3)`` uint8.
    """
    from PIL import Image, ImageDraw

    Kd = torch.as_tensor(K, dtype=torch.float64).reshape(3, 3)
    img = Image.fromarray(picture.numpy())
    draw = ImageDraw.Draw(img)
    width = max(1, round(picture.shape[0] / 200))
    for i in range(len(est.colours)):
        area = int(covered[i].sum())
        T = est.poses[i].to(torch.float64)
        if area == 0 or not bool(torch.isfinite(T).all()) or float(T[2, 3]) <= 0:
            continue
        length = 0.5 * math.sqrt(area) * float(T[2, 3]) / float(Kd[0, 0])  # metres
        ends = (
            T[:3, 3] + length * torch.cat([torch.zeros(1, 3), torch.eye(3)]).double() @ T[:3, :3].T
        )
        if bool((ends[:, 2] <= 0).any()):
            continue
        projected = ends @ Kd.T
        uv = projected[:, :2] / projected[:, 2:]
        for k in (2, 0, 1):  # z first: x and y, in the image plane mostly, stay on top
            draw.line(
                [tuple(uv[0].tolist()), tuple(uv[k + 1].tolist())], fill=AXIS_COLORS[k], width=width
            )
    return torch.from_numpy(np.array(img))


def _gt_outline(
    renderer: Renderer,
    K: Any,
    gt_poses: torch.Tensor | np.ndarray | None,
    gt_object_ids: Sequence[int] | None,
    width: int,
    H: int,
    W: int,
) -> tuple[torch.Tensor, torch.Tensor] | None:
    """The bands just outside the ground-truth silhouettes and the pixels those cover.

    Both ``(H, W)`` bool; None when there is no ground-truth pose.
    """
    if gt_poses is None:
        return None
    G = torch.as_tensor(gt_poses).reshape(-1, 4, 4)
    if not G.shape[0]:
        return None
    gids = list(range(G.shape[0])) if gt_object_ids is None else list(gt_object_ids)
    edge = torch.zeros(H, W, dtype=torch.bool)
    covered = torch.zeros(H, W, dtype=torch.bool)
    for m in renderer.render(G, K, W, H, object_ids=gids, rgb=False).masks_full:
        edge |= _outline(m, width, outside=True)
        covered |= m
    return edge, covered


def _legend_entries(
    est: _Estimates,
    method: str | None,
    mesh_names: Sequence[str] | None,
    gt_color: tuple[int, int, int] | None,
    axes: bool,
) -> list[tuple[tuple[int, int, int] | None, str, bool]]:
    """The legend's lines ``(colour or None, text, dashed)``."""
    entries: list[tuple[tuple[int, int, int] | None, str, bool]] = []
    if method:
        entries.append((None, method, False))
    for i, colour in enumerate(est.colours):
        obj = est.ids[i]
        text = mesh_names[obj] if mesh_names is not None else f"mesh {obj}"
        if est.scores is not None and math.isfinite(est.scores[i]):
            text += f"  score {est.scores[i]:.2f}"
        text += "  valid" if est.valid[i] else "  INVALID"
        entries.append((colour, text, not est.valid[i]))
    if gt_color is not None:
        entries.append((gt_color, "ground truth", False))
    if axes and any(bool(torch.isfinite(T).all()) for T in est.poses):
        entries.append((None, "axes: x red, y green, z blue", False))
    return entries


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


def write_result_overlays(
    folder: str | os.PathLike[str],
    dataset: Any,
    meshes: Mapping[int, Any],
    results: Any,
    *,
    images: Sequence[tuple[int, int]] | None = None,
    method: str | None = None,
    ground_truth: bool = True,
    progress: bool = False,
    workers: int = 1,
) -> list[Path]:
    """One :func:`write_overlay` picture per image of a split.

    Args:
        folder: where ``SSSSSS_IIIIII.png`` (scene and image ids) are written; created.
        dataset: the :class:`~poseflow.data.bop.BOPDataset` split the results are of.
        meshes: ``{obj_id: mesh}`` (Open3D triangle meshes, metres) of every estimated object.
        results: the :class:`~poseflow.eval.results.PoseResults` (one row per valid estimate).
        images: the ``(scene_id, im_id)`` pairs to draw (default: those with an estimate).
        method: the estimator's name, for the legend.
        ground_truth: outline the ground truth too, where the split has it.
        progress: show a progress bar.
        workers: draw the images in this many forked processes of one thread each
            (``poseflow._workers.map_forked``).

    Returns:
        The written files, in scene and image order.
    """
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    ids = sorted(meshes)
    meshes_in_order = [meshes[i] for i in ids]
    renderer = Renderer(meshes_in_order)
    if images is None:
        images = sorted(set(zip(results.scene_ids.tolist(), results.im_ids.tolist())))
    images = list(images)

    def draw(n: int) -> Path:
        scene_id, im_id = images[n]
        scene = dataset.scene(scene_id)
        rows = (results.scene_ids == scene_id) & (results.im_ids == im_id)
        gt: dict[str, Any] = {}
        if ground_truth:
            gts = [g for g in scene.gt_of(im_id) if g.obj_id in meshes]
            if gts:
                gt["gt_poses"] = torch.as_tensor(np.stack([g.pose for g in gts]))
                gt["gt_object_ids"] = [ids.index(g.obj_id) for g in gts]
        path = out / f"{scene_id:06d}_{im_id:06d}.png"
        write_overlay(
            path,
            scene.load_rgb_image(im_id),
            scene.camera[im_id].K,
            meshes_in_order,
            results.poses[rows],
            object_ids=[ids.index(int(o)) for o in results.obj_ids[rows]],
            renderer=renderer,
            method=method,
            scores=results.scores[rows],
            mesh_names=[f"obj {i}" for i in ids],
            **gt,
        )
        return path

    drawn = map_forked(draw, len(images), workers)
    return list(progress_loop(drawn, total=len(images), desc="overlays", enabled=progress))
