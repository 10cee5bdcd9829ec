"""Training the detector on renders of the user's objects (the recipe's synth images).

:func:`detector_images` reads a BOP split with visible masks into memory at the detector's input
scale; each step (:func:`training_batch`) cuts random square crops at a random zoom (depth scaled
with it, as if the camera moved), jitters colour and depth, and builds the heads' targets from the
crops' instances: the class of every pixel (objects the detector does not know, the distractors,
are background), a Gaussian at each instance's centre (the mean of its visible pixels) in its
object's heatmap, and each pixel's offset to that centre. :func:`detector_loss` is cross-entropy
plus soft Dice on the class logits (resampled to the input's resolution, so that mask edges are
learned finer than the heads' grid), CenterNet's focal loss on the heatmaps and L1 on the offsets.

Run ``poseflow train-detector TRAIN_DATASET --out DIR`` (or :func:`train_detector`).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F

from poseflow._progress import progress as progress_loop
from poseflow.detect.detector import Detector, DetectorConfig
from poseflow.detect.network import detector_inputs, resample_to_focal
from poseflow.errors import DegenerateInputError, ValueRangeError

__all__ = [
    "DetectorImages",
    "DetectorTargets",
    "detector_images",
    "detector_loss",
    "detector_targets",
    "train_detector",
    "training_batch",
]

_LOG = logging.getLogger("poseflow")


@dataclass
class DetectorImages:
    """A split's images at the detector's input scale, padded to one size.

    Attributes:
        rgb: colour ``(N, 3, H, W)`` uint8.
        depth: metres, 0 where missing ``(N, H, W)`` float16.
        instances: instance index + 1 of every pixel, 0 for none ``(N, H, W)`` uint8.
        labels: object index (``0..K-1``) of each image's instances, -1 for objects the detector
            does not know ``(N, L)`` int64 (-1 beyond the image's count).
        obj_ids: the object ids of the indices.
    """

    rgb: torch.Tensor
    depth: torch.Tensor
    instances: torch.Tensor
    labels: torch.Tensor
    obj_ids: list[int]

    def __len__(self) -> int:
        return len(self.rgb)


def detector_images(
    root: str | Path,
    split: str = "train",
    *,
    obj_ids: list[int] | None = None,
    input_focal: float = 290.0,
    max_images: int | None = None,
    progress: bool = True,
) -> DetectorImages:
    """Read a BOP split's colour, depth and visible masks at the detector's scale.

    Args:
        root: the BOP dataset folder (the recipe's synth images).
        split: its split.
        obj_ids: the objects to detect (default: every object of ``models_info.json``).
        input_focal: the focal length in pixels the images are resampled to.
        max_images: read at most this many images (default: all).
        progress: show progress.

    Raises:
        DegenerateInputError: the split holds no instance of the objects.
        ValueRangeError: ``max_images`` below 1.
    """
    from poseflow.data.bop import BOPDataset

    if max_images is not None and max_images < 1:
        raise ValueRangeError(f"max_images must be at least 1, got {max_images}")
    ds = BOPDataset(root, split)
    ids = sorted(obj_ids if obj_ids is not None else ds.models_info())
    index = {o: i for i, o in enumerate(ids)}
    images = [(s, i) for s in ds.scene_ids for i in ds.scene(s).im_ids][:max_images]
    rgbs, depths, maps, labels = [], [], [], []
    for s, im in progress_loop(images, total=len(images), desc="detector images", enabled=progress):
        scene = ds.scene(s)
        fy = float(scene.camera[im].K[1][1])
        depth = torch.nan_to_num(scene.load_depth_image(im).float())
        rgb = scene.load_rgb_image(im).float()
        idmap = torch.zeros(depth.shape, dtype=torch.uint8)
        inst_labels = []
        for k, gt in enumerate(scene.gt_of(im)):
            mask = scene.load_mask(im, k, visible=True).bool()
            idmap[mask] = len(inst_labels) + 1
            inst_labels.append(index.get(gt.obj_id, -1))
        rgb_s, depth_s, idmap_s = resample_to_focal(rgb, depth, fy, input_focal, idmap)
        rgbs.append((rgb_s * 255).round().clamp(0, 255).to(torch.uint8))
        depths.append(depth_s.half())
        maps.append(idmap_s)
        labels.append(inst_labels)
    if not any(lab >= 0 for row in labels for lab in row):
        raise DegenerateInputError(f"{root}/{split}: no visible instance of objects {ids}")
    h = max(r.shape[-2] for r in rgbs)
    w = max(r.shape[-1] for r in rgbs)

    def pad(x: torch.Tensor) -> torch.Tensor:
        return F.pad(x, (0, w - x.shape[-1], 0, h - x.shape[-2]))

    width = max(len(row) for row in labels)
    table = torch.full((len(labels), max(width, 1)), -1, dtype=torch.long)
    for n, row in enumerate(labels):
        table[n, : len(row)] = torch.tensor(row, dtype=torch.long)
    return DetectorImages(
        torch.stack([pad(r) for r in rgbs]),
        torch.stack([pad(d) for d in depths]),
        torch.stack([pad(m) for m in maps]),
        table,
        ids,
    )


@dataclass
class DetectorTargets:
    """One batch's targets.

    Attributes:
        classes: class of every input pixel, 0 background, k + 1 object k ``(B, C, C)``.
        heatmaps: centre heatmaps at the heads' resolution ``(B, K, C/2, C/2)``.
        offsets: offset of every head pixel to its instance's centre ``(B, 2, C/2, C/2)``.
        offset_mask: head pixels of known objects ``(B, C/2, C/2)`` bool.
    """

    classes: torch.Tensor
    heatmaps: torch.Tensor
    offsets: torch.Tensor
    offset_mask: torch.Tensor


def training_batch(
    data: DetectorImages,
    batch_size: int,
    crop: int,
    generator: torch.Generator,
    *,
    zoom: tuple[float, float] = (0.7, 1.4),
    input_focal: float = 290.0,
) -> tuple[torch.Tensor, DetectorTargets]:
    """Random zoomed crops of random images with their targets.

    Returns:
        The network input ``(B, 7, C, C)`` and :class:`DetectorTargets`.
    """
    n, _, h, w = data.rgb.shape
    pick = torch.randint(n, (batch_size,), generator=generator)
    a = torch.empty(batch_size).uniform_(math.log(zoom[0]), math.log(zoom[1]), generator=generator)
    a = a.exp()
    span_x, span_y = crop / a / w, crop / a / h  # crop sides in normalised [0, 1] units
    x0 = torch.rand(batch_size, generator=generator) * (1 - span_x).clamp_min(0)
    y0 = torch.rand(batch_size, generator=generator) * (1 - span_y).clamp_min(0)
    x0 -= (span_x - 1).clamp_min(0) / 2
    y0 -= (span_y - 1).clamp_min(0) / 2
    t = (torch.arange(crop) + 0.5) / crop
    gx = (x0[:, None] + t[None] * span_x[:, None]) * 2 - 1  # (B, C) in grid_sample units
    gy = (y0[:, None] + t[None] * span_y[:, None]) * 2 - 1
    grid = torch.stack(torch.broadcast_tensors(gx[:, None, :], gy[:, :, None]), dim=-1)
    rgb = F.grid_sample(data.rgb[pick].float() / 255, grid, align_corners=False)
    near = F.grid_sample(
        torch.cat([data.depth[pick, None].float(), data.instances[pick, None].float()], 1),
        grid,
        mode="nearest",
        align_corners=False,
    )
    depth = near[:, 0] / a[:, None, None]
    inst = near[:, 1].round().long()
    rgb, depth, inst, labels = _paste(rgb, depth, inst, data.labels[pick], generator)
    rgb, depth = _jitter(rgb, depth, generator)
    x = detector_inputs(rgb, depth, torch.full((batch_size,), input_focal))
    return x, detector_targets(inst, labels, len(data.obj_ids))


def _paste(
    rgb: torch.Tensor,
    depth: torch.Tensor,
    inst: torch.Tensor,
    labels: torch.Tensor,
    g: torch.Generator,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Paste a box of another crop in front of half the crops (copy-paste occlusion).

    The box keeps its colour, its instances (with their labels) and its depth's relief, brought
    5-30 cm nearer than this crop's median depth; what it covers is no longer visible.

    Returns:
        Colour, depth, instance maps and the label table ``(B, 2L)`` of both crops' instances.
    """
    b, _, h, w = rgb.shape
    donor = torch.roll(torch.arange(b), 1)
    sides = torch.empty(b, 2).uniform_(0.15, 0.45, generator=g) * torch.tensor([h, w])
    corner = torch.rand(b, 2, generator=g) * (torch.tensor([h, w]) - sides)
    ys, xs = torch.arange(h)[None, :, None], torch.arange(w)[None, None, :]
    y0, x0 = corner[:, 0, None, None], corner[:, 1, None, None]
    y1, x1 = y0 + sides[:, 0, None, None], x0 + sides[:, 1, None, None]
    box = (ys >= y0) & (ys < y1) & (xs >= x0) & (xs < x1)
    box &= (torch.rand(b, generator=g) < 0.5)[:, None, None]
    z = torch.where(depth > 0, depth, torch.full_like(depth, float("nan")))
    median = z.flatten(1).nanmedian(dim=1).values.nan_to_num(1.0)
    near = median - torch.empty(b).uniform_(0.05, 0.3, generator=g)
    relief = depth[donor] - median[donor, None, None]
    pasted = torch.where(depth[donor] > 0, (near[:, None, None] + relief).clamp_min(0.05), 0.0)
    donor_inst = torch.where(inst[donor] > 0, inst[donor] + labels.shape[1], 0)
    return (
        torch.where(box[:, None], rgb[donor], rgb),
        torch.where(box, pasted, depth),
        torch.where(box, donor_inst, inst),
        torch.cat([labels, labels[donor]], dim=1),
    )


def _shadow(b: int, h: int, w: int, g: torch.Generator) -> torch.Tensor:
    """Multiplicative shading ``(B, 1, H, W)``: smooth random dark patches on half the crops."""
    field = F.interpolate(torch.rand(b, 1, 4, 4, generator=g), size=(h, w), mode="bicubic")
    cast = (field - 0.5).mul(8).sigmoid()  # soft-edged blobs
    depth_of_shadow = torch.empty(b, 1, 1, 1).uniform_(0.0, 0.6, generator=g)
    depth_of_shadow *= torch.rand(b, 1, 1, 1, generator=g) < 0.5
    return 1 - depth_of_shadow * cast


def _jitter(
    rgb: torch.Tensor, depth: torch.Tensor, g: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """Colour gain, brightness, contrast, shadows, blur, grey and noise; depth noise and holes."""
    b = len(rgb)

    def u(lo: float, hi: float, *shape: int) -> torch.Tensor:
        return torch.empty(b, *shape).uniform_(lo, hi, generator=g)

    rgb = rgb * u(0.8, 1.2, 3, 1, 1) * u(0.6, 1.4, 1, 1, 1) * _shadow(b, *rgb.shape[-2:], g)
    blurred = F.avg_pool2d(F.pad(rgb, (1, 1, 1, 1), mode="replicate"), 3, stride=1)
    rgb = torch.where(torch.rand(b, 1, 1, 1, generator=g) < 0.3, blurred, rgb)
    mean = rgb.mean(dim=(1, 2, 3), keepdim=True)
    rgb = (rgb - mean) * u(0.7, 1.3, 1, 1, 1) + mean
    grey = torch.rand(b, 1, 1, 1, generator=g) < 0.1
    rgb = torch.where(grey, rgb.mean(dim=1, keepdim=True).expand_as(rgb), rgb)
    rgb = rgb + torch.randn(rgb.shape, generator=g) * u(0.0, 0.04, 1, 1, 1)
    noise = 1 + torch.randn(depth.shape, generator=g) * 0.002
    dropped = torch.rand(depth.shape, generator=g) < u(0.0, 0.1, 1, 1)
    depth = torch.where(dropped, torch.zeros_like(depth), depth * noise)
    return rgb.clamp(0, 1), depth


def detector_targets(instances: torch.Tensor, labels: torch.Tensor, k: int) -> DetectorTargets:
    """The heads' targets of instance maps: classes, centre heatmaps and offsets.

    Args:
        instances: instance index + 1 of every input pixel, 0 for none ``(B, H, W)`` (H, W even).
        labels: object index of each instance, -1 for an object not detected ``(B, L)``.
        k: the number of objects K.

    Returns:
        :class:`DetectorTargets`: classes at the input's resolution, the rest at the heads'
        (every second pixel). An instance's centre is the mean of its head pixels; its Gaussian
        (sigma a tenth of the square root of its area, 1 to 4 head pixels) peaks at 1 on the
        pixel nearest the centre.
    """
    instances = instances.long()
    table = torch.cat([torch.full((len(labels), 1), -1), labels.long()], dim=1)
    obj = table.gather(1, instances.flatten(1)).view_as(instances)  # -1: background or unknown
    inst_head, obj_head = instances[:, ::2, ::2], obj[:, ::2, ::2]
    b, h, w = inst_head.shape
    ys, xs = torch.meshgrid(
        torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij"
    )
    known = obj_head >= 0
    key = (torch.arange(b)[:, None, None] * 256 + inst_head)[known]
    uniq, slot = key.unique(return_inverse=True)
    count = torch.zeros(len(uniq)).index_add_(0, slot, torch.ones(len(slot)))
    cx = torch.zeros(len(uniq)).index_add_(0, slot, xs.expand(b, h, w)[known]) / count
    cy = torch.zeros(len(uniq)).index_add_(0, slot, ys.expand(b, h, w)[known]) / count
    offsets = torch.zeros(b, 2, h, w)
    offsets[:, 0][known] = cx[slot] - xs.expand(b, h, w)[known]
    offsets[:, 1][known] = cy[slot] - ys.expand(b, h, w)[known]
    heat = torch.zeros(b * k, h, w)
    if len(uniq):
        first = _first_index(slot, len(uniq))
        label = obj_head[known][first]
        batch = uniq // 256
        sigma = (0.1 * count.sqrt()).clamp(1.0, 4.0)
        rx, ry = cx.round(), cy.round()
        d2 = (xs[None] - rx[:, None, None]) ** 2 + (ys[None] - ry[:, None, None]) ** 2
        g = torch.exp(-d2 / (2 * sigma[:, None, None] ** 2))
        rows = (batch * k + label)[:, None].expand(-1, h * w)
        heat.view(b * k, h * w).scatter_reduce_(0, rows, g.view(-1, h * w), "amax")
    classes = obj + 1
    return DetectorTargets(classes, heat.view(b, k, h, w), offsets, known)


def _first_index(slot: torch.Tensor, n: int) -> torch.Tensor:
    """For each of ``n`` groups, the position of one member in ``slot``."""
    out = torch.zeros(n, dtype=torch.long)
    out[slot] = torch.arange(len(slot))
    return out


def detector_loss(
    outputs: tuple[torch.Tensor, torch.Tensor, torch.Tensor], targets: DetectorTargets
) -> dict[str, torch.Tensor]:
    """Cross-entropy and Dice on classes, CenterNet focal loss on heatmaps, L1 on offsets.

    Returns:
        ``{"total", "classes", "centres", "offsets"}`` scalars.
    """
    semantic, centres, offsets = outputs
    logits = F.interpolate(
        semantic, size=targets.classes.shape[-2:], mode="bilinear", align_corners=False
    )
    l_cls = F.cross_entropy(logits, targets.classes) + _dice_loss(logits, targets.classes)
    p = centres.sigmoid().clamp(1e-4, 1 - 1e-4)
    y = targets.heatmaps
    pos = y >= 1.0 - 1e-6
    focal = torch.where(pos, (1 - p) ** 2 * p.log(), (1 - y) ** 4 * p**2 * (1 - p).log())
    l_cen = -focal.sum() / pos.sum().clamp_min(1)
    m = targets.offset_mask[:, None].expand_as(offsets)
    l_off = (offsets - targets.offsets).abs()[m].sum() / m.sum().clamp_min(1) / 4
    return {"total": l_cls + l_cen + l_off, "classes": l_cls, "centres": l_cen, "offsets": l_off}


def _dice_loss(logits: torch.Tensor, classes: torch.Tensor) -> torch.Tensor:
    """1 - soft Dice of each object class in the batch, averaged: weighs objects as background."""
    probs = logits.softmax(dim=1)[:, 1:]
    onehot = F.one_hot(classes, logits.shape[1]).permute(0, 3, 1, 2)[:, 1:].to(probs.dtype)
    inter = (probs * onehot).sum(dim=(0, 2, 3))
    total = probs.sum(dim=(0, 2, 3)) + onehot.sum(dim=(0, 2, 3))
    present = onehot.sum(dim=(0, 2, 3)) > 0
    if not bool(present.any()):
        return logits.new_zeros(())
    return (1 - (2 * inter + 1) / (total + 1))[present].mean()


def train_detector(
    root: str | Path,
    out: str | Path,
    *,
    split: str = "train",
    steps: int = 4000,
    batch_size: int = 8,
    crop: int = 192,
    lr: float = 2e-3,
    max_images: int | None = None,
    widths: tuple[int, ...] = (24, 32, 48, 64, 96),
    input_focal: float = 290.0,
    seed: int = 0,
    progress: bool = True,
) -> Detector:
    """Train a :class:`Detector` of a BOP dataset's objects on one of its splits and save it.

    Args:
        root: the BOP dataset (the recipe's synth images).
        out: the detector's folder (``config.json`` + ``model.safetensors``).
        split: the split to train on.
        steps: optimiser steps (AdamW, one-cycle learning rate).
        batch_size: crops per step.
        crop: side of the square crops in input pixels (a multiple of 32).
        lr: peak learning rate.
        max_images: read at most this many images.
        widths: the network's channels at strides 2-32.
        input_focal: the focal length the images are resampled to.
        seed: seed of the initial weights and the batches.
        progress: show progress (a bar on a terminal, a line every 30 s in a log).

    Returns:
        The trained detector, in evaluation mode.

    Raises:
        ValueRangeError: ``steps`` or ``batch_size`` below 1, or ``crop`` not a multiple of 32.
    """
    if steps < 1 or batch_size < 1:
        raise ValueRangeError(f"steps and batch_size must be at least 1, got {steps}, {batch_size}")
    if crop < 32 or crop % 32:
        raise ValueRangeError(f"crop must be a positive multiple of 32, got {crop}")
    start = time.perf_counter()
    data = detector_images(
        root, split, input_focal=input_focal, max_images=max_images, progress=progress
    )
    torch.manual_seed(seed)
    config = DetectorConfig(obj_ids=data.obj_ids, widths=tuple(widths), input_focal=input_focal)
    detector = Detector(config)
    net = detector.net.train()
    opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=1e-4)
    schedule = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=steps)
    g = torch.Generator().manual_seed(seed)
    running: dict[str, float] = {}
    for step in progress_loop(range(steps), total=steps, desc="detector", enabled=progress):
        x, targets = training_batch(data, batch_size, crop, g, input_focal=input_focal)
        losses = detector_loss(net(x), targets)
        opt.zero_grad(set_to_none=True)
        losses["total"].backward()
        opt.step()
        schedule.step()
        for name, value in losses.items():
            v = float(value.detach())
            running[name] = 0.98 * running.get(name, v) + 0.02 * v
        if progress and (step + 1) % 500 == 0:
            _LOG.info("detector step %d: %s", step + 1, _fmt(running))
    detector.eval()
    minutes = (time.perf_counter() - start) / 60
    detector.save(
        out,
        training={
            "dataset": str(Path(root).resolve()),
            "split": split,
            "steps": steps,
            "batch_size": batch_size,
            "crop": crop,
            "lr": lr,
            "images": len(data),
            "seed": seed,
            "loss": {k: round(v, 4) for k, v in running.items()},
            "minutes": round(minutes, 2),
        },
    )
    return detector


def _fmt(losses: dict[str, float]) -> str:
    return ", ".join(f"{k} {v:.3f}" for k, v in losses.items())
