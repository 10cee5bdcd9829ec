"""``poseflow synth``: render a synthetic BOP dataset (train and test splits).

Example::

    poseflow synth data/synth --train 200 --test 50 --seed 0
    poseflow synth data/mine --objects my_meshes/ --mesh-scale 0.001 --width 320 --height 240
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from poseflow.cli.common import add_seed_argument, nonnegative_int, positive_int

__all__ = ["DESCRIPTION", "HELP", "add_arguments", "check_output_folder", "run"]


#: ``synth``'s line in ``poseflow --help``.
HELP = "render a synthetic cluttered RGBD dataset in the BOP format"

#: What ``poseflow synth --help`` says.
DESCRIPTION = """\
Render textured objects resting on a plane among distractors, seen from random viewpoints with
random light and a depth-sensor noise model, and write a BOP dataset (models/, train/, test/,
test_targets_bop19.json). Without --objects the library's demo objects are used."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options of ``poseflow synth`` (its ``run`` is :func:`run`)."""
    parser.add_argument("out", help="output dataset folder")
    parser.add_argument(
        "--train", type=nonnegative_int, default=200, help="images of the train split"
    )
    parser.add_argument("--test", type=nonnegative_int, default=50, help="images of the test split")
    _add_count_argument(parser, "--objects-per-image", [3, 6], "objects")
    _add_count_argument(parser, "--distractors", [1, 4], "distractor boxes/cylinders")
    parser.add_argument(
        "--images-per-scene", type=positive_int, default=10, help="viewpoints per layout"
    )
    parser.add_argument("--width", type=positive_int, default=640, help="image width, px")
    parser.add_argument("--height", type=positive_int, default=480, help="image height, px")
    add_seed_argument(parser, draws="the layouts, viewpoints, light and sensor noise")
    parser.add_argument(
        "--objects",
        default=None,
        metavar="DIR",
        help="folder of .ply/.obj meshes to use (default: the library's demo objects)",
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


def _add_count_argument(
    parser: argparse.ArgumentParser, flag: str, default: list[int], what: str
) -> None:
    """Add ``flag N [N]``: how many ``what`` per scene, one number or a range LOW HIGH."""
    parser.add_argument(
        flag,
        type=int,
        nargs="+",
        default=default,
        metavar="N",
        help=f"{what} per scene: a number or a range LOW HIGH",
    )


def _count_range(values: list[int], flag: str) -> int | tuple[int, int]:
    """The value of a :func:`_add_count_argument` option: ``N`` or ``(LOW, HIGH)``."""
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
    """Generate the dataset described by ``args``; prints a summary and returns 0.

    With ``--threads N`` the images are rendered in N processes of one thread each.
    """
    from poseflow.cli.common import image_workers

    objects_per_image = _count_range(args.objects_per_image, "--objects-per-image")
    distractors = _count_range(args.distractors, "--distractors")
    check_output_folder(args.out, overwrite=args.overwrite)
    with image_workers("cpu") as workers:
        root = _generate(args, objects_per_image, distractors, workers)
    print(f"wrote {args.train} train and {args.test} test images to {root}")
    return 0


def _generate(
    args: argparse.Namespace, objects_per_image: Any, distractors: Any, workers: int
) -> Path:
    """The dataset of ``args`` rendered in ``workers`` processes; its folder."""
    from poseflow.cli.common import option_values, show_progress
    from poseflow.data.synthetic import DepthNoise, generate_dataset

    return generate_dataset(
        args.out,
        args.objects,
        num_train_images=args.train,
        num_test_images=args.test,
        objects_per_image=objects_per_image,
        distractors_per_image=distractors,
        **option_values(args, "images_per_scene", "width", "height", "seed", "mesh_scale"),
        depth_noise=None if args.clean_depth else DepthNoise(),
        image_ext=".jpg" if args.jpg else ".png",
        progress=show_progress(args),
        overwrite=args.overwrite,
        workers=workers,
    )
