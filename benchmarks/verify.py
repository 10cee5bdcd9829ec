"""Render-and-compare verification of an estimator's results, and the renderer it uses.

Re-scores the estimates of a BOP results CSV made without verification (e.g. ``poseflow predict
DATASET --method baseline --no-verify``) with :class:`poseflow.verify.PoseVerifier`: for every
image, each estimate is expanded with its object's near-symmetric candidates, the best are refined
by ICP of the observed cloud (the masked depth, lifted and thinned as the classic baseline does)
onto the model, all are scored against the RGB-D image, and a candidate replaces the estimate only
where it clearly beats it. Writes the verified CSV (score = the verifier's, time = the estimator's
plus the verification's) for ``poseflow eval DATASET CSV``, and prints one JSON line: the time the
verification added per image (wall and CPU time of the process, the fastest of ``--repeats`` runs
per image; one thread unless ``OMP_NUM_THREADS`` says otherwise), how many estimates it replaced
per object, and the time to prepare each object; then the command.

``--renderers`` also measures the z-buffered point renderer the verifier uses against the
library's Open3D ray caster (one thread) on the same hypotheses (each rendered on the verifier's
crop, the ray caster one call per hypothesis): time per batch, how far apart their depth,
silhouette and colour are, and whether the verifier scores and chooses the same with either.

Run ``python benchmarks/verify.py DATASET --results CSV --out CSV`` (``--quick``: 4 images).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from _common import clocked, report

from poseflow.cli.options import parse_set
from poseflow.data import ImageInstances
from poseflow.data.bop import BOPDataset
from poseflow.data.object_folder import load_object_models
from poseflow.eval.results import PoseResults, read_results, write_results
from poseflow.geometry.pointcloud import (
    backproject_depth,
    remove_statistical_outliers,
    voxel_downsample,
)
from poseflow.verify import (
    PointRendering,
    PoseVerifier,
    VerifierConfig,
    crop_intrinsics,
    crop_observation,
    render_points,
    score_renderings,
    select_significant,
)


def observed_clouds(
    depth: torch.Tensor, K: torch.Tensor, masks: torch.Tensor, diameters: list[float]
) -> tuple[torch.Tensor, torch.Tensor]:
    """The classic baseline's target clouds: lift, drop outliers, thin to 4 % of the diameter."""
    cloud = backproject_depth(depth.expand(masks.shape[0], *depth.shape), K, masks)
    ok = cloud.mask & remove_statistical_outliers(cloud.points, cloud.mask)
    parts = []
    for b, d in enumerate(diameters):
        idx, vok = voxel_downsample(cloud.points[b : b + 1], 0.04 * d, ok[b : b + 1])
        parts.append(cloud.points[b, idx[0][vok[0]]])
    M = max(1, max(p.shape[0] for p in parts))
    points = torch.zeros(len(parts), M, 3, dtype=K.dtype)
    mask = torch.zeros(len(parts), M, dtype=torch.bool)
    for b, p in enumerate(parts):
        points[b, : p.shape[0]], mask[b, : p.shape[0]] = p, True
    return points, mask


def assign_masks(
    poses: torch.Tensor, obj_ids: list[int], gt_obj: list[int], masks: list[torch.Tensor], K
) -> list[int]:
    """The visible GT mask each estimate was made from.

    The mask of the same object nearest to the estimate's projected centre (this only matters
    where an image holds one object twice).
    """
    centres = []
    for m in masks:
        vv, uu = m.nonzero(as_tuple=True)
        centres.append(torch.stack((uu.double().mean(), vv.double().mean())) if len(vv) else None)
    taken: set[int] = set()
    out = []
    for pose, obj in zip(poses, obj_ids):
        c = K.double() @ pose[:3, 3].double()
        uv = c[:2] / c[2]
        best, best_d = -1, float("inf")
        for g, (o, centre) in enumerate(zip(gt_obj, centres)):
            if o != obj or g in taken or centre is None:
                continue
            d = float((centre - uv).norm())
            if d < best_d:
                best, best_d = g, d
        out.append(best)
        taken.add(best)
    return out


