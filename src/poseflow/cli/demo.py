"""``poseflow demo``: FunFlow6D end to end on freshly generated scenes, next to the baseline.

1. load the ``small`` FunFlow6D checkpoint shipped with the package (prepared objects included);
2. render a small cluttered test set of the default demo objects (BOP format);
3. estimate every target instance of every image, all instances of an image in one batch, with
   the paper's per-stage timing;
4. run the classic baseline (FPFH + RANSAC + ICP) on the same images and masks;
5. score both with the BOP 2019 Average Recall and write results, timing and overlay pictures.

``poseflow demo registration`` runs the registration stage alone against Open3D.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from poseflow.cli.common import (
    add_device_argument,
    add_model_argument,
    add_seed_argument,
    positive_int,
)

__all__ = ["DESCRIPTION", "FORMATTER", "HELP", "add_arguments", "run", "write_timing_chart"]

#: ``demo``'s line in ``poseflow --help``.
HELP = "estimate poses on generated scenes and compare with the classic baseline"

#: What ``poseflow demo --help`` says (plain text: the module docstring is reStructuredText).
DESCRIPTION = """\
Estimate object poses on freshly generated scenes and compare with the classic baseline:

  1. load the small FunFlow6D model shipped with poseflow (its prepared objects included);
  2. render a few cluttered test images of the three demo objects (a BOP dataset);
  3. estimate every target instance, all instances of an image in one batch, timed per stage;
  4. run the classic baseline (FPFH + RANSAC + ICP) on the same images and masks;
  5. score both with the BOP 2019 Average Recall; write the results, the timing and overlays.

The timing chart (timing.png) needs matplotlib (pip install 'poseflow[viz]'); without it the
demo skips the chart and says so.

`poseflow demo registration` runs the registration stage alone against Open3D."""

#: :data:`DESCRIPTION` is shown as written.
FORMATTER = argparse.RawDescriptionHelpFormatter


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options of ``poseflow demo`` (:func:`run`) and its ``demo registration``."""
    parser.add_argument("--out", default="demo_output", help="folder for everything written")
    parser.add_argument("--images", type=positive_int, default=6, help="test images to generate")
    add_seed_argument(parser, draws="the scenes and the model")
    add_model_argument(parser, default="demo", without="demo")
    add_device_argument(parser)
    parser.add_argument("--no-baseline", action="store_true", help="skip the classic baseline")
    parser.add_argument("--no-overlays", action="store_true", help="write no overlay pictures")
    _add_registration_parser(parser.add_subparsers(dest="demo", metavar="{registration}"))


def _add_registration_parser(subparsers: argparse._SubParsersAction) -> None:
    """Register ``demo registration`` (:func:`poseflow.cli.registration_demo.run`)."""
    parser = subparsers.add_parser(
        "registration",
        help="recover generated object poses with poseflow and Open3D, and compare",
        description=(
            "Registration demo: batched RANSAC-Procrustes + coarse-to-fine ICP on generated "
            "correspondences with outliers; errors against the true poses and time against "
            "Open3D on the same data."
        ),
    )
    parser.add_argument("--instances", type=int, default=8, help="objects (batch size)")
    parser.add_argument("--points", type=int, default=1000, help="correspondences per object")
    parser.add_argument("--model-points", type=int, default=5000, help="model cloud size")
    parser.add_argument("--outliers", type=float, default=0.4, help="fraction of wrong pairs")
    parser.add_argument("--noise", type=float, default=0.0005, help="depth noise std, metres")
    parser.add_argument(
        "--flow-noise", type=float, default=0.004, help="noise std of the predictions, metres"
    )
    parser.add_argument("--iterations", type=int, default=1000, help="RANSAC hypotheses")
    add_seed_argument(parser, draws="the generated scenes and RANSAC")
    parser.add_argument("--no-open3d", action="store_true", help="skip the Open3D comparison")
    parser.set_defaults(run=_run_registration)


