"""The parts the verifier is made of: prepared objects, candidates, ICP, crops and scores.

:class:`PoseScorer` holds the verifier's prepared objects and does each step of a verification on
its own: :meth:`~PoseScorer.expand` an estimate with its near-symmetric candidates,
:meth:`~PoseScorer.refine` hypotheses by ICP, :meth:`~PoseScorer.score` them by rendering and
comparing on the crop of :meth:`~PoseScorer.crop_boxes`, :meth:`~PoseScorer.polish` a pose on
that score. :class:`~poseflow.verify.PoseVerifier` runs them as one contest.

Shape letters: B instances of one image, H hypotheses per instance, N model points, M observed
points, Hi x Wi the image, S the crop side.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from poseflow._checks import check_mask, check_same, check_tensor
from poseflow.data.frame import ImageInstances
from poseflow.data.objects import ObjectModel
from poseflow.errors import ShapeError, ValueRangeError
from poseflow.geometry.pointcloud import backproject_depth, remove_statistical_outliers
from poseflow.geometry.se3 import axis_angle_to_rotation, inverse_transform
from poseflow.registration.icp import multi_scale_icp
from poseflow.verify.config import VerifierConfig
from poseflow.verify.objects import VerifierObject, cached_verifier_object, verifier_fingerprint
from poseflow.verify.render import (
    ObservedCrops,
    crop_intrinsics,
    crop_observation,
    render_points,
)
from poseflow.verify.results import Hypotheses
from poseflow.verify.score import VerifierScore, score_renderings, select_significant

__all__ = ["PoseScorer"]


class PoseScorer:
    """Expands, refines and scores pose hypotheses of prepared objects against one image.

    Built once; :meth:`prepare` caches what each object needs (surface points with normals and
    albedo, its near-symmetries). Every step takes the instances of one image (:meth:`score` as
    an :class:`~poseflow.data.ImageInstances`, the others their masks and object ids), and
    hypotheses ``(B, H, 4, 4)``, model to camera.

    Args:
        config: the hyper-parameters; default :class:`VerifierConfig()`.
        seed: seed of the surface sampling and of the observed cloud's thinning.

    Example:
        >>> import open3d as o3d
        >>> from poseflow.data import ImageInstances, ObjectModel
        >>> from poseflow.render import Renderer
        >>> box = o3d.geometry.TriangleMesh.create_box(0.1, 0.06, 0.03)
        >>> model = ObjectModel.from_mesh(box.translate((-0.05, -0.03, -0.015)), num_points=64)
        >>> scorer = PoseScorer(VerifierConfig(num_points=1024, crop_size=32))
        >>> K = torch.tensor([[300.0, 0, 80], [0, 300.0, 60], [0, 0, 1]])
        >>> pose = torch.eye(4); pose[2, 3] = 0.4
        >>> out = Renderer([model.mesh]).render(pose[None], K, 160, 120)
        >>> wrong = pose.clone(); wrong[0, 3] = 0.02  # 2 cm off
        >>> _ = scorer.prepare(1, model)
        >>> image = ImageInstances(None, out.depth, K, out.masks_full, [1])
        >>> score = scorer.score(image, torch.stack((pose, wrong))[None])
        >>> score.total[0, 0] > score.total[0, 1]
        tensor(True)
        >>> off = pose.clone(); off[0, 3] = 0.01  # 1 cm off
        >>> polished, total = scorer.polish(image, off[None])
        >>> bool((polished[0, :3, 3] - pose[:3, 3]).norm() < 0.002)
        True
    """

    def __init__(self, config: VerifierConfig | None = None, *, seed: int = 0) -> None:
        self.config = VerifierConfig() if config is None else config
        if not isinstance(self.config, VerifierConfig):
            raise ValueRangeError(f"config must be a VerifierConfig, got {type(config).__name__}")
        self.seed = int(seed)
        self.objects: dict[int, VerifierObject] = {}

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.config!r}, objects={sorted(self.objects)})"

    # --------------------------------------------------------------------------------------
    # Per object

    def fingerprint(self) -> dict[str, Any]:
        """What a prepared object depends on besides the mesh (:func:`verifier_fingerprint`).

        Example:
            >>> PoseScorer().fingerprint()["num_points"]
            4096
        """
        return verifier_fingerprint(self.config, seed=self.seed)

    def prepare(
        self, obj_id: int, model: ObjectModel, *, cache_dir: str | Path | None = None
    ) -> VerifierObject:
        """Sample the object's surface and find its near-symmetries (once per object id).

        Args:
            obj_id: the id the object is known by in later calls.
            model: its :class:`~poseflow.data.objects.ObjectModel` (metres); its declared
                symmetries are not returned as candidates.
            cache_dir: an on-disk cache of prepared objects, whose entries are keyed by the
                mesh's content and scale and by :meth:`fingerprint`
                (:func:`~poseflow.verify.cached_verifier_object`); None prepares without one.

        Returns:
            The :class:`~poseflow.verify.VerifierObject` held under ``obj_id``: the one already
            held (drop it from :attr:`objects` to prepare another mesh under that id), else the
            cached or newly prepared one.

        Raises:
            DegenerateInputError: the mesh has no surface.
        """
        obj_id = int(obj_id)
        if obj_id not in self.objects:
            self.objects[obj_id] = cached_verifier_object(
                model, self.config, seed=self.seed, obj_id=obj_id, cache_dir=cache_dir
            )
        return self.objects[obj_id]

    def _objects(self, obj_ids: Sequence[int] | torch.Tensor, B: int) -> list[VerifierObject]:
        ids = [int(o) for o in torch.as_tensor(obj_ids).reshape(-1).tolist()]
        if len(ids) != B:
            raise ShapeError(f"got {B} instances but {len(ids)} object ids")
        missing = sorted({o for o in ids if o not in self.objects})
        if missing:
            raise ValueRangeError(f"objects {missing} are not prepared: call prepare() first")
        return [self.objects[o] for o in ids]

    # --------------------------------------------------------------------------------------
    # Per image

    def expand(self, poses: torch.Tensor, obj_ids: Sequence[int] | torch.Tensor) -> Hypotheses:
        """Add each estimate's near-symmetric candidates: ``pose @ S`` for every candidate ``S``.

        Args:
            poses: estimates ``(B, 4, 4)``, model to camera.
            obj_ids: object id of each instance ``(B,)``.

        Returns:
            :class:`Hypotheses` ``(B, H, 4, 4)`` with ``H = 1 +`` the largest candidate count,
            the estimate first.

        Raises:
            ShapeError: wrong shapes.
            ValueRangeError: an object that was not prepared.

        Example:
            >>> v = PoseScorer()
            >>> v.objects[3] = VerifierObject(*[torch.zeros(1, 3)] * 4,
            ...                               torch.zeros(3), 0.1,
            ...                               torch.eye(4)[None].repeat(2, 1, 1), torch.ones(2))
            >>> v.expand(torch.eye(4)[None], [3]).poses.shape
            torch.Size([1, 3, 4, 4])
        """
        sizes = check_tensor(poses, "poses", ("B", 4, 4), finite=True)
        objects = self._objects(obj_ids, sizes["B"])
        B = sizes["B"]
        H = 1 + max((len(o.candidates) for o in objects), default=0)
        out = poses[:, None].repeat(1, H, 1, 1)
        mask = torch.zeros(B, H, dtype=torch.bool, device=poses.device)
        mask[:, 0] = True
        for b, o in enumerate(objects):
            c = len(o.candidates)
            if c:
                S = o.candidates.to(dtype=poses.dtype, device=poses.device)
                out[b, 1 : 1 + c] = poses[b] @ S
                mask[b, 1 : 1 + c] = True
        return Hypotheses(out, mask)

    def refine(
        self,
        hypotheses: torch.Tensor,
        obj_ids: Sequence[int] | torch.Tensor,
        observed: torch.Tensor,
        observed_mask: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Refine hypotheses by multi-scale ICP of the observed cloud onto the model.

        Args:
            hypotheses: ``(B, H, 4, 4)`` model-to-camera poses.
            obj_ids: ``(B,)`` object ids.
            observed: the observed clouds, camera frame, ``(B, M, 3)``.
            observed_mask: ``(B, M)`` bool, True for real points.

        Returns:
            Refined poses ``(B, H, 4, 4)``; a hypothesis ICP could not refine (too few pairs) is
            returned unchanged.

        Raises:
            ShapeError: wrong shapes, devices or dtypes.
            ValueRangeError: an object that was not prepared.
        """
        sizes = check_tensor(hypotheses, "hypotheses", ("B", "H", 4, 4), finite=True)
        check_tensor(observed, "observed", ("B", "M", 3), sizes=sizes)
        check_same(("hypotheses", hypotheses), ("observed", observed))
        if observed_mask is not None:
            check_mask(observed_mask, "observed_mask", ("B", "M"), sizes)
        B, H = sizes["B"], sizes["H"]
        objects = self._objects(obj_ids, B)
        points, _, _, diam = _stack(objects, hypotheses)
        src, src_mask = self._thin(observed, observed_mask)
        # One ICP call for every instance and hypothesis: each instance is measured in units of
        # its object's diameter (ICP commutes with scaling), so the correspondence distances,
        # fractions of the diameter, are the same numbers for all.
        scale = diam[:, None, None]
        n = src.shape[1]
        init = inverse_transform(hypotheses).clone()  # camera -> model, (B, H, 4, 4)
        init[..., :3, 3] = init[..., :3, 3] / scale
        result = multi_scale_icp(
            (src / scale)[:, None].expand(B, H, n, 3).reshape(B * H, n, 3),
            (points / scale)[:, None].expand(B, H, -1, 3).reshape(B * H, -1, 3),
            init.reshape(B * H, 4, 4),
            max_correspondence_distances=list(self.config.icp_distances),
            max_iterations=self.config.icp_iterations,
            relative_rmse=self.config.icp_relative_rmse,
            source_mask=src_mask[:, None].expand(B, H, n).reshape(B * H, n),
        )
        T = result.transformation.reshape(B, H, 4, 4).clone()
        T[..., :3, 3] = T[..., :3, 3] * scale
        ok = result.valid.reshape(B, H)[..., None, None]
        return torch.where(ok, inverse_transform(T), hypotheses)

    def polish(
        self, image: ImageInstances, poses: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Refine poses by a pattern search of their total score on the full grid.

        ICP fits the observed depth and leaves what the depth alone does not fix: a thin part
        a few pixels off its mask, a printed box slid along its axis, a handle turned by a few
        degrees. Each pose moves to the best of its 12 steps (turns of ``polish_rotation``
        degrees either way about the camera's axes through the model's origin, shifts of
        ``polish_translation`` of the diameter either way along them) while that raises its
        total score, at most ``polish_moves`` times; then the steps are halved, for
        ``polish_levels`` sizes. Every step of every instance is scored in one rendering, on
        the crop of the pose polished. The polished pose is kept only where it beats the pose
        by the verifier's significance test (:func:`~poseflow.verify.select_significant`), as a
        candidate must: on a plateau of the score (a pose already right to the pixel) the
        search would otherwise drift with the rendering's noise.

        Args:
            image: the colour image ``(3, Hi, Wi)`` (or None), depth in metres ``(Hi, Wi)``,
                intrinsics ``(3, 3)``, and the ``B`` instances' masks ``(B, Hi, Wi)`` bool and
                object ids ``(B,)``, all prepared.
            poses: model-to-camera poses ``(B, 4, 4)``.

        Returns:
            ``(poses, total)``: the polished poses ``(B, 4, 4)`` (the given ones where the
            polish was not significant) and their total scores ``(B,)`` on that crop (``-inf``
            where a pose cannot be scored; it is returned unchanged).

        Raises:
            ShapeError: wrong shapes, devices or dtypes.
            ValueRangeError: an object that was not prepared.

        Example: see :class:`PoseScorer`'s, which polishes a pose 1 cm off.
        """
        sizes = check_tensor(poses, "poses", ("B", 4, 4), finite=True)
        rgb, depth, K, masks, obj_ids = image
        check_mask(masks, "masks", ("B", None, None), sizes)
        B = sizes["B"]
        cfg = self.config
        if B == 0:
            return poses.clone(), poses.new_zeros(0)
        objects = self._objects(obj_ids, B)
        Kd = K.to(poses.dtype)
        boxes = self.crop_boxes(poses, obj_ids, Kd, masks)
        crops = crop_observation(depth, masks, boxes, cfg.crop_size, rgb)
        kw = {"dtype": poses.dtype, "device": poses.device}
        diameter = torch.tensor([o.diameter for o in objects], **kw)
        eye = torch.eye(3, **kw)
        directions = torch.cat((eye, -eye))  # (6, 3)
        current = poses.clone()
        angle, shift = math.radians(cfg.polish_rotation), cfg.polish_translation
        for _ in range(cfg.polish_levels):
            moving = torch.ones(B, dtype=torch.bool, device=poses.device)
            for _ in range(cfg.polish_moves):
                turned = current[:, None].repeat(1, 13, 1, 1)  # the pose, then its 12 steps
                turned[:, 1:7, :3, :3] = (
                    axis_angle_to_rotation(angle * directions) @ current[:, None, :3, :3]
                )
                turned[:, 7:, :3, 3] += shift * diameter[:, None, None] * directions
                score = self._compare(
                    objects, turned, moving[:, None].expand(B, 13), crops, Kd, boxes
                )
                total = torch.where(score.valid, score.total, -torch.inf)
                step = total[:, 1:].argmax(1) + 1
                gain = total.gather(1, step[:, None])[:, 0]
                moving &= gain > total[:, 0]
                rows = moving.nonzero()[:, 0]
                current[rows] = turned[rows, step[rows]]
                if not len(rows):
                    break
            angle, shift = angle / 2, shift / 2
        # kept only where it explains the image significantly better, as a candidate must
        both = torch.stack((poses, current), dim=1)
        score = self._compare(objects, both, None, crops, Kd, boxes)
        index, _ = select_significant(score, significance=cfg.significance)
        total = torch.where(score.valid, score.total, -torch.inf)
        kept = index == 1
        return torch.where(kept[:, None, None], current, poses), total[:, 1].where(
            kept, total[:, 0]
        )

    def _thin(
        self, observed: torch.Tensor, mask: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """At most ``max_observed_points`` valid points per cloud, an even random subset."""
        B, M, _ = observed.shape
        if mask is None:
            mask = torch.ones(B, M, dtype=torch.bool, device=observed.device)
        cap = self.config.max_observed_points
        if B == 0 or int(mask.sum(-1).max()) <= cap:
            return observed, mask
        g = torch.Generator().manual_seed(self.seed)
        r = torch.rand(B, M, generator=g).to(observed.device)
        r = torch.where(mask, r, torch.full_like(r, 2.0))
        pick = r.argsort(-1)[:, :cap].sort(-1).values
        return observed.gather(1, pick[..., None].expand(-1, -1, 3)), mask.gather(1, pick)

    def score(
        self,
        image: ImageInstances,
        hypotheses: torch.Tensor,
        hypothesis_mask: torch.Tensor | None = None,
        *,
        crop_size: int | None = None,
        boxes: torch.Tensor | None = None,
    ) -> VerifierScore:
        """Render every hypothesis and compare it with the observation.

        Args:
            image: the colour image ``(3, Hi, Wi)`` (float in ``[0, 1]`` or uint8, or None to
                score depth and silhouette only), depth in metres ``(Hi, Wi)`` (0 or NaN where
                missing), intrinsics ``(3, 3)`` tensor, and the ``B`` instances' masks
                ``(B, Hi, Wi)`` bool and object ids ``(B,)``.
            hypotheses: model-to-camera poses ``(B, H, 4, 4)``.
            hypothesis_mask: ``(B, H)`` bool, False for padding.
            crop_size: side of the compared grid; default ``config.crop_size``. A coarser grid
                draws a proportional prefix of the surface points (the points are in
                farthest-point order, so every prefix is spread evenly), keeping the points per
                pixel, and costs proportionally less.
            boxes: the crops ``(B, 4)`` (see :meth:`crop_boxes`); by default those of
                hypothesis 0, so that all hypotheses of an instance share one crop.

        Returns:
            A :class:`~poseflow.verify.VerifierScore` in the hypotheses' dtype; without
            instances (``B = 0``) one of empty fields ``(0, H)`` and ``(0, H, G)``.

        Raises:
            ShapeError: wrong shapes, devices or dtypes, or no hypothesis for some instance
                (``H = 0`` with ``B > 0``: hypothesis 0 places each instance's crop).
            ValueRangeError: an object that was not prepared, NaN in the hypotheses.
        """
        rgb, depth, K, masks, obj_ids = image
        sizes = check_tensor(hypotheses, "hypotheses", ("B", "H", 4, 4), finite=True)
        d_sizes = check_tensor(depth, "depth", ("Hi", "Wi"))
        check_mask(masks, "masks", ("B", "Hi", "Wi"), {**d_sizes, "B": sizes["B"]})
        check_tensor(K, "K", (3, 3), finite=True)
        check_same(("hypotheses", hypotheses), ("depth", depth), ("K", K), dtype=False)
        check_same(("hypotheses", hypotheses), ("masks", masks), dtype=False)
        cfg = self.config
        objects = self._objects(obj_ids, sizes["B"])
        S = cfg.crop_size if crop_size is None else int(crop_size)
        if not 0 < S <= cfg.crop_size or S % cfg.block_size:
            raise ValueRangeError(
                f"crop_size must be a multiple of block_size ({cfg.block_size}) up to "
                f"{cfg.crop_size}, got {crop_size}"
            )
        if sizes["B"] == 0:
            return VerifierScore.zeros(0, sizes["H"], (S // cfg.block_size) ** 2, like=hypotheses)
        if sizes["H"] == 0:
            raise ShapeError(
                f"hypotheses has shape {tuple(hypotheses.shape)}: score needs at least one "
                "hypothesis per instance (H >= 1; the first places the instance's crop)"
            )
        Kd = K.to(hypotheses.dtype)
        if boxes is None:
            boxes = self.crop_boxes(hypotheses[:, 0], obj_ids, Kd, masks)
        crops = crop_observation(depth, masks, boxes, S, rgb)
        return self._compare(objects, hypotheses, hypothesis_mask, crops, Kd, boxes)

    def _compare(
        self,
        objects: list[VerifierObject],
        hypotheses: torch.Tensor,
        hypothesis_mask: torch.Tensor | None,
        observed: ObservedCrops,
        K: torch.Tensor,
        boxes: torch.Tensor,
    ) -> VerifierScore:
        """Render the hypotheses ``(B, H, 4, 4)`` onto the crops ``boxes`` and score them.

        Hypotheses masked out (padding, duplicates) are neither rendered nor scored: they get
        :meth:`VerifierScore.zeros`' entries, as scoring them masked would give.
        """
        cfg = self.config
        S = observed.depth.shape[-1]
        points, normals, albedo, diam = _stack(objects, hypotheses)
        n = min(points.shape[1], math.ceil(points.shape[1] * (S / cfg.crop_size) ** 2))
        Kc = crop_intrinsics(K, boxes, S)
        pixel = (boxes[:, 2] - boxes[:, 0]) / S / K[:2, :2].diagonal().min()  # m per m depth
        z0 = hypotheses[:, 0, 2, 3].abs().clamp_min(1e-3)
        per_instance = _Instances(
            points[:, :n], normals[:, :n], albedo[:, :n], Kc, 2 * pixel * z0, diam, observed
        )
        if hypothesis_mask is None or bool(hypothesis_mask.all()):
            return self._render_and_score(per_instance, hypotheses, hypothesis_mask)
        B, H = hypothesis_mask.shape
        out = VerifierScore.zeros(B, H, (S // cfg.block_size) ** 2, like=hypotheses)
        b, h = hypothesis_mask.nonzero(as_tuple=True)
        if len(b):
            part = self._render_and_score(per_instance.take(b), hypotheses[b, h][:, None], None)
            for name in VerifierScore.__dataclass_fields__:
                getattr(out, name)[b, h] = getattr(part, name)[:, 0]
        return out

    def _render_and_score(
        self, inst: _Instances, hypotheses: torch.Tensor, hypothesis_mask: torch.Tensor | None
    ) -> VerifierScore:
        """:func:`render_points` and :func:`score_renderings` of ``(B, H, 4, 4)`` hypotheses."""
        cfg = self.config
        rendering = render_points(
            inst.points,
            inst.normals,
            inst.albedo,
            hypotheses,
            inst.K,
            inst.observed.depth.shape[-1],
            surface_tolerance=inst.surface_tolerance,
            occlusion_tolerance=cfg.occlusion_tolerance * inst.diameter,
        )
        return score_renderings(
            rendering,
            inst.observed,
            depth_tolerance=cfg.depth_tolerance * inst.diameter,
            visibility_tolerance=cfg.visibility_tolerance * inst.diameter,
            appearance_window=cfg.appearance_window,
            contrast_reference=cfg.contrast_reference,
            weights=(cfg.depth_weight, cfg.silhouette_weight, cfg.appearance_weight),
            block_size=cfg.block_size,
            hypothesis_mask=hypothesis_mask,
        )

    def crop_boxes(
        self,
        poses: torch.Tensor,
        obj_ids: Sequence[int] | torch.Tensor,
        K: torch.Tensor,
        masks: torch.Tensor,
    ) -> torch.Tensor:
        """The square crop each instance is compared on, ``(B, 4)``.

        Centred on the projection of the object's centre at ``poses``, with a side of
        ``crop_margin`` times the projected diameter, so that every crop pixel covers the same
        fraction of the object whatever its distance. An estimate with its centre behind the
        camera gets the bounding square of its mask (of the image if the mask is empty).

        Args:
            poses: ``(B, 4, 4)`` model-to-camera poses.
            obj_ids: ``(B,)`` object ids.
            K: intrinsics ``(3, 3)``.
            masks: ``(B, Hi, Wi)`` bool.

        Returns:
            Boxes ``(x0, y0, x1, y1)`` ``(B, 4)`` in the poses' dtype.
        """
        B = poses.shape[0]
        objects = self._objects(obj_ids, B)
        kw = {"dtype": poses.dtype, "device": poses.device}
        centroid = torch.stack([o.centroid for o in objects]).to(**kw)
        diam = torch.tensor([o.diameter for o in objects], **kw)
        K = K.to(**kw)
        c = (poses[:, :3, :3] @ centroid[..., None])[..., 0] + poses[:, :3, 3]
        z = c[:, 2]
        ahead = z > 0.1 * diam
        zs = torch.where(ahead, z, torch.ones_like(z))
        uv = (c @ K.T)[:, :2] / zs[:, None]
        half = 0.5 * self.config.crop_margin * K[:2, :2].diagonal().max() * diam / zs
        boxes = torch.cat((uv - half[:, None], uv + half[:, None]), -1)
        if bool(ahead.all()):
            return boxes
        Hi, Wi = masks.shape[-2:]
        fallback = torch.tensor([-0.5, -0.5, Wi - 0.5, Hi - 0.5], **kw).repeat(B, 1)
        for b in (~ahead).nonzero()[:, 0].tolist():
            vv, uu = masks[b].nonzero(as_tuple=True)
            if vv.numel():
                lo = torch.stack((uu.min(), vv.min())).to(**kw) - 0.5
                hi = torch.stack((uu.max(), vv.max())).to(**kw) + 0.5
                centre, side = (lo + hi) / 2, (hi - lo).max()
                fallback[b] = torch.cat((centre - side / 2, centre + side / 2))
        return torch.where(ahead[:, None], boxes, fallback)

    def observed_cloud(
        self, depth: torch.Tensor, K: torch.Tensor, masks: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Lift each instance's masked depth to a camera-frame cloud for :meth:`refine`.

        For callers that have not lifted the depth themselves: statistical outliers (flying
        pixels at depth edges) are dropped and at most ``max_observed_points`` points kept.

        Args:
            depth: ``(Hi, Wi)`` metres.
            K: ``(3, 3)`` floating intrinsics.
            masks: ``(B, Hi, Wi)`` bool.

        Returns:
            ``(points (B, M, 3), mask (B, M))`` in ``K``'s dtype.
        """
        B = masks.shape[0]
        d = torch.nan_to_num(depth, nan=0.0, posinf=0.0, neginf=0.0)
        cloud = backproject_depth(d.expand(B, *d.shape), K, masks)
        if cloud.points.shape[1] == 0:
            return cloud.points, cloud.mask
        ok = cloud.mask & remove_statistical_outliers(cloud.points, cloud.mask)
        return self._thin(cloud.points, ok)


@dataclass(frozen=True)
class _Instances:
    """What scoring needs of each of ``B`` instances on its crop.

    Attributes:
        points, normals, albedo: the model's surface samples ``(B, n, 3)``.
        K: the crops' intrinsics ``(B, 3, 3)``.
        surface_tolerance: ``(B,)`` metres, from the crop's pixel size at the first hypothesis.
        diameter: ``(B,)`` metres.
        observed: the observed crops ``(B, ...)``.
    """

    points: torch.Tensor
    normals: torch.Tensor
    albedo: torch.Tensor
    K: torch.Tensor
    surface_tolerance: torch.Tensor
    diameter: torch.Tensor
    observed: ObservedCrops

    def take(self, rows: torch.Tensor) -> _Instances:
        """The instances ``rows`` ``(P,)`` (repeats allowed)."""
        o = self.observed
        color = None if o.color is None else o.color[rows]
        return _Instances(
            *(getattr(self, f)[rows] for f in ("points", "normals", "albedo", "K")),
            self.surface_tolerance[rows],
            self.diameter[rows],
            ObservedCrops(o.depth[rows], o.mask[rows], color),
        )


def _stack(
    objects: list[VerifierObject], like: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Points, normals, albedo ``(B, N, 3)`` and diameters ``(B,)`` like ``like``."""
    kw = {"dtype": like.dtype, "device": like.device}
    return (
        torch.stack([o.points for o in objects]).to(**kw),
        torch.stack([o.normals for o in objects]).to(**kw),
        torch.stack([o.albedo for o in objects]).to(**kw),
        torch.tensor([o.diameter for o in objects], **kw),
    )
