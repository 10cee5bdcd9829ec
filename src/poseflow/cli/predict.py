r"""``poseflow predict``: estimate the poses of a BOP split and write the BOP results CSV.

The instances of an image come from its ground-truth visible masks (default) or from a BOP
detection/segmentation file (``--detections``, e.g. the public CNOS or ZebraPose masks); the
images are walked by :func:`poseflow.eval.predict.predict_dataset`, so that all instances of one
image go through one batched :meth:`FunFlow6D.estimate <poseflow.models.FunFlow6D.estimate>`
call. The CSV (:func:`poseflow.eval.results.write_results`) holds one line per valid estimate,
poses in millimetres with ``R`` row-major, and the wall-clock seconds of the image (image loading
excluded; plus the detector's reported time when the detections file gives one, as the BOP
challenge counts it). ``--method baseline`` runs the
classic FPFH/RANSAC/ICP baseline (:class:`poseflow.baselines.ClassicBaseline`) instead and needs
no model; ``--method hybrid`` (:class:`poseflow.models.Hybrid`) pools the model's hypotheses and
the baseline's pose of each instance into one verification, every candidate scored on the
verifier's full grid (:func:`poseflow.models.full_grid_ranking`, unless ``--set`` names
``verifier.coarse_crop_size``). ``--timing`` writes the per-stage
breakdown of :class:`poseflow.eval.timing.StageTimer`, in wall-clock time or, with
``--clock cpu``, in the process's CPU time.

Both estimators verify their poses by rendering and comparing (:mod:`poseflow.verify`) unless
``--no-verify`` is given, whatever the model's configuration says (the verifier is training-free,
so it applies to checkpoints saved before it existed too); the CSV's scores are then the
verifier's.

Started by ``torchrun`` (``WORLD_SIZE`` above 1), the command splits the images over the
processes (:mod:`poseflow.eval.distributed`): each estimates its share on its own device
(``cuda:LOCAL_RANK``, or the CPU with its share of the cores) and rank 0 writes one CSV, the same
rows in the same order as one process writes, and one timing JSON over all images. Every image's
random draws are seeded from ``--seed`` and its ids, so that its estimate does not depend on the
images before it. A failed process stops the others, and no CSV is written.

Example::

    poseflow predict data/synth --model runs/small/model --out results/ff_synth-test.csv
    poseflow predict data/lmo --model runs/small/model --detections cnos_lmo.json \
        --out results/ff_lmo-test.csv --device cuda --timing results/ff_lmo_timing.json
    poseflow predict data/synth --method baseline --out results/base_synth-test.csv
    poseflow predict data/synth --method baseline --no-verify --out results/base_nv-test.csv
    poseflow predict data/synth --method hybrid --model runs/small/model \
        --out results/hybrid_synth-test.csv
    torchrun --nproc_per_node=4 -m poseflow.cli predict data/lmo --model runs/small/model \
        --device cuda --out results/ff_lmo-test.csv
    poseflow eval data/synth results/ff_synth-test.csv
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from poseflow.cli.common import (
    add_cache_argument,
    add_device_argument,
    add_model_argument,
    add_seed_argument,
    positive_int,
)
from poseflow.cli.options import add_inference_arguments, inference_changes

if TYPE_CHECKING:
    import torch

    from poseflow.eval.distributed import PredictionPart, Ranks
    from poseflow.eval.predict import Estimator
    from poseflow.eval.results import PoseResults

#: The estimators of ``--method``; all but ``baseline`` need a model.
METHODS = ("funflow6d", "baseline", "hybrid")
#: How the overlays' legends name them.
METHOD_LABELS = {"funflow6d": "FunFlow6D", "baseline": "classic baseline", "hybrid": "hybrid"}

__all__ = ["DESCRIPTION", "HELP", "add_arguments", "estimate_split", "run", "select_targets"]


#: ``predict``'s line in ``poseflow --help``.
HELP = "estimate object poses on a BOP split and write a BOP results CSV"

#: What ``poseflow predict --help`` says.
DESCRIPTION = """\
Estimate the pose of every instance of the split's images (ground-truth masks, or the masks of a
BOP detections file) with FunFlow6D or the classic baseline, and write the BOP 2019 results CSV
with per-image times. By default only the instances named by test_targets_bop19.json are estimated
on test splits."""

#: What ``poseflow predict --help`` says after the options.
EPILOG = """\
Several processes: `torchrun --nproc_per_node=K -m poseflow.cli predict ...` (also across machines,
as torchrun allows) splits the images over K processes, each on its own GPU (cuda:LOCAL_RANK) or on
the CPU with its share of the cores (torchrun sets OMP_NUM_THREADS=1 unless it is set); rank 0
writes the same CSV as one process. A failed process stops all of them, and no CSV is written."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options of ``poseflow predict`` (its ``run`` is :func:`run`)."""
    parser.add_argument("dataset", help="BOP dataset folder")
    add_model_argument(parser)
    parser.add_argument("--out", required=True, metavar="CSV", help="results CSV to write")
    parser.add_argument("--split", default="test", help="split folder (default: test)")
    _add_instance_arguments(parser)
    parser.add_argument(
        "--method",
        choices=METHODS,
        default="funflow6d",
        help="estimator: the model, the classic baseline, or both under one verification",
    )
    add_inference_arguments(
        parser,
        set_help="change an inference-time config field of the model (num_hypotheses, "
        "flow_precision, appearance_precision, pose_solver, ransac_*, icp_*, verifier or "
        "verifier.FIELD, ...; with --method baseline: "
        "verifier only, its fields changing the baseline's defaults); VALUE read as JSON, "
        "repeatable",
    )
    parser.add_argument(
        "--max-images",
        type=positive_int,
        default=None,
        metavar="N",
        help="stop after N images (default: all)",
    )
    _add_report_arguments(parser)
    add_cache_argument(parser, without="the model folder")
    add_seed_argument(parser, draws="the noise, sampling and RANSAC")
    add_device_argument(parser)


