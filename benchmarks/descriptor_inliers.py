"""Correspondence inliers of the appearance conditioning: dense SIFT against the learned descriptor.

On a BOP split's test images (devbench by default; ground-truth poses and visible masks are used
only to measure), every BOP19 target instance is observed as FunFlow6D observes it (``N`` points by
farthest-point sampling of the masked depth, the crop around their barycentre), and paired with
its object's query cloud (``N`` points, features lifted from ``query_views`` renderings). The
mutual nearest neighbours (cosine) of the query's and the target's appearance features are
counted as inliers when their two points lie within 10 % (and 5 %) of the diameter under the
ground-truth pose, next to the count perfect features (the true canonical coordinates) give on
the same clouds, the ceiling. Two feature stages are scored:

- ``conditioning``: what the flow network is fed (``FlowInputs.semantic``: the query pooled as the
  encoder asks, then the object's PCA reducer), as ``benchmarks/diagnose.py`` scores it;
- ``symmetric``: the same features, a match confirmed by any one symmetric equivalent of the
  ground truth (the object's ``models_info.json`` symmetries; the equivalent that confirms the
  most counts, :func:`~poseflow.eval.correspondence_inliers` with ``equivalents``), which is what
  a symmetric object's pose needs; equal to ``conditioning`` for asymmetric objects;
- ``raw``: the encoder's features before the reducer.

Encoders: ``dsift`` (poseflow's default, ``query_pooling="select"``), the learned descriptor with
its own ``"mean"`` pooling and with ``"select"``, and with ``--surface FOLDER`` a surface
embedding of the dataset's objects (:mod:`poseflow.features.surface_training`; the query's
features are its keys, the reducer keeps its width when under 64). The same generator seed gives
every encoder the same target points. Prints a table per ``N``, one JSON line and the command.
Run ``python benchmarks/descriptor_inliers.py [DATASET] [--learned FOLDER] [--surface
FOLDER]``; ``--quick`` (CI) scores two images with ``N = 64`` and four query views.
"""

from __future__ import annotations

import argparse
import functools
import statistics
from collections import defaultdict
from pathlib import Path

import _common
import torch
from _common import clocked, target_instances

from poseflow.data import ImageInstances
from poseflow.data.bop import BOPDataset
from poseflow.data.object_folder import load_object_models
from poseflow.eval.inliers import correspondence_inliers
from poseflow.features.learned import SHIPPED_DESCRIPTOR_DIR, LearnedAppearanceEncoder
from poseflow.flows import pad_maps
from poseflow.models import FunFlow6D, FunFlow6DConfig
from poseflow.models.components import build_appearance_encoder
from poseflow.models.inputs import equivalent_maps

DEVBENCH = Path("/work/shared/devbench")
THRESHOLDS = (0.10, 0.05)
STAGES = ("conditioning", "symmetric", "raw")
ENCODERS = ("dsift", "learned/mean", "learned/select", "surface")


def _encoders(learned: Path | None, surface: Path | None) -> list[tuple[str, str, str | None]]:
    """``(label, appearance_encoder name, query_pooling override)`` of each scored encoder."""
    out: list[tuple[str, str, str | None]] = [("dsift", "dsift", None)]
    if learned is not None:
        out += [
            ("learned/mean", f"learned:{learned}", "mean"),
            ("learned/select", f"learned:{learned}", "select"),
        ]
    if surface is not None:
        out.append(("surface", f"surface:{surface}", None))
    return out


def _images(ds: BOPDataset, max_images: int | None) -> dict[tuple[int, int], set[int]]:
    """``{(scene, image): {obj_id}}`` of the BOP19 targets on the first ``max_images`` images."""
    images: dict[tuple[int, int], set[int]] = defaultdict(set)
    for t in ds.test_targets():
        images[(t.scene_id, t.im_id)].add(t.obj_id)
    keep = sorted(images)[:max_images]
    return {k: images[k] for k in keep}


