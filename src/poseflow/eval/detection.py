"""Detection quality as the field reports it: COCO segmentation AP and the recall of BOP targets.

:func:`score_detections` scores BOP detections (COCO-RLE masks) against a BOP split's visible
masks: COCO's mask AP (pycocotools' ``COCOeval``, all objects and each one) over the ground-truth
instances at least 10 % visible, and the recall of the BOP targets: the share of the target
instances that one of the detections kept for them (the ``inst_count`` best-scored of their
object in their image, as pose estimation keeps them) covers with mask IoU ≥ 0.5, with the mean
IoU of those.
"""

from __future__ import annotations

import contextlib
import io
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image

from poseflow.data.bop import BOPDataset, Detection
from poseflow.errors import MissingDependencyError

__all__ = ["score_detections"]

#: Visible fraction below which a ground-truth instance is not a BOP target.
_MIN_VISIB = 0.1


def score_detections(
    root: str | Path,
    detections: Sequence[Detection],
    *,
    split: str = "test",
    iou_threshold: float = 0.5,
) -> dict[str, Any]:
    """COCO mask AP and BOP target recall of detections on a BOP split.

    Args:
        root: the BOP dataset folder (visible masks, ``scene_gt_info.json``,
            ``test_targets_bop19.json`` when the split has one).
        detections: the detections of the split's images (others are ignored).
        split: the split.
        iou_threshold: mask IoU at which a target instance counts as found.

    Returns:
        ``{"AP", "AP50", "AP75", "recall", "mean_iou", "per_object": {obj_id: {"AP", "AP50",
        "recall", "mean_iou", "targets"}}, "images", "detections"}``.

    Raises:
        MissingDependencyError: pycocotools is not installed.
    """
    try:
        from pycocotools import mask as mask_utils
        from pycocotools.coco import COCO
        from pycocotools.cocoeval import COCOeval
    except ImportError as err:
        raise MissingDependencyError("pycocotools", "bench", "detection AP") from err
    ds = BOPDataset(root, split)
    images = {(s, i): n for n, (s, i) in enumerate(_images(ds))}
    gts, targets, sizes = _ground_truth(ds, images, mask_utils)
    dets = [d for d in detections if (d.scene_id, d.im_id) in images and d.segmentation]
    obj_ids = sorted({g["category_id"] for g in gts})
    coco = COCO()
    coco.dataset = {
        "images": [{"id": n, "height": h, "width": w} for n, (h, w) in sizes.items()],
        "annotations": gts,
        "categories": [{"id": o} for o in obj_ids],
    }
    with contextlib.redirect_stdout(io.StringIO()):
        coco.createIndex()
    results = [
        {
            "image_id": images[(d.scene_id, d.im_id)],
            "category_id": d.obj_id,
            "segmentation": _compressed(d.segmentation, mask_utils),
            "score": d.score,
        }
        for d in dets
        if d.obj_id in obj_ids
    ]

    with contextlib.redirect_stdout(io.StringIO()):
        found = coco.loadRes(results) if results else None

    def ap(categories: list[int]) -> tuple[float, float, float]:
        if found is None:
            return 0.0, 0.0, 0.0
        with contextlib.redirect_stdout(io.StringIO()):
            run = COCOeval(coco, found, iouType="segm")
            run.params.catIds = categories
            run.evaluate()
            run.accumulate()
            run.summarize()
        return tuple(max(0.0, float(x)) for x in run.stats[:3])  # type: ignore[return-value]

    recall = _target_recall(targets, dets, iou_threshold, mask_utils)
    out: dict[str, Any] = {}
    out["AP"], out["AP50"], out["AP75"] = ap(obj_ids)
    hits = [iou for per in recall.values() for iou in per]
    out["recall"] = _share(hits, iou_threshold)
    out["mean_iou"] = _mean_found(hits, iou_threshold)
    out["per_object"] = {}
    for o in obj_ids:
        a, a50, _ = ap([o])
        ious = recall.get(o, [])
        out["per_object"][o] = {
            "AP": a,
            "AP50": a50,
            "recall": _share(ious, iou_threshold),
            "mean_iou": _mean_found(ious, iou_threshold),
            "targets": len(ious),
        }
    out["images"], out["detections"] = len(images), len(dets)
    return out


