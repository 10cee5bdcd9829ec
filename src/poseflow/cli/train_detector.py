"""``poseflow train-detector``: learn a detector of a dataset's objects from its rendered images.

Trains :class:`~poseflow.detect.Detector` (:func:`~poseflow.detect.train_detector`) on a BOP
split with visible masks, in the recipe the ``poseflow synth`` images of the user's meshes, and
writes its folder (``config.json`` + ``model.safetensors``). Put it at ``MODEL_DIR/detector`` and
``poseflow predict --detections own`` and ``poseflow estimate`` without ``--mask`` find it there.
"""

from __future__ import annotations

import argparse

__all__ = ["DESCRIPTION", "HELP", "add_arguments", "run"]

#: ``train-detector``'s line in ``poseflow --help``.
HELP = "train the detector of a dataset's objects on its rendered images"

#: What ``poseflow train-detector --help`` says.
DESCRIPTION = """\
Train the detector of a BOP dataset's objects (every object of its models_info.json) on one of
its splits with visible masks: in the recipe, the images `poseflow synth` rendered of your meshes.
Write it to MODEL_DIR/detector so that `poseflow predict --detections own` and `poseflow estimate`
without --mask use it."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options of ``poseflow train-detector`` (its ``run`` is :func:`run`)."""
    parser.add_argument("dataset", help="BOP dataset with visible masks (the synth images)")
    parser.add_argument("--out", required=True, help="the detector's folder")
    parser.add_argument("--split", default="train", help="split to train on (default: train)")
    parser.add_argument("--steps", type=int, default=4000, help="optimiser steps (default: 4000)")
    parser.add_argument("--batch-size", type=int, default=8, help="crops per step (default: 8)")
    parser.add_argument(
        "--crop",
        type=int,
        default=192,
        help="crop side in input pixels, a multiple of 32 (default: 192)",
    )
    parser.add_argument(
        "--lr", type=float, default=2e-3, help="peak learning rate (default: 0.002)"
    )
    parser.add_argument(
        "--max-images", type=int, default=None, help="train on the first N images (default: all)"
    )
    parser.add_argument(
        "--seed", type=int, default=0, help="seed of the weights and batches (default: 0)"
    )
    parser.add_argument(
        "--overwrite", action="store_true", help="replace --out when it holds a detector"
    )


def run(args: argparse.Namespace) -> int:
    """Train and save the detector; prints where it went. Returns 0."""
    from pathlib import Path

    from poseflow.cli.common import LOG, check_writable
    from poseflow.data.object_folder import check_dataset
    from poseflow.detect import train_detector
    from poseflow.errors import OutputExistsError, UsageError

    if args.steps < 1 or args.batch_size < 1:
        raise UsageError("--steps and --batch-size must be at least 1")
    if args.max_images is not None and args.max_images < 1:
        raise UsageError(f"--max-images must be at least 1, got {args.max_images}")
    root = check_dataset(args.dataset, args.split)
    out = Path(args.out)
    if (out / "model.safetensors").exists() and not args.overwrite:
        raise OutputExistsError(f"{out} already holds a detector; pass --overwrite to replace it")
    check_writable(out, folder=True)
    detector = train_detector(
        root,
        out,
        split=args.split,
        steps=args.steps,
        batch_size=args.batch_size,
        crop=args.crop,
        lr=args.lr,
        max_images=args.max_images,
        seed=args.seed,
        progress=not args.quiet,
    )
    LOG.info("detector of objects %s written to %s", detector.config.obj_ids, out)
    return 0