def measure(
    root: Path,
    images: dict[tuple[int, int], set[int]],
    objects: dict,
    name: str,
    pooling: str | None,
    *,
    num_points: int,
    crop_size: int,
    query_views: int,
    seed: int,
) -> dict:
    """Inliers per object of one encoder at one ``N``: ``{stage: {threshold: {obj: [..]}}}``."""
    cfg = FunFlow6DConfig(
        num_points=num_points,
        crop_size=crop_size,
        query_views=query_views,
        appearance_encoder=name,
        geometric_encoder="none",
        verifier=None,
        feature_dim=min(64, build_appearance_encoder(name, crop_size=crop_size).dim),
    )
    model = FunFlow6D(cfg)
    if pooling is not None and isinstance(model.appearance_encoder, LearnedAppearanceEncoder):
        model.appearance_encoder.query_pooling = pooling
    prepare_s, _ = clocked(lambda: model.prepare_objects(objects, progress=False))
    ds = BOPDataset(root, "test")
    g = torch.Generator().manual_seed(seed)
    res: dict = {s: {th: defaultdict(list) for th in THRESHOLDS} for s in (*STAGES, "ceiling")}
    observe_s = 0.0
    for (s, i), wanted in sorted(images.items()):
        obj_ids, masks, gt, *image = target_instances(ds.scene(s), i, wanted)
        with torch.no_grad():
            instances = ImageInstances(*image, masks, obj_ids)
            observe = functools.partial(model.observe, instances, generator=g)
            seconds, obs = clocked(observe)
            observe_s += seconds
            inputs = model.flow_inputs(obs, poses=gt)
        n = num_points
        B = len(obj_ids)
        pooled = model.appearance_encoder.query_pooling
        raw_q = []
        for b, o in enumerate(obj_ids):
            bank = model.objects[o].bank
            if not bool(obs.valid[b]):  # too few points: not scored
                raw_q.append(torch.zeros_like(obs.appearance[b]))
            elif pooled == "select":
                raw_q.append(bank.select(obs.appearance[b : b + 1], obs.mask[b : b + 1])[0])
            else:
                raw_q.append(bank.pooled())
        feats = {
            "conditioning": (inputs.semantic[:, :n], inputs.semantic[:, n:]),
            "symmetric": (inputs.semantic[:, :n], inputs.semantic[:, n:]),
            "raw": (torch.stack(raw_q).to(obs.appearance), obs.appearance),
            "ceiling": (inputs.x_1[:, :n], inputs.x_1[:, n:]),
        }
        maps = pad_maps(
            [equivalent_maps(objects[o].symmetries, objects[o].diameter / 2) for o in obj_ids],
            dtype=inputs.x_1.dtype,
        )
        for stage, (fq, ft) in feats.items():
            for th in THRESHOLDS:
                r = correspondence_inliers(
                    fq, ft, inputs.points[:, :n], inputs.x_1[:, n:], torch.full((B,), 2.0), th,
                    t_mask=inputs.mask[:, n:],
                    metric="euclidean" if stage == "ceiling" else "cosine",
                    equivalents=maps if stage == "symmetric" else None,
                )  # fmt: skip
                for b, o in enumerate(obj_ids):
                    if bool(obs.valid[b]):
                        res[stage][th][o].append(float(r.num_inliers[b]))
    return {"inliers": res, "prepare_s": prepare_s, "observe_s": observe_s}


