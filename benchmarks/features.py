"""Feature discriminativity and speed (the paper's "Feature discriminativity analysis").

A synthetic BOP test split of cluttered scenes is generated with the three demo objects
(``poseflow.data.synthetic``); for every visible instance (visib_fract >= 0.3) the target cloud
``T`` (<= 1,500 masked depth pixels) is matched against the object's query cloud ``Q`` (2,000
surface points) by mutual nearest neighbours in feature space, and the correspondences within 3 %
of the diameter under the ground-truth pose are counted (``poseflow.eval.inliers``). Reported:
the average number of inliers

- per geometric encoder: FPFH at 0.30 and 0.40 of the diameter (GeDi/dGeDi need weights that are
  not available offline: they appear only in the timings, with random weights);
- per appearance encoder and query representation: dense SIFT with the query features mean-pooled
  over 20 views (the paper's pooling) or kept per view and roll (20 views x 8 rolls) and selected
  per instance (``QueryFeatureBank.select``), and DINOv2 ViT-S/14 when its weights are on disk
  (otherwise a randomly initialised ViT-S as a control);
- per reduction of the dense-SIFT features to 64-d: none, none + L2 normalisation, PCA, UMAP with
  umap-learn's ``transform``, UMAP with poseflow's torch ``transform`` (the same fitted UMAP).

Timings per instance (CPU here): encoders, target lifting, and the reducer transform of 2,000
points, poseflow against umap-learn in the same run and on the same fitted UMAP, both warm (a
warm-up call, then the best of three; umap-learn's first call of the run, which includes its
numba compilation, is reported on its own line); FPFH's torch and compiled (numba) backends
against its Open3D backend, on one 2,000-point cloud and on a padded batch of 8 target clouds
of 256 points (FunFlow6D's batch).

Prints a table, one JSON line with every figure, writes ``features.json`` and a bar chart
``features.png`` to ``--out``, then the command. Run ``python benchmarks/features.py``
(``--quick`` for CI: fewer images and views).
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from _common import clocked, report, timed, timings

from poseflow.data.bop import BOPInstanceDataset
from poseflow.data.demo_objects import demo_objects
from poseflow.data.synthetic import generate_dataset
from poseflow.errors import MissingWeightsError
from poseflow.eval.inliers import correspondence_inliers
from poseflow.features import (
    DenseSIFTEncoder,
    DINOv2Encoder,
    FeatureCache,
    FPFHEncoder,
    GeDiEncoder,
    GeDiNet,
    IdentityReducer,
    PCAReducer,
    UMAPReducer,
    cached_query_features,
    lift_target_features,
)
from poseflow.geometry.pointcloud import backproject_depth
from poseflow.geometry.se3 import inverse_transform, transform_points

#: Points of each object's query cloud.
N_POINTS = 2000


def _warm_ms(fn, repeats: int = 3) -> float:
    """Best of ``repeats`` timed calls (ms), after one untimed warm-up call.

    JIT compilation, index preparation and caches are paid before the clock starts.
    """
    fn()
    return 1e3 * min(timings(fn, repeats)[0])


def _ms(fn, repeats: int = 3) -> tuple[float, object]:
    """Median of ``repeats`` timed calls (ms), without a warm-up call, and the last output."""
    seconds, out = timed(fn, repeats, warmup=False)
    return 1e3 * seconds, out


def _instances(root: Path, max_points: int, limit: int) -> list[dict]:
    ds = BOPInstanceDataset(root, "test", min_visib_fract=0.3)
    out = []
    gen = torch.Generator().manual_seed(0)
    for i in range(len(ds)):
        item = ds[i]
        if not item["valid"]:
            continue
        K = item["K"].float()
        cloud = backproject_depth(
            item["depth"][None].float(), K, item["mask"][None], max_points=max_points, generator=gen
        )
        if int(cloud.mask.sum()) < 50:
            continue
        pts = cloud.points[0][cloud.mask[0]]
        pix = cloud.pixels[0][cloud.mask[0]]
        canon = transform_points(inverse_transform(item["pose"].float()[None]), pts[None])[0]
        out.append(
            {
                "obj_id": int(item["obj_id"]),
                "rgb": item["rgb"].float(),
                "K": K,
                "points": pts,
                "pixels": pix,
                "canonical": canon,
            }
        )
        if len(out) >= limit:
            break
    return out


def _target_batch(
    instances: list[dict], objects: dict, size: int, n: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Up to ``size`` target clouds of at most ``n`` random points, padded; mask; diameters."""
    gen = torch.Generator().manual_seed(0)
    chosen = instances[:size]
    points = torch.zeros(len(chosen), n, 3)
    mask = torch.zeros(len(chosen), n, dtype=torch.bool)
    for b, inst in enumerate(chosen):
        pts = inst["points"]
        keep = pts[torch.randperm(len(pts), generator=gen)[:n]]
        points[b, : len(keep)], mask[b, : len(keep)] = keep, True
    diameters = torch.tensor([objects[inst["obj_id"]].diameter for inst in chosen])
    return points, mask, diameters


