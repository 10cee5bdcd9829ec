"""Data-stage speed: lifting an RGBD image to instance clouds, and rendering, against Open3D.

Lifting: a 640x480 scene of 8 demo-object instances is rendered once; then, per image, every
instance's visible mask is back-projected (``backproject_depth``, one batched call, capped at
``--cap`` random pixels per instance), downsampled to a fixed ``M`` points by farthest-point
sampling and given PCA normals over ``k`` neighbours. The Open3D baseline does the same per
instance: ``PointCloud.create_from_depth_image`` on the masked depth, ``random_down_sample`` to the
same cap, ``farthest_point_down_sample(M)`` and ``estimate_normals(KNN k)``.

Rendering: the three demo objects at random poses in a 640x480 image with depth, instance map,
full masks of each object and shaded textured RGB (``poseflow.render.Renderer``, scenes built
once). The Open3D baseline is what a user would write with the same library: a
``RaycastingScene`` of the posed meshes rebuilt for each image and a full-image
``create_rays_pinhole`` cast, which yields depth and the instance map only (no full masks, no
colour).

Prints one JSON line with images/s and renders/s for both and their ratios, then the command.
Lifting is timed alternately on both sides after a warm-up; its figures are the best of
``--repeats`` (the ratio of the medians is given too). For one core on both sides run
``OMP_NUM_THREADS=1 taskset -c 0 python benchmarks/data.py --threads 1`` (``taskset`` also keeps
poseflow's k-d tree searches, which otherwise use a thread per core, on one core).
Run ``python benchmarks/data.py`` (``--quick`` for CI).
"""

from __future__ import annotations

import argparse
import statistics

import numpy as np
import open3d as o3d
import torch
from _common import machine, report, timed, timed_pair

from poseflow.data.demo_objects import DEMO_OBJECT_NAMES, demo_mesh
from poseflow.geometry.pointcloud import (
    backproject_depth,
    estimate_normals,
    farthest_point_sample,
)
from poseflow.geometry.se3 import random_rotation
from poseflow.render import Renderer

W, H = 640, 480
K = torch.tensor([[600.0, 0.0, 319.5], [0.0, 600.0, 239.5], [0.0, 0.0, 1.0]], dtype=torch.float64)


