"""BOP evaluation speed: about 1,000 estimates on a 640x480 dataset, against per-estimate loops.

Generates a synthetic BOP dataset (the three demo objects with their geometric symmetries, so the
can's continuous symmetry is sampled 315 times, several instances per image), perturbs every
ground-truth pose a little (so errors spread over the thresholds), and times
:func:`poseflow.eval.evaluate.evaluate_bop` (VSD, MSSD and MSPD, matching and recall). The BOP
toolkit cannot be installed here (not on PyPI, numpy < 2), so the reference is its algorithm as a
user would write it: MSSD and MSPD one estimate and one symmetry at a time in numpy, timed on the
same pairs; the two must agree. Prints one JSON line, then the command.

Run ``python benchmarks/eval.py`` (``--quick`` for CI: a smaller dataset at 320x240).
"""

from __future__ import annotations

import argparse
import platform
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from _common import clocked, report

from poseflow.data.bop import BOPDataset
from poseflow.data.demo_objects import demo_objects
from poseflow.data.synthetic import generate_dataset
from poseflow.eval.errors import mspd, mssd
from poseflow.eval.evaluate import evaluate_bop, gt_results, load_eval_models
from poseflow.eval.recall import Target, assign
from poseflow.eval.results import PoseResults
from poseflow.geometry.se3 import random_transform


def loop_mssd_mspd(T_est, T_gt, K, pts, syms):
    """The toolkit's algorithm, one pair and one symmetry at a time (numpy)."""
    pe = pts @ T_est[:3, :3].T + T_est[:3, 3]
    ue = pe @ K.T
    ue = ue[:, :2] / ue[:, 2:]
    best_s, best_p = np.inf, np.inf
    for S in syms:
        G = T_gt @ S
        pg = pts @ G[:3, :3].T + G[:3, 3]
        best_s = min(best_s, float(np.linalg.norm(pe - pg, axis=1).max()))
        ug = pg @ K.T
        ug = ug[:, :2] / ug[:, 2:]
        best_p = min(best_p, float(np.linalg.norm(ue - ug, axis=1).max()))
    return best_s, best_p


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small dataset (CI)")
    parser.add_argument("--images", type=int, default=None, help="test images")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    width, height = (320, 240) if args.quick else (640, 480)
    images = args.images or (8 if args.quick else 110)
    torch.manual_seed(args.seed)
    objects = demo_objects(num_points=256, geometric_symmetries=True)
    with tempfile.TemporaryDirectory() as tmp:
        gen_s, root = clocked(
            lambda: generate_dataset(
                tmp,
                {i + 1: o for i, o in enumerate(objects)},
                num_train_images=0,
                num_test_images=images,
                objects_per_image=(8, 10),
                distractors_per_image=0,
                width=width,
                height=height,
                seed=args.seed,
                progress=False,
            )
        )
        est = _perturbed(root, args.seed)
        eval_s, report_all = clocked(lambda: evaluate_bop(root, est))
        mssd_mspd_s, report_no_vsd = clocked(
            lambda: evaluate_bop(root, est, metrics=("mssd", "mspd"))
        )
        pairs = _Pairs.of(root, est)
        loop_s, loop = clocked(lambda: pairs.loop_errors(est))
        worst = pairs.worst_difference(est, loop)

    record = {
        "benchmark": "eval",
        "machine": f"{platform.machine()} {torch.get_num_threads()} threads",
        "image_size": [width, height],
        "images": images,
        "estimates": len(est),
        "evaluated_pairs": int(pairs.row.numel()),
        "targets": report_all["num_targets"],
        "generate_s": round(gen_s, 2),
        "evaluate_all_s": round(eval_s, 2),
        "evaluate_mssd_mspd_s": round(mssd_mspd_s, 2),
        "loop_mssd_mspd_s": round(loop_s, 2),
        "speedup_mssd_mspd": round(loop_s / mssd_mspd_s, 1),
        "AR": round(report_all["AR"], 4),
        "AR_VSD": round(report_all["AR_VSD"], 4),
        "AR_MSSD": round(report_all["AR_MSSD"], 4),
        "AR_MSPD": round(report_all["AR_MSPD"], 4),
        "max_abs_diff_vs_loop": worst,
        "same_ar_without_vsd": report_no_vsd["AR_MSSD"] == report_all["AR_MSSD"],
    }
    report(record, __file__)


