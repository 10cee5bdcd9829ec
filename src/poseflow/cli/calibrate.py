"""``poseflow calibrate``: fit what ``valid`` means for a model, on images with ground truth.

For each estimator (``--method``, default all three), the split is predicted from its
ground-truth masks (``poseflow predict``'s estimation, in this process, into
``WORK/METHOD.csv``, and each pose's score, agreement and error in ``WORK/METHOD_poses.csv``;
``--work``, default ``MODEL/calibration``); each pose's MSSD error against
the truth (:func:`~poseflow.eval.validity.estimate_errors`) and the agreement of the
estimator's hypotheses with it then fit a :class:`~poseflow.eval.validity.ValidityRule` (per
object, the lowest score, and for FunFlow6D and the hybrid the least agreement, from which
``--precision`` of the poses were right), stored in ``MODEL/validity.json`` and drawn in
``WORK/validity.png`` (score against error; with matplotlib, the ``viz`` extra).
``poseflow onboard`` runs it on renders of the
user's objects that no training saw; calibrating on test images would make the figures on them
meaningless. ``--check`` measures instead how well the stored rules hold on DATASET.
"""

from __future__ import annotations

import argparse
import json
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
store per object the lowest score (and the least agreement of the estimator's hypotheses) from
which the poses were right in --precision of cases in MODEL/validity.json (drawn in
WORK/validity.png). `poseflow estimate` then marks a pose valid only from there. `poseflow
onboard` runs this as its last phase; --check measures how well the rules hold on a test set."""

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
        "--check",
        action="store_true",
        help="measure how well MODEL_DIR's rules hold on DATASET (e.g. a test split), "
        "without fitting them again",
    )
    parser.add_argument(
        "--cache",
        default=None,
        help="folder of the prepared objects (default: the model folder, as predict's)",
    )
    parser.add_argument(
        "--work",
        default=None,
        help="folder of the predictions and the picture (default: MODEL_DIR/calibration, "
        "with --check MODEL_DIR/check)",
    )


def run(args: argparse.Namespace) -> int:
    """Predict, measure, fit (or check) the rules; prints one block per method. Returns 0."""
    from poseflow.cli.common import LOG, check_writable, show_progress
    from poseflow.data.bop import BOPDataset
    from poseflow.data.object_folder import check_dataset, load_object_models
    from poseflow.errors import MissingDependencyError, MissingFileError, UsageError
    from poseflow.eval.results import write_results
    from poseflow.eval.validity import (
        VALIDITY_FILE,
        ValidityRule,
        mesh_key,
        plot_reliability,
        read_validity,
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
    work = check_writable(
        args.work or model / ("check" if args.check else "calibration"), folder=True
    )
    ds = BOPDataset(args.dataset, args.split, load_rgb=False, load_masks=False)
    objects = load_object_models(args.dataset, progress=show_progress(args))
    keys = {o: mesh_key(m) for o, m in objects.items()}
    panels, figures = {}, {}
    for method in args.method:
        known = read_validity(model, method) if args.check else None
        if args.check and known is None:
            raise MissingFileError(
                f"{model / VALIDITY_FILE} holds no rule for {method}: calibrate it first"
            )
        res, agreement, errors = _poses(args, model, method, work, ds)
        write_results(work / f"{method}.csv", res)
        _write_poses(work / f"{method}_poses.csv", res, agreement, errors)
        shares = None if bool(agreement.isnan().all()) else agreement
        rule = known or ValidityRule.fit(
            method, res.scores, errors, res.obj_ids, precision=args.precision,
            tolerance=args.tolerance, mesh_keys=keys, agreement=shares,
        )  # fmt: skip
        if not args.check:
            write_validity(model, rule)
        valid, _ = rule.decide(res.scores, res.obj_ids, keys, shares)
        figures[method] = validity_report(valid, errors, res.obj_ids, tolerance=rule.tolerance)
        print(_summary(method, rule, figures[method], checked=args.check))
        panels[method] = (res.scores, errors, res.obj_ids, rule)
    (work / "validity_report.json").write_text(json.dumps(figures, indent=1))
    done = "checked" if args.check else "written to"
    print(f"rules {done} {model / VALIDITY_FILE}; per-object figures in {work}")
    try:
        plot_reliability(work / "validity.png", panels)
    except MissingDependencyError:
        LOG.info("note: validity.png skipped: the picture needs matplotlib (pip install "
                 "'poseflow[viz]')")  # fmt: skip
    return 0


def _poses(
    args: argparse.Namespace, model: Path, method: str, work: Path, ds: Any
) -> tuple[Any, Any, Any]:
    """``method``'s poses of the split from its ground-truth masks: results, agreement, errors."""
    from poseflow.cli.common import LOG
    from poseflow.cli.predict import estimate_split
    from poseflow.eval.validity import estimate_errors

    argv = [str(args.dataset), "--model", str(model), "--method", method, "--split",
            args.split, "--out", str(work / f"{method}.csv"), "--seed", str(args.seed),
            "-q"]  # fmt: skip
    argv += ["--no-progress"] if args.no_progress else []
    argv += ["--max-images", str(args.max_images)] if args.max_images else []
    argv += ["--cache", str(args.cache)] if args.cache else []
    LOG.info("predicting: poseflow predict %s", " ".join(argv))
    res, agreement = estimate_split(argv)
    return res, agreement, estimate_errors(ds, res)


def _write_poses(path: Path, res: Any, agreement: Any, errors: Any) -> None:
    """One line per pose: its ids, score, agreement (empty: none) and MSSD fraction."""
    lines = ["scene_id,im_id,obj_id,score,agreement,mssd"]
    for s, i, o, score, a, e in zip(
        res.scene_ids.tolist(), res.im_ids.tolist(), res.obj_ids.tolist(),
        res.scores.tolist(), agreement.tolist(), errors.tolist(),
    ):  # fmt: skip
        lines.append(f"{s},{i},{o},{score:.6f},{'' if math.isnan(a) else f'{a:.4f}'},{e:.6f}")
    path.write_text("\n".join(lines) + "\n")


def _summary(
    method: str, rule: ValidityRule, report: dict[str, Any], *, checked: bool = False
) -> str:
    """One line per object (poses, right, valid, thresholds), then the figures of all."""
    pad = " " * (len(method) + 2)
    lines = [f"{method}: {'object':>6} {'poses':>6} {'right':>6} {'valid':>6} "
             f"{'precision':>9} {'recall':>6}  valid from score / agreement"]  # fmt: skip
    for obj, threshold in sorted(rule.thresholds.items()):
        row = report["per_object"].get(str(obj))
        if row is None:
            continue
        cut = "never" if math.isinf(threshold) else f"{threshold:.3f}"
        least = rule.agreements.get(obj, 0.0)
        lines.append(
            f"{pad}{obj:>6} {row['poses']:>6} {row['right']:>6} {row['valid']:>6} "
            f"{row['precision']:>9.3f} {row['recall']:>6.3f}  {cut}"
            + (f" / {least:.2f}" if least else "")
        )
    where = "on these images (not the calibration's)" if checked else "on these images"
    lines.append(
        f"{pad}{where}: precision {report['precision']:.3f}, recall {report['recall']:.3f} "
        f"({report['valid']} of {report['poses']} poses valid, {report['right']} right)"
    )
    return "\n".join(lines)