def _add_instance_arguments(parser: argparse.ArgumentParser) -> None:
    """``--detections``, ``--score-threshold`` and ``--targets`` or ``--all-instances``."""
    parser.add_argument(
        "--detections",
        default=None,
        metavar="JSON|own",
        help="the instances: a BOP detections JSON with COCO-RLE segmentations, or own for the "
        "detector of the model folder (MODEL_DIR/detector, or --detector) run on every image "
        "(default: the split's ground-truth visible masks)",
    )
    parser.add_argument(
        "--detector",
        default=None,
        metavar="DIR",
        help="with --detections own: this detector folder instead of MODEL_DIR/detector",
    )
    parser.add_argument(
        "--score-threshold",
        type=float,
        default=0.0,
        help="drop detections scoring below this (default: 0)",
    )
    targets = parser.add_mutually_exclusive_group()
    targets.add_argument(
        "--targets",
        default=None,
        metavar="JSON",
        help="targets JSON (default: DATASET/test_targets_bop19.json on test splits)",
    )
    targets.add_argument(
        "--all-instances", action="store_true", help="ignore the targets: every instance"
    )


def _add_report_arguments(parser: argparse.ArgumentParser) -> None:
    """``--timing``, ``--overlays`` and ``--clock``."""
    parser.add_argument(
        "--timing", default=None, metavar="JSON", help="write the stage breakdown JSON here"
    )
    parser.add_argument(
        "--overlays",
        default=None,
        metavar="DIR",
        help="write one picture per image here: the estimates outlined with a legend (method, "
        "score), the ground truth outlined in green where the split has it",
    )
    parser.add_argument(
        "--clock",
        choices=("wall", "cpu"),
        default="wall",
        help="what --timing measures: wall-clock time, or this process's CPU time (steadier on "
        "a busy machine; with one thread, the cost of each stage)",
    )