def _run_registration(args: argparse.Namespace) -> int:
    from poseflow.cli.registration_demo import run as run_registration

    return run_registration(args)


def write_timing_chart(timer: Any, path: Path, *, title: str | None = None) -> bool:
    """Draw the timer's stage breakdown to ``path``; without matplotlib, say so and skip it.

    The chart has one bar per stage, longest first, each named with its ms per image and its
    share of the total (:meth:`~poseflow.eval.StageTimer.plot`).

    Args:
        timer: the :class:`~poseflow.eval.StageTimer`.
        path: the PNG to write.
        title: what was timed, for the chart's title (e.g. ``FunFlow6D``).

    Returns:
        Whether the chart was written.
    """
    from poseflow.cli.common import LOG
    from poseflow.errors import MissingDependencyError

    try:
        timer.plot(path, title=title)
    except MissingDependencyError:
        LOG.info(
            f"note: {path.name} skipped: the chart needs matplotlib (pip install 'poseflow[viz]')"
        )
        return False
    return True


def run(args: argparse.Namespace) -> int:
    """Run the pose demo; prints the AR table and the timing breakdown.

    With ``--threads N`` on the CPU the images are estimated in N processes of one thread each
    (:func:`~poseflow.cli.common.image_workers`).
    """
    from poseflow.cli.common import image_workers, resolve_device

    with image_workers(resolve_device(args.device)) as workers:
        return _run(args, workers)


def _run(args: argparse.Namespace, workers: int) -> int:
    """The demo with its images estimated in ``workers`` processes."""
    import torch

    from poseflow.cli.common import (
        LOG,
        check_writable,
        load_model,
        resolve_device,
        resolve_model,
        show_progress,
    )
    from poseflow.data.synthetic import generate_dataset
    from poseflow.eval import evaluate_bop

    start = time.perf_counter()
    out = check_writable(args.out, folder=True)
    progress = show_progress(args)
    torch.manual_seed(args.seed)

    model_dir = resolve_model(args.model)
    device = resolve_device(args.device)
    LOG.info(f"[1/5] loading FunFlow6D from {model_dir}")
    model = load_model(model_dir, device=device)

    LOG.info(f"[2/5] rendering {args.images} test images of the demo objects")
    root = generate_dataset(
        out / "dataset",
        num_train_images=0,
        num_test_images=args.images,
        seed=args.seed,
        progress=progress,
        overwrite=True,  # the demo's own folder, made again on every run
        workers=workers,
    )
    models = _prepared(model, model_dir, root, out, progress)

    LOG.info("[3/5] FunFlow6D: estimating every target instance")
    funflow, timer, written = _predict_funflow(
        model, root, out, seed=args.seed, progress=progress, workers=workers
    )
    reports = {"FunFlow6D": evaluate_bop(root, funflow)}
    times = {"FunFlow6D": funflow.average_time()}
    if not args.no_baseline:
        LOG.info("[4/5] classic baseline: FPFH + RANSAC + ICP on the same masks")
        base = _predict_baseline(
            models, root, out, seed=args.seed, progress=progress, workers=workers
        )
        written.append("baseline.csv")
        reports["baseline"] = evaluate_bop(root, base)
        times["baseline"] = base.average_time()
    else:
        LOG.info("[4/5] classic baseline skipped")

    LOG.info("[5/5] scoring")
    _print_scores(reports, times, timer)
    if not args.no_overlays:
        _write_overlays(out / "overlays", root, models, funflow, workers)
        written.append("overlays/")
    print(f"\nwrote {out}/{', '.join(written)} in {time.perf_counter() - start:.0f} s")
    return 0


def _prepared(model: Any, model_dir: Path, root: Path, out: Path, progress: bool) -> dict:
    """Prepare the objects of ``root``'s models/ (from the model's cache); returns the models.

    The objects as the dataset's models/ hold them, as ``poseflow predict`` reads them: the
    prepared objects shipped with the model are keyed by these meshes.
    """
    from poseflow.data.object_folder import load_object_models, object_cache_dir

    models = load_object_models(root, progress=progress)
    shipped = object_cache_dir(model_dir, root)
    cache = shipped if shipped.is_dir() else out / "objects"
    model.prepare_objects(models, cache_dir=cache, progress=progress)
    return models


