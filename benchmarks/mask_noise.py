"""Ground-truth masks made imperfect, as BOP detections: eroded, dilated or cut by an occluder.

Writes a BOP detections JSON of a dataset's test targets whose masks are the ground-truth visible
masks changed as a detector would get them wrong: ``--erode N`` / ``--dilate N`` pixels (a square
structuring element), or ``--cut F`` (the share F of each mask's pixels removed by a straight edge
at a random angle, as an object in front would hide them). Score 1, no time. Estimate with
``poseflow predict DATASET --detections OUT.json`` (or ``benchmarks/unseen.py --predict-args
"--detections OUT.json" --detections gt``) to read how much each estimator loses to the mask.

Run ``python benchmarks/mask_noise.py ../shared/devbench --dilate 5 --out runs/masks/dilate5.json``.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import torch
import torch.nn.functional as F
from _common import report

from poseflow.data.bop import BOPDataset, Detection, write_detections
from poseflow.data.rle import rle_encode
from poseflow.detect import mask_box


def erode_or_dilate(mask: torch.Tensor, pixels: int) -> torch.Tensor:
    """``mask (H, W)`` dilated by ``pixels`` (> 0) or eroded by ``-pixels`` (< 0), square element.

    Example:
        >>> m = torch.zeros(7, 7, dtype=torch.bool); m[3, 3] = True
        >>> int(erode_or_dilate(m, 1).sum()), int(erode_or_dilate(erode_or_dilate(m, 1), -1).sum())
        (9, 1)
    """
    if pixels == 0:
        return mask.clone()
    k = 2 * abs(pixels) + 1
    x = mask[None, None].float() if pixels > 0 else (~mask)[None, None].float()
    grown = F.max_pool2d(x, k, stride=1, padding=abs(pixels))[0, 0] > 0
    return grown if pixels > 0 else ~grown


def cut(mask: torch.Tensor, share: float, generator: torch.Generator) -> torch.Tensor:
    """``mask (H, W)`` less the ``share`` of its pixels beyond a straight edge at a random angle."""
    ys, xs = mask.nonzero(as_tuple=True)
    if len(xs) == 0 or share <= 0:
        return mask.clone()
    angle = float(torch.rand((), generator=generator)) * 2 * math.pi
    along = xs.float() * math.cos(angle) + ys.float() * math.sin(angle)
    edge = torch.quantile(along, 1 - share)
    out = mask.clone()
    out[ys[along > edge], xs[along > edge]] = False
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", help="BOP dataset with test_targets_bop19.json")
    parser.add_argument("--out", required=True, help="detections JSON to write")
    change = parser.add_mutually_exclusive_group(required=True)
    change.add_argument("--erode", type=int, default=None, help="pixels to erode")
    change.add_argument("--dilate", type=int, default=None, help="pixels to dilate")
    change.add_argument("--cut", type=float, default=None, help="share of pixels to cut off")
    parser.add_argument("--seed", type=int, default=0, help="seed of the cuts' angles")
    args = parser.parse_args()
    ds = BOPDataset(args.dataset, "test")
    wanted = {(t.scene_id, t.im_id, t.obj_id) for t in ds.test_targets()}
    g = torch.Generator().manual_seed(args.seed)
    dets, areas = [], []
    for s in ds.scene_ids:
        scene = ds.scene(s)
        for im in scene.im_ids:
            infos = scene.gt_info.get(im, [])
            for k, gt in enumerate(scene.gt_of(im)):
                if (s, im, gt.obj_id) not in wanted or (infos and infos[k].visib_fract < 0.1):
                    continue
                mask = scene.load_mask(im, k, visible=True).bool()
                if args.cut is not None:
                    new = cut(mask, args.cut, g)
                else:
                    new = erode_or_dilate(mask, args.dilate if args.dilate else -args.erode)
                areas.append(float(new.sum()) / max(1.0, float(mask.sum())))
                dets.append(Detection(s, im, gt.obj_id, 1.0, mask_box(new), rle_encode(new)))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    write_detections(args.out, dets)
    change_name = "cut" if args.cut is not None else "dilate" if args.dilate else "erode"
    amount = args.cut if args.cut is not None else args.dilate or args.erode
    report(
        {
            "benchmark": "mask_noise",
            "dataset": Path(args.dataset).resolve().name,
            "change": change_name,
            "amount": amount,
            "instances": len(dets),
            "mean_area_ratio": round(sum(areas) / max(1, len(areas)), 4),
            "out": str(args.out),
        },
        __file__,
    )


if __name__ == "__main__":
    main()
