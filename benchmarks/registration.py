"""Registration speed and accuracy: poseflow against Open3D on the same data, in one run.

RANSAC: a batch of instances with putative correspondences (40% outliers), 1,000 hypotheses each,
against ``registration_ransac_based_on_correspondence`` looped over the batch with the same
iteration count (confidence 1.0 on both sides, so neither stops early). ICP: point-to-point on
clouds of 2,000 points from a perturbed start, against ``registration_icp`` looped over the batch
with the same criteria. Prints one JSON line with both times, their ratio and both accuracies,
then the command.
Where Open3D is not installed (a GPU machine, say) only poseflow's side is measured.

ICP is timed alternately on both sides after a warm-up, and reported as the best of
``--repeats`` (with the ratio of the medians). Run
``OMP_NUM_THREADS=1 taskset -c 0 python benchmarks/registration.py`` for one core on both sides
(``--quick`` for CI: 2 instances, 200 RANSAC hypotheses, three repeats).

SVD: Procrustes' 3 × 3 SVD (``procrustes.svd3x3``, compiled on the CPU) against
``torch.linalg.svd`` on ``--svd-matrices`` random float64 matrices (RANSAC's minimal samples of
48 instances × 1,000 hypotheses by default), timed alternately, with the largest difference of
the rotations ``U diag(1, 1, det U det Vh) Vh`` both give.
"""

from __future__ import annotations

import argparse
import math
import statistics

import numpy as np
import torch
from _common import machine, report, timed, timed_pair

from poseflow.cli.registration_demo import make_scenes
from poseflow.geometry.se3 import (
    compose,
    inverse_transform,
    random_transform,
    rotation_angle_error,
    translation_error,
)
from poseflow.registration import icp, ransac_procrustes
from poseflow.registration.procrustes import svd3x3

try:
    import open3d as o3d

    REG = o3d.pipelines.registration
except ImportError:
    o3d = REG = None


def cloud(points: torch.Tensor):
    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(points.double().cpu().numpy())
    return pcd


def errors(T: torch.Tensor, pose: torch.Tensor) -> tuple[float, float]:
    """Median rotation (degrees) and translation (mm) errors of the poses ``T^-1`` over the batch.

    ``T`` maps the camera frame to the object frame; its inverse is the object's pose.
    """
    T, truth = inverse_transform(T.double().cpu()), pose.double().cpu()
    rot = rotation_angle_error(T, truth).median().item()
    trans = (translation_error(T, truth) * 1000).median().item()
    return rot, trans


def bench_ransac(args: argparse.Namespace, device: torch.device, dtype: torch.dtype) -> dict:
    scenes = make_scenes(
        args.instances, args.correspondences, outliers=args.outliers, noise=args.noise, seed=0
    )
    truth = inverse_transform(scenes.pose)  # observed (camera) -> predicted (object frame)
    threshold = 5 * args.noise
    src = scenes.observed.to(device, dtype)
    dst = scenes.predicted.to(device, dtype)

    def ours():
        g = torch.Generator(device=device).manual_seed(0)
        return ransac_procrustes(
            src,
            dst,
            max_correspondence_distance=threshold,
            max_iterations=args.iterations,
            confidence=1.0,
            generator=g,
        )

    n = args.correspondences
    ours_s, result = timed(ours, args.repeats, device=device)
    rot, trans = errors(result.transformation, scenes.pose)
    record = {
        "instances": len(truth),
        "correspondences": n,
        "outliers": args.outliers,
        "iterations": args.iterations,
        "threshold_m": threshold,
        "poseflow_ms": round(ours_s * 1000, 2),
        "poseflow_median_rot_deg": round(rot, 4),
        "poseflow_median_trans_mm": round(trans, 3),
    }
    if o3d is None:
        return record
    corres = o3d.utility.Vector2iVector(np.stack([np.arange(n)] * 2, 1).astype(np.int32))
    pairs = [(cloud(scenes.observed[b]), cloud(scenes.predicted[b])) for b in range(len(truth))]
    criteria = REG.RANSACConvergenceCriteria(max_iteration=args.iterations, confidence=1.0)

    def theirs():
        return torch.from_numpy(
            np.stack(
                [
                    REG.registration_ransac_based_on_correspondence(
                        s, d, corres, threshold, REG.TransformationEstimationPointToPoint(), 3,
                        [], criteria,
                    ).transformation
                    for s, d in pairs
                ]
            )
        )  # fmt: skip

    theirs_s, o3d_T = timed(theirs, args.repeats)
    rot_o3d, trans_o3d = errors(o3d_T, scenes.pose)
    return {
        **record,
        "open3d_ms": round(theirs_s * 1000, 2),
        "speedup": round(theirs_s / ours_s, 2),
        "open3d_median_rot_deg": round(rot_o3d, 4),
        "open3d_median_trans_mm": round(trans_o3d, 3),
    }


