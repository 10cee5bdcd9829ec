"""``poseflow train-surface``: learn the surface embedding of a dataset's objects from its renders.

Trains :class:`~poseflow.features.SurfaceEmbedding`
(:func:`~poseflow.features.surface_training.train_surface_embedding`) on a BOP split with poses,
visible masks and depth, in the recipe the ``poseflow synth`` images of the user's meshes, and
writes its folder (``config.json`` + ``model.safetensors``); FunFlow6D uses it with
``--appearance-encoder surface:DIR``. ``poseflow onboard`` runs it as its second phase.
"""

from __future__ import annotations

import argparse

from poseflow.cli.common import nonnegative_int, positive_int

__all__ = ["DESCRIPTION", "HELP", "add_arguments", "run"]

#: ``train-surface``'s line in ``poseflow --help``.
HELP = "learn the surface embedding of a dataset's objects on its rendered images"

#: What ``poseflow train-surface --help`` says.
DESCRIPTION = """\
Learn a surface embedding of a BOP dataset's objects on one of its splits (poses, visible masks,
depth): in the recipe, the images `poseflow synth` rendered of your meshes, never test images.
Each pixel learns which point of its object's surface it shows. `poseflow train --appearance-
encoder surface:DIR` then conditions FunFlow6D on it (about 20 minutes on one thread at the
default steps)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options of ``poseflow train-surface`` (its ``run`` is :func:`run`)."""
    parser.add_argument("dataset", help="BOP dataset with models/ and a split with poses")
    parser.add_argument("--out", required=True, help="the embedding's folder")
    parser.add_argument("--split", default="train", help="split to learn from")
    parser.add_argument("--steps", type=positive_int, default=10000, help="optimiser steps")
    parser.add_argument(
        "--max-images", type=nonnegative_int, default=1600, help="images to learn from (0: all)"
    )
    parser.add_argument("--dim", type=positive_int, default=32, help="embedding channels")
    parser.add_argument("--queries", type=positive_int, default=48, help="pixels per crop per step")
    parser.add_argument(
        "--points-per-crop", type=positive_int, default=128, help="pixels kept per crop"
    )
    parser.add_argument("--lr", type=float, default=2e-3, help="peak learning rate")
    parser.add_argument("--seed", type=int, default=0, help="seed of the weights and batches")
    parser.add_argument("--no-init", action="store_true", help="start the query network at random")
    parser.add_argument(
        "--precision", default="fp32", choices=["fp32", "bf16", "auto"],
        help="the query network's products (auto: bfloat16 where the CPU has it)",
    )  # fmt: skip
    parser.add_argument(
        "--overwrite", action="store_true", help="replace --out when it holds an embedding"
    )


def run(args: argparse.Namespace) -> int:
    """Train and save the embedding; prints where it went. Returns 0."""
    from pathlib import Path

    from poseflow.cli.common import LOG, check_writable, show_progress
    from poseflow.data.object_folder import check_dataset
    from poseflow.errors import OutputExistsError
    from poseflow.features.surface_training import train_surface_embedding

    check_dataset(args.dataset, args.split)
    if (Path(args.out) / "model.safetensors").exists() and not args.overwrite:
        raise OutputExistsError(
            f"{args.out} already holds an embedding; pass --overwrite to replace it"
        )
    out = check_writable(args.out, folder=True)
    folder = train_surface_embedding(
        args.dataset, out, steps=args.steps, split=args.split,
        max_images=args.max_images or None, dim=args.dim, queries=args.queries,
        points_per_crop=args.points_per_crop, lr=args.lr, seed=args.seed,
        init=None if args.no_init else "shipped", precision=args.precision,
        progress=show_progress(args), log=lambda line: LOG.info("%s", line),
    )  # fmt: skip
    print(f"wrote {folder}/model.safetensors and config.json")
    return 0
