"""``poseflow detect``: find the objects in every image of a BOP split; write BOP detections.

Runs a detector folder (``poseflow train-detector``; ``--detector``, or ``--model MODEL_DIR``
for the detector inside a model folder) over a split and writes the BOP detections JSON
(``scene_id``, ``image_id``, ``category_id``, ``score``, ``bbox``, COCO-RLE ``segmentation``,
``time``), which ``poseflow predict --detections FILE`` reads.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from typing import Any

__all__ = ["DESCRIPTION", "HELP", "add_arguments", "check_score_threshold", "load_detector", "run"]

#: ``detect``'s line in ``poseflow --help``.
HELP = "find a dataset's objects with a trained detector; write BOP detections"

#: What ``poseflow detect --help`` says.
DESCRIPTION = """\
Detect the objects of a trained detector in every image of a BOP split and write the BOP
detections JSON (COCO-RLE masks, scores, boxes and the time per image). `poseflow predict
--detections FILE` estimates their poses; `predict --detections own` runs the detector itself."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options of ``poseflow detect`` (its ``run`` is :func:`run`)."""
    parser.add_argument("dataset", help="BOP dataset folder")
    parser.add_argument("--out", required=True, help="detections JSON to write")
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--detector", default=None, help="detector folder (train-detector)")
    source.add_argument("--model", default=None, metavar="MODEL_DIR", help="use MODEL_DIR/detector")
    parser.add_argument("--split", default="test", help="split folder (default: test)")
    parser.add_argument(
        "--score-threshold",
        type=float,
        default=0.0,
        help="drop detections scoring below this (default: 0)",
    )
    parser.add_argument(
        "--max-images", type=int, default=None, help="the first N images (default: all)"
    )


def load_detector(detector: str | None, model: str | None, *, needs: str) -> tuple[Any, str]:
    """The detector of ``--detector DIR``, else of ``--model MODEL_DIR`` (``MODEL_DIR/detector``).

    Args:
        detector: ``--detector``'s value, or None.
        model: ``--model``'s value (``demo`` included), or None.
        needs: the message when neither option names one (the options are added to it).

    Returns:
        ``(detector, folder)``.

    Raises:
        UsageError: neither option is given.
        MissingWeightsError: ``MODEL_DIR`` holds no detector.
    """
    from pathlib import Path

    from poseflow.cli.common import LOG, resolve_model
    from poseflow.detect import Detector
    from poseflow.errors import MissingWeightsError, UsageError

    if detector is None and model is None:
        raise UsageError(f"{needs} (--detector DIR or --model MODEL_DIR)")
    folder = Path(detector) if detector is not None else resolve_model(model) / "detector"
    if detector is None and not folder.is_dir():
        raise MissingWeightsError(
            f"the model {model} has no detector ({folder} is missing): train one with "
            f"`poseflow train-detector SYNTH_DATASET --out {folder}`, or pass --detector DIR"
        )
    LOG.info("finding the objects with the detector %s", folder)
    return Detector.load(folder), str(folder)


def check_score_threshold(found: Sequence[Any], threshold: float) -> None:
    """Raise UsageError when ``--score-threshold`` leaves none of the detections ``found``.

    Example:
        >>> from poseflow.data.bop import Detection
        >>> check_score_threshold([Detection(0, 0, 1, 0.4, (0, 0, 1, 1))], 0.3)
    """
    from poseflow.errors import UsageError

    if found and not any(d.score >= threshold for d in found):
        raise UsageError(
            f"--score-threshold {threshold} leaves no detection (the best scores "
            f"{max(d.score for d in found):.3f})"
        )


def run(args: argparse.Namespace) -> int:
    """Detect and write the JSON; prints a summary. Returns 0."""
    from poseflow.cli.common import LOG, check_writable
    from poseflow.data.bop import write_detections
    from poseflow.data.object_folder import check_dataset
    from poseflow.detect import detect_dataset
    from poseflow.errors import UsageError

    if args.max_images is not None and args.max_images < 1:
        raise UsageError(f"--max-images must be at least 1, got {args.max_images}")
    detector, _ = load_detector(args.detector, args.model, needs="give the detector")
    root = check_dataset(args.dataset, args.split)
    check_writable(args.out)
    found = detect_dataset(
        detector, root, args.split, max_images=args.max_images, progress=not args.quiet
    )
    check_score_threshold(found, args.score_threshold)
    kept = [d for d in found if d.score >= args.score_threshold]
    write_detections(args.out, kept)
    images = len({(d.scene_id, d.im_id) for d in kept})
    LOG.info("%d detections in %d images written to %s", len(kept), images, args.out)
    return 0
