"""Steps per second of the surface embedding's training in float32 and in bfloat16.

:func:`~poseflow.features.surface_training.train_surface_embedding` runs its query network
under ``precision`` (``"fp32"``, the default; ``"bf16"``; ``"auto"``: bfloat16 where the CPU
multiplies it natively).
This trains the same embedding (same crops, seed and batches) for ``--steps`` steps in each
precision, alternately ``--repeats`` times, and prints the seconds per step of each (the
training loop alone, without the crops), their ratio, and the loss over the last steps, then
the JSON line and the command. Where the CPU has no bfloat16 products, ``bf16`` is emulated and
slower (``auto`` then trains in float32).

Run ``python benchmarks/surface_precision.py TRAIN_DATASET [--images 200 --steps 200]``;
``--quick`` (CI) trains three steps on two generated images.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
from pathlib import Path

import _common
import torch

from poseflow.features.surface_training import train_surface_embedding
from poseflow.flows import native_bfloat16

PRECISIONS = ("fp32", "bf16")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", nargs="?", help="BOP dataset with models/ and a train split")
    parser.add_argument("--images", type=int, default=200, help="images to cut crops from")
    parser.add_argument("--steps", type=int, default=200, help="steps per run")
    parser.add_argument("--repeats", type=int, default=2, help="runs per precision")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--quick", action="store_true", help="three steps on two images (CI)")
    args = parser.parse_args()
    torch.set_num_threads(max(1, args.threads))
    with tempfile.TemporaryDirectory() as tmp:
        root = args.dataset
        if root is None and not args.quick:
            parser.error("give a BOP dataset with a train split, or --quick")
        if args.quick:
            from poseflow.data import generate_dataset

            root = generate_dataset(
                Path(tmp) / "ds", num_train_images=2, num_test_images=0, width=160, height=120,
                progress=False,
            )  # fmt: skip
            args.images, args.steps, args.repeats = 2, 3, 1
        seconds: dict[str, list[float]] = {p: [] for p in PRECISIONS}
        losses: dict[str, list[float]] = {p: [] for p in PRECISIONS}
        for r in range(args.repeats):
            for precision in PRECISIONS:
                out = train_surface_embedding(
                    root, Path(tmp) / f"{precision}{r}", steps=args.steps,
                    max_images=args.images, precision=precision, progress=False,
                )  # fmt: skip
                training = json.loads((out / "config.json").read_text())["training"]
                seconds[precision].append(training["seconds"] / args.steps)
                losses[precision].append(training["loss"])
    step = {p: statistics.median(seconds[p]) for p in PRECISIONS}
    print(f"surface embedding, {args.steps} steps on crops of {args.images} images, "
          f"{_common.machine()}, native bfloat16: {native_bfloat16('cpu')}")  # fmt: skip
    for p in PRECISIONS:
        print(f"  {p}: {1000 * step[p]:.1f} ms/step, loss {statistics.mean(losses[p]):.4f}")
    ratio = step["fp32"] / step["bf16"]
    print(f"  bf16 is {ratio:.2f}x as fast as fp32")
    record = {
        "benchmark": "surface_precision", "machine": _common.machine(),
        "native_bf16": native_bfloat16("cpu"), "images": args.images, "steps": args.steps,
        "ms_per_step": {p: round(1000 * step[p], 2) for p in PRECISIONS},
        "loss": {p: round(statistics.mean(losses[p]), 4) for p in PRECISIONS},
        "ratio": round(ratio, 3),
    }  # fmt: skip
    _common.report(record, __file__)


if __name__ == "__main__":
    main()
