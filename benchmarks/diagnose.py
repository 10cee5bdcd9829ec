"""Where FunFlow6D loses accuracy on a BOP split: generation, selection or refinement.

Runs a trained FunFlow6D over a split's targets (ground-truth visible masks) once, and scores, with
the BOP 2019 AR per object, the estimator as it is next to oracle replacements of its stages:

- ``model``: the estimator as shipped (``H`` hypotheses, best by its own score);
- ``oracle_choice``: the same hypotheses, the one closest to the ground truth (MSSD) kept:
  what a perfect selection would give (generation is the limit where this stays low);
- ``oracle_flow``: the predicted canonical points replaced by the ground truth ``Tʳ``, then the
  same RANSAC + ICP: the ceiling of the pose solver on this observation;
- ``no_icp``: the model without ICP (what refinement adds);
- ``verified``: the model with its render-and-compare verification, the verifier ranking the
  hypotheses (as the estimators ship);
- ``oracle_verified``: among the poses the verifier finally scored (the estimate and its best
  candidates, ICP-refined), the one closest to the ground truth: what a perfect final choice of
  the verifier would give;
- ``oracle_candidates``: every hypothesis with every near-symmetric candidate of it, each refined
  by the verifier's ICP, the closest kept: the ceiling of verification over these hypotheses
  (generation is the limit where this stays low, the verifier's ranking where ``verified`` stays
  far below it).

Per object it counts the verifier's wrong choices (MSSD above a tenth of the diameter) and, of
those, the ones whose full-grid score ranks the ground-truth pose itself no higher than the wrong
pose (on the choice's crop): there the score cannot tell the truth from the choice, and no better
search among candidates would find it; in the others the search or the candidates lose it.

It also reports, per object, the flow's endpoint error (median over instances and hypotheses of
the mean distance between predicted and true canonical points, symmetry-aware, as a fraction of
the diameter) and the conditioning's correspondence inliers (mutual nearest neighbours of the
query's and the target's features, within 3 % of the diameter under the ground truth; geometric
and semantic inputs separately, next to the count perfect features would give on these
clouds), the paper's feature-discriminativity metric at ``--inlier-threshold`` (0.1: the
clouds hold only ``N`` points, too sparse for the paper's 3 %).

Prints the table, one JSON line and the command. Run
``python benchmarks/diagnose.py DATASET --model RUN/model``; ``--quick`` (CI) runs the shipped
model on a one-image generated split.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
from collections import defaultdict
from pathlib import Path
from typing import Any

import torch
from _common import report, target_instances

from poseflow.assets import DEMO_CHECKPOINT
from poseflow.cli.common import load_model
from poseflow.cli.options import add_set_argument, inference_changes
from poseflow.data import ImageInstances
from poseflow.data.bop import BOPDataset
from poseflow.data.object_folder import load_object_models, object_cache_dir
from poseflow.eval import evaluate_bop
from poseflow.eval.errors import mssd
from poseflow.eval.inliers import correspondence_inliers
from poseflow.eval.predict import PoseEstimate, invalidate_implausible
from poseflow.eval.recall import Target
from poseflow.eval.results import PoseResults, write_results
from poseflow.flows import get_sampler
from poseflow.models import FunFlow6D
from poseflow.models.objects import select_objects
from poseflow.models.pose import select_hypotheses, solve_pose
from poseflow.models.verification import other_hypotheses, rank_estimate

VARIANTS = (
    "model",
    "oracle_choice",
    "oracle_flow",
    "no_icp",
    "verified",
    "oracle_verified",
    "oracle_candidates",
)


def _targets(ds: BOPDataset, max_images: int | None) -> list[Target]:
    """The split's BOP19 targets, on its first ``max_images`` images."""
    targets = [Target(t.scene_id, t.im_id, t.obj_id, t.inst_count) for t in ds.test_targets()]
    keep = sorted({(t.scene_id, t.im_id) for t in targets})[:max_images]
    return [t for t in targets if (t.scene_id, t.im_id) in set(keep)]


