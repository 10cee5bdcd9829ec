"""Wall-clock of the whole ``poseflow demo`` on 1 and on 2 threads, idle or beside a busy load.

Each run is a fresh ``poseflow demo --threads N`` process (imports, rendering the test images,
FunFlow6D, the classic baseline, scoring and overlays), timed from its start to its exit. The
counts take turns, ``--repeats`` times, so that a change of the machine's load reaches every
count alike; each count keeps its fastest run. ``--load K`` starts K busy processes (one core
each) for the whole benchmark: the competing load a shared machine has. Prints the table, the
ratio to one thread (above 1: faster), whether every run wrote the same poses, the load average,
one JSON line and the command that reproduces it.

``python benchmarks/demo_threads.py [--load 1]`` (``--quick`` for CI: two images, no baseline, one
turn).
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

from _common import machine, report


@contextlib.contextmanager
def busy_load(processes: int) -> Iterator[None]:
    """``processes`` busy loops in other processes for the duration of the block."""
    spin = [sys.executable, "-c", "while True: pass"]
    procs = [subprocess.Popen(spin) for _ in range(processes)]
    try:
        time.sleep(1.0 if procs else 0.0)
        yield
    finally:
        for p in procs:
            p.kill()
            p.wait()


def run_demo(threads: int, out: Path, quick: bool) -> float:
    """Seconds of one ``poseflow demo --threads THREADS --out OUT`` process."""
    command = [sys.executable, "-m", "poseflow.cli", "demo", "--out", str(out), "--no-progress"]
    if quick:
        command += ["--images", "2", "--no-baseline"]
    env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}
    start = time.perf_counter()
    done = subprocess.run([*command, "--threads", str(threads)], env=env, capture_output=True)
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        sys.exit(f"poseflow demo --threads {threads} failed:\n{done.stderr.decode()[-3000:]}")
    return seconds


def poses(out: Path) -> list[tuple[str, ...]]:
    """The rows of the demo's two CSVs but their time column."""
    rows = []
    for name in ("funflow6d.csv", "baseline.csv"):
        if not (out / name).is_file():
            continue
        with open(out / name, newline="") as f:
            rows += [tuple(v for k, v in r.items() if k != "time") for r in csv.DictReader(f)]
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="counts to time")
    parser.add_argument("--repeats", type=int, default=2, help="turns of every count")
    parser.add_argument("--load", type=int, default=0, help="busy processes beside the demo")
    parser.add_argument("--quick", action="store_true", help="a small demo, one turn (CI)")
    args = parser.parse_args()
    if args.quick:
        args.repeats = 1
    counts = list(dict.fromkeys(args.threads))
    seconds: dict[int, list[float]] = {n: [] for n in counts}
    outputs, loads = set(), []
    with tempfile.TemporaryDirectory() as tmp, busy_load(args.load):
        for turn in range(args.repeats):
            for n in counts:
                loads.append(os.getloadavg()[0])
                out = Path(tmp) / f"demo_{n}_{turn}"
                seconds[n].append(run_demo(n, out, args.quick))
                outputs.add(tuple(poses(out)))
    best = {n: min(s) for n, s in seconds.items()}
    first = best[counts[0]]
    print(f"poseflow demo, {args.load} busy processes beside it, fastest of {args.repeats} runs")
    print(f"{'threads':>8} {'seconds':>9} {'ratio':>7}   runs")
    for n in counts:
        runs = " ".join(f"{s:.1f}" for s in seconds[n])
        print(f"{n:>8} {best[n]:>9.1f} {first / best[n]:>7.2f}   {runs}")
    same = len(outputs) == 1
    print(f"same poses in every run: {same}; load average {min(loads):.1f}-{max(loads):.1f}")
    report(
        {
            "benchmark": "demo_threads",
            "busy_processes": args.load,
            "seconds": {str(n): [round(s, 2) for s in seconds[n]] for n in counts},
            "ratio": {str(n): round(first / best[n], 3) for n in counts},
            "same_poses": same,
            "load_average": [round(min(loads), 2), round(max(loads), 2)],
            "machine": machine(),
        },
        __file__,
    )


if __name__ == "__main__":
    main()
