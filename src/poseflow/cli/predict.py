r"""``poseflow predict``: estimate the poses of a BOP split and write the BOP results CSV.

The instances of an image come from its ground-truth visible masks (default) or from a BOP
detection/segmentation file (``--detections``, e.g. the public CNOS or ZebraPose masks); all
instances of one image go through one batched :meth:`FunFlow6D.estimate
<poseflow.models.FunFlow6D.estimate>` call. The CSV (:func:`poseflow.eval.results.write_results`)
holds one line per valid estimate, poses in millimetres with ``R`` row-major, and the wall-clock
seconds of the image (image loading excluded; plus the detector's reported time when the
detections file gives one, as the BOP challenge counts it). ``--method baseline`` runs the
classic FPFH/RANSAC/ICP baseline (:class:`poseflow.baselines.ClassicBaseline`) instead and needs
no model. ``--timing`` writes the per-stage breakdown of :class:`poseflow.eval.timing.StageTimer`.

Example::

    poseflow predict data/synth --model runs/small/model --out results/ff_synth-test.csv
    poseflow predict data/lmo --model runs/small/model --detections cnos_lmo.json \
        --out results/ff_lmo-test.csv --device cuda --timing results/ff_lmo_timing.json
    poseflow predict data/synth --method baseline --out results/base_synth-test.csv
    poseflow eval data/synth results/ff_synth-test.csv
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from poseflow.cli.common import add_device_argument

__all__ = ["ImageWork", "add_parser", "list_images", "run"]


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register the ``predict`` subcommand on ``subparsers``; its ``run`` is :func:`run`."""
    parser = subparsers.add_parser(
        "predict",
        help="estimate object poses on a BOP split and write a BOP results CSV",
        description=(
            "Estimate the pose of every instance of the split's images (ground-truth masks, or "
            "the masks of a BOP detections file) with FunFlow6D or the classic baseline, and "
            "write the BOP 2019 results CSV with per-image times. By default only the "
            "instances named by test_targets_bop19.json are estimated on test splits."
        ),
    )
    parser.add_argument("dataset", help="BOP dataset folder")
    parser.add_argument(
        "--model",
        default=None,
        metavar="MODEL_DIR",
        help="model folder written by `poseflow train`",
    )
    parser.add_argument("--out", required=True, metavar="CSV", help="results CSV to write")
    parser.add_argument("--split", default="test", help="split folder (default: test)")
    parser.add_argument(
        "--detections",
        default=None,
        metavar="JSON",
        help="BOP detections JSON with COCO-RLE segmentations (default: ground-truth masks)",
    )
    parser.add_argument(
        "--score-threshold", type=float, default=0.0, help="drop detections scoring below this"
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
    parser.add_argument(
        "--method", choices=("funflow6d", "baseline"), default="funflow6d", help="estimator"
    )
    parser.add_argument(
        "--hypotheses",
        type=int,
        default=None,
        metavar="H",
        help="noise samples per instance (model's)",
    )
    parser.add_argument(
        "--steps",
        type=int,
        default=None,
        metavar="K",
        help="integration steps K (default: model's)",
    )
    parser.add_argument(
        "--solver", default=None, help="ODE solver: euler, midpoint, heun, rk4 (model's)"
    )
    parser.add_argument(
        "--max-images", type=int, default=None, metavar="N", help="stop after N images"
    )
    parser.add_argument(
        "--timing", default=None, metavar="JSON", help="write the stage breakdown JSON here"
    )
    parser.add_argument(
        "--cache",
        default=None,
        metavar="DIR",
        help="folder holding prepared objects (objects/); default the model folder",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of noise, sampling, RANSAC")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bars")
    add_device_argument(parser)
    parser.set_defaults(run=run)
    return parser


@dataclass
class ImageWork:
    """The instances to estimate in one image.

    Attributes:
        scene_id: scene id.
        im_id: image id.
        obj_ids: object of each instance.
        sources: per instance, the ground-truth index (int) or the
            :class:`~poseflow.data.bop.Detection` whose mask to use.
        extra_time: seconds to add to the image's time (the detector's), 0 when unknown.
    """

    scene_id: int
    im_id: int
    obj_ids: list[int]
    sources: list[Any]
    extra_time: float = 0.0


def list_images(
    root: str | Path,
    split: str,
    *,
    detections: str | Path | None = None,
    targets: str | Path | bool | None = None,
    score_threshold: float = 0.0,
    max_images: int | None = None,
) -> list[ImageWork]:
    """The images of a split and the instances to estimate in each, in (scene, image) order.

    Args:
        root: the dataset folder.
        split: the split folder.
        detections: a BOP detections file, or None for the ground-truth instances.
        targets: a targets file, True for ``root/test_targets_bop19.json``, or None for all.
        score_threshold: drop detections scoring below this.
        max_images: keep the first N images.

    Returns:
        One :class:`ImageWork` per image with at least one instance.
    """
    from poseflow.data.bop import BOPDataset, BOPDetectionDataset, read_test_targets

    root = Path(root)
    work: dict[tuple[int, int], ImageWork] = {}
    if detections is not None:
        dets = BOPDetectionDataset(
            root, split, detections, score_threshold=score_threshold, targets=targets or None
        ).detections
        for d in dets:
            item = work.setdefault((d.scene_id, d.im_id), ImageWork(d.scene_id, d.im_id, [], []))
            item.obj_ids.append(d.obj_id)
            item.sources.append(d)
            item.extra_time = max(item.extra_time, d.time)
    else:
        ds = BOPDataset(root, split)
        if targets:
            path = root / "test_targets_bop19.json" if targets is True else Path(targets)
            wanted: dict[tuple[int, int], set[int]] | None = {}
            for t in read_test_targets(path):
                wanted.setdefault((t.scene_id, t.im_id), set()).add(t.obj_id)
            keys = sorted(wanted)
        else:
            wanted = None
            keys = [(s, i) for s in ds.scene_ids for i in ds.scene(s).im_ids]
        for s, i in keys:
            objs = None if wanted is None else wanted[(s, i)]
            gts = ds.scene(s).gt_of(i)
            sel = [g for g, gt in enumerate(gts) if objs is None or gt.obj_id in objs]
            if sel:
                work[(s, i)] = ImageWork(s, i, [gts[g].obj_id for g in sel], sel)
    items = [work[k] for k in sorted(work)]
    return items if max_images is None else items[: max(0, max_images)]


def _masks(
    scene: Any, item: ImageWork, shape: tuple[int, int]
) -> tuple[Any, list[int], list[float]]:
    """An image's instance masks ``(n, H, W)`` with the object ids and scores of those loaded.

    The score is the detection's (1 for ground-truth masks); the masks are None when none loaded.
    """
    import torch

    from poseflow.data.bop import BOPDataWarning
    from poseflow.errors import BOPFormatError

    masks, ids, scores = [], [], []
    for obj_id, source in zip(item.obj_ids, item.sources):
        if isinstance(source, int):
            m, score = scene.load_mask(item.im_id, source, visible=True), 1.0
        else:
            try:
                m, score = source.mask(), source.score
            except BOPFormatError as exc:
                warnings.warn(f"{exc}; skipped", BOPDataWarning, stacklevel=2)
                continue
        if tuple(m.shape) != shape:
            warnings.warn(
                f"scene {item.scene_id} image {item.im_id} obj {obj_id}: mask "
                f"{tuple(m.shape)} differs from the image {shape}; skipped",
                BOPDataWarning,
                stacklevel=2,
            )
            continue
        masks.append(m.bool())
        ids.append(obj_id)
        scores.append(float(score))
    return (torch.stack(masks) if masks else None), ids, scores


def _only(item: ImageWork, obj_ids: Any) -> ImageWork:
    """``item`` restricted to the instances of objects in ``obj_ids``."""
    keep = [k for k, o in enumerate(item.obj_ids) if o in obj_ids]
    return ImageWork(
        item.scene_id,
        item.im_id,
        [item.obj_ids[k] for k in keep],
        [item.sources[k] for k in keep],
        item.extra_time,
    )


def _default_targets(args: argparse.Namespace, root: Path) -> str | bool | None:
    if args.all_instances:
        return None
    if args.targets is not None:
        return args.targets
    found = (root / "test_targets_bop19.json").is_file()
    return True if found and args.split.startswith("test") else None


def _load_model(args: argparse.Namespace, device: Any) -> Any:
    from poseflow.errors import ValueRangeError
    from poseflow.flows import get_sampler
    from poseflow.models import FunFlow6D

    if args.model is None:
        raise ValueRangeError(
            "--model MODEL_DIR is needed with --method funflow6d (a folder written by "
            "`poseflow train`), or use --method baseline"
        )
    model = FunFlow6D.load(args.model, device=device)
    changes = {
        k: v
        for k, v in (
            ("num_hypotheses", args.hypotheses),
            ("steps", args.steps),
            ("solver", args.solver),
        )
        if v is not None
    }
    if changes:
        model.config = model.config.replace(**changes)
    get_sampler(model.config.solver, steps=model.config.steps)  # fail before the first image
    return model


def _cache_dir(args: argparse.Namespace, root: Path) -> Path | None:
    import os

    from poseflow.cli.common import object_cache_dir

    base = Path(args.cache if args.cache is not None else args.model)
    probe = base
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if not os.access(probe, os.W_OK):
        print(f"note: {base} is not writable; prepared objects are not cached")
        return None
    return object_cache_dir(base, root)


def run(args: argparse.Namespace) -> int:
    """Estimate, write the CSV (and the timing JSON); prints a summary; returns 0."""
    import torch
    from tqdm.auto import tqdm

    from poseflow.cli.common import check_dataset, load_object_models, resolve_device
    from poseflow.data.bop import BOPDataset
    from poseflow.eval.results import PoseResults, write_results
    from poseflow.eval.timing import StageTimer

    root = check_dataset(args.dataset, args.split)
    device = resolve_device(args.device)
    show = not args.no_progress
    model = _load_model(args, device) if args.method == "funflow6d" else None
    items = list_images(
        root,
        args.split,
        detections=args.detections,
        targets=_default_targets(args, root),
        score_threshold=args.score_threshold,
        max_images=args.max_images,
    )
    needed = sorted({o for item in items for o in item.obj_ids})
    infos = BOPDataset(root, args.split).models_info()
    missing = [o for o in needed if o not in infos]
    if missing:
        warnings.warn(f"objects {missing} have no model; their instances are skipped", stacklevel=1)
    needed = [o for o in needed if o in infos]
    objects = load_object_models(root, obj_ids=needed, progress=show)
    import open3d  # noqa: F401  (both methods use it: import it before any clock starts)

    timer = StageTimer()
    if model is not None:
        model.prepare_objects(objects, cache_dir=_cache_dir(args, root), progress=show)
        generator = torch.Generator(device=device).manual_seed(args.seed)
    elif objects:
        from poseflow.baselines import ClassicBaseline

        baseline = ClassicBaseline(objects, seed=args.seed, timer=timer)
        # Its per-object descriptor banks are built on first use: build them now, so that
        # neither the first image's time nor the stage breakdown includes them.
        for obj_id in tqdm(objects, desc="baseline banks", disable=not show):
            baseline._bank(obj_id)
        timer.reset()
    items = [w for w in (_only(item, objects) for item in items) if w.obj_ids]
    ds = BOPDataset(root, args.split, load_masks=False)
    parts, instances, images = [], 0, 0
    bar = tqdm(items, desc=f"predict ({args.method})", disable=not show)
    for item in bar:
        scene = ds.scene(item.scene_id)
        depth = scene.load_depth_image(item.im_id)
        masks, ids, det_scores = _masks(scene, item, tuple(depth.shape))
        if masks is None:
            continue
        K = torch.as_tensor(scene.camera[item.im_id].K, dtype=torch.float32)
        if model is not None:
            rgb = scene.load_rgb_image(item.im_id).to(device)
            depth, K, masks = depth.to(device), K.to(device), masks.to(device)
        _sync(device)
        start = time.perf_counter()
        with timer.image():
            if model is not None:
                est = model.estimate(rgb, depth, K, masks, ids, generator=generator, timer=timer)
            else:
                est = baseline.estimate(depth, K, masks, ids)
        _sync(device)
        elapsed = time.perf_counter() - start + max(item.extra_time, 0.0)
        images += 1
        instances += len(ids)
        valid = est.valid.detach().cpu()
        if bool(valid.any()):
            scores = est.scores.detach().cpu().double() * torch.tensor(det_scores).double()
            parts.append(
                PoseResults.from_columns(
                    [item.scene_id] * int(valid.sum()),
                    [item.im_id] * int(valid.sum()),
                    [o for o, v in zip(ids, valid.tolist()) if v],
                    scores[valid],
                    est.poses.detach().cpu()[valid],
                    elapsed,
                )
            )
        bar.set_postfix(ms_per_image=f"{timer.breakdown()['total_ms']:.0f}")
    bar.close()
    results = PoseResults.concat(parts)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_results(out, results)
    mean = results.average_time()
    print(
        f"{args.method}: {images} images, {instances} instances, {len(results)} poses "
        f"({instances - len(results)} invalid) written to {out}"
    )
    if mean >= 0:
        print(f"mean time per image: {1000 * mean:.1f} ms on {device}")
    if args.timing is not None:
        report = {"method": args.method, "device": str(device), **timer.breakdown()}
        if model is not None:
            report["config"] = model.config.to_json()
        Path(args.timing).parent.mkdir(parents=True, exist_ok=True)
        Path(args.timing).write_text(json.dumps(report, indent=2))
        print(f"stage timing written to {args.timing}")
    return 0


def _sync(device: Any) -> None:
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize(device)