def _symmetric_epe(pred, truth, mask, symmetries, scale):
    """Mean endpoint error ``(R,)`` of each row, minimised over the object's symmetries.

    Args:
        pred: predicted canonical target points ``(R, N, 3)``, normalised by ``scale``.
        truth: true ones ``(R, N, 3)``, same unit.
        mask: valid points ``(R, N)``.
        symmetries: per row the symmetry set ``(S_r, 4, 4)`` in metres (identity first).
        scale: half diameters ``(R,)``, metres.

    Returns:
        Errors as fractions of the diameter ``(R,)``.
    """
    out = []
    w = mask.to(pred.dtype)
    for r in range(len(pred)):
        S = symmetries[r].to(pred)
        # The pose T S is as right as T: its canonical points are S⁻¹ Tʳ.
        R_inv = S[:, :3, :3].transpose(1, 2)
        t = S[:, :3, 3] / scale[r]
        alt = (truth[r][None] - t[:, None]) @ R_inv.transpose(1, 2)
        err = (pred[r][None] - alt).norm(dim=-1)
        mean = (err * w[r]).sum(-1) / w[r].sum().clamp_min(1)
        out.append(mean.min() / 2)  # normalised unit: the diameter is 2
    return torch.stack(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", nargs="?", help="BOP dataset folder")
    parser.add_argument("--model", default=str(DEMO_CHECKPOINT), help="FunFlow6D model folder")
    parser.add_argument("--out", default=None, help="folder of the variants' CSVs and reports")
    parser.add_argument("--hypotheses", type=int, default=None, help="H (default: model's)")
    parser.add_argument("--steps", type=int, default=None, help="Euler steps (default: model's)")
    add_set_argument(
        parser,
        "an inference field of the model's config, as in poseflow predict; repeatable",
    )
    parser.add_argument("--max-images", type=int, default=None)
    parser.add_argument("--seed", type=int, default=0)
    parser.set_defaults(verify=True)  # the verified variants need a verifier
    parser.add_argument(
        "--inlier-threshold", type=float, default=0.1, help="inlier distance, x diameter"
    )
    parser.add_argument("--quick", action="store_true", help="shipped model, one generated image")
    args = parser.parse_args()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        if args.quick:
            from poseflow.data.synthetic import generate_dataset

            args.dataset = str(
                generate_dataset(Path(tmp) / "data", num_train_images=0, num_test_images=1,
                                 seed=3, progress=False)
            )  # fmt: skip
            args.model = str(DEMO_CHECKPOINT)
        if args.dataset is None:
            parser.error("give a BOP dataset folder, or --quick")
        record = diagnose(args, Path(args.out or Path(tmp) / "diagnosis"))
    report(record, __file__)


def _closest(poses, mask, gt, objects, obj_ids) -> torch.Tensor:
    """Index ``(B,)`` of each instance's candidate closest to the ground truth by MSSD.

    Args:
        poses: candidates ``(B, C, 4, 4)``, model to camera.
        mask: ``(B, C)`` bool, the real candidates.
        gt: ground-truth poses ``(B, 4, 4)``.
        objects: ``{obj_id: ObjectModel}``.
        obj_ids: object id of each instance.
    """
    B, C = mask.shape
    err = torch.empty(B, C)
    for b in range(B):
        o = objects[obj_ids[b]]
        err[b] = mssd(poses[b].float(), gt[b].expand(C, 4, 4), o.points, o.symmetries.float())
    return torch.where(mask.cpu(), err, torch.inf).argmin(1)


def _refined_candidates(model, solved, obj_ids, obs) -> tuple[torch.Tensor, torch.Tensor]:
    """Every hypothesis with its near-symmetric candidates, each refined by the verifier's ICP.

    Returns:
        ``(poses (B, H·C, 4, 4), mask (B, H·C))``.
    """
    H = model.config.num_hypotheses
    T, _, valid = solved
    B = len(T) // H
    ok = valid & torch.isfinite(T).flatten(-2).all(-1)
    poses = torch.linalg.inv(torch.where(ok[:, None, None], T, torch.eye(4)))
    hyp = model.verifier.expand(poses, [o for o in obj_ids for _ in range(H)])
    C = hyp.poses.shape[1]
    cand = hyp.poses.reshape(B, H * C, 4, 4)
    mask = (hyp.mask & ok[:, None]).reshape(B, H * C)
    refined = torch.stack([
        model.verifier.refine(cand[b : b + 1], [obj_ids[b]], obs.cloud[b : b + 1],
                              obs.cloud_mask[b : b + 1])[0]
        for b in range(B)
    ])  # fmt: skip
    return refined, mask


def diagnose(args: argparse.Namespace, out: Path) -> dict:
    """Run the variants over the split; returns the report (also printed as a table)."""
    root = Path(args.dataset)
    model = load_model(args.model, inference=inference_changes(args))
    ds = BOPDataset(root, "test")
    targets = _targets(ds, args.max_images)
    images: dict[tuple[int, int], set[int]] = defaultdict(set)
    for t in targets:
        images[(t.scene_id, t.im_id)].add(t.obj_id)
    objects = load_object_models(root, obj_ids=sorted({o for v in images.values() for o in v}))
    model.prepare_objects(objects, cache_dir=object_cache_dir(args.model, root), progress=False)
    model.eval()
    g = torch.Generator().manual_seed(args.seed)
    rows: dict[str, list[PoseResults]] = defaultdict(list)
    quality = _FlowQuality(args.inlier_threshold)
    truth = _TruthCheck()
    for (s, i), wanted in sorted(images.items()):
        obj_ids, masks, gt, rgb, depth, K = target_instances(ds.scene(s), i, wanted)
        image = (rgb, depth, K, masks, obj_ids)
        with torch.no_grad():
            est, obs, solved = _flow_variants(model, objects, image, gt, g, quality)
            est.update(_verified_variants(model, objects, image, gt, est["model"], obs, solved))
            truth.add(model, objects, ImageInstances(*image), gt, est["verified"])
        for name, e_ in est.items():
            ok = e_.valid
            k = int(ok.sum())
            if k:
                ids = [o for o, v in zip(obj_ids, ok.tolist()) if v]
                rows[name].append(
                    PoseResults.from_columns([s] * k, [i] * k, ids, e_.scores[ok], e_.poses[ok], -1)
                )
    out.mkdir(parents=True, exist_ok=True)
    H = model.config.num_hypotheses
    record: dict = {"dataset": root.name, "model": args.model, "hypotheses": H, "variants": {}}
    for name in VARIANTS:
        csv = out / f"{name}_{root.name}-test.csv"
        write_results(csv, PoseResults.concat(rows[name]))
        r = evaluate_bop(root, csv, targets=targets)
        record["variants"][name] = {
            "AR": round(r["AR"], 4),
            "per_object": {o: round(v["AR"], 4) for o, v in r["per_object"].items()},
        }
    record.update(quality.summary())
    record.update(truth.summary())
    _print_table(record)
    return record


def _flow_variants(
    model: FunFlow6D, objects: dict, image: tuple, gt: torch.Tensor, g: torch.Generator, quality
) -> tuple[dict[str, PoseEstimate], Any, tuple]:
    """The model's estimates of one image and its oracle and no-ICP variants.

    Also adds the flow's endpoint errors and the conditioning's inliers to ``quality``.

    Returns:
        ``{variant: PoseEstimate}`` of ``model``, ``oracle_choice``, ``oracle_flow`` and
        ``no_icp``, the observation, and the solved hypotheses ``(B·H, ...)``.
    """
    obj_ids = image[4]
    cfg = model.config
    H = cfg.num_hypotheses
    obs = model.observe(ImageInstances(*image), generator=g)
    inputs = model.flow_inputs(obs, poses=gt)
    n = inputs.points.shape[1] // 2
    x = model.net.sample(inputs, get_sampler(cfg.solver, steps=cfg.steps),
                         frozen_mask=inputs.frozen_mask,
                         x_frozen=inputs.anchor if cfg.anchor == "pinned" else None,
                         generator=g, num_samples=H)  # fmt: skip
    rep = inputs.repeat_interleave(H)
    dense = [o.dense_points for o in select_objects(model.objects, rep.obj_ids)]
    solved = solve_pose(rep, x[:, n:], dense, cfg, generator=g)
    est = {"model": select_hypotheses(*solved, obs.valid, H)}
    # Oracle choice: the hypothesis with the smallest MSSD to the ground truth.
    poses_h = torch.linalg.inv(solved[0].double()).float()  # camera->canonical inverted
    B = len(obj_ids)
    pick = _closest(poses_h.reshape(B, H, 4, 4), torch.ones(B, H, dtype=torch.bool), gt,
                    objects, obj_ids)  # fmt: skip
    onehot = torch.zeros(B, H)
    onehot[torch.arange(B), pick] = 1.0
    est["oracle_choice"] = select_hypotheses(
        solved[0], onehot.reshape(-1) * solved[1].clamp_min(1e-6), solved[2], obs.valid, H
    )
    dense1 = [o.dense_points for o in select_objects(model.objects, inputs.obj_ids)]
    oracle = solve_pose(inputs, inputs.x_1[:, n:], dense1, cfg, generator=g)
    est["oracle_flow"] = select_hypotheses(*oracle, obs.valid, 1)
    no_icp = cfg.replace(icp_distances=())
    est["no_icp"] = select_hypotheses(
        *solve_pose(rep, x[:, n:], dense, no_icp, generator=g), obs.valid, H
    )
    quality.add(objects, obs, inputs, rep, x, obj_ids, H)
    return est, obs, solved


def _verified_variants(
    model: FunFlow6D,
    objects: dict,
    image: tuple,
    gt: torch.Tensor,
    estimate: PoseEstimate,
    obs: Any,
    solved: tuple,
) -> dict[str, PoseEstimate]:
    """The model's estimates verified as the estimators ship them, and the verifier's oracles."""
    obj_ids = image[4]
    instances = ImageInstances(*image)
    H = model.config.num_hypotheses
    shipped = invalidate_implausible(estimate)
    extra = extra_mask = None
    if model.config.verifier.rank_hypotheses:  # as FunFlow6D.estimate
        extra, extra_mask = other_hypotheses(*solved, H)
        shipped, extra, extra_mask = rank_estimate(
            model.verifier, shipped, extra, extra_mask, instances
        )
    ver = model.verifier.verify(
        instances, shipped.poses, (obs.cloud, obs.cloud_mask),
        extra=extra, extra_mask=extra_mask, estimated=shipped.valid,
    )  # fmt: skip
    est = {"verified": PoseEstimate(ver.poses, ver.scores, shipped.valid)}
    B = len(obj_ids)
    rows_b = torch.arange(B)
    kept = ver.score.valid & shipped.valid[:, None]
    best = _closest(ver.hypotheses, kept, gt, objects, obj_ids)
    est["oracle_verified"] = PoseEstimate(
        ver.hypotheses[rows_b, best], torch.ones(B), shipped.valid
    )
    cand, cand_mask = _refined_candidates(model, solved, obj_ids, obs)
    best = _closest(cand, cand_mask, gt, objects, obj_ids)
    est["oracle_candidates"] = PoseEstimate(
        cand[rows_b, best], torch.ones(B), cand_mask.any(1) & obs.valid
    )
    return est


class _FlowQuality:
    """The flow's endpoint errors and the conditioning's inliers, per object."""

    def __init__(self, threshold: float) -> None:
        self.threshold = threshold
        self.epe: dict[int, list[float]] = defaultdict(list)
        # Inliers of the conditioning's features, and of perfect features (the true canonical
        # coordinates) as the ceiling this cloud size allows.
        self.inliers: dict[str, dict[int, list[float]]] = {
            k: defaultdict(list) for k in ("geometric", "semantic", "ceiling")
        }

    def add(self, objects: dict, obs: Any, inputs: Any, rep: Any, x: torch.Tensor,
            obj_ids: list, H: int) -> None:  # fmt: skip
        """Add one image: ``x`` the sampled flows ``(B·H, 2N, 3)`` of ``rep``, ``inputs``'s."""
        n = inputs.points.shape[1] // 2
        truth = rep.x_1[:, n:]
        syms = [objects[o].symmetries for o in rep.obj_ids.tolist()]
        e = _symmetric_epe(x[:, n:], truth, rep.mask[:, n:], syms, rep.scale)
        for r, o in enumerate(rep.obj_ids.tolist()):
            if bool(obs.valid[r // H]):
                self.epe[o].append(float(e[r]))
        for kind in self.inliers:
            feats = inputs.x_1 if kind == "ceiling" else getattr(inputs, kind)
            res = correspondence_inliers(
                feats[:, :n], feats[:, n:], inputs.points[:, :n], inputs.x_1[:, n:],
                torch.full((len(obj_ids),), 2.0), self.threshold, t_mask=inputs.mask[:, n:],
                metric="euclidean" if kind == "ceiling" else "cosine",
            )  # fmt: skip
            for b, o in enumerate(obj_ids):
                self.inliers[kind][o].append(float(res.num_inliers[b]))

    def summary(self) -> dict:
        """``{"epe": {obj: median}, "inliers": {kind: {obj: mean}}}``."""
        return {
            "epe": {str(o): round(statistics.median(v), 4) for o, v in sorted(self.epe.items())},
            "inliers": {
                k: {str(o): round(statistics.fmean(v), 2) for o, v in sorted(d.items())}
                for k, d in self.inliers.items()
            },
        }


class _TruthCheck:
    """Per object: the verifier's wrong choices, and those its score ranks above the truth."""

    def __init__(self) -> None:
        self.wrong: dict[int, int] = defaultdict(int)
        self.truth_not_higher: dict[int, int] = defaultdict(int)
        self.seen: dict[int, int] = defaultdict(int)

    def add(self, model: FunFlow6D, objects: dict, image: ImageInstances, gt: torch.Tensor,
            verified: PoseEstimate) -> None:  # fmt: skip
        """Add one image's verified estimates ``(B, 4, 4)`` against the ground truth ``gt``."""
        rows = verified.valid.nonzero()[:, 0]
        if not len(rows):
            return
        chosen = verified.poses[rows]
        pair = torch.stack((chosen, gt[rows].to(chosen)), dim=1)  # (b, 2, 4, 4), choice's crop
        part = ImageInstances(image.rgb, image.depth, image.K, image.masks[rows],
                              [image.obj_ids[r] for r in rows.tolist()])  # fmt: skip
        score = model.verifier.score(part, pair).total
        for k, r in enumerate(rows.tolist()):
            oid = int(image.obj_ids[r])
            o = objects[oid]
            err = mssd(chosen[k : k + 1].float(), gt[r : r + 1], o.points, o.symmetries.float())
            self.seen[oid] += 1
            if float(err[0]) > 0.1 * o.diameter:
                self.wrong[oid] += 1
                self.truth_not_higher[oid] += int(score[k, 1] <= score[k, 0])

    def summary(self) -> dict:
        """``{"verified_targets", "wrong_choices", "truth_not_higher"}``, each ``{obj: n}``."""
        keys = sorted(self.seen)
        return {
            "verified_targets": {str(o): self.seen[o] for o in keys},
            "wrong_choices": {str(o): self.wrong[o] for o in keys},
            "truth_not_higher": {str(o): self.truth_not_higher[o] for o in keys},
        }


def _print_table(record: dict) -> None:
    """Per object: the AR of every variant, the endpoint error and the inliers."""
    objs = sorted(record["epe"], key=int)
    head = f"{'':<22}" + "".join(f"{o:>8}" for o in objs) + f"{'all':>8}"
    print(head)
    for name in VARIANTS:
        v = record["variants"][name]
        cells = "".join(f"{v['per_object'].get(o, 0.0):>8.3f}" for o in objs)
        print(f"{'AR ' + name:<22}{cells}{v['AR']:>8.3f}")
    print(f"{'EPE (x diameter)':<22}" + "".join(f"{record['epe'][o]:>8.3f}" for o in objs))
    for k in record["inliers"]:
        cells = "".join(f"{record['inliers'][k][o]:>8.1f}" for o in objs)
        print(f"{'inliers ' + k:<22}{cells}")
    for k in ("verified_targets", "wrong_choices", "truth_not_higher"):
        cells = "".join(f"{record[k].get(o, 0):>8d}" for o in objs)
        print(f"{k.replace('_', ' '):<22}{cells}{sum(record[k].values()):>8d}")


if __name__ == "__main__":
    main()
