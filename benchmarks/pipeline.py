"""FunFlow6D's per-image latency with 8 instances, by stage, next to the paper's breakdown.

Runs ``poseflow bench`` (:mod:`poseflow.cli.bench`) on a generated test split of the demo objects
with exactly ``--instances`` (8) objects per image, on the CPU and, when there is one, on the
GPU: Euler-50 (the paper's sampler) and faster settings, each with the paper's stage breakdown,
its AR, and the fastest setting that loses no AR (within ``--ar-tolerance``). The paper reports
1,016 ms per image on an A100 for LM-O (8 instances), Euler-50 integration being 37.5 % of it.

Prints each device's table, then a summary and one JSON line, then the command. Run
``python benchmarks/pipeline.py`` (``--quick`` for CI: one image, two settings, CPU only).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import torch
from _common import report

from poseflow.assets import DEMO_CHECKPOINT
from poseflow.cli import main as poseflow
from poseflow.cli.bench import generated_split

#: The paper's A100 breakdown for LM-O, ms per image (Euler-50 integration + flow network).
PAPER_MS = {"total": 1015.90, "integration_and_flow_net": 381.11 + 91.21}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default=str(DEMO_CHECKPOINT), help="FunFlow6D model folder")
    parser.add_argument("--dataset", default=None, help="BOP dataset (default: generate one)")
    parser.add_argument("--images", type=int, default=10)
    parser.add_argument("--instances", type=int, default=8)
    parser.add_argument("--samplers", nargs="+", default=None, help="SOLVER:STEPS settings")
    parser.add_argument("--devices", nargs="+", default=None, help="default: cpu (+ cuda)")
    parser.add_argument("--cpu-threads", type=int, default=1, help="torch threads on the CPU")
    parser.add_argument("--ar-tolerance", type=float, default=0.01)
    parser.add_argument("--out", default=None, help="output folder (default: temporary)")
    parser.add_argument("--quick", action="store_true", help="one image, two settings (CI)")
    args = parser.parse_args()
    devices = args.devices or ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    samplers = args.samplers or (
        ["euler:50", "euler:5"] if args.quick else ["euler:50", "euler:20", "euler:10", "euler:5"]
    )
    images = 1 if args.quick else args.images
    summary: dict = {"paper_a100_ms": PAPER_MS, "devices": {}}
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(args.out or tmp)
        dataset = args.dataset or generated_split(
            base / "data", images=images, instances=args.instances, seed=7, progress=False
        )
        for device in devices:
            out = base / device.replace(":", "-")
            command = [
                "bench", str(dataset), "--model", args.model, "--out", str(out),
                "--images", str(images),
                "--samplers", *samplers, "--device", device, "--no-progress",
                "--ar-tolerance", str(args.ar_tolerance),
            ]  # fmt: skip
            if device == "cpu":
                command += ["--threads", str(args.cpu_threads)]
            if poseflow(command) != 0:
                sys.exit(f"poseflow bench failed on {device}")
            bench = json.loads((out / "bench.json").read_text())
            rows = bench["settings"]
            summary["devices"][bench["device"]] = {
                "fastest_equal_ar": bench["fastest_equal_ar"],
                "settings": {
                    name: {
                        "ms_per_image": round(row["ms_per_image"], 1),
                        "AR": round(row["AR"], 4) if "AR" in row else None,
                        "instances_per_image": row["instances_per_image"],
                        "stages_ms": {k: round(v, 1) for k, v in row["stages_ms"].items()},
                    }
                    for name, row in rows.items()
                },
            }
    print(f"\n{'device':<40} {'setting':<10} {'ms/image':>9} {'vs paper':>9} {'AR':>6}")
    for where, dev in summary["devices"].items():
        for name, row in dev["settings"].items():
            ratio = row["ms_per_image"] / PAPER_MS["total"]
            mark = " <- fastest at equal AR" if name == dev["fastest_equal_ar"] else ""
            ar = f"{row['AR']:>6.3f}" if row["AR"] is not None else f"{'-':>6}"
            print(f"{where:<40} {name:<10} {row['ms_per_image']:>9.1f} {ratio:>8.2f}x {ar}{mark}")
    report(summary, __file__)


if __name__ == "__main__":
    main()
