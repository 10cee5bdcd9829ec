"""Seconds per image of ``poseflow demo``'s work on 1 and on 2 CPU threads, stage by stage.

The shipped demo model estimates every target of a few generated images of the demo objects
(:meth:`FunFlow6D.predict <poseflow.models.FunFlow6D.predict>`, verification included) once per
thread count of ``--threads``, set with :func:`poseflow.set_num_threads` in this one process.
Each count first runs one untimed image (numba compilation, lazy set-up); then the counts take
turns, ``--repeats`` times, so that a change of the machine's load reaches every count alike, and
each stage keeps its fastest turn. Prints the table, the ratio to the first count (above 1:
faster), whether the poses agree, the load average (timings from a busy machine say how poseflow
shares it, not how fast it is), one JSON line and the command that reproduces it.

``python benchmarks/threads.py`` (``--quick`` for CI: one image, one turn, under a minute).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import sys
import tempfile
import time
from pathlib import Path

import torch

import poseflow
from poseflow.assets import DEMO_CHECKPOINT
from poseflow.cli.common import load_model
from poseflow.data.object_folder import load_object_models, object_cache_dir
from poseflow.data.synthetic import generate_dataset
from poseflow.eval import StageTimer


def _turn(model, root: Path, threads: int, images: int, seed: int) -> tuple[dict, torch.Tensor]:
    """One timed pass over ``images`` on ``threads`` threads: (breakdown, poses ``(E, 4, 4)``)."""
    timer = StageTimer()
    with poseflow.num_threads(threads):
        results = model.predict(root, max_images=images, seed=seed, timer=timer)
    return timer.breakdown(), results.poses


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="counts to time")
    parser.add_argument("--images", type=int, default=4, help="generated test images")
    parser.add_argument("--repeats", type=int, default=3, help="turns of every count")
    parser.add_argument("--model", default=str(DEMO_CHECKPOINT), help="FunFlow6D model folder")
    parser.add_argument("--seed", type=int, default=2026)
    parser.add_argument("--quick", action="store_true", help="one image, one turn (CI)")
    args = parser.parse_args()
    images, repeats = (1, 1) if args.quick else (args.images, args.repeats)
    counts = list(dict.fromkeys(args.threads))
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        root = generate_dataset(
            Path(tmp) / "data",
            num_train_images=0,
            num_test_images=images,
            seed=args.seed,
            progress=False,
        )
        model = load_model(args.model)
        objects = load_object_models(root)
        shipped = object_cache_dir(args.model, root)
        cache = shipped if shipped.is_dir() else Path(tmp)
        model.prepare_objects(objects, cache_dir=cache, progress=False)
        for n in counts:  # warm-up: numba compilation, lazy set-up
            _turn(model, root, n, 1, args.seed)
        best: dict[int, dict[str, float]] = {n: {} for n in counts}
        poses: dict[int, torch.Tensor] = {}
        start = time.perf_counter()
        for _ in range(repeats):
            for n in counts:
                row, poses[n] = _turn(model, root, n, images, args.seed)
                stages = {**row["stages_ms"], "total": row["total_ms"]}
                for stage, ms in stages.items():
                    best[n][stage] = min(best[n].get(stage, ms), ms)
        wall = time.perf_counter() - start
    load = max(load, os.getloadavg()[0])
    first = counts[0]
    stages = [s for s in best[first] if s != "total"] + ["total"]
    print(
        f"FunFlow6D, {images} demo image(s), s per image, fastest of {repeats} turn(s); "
        f"{platform.machine()}, {len(os.sched_getaffinity(0))} usable cores, "
        f"load average {load:.2f}"
    )
    print(f"{'stage':<22}" + "".join(f" {f'{n} thr':>8} {'speedup':>7}" for n in best))
    for stage in stages:
        cells = ""
        for n in best:
            s = best[n].get(stage, 0.0) / 1000
            ratio = best[first].get(stage, 0.0) / max(best[n].get(stage, 0.0), 1e-9)
            cells += f" {s:>8.3f} {ratio:>7.2f}"
        print(f"{stage:<22}{cells}")
    agree = {
        n: poses[n].shape == poses[first].shape
        and bool(torch.allclose(poses[n], poses[first], atol=1e-4))
        for n in best
    }
    print(f"poses agree with {first} thread(s) (1e-4): {agree}")
    summary = {
        "images": images,
        "repeats": repeats,
        "usable_cores": len(os.sched_getaffinity(0)),
        "load_average": round(load, 2),
        "s_per_image": {n: round(best[n]["total"] / 1000, 3) for n in best},
        "stages_s": {n: {s: round(v / 1000, 4) for s, v in best[n].items()} for n in best},
        "poses_agree": agree,
        "wall_s": round(wall, 1),
    }
    print(json.dumps(summary))
    print("reproduce:", shlex.join(["python", "benchmarks/threads.py", *sys.argv[1:]]))


if __name__ == "__main__":
    main()
