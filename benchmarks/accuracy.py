"""FunFlow6D against the classic baseline: BOP Average Recall and per-image stage timing.

A synthetic BOP test split of the demo objects is generated with clutter and occlusion (targets
down to ``visib_fract`` 0.3 by default); FunFlow6D (a checkpoint from ``poseflow train``, the
shipped ``small`` one by default) and the classic baseline (FPFH + RANSAC + ICP) estimate every
target from the ground-truth visible masks; both are scored with the BOP 2019 AR (VSD, MSSD,
MSPD), overall and per object. FunFlow6D runs once per sampler setting in ``--samplers`` (the
paper's Euler-50 first), each with the paper's stage breakdown per image (``StageTimer``).

Prints a table and one JSON line, then the command. Run ``python benchmarks/accuracy.py``
(``--quick`` for CI: two images, Euler-50 and Euler-5, no baseline).
"""

from __future__ import annotations

import argparse
import functools
import platform
import tempfile

import torch
from _common import clocked, report

from poseflow.assets import DEMO_CHECKPOINT
from poseflow.baselines import ClassicBaseline
from poseflow.data.demo_objects import demo_objects
from poseflow.data.object_folder import object_cache_dir
from poseflow.data.synthetic import generate_dataset
from poseflow.eval import StageTimer, evaluate_bop
from poseflow.features import FPFHEncoder
from poseflow.models import FunFlow6D


def _row(report: dict) -> dict:
    keys = ("AR", "AR_VSD", "AR_MSSD", "AR_MSPD")
    out = {k: round(report[k], 4) for k in keys}
    out["per_object"] = {
        o: {k: round(v[k], 4) for k in keys} for o, v in report["per_object"].items()
    }
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default=str(DEMO_CHECKPOINT), help="FunFlow6D checkpoint")
    parser.add_argument("--images", type=int, default=None, help="test images")
    parser.add_argument("--min-visib", type=float, default=0.3, help="smallest target visib_fract")
    parser.add_argument(
        "--samplers", nargs="+", default=None, help="SOLVER:STEPS settings (default euler:50 …)"
    )
    parser.add_argument("--no-baseline", action="store_true")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--quick", action="store_true", help="two images, no baseline (CI)")
    args = parser.parse_args()
    images = args.images or (2 if args.quick else 24)
    samplers = args.samplers or (
        ["euler:50", "euler:5"] if args.quick else ["euler:50", "euler:10", "euler:5", "heun:5"]
    )
    torch.set_num_threads(1)
    model = FunFlow6D.load(args.model)
    objects = dict(enumerate(demo_objects(), start=1))
    out: dict = {"machine": f"{platform.machine()}, {torch.get_num_threads()} torch thread"}
    with tempfile.TemporaryDirectory() as tmp:
        root = generate_dataset(
            tmp,
            num_train_images=0,
            num_test_images=images,
            seed=args.seed,
            min_target_visib=args.min_visib,
            progress=False,
        )
        cache = object_cache_dir(args.model, root)
        model.prepare_objects(objects, cache_dir=cache if cache.is_dir() else None, progress=False)
        for setting in samplers:
            solver, steps = setting.split(":")
            model.config = model.config.replace(solver=solver, steps=int(steps))
            timer = StageTimer()
            results = model.predict(root, seed=args.seed, timer=timer)
            out[f"funflow6d_{setting}"] = {
                **_row(evaluate_bop(root, results)),
                "timing": timer.breakdown(),
            }
        if not (args.quick or args.no_baseline):
            baseline = functools.partial(ClassicBaseline, objects, encoder=FPFHEncoder())
            seconds, base = clocked(lambda: baseline(seed=args.seed).predict(root))
            out["baseline"] = {**_row(evaluate_bop(root, base)), "seconds": seconds}
    print(f"{'method':<22} {'AR':>6} {'AR_VSD':>7} {'AR_MSSD':>8} {'AR_MSPD':>8} {'ms/image':>9}")
    for name, row in out.items():
        if not isinstance(row, dict) or "AR" not in row:
            continue
        ms = row["timing"]["total_ms"] if "timing" in row else float("nan")
        print(
            f"{name:<22} {row['AR']:>6.3f} {row['AR_VSD']:>7.3f} {row['AR_MSSD']:>8.3f} "
            f"{row['AR_MSPD']:>8.3f} {ms:>9.0f}"
        )
    report(out, __file__)


if __name__ == "__main__":
    main()