def scene_poses(n: int, g: torch.Generator) -> torch.Tensor:
    """``n`` poses on a 4 x 2 grid about 0.7 m in front of the camera."""
    T = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    T[:, :3, :3] = random_rotation(n, generator=g, dtype=torch.float64)
    for i in range(n):
        T[i, :3, 3] = torch.tensor([-0.24 + 0.16 * (i % 4), -0.08 + 0.16 * (i // 4 % 2), 0.7])
    return T


def bench_lifting(args: argparse.Namespace) -> dict:
    meshes = [demo_mesh(n) for n in DEMO_OBJECT_NAMES]
    g = torch.Generator().manual_seed(0)
    ids = [i % len(meshes) for i in range(args.instances)]
    out = Renderer(meshes).render(scene_poses(args.instances, g), K, W, H, object_ids=ids)
    depth, masks = out.depth, out.masks_visible
    n = args.instances
    Kf = K.float()

    def ours():
        cloud = backproject_depth(
            depth.expand(n, H, W), Kf, masks, max_points=args.cap, generator=torch.Generator()
        )
        idx, valid = farthest_point_sample(cloud.points, args.points, cloud.mask)
        pts = cloud.points.gather(1, idx.unsqueeze(-1).expand(-1, -1, 3))
        pixels = cloud.pixels.gather(1, idx.unsqueeze(-1).expand(-1, -1, 2))
        normals = estimate_normals(pts, valid, k=args.k)
        return pts, valid, pixels, normals

    intr = o3d.camera.PinholeCameraIntrinsic(W, H, 600.0, 600.0, 319.5, 239.5)
    depth_np = depth.numpy()
    masks_np = masks.numpy()

    def theirs():
        clouds = []
        for i in range(n):
            d = o3d.geometry.Image(np.where(masks_np[i], depth_np, 0.0).astype(np.float32))
            pcd = o3d.geometry.PointCloud.create_from_depth_image(d, intr, depth_scale=1.0)
            if len(pcd.points) > args.cap:
                pcd = pcd.random_down_sample(args.cap / len(pcd.points))
            pcd = pcd.farthest_point_down_sample(min(args.points, len(pcd.points)))
            pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(args.k))
            clouds.append(pcd)
        return clouds

    t_ours, t_theirs, (_, valid, _, normals), clouds = timed_pair(ours, theirs, args.repeats)
    ours_s, theirs_s = min(t_ours), min(t_theirs)
    median_ratio = statistics.median(t_ours) / statistics.median(t_theirs)
    pixels_per_instance = masks.flatten(1).sum(1)
    return {
        "instances": n,
        "visible_pixels_per_instance_median": int(pixels_per_instance.median()),
        "cap": args.cap,
        "M": args.points,
        "k": args.k,
        "repeats": args.repeats,
        "poseflow_ms": round(ours_s * 1000, 2),
        "open3d_ms": round(theirs_s * 1000, 2),
        "poseflow_images_per_s": round(1 / ours_s, 2),
        "open3d_images_per_s": round(1 / theirs_s, 2),
        "ratio_poseflow_over_open3d_time": round(ours_s / theirs_s, 3),
        "ratio_of_medians": round(median_ratio, 3),
        "poseflow_points": int(valid.sum()),
        "open3d_points": sum(len(c.points) for c in clouds),
        "poseflow_unit_normals": bool(((normals[valid].norm(dim=-1) - 1).abs() < 1e-4).all()),
    }


def bench_render(args: argparse.Namespace) -> dict:
    meshes = [demo_mesh(n) for n in DEMO_OBJECT_NAMES]
    renderer = Renderer(meshes)
    g = torch.Generator().manual_seed(1)
    poses = [scene_poses(len(meshes), g) for _ in range(args.render_scenes)]
    for P in poses:  # tighter: three objects side by side, overlapping a little
        P[:, 0, 3] = torch.tensor([-0.09, 0.0, 0.09])
        P[:, 1, 3] = 0.0

    def ours_at(P: torch.Tensor):
        return renderer.render(P, K, W, H)

    legacy = [m.to_open3d() for m in meshes]
    # Open3D shoots pixel (u, v)'s ray through (u + 0.5, v + 0.5): moving the principal point by
    # +0.5 makes its rays pass through the integer pixel positions, as poseflow's do
    rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(
        o3d.core.Tensor(K.numpy() + np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])),
        o3d.core.Tensor(np.eye(4)),
        W,
        H,
    )

    def theirs_at(P: torch.Tensor):
        scene = o3d.t.geometry.RaycastingScene()
        for m, T in zip(legacy, P.numpy()):
            posed = o3d.geometry.TriangleMesh(m).transform(T)
            scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(posed))
        return scene.cast_rays(rays)

    def cycling(fn):
        state = {"i": 0}

        def call():
            state["i"] += 1
            return fn(poses[state["i"] % len(poses)])

        return call

    ours_s, _ = timed(cycling(ours_at), args.repeats)
    theirs_s, _ = timed(cycling(theirs_at), args.repeats)
    out, hit = ours_at(poses[0]), theirs_at(poses[0])
    # both cast rays through the same pixel centres: the z of their hits must agree (up to the
    # float32 placement of the meshes; pixels on silhouettes may see different surfaces)
    t = hit["t_hit"].numpy()
    z = t * rays.numpy()[..., 5]
    both = np.isfinite(z) & (out.depth.numpy() > 0)
    agree = np.abs(z[both] - out.depth.numpy()[both]) < 1e-4
    return {
        "objects": len(meshes),
        "triangles": sum(m.num_triangles for m in meshes),
        "size": f"{W}x{H}",
        "poseflow_ms": round(ours_s * 1000, 2),
        "open3d_depth_only_ms": round(theirs_s * 1000, 2),
        "poseflow_renders_per_s": round(1 / ours_s, 2),
        "open3d_depth_only_renders_per_s": round(1 / theirs_s, 2),
        "ratio_poseflow_over_open3d_time": round(ours_s / theirs_s, 3),
        "depth_agreement_within_0.1mm": round(float(agree.mean()), 5) if both.any() else None,
        "silhouette_pixels_differing": int((np.isfinite(z) != (out.depth.numpy() > 0)).sum()),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats, smaller M (CI)")
    parser.add_argument("--instances", type=int, default=8)
    parser.add_argument("--points", type=int, default=1024, help="M, points per instance")
    parser.add_argument("--cap", type=int, default=4096, help="random pixels kept per instance")
    parser.add_argument("--k", type=int, default=30, help="neighbours for normals")
    parser.add_argument("--render-scenes", type=int, default=5)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: default)")
    args = parser.parse_args(argv)
    if args.quick:
        args.points, args.cap, args.repeats, args.render_scenes = 256, 1024, 1, 2
    if args.threads:
        torch.set_num_threads(args.threads)
    record = {
        "benchmark": "data",
        "machine": machine(),
        "torch": torch.__version__,
        "open3d": o3d.__version__,
        "lifting": bench_lifting(args),
        "render": bench_render(args),
    }
    report(record, __file__, argv)


if __name__ == "__main__":
    main()
