"""``poseflow eval``: BOP 2019 Average Recall of a results file, per object and overall.

Prints a table (one row per object, then all targets pooled) and writes the full report as JSON
(see :func:`poseflow.eval.evaluate.evaluate_bop`). With ``--run-baseline`` the classic
FPFH/RANSAC/ICP baseline first predicts the split from its ground-truth masks and writes its
results to the given CSV (an existing one only with ``--overwrite``), which is then evaluated
the same way.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

__all__ = ["DESCRIPTION", "HELP", "add_arguments", "format_table", "run"]

#: ``eval``'s line in ``poseflow --help``.
HELP = "BOP Average Recall (VSD, MSSD, MSPD) of a results CSV"

#: What ``poseflow eval --help`` says.
DESCRIPTION = """\
Evaluate pose estimates in the BOP 2019 CSV format on a BOP dataset with the BOP 2019 protocol:
AR = mean of the VSD, MSSD and MSPD recalls. Prints a per-object table and writes the report as
JSON."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options of ``poseflow eval`` (its ``run`` is :func:`run`)."""
    parser.add_argument("dataset", type=Path, help="BOP dataset folder (models_eval/, split)")
    parser.add_argument("results", type=Path, help="results CSV (scene_id,im_id,obj_id,...)")
    parser.add_argument("--split", default="test", help="split folder (default: test)")
    parser.add_argument(
        "--targets",
        type=Path,
        default=None,
        help="targets JSON file (default: DATASET/test_targets_bop19.json, else every object "
        "seen at least 10%% in an image)",
    )
    parser.add_argument(
        "--metrics",
        default="vsd,mssd,mspd",
        help="comma-separated subset of vsd,mssd,mspd (default: all three)",
    )
    parser.add_argument(
        "--json", type=Path, default=None, help="report path (default: RESULTS_scores.json)"
    )
    parser.add_argument(
        "--run-baseline",
        action="store_true",
        help="first predict with the classic baseline and write its results to RESULTS",
    )
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="with --run-baseline: replace RESULTS when it exists",
    )


def format_table(report: dict[str, Any]) -> str:
    """The per-object and overall table of a report from ``evaluate_bop``.

    Example:
        >>> rep = {"metrics": ["mssd"], "AR_MSSD": 0.5, "AR": 0.5, "num_targets": 2,
        ...        "per_object": {"1": {"AR_MSSD": 0.5, "AR": 0.5, "num_targets": 2}}}
        >>> print(format_table(rep))
        object  targets  AR_MSSD      AR
             1        2    0.500   0.500
           all        2    0.500   0.500
    """
    cols = [f"AR_{m.upper()}" for m in report["metrics"]] + ["AR"]
    head = f"{'object':>6}  {'targets':>7}" + "".join(f"  {c:>6}" for c in cols)
    lines = [head]
    rows = [(k, v) for k, v in report["per_object"].items()]
    rows.append(("all", {**{c: report[c] for c in cols}, "num_targets": report["num_targets"]}))
    for name, row in rows:
        vals = "".join(f"  {row[c]:>{max(6, len(c))}.3f}" for c in cols)
        lines.append(f"{name:>6}  {row['num_targets']:>7d}{vals}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Evaluate (after predicting with the baseline when asked), print, write JSON."""
    from poseflow.cli.common import LOG, check_writable, show_progress
    from poseflow.data.object_folder import check_dataset
    from poseflow.errors import MissingFileError, OutputExistsError, UsageError
    from poseflow.eval.evaluate import METRICS, evaluate_bop

    metrics = tuple(m.strip() for m in args.metrics.split(",") if m.strip())
    unknown = [m for m in metrics if m not in METRICS]
    if unknown or not metrics:
        raise UsageError(f"--metrics takes a subset of {','.join(METRICS)}, got {args.metrics!r}")
    check_dataset(args.dataset, args.split)
    results: Path = args.results
    if args.run_baseline:
        if results.exists() and not args.overwrite:
            raise OutputExistsError(
                f"{results} exists; --run-baseline would replace it: pass --overwrite, or give "
                "another RESULTS path"
            )
        check_writable(results, flag="RESULTS")
    elif not results.is_file():
        raise MissingFileError(
            f"results file {results} does not exist: write one with `poseflow predict`, or pass "
            "--run-baseline to predict with the classic baseline first"
        )
    out = args.json or results.with_name(results.stem + "_scores.json")
    check_writable(out, flag="--json")
    if args.run_baseline:
        _predict_baseline(args.dataset, args.split, results, progress=show_progress(args))
    LOG.info(f"evaluating {results} on {args.dataset}/{args.split}")
    report = evaluate_bop(
        args.dataset,
        results,
        split=args.split,
        targets=args.targets,
        metrics=metrics,
        progress=show_progress(args),
    )
    print(format_table(report))
    out.write_text(json.dumps(report, indent=2))
    t = report["average_time"]
    if t >= 0:
        print(f"average time per image: {1000 * t:.1f} ms")
    print(f"report written to {out}")
    return 0


def _predict_baseline(root: Path, split: str, out: Path, *, progress: bool) -> None:
    from poseflow.baselines import ClassicBaseline
    from poseflow.data.bop import BOPDataset
    from poseflow.data.object_folder import load_object_models
    from poseflow.eval.results import write_results

    ds = BOPDataset(root, split, load_rgb=False)
    models = load_object_models(root, progress=progress)
    baseline = ClassicBaseline(models)
    results = baseline.predict(ds, progress=progress)
    write_results(out, results)
    print(f"classic baseline: {len(results)} estimates written to {out}")