def select_targets(
    dataset: Any,
    *,
    targets: str | Path | bool | None = None,
    detections: Sequence[Any] | None = None,
) -> list[Any]:
    """The targets to estimate: from a targets file, or every instance of the split.

    Args:
        dataset: the :class:`~poseflow.data.bop.BOPDataset` of the split.
        targets: a targets JSON, True for ``test_targets_bop19.json`` in the dataset folder, or
            None for every instance: every ground-truth instance, or with ``detections`` every
            detection.
        detections: the detections that replace the ground-truth masks, if any.

    Returns:
        :class:`~poseflow.eval.recall.Target` records sorted by scene, image and object.
    """
    from poseflow.data.bop import read_test_targets
    from poseflow.eval.recall import Target

    if targets:
        path = dataset.root / "test_targets_bop19.json" if targets is True else Path(targets)
        found = [
            Target(t.scene_id, t.im_id, t.obj_id, t.inst_count) for t in read_test_targets(path)
        ]
    else:
        counts: dict[tuple[int, int, int], int] = {}
        if detections is not None:
            for d in detections:
                key = (d.scene_id, d.im_id, d.obj_id)
                counts[key] = counts.get(key, 0) + 1
        else:
            for s in dataset.scene_ids:
                scene = dataset.scene(s)
                for i in scene.im_ids:
                    for gt in scene.gt_of(i):
                        key = (s, i, gt.obj_id)
                        counts[key] = counts.get(key, 0) + 1
        found = [Target(s, i, o, n) for (s, i, o), n in counts.items()]
    return sorted(found, key=lambda t: (t.scene_id, t.im_id, t.obj_id))


def _detections(
    args: argparse.Namespace, dataset: Any, targets: Any, progress: bool = False
) -> list[Any]:
    """Detections kept by the threshold and the targets, minus masks of the wrong size.

    ``--detections own`` runs the detector (:func:`_own_detections`) first.

    Raises:
        BOPFormatError: the detections name objects the dataset has no model of.
        UsageError: ``--score-threshold`` leaves none of them.
    """
    from PIL import Image

    from poseflow.cli.detect import check_score_threshold
    from poseflow.data.bop import BOPDataWarning, BOPDetectionDataset, read_detections
    from poseflow.errors import BOPFormatError

    if args.detections == "own":
        found = _own_detections(args, dataset, targets, progress)
    else:
        found = read_detections(args.detections)
    strangers = sorted({d.obj_id for d in found} - set(dataset.models_info()))
    if strangers:
        raise BOPFormatError(
            f"the detections name objects {strangers} that {dataset.root} has no model of: are "
            "they for another dataset?"
        )
    check_score_threshold(found, args.score_threshold)
    dets = BOPDetectionDataset(
        dataset.root,
        args.split,
        found,
        score_threshold=args.score_threshold,
        targets=targets or None,
    ).detections
    sizes: dict[tuple[int, int], tuple[int, int]] = {}
    kept = []
    for d in dets:
        key = (d.scene_id, d.im_id)
        if key not in sizes:
            with Image.open(dataset.scene(d.scene_id).depth_path(d.im_id)) as im:
                sizes[key] = (im.height, im.width)
        size = tuple(int(x) for x in d.segmentation["size"]) if d.segmentation else None
        if size != sizes[key]:
            warnings.warn(
                f"detection of obj {d.obj_id} in scene {d.scene_id} image {d.im_id}: mask "
                f"{size} differs from the image {sizes[key]}; skipped",
                BOPDataWarning,
                stacklevel=2,
            )
            continue
        kept.append(d)
    return kept


def _own_detections(
    args: argparse.Namespace, dataset: Any, targets: Any, progress: bool
) -> list[Any]:
    """The detector's detections in the images to estimate (the targets' first ``--max-images``)."""
    from poseflow.cli.detect import load_detector
    from poseflow.detect import detect_dataset

    detector, _ = load_detector(
        args.detector, args.model, needs="--detections own needs a detector"
    )
    wanted = select_targets(dataset, targets=targets)
    images = sorted({(t.scene_id, t.im_id) for t in wanted})[: args.max_images]
    return detect_dataset(detector, dataset.root, args.split, images=images, progress=progress)


def _targets_option(args: argparse.Namespace, root: Path) -> str | bool | None:
    if args.all_instances:
        return None
    if args.targets is not None:
        return args.targets
    found = (root / "test_targets_bop19.json").is_file()
    return True if found and args.split.startswith("test") else None


