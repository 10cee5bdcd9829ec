"""FunFlow6D against the classic baseline on a user's own BOP dataset, by the README's recipe.

The recipe a new user follows, end to end, on any BOP folder with ``models/`` (millimetres) and a
test split: ``poseflow synth`` renders training images of the dataset's own meshes (never its
test images), ``poseflow train`` trains FunFlow6D on them (and, with ``--distill-steps``,
``poseflow train --distill-from`` distils it into a one-step sampler), ``poseflow predict``
estimates every target of the test split with the trained model, the classic baseline and their
hybrid under one verification (ground-truth visible masks; ``--methods`` picks), once per seed, and
``poseflow eval`` scores them with the BOP 2019 AR. Prints the AR of each per object (mean and
spread over the seeds), one JSON line and the command. ``--oracle`` adds the column ``oracle``:
per image and object, FunFlow6D's or the baseline's estimates, whichever are closer to the truth
(:func:`~poseflow.eval.closest_results`), the most a choice between the two could give, to read
against the hybrid's.

``--detections`` picks the instances: the split's ground-truth visible masks (``gt``), the
recipe's own detector (``own``: ``poseflow train-detector`` on the synth images, into
``MODEL/detector``, then ``poseflow predict --detections own``; no ground-truth mask or box at
test time) or both (the default; the detector's columns are tagged ``-own``).

``--predict-args`` go to FunFlow6D and the hybrid whole; the baseline, which has no network, takes
them without their ``--set`` of fields other than the verifier's (the verification stays alike).

Everything is written under ``--work`` (default ``runs/unseen/DATASET_NAME``) and reused when
run again, so a second run with other seeds or ``--predict-args`` only predicts and scores.

Run ``python benchmarks/unseen.py ../shared/devbench --threads 2`` (the README recipe: the synth
of 3,200 images, the surface embedding, the detector, the training set's features and the
training; the minutes of each step are printed; then 0.3-2 s per image and estimator). The
recipe learns a surface embedding of the dataset's objects on the synth images
(``--surface-steps``, ``--surface-images``; 0 steps keeps the configuration's descriptor) and
trains FunFlow6D on it, all by ``poseflow onboard`` (the library's command, into ``--work``);
``--threads`` sets the synth's processes, the embedding's threads, the processes that compute
the training set's features and the flow network's threads.

``--quick`` (CI) generates a two-image test split of the demo objects as the "user's dataset"
and trains a few steps on four generated images (with ``--oracle`` when both estimators run): it
checks that the recipe runs, not its accuracy.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import statistics
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import torch

from poseflow.cli import main as poseflow
from poseflow.eval import closest_results, write_results

REPO = Path(__file__).resolve().parents[1]
METRICS = ("AR", "AR_VSD", "AR_MSSD", "AR_MSPD")
METHODS = ("funflow6d", "baseline", "hybrid")


def _run(command: list[str]) -> None:
    print("$ poseflow " + " ".join(command), flush=True)
    if poseflow(command) != 0:
        sys.exit(f"poseflow {command[0]} failed")


def _recipe(args: argparse.Namespace, dataset: Path, work: Path) -> Path:
    """``poseflow onboard`` of the dataset's meshes into ``work`` (then the distillation).

    Returns the model folder; the onboarding prints each phase's minutes.
    """
    threads = [] if args.threads is None else ["--threads", str(args.threads)]
    detector_steps = 0 if args.detections == "gt" else args.detector_steps
    _run([
        "onboard", str(dataset), "--out", str(work), "--mesh-scale", str(args.mesh_scale),
        "--images", str(args.train_images), "--seed", str(args.synth_seed),
        "--surface-steps", str(args.surface_steps), "--surface-images", str(args.surface_images),
        "--detector-steps", str(detector_steps), "--steps", str(args.steps),
        "--config", str(args.config), "--train-args", args.train_args, "--calibration-images",
        str(args.calibration_images), "--no-progress", *threads,
    ])  # fmt: skip
    model = work / "model"
    if not args.distill_steps:
        return model
    one_step = work / "run_1step"
    if not (one_step / "model" / "model.safetensors").is_file():
        with _minutes("distillation"):
            _run([
                "train", str(work / "train_data"), "--out", str(one_step), "--distill-from",
                str(model), "--steps", str(args.distill_steps), "--batch-size", "16", "--lr",
                str(args.distill_lr), "--ema-decay", "0.995", "--device", "cpu", "--no-progress",
            ])  # fmt: skip
    return one_step / "model"


@contextlib.contextmanager
def _minutes(step: str) -> Iterator[None]:
    """Print the wall-clock minutes of one step of the recipe."""
    start = time.perf_counter()
    yield
    print(f"recipe: {step} took {(time.perf_counter() - start) / 60:.1f} min", flush=True)


def _baseline_args(extra: list[str]) -> list[str]:
    """``extra`` without its ``--set`` of FunFlow6D's fields: the baseline has only a verifier."""
    out, rest = [], iter(extra)
    for arg in rest:
        value = next(rest, "") if arg == "--set" else None
        if value is None:
            out.append(arg)
        elif value.split("=")[0].split(".")[0] == "verifier":
            out += [arg, value]
    return out