def _inliers(fq: torch.Tensor, ft: torch.Tensor, obj, inst: dict) -> int:
    res = correspondence_inliers(
        fq.float(), ft.float(), obj.points.float(), inst["canonical"], obj.diameter
    )
    return int(res.num_inliers)


@dataclass
class _Run:
    """What the measurements share: the objects, the instances and their features.

    ``banks`` holds the query features of every (encoder, object); ``targets`` the appearance of
    every instance per encoder, ``(M_i, G)``; ``selected`` the query features that each
    instance's per-view selection picked, per encoder ``(P, G)``.
    """

    objects: dict[int, Any]
    instances: list[dict]
    appearance: dict[str, tuple]
    banks: dict[tuple[str, int], Any] = field(default_factory=dict)
    targets: dict[str, list[torch.Tensor]] = field(default_factory=dict)
    selected: dict[str, list[torch.Tensor]] = field(default_factory=dict)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="small run for CI")
    parser.add_argument("--out", default="runs/bench_features", help="output folder")
    parser.add_argument("--images", type=int, default=None, help="test images to generate")
    parser.add_argument("--instances", type=int, default=None, help="instances to evaluate")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    n_images = args.images or (3 if args.quick else 12)
    n_inst = args.instances or (6 if args.quick else 30)
    views = 8 if args.quick else 20
    rolls = 4 if args.quick else 8

    root = out / f"data_{n_images}"
    if not (root / "test").is_dir():
        generate_dataset(
            root, None, num_train_images=0, num_test_images=n_images, images_per_scene=3,
            objects_per_image=3, seed=0, progress=False, overwrite=True,  # an interrupted one
        )  # fmt: skip
    objects = {i + 1: m for i, m in enumerate(demo_objects(num_points=N_POINTS, seed=0))}
    instances = _instances(root, 1500, n_inst)
    sift, (dino, dino_note) = DenseSIFTEncoder(input_size=128), _dinov2()
    appearance: dict[str, tuple] = {"dense SIFT": (sift, views, rolls)}
    if not args.quick:
        appearance["DINOv2"] = (dino, views, 1)
    run = _Run(objects, instances, appearance)
    query_s = _query_features(run, FeatureCache(out / "cache"))
    _target_features(run)

    fpfh = FPFHEncoder(backend="torch")
    results: dict[str, dict[str, float]] = {
        "geometric": {"FPFH 0.30+0.40": _geometric_inliers(run, fpfh)},
        "appearance": _appearance_inliers(run),
    }
    results["reduction"], fitted, cold_umap_learn = _reduction_inliers(run)

    timings_ms, fpfh_ratio = _encoder_timings(run, fpfh, sift, dino, quick=args.quick)
    red = fitted["UMAP", run.instances[0]["obj_id"]]  # the last fitted UMAP (per-view selection)
    speedup, large = _umap_timings(run, red, cold_umap_learn, timings_ms)
    timings_ms["query features per object, s (render+encode, or cache load)"] = {
        k: v / len(objects) for k, v in query_s.items()
    }

    summary = {
        "benchmark": "features",
        "machine": f"{platform.machine()} {platform.processor()}, torch threads {args.threads}",
        "instances": len(run.instances),
        "images": n_images,
        "query_views": views,
        "rolls": rolls,
        "dinov2": dino_note,
        "avg_inliers": results,
        "timings_ms": timings_ms,
        "umap_transform_speedup_warm": speedup,
        "umap_transform_speedup_warm_fit_5000": large,
        "fpfh_time_over_open3d": fpfh_ratio,
    }
    print(_table(len(run.instances), results, timings_ms, speedup, large, fpfh_ratio))
    (out / "features.json").write_text(json.dumps(summary, indent=2))
    _plot(results, out / "features.png")
    report(summary, __file__)


