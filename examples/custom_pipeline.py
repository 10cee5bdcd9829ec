"""Compose a training-free pose estimator by hand from poseflow's parts.

Each stage is one library call, so any of them can be swapped for your own:

1. ``backproject_depth``: the masked depth of the observed object -> a camera-frame cloud,
   cleaned by ``remove_statistical_outliers`` and thinned by ``voxel_downsample``;
2. ``FPFHEncoder``: multi-scale FPFH descriptors of that cloud and of the model, the model being
   described from a few rendered partial views (``Renderer`` + ``viewpoint_poses``), because
   descriptors of the complete model mix in surfaces the camera never sees;
3. ``mutual_nearest_neighbors``: putative model <-> observation pairs in descriptor space;
4. ``ransac_procrustes``: a model-to-camera pose from those pairs, several restarts in one batch;
5. ``multi_scale_icp``: coarse-to-fine refinement of the observed cloud onto the dense model; the
   restart that explains the observation best wins.

The scene is the library's grey bracket (geometry only, no texture needed) rendered at random
poses; errors against the true poses are printed per stage. ``poseflow.baselines`` packages the
same recipe (with more care) as ``ClassicBaseline``.

Run ``python examples/custom_pipeline.py`` (5 poses) or ``--quick`` (CI: 2 poses, a few seconds).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence

import torch

from poseflow.data.demo_objects import demo_objects
from poseflow.data.objects import ObjectModel
from poseflow.eval.inliers import mutual_nearest_neighbors
from poseflow.features.geometric import FPFHEncoder
from poseflow.features.lifting import viewpoint_poses
from poseflow.geometry.pointcloud import (
    backproject_depth,
    estimate_normals,
    remove_statistical_outliers,
    voxel_downsample,
)
from poseflow.geometry.se3 import (
    from_Rt,
    inverse_transform,
    random_rotation,
    rotation_angle_error,
    translation_error,
)
from poseflow.registration.icp import multi_scale_icp
from poseflow.registration.ransac import ransac_procrustes
from poseflow.render.raycast import Renderer

WIDTH, HEIGHT = 320, 240
K = torch.tensor([[400.0, 0, 159.5], [0, 400.0, 119.5], [0, 0, 1]], dtype=torch.float64)


def observe(depth: torch.Tensor, K: torch.Tensor, mask: torch.Tensor, voxel: float):
    """Stage 1-2: lift the masked depth, clean and thin it; returns points ``(M, 3)``, normals."""
    cloud = backproject_depth(depth[None], K, mask[None])
    keep = remove_statistical_outliers(cloud.points, cloud.mask)
    idx, ok = voxel_downsample(cloud.points, voxel, keep)
    points = cloud.points[0, idx[0][ok[0]]]
    normals = estimate_normals(points[None], k=20)[0]  # turned toward the camera
    return points, normals


def model_bank(obj: ObjectModel, encoder: FPFHEncoder, views: int, voxel: float):
    """Describe the model from rendered partial views: points (model frame) and descriptors."""
    renderer = Renderer([obj.mesh])
    points, feats = [], []
    for T in viewpoint_poses(views, distance=0.45):
        view = renderer.render(T[None], K, WIDTH, HEIGHT, rgb=False)
        p, n = observe(view.depth.double(), K, view.masks_full[0], voxel)
        feats.append(encoder.encode(p[None], n[None], None, obj.diameter)[0])
        points.append((p - T[:3, 3]) @ T[:3, :3])  # camera -> model frame
    return torch.cat(points), torch.cat(feats)


def estimate(obj, bank, encoder, depth, mask, *, restarts: int, generator: torch.Generator):
    """Stages 1-5 for one observation; returns the RANSAC and the refined model-to-camera poses."""
    d = obj.diameter
    target, normals = observe(depth, K, mask, 0.03 * d)
    target_feats = encoder.encode(target[None], normals[None], None, d)[0]
    bank_points, bank_feats = bank
    match = mutual_nearest_neighbors(bank_feats[None], target_feats[None])[0]  # (M,) or -1
    src, dst = bank_points[match[match >= 0]], target[match >= 0]
    # Every restart sees a random half of the pairs (the first sees them all).
    subsets = torch.rand(restarts, len(src), generator=generator) < 0.5
    subsets[0] = True
    coarse = ransac_procrustes(
        src.expand(restarts, -1, -1),
        dst.expand(restarts, -1, -1),
        subsets,
        max_correspondence_distance=0.05 * d,
        generator=generator,
    )
    fine = multi_scale_icp(  # the observation onto the model, starting from RANSAC's inverse
        target.expand(restarts, -1, -1),
        obj.points.double().expand(restarts, -1, -1),
        inverse_transform(coarse.transformation),
        max_correspondence_distances=[0.1 * d, 0.05 * d, 0.02 * d],
    )
    best = int(torch.where(coarse.valid, fine.fitness, -1.0).argmax())
    return coarse.transformation[best], inverse_transform(fine.transformation[best : best + 1])[0]


def main(argv: Sequence[str] | None = None) -> dict:
    """Render, estimate and print the errors; returns them as a dict."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="2 poses and 8 model views (CI)")
    parser.add_argument("--poses", type=int, default=None, help="random poses to estimate")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    poses = args.poses or (2 if args.quick else 5)
    views = 8 if args.quick else 16
    g = torch.Generator().manual_seed(args.seed)
    obj = demo_objects(num_points=2048, names=["bracket"])[0]
    encoder = FPFHEncoder()  # radii 0.30 and 0.40 of the diameter, as in the paper
    start = time.perf_counter()
    bank = model_bank(obj, encoder, views, 0.03 * obj.diameter)
    print(
        f"model bank: {len(bank[0])} points from {views} views, {time.perf_counter() - start:.1f} s"
    )
    R = random_rotation(poses, generator=g, dtype=torch.float64)
    t = torch.tensor([0.0, 0.0, 0.5], dtype=torch.float64) + 0.03 * torch.randn(
        poses, 3, generator=g, dtype=torch.float64
    )
    truth = from_Rt(R, t)
    renderer = Renderer([obj.mesh])
    rows = {"ransac_deg": [], "ransac_mm": [], "icp_deg": [], "icp_mm": [], "seconds": []}
    print(f"{'pose':>4}  {'RANSAC deg':>10} {'mm':>6}  {'+ ICP deg':>9} {'mm':>6}  {'s':>5}")
    for i in range(poses):
        view = renderer.render(truth[i : i + 1], K, WIDTH, HEIGHT, rgb=False)
        t0 = time.perf_counter()
        coarse, fine = estimate(
            obj, bank, encoder, view.depth.double(), view.masks_full[0], restarts=8, generator=g
        )
        rows["seconds"].append(time.perf_counter() - t0)
        for name, pose in (("ransac", coarse), ("icp", fine)):
            rows[f"{name}_deg"].append(float(rotation_angle_error(pose[None], truth[i : i + 1])[0]))
            rows[f"{name}_mm"].append(
                1000 * float(translation_error(pose[None], truth[i : i + 1])[0])
            )
        print(
            f"{i:>4}  {rows['ransac_deg'][-1]:>10.2f} {rows['ransac_mm'][-1]:>6.1f}  "
            f"{rows['icp_deg'][-1]:>9.2f} {rows['icp_mm'][-1]:>6.1f}  {rows['seconds'][-1]:>5.2f}"
        )
    return rows


if __name__ == "__main__":
    main()
