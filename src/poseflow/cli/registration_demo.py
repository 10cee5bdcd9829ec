"""``poseflow demo registration``: the registration stage of the paper on generated data.

Its arguments are declared in :mod:`poseflow.cli.demo`, so that ``poseflow --help`` does not
import torch.

For a few object instances with known poses, putative correspondences between the observed cloud
(camera frame) and its predicted canonical coordinates, 40% of them wrong, go through poseflow's
batched RANSAC-Procrustes and coarse-to-fine ICP against the model cloud; the recovered poses are
compared with the truth, and the time with Open3D's looped equivalents on the same data.

The generators (:func:`blob_shapes`, :func:`sample_surface`, :func:`make_scenes`) are also used by
``benchmarks/registration.py``.
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass

import torch

__all__ = ["Scenes", "blob_shapes", "make_scenes", "run", "sample_surface"]

#: Radius of the generated objects, in metres (objects about 20 cm across).
OBJECT_RADIUS = 0.1


@dataclass
class Scenes:
    """Generated registration problems, batch-first, float64, in metres.

    Attributes:
        model: model clouds in the object frame ``(B, P, 3)``.
        observed: observed clouds in the camera frame ``(B, N, 3)``: a noisy half of each object
            seen from a random side, sampled independently of ``model``.
        predicted: predicted canonical coordinates of ``observed`` ``(B, N, 3)``; pairs flagged
            in ``outlier`` point somewhere else on the object.
        outlier: ``(B, N)`` bool, the wrong pairs.
        pose: true model-to-camera poses ``(B, 4, 4)``.
    """

    model: torch.Tensor
    observed: torch.Tensor
    predicted: torch.Tensor
    outlier: torch.Tensor
    pose: torch.Tensor


def blob_shapes(B: int, *, generator: torch.Generator, terms: int = 4) -> torch.Tensor:
    """Draw ``B`` random smooth, asymmetric, elongated star-shaped surfaces.

    A shape is ``x(u) = OBJECT_RADIUS * diag(e) u (1 + sum_k a_k sin(w_k . u + phi_k))`` over
    unit directions ``u``, with axis lengths ``e`` between 0.4 and 1, so that no rotation maps
    it onto itself and ICP has a well-defined optimum.

    Returns:
        Parameters ``(B, terms + 1, 5)``: the first row holds ``e`` (3) then zeros, each other
        row a frequency vector ``w`` (3), an amplitude ``a`` and a phase ``phi``.
    """
    kw = {"generator": generator, "dtype": torch.float64}
    w = torch.randn(B, terms, 3, **kw)
    w = w / w.norm(dim=-1, keepdim=True) * (1.5 + 1.5 * torch.rand(B, terms, 1, **kw))
    a = 0.08 + 0.12 * torch.rand(B, terms, 1, **kw)
    phi = 2 * math.pi * torch.rand(B, terms, 1, **kw)
    axes = torch.tensor([1.0, 0.7, 0.4], dtype=torch.float64) + 0.1 * torch.rand(B, 3, **kw)
    first = torch.cat((axes, torch.zeros(B, 2, dtype=torch.float64)), -1).unsqueeze(1)
    return torch.cat((first, torch.cat((w, a, phi), -1)), 1)


def sample_surface(
    shapes: torch.Tensor,
    n: int,
    *,
    generator: torch.Generator,
    view: torch.Tensor | None = None,
) -> torch.Tensor:
    """Sample ``n`` points on each shape of :func:`blob_shapes`, in the object frame.

    Args:
        shapes: ``(B, K + 1, 5)`` shape parameters.
        n: points per shape.
        generator: seeded generator.
        view: optional ``(B, 3)`` directions; only the half of each surface facing it is sampled.

    Returns:
        Points ``(B, n, 3)`` (float64).
    """
    B = shapes.shape[0]
    u = torch.randn(B, n, 3, generator=generator, dtype=torch.float64)
    u = u / u.norm(dim=-1, keepdim=True)
    if view is not None:
        u = u * torch.where((u * view[:, None]).sum(-1, keepdim=True) < 0, -1.0, 1.0)
    axes, terms = shapes[:, 0, :3], shapes[:, 1:]
    w, a, phi = terms[..., :3], terms[..., 3], terms[..., 4]
    r = 1 + (a[:, None] * torch.sin(u @ w.transpose(1, 2) + phi[:, None])).sum(-1)
    return u * axes[:, None] * (OBJECT_RADIUS * r).unsqueeze(-1)


def make_scenes(
    B: int,
    n: int,
    *,
    model_points: int = 2000,
    outliers: float = 0.4,
    noise: float = 0.001,
    flow_noise: float | None = None,
    seed: int = 0,
) -> Scenes:
    """Generate ``B`` registration problems with known poses (see :class:`Scenes`).

    Args:
        B: number of instances.
        n: observed points (correspondences) per instance.
        model_points: model cloud size.
        outliers: fraction of wrong correspondences (exactly ``round(outliers * n)`` each).
        noise: standard deviation of the Gaussian noise on the observed cloud, in metres.
        flow_noise: that of the predicted canonical coordinates (``noise`` by default).
        seed: seed of the generator.

    Returns:
        The generated :class:`Scenes`.
    """
    from poseflow.geometry.se3 import from_Rt, random_rotation, transform_points

    g = torch.Generator().manual_seed(seed)
    shapes = blob_shapes(B, generator=g)
    model = sample_surface(shapes, model_points, generator=g)
    view = torch.randn(B, 3, generator=g, dtype=torch.float64)
    local = sample_surface(shapes, n, generator=g, view=view)
    R = random_rotation(B, generator=g, dtype=torch.float64)
    t = torch.randn(B, 3, generator=g, dtype=torch.float64) * 0.1
    t[:, 2] += 0.8  # in front of the camera
    pose = from_Rt(R, t)
    observed = transform_points(pose, local)
    observed = observed + noise * torch.randn(B, n, 3, generator=g, dtype=torch.float64)
    flow_noise = noise if flow_noise is None else flow_noise
    predicted = local + flow_noise * torch.randn(B, n, 3, generator=g, dtype=torch.float64)
    k = round(outliers * n)
    outlier = torch.zeros(B, n, dtype=torch.bool)
    rows = torch.arange(B)[:, None]
    outlier[rows, torch.rand(B, n, generator=g).argsort(-1)[:, :k]] = True
    wrong = sample_surface(shapes, n, generator=g)  # elsewhere on the object
    predicted = torch.where(outlier[..., None], wrong, predicted)
    return Scenes(model, observed, predicted, outlier, pose)


def _open3d_pipeline(scenes: Scenes, iterations: int, threshold: float, icp_scales: list[float]):
    """Open3D's RANSAC on the same correspondences, then its ICP per scale, looped over B."""
    import numpy as np

    from poseflow.render.backend import import_open3d

    o3d = import_open3d("the comparison with Open3D")

    reg = o3d.pipelines.registration
    B, N = scenes.observed.shape[:2]
    corres = o3d.utility.Vector2iVector(np.stack([np.arange(N)] * 2, 1).astype(np.int32))
    clouds = []
    for b in range(B):
        obs, pred = o3d.geometry.PointCloud(), o3d.geometry.PointCloud()
        obs.points = o3d.utility.Vector3dVector(scenes.observed[b].numpy())
        pred.points = o3d.utility.Vector3dVector(scenes.predicted[b].numpy())
        model = o3d.geometry.PointCloud()
        model.points = o3d.utility.Vector3dVector(scenes.model[b].numpy())
        clouds.append((obs, pred, model))
    criteria = reg.RANSACConvergenceCriteria(max_iteration=iterations, confidence=0.999)
    out = []
    start = time.perf_counter()
    for obs, pred, model in clouds:
        T = reg.registration_ransac_based_on_correspondence(
            obs,
            pred,
            corres,
            threshold,
            reg.TransformationEstimationPointToPoint(),
            3,
            [],
            criteria,
        ).transformation
        for distance in icp_scales:
            T = reg.registration_icp(obs, model, distance, T).transformation
        out.append(np.linalg.inv(T))
    elapsed = time.perf_counter() - start
    return torch.from_numpy(np.stack(out)), elapsed


