"""How much a trained FunFlow6D reads each conditioning stream: AR with its features shuffled.

The model predicts the split as shipped (verification included), then again with the observed
target's semantic features, its geometric features, or both, dealt at random over the target's
points before the network (the query's features untouched): what the flow reads of a stream is
what the AR loses when that stream no longer says which observed point is which. A stream whose
shuffling costs nothing is conditioning the flow ignores, however many true matches it holds.

Prints the AR per object of each variant, one JSON line and the command. Run
``python benchmarks/conditioning_use.py DATASET --model RUN/model [--steps 1 --solver midpoint]``;
``--quick`` (CI) runs the shipped model on a two-image generated split.
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
from pathlib import Path

import torch
from _common import report

from poseflow.assets import DEMO_CHECKPOINT
from poseflow.cli.common import load_model
from poseflow.cli.options import add_inference_arguments, inference_changes
from poseflow.data.object_folder import load_object_models, object_cache_dir
from poseflow.data.synthetic import generate_dataset
from poseflow.eval import evaluate_bop

#: What each variant deals at random over the target's points.
VARIANTS = {"model": (), "semantic": ("semantic",), "geometric": ("geometric",),
            "both": ("semantic", "geometric")}  # fmt: skip


def shuffled_inputs(flow_inputs, streams: tuple[str, ...], seed: int = 0):
    """``flow_inputs`` (a model's method) with the target half of ``streams`` permuted per instance.

    The inputs are ``[Q ; T]`` of ``2N`` points; row ``b``'s target features ``[N:]`` are dealt
    over its target points by a permutation drawn from a generator seeded ``seed``.
    """

    def inputs(obs, poses=None):
        out = flow_inputs(obs, poses)
        if not streams:
            return out
        N = out.points.shape[1] // 2
        generator = torch.Generator().manual_seed(seed)
        changes = {}
        for name in streams:
            features = getattr(out, name).clone()
            for b in range(features.shape[0]):
                features[b, N:] = features[b, N:][torch.randperm(N, generator=generator)]
            changes[name] = features
        return dataclasses.replace(out, **changes)

    return inputs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", nargs="?", help="BOP dataset folder")
    parser.add_argument("--model", default=str(DEMO_CHECKPOINT), help="FunFlow6D model folder")
    parser.add_argument("--seed", type=int, default=0, help="the predict seed")
    parser.add_argument("--max-images", type=int, default=None)
    parser.add_argument("--quick", action="store_true", help="shipped model, two generated images")
    add_inference_arguments(parser, set_help="an inference setting of the model, e.g. steps=1")
    args = parser.parse_args()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        if args.quick:
            dataset = generate_dataset(
                Path(tmp) / "data", num_train_images=0, num_test_images=2, width=320,
                height=240, progress=False,
            )  # fmt: skip
            args.model = str(DEMO_CHECKPOINT)
        elif args.dataset is None:
            parser.error("give a BOP dataset folder, or --quick")
        else:
            dataset = Path(args.dataset).resolve()
        changes = inference_changes(args)
        objects = load_object_models(dataset)
        cache = None if args.quick else object_cache_dir(args.model, dataset)
        ars = {}
        for name, streams in VARIANTS.items():
            model = load_model(args.model, inference=changes)
            model.flow_inputs = shuffled_inputs(model.flow_inputs, streams)
            model.prepare_objects(objects, cache_dir=cache, progress=False)
            results = model.predict(dataset, seed=args.seed, max_images=args.max_images)
            rep = evaluate_bop(dataset, results)
            ars[name] = {"AR": round(rep["AR"], 4)} | {
                o: round(v["AR"], 4)
                for o, v in sorted(rep["per_object"].items(), key=lambda x: int(x[0]))
            }
    objects_ids = [k for k in ars["model"] if k != "AR"]
    print(f"{'shuffled':<10}" + "".join(f"{o:>8}" for o in objects_ids) + f"{'AR':>8}")
    for name, row in ars.items():
        label = "nothing" if name == "model" else name
        print(
            f"{label:<10}" + "".join(f"{row[o]:>8.3f}" for o in objects_ids) + f"{row['AR']:>8.3f}"
        )
    report({"benchmark": "conditioning_use", "dataset": Path(dataset).name, "seed": args.seed,
            "AR": ars}, __file__)  # fmt: skip


if __name__ == "__main__":
    main()