def _images(ds: BOPDataset) -> list[tuple[int, int]]:
    return [(s, i) for s in ds.scene_ids for i in ds.scene(s).im_ids]


def _ground_truth(
    ds: BOPDataset, images: dict[tuple[int, int], int], mask_utils: Any
) -> tuple[
    list[dict[str, Any]], dict[tuple[int, int, int], list[torch.Tensor]], dict[int, tuple[int, int]]
]:
    """The instances ≥ 10 % visible: COCO annotations, masks by image and object, image sizes."""
    known = set(ds.models_info())
    gts: list[dict[str, Any]] = []
    masks: dict[tuple[int, int, int], list[torch.Tensor]] = {}
    sizes: dict[int, tuple[int, int]] = {}
    for (s, i), n in images.items():
        scene = ds.scene(s)
        with Image.open(scene.depth_path(i)) as im:
            sizes[n] = (im.height, im.width)
        infos = scene.gt_info.get(i, [])
        for k, gt in enumerate(scene.gt_of(i)):
            if gt.obj_id not in known or (k < len(infos) and infos[k].visib_fract < _MIN_VISIB):
                continue
            mask = scene.load_mask(i, k, visible=True).bool()
            if not bool(mask.any()):
                continue
            rle = mask_utils.encode(np.asfortranarray(mask.numpy().astype(np.uint8)))
            gts.append({
                "id": len(gts) + 1,
                "image_id": n,
                "category_id": gt.obj_id,
                "segmentation": rle,
                "area": float(mask_utils.area(rle)),
                "bbox": [float(x) for x in mask_utils.toBbox(rle)],
                "iscrowd": 0,
            })  # fmt: skip
            masks.setdefault((s, i, gt.obj_id), []).append(mask)
    return gts, masks, sizes


def _compressed(rle: Any, mask_utils: Any) -> dict[str, Any]:
    """A COCO RLE with compressed counts, as pycocotools wants it."""
    if isinstance(rle.get("counts"), list):
        h, w = rle["size"]
        return mask_utils.frPyObjects(dict(rle), h, w)
    counts = rle["counts"]
    return {
        "size": list(rle["size"]),
        "counts": counts.encode() if isinstance(counts, str) else counts,
    }


def _target_recall(
    targets: dict[tuple[int, int, int], list[torch.Tensor]],
    dets: Sequence[Detection],
    iou_threshold: float,
    mask_utils: Any,
) -> dict[int, list[float]]:
    """Per object, each target instance's IoU with the best of the detections kept for it."""
    by_key: dict[tuple[int, int, int], list[Detection]] = {}
    for d in sorted(dets, key=lambda d: -d.score):
        by_key.setdefault((d.scene_id, d.im_id, d.obj_id), []).append(d)
    out: dict[int, list[float]] = {}
    for key, masks in targets.items():
        kept = [d.mask() for d in by_key.get(key, [])[: len(masks)]]
        free = list(range(len(kept)))
        for mask in masks:
            ious = [(_iou(mask, kept[j]), j) for j in free]
            best, j = max(ious, default=(0.0, -1))
            if best >= iou_threshold:
                free.remove(j)
            out.setdefault(key[2], []).append(best)
    return out


def _iou(a: torch.Tensor, b: torch.Tensor) -> float:
    union = int((a | b).sum())
    return int((a & b).sum()) / union if union else 0.0


def _share(ious: list[float], threshold: float) -> float:
    return sum(iou >= threshold for iou in ious) / len(ious) if ious else 0.0


def _mean_found(ious: list[float], threshold: float) -> float:
    found = [iou for iou in ious if iou >= threshold]
    return float(np.mean(found)) if found else 0.0