def _predict_funflow(
    model: Any, root: Path, out: Path, *, seed: int, progress: bool, workers: int
) -> tuple[Any, Any, list[str]]:
    """FunFlow6D's results, its stage timer and the files written (CSV, timing JSON and chart).

    The first image is estimated once before the timed run: its time (one-time kernel
    compilation and allocations included) is printed apart, so that the per-image times, the
    stage table and ``timing.png`` are those of a warm run.
    """
    from poseflow.eval import StageTimer, write_results

    start = time.perf_counter()
    model.predict(root, seed=seed, max_images=1, progress=False)
    first = time.perf_counter() - start
    timer = StageTimer()
    funflow = model.predict(root, seed=seed, timer=timer, progress=progress, workers=workers)
    print(
        f"FunFlow6D: first image {first:.2f} s (one-time set-up included, not in the times "
        f"below); warm: {funflow.average_time():.2f} s per image"
    )
    write_results(out / "funflow6d.csv", funflow)
    timer.to_json(out / "timing.json")
    written = ["funflow6d.csv", "timing.json"]
    if write_timing_chart(timer, out / "timing.png", title="FunFlow6D"):
        written.append("timing.png")
    return funflow, timer, written


def _predict_baseline(
    models: dict, root: Path, out: Path, *, seed: int, progress: bool, workers: int
) -> Any:
    """The classic baseline's results on the same masks, written to ``baseline.csv``."""
    from poseflow.baselines import ClassicBaseline
    from poseflow.eval import write_results
    from poseflow.features import FPFHEncoder

    baseline = ClassicBaseline(models, encoder=FPFHEncoder(), seed=seed)
    base = baseline.predict(root, progress=progress, workers=workers)
    write_results(out / "baseline.csv", base)
    return base


def _print_scores(reports: dict[str, Any], times: dict[str, float], timer: Any) -> None:
    """The AR table of every method, FunFlow6D's per object and its time per stage."""
    from poseflow.cli.eval import format_table

    print("\nBOP 2019 Average Recall (GT visible masks; FunFlow6D timed after a warm-up image)\n")
    print(
        f"{'method':<10}  {'AR':>6}  {'AR_VSD':>6}  {'AR_MSSD':>7}  {'AR_MSPD':>7}  {'s/image':>7}"
    )
    for name, rep in reports.items():
        print(
            f"{name:<10}  {rep['AR']:>7.3f}  {rep['AR_VSD']:>7.3f}  {rep['AR_MSSD']:>7.3f}  "
            f"{rep['AR_MSPD']:>7.3f}  {times[name]:>7.2f}"
        )
    print("\nFunFlow6D per object:")
    print(format_table(reports["FunFlow6D"]))
    breakdown = timer.breakdown()
    print(f"\nFunFlow6D time per image (warm): {breakdown['total_ms']:.0f} ms")
    for stage, ms in breakdown["stages_ms"].items():
        share = breakdown["percent"].get(stage, 0.0)
        print(f"  {stage:<20} {ms:>8.1f} ms  {share:>5.1f}%")


def _write_overlays(folder: Path, root: Path, models: dict, funflow: Any, workers: int) -> None:
    """One overlay picture per test image: FunFlow6D's estimates and the ground truth."""
    from poseflow.data.bop import BOPDataset
    from poseflow.eval import write_result_overlays

    dataset = BOPDataset(root, "test")
    write_result_overlays(
        folder,
        dataset,
        {o: m.mesh for o, m in models.items()},
        funflow,
        images=[(s, i) for s in dataset.scene_ids for i in dataset.scene(s).im_ids],
        method="FunFlow6D",
        workers=workers,
    )
