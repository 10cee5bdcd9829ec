"""``poseflow bench``: FunFlow6D's per-image latency, stage by stage, for several sampler settings.

Every image's instances go through one batched :meth:`FunFlow6D.estimate
<poseflow.models.FunFlow6D.estimate>` call (every ground-truth instance of the image, so a
generated split with ``--instances 8`` gives batches of 8, as in the paper's LM-O timing). For
each ``SOLVER:STEPS`` setting the first ``--warmup`` images run once untimed (kernel compilation,
lazy initialisation), then every image is timed with :class:`~poseflow.eval.timing.StageTimer`
(the paper's stages, and ``verification``, the render-and-compare check of the poses, which
``--no-verify`` turns off; on CUDA the timer synchronises at each stage boundary, so a second pass
without stage timing gives the end-to-end latency). The estimates are written as BOP results
CSVs and scored with the BOP 2019 AR when the split has test targets and Open3D can render VSD
(elsewhere ``poseflow eval DATASET OUT/results_SETTING.csv`` scores them later). The fastest
setting whose AR is within ``--ar-tolerance`` of the first (reference) setting is reported.

Without a dataset, a test split of the demo objects is generated in ``OUT/data`` (``--images``
images with ``--instances`` objects each) and reused by later runs with the same options.

Example::

    poseflow bench                                   # shipped model, generated 8-instance split
    poseflow bench --device cuda --samplers euler:50 euler:10 euler:5 heun:3
    poseflow bench data/lmo --model runs/paper/model --split test --images 50 --out runs/bench
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

from poseflow.cli.common import LOG, add_device_argument, add_model_argument, add_seed_argument
from poseflow.cli.options import add_inference_arguments

__all__ = [
    "BENCH_SEED",
    "DESCRIPTION",
    "HELP",
    "add_arguments",
    "benchmark_settings",
    "fastest_equal_setting",
    "generated_split",
    "parse_setting",
    "run",
]

DEFAULT_SETTINGS = ("euler:50", "euler:10", "euler:5", "heun:5")

#: ``bench``'s default seed (the other commands' is :data:`~poseflow.cli.common.DEFAULT_SEED`):
#: the generated split and the latencies of ``benchmarks/LOG.md`` and ``RESULTS.md`` were made
#: with seed 7, so that a plain ``poseflow bench`` reproduces them.
BENCH_SEED = 7


#: ``bench``'s line in ``poseflow --help``.
HELP = "per-image latency and stage breakdown of FunFlow6D for several sampler settings"

#: What ``poseflow bench --help`` says.
DESCRIPTION = """\
Time FunFlow6D per image, stage by stage (the paper's stages), for several sampler settings; write
each setting's BOP results CSV, score it with the BOP 2019 AR where Open3D can render VSD, and name
the fastest setting within --ar-tolerance of the first. Without DATASET, a test split of the demo
objects with --instances objects per image is generated in OUT/data (and reused)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options of ``poseflow bench`` (its ``run`` is :func:`run`)."""
    parser.add_argument(
        "dataset", nargs="?", default=None, help="BOP dataset folder (default: generate one)"
    )
    add_model_argument(parser)
    parser.add_argument("--out", default="bench_output", help="folder for everything written")
    parser.add_argument("--split", default="test", help="split folder (default: test)")
    parser.add_argument("--images", type=int, default=10, help="images to time (default: 10)")
    parser.add_argument(
        "--instances", type=int, default=8, help="objects per generated image (default: 8)"
    )
    parser.add_argument(
        "--samplers",
        nargs="+",
        default=list(DEFAULT_SETTINGS),
        metavar="SOLVER:STEPS",
        help=f"settings, the reference first (default: {' '.join(DEFAULT_SETTINGS)})",
    )
    add_inference_arguments(
        parser,
        sampler=False,
        set_help="change an inference-time config field (num_hypotheses, dense_points, "
        "flow_precision, appearance_precision, pose_solver, ransac_*, icp_*, verifier or "
        "verifier.FIELD; the sampler comes from "
        "--samplers); VALUE read as JSON, repeatable",
    )
    parser.add_argument("--warmup", type=int, default=1, help="untimed images per setting")
    parser.add_argument(
        "--ar-tolerance", type=float, default=0.01, help="AR a setting may lose and still count"
    )
    parser.add_argument("--no-eval", action="store_true", help="write the CSVs, skip the AR")
    add_seed_argument(parser, draws="the generated data, the noise and RANSAC", default=BENCH_SEED)
    add_device_argument(parser)


def parse_setting(text: str) -> tuple[str, int]:
    """``"euler:50"`` -> ``("euler", 50)``, checked against the known solvers.

    Raises:
        ValueRangeError: not ``SOLVER:STEPS``, an unknown solver, or fewer than 1 step.
    """
    from poseflow.errors import ValueRangeError
    from poseflow.flows import get_sampler

    solver, sep, steps = text.partition(":")
    if not sep or not steps.isdigit() or int(steps) < 1:
        raise ValueRangeError(f"a sampler setting is SOLVER:STEPS, e.g. euler:50; got {text!r}")
    get_sampler(solver, steps=int(steps))
    return solver, int(steps)


def benchmark_settings(
    model: Any,
    dataset: str | Path,
    settings: list[str],
    *,
    split: str = "test",
    max_images: int | None = None,
    warmup: int = 1,
    seed: int = BENCH_SEED,
    evaluate: bool = True,
    out_dir: str | Path | None = None,
    progress: bool = False,
) -> dict[str, dict[str, Any]]:
    """Time (and score) ``model`` on a BOP split once per sampler setting.

    Args:
        model: a :class:`~poseflow.models.FunFlow6D` with its objects prepared.
        dataset: the BOP dataset folder.
        settings: ``SOLVER:STEPS`` strings; the model's sampler is set to each in turn and
            restored afterwards.
        split: the split folder.
        max_images: time at most this many images.
        warmup: images run untimed before each setting's timing.
        seed: seeds the noise, sampling and RANSAC (the same for every setting).
        evaluate: score with the BOP 2019 AR (needs test targets and Open3D for VSD).
        out_dir: where ``results_SOLVER-STEPS.csv`` and ``timing_SOLVER-STEPS.json`` go (None:
            nothing written).
        progress: show progress bars.

    Returns:
        ``{setting: {"ms_per_image", "stages_ms", "percent", "instances_per_image", "AR", ...}}``:
        ``ms_per_image`` is the end-to-end mean (a separate unsynchronised pass on CUDA, the staged
        total on the CPU); ``AR``, ``AR_VSD``, ``AR_MSSD``, ``AR_MSPD`` and ``per_object`` only
        when evaluated.
    """
    import torch

    from poseflow.cli.predict import select_targets
    from poseflow.data.bop import BOPDataset
    from poseflow.eval import StageTimer, evaluate_bop, write_results

    ds = BOPDataset(dataset, split)
    targets = select_targets(ds, targets=None)  # every instance: the batch the image holds
    images = sorted({(t.scene_id, t.im_id) for t in targets})[:max_images]
    chosen = set(images)
    targets = [t for t in targets if (t.scene_id, t.im_id) in chosen]
    device = next(model.net.parameters()).device
    original = model.config
    out: dict[str, dict[str, Any]] = {}
    try:
        for text in settings:
            solver, steps = parse_setting(text)
            model.config = original.replace(solver=solver, steps=steps)
            if warmup > 0:
                model.predict(ds, targets=targets, max_images=warmup, seed=seed)
            timer = StageTimer()
            results = model.predict(ds, targets=targets, seed=seed, timer=timer, progress=progress)
            row: dict[str, Any] = timer.breakdown()
            row["ms_per_image"] = row["total_ms"]
            if device.type == "cuda":  # the staged pass synchronises at every boundary
                torch.cuda.synchronize(device)
                start = time.perf_counter()
                model.predict(ds, targets=targets, seed=seed)
                torch.cuda.synchronize(device)
                row["ms_per_image"] = 1000 * (time.perf_counter() - start) / len(images)
            row["instances_per_image"] = sum(t.inst_count for t in targets) / len(images)
            if evaluate:
                report = evaluate_bop(ds, results)
                row.update({k: report[k] for k in ("AR", "AR_VSD", "AR_MSSD", "AR_MSPD")})
                row["per_object"] = report["per_object"]
            if out_dir is not None:
                folder = Path(out_dir)
                folder.mkdir(parents=True, exist_ok=True)
                name = text.replace(":", "-")
                write_results(folder / f"results_{name}.csv", results)
                (folder / f"timing_{name}.json").write_text(json.dumps(row, indent=2))
            out[text] = row
    finally:
        model.config = original
    return out


def fastest_equal_setting(rows: dict[str, dict[str, Any]], tolerance: float) -> str | None:
    """The fastest setting whose AR is at most ``tolerance`` below the first's (None: no AR)."""
    names = list(rows)
    if not names or "AR" not in rows[names[0]]:
        return None
    floor = rows[names[0]]["AR"] - tolerance
    equal = [n for n in names if rows[n]["AR"] >= floor]
    return min(equal, key=lambda n: rows[n]["ms_per_image"])


def generated_split(
    root: str | Path, *, images: int, instances: int, seed: int, progress: bool = True
) -> Path:
    """A test split of the demo objects with ``instances`` objects per image, made once.

    The split is generated in ``root`` (targets down to ``visib_fract`` 0.3) and reused while
    ``images``, ``instances`` and ``seed`` stay the same.

    Returns:
        ``root`` as a :class:`~pathlib.Path`.
    """
    from poseflow.data.synthetic import generate_dataset

    root = Path(root)
    options = {"images": images, "instances": instances, "seed": seed}
    record = root / "bench_options.json"
    if record.is_file() and json.loads(record.read_text()) == options:
        LOG.info(f"reusing the generated split in {root}")
        return root
    LOG.info(f"generating {images} test images with {instances} objects each in {root}")
    generate_dataset(
        root,
        num_train_images=0,
        num_test_images=images,
        objects_per_image=instances,
        seed=seed,
        min_target_visib=0.3,
        progress=progress,
        overwrite=True,  # a split of other options is generated again in its place
    )
    record.write_text(json.dumps(options))
    return root


def _dataset(args: argparse.Namespace, out: Path, progress: bool) -> Path:
    """The dataset to time: ``args.dataset``, or a generated split in ``out/data``."""
    from poseflow.data.object_folder import check_dataset
    from poseflow.errors import ValueRangeError

    if args.dataset is not None:
        return check_dataset(args.dataset, args.split)
    if args.split != "test":
        raise ValueRangeError("a generated dataset has only the test split; drop --split")
    return generated_split(
        out / "data",
        images=args.images,
        instances=args.instances,
        seed=args.seed,
        progress=progress,
    )


def run(args: argparse.Namespace) -> int:
    """Time every setting, print the table and the stage breakdowns; returns 0."""
    import importlib.util

    from poseflow.cli.common import load_model, resolve_device, resolve_model, show_progress
    from poseflow.cli.options import inference_changes
    from poseflow.data.object_folder import load_object_models, object_cache_dir
    from poseflow.errors import ValueRangeError

    for name in ("images", "instances"):
        if getattr(args, name) < 1:
            raise ValueRangeError(f"--{name} must be at least 1, got {getattr(args, name)}")
    if args.warmup < 0:
        raise ValueRangeError(f"--warmup must be at least 0, got {args.warmup}")
    for text in args.samplers:
        parse_setting(text)  # fail before any work
    changes = inference_changes(args)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    device = resolve_device(args.device)
    show = show_progress(args)
    model_dir = resolve_model(args.model)
    model = load_model(model_dir, device=device, inference=changes)  # checked before any work
    root = _dataset(args, out, show)
    cache = object_cache_dir(model_dir, root)
    objects = load_object_models(root, progress=show)
    cache = cache if cache.is_dir() else out / "objects"
    model.prepare_objects(objects, cache_dir=cache, progress=show)
    targets_file = (root / "test_targets_bop19.json").is_file()
    can_render = importlib.util.find_spec("open3d") is not None
    evaluate = not args.no_eval and targets_file and can_render
    if not args.no_eval and not evaluate:
        why = "no test_targets_bop19.json" if not targets_file else "Open3D is not installed"
        LOG.info(f"note: AR not computed ({why}); score the CSVs with `poseflow eval` elsewhere")
    rows = benchmark_settings(
        model,
        root,
        list(args.samplers),
        split=args.split,
        max_images=args.images,
        warmup=args.warmup,
        seed=args.seed,
        evaluate=evaluate,
        out_dir=out,
        progress=show,
    )
    where = _device_name(device)
    first = next(iter(rows.values()))
    print(
        f"\nFunFlow6D on {where}: {first['num_images']} images, "
        f"{first['instances_per_image']:.1f} instances per image, hypotheses "
        f"{model.config.num_hypotheses}, verification {'on' if args.verify else 'off'}"
    )
    _print_settings(rows)
    _print_stages(rows)
    best = fastest_equal_setting(rows, args.ar_tolerance)
    if best is not None:
        ref = next(iter(rows))
        print(
            f"\nfastest setting within {args.ar_tolerance} AR of {ref}: {best} "
            f"({rows[best]['ms_per_image']:.1f} ms vs {rows[ref]['ms_per_image']:.1f} ms, "
            f"AR {rows[best]['AR']:.3f} vs {rows[ref]['AR']:.3f})"
        )
    report = {
        "device": where,
        "model": str(model_dir),
        "dataset": str(root),
        "config": model.config.to_dict(),
        "settings": rows,
        "fastest_equal_ar": best,
    }
    (out / "bench.json").write_text(json.dumps(report, indent=2))
    print(f"wrote {out}/bench.json and the results_*.csv / timing_*.json of every setting")
    return 0


def _device_name(device: Any) -> str:
    """``device`` with its GPU's name, or the CPU's architecture and threads."""
    import platform

    import torch

    from poseflow import get_num_threads

    if device.type == "cuda":
        return f"{device} ({torch.cuda.get_device_name(device)})"
    return f"{device} ({platform.machine()}, {get_num_threads()} threads)"


def _print_settings(rows: dict[str, dict[str, Any]]) -> None:
    """One line per setting: ms per image and the AR (``-`` where not computed)."""
    print(f"{'setting':<10} {'ms/image':>9} {'AR':>6} {'AR_VSD':>7} {'AR_MSSD':>8} {'AR_MSPD':>8}")
    for name, row in rows.items():
        ar = "".join(
            f" {row[k]:>{w}.3f}" if k in row else f" {'-':>{w}}"
            for k, w in (("AR", 6), ("AR_VSD", 7), ("AR_MSSD", 8), ("AR_MSPD", 8))
        )
        print(f"{name:<10} {row['ms_per_image']:>9.1f}{ar}")


def _print_stages(rows: dict[str, dict[str, Any]]) -> None:
    """The stage breakdown: one line per stage, ms per image and share for every setting."""
    stages = list(dict.fromkeys(s for row in rows.values() for s in row["stages_ms"]))
    print("\nstage breakdown, ms per image (share of the staged total):")
    print(f"{'stage':<20}" + "".join(f" {name:>16}" for name in rows))
    for stage in stages:
        cells = "".join(
            f" {row['stages_ms'].get(stage, 0.0):>8.1f} ({row['percent'].get(stage, 0.0):>4.1f}%)"
            for row in rows.values()
        )
        print(f"{stage:<20}{cells}")