def _dinov2() -> tuple[DINOv2Encoder, str]:
    """DINOv2 ViT-S/14 with its local weights, else randomly initialised (a control)."""
    try:
        return DINOv2Encoder("vits14"), "DINOv2 ViT-S/14 (local weights)"
    except MissingWeightsError:
        from transformers import Dinov2Config, Dinov2Model

        torch.manual_seed(0)
        cfg = Dinov2Config(hidden_size=384, num_attention_heads=6, num_hidden_layers=12)
        note = "DINOv2 ViT-S/14, random init (control: no weights offline)"
        return DINOv2Encoder(Dinov2Model(cfg)), note


def _query_features(run: _Run, cache: FeatureCache) -> dict[str, float]:
    """Fill ``run.banks``, once per object and encoder (cached on disk); seconds per encoder."""
    seconds: dict[str, float] = {}
    for name, (enc, nv, nr) in run.appearance.items():
        t = time.perf_counter()
        for oid, obj in run.objects.items():
            run.banks[name, oid] = cached_query_features(
                cache, obj.name, enc, obj.mesh, obj.points, obj.diameter, num_views=nv, rolls=nr
            )
        seconds[name] = time.perf_counter() - t
    return seconds


def _target_features(run: _Run) -> None:
    """Fill ``run.targets``: every instance's appearance features, per encoder."""
    run.targets = {name: [] for name in run.appearance}
    for inst in run.instances:
        for name, (enc, _, _) in run.appearance.items():
            f = lift_target_features(
                enc, inst["rgb"][None], inst["points"][None], inst["K"], pixels=inst["pixels"][None]
            )
            run.targets[name].append(f[0])


def _geometric_inliers(run: _Run, fpfh: FPFHEncoder) -> float:
    """Average inliers of FPFH (0.30 and 0.40 of the diameter) over the instances."""
    q_fpfh = {
        oid: fpfh.encode(o.points[None].float(), None, None, o.diameter)[0]
        for oid, o in run.objects.items()
    }
    counts = []
    for inst in run.instances:
        obj = run.objects[inst["obj_id"]]
        ft = fpfh.encode(inst["points"][None], None, None, obj.diameter)[0]
        counts.append(_inliers(q_fpfh[inst["obj_id"]], ft, obj, inst))
    return statistics.mean(counts)


def _appearance_inliers(run: _Run) -> dict[str, float]:
    """Average inliers per encoder, query mean-pooled vs per-view selection (L2-normalised).

    Fills ``run.selected``.
    """
    rows = {}
    run.selected = {name: [] for name in run.appearance}
    for name in run.appearance:
        mean_c, sel_c = [], []
        for inst, ft in zip(run.instances, run.targets[name]):
            obj, bank = run.objects[inst["obj_id"]], run.banks[name, inst["obj_id"]]
            ftn = torch.nn.functional.normalize(ft, dim=-1)
            fq_mean = torch.nn.functional.normalize(bank.pooled(), dim=-1)
            mean_c.append(_inliers(fq_mean, ftn, obj, inst))
            fq_sel = bank.select(ft[None])[0]
            run.selected[name].append(fq_sel)
            sel_c.append(_inliers(torch.nn.functional.normalize(fq_sel, dim=-1), ftn, obj, inst))
        rows[f"{name}, mean over views"] = statistics.mean(mean_c)
        if run.banks[name, 1].rolls > 1 or name == "dense SIFT":
            rows[f"{name}, per-view selection"] = statistics.mean(sel_c)
    return rows


#: The reductions of dense SIFT to 64-d.
REDUCERS = {
    "none": lambda: IdentityReducer(normalize=False),
    "none + normalised": lambda: IdentityReducer(normalize=True),
    "PCA": lambda: PCAReducer(64),
    "UMAP": lambda: UMAPReducer(),
}