def run(args: argparse.Namespace) -> int:
    """Run the demo with the parsed arguments; prints a table and returns 0."""
    from poseflow.cli.common import option_values
    from poseflow.geometry.se3 import inverse_transform, rotation_angle_error, translation_error
    from poseflow.registration import multi_scale_icp, ransac_procrustes

    if args.instances < 1 or args.points < 3 or not 0 <= args.outliers < 1:
        from poseflow.errors import ValueRangeError

        raise ValueRangeError("need --instances >= 1, --points >= 3 and 0 <= --outliers < 1")
    scenes = make_scenes(
        args.instances,
        args.points,
        **option_values(args, "model_points", "outliers", "noise", "flow_noise", "seed"),
    )
    # Three standard deviations of the pair residual's norm; ICP from 2 cm down to 5 mm.
    threshold = max(3 * math.hypot(args.noise, args.flow_noise) * math.sqrt(3), 1e-4)
    icp_scales = [0.02, 0.01, 0.005]

    def pipeline(sc: Scenes) -> tuple:
        g = torch.Generator().manual_seed(args.seed)
        start = time.perf_counter()
        coarse = ransac_procrustes(
            sc.observed,
            sc.predicted,
            max_correspondence_distance=threshold,
            max_iterations=args.iterations,
            generator=g,
        )
        ransac_s = time.perf_counter() - start
        # The paper's refinement: ICP of the observation onto the model, camera -> object frame.
        fine = multi_scale_icp(
            sc.observed, sc.model, coarse.transformation, max_correspondence_distances=icp_scales
        )
        return coarse, fine, ransac_s, time.perf_counter() - start

    first = Scenes(*(x[:1] for x in vars(scenes).values()))
    pipeline(first)  # warm-up: first calls pay for lazy imports and thread start-up
    coarse, fine, ransac_s, total_s = pipeline(scenes)
    coarse_pose = inverse_transform(coarse.transformation)
    pose = inverse_transform(fine.transformation)

    rot_c = rotation_angle_error(coarse_pose, scenes.pose)
    rot = rotation_angle_error(pose, scenes.pose)
    trans = translation_error(pose, scenes.pose) * 1000
    ours = (coarse.fitness, rot_c, rot, trans, total_s, ransac_s)
    if args.no_open3d:
        _print_report(args, ours, None)
        return 0
    _open3d_pipeline(first, args.iterations, threshold, icp_scales)  # warm-up
    o3d_pose, o3d_s = _open3d_pipeline(scenes, args.iterations, threshold, icp_scales)
    rot_o3d = rotation_angle_error(o3d_pose, scenes.pose)
    trans_o3d = translation_error(o3d_pose, scenes.pose) * 1000
    _print_report(args, ours, (rot_o3d, trans_o3d, o3d_s))
    return 0


