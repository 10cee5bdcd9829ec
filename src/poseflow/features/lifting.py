"""Lifting pixel features to points: the target crop and the query's multi-view bank.

Target (paper, "Feature extraction"): the square crop of the RGB image centred on the projection of
the target cloud's barycentre (:func:`~poseflow.geometry.crops.crop_box_around`), resized to
the encoder's input size; the feature map is sampled bilinearly at every point's pixel.

Query: the textured model is rendered from ``num_views`` viewpoints on a sphere (Fibonacci
lattice), each at ``rolls`` in-plane rotations of the camera; every rendering is cropped exactly
like a target (same box rule, same resize), encoded, and its features are read at the pixels of the
model points that the view sees (a point is seen when its depth agrees with the rendered depth at
its pixel within ``visibility_tolerance × diameter``). The result is a
:class:`QueryFeatureBank` ``(N, K, G)`` with a visibility mask ``(N, K)``, ``K = num_views ×
rolls``, from which the pipeline takes

- :meth:`QueryFeatureBank.pooled`: the mean over the views that see each point (the paper's
  mean pooling; right for descriptors that barely change with the view, the DINOv2 default), or
- :meth:`QueryFeatureBank.select`: per target instance, each point's feature from the view that
  best matches the target (views scored by the mean, over target points, of the best cosine
  similarity to that view's features); for descriptors tied to the image axes such as SIFT, whose
  average over views with arbitrary roll washes out.

Points that no view sees get the feature of the nearest seen point (3D distance) in both modes.

``python benchmarks/features.py`` measures both modes by correspondence inliers (figures in
``benchmarks/RESULTS.md``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from torch.nn import functional as F

from poseflow._checks import check_mask, check_tensor
from poseflow.errors import DegenerateInputError, ShapeError, ValueRangeError
from poseflow.features.appearance import AppearanceEncoder, features_at
from poseflow.features.learned import depth_layers
from poseflow.geometry.crops import crop_box_around, crop_resize, pixels_to_crop
from poseflow.geometry.neighbors import nearest_neighbors
from poseflow.geometry.projection import project_points

__all__ = [
    "QueryFeatureBank",
    "jitter_boxes",
    "lift_query_features",
    "lift_target_features",
    "viewpoint_poses",
]


@torch.no_grad()
def lift_target_features(
    encoder: AppearanceEncoder,
    images: torch.Tensor,
    points: torch.Tensor,
    K: torch.Tensor,
    mask: torch.Tensor | None = None,
    *,
    pixels: torch.Tensor | None = None,
    margin: float = 1.1,
    jitter: float = 0.0,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Appearance features of observed points from the crop around their barycentre.

    Args:
        encoder: the appearance encoder (its ``input_size`` is the crop side).
        images: RGB images ``(B, 3, H, W)`` in ``[0, 1]``; one per target instance (repeat the
            image for several instances of one image, the crops are batched). A depth-aware
            encoder (``in_channels`` 5) takes each instance's
            :func:`~poseflow.features.learned.depth_layers` appended, ``(B, 5, H, W)``.
        points: target clouds in the camera frame ``(B, M, 3)``, metres.
        K: intrinsics ``(B, 3, 3)`` or ``(3, 3)``.
        mask: valid points ``(B, M)`` bool, or None.
        pixels: each point's pixel ``(B, M, 2)`` (``(u, v)``, from the back-projection); None
            projects the points with ``K``.
        margin: crop side over the tight square around the points' projections.
        jitter: training augmentation of the crop (a detector's imprecise box): each box is
            shifted by up to ``jitter`` of its side along each axis and its side scaled by a
            factor in ``[1 - jitter, 1 + jitter]``, uniformly; 0 (inference) leaves it exact.
        generator: seeds the jitter.

    Returns:
        Features ``(B, M, G)`` in the images' dtype, zero on padded rows.

    Raises:
        ValueRangeError: NaN or inf in the crop of an instance.

    Example:
        >>> from poseflow.features.appearance import DenseSIFTEncoder
        >>> K = torch.tensor([[100.0, 0, 32], [0, 100.0, 32], [0, 0, 1]])
        >>> pts = torch.rand(1, 50, 3, generator=torch.Generator().manual_seed(0)) * 0.1
        >>> pts[..., 2] += 1.0
        >>> enc = DenseSIFTEncoder(input_size=32)
        >>> lift_target_features(enc, torch.rand(1, 3, 64, 64), pts, K).shape
        torch.Size([1, 50, 128])
    """
    channels = getattr(encoder, "in_channels", 3)
    sizes = check_tensor(images, "images", ("B", channels, "H", "W"))
    check_tensor(points, "points", ("B", "M", 3), sizes=sizes)
    if mask is None:
        mask = torch.ones(points.shape[:2], dtype=torch.bool, device=points.device)
    check_mask(mask, "mask", ("B", "M"), sizes)
    K = K.to(points.dtype)
    box = crop_box_around(points, K, mask, margin=margin)
    if jitter > 0:
        box = jitter_boxes(box, jitter, generator=generator)
    size = encoder.input_size
    crops = crop_resize(images, box.to(images.dtype), size)
    if not bool(torch.isfinite(crops).all()):  # what the encoder reads, not the whole images
        raise ValueRangeError("images contain NaN or inf where an instance is cropped")
    uv = project_points(points, K, mask) if pixels is None else pixels
    crop_uv = pixels_to_crop(uv, box, size).to(crops.dtype)
    out = features_at(encoder, crops, crop_uv)
    return torch.where(mask[..., None], out, torch.zeros((), dtype=out.dtype, device=out.device))


