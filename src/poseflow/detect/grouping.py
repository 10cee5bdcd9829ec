"""Instances from the detector's dense heads: centre peaks, offset votes and per-pixel classes.

Shape letters: K objects, I instances, h/w head rows/columns, H/W image rows/columns.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

__all__ = ["Instances", "group_instances", "head_to_image"]


@dataclass
class Instances:
    """The instances found in one image, best score first.

    Attributes:
        labels: object index in ``0..K-1`` of each ``(I,)``.
        masks: visible masks at the image's resolution ``(I, H, W)`` bool.
        scores: confidence in ``[0, 1]`` ``(I,)``: the centre's heatmap peak times the mean
            class probability over the mask.
    """

    labels: torch.Tensor
    masks: torch.Tensor
    scores: torch.Tensor

    def __len__(self) -> int:
        return len(self.labels)


def head_to_image(
    x: torch.Tensor, input_size: tuple[int, int], image_size: tuple[int, int]
) -> torch.Tensor:
    """Resample head maps to the image: up to the padded input, crop the padding, resize.

    Args:
        x: maps at the head's resolution ``(C, h, w)``, half the padded input's.
        input_size: ``(rows, columns)`` of the input before padding.
        image_size: ``(H, W)`` of the image.

    Returns:
        ``(C, H, W)``, bilinear with pixel centres aligned (``align_corners=False``).

    Example:
        >>> head_to_image(torch.ones(2, 8, 8), (14, 12), (28, 24)).shape
        torch.Size([2, 28, 24])
    """
    h, w = x.shape[-2:]
    up = F.interpolate(x[None], size=(2 * h, 2 * w), mode="bilinear", align_corners=False)
    up = up[..., : input_size[0], : input_size[1]]
    if tuple(input_size) != tuple(image_size):
        up = F.interpolate(up, size=tuple(image_size), mode="bilinear", align_corners=False)
    return up[0]


def group_instances(
    semantic: torch.Tensor,
    centres: torch.Tensor,
    offsets: torch.Tensor,
    *,
    input_size: tuple[int, int],
    image_size: tuple[int, int],
    centre_threshold: float = 0.1,
    peak_window: int = 5,
    max_instances: int = 32,
    min_pixels: int = 30,
) -> Instances:
    """Group one image's pixels into instances (Panoptic-DeepLab's class-aware grouping).

    Peaks of each object's centre heatmap above ``centre_threshold`` (local maxima in a
    ``peak_window`` square) are the instances; every pixel whose class is an object votes for a
    centre (its position plus its offset) and joins the nearest peak of its own class. The masks
    are the pixels of each instance whose class at the image's resolution (the semantic logits
    resampled) is the instance's object.

    Args:
        semantic: logits of background and the objects ``(K + 1, h, w)``.
        centres: logits of the objects' centre heatmaps ``(K, h, w)``.
        offsets: from each pixel to its centre in head pixels, ``(x, y)`` ``(2, h, w)``.
        input_size: the network input's ``(rows, columns)`` before padding.
        image_size: ``(H, W)`` of the masks returned.
        centre_threshold: lowest heatmap peak that makes an instance.
        peak_window: side of the square in which a peak must be the maximum (odd).
        max_instances: most peaks kept (the highest).
        min_pixels: fewest mask pixels an instance keeps.

    Returns:
        :class:`Instances`, best score first.

    Example:
        >>> sem = torch.full((2, 8, 8), -5.0)
        >>> sem[0] = 5.0
        >>> sem[:, 2:5, 2:5] = torch.tensor([-5.0, 5.0])[:, None, None]
        >>> cen = torch.full((1, 8, 8), -9.0)
        >>> cen[0, 3, 3] = 3.0
        >>> found = group_instances(
        ...     sem, cen, torch.zeros(2, 8, 8), input_size=(16, 16), image_size=(16, 16),
        ...     min_pixels=1,
        ... )
        >>> len(found), found.labels.tolist(), int(found.masks[0].sum()) > 0
        (1, [0], True)
    """
    h, w = centres.shape[-2:]
    heat = centres.float().sigmoid()
    pooled = F.max_pool2d(heat[None], peak_window, stride=1, padding=peak_window // 2)[0]
    is_peak = (heat == pooled) & (heat > centre_threshold)
    values = heat[is_peak]
    where = is_peak.nonzero()  # (I, 3): object, row, column
    order = values.argsort(descending=True)[:max_instances]
    values, where = values[order], where[order]
    empty = Instances(
        torch.zeros(0, dtype=torch.long),
        torch.zeros(0, *image_size, dtype=torch.bool),
        torch.zeros(0),
    )
    if len(values) == 0:
        return empty
    labels = where[:, 0]
    peak_xy = where[:, [2, 1]].float()
    probs = semantic.float().softmax(dim=0)
    pixel_class = probs.argmax(dim=0).flatten() - 1  # -1: background
    ys, xs = torch.meshgrid(
        torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij"
    )
    votes = torch.stack([xs, ys], dim=-1).reshape(-1, 2) + offsets.float().reshape(2, -1).T
    distance = torch.cdist(votes, peak_xy)  # (h*w, I)
    distance = distance.masked_fill(pixel_class[:, None] != labels[None], float("inf"))
    nearest = distance.argmin(dim=1)
    assigned = torch.isfinite(distance.gather(1, nearest[:, None])[:, 0])
    owner = torch.where(assigned, nearest, torch.full_like(nearest, -1)).reshape(h, w)
    member = owner[None] == torch.arange(len(labels))[:, None, None]  # (I, h, w)
    class_prob = probs[labels + 1]  # (I, h, w)
    counts = member.flatten(1).sum(1)
    mean_prob = (class_prob * member).flatten(1).sum(1) / counts.clamp_min(1)
    image_class = head_to_image(semantic.float(), input_size, image_size).argmax(dim=0) - 1
    masks = head_to_image(member.float(), input_size, image_size) > 0.5
    masks &= image_class[None] == labels[:, None, None]
    scores = values * mean_prob
    keep = masks.flatten(1).sum(1) >= min_pixels
    if not bool(keep.any()):
        return empty
    order = scores[keep].argsort(descending=True)
    return Instances(labels[keep][order], masks[keep][order], scores[keep][order])
