"""The paper's ablation table, rerun: every row of ``poseflow.models.ABLATIONS`` trained and scored.

Each row changes the base configuration (``--config``, default ``configs/demo_small.json``) as the
paper's table does (reduction, fusion variant, refinement), trains a model from scratch on the
training split of ``--train-data`` for ``--steps`` steps (training sets are cached per feature
configuration in ``--work``, so rows that differ only in the network share one), and scores it with
the BOP 2019 AR on a generated test split (targets down to ``visib_fract`` 0.3).

Prints a table and one JSON line, then the command. Run
``python benchmarks/ablation.py --train-data data/demo_train --steps 5000`` (``--quick`` for CI:
a tiny configuration, two rows, a few steps on a tiny generated dataset).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import torch

from poseflow.data.demo_objects import demo_objects
from poseflow.data.synthetic import generate_dataset
from poseflow.eval import evaluate_bop
from poseflow.flows import TrainConfig
from poseflow.models import ABLATIONS, FunFlow6D, FunFlow6DConfig
from poseflow.models.training import FlowTrainingSet, build_training_set, train

TINY = {
    "num_points": 32,
    "crop_size": 32,
    "query_views": 2,
    "dit_preset": "tiny",
    "steps": 5,
    "ransac_iterations": 100,
    "net": {"fusion_heads": 2, "posenc_dim": 16, "posenc_frequencies": 2},
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="configs/demo_small.json", help="base configuration")
    parser.add_argument("--train-data", default=None, help="BOP dataset with a train split")
    parser.add_argument("--rows", nargs="+", default=None, help="rows of ABLATIONS to run")
    parser.add_argument("--steps", type=int, default=5000)
    parser.add_argument("--test-images", type=int, default=24)
    parser.add_argument("--work", default=None, help="cache folder (default: temporary)")
    parser.add_argument("--quick", action="store_true", help="tiny configuration and data (CI)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    rows = args.rows or (["3_pca_sum", "8_umap_gated"] if args.quick else sorted(ABLATIONS))
    base = FunFlow6DConfig(**TINY) if args.quick else FunFlow6DConfig.from_json(args.config)
    steps = 10 if args.quick else args.steps
    objects = dict(enumerate(demo_objects(), start=1))
    out: dict = {"steps": steps, "rows": {}}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.work or tmp)
        size = {"width": 160, "height": 120} if args.quick else {}
        train_root = args.train_data or generate_dataset(
            work / "train", num_train_images=3 if args.quick else 200, num_test_images=0,
            seed=1, progress=False, **size,
        )  # fmt: skip
        n_test = 2 if args.quick else args.test_images
        test_root = generate_dataset(
            work / "test", num_train_images=0, num_test_images=n_test, seed=7,
            min_target_visib=0.3, progress=False, **size,
        )  # fmt: skip
        for name in rows:
            cfg = base.replace(**ABLATIONS[name])
            if args.quick and cfg.reducer == "umap":
                cfg = cfg.replace(reducer="pca")  # umap-learn needs more points than TINY has
            torch.manual_seed(0)
            model = FunFlow6D(cfg)
            key = f"{cfg.reducer}_{cfg.appearance_encoder}_{cfg.geometric_encoder}"
            model.prepare_objects(objects, cache_dir=work / "objects" / key, progress=False)
            cached = work / f"train_set_{key}.safetensors"
            if cached.is_file():
                data = FlowTrainingSet.load(cached)
            else:
                data = build_training_set(model, train_root, progress=False)
                data.save(cached)
            start = time.perf_counter()
            batch = 4 if args.quick else 16
            schedule = TrainConfig(
                steps=steps, batch_size=batch, lr=1e-3, warmup_steps=steps // 10,
                ema_decay=0.995, progress=False,
            )  # fmt: skip
            train(model, data, config=schedule)
            train_s = time.perf_counter() - start
            report = evaluate_bop(test_root, model.predict(test_root, seed=7))
            out["rows"][name] = {
                **{k: round(report[k], 4) for k in ("AR", "AR_VSD", "AR_MSSD", "AR_MSPD")},
                "train_s": round(train_s, 1),
            }
            print(name, out["rows"][name], flush=True)
    print(json.dumps(out))
    print("command:", " ".join([sys.executable, *sys.argv]))


if __name__ == "__main__":
    main()