def _perturbed(root: Path, seed: int) -> PoseResults:
    """Every ground-truth pose moved a little (so errors spread over the thresholds)."""
    res = gt_results(root)
    g = torch.Generator().manual_seed(seed)
    noise = random_transform(
        len(res), max_angle=0.15, max_translation=0.01, generator=g, dtype=torch.float64
    )
    return PoseResults(
        res.scene_ids,
        res.im_ids,
        res.obj_ids,
        torch.rand(len(res), generator=g),
        res.poses @ noise,
        torch.full((len(res),), 0.5, dtype=torch.float64),
    )


@dataclass
class _Pairs:
    """The (estimate, ground truth) pairs that the evaluation matches, for the reference.

    ``row`` names each pair's target in ``assignment.targets``, ``e_idx`` its estimate and
    ``g_idx`` its ground-truth instance in the image, all ``(P,)``.
    """

    ds: BOPDataset
    assignment: Any
    row: torch.Tensor
    e_idx: torch.Tensor
    g_idx: torch.Tensor
    models: dict[int, Any]

    @classmethod
    def of(cls, root: Path, est: PoseResults) -> _Pairs:
        """The pairs of ``est`` on the test split of ``root``, matched as the evaluation does."""
        ds = BOPDataset(root, "test", load_rgb=False, load_masks=False)
        targets = [Target(t.scene_id, t.im_id, t.obj_id, t.inst_count) for t in ds.test_targets()]
        gts = {}
        for t in targets:
            scene = ds.scene(t.scene_id)
            gts[(t.scene_id, t.im_id)] = [
                (x.obj_id, i.visib_fract)
                for x, i in zip(scene.gt_of(t.im_id), scene.gt_info[t.im_id])
            ]
        a = assign(targets, gts, est.scene_ids, est.im_ids, est.obj_ids, est.scores)
        row, _, _, e_idx, g_idx = a.pairs()
        models = load_eval_models(ds, [t.obj_id for t in targets])
        return cls(ds, a, row, e_idx, g_idx, models)

    def _target_scene(self, r: int) -> tuple[Any, Any]:
        t = self.assignment.targets[r]
        return t, self.ds.scene(t.scene_id)

    def loop_errors(self, est: PoseResults) -> list[tuple[float, float]]:
        """MSSD and MSPD of every pair, the toolkit's way: one pair at a time."""
        loop = []
        for r, e, gi in zip(self.row.tolist(), self.e_idx.tolist(), self.g_idx.tolist()):
            t, scene = self._target_scene(r)
            m = self.models[t.obj_id]
            loop.append(
                loop_mssd_mspd(
                    est.poses[e].numpy(),
                    scene.gt_of(t.im_id)[gi].pose,
                    np.asarray(scene.camera[t.im_id].K),
                    m.vertices.numpy(),
                    m.symmetries.numpy(),
                )
            )
        return loop

    def worst_difference(self, est: PoseResults, loop: list[tuple[float, float]]) -> float:
        """The largest difference of vectorised MSSD and MSPD (a call per object) to ``loop``."""
        worst = 0.0
        obj = torch.tensor([self.assignment.targets[r].obj_id for r in self.row.tolist()])
        for o in obj.unique().tolist():
            sel = (obj == o).nonzero()[:, 0]
            T_e = est.poses[self.e_idx[sel]]
            T_g, K = [], []
            for r, gi in zip(self.row[sel].tolist(), self.g_idx[sel].tolist()):
                t, scene = self._target_scene(r)
                T_g.append(scene.gt_of(t.im_id)[gi].pose)
                K.append(scene.camera[t.im_id].K)
            T_g, K = torch.from_numpy(np.stack(T_g)), torch.from_numpy(np.stack(K))
            m = self.models[o]
            vec_s = mssd(T_e, T_g, m.vertices, m.symmetries)
            vec_p = mspd(T_e, T_g, K, m.vertices, m.symmetries)
            ref = torch.tensor([loop[i] for i in sel.tolist()], dtype=torch.float64)
            worst = max(worst, float((vec_s - ref[:, 0]).abs().max()))
            worst = max(worst, float((vec_p - ref[:, 1]).abs().max()))
        return worst


if __name__ == "__main__":
    main()
