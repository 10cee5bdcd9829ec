"""Rotation errors of a nearly symmetric object split into turns about its axis and tilts.

For one object of a BOP split and one or more results CSVs, each estimate is matched to the
ground-truth instance of its object nearest in translation, and its rotation error
``R_gt^T R_est`` is split by the object's axis of revolution (fitted to the model's surface
normals, :func:`poseflow.verify.revolution_axis`): the tilt is the angle by which the axis
moves, the turn the rest. Prints per CSV how many estimates are within 10°, beyond 20°, and of
those how many are turns about the axis (tilt under 10°) or upside down (tilt over 150°).

``--scan`` also asks whether the render-and-compare verifier could tell the turns apart on these
images: the ground-truth pose of every target is turned about the axis in ``--step`` degree
steps, each turn is refined by the verifier's ICP and scored on its full grid, and the script
counts the targets whose best score is at the true turn, and those where no other turn scores
within ``--margin`` of it. ``--set KEY=VALUE`` changes a field of the scan's
:class:`~poseflow.verify.VerifierConfig` (``crop_size=128`` compares on a finer grid).

Run ``python benchmarks/turns.py DATASET --obj ID --results A.csv [B.csv ...] [--scan]``.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import _common
import torch

from poseflow.cli.options import add_set_argument, parse_set
from poseflow.data import ImageInstances
from poseflow.data.bop import BOPDataset
from poseflow.data.object_folder import load_object_models
from poseflow.eval.results import read_results
from poseflow.geometry.se3 import axis_angle_to_rotation
from poseflow.models.verification import prepare_verification
from poseflow.verify import PoseVerifier, VerifierConfig, revolution_axis


def split_error(R_gt: torch.Tensor, R_est: torch.Tensor, axis: torch.Tensor) -> tuple[float, float]:
    """``(angle, tilt)`` in degrees of the relative rotation ``R_gt^T R_est`` about ``axis``."""
    rel = R_gt.T @ R_est
    angle = math.degrees(math.acos(max(-1.0, min(1.0, (float(rel.trace()) - 1) / 2))))
    tilt = math.degrees(math.acos(max(-1.0, min(1.0, float(axis @ rel @ axis)))))
    return angle, tilt


def turns_about(axis: torch.Tensor, point: torch.Tensor, degrees: torch.Tensor) -> torch.Tensor:
    """Model-frame transforms ``(A, 4, 4)`` turning by ``degrees`` about ``point + s axis``."""
    R = axis_angle_to_rotation(axis.expand(len(degrees), 3), torch.deg2rad(degrees))
    T = torch.eye(4, dtype=axis.dtype).repeat(len(degrees), 1, 1)
    T[:, :3, :3] = R
    T[:, :3, 3] = point - (R @ point[:, None])[..., 0]
    return T


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", help="BOP dataset folder (models/, test/)")
    parser.add_argument("--obj", type=int, required=True, help="the object id")
    parser.add_argument("--results", nargs="+", required=True, help="BOP results CSVs")
    parser.add_argument("--split", default="test")
    parser.add_argument("--scan", action="store_true", help="score the true pose's turns")
    parser.add_argument("--step", type=float, default=10.0, help="turn step of --scan, degrees")
    parser.add_argument("--margin", type=float, default=0.01, help="score margin of --scan")
    add_set_argument(parser, "change a field of the scan's verifier configuration")
    args = parser.parse_args()
    torch.set_num_threads(1)

    root = Path(args.dataset)
    model = load_object_models(root, obj_ids=[args.obj])[args.obj]
    direction, point = revolution_axis(model.points.double(), model.normals.double())
    ds = BOPDataset(root, args.split)
    report: dict[str, dict] = {}
    targets: set[tuple[int, int, int]] = set()
    for path in args.results:
        res = read_results(path)
        counts = dict.fromkeys(("estimates", "under_10", "over_20", "turns", "upside_down"), 0)
        for e in (res.obj_ids == args.obj).nonzero()[:, 0].tolist():
            s, i = int(res.scene_ids[e]), int(res.im_ids[e])
            pose = res.poses[e].double()
            gts = [(k, g) for k, g in enumerate(ds.scene(s).gt_of(i)) if g.obj_id == args.obj]
            if not gts:
                continue
            k, gt = min(gts, key=lambda kg: float(torch.linalg.norm(
                torch.as_tensor(kg[1].pose[:3, 3]) - pose[:3, 3])))  # fmt: skip
            targets.add((s, i, k))
            angle, tilt = split_error(torch.as_tensor(gt.pose[:3, :3]), pose[:3, :3], direction)
            counts["estimates"] += 1
            counts["under_10"] += angle < 10
            if angle > 20:
                counts["over_20"] += 1
                counts["turns"] += tilt < 10
                counts["upside_down"] += tilt > 150
        report[Path(path).name] = counts
        print(f"{Path(path).name}: {counts}")

    if args.scan:
        verifier = PoseVerifier(VerifierConfig(**parse_set(args.set_fields)))
        prepare_verification(verifier, {args.obj: model}, progress=False)
        degrees = torch.arange(0.0, 360.0, args.step, dtype=torch.float64)
        turns = turns_about(direction, point, degrees).float()
        best_at_truth = unique = 0
        for s, i, k in sorted(targets):
            scene = ds.scene(s)
            gt = torch.as_tensor(scene.gt_of(i)[k].pose, dtype=torch.float32)
            mask = scene.load_mask(i, k, visible=True)[None]
            rgb, depth = scene.load_rgb_image(i), scene.load_depth_image(i)
            K = torch.as_tensor(scene.camera[i].K, dtype=torch.float32)
            observed, observed_mask = verifier.observed_cloud(depth, K, mask)
            poses = verifier.refine((gt @ turns)[None], [args.obj], observed, observed_mask)
            boxes = verifier.crop_boxes(gt[None], [args.obj], K, mask)
            image = ImageInstances(rgb, depth, K, mask, [args.obj])
            total = verifier.score(image, poses, boxes=boxes).total[0]
            best_at_truth += int(total.argmax()) == 0
            unique += bool((total[1:] < total[0] - args.margin).all())
        report["scan"] = {
            "targets": len(targets),
            "best_at_true_turn": best_at_truth,
            "no_other_turn_within_margin": unique,
            "step_degrees": args.step,
            "margin": args.margin,
            "verifier": parse_set(args.set_fields),
        }
        print(f"scan: {report['scan']}")
    _common.report(report, __file__)


if __name__ == "__main__":
    main()