def _cache_dir(args: argparse.Namespace, root: Path) -> Path | None:
    import os

    from poseflow.cli.common import LOG
    from poseflow.data.object_folder import object_cache_dir

    base = Path(args.cache if args.cache is not None else args.model)
    probe = base
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if not os.access(probe, os.W_OK):
        LOG.info("note: %s is not writable; prepared objects are not cached", base)
        return None
    return object_cache_dir(base, root)


def run(args: argparse.Namespace) -> int:
    """Estimate, write the CSV (and the timing JSON); prints a summary; returns 0.

    Under ``torchrun`` every process estimates its share of the images and rank 0 writes the
    merged outputs (:mod:`poseflow.eval.distributed`).
    """
    from poseflow.cli.common import check_writable, image_workers, resolve_device
    from poseflow.data.object_folder import check_dataset
    from poseflow.eval.distributed import join_ranks

    root = check_dataset(args.dataset, args.split)
    check_writable(args.out)
    if args.timing is not None:
        check_writable(args.timing, flag="--timing")
    if args.overlays is not None:
        check_writable(args.overlays, flag="--overlays", folder=True)
    device = resolve_device(args.device)
    changes = inference_changes(args, method=args.method)
    ranks = join_ranks(device)
    if ranks is None:
        with image_workers(device) as workers:
            _report(args, _predict(args, root, device, changes, workers=workers), workers)
        return 0
    with ranks:
        ranks.run(
            lambda: _predict(args, root, ranks.device, changes, ranks),
            lambda merged: _report(args, merged),
        )
    return 0


def estimate_split(argv: Sequence[str]) -> tuple[PoseResults, torch.Tensor]:
    """``poseflow predict ARGV`` run in this process, writing nothing.

    For commands that need more of each estimate than the results file holds
    (``poseflow calibrate``). ``--out`` must be given but is not written; the process's thread
    count is used as ``predict``'s ``--threads``.

    Returns:
        ``(results, agreement)``: the results, and each row's agreement of the estimator's
        hypotheses (:class:`~poseflow.eval.predict.PoseEstimate`; NaN where it gives none).
    """
    import torch

    from poseflow.cli import build_parser
    from poseflow.cli.common import image_workers, resolve_device
    from poseflow.data.object_folder import check_dataset

    args = build_parser().parse_args(["predict", *argv])
    root = check_dataset(args.dataset, args.split)
    device = resolve_device(args.device)
    rows: list[torch.Tensor] = []

    def keep(scene_id: int, im_id: int, obj_ids: list[int], estimate: Any) -> None:
        ok = estimate.valid
        shares = estimate.agreement
        if shares is None:
            shares = torch.full(ok.shape, float("nan"), dtype=torch.float64)
        rows.append(shares.double()[ok])

    with image_workers(device) as workers:
        changes = inference_changes(args, method=args.method)
        part = _predict(args, root, device, changes, workers=workers, after_image=keep)
    agreement = torch.cat(rows) if rows else torch.zeros(0, dtype=torch.float64)
    return part.results, agreement


