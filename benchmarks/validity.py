"""Does ``valid`` mean right? Precision and recall of a model's calibrated ``valid`` on a test set.

For each estimator and predict seed, DATASET's test split is estimated from its ground-truth
masks (in this process, so that each pose's agreement of the estimator's hypotheses is kept;
the results CSVs go to ``--work``) and scored against the truth: a pose is right when its MSSD
is below the rule's tolerance (a tenth of the diameter), valid when the model's
``validity.json`` (``poseflow calibrate``, fitted on renders, never on DATASET) marks it so.
Prints one row per estimator and seed (poses, right, valid, precision = right among valid,
recall = valid among right), per object beside, and draws score against error with each
object's threshold (``--picture``, the first seed).

Run ``python benchmarks/validity.py ../shared/devbench --model runs/unseen/dev/run/model
--work runs/cal/check``; ``--quick`` (CI) calibrates the demo model's baseline rule on two
generated images and checks it on two others.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import torch
from _common import report

from poseflow.assets import DEMO_CHECKPOINT
from poseflow.cli import main as poseflow
from poseflow.cli.predict import estimate_split
from poseflow.eval.results import write_results
from poseflow.eval.validity import estimate_errors, plot_reliability, read_validity, validity_report

METHODS = ("funflow6d", "baseline", "hybrid")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", nargs="?", help="BOP dataset with a test split")
    parser.add_argument("--model", default=None, help="a calibrated model folder")
    parser.add_argument("--work", default=None, help="folder of the results CSVs")
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--picture", default=None, help="PNG of the first seed's poses")
    parser.add_argument("--quick", action="store_true", help="tiny generated set (CI)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        if args.quick:
            _quick(args, Path(tmp))
        if args.dataset is None or args.model is None or args.work is None:
            parser.error("give DATASET, --model and --work, or --quick")
        work = Path(args.work)
        work.mkdir(parents=True, exist_ok=True)
        rows, panels = [], {}
        for method in args.methods:
            rule = read_validity(args.model, method)
            if rule is None:
                parser.error(f"{args.model} has no rule for {method}: run `poseflow calibrate`")
            for seed in args.seeds:
                csv = work / f"{method}_seed{seed}.csv"
                res, agreement = estimate_split([args.dataset, "--model", args.model, "--method",
                                                 method, "--out", str(csv), "--seed", str(seed),
                                                 "--no-progress", "-q"])  # fmt: skip
                write_results(csv, res)
                errors = estimate_errors(args.dataset, res)
                shares = None if bool(agreement.isnan().all()) else agreement
                valid, _ = rule.decide(res.scores, res.obj_ids, agreement=shares)
                rep = validity_report(valid, errors, res.obj_ids, tolerance=rule.tolerance)
                rows.append({"method": method, "seed": seed, **rep})
                if seed == args.seeds[0]:
                    panels[method] = (res.scores, errors, res.obj_ids, rule)
        _print(rows)
        if args.picture:
            plot_reliability(args.picture, panels)
            print(f"picture: {args.picture}")
        report({"validity": rows, "model": str(args.model)}, __file__)


def _quick(args: argparse.Namespace, tmp: Path) -> None:
    """Calibrate a copy of the demo model's baseline rule on two renders; check two others."""
    import shutil

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
