"""``poseflow train``: train FunFlow6D on the training images of a BOP dataset.

Steps: prepare the dataset's objects (cached under ``RUN_DIR/model/objects/`` or ``--cache``),
run the frozen encoders over the training instances once (whole images in ``--threads``
processes of one thread each; ``--copies`` augmented copies each,
with the maps to the symmetric equivalents of the objects that ``models_info.json`` declares
symmetric, so that a flipped ground truth of a symmetric object costs no loss; cached as
``RUN_DIR/train_set.safetensors`` and reused while the dataset, the feature settings and the
options that shape the set are unchanged), train the network by flow matching
(:func:`poseflow.models.training.train`; checkpoints and ``metrics.jsonl`` in
``RUN_DIR/checkpoints``), and save the EMA weights with :meth:`FunFlow6D.save
<poseflow.models.FunFlow6D.save>` to ``RUN_DIR/model``, the folder ``poseflow predict --model``
takes.

Under ``torchrun --nproc_per_node=K`` the same command trains with DDP: rank 0 prepares the
objects and the training set first while the other ranks wait, then every rank reads the caches;
only rank 0 writes. The wait is a collective of the process group (30 minutes at most), which also
tells the other ranks at once when rank 0 fails; on a large dataset run ``poseflow train ...
--data-only`` once in a single process first.

Example::

    poseflow synth data/synth --train 2000 --test 50
    poseflow train data/synth --out runs/small --preset small --steps 20000 --copies 4
    torchrun --nproc_per_node=4 -m poseflow.cli train data/synth --out runs/small --resume
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

from poseflow.cli.common import (
    add_cache_argument,
    add_device_argument,
    add_seed_argument,
    option_values,
    positive_int,
)
from poseflow.cli.options import add_config_arguments

__all__ = ["DESCRIPTION", "HELP", "RESUME_SETTINGS", "add_arguments", "run"]


def _network_fields() -> tuple[str, ...]:
    """Configuration fields that leave the precomputed training set valid.

    The network's fields and the inference-time ones, except the dense-cloud cap (it shapes the
    observed clouds).
    """
    from poseflow.models.config import INFERENCE_FIELDS

    network = ("fusion", "dit_preset", "anchor", "noise_conditioning", "time_sampler", "net")
    return network + tuple(f for f in INFERENCE_FIELDS if f != "dense_points")


#: ``train``'s line in ``poseflow --help``.
HELP = "train FunFlow6D on a BOP dataset's training split"

#: What ``poseflow train --help`` says.
DESCRIPTION = """\
Prepare the objects, precompute the flow inputs of every training instance (cached in
RUN_DIR/train_set.safetensors), train by conditional flow matching and save the model to
RUN_DIR/model. Runs under torchrun (DDP) unchanged."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options of ``poseflow train`` (its ``run`` is :func:`run`)."""
    parser.add_argument("dataset", help="BOP dataset folder")
    parser.add_argument("--out", required=True, metavar="RUN_DIR", help="run folder RUN_DIR")
    parser.add_argument("--split", default="train", help="training split (default: train)")
    parser.add_argument("--steps", type=int, default=10_000, help="optimiser steps")
    parser.add_argument("--batch-size", type=int, default=32, help="instances per step and process")
    parser.add_argument("--lr", type=float, default=1e-4, help="peak learning rate")
    parser.add_argument(
        "--warmup-steps", type=int, default=None, help="linear warm-up (default: steps/10, ≤500)"
    )
    parser.add_argument(
        "--ema-decay", type=float, default=0.999, help="decay of the weight EMA that is saved"
    )
    parser.add_argument(
        "--copies", type=int, default=1, help="augmented copies of each instance (first clean)"
    )
    parser.add_argument(
        "--crop-jitter",
        type=float,
        default=0.1,
        help="jitter of the appearance crop in augmented copies, fraction of its side",
    )
    parser.add_argument(
        "--occlusion",
        type=float,
        default=0.0,
        help="probability that an instance of an augmented copy is cut to a part",
    )
    parser.add_argument(
        "--max-images",
        type=positive_int,
        default=None,
        metavar="N",
        help="use at most N images (default: all)",
    )
    parser.add_argument(
        "--min-visib-fract", type=float, default=0.1, help="skip less visible instances"
    )
    parser.add_argument("--precision", default="bf16", help="bf16, fp16 or fp32 autocast on CUDA")
    parser.add_argument("--ckpt-every", type=int, default=1000, help="steps between checkpoints")
    add_seed_argument(parser, draws="the network's initialisation, the augmentation and training")
    parser.add_argument(
        "--resume", action="store_true", help="continue from RUN_DIR's latest checkpoint"
    )
    add_cache_argument(parser, without="RUN_DIR/model")
    parser.add_argument(
        "--data-only", action="store_true", help="stop after caching the training set"
    )
    parser.add_argument(
        "--distill-from",
        metavar="MODEL_DIR",
        default=None,
        help="distil this trained model into a one-step sampler: start from its weights and "
        "configuration and learn to take in one Euler step what its solver takes in several "
        "(the training set of the run folder holding MODEL_DIR is reused when it was made "
        "from the same dataset and data options); --resume finds the teacher in run.json",
    )
    parser.add_argument(
        "--symmetric-targets",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="train symmetric objects (symmetries_discrete / symmetries_continuous of "
        "models_info.json) towards the nearest symmetric equivalent of the ground truth "
        "(default: on)",
    )
    add_device_argument(parser)
    add_config_arguments(parser)