def _reduction_inliers(
    run: _Run,
) -> tuple[dict[str, float], dict[tuple[str, int], Any], tuple[float, int] | None]:
    """Average inliers of each reduction of dense SIFT, for both query representations.

    Returns:
        The rows, the reducers fitted for the last representation (per-view selection) by
        (reducer, object), and the ms and points of umap-learn's first transform of the run.
    """
    rows: dict[str, float] = {}
    cold: list[tuple[float, int]] = []  # (ms, points) of umap-learn's first call
    for rep in ("mean over views", "per-view selection"):
        fitted = {}
        for oid in run.objects:
            train = _reducer_training_rows(run.banks["dense SIFT", oid], rep)
            fitted.update({(rname, oid): make().fit(train) for rname, make in REDUCERS.items()})
        for rname in REDUCERS:
            variants = ["umap-learn transform", "poseflow transform"] if rname == "UMAP" else [""]
            for variant in variants:
                c = [
                    _reduced_inliers(run, k, fitted[rname, inst["obj_id"]], rep, variant, cold)
                    for k, inst in enumerate(run.instances)
                ]
                label = f"{rname} ({variant})" if variant else rname
                rows[f"{label}, SIFT {rep}"] = statistics.mean(c)
    return rows, fitted, cold[0] if cold else None


def _reducer_training_rows(bank: Any, rep: str) -> torch.Tensor:
    """The features a reducer is fitted on: the pooled query, or 2,000 seen bank entries."""
    if rep == "mean over views":
        return bank.pooled()
    seen = bank.features[bank.visible]  # a subsample, 2,000 rows like the pooled case
    pick = torch.randperm(len(seen), generator=torch.Generator().manual_seed(0))
    return seen[pick[:N_POINTS]]


def _reduced_inliers(
    run: _Run, k: int, red: Any, rep: str, variant: str, cold: list[tuple[float, int]]
) -> int:
    """Inliers of instance ``k`` after reducing both sides with ``red`` (umap-learn's or ours).

    The first umap-learn transform of the run (numba compiles) is timed into ``cold``.
    """
    inst, ft = run.instances[k], run.targets["dense SIFT"][k]
    bank = run.banks["dense SIFT", inst["obj_id"]]
    fq = bank.pooled() if rep == "mean over views" else run.selected["dense SIFT"][k]
    if variant == "umap-learn transform":
        seconds, rt = clocked(lambda: torch.from_numpy(red.transform_umap_learn(ft.numpy())))
        if not cold:  # the run's first call: numba compiles
            cold.append((seconds * 1e3, len(ft)))
        rq = torch.from_numpy(red.transform_umap_learn(fq.numpy()))
    else:
        rt = red.transform(ft)
        rq = red.transform(fq)
    return _inliers(rq, rt, run.objects[inst["obj_id"]], inst)


