"""Does ``valid`` mean right? Precision and recall of a model's calibrated ``valid`` on a test set.

For each predict seed, ``poseflow calibrate DATASET --model MODEL --check`` estimates the test
split from its ground-truth masks with each estimator and scores the model's stored rules
(``validity.json``, fitted on renders, never on DATASET) against the truth: a pose is right when
its MSSD is below the rule's tolerance (a tenth of the diameter). Prints one row per estimator
and seed (poses, right, valid, precision = right among valid, recall = valid among right), per
object beside; ``--picture`` copies the first seed's score-against-error picture.

Run ``python benchmarks/validity.py ../shared/devbench --model runs/unseen/dev/run/model
--work runs/cal/check``; ``--quick`` (CI) calibrates the demo model's baseline rule on two
generated images and checks it on two others.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path

from _common import report as report_line

from poseflow.assets import DEMO_CHECKPOINT
from poseflow.cli import main as poseflow

METHODS = ("funflow6d", "baseline", "hybrid")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", nargs="?", help="BOP dataset with a test split")
    parser.add_argument("--model", default=None, help="a calibrated model folder")
    parser.add_argument("--work", default=None, help="folder of each seed's check")
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--picture", default=None, help="PNG of the first seed's poses")
    parser.add_argument("--quick", action="store_true", help="tiny generated set (CI)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        if args.quick:
            _quick(args, Path(tmp))
        if args.dataset is None or args.model is None or args.work is None:
            parser.error("give DATASET, --model and --work, or --quick")
        rows = []
        for seed in args.seeds:
            work = Path(args.work) / f"seed{seed}"
            argv = ["calibrate", args.dataset, "--model", args.model, "--check", "--method",
                    *args.methods, "--seed", str(seed), "--work", str(work),
                    "--no-progress"]  # fmt: skip
            if poseflow(argv) != 0:
                raise SystemExit(f"`poseflow {' '.join(argv)}` failed")
            report = json.loads((work / "validity_report.json").read_text())
            rows += [{"method": m, "seed": seed, **report[m]} for m in args.methods]
        _print(sorted(rows, key=lambda r: METHODS.index(r["method"])))
        if args.picture:
            shutil.copy(Path(args.work) / f"seed{args.seeds[0]}" / "validity.png", args.picture)
            print(f"picture: {args.picture}")
        report_line({"validity": rows, "model": str(args.model)}, __file__)


def _quick(args: argparse.Namespace, tmp: Path) -> None:
    """Calibrate a copy of the demo model's baseline rule on two renders; check two others."""
    for name, seed in (("calib", 7), ("test", 8)):
        poseflow(["synth", str(tmp / name), "--train", "0", "--test", "2", "--seed", str(seed),
                  "--width", "320", "--height", "240", "--images-per-scene", "1",
                  "--no-progress"])  # fmt: skip
    model = tmp / "model"
    shutil.copytree(DEMO_CHECKPOINT, model)
    poseflow(["calibrate", str(tmp / "calib"), "--model", str(model), "--method", "baseline",
              "--no-progress"])  # fmt: skip
    args.dataset, args.model, args.work = str(tmp / "test"), str(model), str(tmp / "check")
    args.methods, args.seeds = ["baseline"], [0]


def _print(rows: list[dict]) -> None:
    print(f"{'method':>10} {'seed':>4} {'poses':>5} {'right':>5} {'valid':>5} "
          f"{'precision':>9} {'recall':>6}   per object: precision / recall")  # fmt: skip
    for r in rows:
        per = "  ".join(
            f"{o}: {v['precision']:.2f}/{v['recall']:.2f}" for o, v in r["per_object"].items()
        )
        print(f"{r['method']:>10} {r['seed']:>4} {r['poses']:>5} {r['right']:>5} {r['valid']:>5} "
              f"{r['precision']:>9.3f} {r['recall']:>6.3f}   {per}")  # fmt: skip


if __name__ == "__main__":
    main()