def compare_renderers(verifier: PoseVerifier, models: dict, batches: list, repeats: int) -> dict:
    """Point renderer vs Open3D ray caster on the verifier's crops, same hypotheses."""
    from poseflow.render.raycast import Renderer

    casters = {o: Renderer([models[o].mesh], nthreads=1) for o in models}
    t_points, t_rays, ious, depth_err, color_err = [], [], [], [], []
    total_diff, same_best, same_choice = [], [], []
    for batch in batches:
        crops = _Crops.of(verifier, batch)
        for _ in range(repeats):
            seconds, ours = clocked(lambda crops=crops: crops.points(verifier))
            t_points.append(seconds)
            seconds, theirs = clocked(lambda crops=crops: crops.rays(casters))
            t_rays.append(seconds)
        for iou, dz, dc in crops.differences(ours, theirs):
            ious.append(iou)
            depth_err.append(dz)
            color_err.append(dc)
        # what matters: the verifier's scores and choices with either rendering
        diff, best, choice = crops.score_agreement(verifier.config, ours, theirs)
        total_diff += diff
        same_best += best
        same_choice += choice
    return {
        "points_ms_per_batch": 1000 * statistics.median(t_points),
        "raycast_ms_per_batch": 1000 * statistics.median(t_rays),
        "speedup": statistics.median(t_rays) / statistics.median(t_points),
        "mask_iou_median": statistics.median(ious),
        "mask_iou_min": min(ious),
        "depth_diff_median_over_diameter": statistics.median(depth_err),
        "color_abs_diff_mean": statistics.mean(color_err),
        "total_score_abs_diff_median": statistics.median(total_diff),
        "total_score_abs_diff_max": max(total_diff),
        "same_best_hypothesis": f"{sum(same_best)}/{len(same_best)}",
        "same_choice": f"{sum(same_choice)}/{len(same_choice)}",
        "renderings": len(ious),
    }