def jitter_boxes(
    box: torch.Tensor, amount: float, *, generator: torch.Generator | None = None
) -> torch.Tensor:
    """Square boxes moved and rescaled at random, as a detector's imprecision would.

    Args:
        box: boxes ``(B, 4)`` as ``(x0, y0, x1, y1)`` with equal sides.
        amount: largest shift, as a fraction of the side, and largest relative change of the
            side; in ``[0, 0.5)``.
        generator: seeds the draw (made on the generator's device; the result is on ``box``'s).

    Returns:
        Square boxes ``(B, 4)``.

    Example:
        >>> b = jitter_boxes(torch.tensor([[0.0, 0.0, 10.0, 10.0]]), 0.1,
        ...                  generator=torch.Generator().manual_seed(0))
        >>> side = b[0, 2] - b[0, 0]
        >>> bool(9.0 <= side <= 11.0), bool(torch.isclose(side, b[0, 3] - b[0, 1]))
        (True, True)
    """
    if not 0 <= amount < 0.5:
        raise ValueRangeError(f"jitter must be in [0, 0.5), got {amount}")
    check_tensor(box, "box", ("B", 4))
    where = generator.device if generator is not None else box.device
    u = torch.rand(box.shape[0], 3, generator=generator, dtype=torch.float64, device=where)
    u = (u * 2 - 1).to(box)
    side = box[:, 2] - box[:, 0]
    centre = (box[:, :2] + box[:, 2:]) / 2 + amount * side[:, None] * u[:, :2]
    half = side * (1 + amount * u[:, 2]) / 2
    return torch.cat([centre - half[:, None], centre + half[:, None]], dim=1)