def _print_report(args: argparse.Namespace, ours: tuple, open3d: tuple | None) -> None:
    """The per-object errors ``(B,)`` of poseflow (and Open3D), their medians and the times.

    Args:
        args: the parsed arguments.
        ours: RANSAC's inlier fractions, its rotation errors, the rotation and translation
            errors after ICP (degrees, mm), the total and the RANSAC seconds.
        open3d: Open3D's rotation and translation errors and its seconds, or None.
    """
    fitness, rot_c, rot, trans, total_s, ransac_s = ours
    print(
        f"poseflow registration demo: {args.instances} objects, {args.points} correspondences "
        f"each, {args.outliers:.0%} outliers, noise {args.noise * 1000:.1f} mm (depth) and "
        f"{args.flow_noise * 1000:.1f} mm (predictions), seed {args.seed}"
    )
    header = f"{'object':>6} {'inliers':>8} {'RANSAC rot':>11} {'+ICP rot':>9} {'+ICP trans':>11}"
    if open3d is not None:
        header += f" {'Open3D rot':>11} {'Open3D trans':>13}"
    print(header)
    for b in range(args.instances):
        line = (
            f"{b:>6} {fitness[b].item():>8.1%} {rot_c[b].item():>9.3f} ° "
            f"{rot[b].item():>7.3f} ° {trans[b].item():>8.2f} mm"
        )
        if open3d is not None:
            line += f" {open3d[0][b].item():>9.3f} ° {open3d[1][b].item():>10.2f} mm"
        print(line)
    print(
        f"median rotation error: poseflow {rot.median().item():.3f}°"
        + ("" if open3d is None else f", Open3D {open3d[0].median().item():.3f}°")
    )
    print(
        f"time for all {args.instances}: poseflow {total_s * 1000:.1f} ms "
        f"(RANSAC {ransac_s * 1000:.1f} ms)"
        + (
            ""
            if open3d is None
            else f", Open3D {open3d[2] * 1000:.1f} ms ({open3d[2] / total_s:.1f}x poseflow's time)"
        )
    )