@dataclass
class _Crops:
    """The verifier's crops of one image's ``B`` instances and their ``H`` hypotheses.

    ``batch`` is ``(rgb, depth, K, masks, obj_ids, hyps)`` with poses ``hyps`` ``(B, H, 4, 4)``;
    ``boxes`` ``(B, 4)`` and ``Kc`` ``(B, 3, 3)`` are the crops and their intrinsics, ``S`` their
    side; ``pts``, ``nrm``, ``col`` are the objects' clouds ``(B, P, 3)`` and ``diam``,
    ``pixel`` ``(B,)`` their diameters and the crops' pixel size at unit depth.
    """

    batch: tuple
    S: int
    boxes: torch.Tensor
    Kc: torch.Tensor
    objs: list
    pts: torch.Tensor
    nrm: torch.Tensor
    col: torch.Tensor
    diam: torch.Tensor
    pixel: torch.Tensor

    @classmethod
    def of(cls, verifier: PoseVerifier, batch: tuple) -> _Crops:
        """The crops of ``batch`` as the verifier makes them."""
        _, _, K, masks, obj_ids, hyps = batch
        S = verifier.config.crop_size
        boxes = verifier.crop_boxes(hyps[:, 0], obj_ids, K, masks)
        objs = [verifier.objects[o] for o in obj_ids]
        return cls(
            batch,
            S,
            boxes,
            crop_intrinsics(K, boxes, S),
            objs,
            torch.stack([o.points for o in objs]).double(),
            torch.stack([o.normals for o in objs]).double(),
            torch.stack([o.colors for o in objs]).double(),
            torch.tensor([o.diameter for o in objs], dtype=torch.float64),
            (boxes[:, 2] - boxes[:, 0]) / S / K[:2, :2].diagonal().min(),
        )

    def points(self, verifier: PoseVerifier) -> PointRendering:
        """The point renderer's rendering of every hypothesis, as the verifier renders."""
        hyps = self.batch[5]
        return render_points(
            self.pts, self.nrm, self.col, hyps, self.Kc, self.S,
            surface_tolerance=2 * self.pixel * hyps[:, 0, 2, 3],
            occlusion_tolerance=verifier.config.occlusion_tolerance * self.diam,
        )  # fmt: skip

    def rays(self, casters: dict) -> list:
        """The ray caster's rendering (albedo only) of every hypothesis, one call each."""
        from poseflow.render.raycast import Light

        obj_ids, hyps = self.batch[4], self.batch[5]
        albedo = Light(ambient=1.0, diffuse=0.0)
        out = []
        for b, o in enumerate(obj_ids):
            for h in range(hyps.shape[1]):
                out.append(
                    casters[o].render(hyps[b, h][None], self.Kc[b], self.S, self.S, light=albedo)
                )
        return out

    def differences(self, ours: PointRendering, theirs: list) -> list[tuple[float, float, float]]:
        """Per rendering seen by both: mask IoU, median depth gap / diameter, mean colour gap."""
        H = self.batch[5].shape[1]
        out = []
        for i, ref in enumerate(theirs):
            b, h = divmod(i, H)
            a, r = ours.mask[b, h], ref.masks_full[0]
            union = int((a | r).sum())
            if union == 0:
                continue
            both = a & r
            dz = (ours.depth[b, h][both] - ref.depth.double()[both]).abs()
            albedo_img = ref.rgb.double().permute(2, 0, 1) / 255.0
            dc = (ours.color[b, h][:, both] - albedo_img[:, both]).abs().mean()
            out.append(
                (int(both.sum()) / union, float(dz.median() / self.objs[b].diameter), float(dc))
            )
        return out

    def score_agreement(
        self, cfg: VerifierConfig, ours: PointRendering, theirs: list
    ) -> tuple[list[float], list[bool], list[bool]]:
        """The verifier's scores with either rendering: total gaps, same best, same choice."""
        rgb, depth, _, masks, _, hyps = self.batch
        B, H, S = hyps.shape[0], hyps.shape[1], self.S
        rays = PointRendering(
            depth=torch.stack([r.depth.double() for r in theirs]).reshape(B, H, S, S),
            mask=torch.stack([r.masks_full[0] for r in theirs]).reshape(B, H, S, S),
            color=torch.stack([r.rgb.double().permute(2, 0, 1) / 255 for r in theirs]).reshape(
                B, H, 3, S, S
            ),
        )
        observed = crop_observation(depth, masks, self.boxes, S, rgb)
        kw = {
            "depth_tolerance": cfg.depth_tolerance * self.diam,
            "visibility_tolerance": cfg.visibility_tolerance * self.diam,
            "appearance_window": cfg.appearance_window,
            "contrast_reference": cfg.contrast_reference,
            "weights": (cfg.depth_weight, cfg.silhouette_weight, cfg.appearance_weight),
            "block_size": cfg.block_size,
        }
        s_points = score_renderings(ours, observed, **kw)
        s_rays = score_renderings(rays, observed, **kw)
        choice = [
            select_significant(x, significance=cfg.significance)[0] for x in (s_points, s_rays)
        ]
        return (
            (s_points.total - s_rays.total).abs().flatten().tolist(),
            (s_points.total.argmax(-1) == s_rays.total.argmax(-1)).tolist(),
            (choice[0] == choice[1]).tolist(),
        )


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("dataset", type=Path)
    p.add_argument("--results", type=Path, required=True, help="estimates to verify (BOP CSV)")
    p.add_argument("--out", type=Path, required=True, help="verified results CSV to write")
    p.add_argument("--split", default="test")
    p.add_argument("--quick", action="store_true", help="4 images only")
    p.add_argument("--renderers", action="store_true", help="also compare the two renderers")
    p.add_argument(
        "--repeats", type=int, default=1, help="verify each image this often, keep the fastest"
    )
    p.add_argument(
        "--set", nargs="*", default=[], metavar="FIELD=VALUE", help="VerifierConfig fields"
    )
    args = p.parse_args(argv)

    overrides = parse_set(args.set)
    config = VerifierConfig.from_dict({**VerifierConfig().to_dict(), **overrides})
    results = read_results(args.results)
    ds = BOPDataset(args.dataset, args.split)
    obj_ids = sorted(set(results.obj_ids.tolist()))
    models = load_object_models(args.dataset, obj_ids=obj_ids)
    verifier = PoseVerifier(config)
    prepare_s = {}
    for o in obj_ids:
        seconds, _ = clocked(lambda o=o: verifier.prepare(o, models[o]))
        prepare_s[o] = round(seconds, 2)

    images = sorted(set(zip(results.scene_ids.tolist(), results.im_ids.tolist())))
    if args.quick:
        images = images[:4]
    parts, added, added_cpu, by_count = [], [], [], {}
    replaced, per_object, batches = Counter(), Counter(), []
    for s, i in images:
        rows, ids, out, (elapsed, cpu), batch = _verify_image(
            verifier, ds.scene(s), (s, i), results, args.repeats, renderers=args.renderers
        )
        added.append(elapsed)
        added_cpu.append(cpu)
        by_count.setdefault(len(ids), []).append(cpu)
        for o, c in zip(ids, out.chosen.tolist()):
            per_object[o] += 1
            replaced[o] += int(c != 0)
        if args.renderers:
            batches.append(batch)
        parts.append(
            PoseResults.from_columns(
                results.scene_ids[rows],
                results.im_ids[rows],
                results.obj_ids[rows],
                out.scores,
                out.poses,
                results.times[rows] + elapsed,
            )
        )
    write_results(args.out, PoseResults.concat(parts))
    record = {
        "benchmark": "verify",
        "dataset": str(args.dataset),
        "images": len(images),
        "instances": sum(per_object.values()),
        "threads": torch.get_num_threads(),
        "repeats": args.repeats,
        **_times_ms(added, added_cpu, by_count),
        "load_average": list(os.getloadavg()),
        "replaced": {str(o): f"{replaced[o]}/{per_object[o]}" for o in sorted(per_object)},
        "prepare_s": {str(o): t for o, t in prepare_s.items()},
        "candidates": {str(o): len(verifier.objects[o].candidates) for o in obj_ids},
        "config": {k: v for k, v in config.to_dict().items() if k in overrides},
        "machine": f"{platform.machine()} {platform.system()}, torch {torch.__version__}",
    }
    if args.renderers:
        record["renderers"] = compare_renderers(verifier, models, batches, repeats=3)
    report(record, __file__, argv)