def _score(dataset: Path, csv: Path) -> dict:
    report_path = csv.with_suffix(".json")
    _run(["eval", str(dataset), str(csv), "--json", str(report_path)])
    return json.loads(report_path.read_text())


def _summary(reports: list[dict]) -> dict:
    """Mean and spread (half the range) of each figure over the seeds' reports."""

    def stats(values: list[float]) -> dict:
        return {
            "mean": round(statistics.fmean(values), 4),
            "spread": round((max(values) - min(values)) / 2, 4),
        }

    out = {k: stats([r[k] for r in reports]) for k in METRICS}
    objects = sorted(reports[0]["per_object"], key=int)
    out["per_object"] = {
        o: {k: stats([r["per_object"][o][k] for r in reports]) for k in METRICS} for o in objects
    }
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", nargs="?", help="BOP dataset folder (models/ in mm, test/)")
    parser.add_argument("--work", default=None, help="output folder (default runs/unseen/NAME)")
    parser.add_argument("--config", default=str(REPO / "configs" / "learned_small.json"))
    parser.add_argument("--train-images", type=int, default=3200)
    parser.add_argument("--steps", type=int, default=10000)
    parser.add_argument(
        "--distill-steps",
        type=int,
        default=0,
        help="then distil the model into a one-step sampler in this many steps (0: not); "
        "its results are tagged 1step (--train-args apply to the teacher only)",
    )
    parser.add_argument("--distill-lr", type=float, default=2e-4)
    parser.add_argument(
        "--surface-steps",
        type=int,
        default=10000,
        help="steps of the surface embedding of the dataset's objects, learned on the synth images "
        "before FunFlow6D is trained on it (0: train on the shipped descriptor)",
    )
    parser.add_argument(
        "--surface-images",
        type=int,
        default=1600,
        help="synth images the surface embedding learns from (0: all)",
    )
    parser.add_argument(
        "--threads",
        type=int,
        default=None,
        help="CPU threads of the recipe: the synth's and the training features' processes, the "
        "surface embedding's and the flow network's threads (default: $OMP_NUM_THREADS if set, "
        "else 1)",
    )
    parser.add_argument("--mesh-scale", type=float, default=0.001, help="model units to metres")
    parser.add_argument("--synth-seed", type=int, default=1)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="predict seeds")
    parser.add_argument("--max-images", type=int, default=None, help="test images per run")
    parser.add_argument("--train-args", default="", help="more `poseflow train` flags, one string")
    parser.add_argument(
        "--predict-args", default="", help="more `poseflow predict` flags, one string"
    )
    parser.add_argument("--tag", default="", help="suffix of the result files of this setting")
    parser.add_argument(
        "--methods", nargs="+", choices=METHODS, default=list(METHODS), help="estimators to run"
    )
    parser.add_argument(
        "--oracle",
        action="store_true",
        help="also score the per-target closer of FunFlow6D's and the baseline's estimates",
    )
    parser.add_argument(
        "--detections",
        choices=["gt", "own", "both"],
        default="both",
        help="the instances: ground-truth visible masks, the recipe's own detector "
        "(`poseflow train-detector` on the synth images, `predict --detections own`), or both "
        "(default; results of the detector's are tagged -own)",
    )
    parser.add_argument(
        "--detector-steps", type=int, default=4000, help="training steps of the detector"
    )
    parser.add_argument(
        "--calibration-images",
        type=int,
        default=80,
        help="renders `valid` is calibrated on (onboard's last phase; 0: not calibrated)",
    )
    parser.add_argument("--quick", action="store_true", help="tiny generated dataset (CI)")
    args = parser.parse_args()
    if args.oracle and not {"funflow6d", "baseline"} <= set(args.methods):
        parser.error("--oracle needs funflow6d and baseline among --methods")
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        if args.quick:
            dataset = Path(tmp) / "user_dataset"
            _run(["synth", str(dataset), "--train", "0", "--test", "2", "--seed", "5",
                  "--width", "320", "--height", "240", "--no-progress"])  # fmt: skip
            args.train_images, args.steps, args.seeds = 4, 20, [0]
            args.distill_steps = min(args.distill_steps, 5)
            args.surface_steps = min(args.surface_steps, 5)
            args.detector_steps = min(args.detector_steps, 3)
            args.calibration_images = min(args.calibration_images, 2)
            args.oracle = {"funflow6d", "baseline"} <= set(args.methods)  # runs it too
            work = Path(tmp) / "work"
        elif args.dataset is None:
            parser.error("give a BOP dataset folder, or --quick")
        else:
            dataset = Path(args.dataset).resolve()
            work = Path(args.work or REPO / "runs" / "unseen" / dataset.name)
        work.mkdir(parents=True, exist_ok=True)
        model = _recipe(args, dataset, work)
        extra = args.predict_args.split()
        if args.max_images is not None:
            extra += ["--max-images", str(args.max_images)]
        sources = {"gt": [""], "own": ["-own"], "both": ["", "-own"]}[args.detections]
        columns = [m + source for source in sources for m in args.methods]
        reports: dict[str, list[dict]] = {c: [] for c in columns}
        for seed in args.seeds:
            csvs = {}
            for source in sources:
                for method in args.methods:
                    tag = args.tag + (
                        "1step" if args.distill_steps and method != "baseline" else ""
                    )
                    name = f"{method}{tag}{source}-seed{seed}_{dataset.name}-test.csv"
                    csv = csvs[method + source] = work / name
                    command = ["predict", str(dataset), "--out", str(csv), "--seed", str(seed)]
                    command += ["--method", method, "--no-progress"]
                    if source:
                        command += ["--detections", "own", "--detector", str(model / "detector")]
                    if method == "baseline":
                        command += _baseline_args(extra)
                    else:
                        command += ["--model", str(model), *extra]
                    _run(command)
                    reports[method + source].append(_score(dataset, csv))
            if args.oracle:
                csv = work / f"oracle{args.tag}-seed{seed}_{dataset.name}-test.csv"
                pair = [csvs["funflow6d" + sources[0]], csvs["baseline" + sources[0]]]
                chosen, counts = closest_results(dataset, pair)
                write_results(csv, chosen)
                print(f"oracle, seed {seed}: FunFlow6D closer for {counts[0]} image-objects, "
                      f"the baseline for {counts[1]}")  # fmt: skip
                reports.setdefault("oracle", []).append(_score(dataset, csv))
                if "oracle" not in columns:
                    columns.append("oracle")
        summary = {m: _summary(r) for m, r in reports.items()}
    summary["dataset"], summary["seeds"] = dataset.name, args.seeds
    summary["distill_steps"] = args.distill_steps
    runs = [summary[m] for m in columns]
    print(f"\n{dataset.name}: AR over seeds {args.seeds} (mean ± half range)")
    print(f"{'object':<10}" + "".join(f"{m:>17}" for m in columns))
    cell = lambda s: f"{s['mean']:>10.3f} ± {s['spread']:.3f}"  # noqa: E731
    for o in runs[0]["per_object"]:
        print(f"{o:<10}" + "".join(cell(r["per_object"][o]["AR"]) for r in runs))
    for k in METRICS:
        print(f"{k:<10}" + "".join(cell(r[k]) for r in runs))
    print(json.dumps(summary))
    print("command:", " ".join([sys.executable, *sys.argv]))


if __name__ == "__main__":
    main()
