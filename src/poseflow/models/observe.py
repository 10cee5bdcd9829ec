"""Observations: the target cloud of every masked instance of an RGBD image, with its features.

For each instance mask the depth is back-projected (camera frame, metres), cut to a random subset
of at most ``dense_points`` points, cleaned of statistical outliers and thinned to ``N`` points by
farthest-point sampling; normals are estimated and the frozen encoders describe the cloud. The
stages are reported to the active :class:`~poseflow.eval.timing.StageTimer` (``other``,
``geometric_encoder``, ``appearance_encoder``).

Shape letters: ``B`` instances, ``N`` points per cloud, ``Dg`` geometric channels, ``G`` raw
appearance channels, ``H`` / ``W`` image size.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from poseflow._checks import check_tensor
from poseflow._precision import precision_autocast
from poseflow._units import check_intrinsics
from poseflow.errors import ShapeError
from poseflow.eval.timing import stage
from poseflow.features import (
    AppearanceEncoder,
    GeometricEncoder,
    depth_layers,
    encode_on_support,
    lift_target_features,
)
from poseflow.geometry.pointcloud import (
    backproject_depth,
    estimate_normals,
    farthest_point_sample,
    remove_statistical_outliers,
    voxel_downsample,
)

__all__ = ["MIN_POINTS", "Observation", "observe"]

#: Instances with fewer valid target points are flagged invalid.
MIN_POINTS = 16

#: Neighbours of the normals of the grid-thinned descriptor support.
_SUPPORT_NORMAL_NEIGHBOURS = 16


@dataclass
class Observation:
    """Target clouds lifted from an RGBD image, with their frozen features.

    Attributes:
        obj_ids: object of each instance ``(B,)``.
        points: target clouds ``(B, N, 3)``, camera frame, metres (padded rows repeat a point).
        normals: unit normals ``(B, N, 3)`` facing the camera.
        mask: valid points ``(B, N)``.
        valid: instances with enough points ``(B,)``; the others are padding only.
        geometric: ``Φ(T)`` ``(B, N, Dg)`` or None.
        appearance: raw lifted appearance features ``(B, N, G)`` or None.
        cloud: the denser cloud ``T`` was sampled from ``(B, P, 3)``, camera frame, metres: the
            masked depth after the ``dense_points`` cap and outlier removal (for refinements
            that want more points than ``N``), or None.
        cloud_mask: its valid points ``(B, P)``, or None.
    """

    obj_ids: torch.Tensor
    points: torch.Tensor
    normals: torch.Tensor
    mask: torch.Tensor
    valid: torch.Tensor
    geometric: torch.Tensor | None
    appearance: torch.Tensor | None
    cloud: torch.Tensor | None = None
    cloud_mask: torch.Tensor | None = None


@torch.no_grad()
def observe(
    rgb: torch.Tensor,
    depth: torch.Tensor,
    K: torch.Tensor,
    masks: torch.Tensor,
    obj_ids: torch.Tensor | Sequence[int],
    diameters: Sequence[float],
    *,
    num_points: int,
    dense_points: int,
    geometric_encoder: GeometricEncoder | None = None,
    appearance_encoder: AppearanceEncoder | None = None,
    geometric_support_voxel: float = 0.0,
    generator: torch.Generator | None = None,
    crop_jitter: float = 0.0,
    appearance_precision: str = "fp32",
) -> Observation:
    """Lift the masked depth of each instance to a cloud of ``N`` points with its features.

    Args:
        rgb: the image ``(3, H, W)`` in ``[0, 1]`` (float) or ``[0, 255]`` (uint8).
        depth: depth ``(H, W)`` in metres (0 or NaN where missing).
        K: intrinsics ``(3, 3)``.
        masks: instance masks ``(B, H, W)`` bool.
        obj_ids: object id of each mask ``(B,)``.
        diameters: the diameter of each instance's object, metres ``(B,)``.
        num_points: points ``N`` per cloud.
        dense_points: cap on the back-projected cloud before outlier removal and sampling.
        geometric_encoder: the frozen geometric encoder, or None.
        appearance_encoder: the frozen appearance encoder, or None.
        geometric_support_voxel: describe the ``N`` points within the cleaned dense cloud
            thinned on a grid of this many diameters (see
            :func:`~poseflow.features.encode_on_support`); 0: within the ``N`` points alone.
        generator: seeds the dense-cloud cap and the start of the farthest-point sampling.
        crop_jitter: training augmentation of the appearance crop (see
            :func:`~poseflow.features.lifting.jitter_boxes`); 0 at inference.
        appearance_precision: what an appearance encoder that is a network (``autocast``
            True) computes in, as :func:`~poseflow.flows.autocast_dtype` names it.

    Returns:
        The :class:`Observation`; instances with fewer than :data:`MIN_POINTS` valid points are
        flagged invalid (their features are computed on padding and ignored downstream).
        Without masks (``B = 0``) every field has a batch size of 0.

    Raises:
        ShapeError: inconsistent shapes, not as many ids as masks, or ``K`` not 9 numbers.
        ValueRangeError: ``K`` is not a pinhole matrix of this image (see
            :func:`~poseflow._units.check_intrinsics`).
    """
    obj_ids = torch.as_tensor(obj_ids, dtype=torch.long).reshape(-1)
    sizes = check_tensor(masks, "masks", ("B", "H", "W"), floating=False)
    check_tensor(depth, "depth", ("H", "W"), sizes=sizes, floating=False)
    check_tensor(rgb, "rgb", (3, "H", "W"), sizes=sizes, floating=False)
    if len(obj_ids) != sizes["B"]:
        raise ShapeError(f"got {sizes['B']} masks but {len(obj_ids)} object ids")
    K = check_intrinsics(K, sizes["W"], sizes["H"], dtype=torch.float32, device=depth.device)
    if sizes["B"] == 0:
        return _empty_observation(
            obj_ids.to(depth.device), num_points, geometric_encoder, appearance_encoder
        )
    image = rgb.float() / 255.0 if not rgb.is_floating_point() else rgb.float()
    depth = torch.nan_to_num(depth.float(), nan=0.0, posinf=0.0)
    with stage("lifting"):
        obs, pixels = _lift(depth, K, masks, obj_ids, num_points, dense_points, generator)
    diameter = torch.tensor(list(diameters), device=obs.points.device)
    if geometric_encoder is not None:
        with stage("geometric_encoder"):
            obs.geometric = _geometric_features(
                obs, geometric_encoder, diameter, geometric_support_voxel
            )
    if appearance_encoder is not None:
        with stage("appearance_encoder"):
            if getattr(appearance_encoder, "in_channels", 3) > 3:
                layers = depth_layers(depth.expand(len(masks), *depth.shape), masks, diameter)
                image = torch.cat([image.expand(len(masks), *image.shape), layers], dim=1)
            precision = (
                appearance_precision if getattr(appearance_encoder, "autocast", False) else "fp32"
            )
            with precision_autocast(precision, image.device):
                obs.appearance = _appearance_features(
                    obs, pixels, appearance_encoder, image, K, crop_jitter, generator
                )
    return obs


def _lift(
    depth: torch.Tensor,
    K: torch.Tensor,
    masks: torch.Tensor,
    obj_ids: torch.Tensor,
    num_points: int,
    dense_points: int,
    generator: torch.Generator | None,
) -> tuple[Observation, torch.Tensor]:
    """The clouds of the masks, without features, and the pixels ``(B, N, 2)`` of their points.

    The masked depth ``(H, W)`` is back-projected, capped at ``dense_points`` random points,
    cleaned of statistical outliers and thinned to ``N = num_points`` by farthest-point sampling;
    the normals of the ``N`` points face the camera.
    """
    B = masks.shape[0]
    cloud = backproject_depth(depth.expand(B, *depth.shape), K, masks.bool())
    cloud_points, cloud_pixels, keep = cloud.points, cloud.pixels, cloud.mask
    if cloud_points.shape[1] == 0:  # every mask empty: one padded point each
        cloud_points = K.new_zeros(B, 1, 3)
        cloud_pixels = torch.zeros(B, 1, 2, dtype=torch.long, device=K.device)
        keep = torch.zeros(B, 1, dtype=torch.bool, device=K.device)
    if cloud_points.shape[1] > dense_points:
        cloud_points, cloud_pixels, keep = _random_subset(
            cloud_points, cloud_pixels, keep, dense_points, generator
        )
    if cloud_points.shape[1] >= 20:
        keep = remove_statistical_outliers(cloud_points, keep, k=20)
    idx, valid_pts = farthest_point_sample(cloud_points, num_points, keep, generator=generator)
    points = torch.gather(cloud_points, 1, idx[..., None].expand(-1, -1, 3))
    pixels = torch.gather(cloud_pixels, 1, idx[..., None].expand(-1, -1, 2))
    valid = valid_pts.sum(dim=1) >= MIN_POINTS
    normals = estimate_normals(points, valid_pts, k=min(16, num_points))
    obs = Observation(obj_ids, points, normals, valid_pts, valid, None, None, cloud_points, keep)
    return obs, pixels


def _geometric_features(
    obs: Observation, encoder: GeometricEncoder, diameter: torch.Tensor, support_voxel: float
) -> torch.Tensor:
    """``Φ(T)`` ``(B, N, Dg)`` of the instances with enough points (zero for the others).

    With a ``support_voxel`` (in diameters), the points are described within their grid-thinned
    cleaned dense cloud (:func:`~poseflow.features.encode_on_support`).
    """
    B, n = obs.mask.shape
    v = obs.valid
    geometric = obs.points.new_zeros(B, n, encoder.dim)
    if not bool(v.any()):
        return geometric
    points, normals, mask = obs.points[v], obs.normals[v], obs.mask[v]
    if support_voxel:
        support, support_ok = _grid_thinned(
            obs.cloud[v], obs.cloud_mask[v], support_voxel * diameter[v]
        )
        support_normals = estimate_normals(support, support_ok, k=_SUPPORT_NORMAL_NEIGHBOURS)
        geometric[v] = encode_on_support(
            encoder, points, normals, mask, support, support_normals, support_ok, diameter[v]
        )
    else:
        geometric[v] = encoder.encode(points, normals, mask, diameter[v])
    return geometric


def _appearance_features(
    obs: Observation,
    pixels: torch.Tensor,
    encoder: AppearanceEncoder,
    image: torch.Tensor,
    K: torch.Tensor,
    crop_jitter: float,
    generator: torch.Generator | None,
) -> torch.Tensor:
    """Raw appearance features ``(B, N, G)`` lifted from the image to the points.

    ``image`` is the colour ``(3, H, W)``, or per instance ``(B, C, H, W)`` (the colour and the
    instance's depth layers for a depth-aware encoder).

    Only the instances with enough points are described; the others stay zero.
    """
    B, n = obs.mask.shape
    v = obs.valid
    appearance = obs.points.new_zeros(B, n, encoder.dim)
    if bool(v.any()):
        appearance[v] = lift_target_features(
            encoder,
            (image if bool(v.all()) else image[v])  # no copy of the full images when all are valid
            if image.dim() == 4
            else image.expand(int(v.sum()), *image.shape),
            obs.points[v],
            K,
            obs.mask[v],
            pixels=pixels[v].to(obs.points.dtype),
            jitter=crop_jitter,
            generator=generator if crop_jitter > 0 else None,
        )
    return appearance


def _empty_observation(
    obj_ids: torch.Tensor,
    n: int,
    geometric_encoder: GeometricEncoder | None,
    appearance_encoder: AppearanceEncoder | None,
) -> Observation:
    """The :class:`Observation` of no instance: every field with a batch size of 0."""
    points = torch.zeros(0, n, 3, device=obj_ids.device)
    none = torch.zeros(0, n, dtype=torch.bool, device=obj_ids.device)
    return Observation(
        obj_ids=obj_ids,
        points=points,
        normals=points.clone(),
        mask=none,
        valid=none[:, 0],
        geometric=None
        if geometric_encoder is None
        else points.new_zeros(0, n, geometric_encoder.dim),
        appearance=None
        if appearance_encoder is None
        else points.new_zeros(0, n, appearance_encoder.dim),
        cloud=points.new_zeros(0, 1, 3),
        cloud_mask=none[:, :1],
    )


def _random_subset(
    points: torch.Tensor,
    pixels: torch.Tensor,
    mask: torch.Tensor,
    size: int,
    generator: torch.Generator | None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A uniform random subset of at most ``size`` valid points per cloud.

    Args:
        points: clouds ``(B, P, 3)``.
        pixels: their pixels ``(B, P, 2)``.
        mask: validity ``(B, P)`` bool.
        size: points kept, ``< P``.
        generator: seeds the draw (None: a fixed seed, so that repeated calls agree).

    Returns:
        ``(points, pixels, mask)`` with ``size`` columns; clouds with fewer valid points keep
        them all (and padding).
    """
    if generator is None:
        generator = torch.Generator(device=mask.device).manual_seed(0)
    keys = torch.rand(mask.shape, generator=generator, device=mask.device)
    keys = torch.where(mask, keys, 2.0)  # valid points first, in random order
    idx = keys.topk(size, dim=1, largest=False).indices
    take = lambda t: torch.gather(t, 1, idx[..., None].expand(-1, -1, t.shape[-1]))  # noqa: E731
    return take(points), take(pixels), torch.gather(mask, 1, idx)


def _grid_thinned(
    points: torch.Tensor, mask: torch.Tensor, voxel: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """One point per grid cell of side ``voxel[b]`` of each cloud: ``(B, M, 3)`` and its mask.

    The clouds are scaled to unit voxels so that one call thins every instance at its own size.
    """
    idx, ok = voxel_downsample(points / voxel[:, None, None], 1.0, mask)
    return torch.gather(points, 1, idx[..., None].expand(-1, -1, 3)), ok