def _predict(
    args: argparse.Namespace,
    root: Path,
    device: Any,
    changes: dict[str, Any],
    ranks: Ranks | None = None,
    *,
    workers: int = 1,
    after_image: Any = None,
) -> PredictionPart:
    """Estimate the images (this rank's share under ``torchrun``) in ``workers`` processes.

    ``after_image`` is also called as :func:`~poseflow.eval.predict.predict_dataset` calls it.
    """
    import time

    from poseflow.cli.common import load_model, resolve_model, show_progress
    from poseflow.data.bop import BOPDataset
    from poseflow.eval.distributed import PredictionPart, image_seed
    from poseflow.eval.predict import predict_dataset
    from poseflow.eval.timing import StageTimer

    show = show_progress(args) and (ranks is None or ranks.is_main)
    model = None
    if args.method != "baseline":
        args.model = str(resolve_model(args.model))
        model = load_model(args.model, device=device, inference=changes)
        if args.method == "hybrid" and not _sets_coarse_grid(changes):
            from poseflow.models import full_grid_ranking

            model.config = full_grid_ranking(model.config)
    ds = BOPDataset(root, args.split)
    wanted = _targets_option(args, root)
    detections = _detections(args, ds, wanted, show) if args.detections is not None else None
    targets = select_targets(ds, targets=wanted, detections=detections)
    targets, images = _share(targets, args, device, ranks)
    objects = _objects(ds, root, [t for t in targets if (t.scene_id, t.im_id) in images], show)
    from poseflow.render import import_open3d

    if importlib.util.find_spec("open3d") is not None:  # import it before any clock starts
        import_open3d("prediction")  # a missing system library: the error names its package
    estimator, generator = _estimator(
        args, root, model, objects, device, changes, progress=show, workers=workers
    )
    instances = 0

    def count(scene_id: int, im_id: int, obj_ids: list[int], estimate: Any) -> None:
        nonlocal instances
        instances += len(obj_ids)
        if after_image is not None:
            after_image(scene_id, im_id, obj_ids, estimate)

    def before_image(scene_id: int, im_id: int) -> None:
        if ranks is not None:
            ranks.check_peers()  # another rank failed: stop here
        if generator is not None:
            generator.manual_seed(image_seed(args.seed, scene_id, im_id))

    timer = StageTimer(clock=time.process_time if args.clock == "cpu" else time.perf_counter)
    results = predict_dataset(
        estimator,
        ds,
        split=args.split,
        object_ids=sorted(objects),
        targets=targets,
        detections=detections,
        load_rgb=model is not None or args.verify,
        max_images=args.max_images,
        timer=timer,
        progress=show,
        before_image=before_image,
        after_image=count,
        workers=workers,
    )
    if detections:
        results = _add_detection_time(results, detections)
    config = model.config.to_dict() if model is not None else None
    return PredictionPart(results, timer, instances, [str(device)], [timer.num_images], config)


def _share(
    targets: list[Any], args: argparse.Namespace, device: Any, ranks: Ranks | None
) -> tuple[list[Any], set[tuple[int, int]]]:
    """The targets and the images to estimate: the first ``--max-images`` images of the split.

    Under ``torchrun`` this rank's share of them, balanced by instances
    (:meth:`~poseflow.eval.distributed.Ranks.shard_targets`).
    """
    from poseflow.cli.common import LOG

    images = set(sorted({(t.scene_id, t.im_id) for t in targets})[: args.max_images])
    if ranks is None:
        return targets, images
    targets = ranks.shard_targets([t for t in targets if (t.scene_id, t.im_id) in images])
    images = {(t.scene_id, t.im_id) for t in targets}
    LOG.info(
        "rank %d of %d: %d images on %s (%d threads)",
        ranks.rank,
        ranks.world_size,
        len(images),
        device,
        ranks.threads,
    )
    return targets, images


def _sets_coarse_grid(changes: dict[str, Any]) -> bool:
    """Whether ``--set`` chose the verifier's coarse grid (the hybrid's default is the full)."""
    verifier = changes.get("verifier")
    return "verifier.coarse_crop_size" in changes or (
        isinstance(verifier, dict) and "coarse_crop_size" in verifier
    )


def _objects(ds: Any, root: Path, targets: list[Any], progress: bool) -> dict[int, Any]:
    """The models of the targets' objects; the instances of an object without one are skipped."""
    from poseflow.data.object_folder import load_object_models

    infos = ds.models_info()
    needed = sorted({t.obj_id for t in targets})
    missing = [o for o in needed if o not in infos]
    if missing:
        warnings.warn(f"objects {missing} have no model; their instances are skipped", stacklevel=1)
    return load_object_models(root, obj_ids=[o for o in needed if o in infos], progress=progress)