def _run_config(args: argparse.Namespace, out: Path, teacher: Any = None) -> Any:
    """The model configuration: from the options, the teacher's, or the saved run's (resuming)."""
    from poseflow.cli.options import build_config, config_requested
    from poseflow.errors import UsageError
    from poseflow.flows import latest_checkpoint
    from poseflow.models import FunFlow6DConfig

    run_file = out / "run.json"
    if args.resume and run_file.is_file():
        saved = FunFlow6DConfig.from_dict(json.loads(run_file.read_text())["config"])
        if not config_requested(args):
            return saved
        config = build_config(args)
        if config.to_dict() != saved.to_dict():
            raise UsageError(
                f"the configuration differs from that of the run in {out} ({run_file}); drop "
                "the configuration options to resume it, or train into a new --out"
            )
        return config
    if not args.resume and latest_checkpoint(out / "checkpoints") is not None:
        raise UsageError(
            f"{out} already holds the checkpoints of a run; pass --resume to continue it or "
            "choose another --out"
        )
    if teacher is not None:
        if config_requested(args):
            raise UsageError(
                "--distill-from keeps the teacher's configuration; drop the configuration options"
            )
        return teacher.config
    return build_config(args)


def _teacher_folder(args: argparse.Namespace, out: Path) -> str | None:
    """The model to distil: ``--distill-from``, or on ``--resume`` the one ``run.json`` names.

    Raises:
        UsageError: resuming with a ``--distill-from`` other than the run's, or a run that
            trains by flow matching with one.
    """
    from poseflow.errors import UsageError

    run_file = out / "run.json"
    if not (args.resume and run_file.is_file()):
        return args.distill_from
    recorded = json.loads(run_file.read_text()).get("distilled_from")
    given = None if args.distill_from is None else str(Path(args.distill_from).resolve())
    if recorded is None and given is not None:
        raise UsageError(
            f"the run in {out} trains by flow matching; distil into a new --out instead"
        )
    if recorded is not None and given is not None and given != recorded:
        raise UsageError(f"the run in {out} distils {recorded}, not {given}")
    return recorded


#: Trainer settings whose change on ``--resume`` makes the run differ from an uninterrupted one.
RESUME_SETTINGS = ("steps", "batch_size", "lr", "warmup_steps", "ema_decay", "precision", "seed")


def _train_set_key(config: Any, root: Path, args: argparse.Namespace) -> dict[str, Any]:
    """Everything the training set is made from: its cache key.

    The dataset (its path, the annotations' content, every file of the split by path, size and
    modification time), the options that shape the set and the feature configuration.
    """
    from poseflow._cache import files_key
    from poseflow.data.object_folder import dataset_fingerprint

    network = _network_fields()
    features = {k: v for k, v in config.to_dict().items() if k not in network}
    split_files = [p for p in (root / args.split).rglob("*") if p.is_file()]
    return {
        "dataset": dataset_fingerprint(root, args.split),
        "dataset_path": str(root.resolve()),
        "files": files_key(split_files),
        "num_files": len(split_files),
        "split": args.split,
        "copies": args.copies,
        "crop_jitter": args.crop_jitter if args.copies > 1 else 0.0,
        # only where it acts, so that the keys of sets built without it stay as they were
        **({"occlusion": args.occlusion} if args.copies > 1 and args.occlusion else {}),
        "max_images": args.max_images,
        "min_visib_fract": args.min_visib_fract,
        "seed": args.seed,
        "draws": "per image",  # each image's own generator (any number of workers)
        "symmetric_targets": args.symmetric_targets,
        "features": features,
    }