def viewpoint_poses(
    num_views: int,
    *,
    rolls: int = 1,
    distance: float,
    centre: torch.Tensor | None = None,
    dtype: torch.dtype = torch.float64,
) -> torch.Tensor:
    """Model-to-camera poses looking at ``centre`` from a Fibonacci sphere, at several rolls.

    Args:
        num_views: viewpoints on the sphere.
        rolls: in-plane camera rotations per viewpoint, evenly spaced over 360°.
        distance: camera distance to ``centre`` in metres.
        centre: the point looked at, ``(3,)`` in the model frame (default the origin).
        dtype: output dtype.

    Returns:
        Poses ``(num_views * rolls, 4, 4)`` (``x_cam = R x_model + t``), view-major.

    Example:
        >>> T = viewpoint_poses(4, rolls=2, distance=1.0)
        >>> T.shape, bool(torch.allclose(T[:, 2, 3], torch.ones(8, dtype=T.dtype)))
        (torch.Size([8, 4, 4]), True)
    """
    if num_views < 1 or rolls < 1 or not distance > 0:
        raise ValueRangeError("need num_views >= 1, rolls >= 1 and distance > 0")
    i = torch.arange(num_views, dtype=torch.float64) + 0.5
    polar = torch.acos(1 - 2 * i / num_views)
    azim = math.pi * (1 + 5**0.5) * i
    dirs = torch.stack(
        [polar.sin() * azim.cos(), polar.sin() * azim.sin(), polar.cos()], dim=-1
    )  # camera positions on the unit sphere
    z = -dirs  # optical axis towards the centre
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand_as(z)
    alt = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64).expand_as(z)
    up = torch.where(
        (z @ torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)).abs()[:, None] > 0.99, alt, up
    )
    x = F.normalize(torch.linalg.cross(up, z, dim=-1), dim=-1)
    y = torch.linalg.cross(z, x, dim=-1)
    cam_to_model = torch.stack([x, y, z], dim=-1)  # columns: camera axes in the model frame
    angles = torch.arange(rolls, dtype=torch.float64) * (2 * math.pi / rolls)
    c, s = angles.cos(), angles.sin()
    roll = torch.zeros(rolls, 3, 3, dtype=torch.float64)
    roll[:, 0, 0], roll[:, 0, 1], roll[:, 1, 0], roll[:, 1, 1], roll[:, 2, 2] = c, -s, s, c, 1
    R = roll[None] @ cam_to_model.transpose(1, 2)[:, None]  # (V, R, 3, 3) model -> camera
    R = R.reshape(-1, 3, 3)
    ctr = torch.zeros(3, dtype=torch.float64) if centre is None else centre.double().reshape(3)
    eye = (ctr + distance * dirs).repeat_interleave(rolls, dim=0)
    T = torch.zeros(len(R), 4, 4, dtype=torch.float64)
    T[:, :3, :3] = R
    T[:, :3, 3] = -(R @ eye[..., None])[..., 0]
    T[:, 3, 3] = 1
    return T.to(dtype)


