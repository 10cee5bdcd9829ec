"""The detector on a BOP test split: COCO mask AP, BOP target recall and time per image.

Detects every image of DATASET's test split with a detector folder (``--detector``), or first
trains one on a synth folder of the same objects (``--train SYNTH --out DIR``, the recipe's
``poseflow train-detector``), writes the BOP detections JSON (``--detections``, default
``DIR/detections_DATASET-test.json``) and prints COCO's mask AP (pycocotools), the recall of the
BOP targets (mask IoU ≥ 0.5 with one of the detections kept for them) per object, the mean IoU of
those and the detector's seconds per image (one thread unless ``OMP_NUM_THREADS`` says more).

Run ``python benchmarks/detection.py ../shared/devbench --detector runs/unseen/dev/detector``;
``--quick`` (CI) trains a few steps on a generated set and scores its test split.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
from pathlib import Path

import torch
from _common import report

from poseflow.cli import main as poseflow
from poseflow.data.bop import write_detections
from poseflow.detect import Detector, detect_dataset, train_detector
from poseflow.eval.detection import score_detections


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", nargs="?", help="BOP dataset with a test split")
    parser.add_argument("--detector", default=None, help="a trained detector folder")
    parser.add_argument("--train", default=None, help="train first on this synth folder")
    parser.add_argument("--out", default=None, help="where --train writes the detector")
    parser.add_argument("--steps", type=int, default=4000, help="training steps with --train")
    parser.add_argument("--max-images", type=int, default=None, help="training images")
    parser.add_argument("--detections", default=None, help="detections JSON to write")
    parser.add_argument("--quick", action="store_true", help="tiny generated set (CI)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        if args.quick:
            data = Path(tmp) / "synth"
            poseflow(["synth", str(data), "--train", "4", "--test", "2", "--seed", "5",
                      "--width", "320", "--height", "240", "--no-progress"])  # fmt: skip
            args.dataset, args.train, args.out, args.steps = str(data), str(data), None, 5
        if args.dataset is None:
            parser.error("give a BOP dataset folder, or --quick")
        if args.train is not None:
            out = Path(args.out or Path(tmp) / "detector")
            detector = train_detector(
                args.train, out, steps=args.steps, max_images=args.max_images, progress=True
            )
        elif args.detector is not None:
            out = Path(args.detector)
            detector = Detector.load(out)
        else:
            parser.error("give --detector DIR or --train SYNTH")
        detections = detect_dataset(detector, args.dataset, progress=False)
        name = Path(args.dataset).resolve().name
        path = Path(args.detections or out / f"detections_{name}-test.json")
        write_detections(path, detections)
        scores = score_detections(args.dataset, detections)
    seconds = {(d.scene_id, d.im_id): d.time for d in detections}
    scores["seconds_per_image"] = round(statistics.median(seconds.values()), 4) if seconds else 0
    print(f"{name}: mask AP {scores['AP']:.3f} (AP50 {scores['AP50']:.3f}), target recall "
          f"{scores['recall']:.3f}, mean IoU {scores['mean_iou']:.3f}, "
          f"{scores['seconds_per_image']:.3f} s/image")  # fmt: skip
    for o, s in scores["per_object"].items():
        print(f"  obj {o}: AP {s['AP']:.3f} AP50 {s['AP50']:.3f} recall {s['recall']:.3f} "
              f"({s['targets']} targets) IoU {s['mean_iou']:.3f}")  # fmt: skip
    print(f"detections: {path}" if not args.quick else "detections: (temporary)")
    report({"benchmark": "detection", "dataset": name, **scores}, __file__)


if __name__ == "__main__":
    main()