def _cached_training_set(path: Path, meta: Path, key: dict[str, Any]) -> Any:
    """The cached training set when its key is ``key`` and it reads back whole, else None.

    A corrupt cache (a truncated key or tensor file) is reported with a warning and rebuilt.
    """
    import warnings

    from poseflow.errors import CheckpointError, MissingWeightsError
    from poseflow.flows.checkpoint import check_safetensors
    from poseflow.models.training import FlowTrainingSet

    if not (path.is_file() and meta.is_file()):
        return None
    try:
        saved = json.loads(meta.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        warnings.warn(f"{meta} is corrupt ({exc}); rebuilding the training set", stacklevel=2)
        return None
    if saved != key:
        return None
    try:
        check_safetensors(path)
    except (CheckpointError, MissingWeightsError) as exc:
        warnings.warn(f"{exc}; rebuilding the training set", stacklevel=2)
        return None
    return FlowTrainingSet.load(path)


def _training_set(
    model: Any,
    root: Path,
    args: argparse.Namespace,
    out: Path,
    *,
    symmetries: dict[int, Any],
    write: bool,
    progress: bool,
    also: Path | None = None,
) -> tuple[Any, Path | None]:
    """Load the cached training set when its key matches, else build (and, on rank 0, save) it.

    ``also``: another run folder whose cached set is used when its key matches (read only).
    Returns the set and the folder it was read from (None: built).
    """
    from poseflow._cache import atomic_write
    from poseflow.cli.common import image_workers
    from poseflow.models.training import build_training_set

    key = _train_set_key(model.config, root, args)
    path, meta = out / "train_set.safetensors", out / "train_set.json"
    for folder in (out, also) if also is not None else (out,):
        cached = _cached_training_set(
            folder / "train_set.safetensors", folder / "train_set.json", key
        )
        if cached is not None:
            return cached, folder
    with image_workers("cpu") as workers:  # the training set is computed on the CPU
        data = build_training_set(
            model,
            root,
            **option_values(
                args,
                "split",
                "copies",
                "crop_jitter",
                "occlusion",
                "min_visib_fract",
                "max_images",
                "seed",
            ),
            symmetries=symmetries if args.symmetric_targets else None,
            workers=workers,
            progress=progress,
        )
    if write:
        meta.unlink(missing_ok=True)  # no key beside a half-written set
        data.save(path)
        text = json.dumps(key, indent=1)
        atomic_write(meta, lambda tmp: tmp.write_text(text))
    return data, None


def _run_record(
    out: Path, args: argparse.Namespace, root: Path, config: Any, train_config: Any
) -> dict[str, Any]:
    """The ``run.json`` to write.

    A new run's record, or the original one with this resumption appended (and a warning when its
    trainer settings differ from the original's).
    """
    import warnings

    settings = train_config.to_json()
    record = {"config": config.to_dict(), "train": settings}
    record.update({"dataset": str(root), "split": args.split})
    run_file = out / "run.json"
    if not (args.resume and run_file.is_file()):
        return record
    original = json.loads(run_file.read_text())
    before = original.get("train", {})
    for earlier in original.get("resumed", []):
        before = {**before, **earlier.get("train", {})}
    changed = {
        k: (before.get(k), settings[k])
        for k in RESUME_SETTINGS
        if k in before and before.get(k) != settings[k]
    }
    if changed:
        text = ", ".join(f"{k} {new} (was {old})" for k, (old, new) in changed.items())
        warnings.warn(
            f"resuming {out} with other trainer settings: {text}; the result will differ from "
            "an uninterrupted run (run.json keeps the original settings and records these)",
            stacklevel=2,
        )
    resumed = {"train": settings, "dataset": str(root), "split": args.split}
    original.setdefault("resumed", []).append(resumed)
    return original


def run(args: argparse.Namespace) -> int:
    """Prepare, build the training set, train and save; prints the times; returns 0."""
    import torch.distributed as dist

    from poseflow.cli.common import check_writable, load_model, resolve_device
    from poseflow.data.object_folder import check_dataset
    from poseflow.errors import PoseflowError, UsageError
    from poseflow.flows import destroy_distributed, init_distributed, main_rank_succeeded
    from poseflow.models.training import train

    start = time.perf_counter()
    root = check_dataset(args.dataset, args.split)
    out = check_writable(args.out, folder=True)
    if args.copies < 1 or args.steps < 1:
        raise UsageError("--copies and --steps must be at least 1")
    if not 0.0 <= args.occlusion <= 1.0:
        raise UsageError(f"--occlusion must lie in [0, 1], got {args.occlusion}")
    train_config = _train_config(args)
    device = resolve_device(args.device)
    had_group = dist.is_available() and dist.is_initialized()
    ctx = init_distributed(device=device)
    try:
        # Rank 0 computes and writes the caches (and run.json) first; the other ranks then read.
        # Its failure reaches them at once (rather than leaving them at a barrier).
        if not ctx.is_main and not main_rank_succeeded(ctx):
            raise PoseflowError("rank 0 failed to prepare the objects or the training set")
        try:
            args.distill_from = _teacher_folder(args, out)
            teacher = load_model(args.distill_from) if args.distill_from is not None else None
            model, data, source, times = _prepare(
                args, root, out, train_config, ctx.is_main, teacher
            )
        except BaseException:
            if ctx.is_main:
                main_rank_succeeded(ctx, False)
            raise
        if ctx.is_main:
            main_rank_succeeded(ctx, True)
            where = "reused" if source is not None else "built"
            print(f"training set {where}: {len(data)} instances from {root}/{args.split}")
        if args.data_only:
            if ctx.is_main:
                cached = (source or out) / "train_set.safetensors"
                print(f"cached in {cached} ({_fmt(times)})")
            return 0
        t0 = time.perf_counter()
        metrics = train(
            model,
            data,
            config=train_config,
            out_dir=out / "checkpoints",
            resume=args.resume,
            device=ctx.device,
            teacher=teacher,
        )
        times["training"] = time.perf_counter() - t0
        if ctx.is_main:
            model.save(out / "model")
            loss = f", final loss {metrics['loss']:.4f}" if "loss" in metrics else ""
            world = f" on {ctx.world_size} processes" if ctx.is_distributed else ""
            what = "distilled into a one-step sampler in" if teacher is not None else "trained"
            print(f"{what} {args.steps} steps{world} on {ctx.device}{loss}")
            total = time.perf_counter() - start
            print(f"model saved to {out / 'model'} in {total:.1f} s ({_fmt(times)})")
        return 0
    finally:
        if not had_group:
            destroy_distributed()


def _train_config(args: argparse.Namespace) -> Any:
    """The trainer's settings of the options (warm-up by default a tenth of the steps, ≤ 500)."""
    from poseflow.cli.common import show_progress
    from poseflow.flows import TrainConfig

    warmup = min(500, args.steps // 10) if args.warmup_steps is None else args.warmup_steps
    return TrainConfig(
        **option_values(args, "steps", "batch_size", "lr", "ema_decay", "precision", "seed"),
        ckpt_every=args.ckpt_every,
        warmup_steps=warmup,
        progress=show_progress(args),
    )


def _prepare(
    args: argparse.Namespace,
    root: Path,
    out: Path,
    train_config: Any,
    main: bool,
    teacher: Any = None,
) -> tuple[Any, Any, Path | None, dict[str, float]]:
    """The model with its objects prepared and its training set (rank 0 writes ``run.json``).

    Distilling, the model starts as a copy of the ``teacher`` and the teacher's run folder's
    training set is reused when it matches.

    Returns:
        The model, the training set, the folder whose cached set was reused (None: built), and
        the seconds of each step.
    """
    import torch

    from poseflow._cache import atomic_write
    from poseflow.cli.common import show_progress
    from poseflow.data.object_folder import load_object_models, object_cache_dir
    from poseflow.models import FunFlow6D

    config = _run_config(args, out, teacher)
    torch.manual_seed(args.seed)
    model = FunFlow6D(config)
    if teacher is not None:
        model.load_state_dict(teacher.state_dict())
    cache = Path(args.cache) if args.cache is not None else out / "model"
    show = show_progress(args) and main
    times = {}
    t0 = time.perf_counter()
    models = load_object_models(root, progress=show)
    model.prepare_objects(models, cache_dir=object_cache_dir(cache, root), progress=show)
    times["objects"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    symmetries = {oid: m.symmetries for oid, m in models.items()}
    also = Path(args.distill_from).resolve().parent if teacher is not None else None
    data, source = _training_set(
        model, root, args, out, symmetries=symmetries, write=main, progress=show, also=also
    )
    times["training set"] = time.perf_counter() - t0
    if main:
        out.mkdir(parents=True, exist_ok=True)
        record = _run_record(out, args, root, config, train_config)
        if teacher is not None:
            record.setdefault("distilled_from", str(Path(args.distill_from).resolve()))
        text = json.dumps(record, indent=1)
        atomic_write(out / "run.json", lambda tmp: tmp.write_text(text))
    return model, data, source, times


def _fmt(times: dict[str, float]) -> str:
    return ", ".join(f"{k} {v:.1f} s" for k, v in times.items())
