"""``poseflow calibrate``: fit what ``valid`` means for a model, on images with ground truth.

For each estimator (``--method``, default all three), ``poseflow predict`` runs on the split
from its ground-truth masks into ``WORK/METHOD.csv`` (``--work``, default
``MODEL/calibration``); each pose's MSSD error
against the truth (:func:`~poseflow.eval.validity.estimate_errors`) then fits a
:class:`~poseflow.eval.validity.ValidityRule` (per object, the lowest score from which
``--precision`` of the poses were right), stored in ``MODEL/validity.json`` and drawn in
``WORK/validity.png`` (score against error). ``poseflow onboard`` runs it on renders of the
user's objects that no training saw; calibrating on test images would make the figures on them
meaningless.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

from poseflow.cli.common import positive_int

if TYPE_CHECKING:
    from poseflow.eval.validity import ValidityRule

__all__ = ["DESCRIPTION", "HELP", "METHODS", "add_arguments", "run"]

#: ``calibrate``'s line in ``poseflow --help``.
HELP = "fit when poses are marked valid, on images with ground truth (calibration renders)"

#: What ``poseflow calibrate --help`` says.
DESCRIPTION = """\
Make `valid` mean "within MSSD < 0.1 diameter" with a stated precision: predict the split of
DATASET (images with ground truth that the model never trained on, such as `poseflow synth`
renders of your objects with another seed) with each estimator, measure each pose's error, and
store per object the lowest score from which the poses were right in --precision of cases in
MODEL/validity.json (drawn in WORK/validity.png). `poseflow estimate` then marks a pose valid
only from that score. `poseflow onboard` runs this as its last phase."""

#: The estimators a model folder serves.
METHODS = ("funflow6d", "baseline", "hybrid")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options of ``poseflow calibrate`` (its ``run`` is :func:`run`)."""
    parser.add_argument("dataset", type=Path, help="BOP dataset with ground truth (not test data)")
    parser.add_argument("--model", required=True, metavar="MODEL_DIR", help="the model folder")
    parser.add_argument(
        "--method", nargs="+", choices=METHODS, default=list(METHODS), help="estimators to fit"
    )
    parser.add_argument("--split", default="test", help="split folder")
    parser.add_argument(
        "--precision", type=float, default=0.95, help="share of right poses among valid ones"
    )
    parser.add_argument(
        "--tolerance", type=float, default=0.1, help="MSSD fraction of the diameter that is right"
    )
    parser.add_argument("--max-images", type=positive_int, default=None, help="images to use")
    parser.add_argument("--seed", type=int, default=0, help="seed of the predictions")
    parser.add_argument(
        "--cache",
        default=None,
        help="folder of the prepared objects (default: the model folder, as predict's)",
    )
    parser.add_argument(
        "--work",
        default=None,
        help="folder of the predictions and the picture (default: MODEL_DIR/calibration)",
    )


def run(args: argparse.Namespace) -> int:
    """Predict, measure, fit and write the rules; prints one line per object. Returns 0."""
    from poseflow.cli import main as poseflow
    from poseflow.cli.common import LOG, check_writable, show_progress
    from poseflow.data.bop import BOPDataset
    from poseflow.data.object_folder import check_dataset, load_object_models
    from poseflow.errors import PoseflowError, UsageError
    from poseflow.eval.results import read_results
    from poseflow.eval.validity import (
        ValidityRule,
        estimate_errors,
        mesh_key,
        plot_reliability,
        validity_report,
        write_validity,
    )

    if not 0 < args.precision < 1:
        raise UsageError(f"--precision must lie strictly between 0 and 1, got {args.precision}")
    if not args.tolerance > 0:
        raise UsageError(f"--tolerance must be positive, got {args.tolerance}")
    check_dataset(args.dataset, args.split)
    model = Path(args.model)
    if not (model / "config.json").is_file():
        raise UsageError(f"{model} is not a model folder (no config.json)")
    work = check_writable(args.work or model / "calibration", folder=True)
    ds = BOPDataset(args.dataset, args.split, load_rgb=False, load_masks=False)
    objects = load_object_models(args.dataset, progress=show_progress(args))
    keys = {o: mesh_key(m) for o, m in objects.items()}
    common = ["--threads", str(args.threads)] if args.threads else []
    common += ["--no-progress"] if args.no_progress else []
    common += ["--max-images", str(args.max_images)] if args.max_images else []
    common += ["--cache", str(args.cache)] if args.cache else []
    panels = {}
    for method in args.method:
        csv = work / f"{method}.csv"
        command = ["predict", str(args.dataset), "--model", str(model), "--method", method,
                   "--split", args.split, "--out", str(csv), "--seed", str(args.seed), "-q",
                   *common]  # fmt: skip
        LOG.info("$ poseflow %s", " ".join(command))
        if poseflow(command) != 0:
            raise PoseflowError(f"calibrate: `poseflow {' '.join(command)}` failed (see above)")
        res = read_results(csv)
        errors = estimate_errors(ds, res)
        rule = ValidityRule.fit(
            method, res.scores, errors, res.obj_ids, precision=args.precision,
            tolerance=args.tolerance, mesh_keys=keys,
        )  # fmt: skip
        write_validity(model, rule)
        valid, _ = rule.decide(res.scores, res.obj_ids)
        report = validity_report(valid, errors, res.obj_ids, tolerance=args.tolerance)
        print(_summary(method, rule, report))
        panels[method] = (res.scores, errors, res.obj_ids, rule)
    picture = plot_reliability(work / "validity.png", panels)
    print(f"rules written to {model / 'validity.json'}, picture {picture}")
    return 0


def _summary(method: str, rule: ValidityRule, report: dict[str, Any]) -> str:
    """One line per object (poses, right, threshold), then the calibration's own figures."""
    lines = [f"{method}: {'object':>6} {'poses':>6} {'right':>6} {'valid from':>10}"]
    for obj, threshold in sorted(rule.thresholds.items()):
        n, right = rule.counts[obj]
        cut = "never" if math.isinf(threshold) else f"{threshold:.3f}"
        lines.append(f"{'':{len(method) + 1}} {obj:>6} {n:>6} {right:>6} {cut:>10}")
    lines.append(
        f"{'':{len(method) + 1}} on these images: precision {report['precision']:.3f}, recall "
        f"{report['recall']:.3f} ({report['valid']} of {report['poses']} poses valid)"
    )
    return "\n".join(lines)