def _mean(v: list[float]) -> float:
    return round(statistics.fmean(v), 2) if v else float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("dataset", nargs="?", default=str(DEVBENCH), help="BOP dataset folder")
    parser.add_argument(
        "--learned",
        default=None,
        help="learned descriptor folder (default: the shipped weights, when present)",
    )
    parser.add_argument(
        "--surface",
        default=None,
        help="also a surface embedding of its objects (poseflow.features.surface_training)",
    )
    parser.add_argument("--points", type=int, nargs="+", default=[64, 256], help="N values")
    parser.add_argument("--crop-size", type=int, default=96)
    parser.add_argument("--query-views", type=int, default=12)
    parser.add_argument("--max-images", type=int, default=None)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--encoders",
        nargs="+",
        choices=ENCODERS,
        default=list(ENCODERS),
        help="the encoders to score (the learned ones need a descriptor folder)",
    )
    parser.add_argument("--quick", action="store_true", help="two images, N = 64, 4 query views")
    args = parser.parse_args()
    if args.quick:
        args.max_images, args.points, args.query_views = 2, [64], 4
    torch.set_num_threads(1)
    learned = Path(args.learned) if args.learned else None
    if learned is None and (SHIPPED_DESCRIPTOR_DIR / "model.safetensors").is_file():
        learned = SHIPPED_DESCRIPTOR_DIR
    root = Path(args.dataset)
    ds = BOPDataset(root, "test")
    images = _images(ds, args.max_images)
    obj_set = sorted({o for v in images.values() for o in v})
    surface = Path(args.surface) if args.surface else None
    encoders = [e for e in _encoders(learned, surface) if e[0] in args.encoders]
    report: dict = {
        "benchmark": "descriptor_inliers",
        "dataset": root.name,
        "images": len(images),
        "learned": str(learned) if learned else None,
        "surface": str(surface) if surface else None,
        "crop_size": args.crop_size,
        "query_views": args.query_views,
        "results": {},
    }
    for N in args.points:
        objects = load_object_models(root, obj_ids=obj_set)
        per_n: dict = {}
        for label, name, pooling in encoders:
            out = measure(
                root, images, objects, name, pooling, num_points=N, crop_size=args.crop_size,
                query_views=args.query_views, seed=args.seed,
            )  # fmt: skip
            per_n[label] = out
        summary = _summary(per_n, obj_set)
        report["results"][str(N)] = summary
        _print_summary(N, summary, per_n, obj_set)
    _common.report(report, __file__)


def _summary(per_n: dict, obj_set: list[int]) -> dict:
    """Mean inliers per object and overall: the ceiling, then each encoder's stages and times."""

    def means(d: dict) -> dict[str, float]:
        return {
            **{str(o): _mean(d[o]) for o in obj_set},
            "all": _mean([x for o in obj_set for x in d[o]]),
        }

    ceiling = next(iter(per_n.values()))["inliers"]["ceiling"]
    summary: dict = {"ceiling": {str(th): means(ceiling[th]) for th in THRESHOLDS}, "encoders": {}}
    for label, out in per_n.items():
        entry: dict = {
            "prepare_s": round(out["prepare_s"], 1),
            "observe_s": round(out["observe_s"], 1),
        }
        for stage in STAGES:
            for th in THRESHOLDS:
                entry[f"{stage}@{th}"] = means(out["inliers"][stage][th])
        summary["encoders"][label] = entry
    return summary


def _print_summary(N: int, summary: dict, per_n: dict, obj_set: list[int]) -> None:
    """The tables of one ``N``: per stage and threshold, each encoder's row and the ceiling."""
    ceiling = next(iter(per_n.values()))["inliers"]["ceiling"]
    instances = sum(len(ceiling[THRESHOLDS[0]][o]) for o in obj_set)
    print(f"\nN = {N}: mean mutual-NN inliers per instance ({instances} instances)")
    cols = [str(o) for o in obj_set] + ["all"]
    for stage in STAGES:
        for th in THRESHOLDS:
            print(f"\n{stage}, within {th:.0%} of the diameter")
            print(f"{'':<16}" + "".join(f"{c:>8}" for c in cols))
            for label in per_n:
                row = summary["encoders"][label][f"{stage}@{th}"]
                print(f"{label:<16}" + "".join(f"{row[c]:>8.2f}" for c in cols))
            row = summary["ceiling"][str(th)]
            print(f"{'ceiling':<16}" + "".join(f"{row[c]:>8.2f}" for c in cols))
    for label in per_n:
        e = summary["encoders"][label]
        print(f"{label}: query preparation {e['prepare_s']} s, observation {e['observe_s']} s")


if __name__ == "__main__":
    main()