def _encoder_timings(
    run: _Run, fpfh: FPFHEncoder, sift: Any, dino: Any, *, quick: bool
) -> tuple[dict[str, Any], dict[str, float]]:
    """Per-instance encoder times (ms): 2,000 points for geometry, one crop for appearance.

    Returns:
        The timings and the torch and numba backends' FPFH time over Open3D's, per size.
    """
    timings_ms: dict[str, Any] = {}
    inst = run.instances[0]
    obj = run.objects[inst["obj_id"]]
    q = obj.points[None].float()
    batch, batch_mask, batch_diam = _target_batch(run.instances, run.objects, 8, 256)
    sizes = ("2000 points", f"{len(batch)} x 256 target points")
    backends = {
        "torch": fpfh,
        "numba": FPFHEncoder(backend="numba"),
        "Open3D": FPFHEncoder(backend="open3d"),
    }
    for name, enc in backends.items():
        timings_ms[f"FPFH ({name}), {sizes[0]}"], _ = _ms(
            lambda enc=enc: enc.encode(q, None, None, obj.diameter)
        )
        timings_ms[f"FPFH ({name}), {sizes[1]}"], _ = _ms(
            lambda enc=enc: enc.encode(batch, None, batch_mask, batch_diam)
        )
    fpfh_ratio = {
        f"{name} / Open3D, {s}": timings_ms[f"FPFH ({name}), {s}"]
        / timings_ms[f"FPFH (Open3D), {s}"]
        for name in ("torch", "numba")
        for s in sizes
    }
    crop = torch.rand(1, 3, 128, 128)
    timings_ms["dense SIFT encode, 128x128 crop"], _ = _ms(lambda: sift.encode(crop))
    timings_ms["DINOv2 ViT-S/14 encode, 224x224 crop"], _ = _ms(
        lambda: dino.encode(torch.rand(1, 3, 224, 224)), repeats=2
    )
    timings_ms["target lifting (crop+SIFT+sample)"], _ = _ms(
        lambda: lift_target_features(
            sift, inst["rgb"][None], inst["points"][None], inst["K"], pixels=inst["pixels"][None]
        )
    )
    torch.manual_seed(0)
    gedi = GeDiEncoder(GeDiNet(), samples_per_patch=512)
    sub = q[:, :: max(1, N_POINTS // (25 if quick else 100))]
    t_gedi, _ = _ms(lambda: gedi.encode(sub, None, None, obj.diameter), repeats=1)
    timings_ms["GeDi (random weights), 2000 points, extrapolated"] = (
        t_gedi * N_POINTS / sub.shape[1]
    )
    return timings_ms, fpfh_ratio


def _umap_timings(
    run: _Run, red: Any, cold: tuple[float, int] | None, timings_ms: dict[str, Any]
) -> tuple[float, float | None]:
    """UMAP transform of 2,000 points, poseflow against umap-learn, both warm, into ``timings_ms``.

    Returns:
        umap-learn's time over poseflow's, and the same for a UMAP fitted on 5,000 points (None
        when the bank has fewer seen rows).
    """
    x2000 = run.selected["dense SIFT"][0]
    # both warm: a warm-up call first, then the best of three
    t_ours = _warm_ms(lambda: red.transform(x2000))
    t_ref = _warm_ms(lambda: red.transform_umap_learn(x2000.numpy()))
    timings_ms["UMAP transform 2000 points, poseflow (warm)"] = t_ours
    timings_ms["UMAP transform 2000 points, umap-learn (warm)"] = t_ref
    if cold is not None:
        ms, n = cold
        timings_ms[f"UMAP transform, umap-learn's first call of the run ({n} points, cold)"] = ms
    # umap-learn transforms with exact pairwise distances (a Python metric per pair, through
    # scikit-learn) when it was fitted on fewer than 4,096 points, as above; fitted on more, it
    # searches its NN-descent index instead. The same comparison on a fit of 5,000 bank rows:
    bank = run.banks["dense SIFT", run.instances[0]["obj_id"]]
    seen = bank.features[bank.visible]
    if len(seen) < 5000:
        return t_ref / t_ours, None
    pick = torch.randperm(len(seen), generator=torch.Generator().manual_seed(1))[:5000]
    big = UMAPReducer().fit(seen[pick])
    t_big_ours = _warm_ms(lambda: big.transform(x2000))
    t_big_ref = _warm_ms(lambda: big.transform_umap_learn(x2000.numpy()))
    timings_ms["UMAP (fit on 5000) transform 2000 points, poseflow (warm)"] = t_big_ours
    timings_ms["UMAP (fit on 5000) transform 2000 points, umap-learn (warm)"] = t_big_ref
    return t_ref / t_ours, t_big_ref / t_big_ours


def _table(
    instances: int,
    results: dict[str, dict[str, float]],
    timings_ms: dict[str, Any],
    speedup: float,
    large: float | None,
    fpfh_ratio: dict[str, float],
) -> str:
    """The printed table: average inliers per group, then the timings and ratios."""
    lines = [f"{instances} instances, average inliers (mutual NN, 3% of the diameter)"]
    for group, rows in results.items():
        lines.append(f"[{group}]")
        lines += [f"  {k:<58s} {v:8.2f}" for k, v in rows.items()]
    lines.append("[timings, ms]")
    for k, v in timings_ms.items():
        lines.append(f"  {k:<58s} {v}" if isinstance(v, dict) else f"  {k:<58s} {v:10.1f}")
    lines.append(f"  UMAP transform speed-up, both warm (umap-learn / poseflow): {speedup:.1f}x")
    if large is not None:
        lines.append(f"  the same, UMAP fitted on 5,000 points: {large:.1f}x")
    lines.append(
        "  FPFH time against Open3D's: "
        + ", ".join(f"{key} {r:.2f}x" for key, r in fpfh_ratio.items())
    )
    return "\n".join(lines)


def _plot(results: dict[str, dict[str, float]], path: Path) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib missing: no chart", file=sys.stderr)
        return
    fig, axes = plt.subplots(1, 3, figsize=(16, 5), gridspec_kw={"width_ratios": [2, 1, 4]})
    for ax, group in zip(axes, ("appearance", "geometric", "reduction")):
        rows = results[group]
        ax.bar(range(len(rows)), list(rows.values()), color="tab:blue")
        ax.set_xticks(range(len(rows)), list(rows.keys()), rotation=60, ha="right", fontsize=7)
        ax.set_title(group)
        ax.set_ylabel("average inliers")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"chart: {path}", file=sys.stderr)


if __name__ == "__main__":
    main()
