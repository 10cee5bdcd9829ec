"""Forward time and peak memory of the trainable networks: PointDiT eager, compiled, shortcuts.

One forward pass of the DiT velocity net on a batch of ``B`` instances of ``2N`` points each
(``[Q ; T]``, ``num_query=N``), as in one Euler step of inference, for the ``paper`` preset at
``N = 1024`` and ``2048``; plus the gated cross-attention fusion of the same batch (run once per
image, before the sampler). Each (size, mode) case runs in its own subprocess so that its peak
memory is its own: on CUDA ``torch.cuda.max_memory_allocated``, on CPU the peak resident set size
(``ru_maxrss``) above the RSS before the first forward (torch's CPU allocator is invisible to
tracemalloc). The paper reports the DiT forward at 91 ms per image of about 8 instances on an A100.

Usage::

    python benchmarks/networks.py                  # paper preset, B=8, N=1024 and 2048
    python benchmarks/networks.py --quick          # tiny preset and sizes, for CI
    python benchmarks/networks.py --sizes 256 --batch 2 --threads 1

Prints one JSON line with every case and each mode's speed-up over eager, then the command that
reproduces it. Mode ``shortcuts`` is the eager model as FunFlow6D samples it: the batch holds
``--samples`` samples per instance sharing their query cloud (pinned), called with
``frozen_query=True, query_repeats=--samples``; against ``eager`` on the same inputs::

    python benchmarks/networks.py --preset small --sizes 64 --batch 48 --samples 12 \
        --modes eager shortcuts --threads 1 --repeats 20

On a CPU the default run is long: about 22 minutes at one thread on a shared
2-core x86_64 machine (each case runs its forward once to warm up, then ``--repeats`` times).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys

import torch
from _common import clocked, report, timings

from poseflow.flows.dit import PointDiT
from poseflow.fusion import GatedCrossAttentionFusion


def _rss_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def run_case(args: argparse.Namespace) -> dict:
    """Time one (N, mode) case in this process and return its figures."""
    device = torch.device(args.device)
    dtype = {"float32": torch.float32, "bfloat16": torch.bfloat16}[args.dtype]
    torch.manual_seed(0)
    model = PointDiT.from_preset(args.preset).to(device=device, dtype=dtype).eval()
    fusion_dim = 64 if args.preset != "tiny" else 8
    fusion = GatedCrossAttentionFusion(fusion_dim).to(device=device, dtype=dtype).eval()
    b, n, cond = args.batch, args.case_n, model.config.cond_dim
    gen = torch.Generator(device="cpu").manual_seed(1)
    x = torch.randn(b, 2 * n, 3, generator=gen).to(device=device, dtype=dtype)
    t = torch.rand(b, generator=gen).to(device=device, dtype=dtype)
    c = torch.randn(b, 2 * n, cond, generator=gen).to(device=device, dtype=dtype)
    g = torch.randn(2 * b, n, fusion_dim, generator=gen).to(device=device, dtype=dtype)
    s = torch.randn(2 * b, n, fusion_dim, generator=gen).to(device=device, dtype=dtype)
    mask = torch.ones(b, 2 * n, dtype=torch.bool, device=device)
    # every instance's samples share the pinned query cloud, as FunFlow6D samples them
    for value in (x, c):
        value[:, :n] = value[:: args.samples, :n].repeat_interleave(args.samples, dim=0)
    t = t[:: args.samples].repeat_interleave(args.samples)
    shortcuts = (
        {"frozen_query": True, "query_repeats": args.samples}
        if args.case_mode == "shortcuts"
        else {}
    )

    def dit() -> torch.Tensor:
        return net(x, t, condition=c, mask=mask, num_query=n, **shortcuts)

    net = torch.compile(model) if args.case_mode == "compiled" else model
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    rss0 = _rss_mib()
    with torch.inference_mode():
        first_s, _ = clocked(dit, device=device)
        times, _ = timings(dit, args.repeats, device=device)
        fusion(g[:1], s[:1])
        # Q and T of all B instances: 2B clouds of N points
        fusion_s, _ = clocked(lambda: fusion(g, s), device=device)
    if device.type == "cuda":
        peak = torch.cuda.max_memory_allocated(device) / 2**20
        peak_kind = "cuda_max_memory_allocated"
    else:
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 - rss0
        peak_kind = "cpu_peak_rss_above_start"
    return {
        "N": n,
        "points_per_instance": 2 * n,
        "mode": args.case_mode,
        "dit_forward_ms": round(1e3 * statistics.median(times), 2),
        "dit_forward_ms_all": [round(1e3 * v, 2) for v in times],
        "first_call_s": round(first_s, 2),
        "fusion_forward_ms": round(1e3 * fusion_s, 2),
        "peak_memory_mib": round(peak, 1),
        "peak_memory_kind": peak_kind,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="tiny preset and sizes (CI)")
    parser.add_argument("--preset", default=None, help="PointDiT preset (default: paper)")
    parser.add_argument("--sizes", type=int, nargs="+", default=None, help="N per cloud")
    parser.add_argument("--batch", type=int, default=None, help="instances per batch (8)")
    parser.add_argument("--repeats", type=int, default=None, help="timed calls after warm-up")
    parser.add_argument("--samples", type=int, default=1, help="samples per instance (1)")
    parser.add_argument(
        "--modes",
        nargs="+",
        default=["eager", "compiled"],
        choices=["eager", "compiled", "shortcuts"],
    )
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--dtype", default="float32", choices=["float32", "bfloat16"])
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    parser.add_argument("--case-n", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--case-mode", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.quick:
        args.preset = args.preset or "tiny"
        args.sizes = args.sizes or [16]
        args.batch = args.batch or 2
        args.repeats = args.repeats or 3
    args.preset = args.preset or "paper"
    args.sizes = args.sizes or [1024, 2048]
    args.batch = args.batch or 8
    args.repeats = args.repeats or 3
    if args.samples < 1 or args.batch % args.samples:
        parser.error(f"--samples must divide --batch ({args.batch}), got {args.samples}")
    if args.threads:
        torch.set_num_threads(args.threads)

    if args.case_n is not None:
        print(json.dumps(run_case(args)))
        return

    cases = []
    for n in args.sizes:
        for mode in args.modes:
            cmd = [sys.executable, *sys.argv, "--case-n", str(n), "--case-mode", mode]
            out = subprocess.run(cmd, capture_output=True, text=True, check=False)
            if out.returncode:
                lines = out.stderr.strip().splitlines() or [f"exit status {out.returncode}"]
                cases.append({"N": n, "mode": mode, "error": lines[-1]})
            else:
                cases.append(json.loads(out.stdout.strip().splitlines()[-1]))
    speedups: dict[str, dict[str, float]] = {}
    for n in args.sizes:
        by_mode = {c["mode"]: c for c in cases if c["N"] == n and "error" not in c}
        for mode in ("compiled", "shortcuts"):
            if {"eager", mode} <= by_mode.keys():
                ratio = by_mode["eager"]["dit_forward_ms"] / by_mode[mode]["dit_forward_ms"]
                speedups.setdefault(mode, {})[str(n)] = round(ratio, 3)
    with torch.device("meta"):
        params = sum(p.numel() for p in PointDiT.from_preset(args.preset).parameters())
    device = args.device
    if device.startswith("cuda"):
        device_name = torch.cuda.get_device_name(torch.device(device))
    else:
        device_name = platform.processor() or platform.machine()
    result = {
        "benchmark": "networks",
        "preset": args.preset,
        "dit_parameters": params,
        "batch": args.batch,
        "samples_per_instance": args.samples,
        "dtype": args.dtype,
        "device": device,
        "device_name": device_name,
        "cpu_count": os.cpu_count(),
        "torch_threads": args.threads or torch.get_num_threads(),
        "torch": torch.__version__,
        "cases": cases,
        "speedup_over_eager": speedups,
        "paper_dit_forward_ms_a100": 91.21,
    }
    report(result, __file__)


if __name__ == "__main__":
    main()