@dataclass
class QueryFeatureBank:
    """Per-view appearance features of a model's points.

    Attributes:
        points: the model points ``(N, 3)`` in the model frame.
        features: features per point and view ``(N, K, G)`` (zero where not seen).
        visible: which views see which point ``(N, K)`` bool.
        poses: the rendering poses ``(K, 4, 4)``.
        rolls: in-plane rotations per viewpoint (``K = viewpoints × rolls``).
    """

    points: torch.Tensor
    features: torch.Tensor
    visible: torch.Tensor
    poses: torch.Tensor
    rolls: int = 1

    @classmethod
    def one_view(cls, points: torch.Tensor, features: torch.Tensor) -> QueryFeatureBank:
        """A bank of features ``(N, G)`` that describe points ``(N, 3)`` without views.

        For encoders that describe surface points directly (a surface embedding's keys): one
        view that sees every point, at the identity pose; float32 on the CPU.

        Example:
            >>> bank = QueryFeatureBank.one_view(torch.zeros(4, 3), torch.ones(4, 2))
            >>> bank.features.shape, bool(bank.visible.all())
            (torch.Size([4, 1, 2]), True)
        """
        check_tensor(points, "points", ("N", 3))
        check_tensor(features, "features", ("N", "G"))
        return cls(
            points.detach().clone().cpu().float(),
            features.detach().cpu().float()[:, None],
            torch.ones(points.shape[0], 1, dtype=torch.bool),
            torch.eye(4)[None],
        )

    @property
    def dim(self) -> int:
        """The feature size ``G``."""
        return int(self.features.shape[-1])

    def to(
        self, device: str | torch.device | None = None, dtype: torch.dtype | None = None
    ) -> QueryFeatureBank:
        """A copy with the floating tensors on ``device`` and in ``dtype``."""
        return QueryFeatureBank(
            self.points.to(device=device, dtype=dtype),
            self.features.to(device=device, dtype=dtype),
            self.visible.to(device=device),
            self.poses.to(device=device, dtype=dtype),
            self.rolls,
        )

    def _fill_unseen(self, feats: torch.Tensor, seen: torch.Tensor) -> torch.Tensor:
        """Copy, to points no view sees, the feature of their nearest seen point.

        ``feats`` is ``(N, G)`` or ``(B, N, G)``; ``seen`` ``(N,)``.
        """
        if bool(seen.all()):
            return feats
        if not bool(seen.any()):
            raise DegenerateInputError("no view sees any point of the model")
        pts = self.points.to(feats.device)
        _, idx = nearest_neighbors(pts[None], pts[None], k=1, reference_mask=seen[None])
        return torch.where(seen[:, None], feats, feats.index_select(-2, idx[0, :, 0]))

    def pooled(self) -> torch.Tensor:
        """Mean over the views that see each point (unseen points: nearest seen point), ``(N, G)``.

        Example:
            >>> bank = QueryFeatureBank(torch.rand(3, 3), torch.ones(3, 2, 4),
            ...                         torch.tensor([[True, False], [True, True], [False, False]]),
            ...                         torch.eye(4).expand(2, 4, 4))
            >>> bank.pooled().shape
            torch.Size([3, 4])
        """
        w = self.visible.to(self.features.dtype)[..., None]
        count = w.sum(dim=1)
        mean = (self.features * w).sum(dim=1) / count.clamp_min(1.0)
        return self._fill_unseen(mean, count[:, 0] > 0)

    @torch.no_grad()
    def select(
        self,
        target_features: torch.Tensor,
        target_mask: torch.Tensor | None = None,
        *,
        max_target_points: int = 256,
        max_query_points: int = 512,
    ) -> torch.Tensor:
        """Per target instance, each point's feature from the best-matching view that sees it.

        Every view ``k`` is scored by the mean, over (up to ``max_target_points``) target points,
        of the best cosine similarity among (up to ``max_query_points``) query points seen in
        ``k``; each query point then takes its feature from the highest-scoring view that sees
        it (points seen by no view: nearest seen point).

        Args:
            target_features: ``(B, M, G)`` features of the target instances.
            target_mask: valid target points ``(B, M)``, or None.
            max_target_points: target points used to score views (evenly strided subset).
            max_query_points: query points used to score views (evenly strided subset).

        Returns:
            Query features ``(B, N, G)`` in the target features' dtype and device.

        Example:
            >>> g = torch.Generator().manual_seed(0)
            >>> pts, feats = torch.rand(5, 3, generator=g), torch.randn(5, 3, 8, generator=g)
            >>> vis = torch.ones(5, 3, dtype=torch.bool)
            >>> bank = QueryFeatureBank(pts, feats, vis, torch.eye(4).expand(3, 4, 4))
            >>> sel = bank.select(bank.features[None, :, 2])  # the target looks like view 2
            >>> bool(torch.equal(sel[0], bank.features[:, 2]))
            True
        """
        sizes = check_tensor(target_features, "target_features", ("B", "M", self.dim), finite=True)
        if target_mask is None:
            target_mask = torch.ones(target_features.shape[:2], dtype=torch.bool)
        target_mask = target_mask.to(target_features.device)
        check_mask(target_mask, "target_mask", ("B", "M"), sizes)
        count = target_mask.sum(dim=1)
        if bool((count == 0).any()):
            empty = int((count == 0).nonzero()[0, 0])
            raise DegenerateInputError(f"target instance {empty} has no valid point")
        dev, dt = target_features.device, target_features.dtype
        bank = self.features.to(device=dev, dtype=dt)
        visible = self.visible.to(dev)
        N, K, G = bank.shape
        B, M = sizes["B"], sizes["M"]
        q_idx = torch.linspace(0, N - 1, min(N, max_query_points), device=dev).round().long()
        q_bank = F.normalize(bank[q_idx], dim=-1).reshape(-1, G)  # (n*K, G)
        q_vis = visible[q_idx]  # (n, K)
        n = len(q_idx)
        # Each instance's valid points, or an evenly strided subset of max_target_points of them.
        order = torch.argsort((~target_mask).to(torch.int8), dim=1, stable=True)  # valid first
        step = (count.to(torch.float64) - 1) / max(max_target_points - 1, 1)
        ranks = torch.arange(max_target_points, device=dev, dtype=torch.float64)
        cols = order.gather(1, (ranks[None] * step[:, None]).round().long().clamp(max=M - 1))
        strided = torch.zeros_like(target_mask).scatter_(1, cols, True)
        used = torch.where((count <= max_target_points)[:, None], target_mask, strided)
        # View scores: mean over used target points of the best similarity within each view,
        # in chunks of instances that keep the (b, M, n, K) similarity block near 2**24 values.
        t = F.normalize(target_features, dim=-1)
        chunk = max(1, 2**24 // max(1, M * n * K))
        score = torch.cat(
            [
                (t[i : i + chunk] @ q_bank.T)
                .reshape(-1, M, n, K)
                .masked_fill(~q_vis, -2.0)
                .amax(dim=2)
                .mul(used[i : i + chunk, :, None])
                .sum(dim=1)
                for i in range(0, B, chunk)
            ]
        ) / used.sum(dim=1, keepdim=True)  # (B, K)
        score = torch.where(q_vis.any(dim=0), score, torch.full_like(score, -3.0))
        per_point = torch.where(visible, score[:, None], torch.full_like(score[:, None], -4.0))
        best = per_point.argmax(dim=2)  # (B, N)
        feats = bank[torch.arange(N, device=dev), best]  # (B, N, G)
        return self._fill_unseen(feats, visible.any(dim=1))

    def state(self) -> dict[str, torch.Tensor]:
        """The bank as named tensors (visibility as uint8) for safetensors.

        The features keep their float32: a bank read back is the bank written, bit for bit, so
        that a cached preparation estimates exactly as a fresh one.
        """
        return {
            "points": self.points.detach().cpu().contiguous(),
            "features": self.features.detach().cpu().float().contiguous(),
            "visible": self.visible.detach().cpu().to(torch.uint8).contiguous(),
            "poses": self.poses.detach().cpu().contiguous(),
            "rolls": torch.tensor([self.rolls]),
        }

    @classmethod
    def from_state(cls, state: dict[str, torch.Tensor]) -> QueryFeatureBank:
        """Inverse of :meth:`state` (features in float32; older float16 entries are widened)."""
        return cls(
            state["points"],
            state["features"].float(),
            state["visible"].bool(),
            state["poses"],
            int(state["rolls"][0]),
        )


@torch.no_grad()
def lift_query_features(
    encoder: AppearanceEncoder,
    mesh: Any,
    points: torch.Tensor,
    diameter: float,
    *,
    num_views: int = 20,
    rolls: int | None = None,
    margin: float = 1.1,
    distance_factor: float = 3.0,
    visibility_tolerance: float = 0.02,
    batch_size: int = 8,
    renderer: Any = None,
) -> QueryFeatureBank:
    """Render the textured model from many views and lift the features to its points.

    Args:
        encoder: the appearance encoder.
        mesh: the textured model (anything :class:`~poseflow.render.Renderer` accepts: a
            ``TexturedMesh``, an ``ObjectModel``, an Open3D mesh), in metres, model frame.
        points: the model's query points ``(N, 3)`` in the model frame.
        diameter: the object diameter in metres.
        num_views: viewpoints on the sphere.
        rolls: in-plane rotations per viewpoint; None: 8 for encoders whose
            ``query_pooling`` is ``"select"``, else 1.
        margin: crop margin, as for the target.
        distance_factor: camera distance in diameters (the crop makes the scale irrelevant
            otherwise).
        visibility_tolerance: depth agreement (fraction of the diameter) for a point to count as
            seen.
        batch_size: renderings encoded per forward pass.
        renderer: a ready :class:`~poseflow.render.Renderer` over ``[mesh]`` (built if None).

    Returns:
        The :class:`QueryFeatureBank` (features in float32 on the CPU).

    Raises:
        DegenerateInputError: no view sees any point.
    """
    from poseflow.render import Renderer

    check_tensor(points, "points", ("N", 3), finite=True)
    if not diameter > 0:
        raise ValueRangeError(f"diameter must be positive, got {diameter}")
    if rolls is None:
        rolls = 8 if getattr(encoder, "query_pooling", "mean") == "select" else 1
    pts = points.detach().cpu().double()
    centre = pts.mean(dim=0)
    distance = distance_factor * diameter
    poses = viewpoint_poses(num_views, rolls=rolls, distance=distance, centre=centre)
    size = int(encoder.input_size)
    f = size * distance / (diameter * margin)
    K = torch.tensor([[f, 0.0, (size - 1) / 2], [0.0, f, (size - 1) / 2], [0.0, 0.0, 1.0]])
    K = K.double()
    renderer = Renderer([mesh]) if renderer is None else renderer
    n_views = len(poses)
    visible = torch.zeros(len(pts), n_views, dtype=torch.bool)
    features: torch.Tensor | None = None
    tolerance = visibility_tolerance * diameter
    depth_diameter = diameter if getattr(encoder, "in_channels", 3) > 3 else None
    for start in range(0, n_views, batch_size):
        chunk = range(start, min(n_views, start + batch_size))
        views = [
            _render_view(renderer, poses[k], K, size, pts, tolerance, margin, depth_diameter)
            for k in chunk
        ]
        crop_uv = torch.cat([pixels_to_crop(uv[None], box, size) for _, box, uv, _ in views])
        feats = features_at(encoder, torch.cat([v[0] for v in views]), crop_uv.float()).float()
        for j, k in enumerate(chunk):
            seen = views[j][3]
            if features is None:
                features = torch.zeros(len(pts), n_views, feats.shape[-1])
            features[:, k] = torch.where(seen[:, None], feats[j], torch.zeros(()))
            visible[:, k] = seen
    if features is None or not bool(visible.any()):
        raise DegenerateInputError("no rendered view sees any point of the model")
    if features.shape[-1] != encoder.dim:
        raise ShapeError(f"encoder returned {features.shape[-1]} channels, expected {encoder.dim}")
    return QueryFeatureBank(pts.to(points.dtype), features, visible, poses.to(points.dtype), rolls)


def _render_view(
    renderer: Any,
    pose: torch.Tensor,
    K: torch.Tensor,
    size: int,
    points: torch.Tensor,
    tolerance: float,
    margin: float,
    depth_diameter: float | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Render the model from ``pose`` ``(4, 4)`` at ``size`` pixels square and crop it as a target.

    A model point ``(N, 3)`` is seen when it projects inside the image and its depth is within
    ``tolerance`` of the rendered depth; with fewer than 3 seen, none is and the crop is the
    whole image. With ``depth_diameter`` (the model's diameter, metres) the rendering's
    :func:`~poseflow.features.learned.depth_layers` are appended to the colour.

    Returns:
        The crop ``(1, C, size, size)`` (C = 3, or 5 with the depth layers) in ``[0, 1]``, its
        box ``(1, 4)``, the points' pixels ``(N, 2)`` and which are seen ``(N,)``.
    """
    out = renderer.render(pose[None], K, size, size)
    cam = points @ pose[:3, :3].T + pose[:3, 3]
    uv = project_points(cam[None], K)[0]
    pix = uv.round().long()
    inside = (pix >= 0).all(dim=1) & (pix[:, 0] < size) & (pix[:, 1] < size)
    pix = pix.clamp(0, size - 1)
    depth = out.depth.double()[pix[:, 1], pix[:, 0]]
    seen = inside & (depth > 0) & ((cam[:, 2] - depth).abs() <= tolerance)
    if int(seen.sum()) < 3:
        seen = torch.zeros_like(seen)
        box = torch.tensor([[-0.5, -0.5, size - 0.5, size - 0.5]], dtype=torch.float64)
    else:
        box = crop_box_around(cam[None], K, seen[None], margin=margin)
    rgb = out.rgb.permute(2, 0, 1)[None].float() / 255.0
    if depth_diameter is not None:
        d = out.depth[None].float()
        layers = depth_layers(d, d > 0, torch.tensor([depth_diameter]))
        rgb = torch.cat([rgb, layers], dim=1)
    return crop_resize(rgb, box.float(), size), box, uv, seen
