"""``poseflow synth``: render a synthetic BOP dataset (train and test splits).

Example::

    poseflow synth data/synth --train 200 --test 50 --seed 0
    poseflow synth data/mine --objects my_meshes/ --mesh-scale 0.001 --width 320 --height 240
"""

from __future__ import annotations

import argparse
from pathlib import Path

from poseflow.cli.common import (
    add_output_arguments,
    add_seed_argument,
    nonnegative_int,
    positive_int,
)

__all__ = ["add_parser", "check_output_folder", "run"]


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register the ``synth`` subcommand on ``subparsers``; its ``run`` is :func:`run`."""
    parser = subparsers.add_parser(
        "synth",
        help="render a synthetic cluttered RGBD dataset in the BOP format",
        description=(
            "Render textured objects resting on a plane among distractors, seen from random "
            "viewpoints with random light and a depth-sensor noise model, and write a BOP "
            "dataset (models/, train/, test/, test_targets_bop19.json). Without --objects the "
            "library's demo objects are used."
        ),
    )
    parser.add_argument("out", help="output dataset folder")
    parser.add_argument(
        "--train", type=nonnegative_int, default=200, help="images of the train split"
    )
    parser.add_argument("--test", type=nonnegative_int, default=50, help="images of the test split")
    parser.add_argument(
        "--objects-per-image",
        type=int,
        nargs="+",
        default=[3, 6],
        metavar="N",
        help="objects per scene: a number or a range LOW HIGH",
    )
    parser.add_argument(
        "--distractors",
        type=int,
        nargs="+",
        default=[1, 4],
        metavar="N",
        help="distractor boxes/cylinders per scene: a number or a range LOW HIGH",
    )
    parser.add_argument(
        "--images-per-scene", type=positive_int, default=10, help="viewpoints per layout"
    )
    parser.add_argument("--width", type=positive_int, default=640)
    parser.add_argument("--height", type=positive_int, default=480)
    add_seed_argument(parser, draws="the layouts, viewpoints, light and sensor noise")
    parser.add_argument(
        "--objects", default=None, metavar="DIR", help="folder of .ply/.obj meshes to use"
    )
    parser.add_argument(
        "--mesh-scale",
        type=float,
        default=1.0,
        help="factor turning the meshes' units into metres (0.001 for meshes in mm)",
    )
    parser.add_argument("--clean-depth", action="store_true", help="no depth-sensor noise")
    parser.add_argument("--jpg", action="store_true", help="write colour images as JPEG")
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="write into OUT even when it is not empty (files of the same names are replaced; "
        "others are left, so prefer an empty folder)",
    )
    add_output_arguments(parser)
    parser.set_defaults(run=run)
    return parser


def _count_range(values: list[int], flag: str) -> int | tuple[int, int]:
    from poseflow.errors import UsageError

    if len(values) == 1:
        return values[0]
    if len(values) == 2:
        return (values[0], values[1])
    raise UsageError(f"{flag} takes one number or a range LOW HIGH, got {values}")


def check_output_folder(out: str | Path, *, overwrite: bool) -> Path:
    """Refuse to write a dataset into a non-empty folder unless ``overwrite``.

    Two generations in one folder mix their images and annotations; scenes of the first that the
    second does not rewrite would stay.

    Raises:
        OutputExistsError: ``out`` holds files and ``overwrite`` is False.
        NotWritableError: ``out`` cannot be written.
    """
    from poseflow.cli.common import check_writable
    from poseflow.errors import OutputExistsError

    out = Path(out)
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise OutputExistsError(
            f"{out} is not empty: a new dataset would mix with what it holds; choose an empty "
            "or new folder, or pass --overwrite"
        )
    return check_writable(out, flag="OUT", folder=True)


def run(args: argparse.Namespace) -> int:
    """Generate the dataset described by ``args``; prints a summary and returns 0."""
    from poseflow.cli.common import show_progress
    from poseflow.data.synthetic import DepthNoise, generate_dataset

    objects_per_image = _count_range(args.objects_per_image, "--objects-per-image")
    distractors = _count_range(args.distractors, "--distractors")
    check_output_folder(args.out, overwrite=args.overwrite)
    root = generate_dataset(
        args.out,
        args.objects,
        num_train_images=args.train,
        num_test_images=args.test,
        objects_per_image=objects_per_image,
        distractors_per_image=distractors,
        images_per_scene=args.images_per_scene,
        width=args.width,
        height=args.height,
        seed=args.seed,
        depth_noise=None if args.clean_depth else DepthNoise(),
        image_ext=".jpg" if args.jpg else ".png",
        mesh_scale=args.mesh_scale,
        progress=show_progress(args),
        overwrite=args.overwrite,
    )
    print(f"wrote {args.train} train and {args.test} test images to {root}")
    return 0