def _estimator(
    args: argparse.Namespace,
    root: Path,
    model: Any,
    objects: dict[int, Any],
    device: Any,
    changes: dict[str, Any],
    *,
    progress: bool,
    workers: int,
) -> tuple[Estimator | None, torch.Generator | None]:
    """The estimator of ``--method``, prepared, and the generator it draws from (None: baseline).

    Every image's draws are seeded from ``--seed`` and its ids (reseeding the generator before
    each image): its estimate does not depend on the images before it, so that any split of the
    images over processes gives the same results. The classic baseline seeds each instance.
    """
    import torch

    from poseflow.baselines import ClassicBaseline

    if model is None:
        if not objects:  # without any, no image reaches the estimator
            return None, None
        baseline = ClassicBaseline(objects, verifier=changes["verifier"], seed=args.seed)
        baseline.prepare(workers=workers)  # now, so that no image's time includes them
        return baseline.estimator(), None
    model.prepare_objects(objects, cache_dir=_cache_dir(args, root), progress=progress)
    generator = torch.Generator(device=device)
    if args.method != "hybrid":
        return model.estimator(generator=generator), generator
    from poseflow.models import Hybrid

    baseline = ClassicBaseline(objects, verifier=None, seed=args.seed)
    baseline.prepare(workers=workers)  # its banks now, so that no image's time includes them
    return Hybrid(model, baseline).estimator(generator=generator), generator


def _report(args: argparse.Namespace, part: PredictionPart, workers: int = 1) -> None:
    """Write the CSV (and the timing JSON) of the whole run; print a summary.

    ``workers``: the processes that estimated the images and draw the overlays.
    """
    from poseflow.eval.results import write_results

    results, timer, processes = part.results, part.timer, len(part.devices)
    device = ", ".join(dict.fromkeys(part.devices))  # each device once, in rank order
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_results(out, results)
    print(
        f"{args.method}{' + verification' if args.verify else ''}: {timer.num_images} images, "
        f"{part.instances} instances, {len(results)} poses "
        f"({part.instances - len(results)} invalid) written to {out}"
        + (f" by {processes} processes" if processes > 1 else "")
        + (f" by {workers} worker processes" if workers > 1 else "")
    )
    mean = results.average_time()
    if mean >= 0:
        print(f"mean time per image: {1000 * mean:.1f} ms on {device}")
    if args.overlays is not None and len(results):
        _write_overlays(args, results, workers)
    if args.timing is not None:
        report = {
            "method": args.method,
            "verification": args.verify,
            "device": device,
            "clock": args.clock,
        }
        if processes > 1:
            report.update(ranks=processes, devices=part.devices, images_per_rank=part.images)
        report.update(timer.breakdown())
        if part.config is not None:
            report["config"] = part.config
        Path(args.timing).parent.mkdir(parents=True, exist_ok=True)
        Path(args.timing).write_text(json.dumps(report, indent=2))
        print(f"stage timing written to {args.timing}")


def _write_overlays(args: argparse.Namespace, results: Any, workers: int) -> None:
    """One overlay picture per image with estimates, in ``args.overlays``."""
    from poseflow.cli.common import show_progress
    from poseflow.data.bop import BOPDataset
    from poseflow.data.object_folder import load_object_models
    from poseflow.eval.overlay import write_result_overlays

    ids = sorted({int(o) for o in results.obj_ids.tolist()})
    objects = load_object_models(Path(args.dataset), obj_ids=ids, progress=False)
    written = write_result_overlays(
        args.overlays,
        BOPDataset(args.dataset, args.split),
        {o: m.mesh for o, m in objects.items()},
        results,
        method=METHOD_LABELS[args.method],
        progress=show_progress(args),
        workers=workers,
    )
    print(f"{len(written)} overlay pictures written to {args.overlays}")


def _add_detection_time(results: Any, detections: Any) -> Any:
    """``results`` with each image's time raised by the detector's time for it (if known)."""
    import torch

    from poseflow.eval.results import PoseResults

    extra: dict[tuple[int, int], float] = {}
    for d in detections:
        key = (d.scene_id, d.im_id)
        extra[key] = max(extra.get(key, 0.0), d.time)
    add = [
        extra.get((s, i), 0.0) for s, i in zip(results.scene_ids.tolist(), results.im_ids.tolist())
    ]
    return PoseResults(
        results.scene_ids,
        results.im_ids,
        results.obj_ids,
        results.scores,
        results.poses,
        results.times + torch.tensor(add, dtype=results.times.dtype),
    )