def bench_icp(args: argparse.Namespace, device: torch.device, dtype: torch.dtype) -> dict:
    scenes = make_scenes(
        args.instances, args.points, model_points=args.points, outliers=0.0, noise=0.0005, seed=1
    )
    truth = inverse_transform(scenes.pose)  # observed (camera) -> model (object frame)
    g = torch.Generator().manual_seed(1)
    offset = random_transform(
        len(truth),
        max_angle=math.radians(args.icp_angle),
        max_translation=args.icp_translation,
        generator=g,
        dtype=torch.float64,
    )
    init = compose(offset, truth)
    src = scenes.observed.to(device, dtype)
    dst = scenes.model.to(device, dtype)
    init_t = init.to(device, dtype)
    distance = args.icp_distance

    def ours():
        return icp(src, dst, init_t, max_correspondence_distance=distance, max_iterations=30)

    rot0, trans0 = errors(init, scenes.pose)
    record = {
        "instances": len(truth),
        "points": args.points,
        "max_correspondence_distance_m": distance,
        "initial_median_rot_deg": round(rot0, 3),
        "initial_median_trans_mm": round(trans0, 2),
        "repeats": args.repeats,
    }
    if o3d is None:
        ours_s, result = timed(ours, args.repeats, device=device)
        rot, trans = errors(result.transformation, scenes.pose)
        return {
            **record,
            "poseflow_ms": round(ours_s * 1000, 2),
            "poseflow_median_rot_deg": round(rot, 4),
            "poseflow_median_trans_mm": round(trans, 3),
            "poseflow_mean_iterations": result.num_iterations.double().mean().item(),
        }
    pairs = [(cloud(scenes.observed[b]), cloud(scenes.model[b])) for b in range(len(truth))]
    criteria = REG.ICPConvergenceCriteria(1e-6, 1e-6, 30)
    init_np = init.numpy()

    def theirs():
        results = [
            REG.registration_icp(
                s, d, distance, init_np[b], REG.TransformationEstimationPointToPoint(), criteria
            )
            for b, (s, d) in enumerate(pairs)
        ]
        return torch.from_numpy(np.stack([r.transformation for r in results]))

    # alternated, best of the repeats (the ratio of the medians too)
    t_ours, t_theirs, result, o3d_T = timed_pair(ours, theirs, args.repeats, device=device)
    rot, trans = errors(result.transformation, scenes.pose)
    rot_o3d, trans_o3d = errors(o3d_T, scenes.pose)
    return {
        **record,
        "poseflow_ms": round(min(t_ours) * 1000, 2),
        "poseflow_median_rot_deg": round(rot, 4),
        "poseflow_median_trans_mm": round(trans, 3),
        "poseflow_mean_iterations": result.num_iterations.double().mean().item(),
        "open3d_ms": round(min(t_theirs) * 1000, 2),
        "ratio_poseflow_over_open3d": round(min(t_ours) / min(t_theirs), 3),
        "ratio_of_medians": round(statistics.median(t_ours) / statistics.median(t_theirs), 3),
        "open3d_median_rot_deg": round(rot_o3d, 4),
        "open3d_median_trans_mm": round(trans_o3d, 3),
    }


def bench_svd(args: argparse.Namespace) -> dict:
    """The compiled 3 × 3 SVD against ``torch.linalg.svd`` on the CPU (float64)."""
    g = torch.Generator().manual_seed(0)
    A = torch.randn(args.svd_matrices, 3, 3, generator=g, dtype=torch.float64)
    t_ours, t_lapack, ours, lapack = timed_pair(
        lambda: svd3x3(A), lambda: torch.linalg.svd(A), args.repeats
    )

    def rotation(U: torch.Tensor, Vh: torch.Tensor) -> torch.Tensor:
        d = torch.linalg.det(U) * torch.linalg.det(Vh)
        return (
            U @ torch.diag_embed(torch.stack((torch.ones_like(d), torch.ones_like(d), d), -1)) @ Vh
        )

    gap = (rotation(ours[0], ours[2]) - rotation(lapack[0], lapack[2])).abs().max()
    return {
        "matrices": args.svd_matrices,
        "poseflow_ms": round(min(t_ours) * 1e3, 2),
        "torch_linalg_svd_ms": round(min(t_lapack) * 1e3, 2),
        "speedup_of_medians": round(statistics.median(t_lapack) / statistics.median(t_ours), 2),
        "max_rotation_difference": float(gap),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small batch, one repeat (CI)")
    parser.add_argument("--device", default="cpu", help="torch device for poseflow")
    parser.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    parser.add_argument("--instances", type=int, default=8)
    parser.add_argument("--correspondences", type=int, default=1000)
    parser.add_argument("--outliers", type=float, default=0.4)
    parser.add_argument("--noise", type=float, default=0.001, help="metres")
    parser.add_argument("--iterations", type=int, default=1000, help="RANSAC hypotheses")
    parser.add_argument("--points", type=int, default=2000, help="ICP cloud size")
    parser.add_argument("--icp-angle", type=float, default=10.0, help="initial error, degrees")
    parser.add_argument("--icp-translation", type=float, default=0.01, help="metres")
    parser.add_argument("--icp-distance", type=float, default=0.02, help="metres")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--svd-matrices", type=int, default=48_000, help="3 x 3 SVD batch")
    args = parser.parse_args(argv)
    if args.quick:
        args.instances, args.iterations, args.repeats, args.svd_matrices = 2, 200, 3, 2_000
    device = torch.device(args.device)
    dtype = getattr(torch, args.dtype)
    record = {
        "benchmark": "registration",
        "device": str(device),
        "machine": machine(),
        "dtype": args.dtype,
        "torch": torch.__version__,
        "open3d": None if o3d is None else o3d.__version__,
        "ransac": bench_ransac(args, device, dtype),
        "icp": bench_icp(args, device, dtype),
        "svd": bench_svd(args),
    }
    report(record, __file__, argv)


if __name__ == "__main__":
    main()