def _verify_image(
    verifier: PoseVerifier,
    scene: Any,
    image: tuple[int, int],
    results: PoseResults,
    repeats: int,
    *,
    renderers: bool,
) -> tuple[torch.Tensor, list[int], Any, tuple[float, float], tuple | None]:
    """Verify the estimates of one image from the visible GT masks they were made from.

    Args:
        verifier: the prepared verifier.
        scene: the image's :class:`~poseflow.data.bop.BOPScene`.
        image: its scene and image ids.
        results: the estimates of every image.
        repeats: how often to verify it (the fastest run is kept).
        renderers: also return the batch for :func:`compare_renderers`.

    Returns:
        The rows of ``results`` verified ``(E,)``, their object ids, the verifier's output, the
        fastest wall and CPU seconds of the runs, and (with ``renderers``) the batch
        ``(rgb, depth, K, masks, obj_ids, hypotheses)``.
    """
    s, i = image
    rows = ((results.scene_ids == s) & (results.im_ids == i)).nonzero()[:, 0]
    gts = scene.gt_of(i)
    rgb, depth = scene.load_rgb_image(i), scene.load_depth_image(i).double()
    K = torch.as_tensor(scene.camera[i].K, dtype=torch.float64)
    poses = results.poses[rows]
    ids = results.obj_ids[rows].tolist()
    gt_masks = [scene.load_mask(i, g, visible=True) for g in range(len(gts))]
    match = assign_masks(poses, ids, [g.obj_id for g in gts], gt_masks, K)
    keep = [j for j, g in enumerate(match) if g >= 0]
    rows, poses, ids = rows[keep], poses[keep], [ids[j] for j in keep]
    masks = torch.stack([gt_masks[match[j]] for j in keep])
    observed, observed_mask = observed_clouds(
        depth, K, masks, [verifier.objects[o].diameter for o in ids]
    )
    # the verifier runs in the dtype of the poses: float32 is twice as fast as float64
    walls, cpus = [], []
    for _ in range(repeats):
        cpu_start = time.process_time()
        wall, out = clocked(
            lambda: verifier.verify(
                ImageInstances(rgb, depth, K, masks, ids),
                poses.float(),
                (observed.float(), observed_mask),
            )
        )
        walls.append(wall)
        cpus.append(time.process_time() - cpu_start)
    batch = (rgb, depth, K, masks, ids, verifier.expand(poses, ids).poses) if renderers else None
    # the fastest of the repeats: what the machine does when other jobs leave it alone
    return rows, ids, out, (min(walls), min(cpus)), batch


def _times_ms(added: list[float], added_cpu: list[float], by_count: dict) -> dict[str, Any]:
    """The verification's added wall and CPU ms per image, overall and by instances."""
    return {
        "added_ms_per_image_median": 1000 * statistics.median(added),
        "added_ms_per_image_mean": 1000 * statistics.mean(added),
        "added_ms_per_image_max": 1000 * max(added),
        "added_cpu_ms_per_image_median": 1000 * statistics.median(added_cpu),
        "added_cpu_ms_per_image_mean": 1000 * statistics.mean(added_cpu),
        "added_cpu_ms_by_instances": {
            str(n): round(1000 * statistics.median(t), 1) for n, t in sorted(by_count.items())
        },
    }


if __name__ == "__main__":
    main()
