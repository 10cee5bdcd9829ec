"""The pose verifier: candidates, ICP refinement, render-and-compare scores and the choice.

Shape letters: B instances of one image, H hypotheses per instance, N model points, M observed
points, Hi x Wi the image.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import torch

from poseflow._checks import check_mask, check_same, check_tensor
from poseflow.data.objects import ObjectModel
from poseflow.errors import ShapeError, ValueRangeError
from poseflow.geometry.pointcloud import backproject_depth, remove_statistical_outliers
from poseflow.geometry.se3 import inverse_transform
from poseflow.registration.icp import multi_scale_icp
from poseflow.verify.config import VerifierConfig
from poseflow.verify.objects import VerifierObject, cached_verifier_object, verifier_fingerprint
from poseflow.verify.render import crop_intrinsics, crop_observation, render_points
from poseflow.verify.score import VerifierScore, score_renderings, select_hypotheses
from poseflow.verify.symmetry import box_turns

__all__ = ["Hypotheses", "PoseVerifier", "Verification"]


@dataclass
class Hypotheses:
    """Pose hypotheses of ``B`` instances, padded to ``H`` each.

    Attributes:
        poses: model-to-camera transforms ``(B, H, 4, 4)``; hypothesis 0 is the estimate.
        mask: ``(B, H)`` bool, False for padding (a copy of the estimate).
    """

    poses: torch.Tensor
    mask: torch.Tensor


@dataclass
class Verification:
    """The outcome of :meth:`PoseVerifier.verify` for ``B`` instances.

    Attributes:
        poses: the chosen poses ``(B, 4, 4)``: the estimate where it was kept (ICP-refined with
            ``refine_estimate``, else unchanged), else the ICP-refined candidate or searched turn
            that beat it.
        scores: the chosen hypothesis's total score clipped to ``[0, 1]`` ``(B,)`` (0 where
            invalid), for ranking estimates.
        valid: ``(B,)`` bool, whether the chosen hypothesis could be scored.
        chosen: ``(B,)`` int64, the index of the chosen hypothesis in ``hypotheses`` (0: the
            estimate was kept).
        hypotheses: the finally scored hypotheses ``(B, H, 4, 4)``: the estimate (refined with
            ``refine_estimate``), then the refined candidates, then, with ``search_below`` on,
            the ``search_top_k`` refined turns of :meth:`PoseVerifier.search` (invalid where the
            instance was not searched).
        score: their scores.
        statistic: each candidate's test statistic against the estimate ``(B, H)`` (a searched
            turn's against the pose it was turned from).
    """

    poses: torch.Tensor
    scores: torch.Tensor
    valid: torch.Tensor
    chosen: torch.Tensor
    hypotheses: torch.Tensor
    score: VerifierScore
    statistic: torch.Tensor


class PoseVerifier:
    """Render-and-compare verification of 6D pose hypotheses with near-symmetry candidates.

    Built once; :meth:`prepare` caches what each object needs (surface points with normals and
    albedo, its near-symmetries). For the instances of one image, :meth:`verify` runs the whole
    stage: :meth:`expand` each estimate with its near-symmetric candidates, :meth:`score` them
    all on a coarse grid, :meth:`refine` the best ``refine_top_k`` candidates (and, with
    ``refine_estimate``, the estimate) by ICP of the observed cloud onto the model, score the
    estimate and those again and keep the estimate unless a candidate beats it by more than the
    score's own spread (:func:`~poseflow.verify.select_hypotheses`); a chosen pose that still
    scores below ``search_below`` is then searched over all orientations (:meth:`search`).
    Each step is public, so the verifier also scores hypotheses from anywhere.

    Args:
        config: the hyper-parameters; default :class:`VerifierConfig()`.
        seed: seed of the surface sampling and of the observed cloud's thinning.

    Example:
        >>> import open3d as o3d
        >>> from poseflow.data.objects import ObjectModel
        >>> from poseflow.render import Renderer
        >>> box = o3d.geometry.TriangleMesh.create_box(0.1, 0.06, 0.03)
        >>> model = ObjectModel.from_mesh(box.translate((-0.05, -0.03, -0.015)), num_points=64)
        >>> cfg = VerifierConfig(num_points=1024, crop_size=32, min_self_overlap=0.9)
        >>> verifier = PoseVerifier(cfg)
        >>> verifier.prepare(1, model).candidates.shape  # the box's three half-turns
        torch.Size([3, 4, 4])
        >>> K = torch.tensor([[300.0, 0, 80], [0, 300.0, 60], [0, 0, 1]])
        >>> pose = torch.eye(4); pose[2, 3] = 0.4
        >>> out = Renderer([model.mesh]).render(pose[None], K, 160, 120)
        >>> wrong = pose.clone(); wrong[0, 3] = 0.02  # 2 cm off
        >>> score = verifier.score(None, out.depth, K, out.masks_full, [1],
        ...                        torch.stack((pose, wrong))[None])
        >>> score.total[0, 0] > score.total[0, 1]
        tensor(True)
    """

    def __init__(self, config: VerifierConfig | None = None, *, seed: int = 0) -> None:
        self.config = VerifierConfig() if config is None else config
        if not isinstance(self.config, VerifierConfig):
            raise ValueRangeError(f"config must be a VerifierConfig, got {type(config).__name__}")
        self.seed = int(seed)
        self.objects: dict[int, VerifierObject] = {}

    def __repr__(self) -> str:
        return f"PoseVerifier({self.config!r}, objects={sorted(self.objects)})"

    # --------------------------------------------------------------------------------------
    # Per object

    def fingerprint(self) -> dict[str, Any]:
        """What a prepared object depends on besides the mesh (:func:`verifier_fingerprint`).

        Example:
            >>> PoseVerifier().fingerprint()["num_points"]
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

    def _stack(
        self, objects: list[VerifierObject], like: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Points, normals, albedo ``(B, N, 3)`` and diameters ``(B,)`` like ``like``."""
        kw = {"dtype": like.dtype, "device": like.device}
        return (
            torch.stack([o.points for o in objects]).to(**kw),
            torch.stack([o.normals for o in objects]).to(**kw),
            torch.stack([o.albedo for o in objects]).to(**kw),
            torch.tensor([o.diameter for o in objects], **kw),
        )

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
            >>> v = PoseVerifier()
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
        points, _, _, diam = self._stack(objects, hypotheses)
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
        rgb: torch.Tensor | None,
        depth: torch.Tensor,
        K: torch.Tensor,
        masks: torch.Tensor,
        obj_ids: Sequence[int] | torch.Tensor,
        hypotheses: torch.Tensor,
        hypothesis_mask: torch.Tensor | None = None,
        *,
        boxes: torch.Tensor | None = None,
        crop_size: int | None = None,
    ) -> VerifierScore:
        """Render every hypothesis and compare it with the observation.

        Args:
            rgb: colour image ``(3, Hi, Wi)`` (float in ``[0, 1]`` or uint8), or None to score
                depth and silhouette only.
            depth: depth in metres ``(Hi, Wi)``, 0 or NaN where missing.
            K: intrinsics ``(3, 3)``.
            masks: instance masks ``(B, Hi, Wi)`` bool.
            obj_ids: object id per instance ``(B,)``.
            hypotheses: model-to-camera poses ``(B, H, 4, 4)``.
            hypothesis_mask: ``(B, H)`` bool, False for padding.
            boxes: the crops ``(B, 4)`` (see :meth:`crop_boxes`); by default those of
                hypothesis 0, so that all hypotheses of an instance share one crop.
            crop_size: side of the compared grid; default ``config.crop_size``. A coarser grid
                draws a proportional prefix of the surface points (the points are in
                farthest-point order, so every prefix is spread evenly), keeping the points per
                pixel, and costs proportionally less.

        Returns:
            A :class:`~poseflow.verify.VerifierScore` in the hypotheses' dtype; without
            instances (``B = 0``) one of empty fields ``(0, H)`` and ``(0, H, G)``.

        Raises:
            ShapeError: wrong shapes, devices or dtypes, or no hypothesis for some instance
                (``H = 0`` with ``B > 0``: hypothesis 0 places each instance's crop).
            ValueRangeError: an object that was not prepared, NaN in the hypotheses.
        """
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
            return _empty_score(hypotheses, (S // cfg.block_size) ** 2)
        if sizes["H"] == 0:
            raise ShapeError(
                f"hypotheses has shape {tuple(hypotheses.shape)}: score needs at least one "
                "hypothesis per instance (H >= 1; the first places the instance's crop)"
            )
        points, normals, albedo, diam = self._stack(objects, hypotheses)
        Kd = K.to(hypotheses.dtype)
        if boxes is None:
            boxes = self.crop_boxes(hypotheses[:, 0], obj_ids, Kd, masks)
        n = min(points.shape[1], math.ceil(points.shape[1] * (S / cfg.crop_size) ** 2))
        points, normals, albedo = points[:, :n], normals[:, :n], albedo[:, :n]
        Kc = crop_intrinsics(Kd, boxes, S)
        pixel = (boxes[:, 2] - boxes[:, 0]) / S / Kd[:2, :2].diagonal().min()  # m per m depth
        z0 = hypotheses[:, 0, 2, 3].abs().clamp_min(1e-3)
        rendering = render_points(
            points,
            normals,
            albedo,
            hypotheses,
            Kc,
            S,
            surface_tolerance=2 * pixel * z0,
            occlusion_tolerance=cfg.occlusion_tolerance * diam,
        )
        observed = crop_observation(depth, masks, boxes, S, rgb)
        return score_renderings(
            rendering,
            observed,
            depth_tolerance=cfg.depth_tolerance * diam,
            visibility_tolerance=cfg.visibility_tolerance * diam,
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

    def verify(
        self,
        rgb: torch.Tensor | None,
        depth: torch.Tensor,
        K: torch.Tensor,
        masks: torch.Tensor,
        obj_ids: Sequence[int] | torch.Tensor,
        poses: torch.Tensor,
        observed: torch.Tensor | None = None,
        observed_mask: torch.Tensor | None = None,
        *,
        extra: torch.Tensor | None = None,
        extra_mask: torch.Tensor | None = None,
        estimated: torch.Tensor | None = None,
    ) -> Verification:
        """Check each estimate against its near-symmetric candidates and keep the best.

        Args:
            rgb: colour image ``(3, Hi, Wi)`` or None (depth and silhouette only).
            depth: depth in metres ``(Hi, Wi)``.
            K: intrinsics ``(3, 3)``.
            masks: instance masks ``(B, Hi, Wi)`` bool.
            obj_ids: object ids ``(B,)``, all prepared.
            poses: the estimates ``(B, 4, 4)``.
            observed: the observed clouds ``(B, M, 3)`` (camera frame) that ICP registers;
                lifted from ``depth`` and ``masks`` when None.
            observed_mask: ``(B, M)`` bool for ``observed``.
            extra: more hypotheses of each instance ``(B, E, 4, 4)`` (e.g. the estimator's
                other solutions), candidates like the near-symmetric ones: scored, the best
                refined, and chosen only where they beat the estimate.
            extra_mask: ``(B, E)`` bool, False for padding of ``extra``.
            estimated: ``(B,)`` bool, False for instances the estimator found no pose for: they
                are not verified and come back unchanged, with score 0 and ``valid`` False.

        Returns:
            A :class:`Verification`; without instances (``B = 0``) an empty one, whose
            ``hypotheses`` are ``(0, 1, 4, 4)``.

        Raises:
            ShapeError: wrong shapes, devices or dtypes.
            ValueRangeError: an object that was not prepared.
        """
        sizes = check_tensor(poses, "poses", ("B", 4, 4), finite=True)
        check_mask(masks, "masks", ("B", None, None), sizes)
        if extra is not None:
            check_tensor(extra, "extra", ("B", "E", 4, 4), sizes=sizes, finite=True)
            check_same(("poses", poses), ("extra", extra))
            if extra_mask is not None:
                check_mask(extra_mask, "extra_mask", ("B", "E"), sizes)
        if sizes["B"] == 0:
            self._objects(obj_ids, 0)
            return self._unscored(poses[:, None])
        if estimated is not None:
            check_mask(estimated, "estimated", ("B",), sizes)
            if not bool(estimated.all()):
                return self._verify_subset(
                    estimated, rgb, depth, K, masks, obj_ids, poses, observed, observed_mask,
                    extra, extra_mask,
                )  # fmt: skip
        Kd = K.to(poses.dtype)
        hyp = self.expand(poses, obj_ids)
        if extra is not None and extra.shape[1]:
            more = extra_mask if extra_mask is not None else torch.ones_like(extra[..., 0, 0])
            hyp = Hypotheses(
                torch.cat((hyp.poses, extra), dim=1), torch.cat((hyp.mask, more.bool()), dim=1)
            )
        boxes = self.crop_boxes(poses, obj_ids, Kd, masks)
        first = self.score(
            rgb, depth, Kd, masks, obj_ids, hyp.poses, hyp.mask, boxes=boxes,
            crop_size=self.config.coarse_crop_size,
        )  # fmt: skip
        k = min(self.config.refine_top_k, hyp.poses.shape[1] - 1)
        if observed is None and (k or self.config.refine_estimate):
            observed, observed_mask = self.observed_cloud(depth, Kd, masks)
        poses_k, mask_k = self._refine_best(
            hyp.poses, hyp.mask, first, k, obj_ids, observed, observed_mask,
            refine_first=self.config.refine_estimate,
        )  # fmt: skip
        final = self.score(rgb, depth, Kd, masks, obj_ids, poses_k, mask_k, boxes=boxes)
        out = _chosen(poses_k, final, self.config.significance)
        if self.config.search_below > 0:
            out = self._search_low(out, rgb, depth, Kd, masks, obj_ids, observed, observed_mask)
        return out

    def search(
        self,
        rgb: torch.Tensor | None,
        depth: torch.Tensor,
        K: torch.Tensor,
        masks: torch.Tensor,
        obj_ids: Sequence[int] | torch.Tensor,
        poses: torch.Tensor,
        observed: torch.Tensor | None = None,
        observed_mask: torch.Tensor | None = None,
    ) -> Verification:
        """Search every orientation for poses that explain the image poorly.

        Each pose is turned by the :func:`~poseflow.verify.box_turns` of its object (the
        flips and quarter turns about its own and its principal axes, and the turns about the
        boxes' diagonals), the turns are scored on the coarse grid, the best ``search_top_k``
        refined by ICP, scored on the full grid and tested against the pose as :meth:`verify`'s
        candidates are. A pose upside down, which no near-symmetry or hypothesis of the
        estimator reaches, is then found by ICP from the turn nearest to the truth.
        :meth:`verify` runs this on its chosen poses that score below ``search_below``.

        Args:
            rgb: colour image ``(3, Hi, Wi)`` or None (depth and silhouette only).
            depth: depth in metres ``(Hi, Wi)``.
            K: intrinsics ``(3, 3)``.
            masks: instance masks ``(B, Hi, Wi)`` bool.
            obj_ids: object ids ``(B,)``, all prepared.
            poses: the poses searched around ``(B, 4, 4)`` (already refined: they are
                compared as they are).
            observed: the observed clouds ``(B, M, 3)`` that ICP registers; lifted from
                ``depth`` and ``masks`` when None.
            observed_mask: ``(B, M)`` bool for ``observed``.

        Returns:
            A :class:`Verification` whose hypotheses are the pose, then ``search_top_k`` refined
            turns (invalid where the object has fewer turns). The crops are centred on
            ``poses``.
        """
        check_tensor(poses, "poses", ("B", 4, 4), finite=True)
        B, k = poses.shape[0], self.config.search_top_k
        if B == 0:
            return self._unscored(poses[:, None].expand(0, 1 + k, 4, 4))
        objects = self._objects(obj_ids, B)
        Kd = K.to(poses.dtype)
        turns_of = {id(o): box_turns(o.points).to(poses) for o in objects}
        count = torch.tensor([len(turns_of[id(o)]) for o in objects], device=poses.device)
        width = max(int(count.max()), k)
        eye = torch.eye(4, dtype=poses.dtype, device=poses.device)
        turns = torch.stack([  # (B, width, 4, 4), padded with the identity
            torch.cat((t, eye.expand(width - len(t), 4, 4)))
            for t in (turns_of[id(o)] for o in objects)
        ])  # fmt: skip
        padded = torch.arange(width, device=poses.device) >= count[:, None]
        hyp = torch.cat((poses[:, None], poses[:, None] @ turns), dim=1)
        hyp_mask = torch.cat((torch.ones_like(padded[:, :1]), ~padded), dim=1)
        boxes = self.crop_boxes(poses, obj_ids, Kd, masks)
        first = self.score(
            rgb, depth, Kd, masks, obj_ids, hyp, hyp_mask, boxes=boxes,
            crop_size=self.config.coarse_crop_size,
        )  # fmt: skip
        if observed is None:
            observed, observed_mask = self.observed_cloud(depth, Kd, masks)
        hyp, mask = self._refine_best(
            hyp, hyp_mask, first, k, obj_ids, observed, observed_mask, refine_first=False
        )
        final = self.score(rgb, depth, Kd, masks, obj_ids, hyp, mask, boxes=boxes)
        return _chosen(hyp, final, self.config.significance)

    def _refine_best(
        self,
        hypotheses: torch.Tensor,
        mask: torch.Tensor,
        first: VerifierScore,
        k: int,
        obj_ids: Sequence[int] | torch.Tensor,
        observed: torch.Tensor | None,
        observed_mask: torch.Tensor | None,
        *,
        refine_first: bool,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The incumbent and the ``k`` best other hypotheses by their ``first`` (coarse) score.

        Args:
            hypotheses: ``(B, H, 4, 4)``, the incumbent first.
            mask: ``(B, H)`` bool, False for padding.
            first: their coarse scores.
            k: other hypotheses kept, ``k < H``.
            obj_ids: ``(B,)``.
            observed: the clouds ICP registers ``(B, M, 3)``; None refines nothing.
            observed_mask: ``(B, M)`` bool.
            refine_first: refine the incumbent too.

        Returns:
            ``(poses (B, 1 + k, 4, 4), mask (B, 1 + k))``: the kept hypotheses, ICP-refined (the
            incumbent only with ``refine_first``), and whether each is real and was scored.
        """
        B = hypotheses.shape[0]
        keep = torch.zeros(B, 1 + k, dtype=torch.long, device=hypotheses.device)
        if k:
            cand = torch.where(first.valid[:, 1:], first.total[:, 1:], -torch.inf)
            keep[:, 1:] = cand.topk(k, dim=-1).indices + 1
        poses = hypotheses.gather(1, keep[..., None, None].expand(-1, -1, 4, 4))
        kept = mask.gather(1, keep)
        kept[:, 1:] &= first.valid.gather(1, keep[:, 1:])
        start = 0 if refine_first else 1
        if observed is not None and observed.shape[1] >= 3 and poses.shape[1] > start:
            refined = self.refine(
                poses[:, start:], obj_ids, observed.to(poses.dtype), observed_mask
            )
            poses = torch.cat((poses[:, :start], refined), dim=1)
        return poses, kept

    def _search_low(
        self,
        out: Verification,
        rgb: torch.Tensor | None,
        depth: torch.Tensor,
        K: torch.Tensor,
        masks: torch.Tensor,
        obj_ids: Sequence[int] | torch.Tensor,
        observed: torch.Tensor | None,
        observed_mask: torch.Tensor | None,
    ) -> Verification:
        """``out`` with its instances scoring below ``search_below`` searched (:meth:`search`).

        The searched turns follow the hypotheses as ``search_top_k`` more columns (invalid,
        the pose repeated, where an instance was not searched), so ``chosen`` still indexes
        ``hypotheses``; they are scored on a crop centred on the pose searched around, and
        their statistics are against it.
        """
        B, H = out.hypotheses.shape[:2]
        k = self.config.search_top_k
        low = out.valid & (out.scores < self.config.search_below)
        hypotheses = torch.cat((out.hypotheses, out.poses[:, None].expand(B, k, 4, 4)), dim=1)
        score = VerifierScore(*(
            torch.cat((t, t.new_zeros(B, k, *t.shape[2:])), dim=1)
            for t in (getattr(out.score, f.name) for f in fields(out.score))
        ))  # fmt: skip
        statistic = torch.cat((out.statistic, out.statistic.new_zeros(B, k)), dim=1)
        merged = Verification(
            out.poses.clone(), out.scores.clone(), out.valid.clone(), out.chosen.clone(),
            hypotheses, score, statistic,
        )  # fmt: skip
        idx = low.nonzero()[:, 0]
        if not len(idx):
            return merged
        ids = torch.as_tensor(obj_ids).reshape(-1)[idx.cpu()]
        take = lambda t: None if t is None else t[idx]  # noqa: E731
        found = self.search(
            rgb, depth, K, masks[idx], ids, out.poses[idx], take(observed), take(observed_mask)
        )
        moved = found.chosen > 0  # the others keep their pose and its score on the first crop
        rows = idx[moved]
        merged.poses[rows] = found.poses[moved]
        merged.scores[rows] = found.scores[moved]
        merged.valid[rows] = found.valid[moved]
        merged.chosen[rows] = H + found.chosen[moved] - 1
        merged.hypotheses[idx, H:] = found.hypotheses[:, 1:]
        for f in fields(score):
            getattr(merged.score, f.name)[idx, H:] = getattr(found.score, f.name)[:, 1:]
        merged.statistic[idx, H:] = found.statistic[:, 1:]
        return merged

    def _unscored(self, hypotheses: torch.Tensor) -> Verification:
        """The :class:`Verification` of ``(B, H, 4, 4)`` unscored hypotheses: the first kept."""
        B = hypotheses.shape[0]
        score = _empty_score(hypotheses, (self.config.crop_size // self.config.block_size) ** 2)
        return Verification(
            poses=hypotheses[:, 0].clone(),
            scores=hypotheses.new_zeros(B),
            valid=score.valid[:, 0].clone(),
            chosen=torch.zeros(B, dtype=torch.long, device=hypotheses.device),
            hypotheses=hypotheses.clone(),
            score=score,
            statistic=score.total,
        )

    def _verify_subset(
        self,
        estimated: torch.Tensor,
        rgb: torch.Tensor | None,
        depth: torch.Tensor,
        K: torch.Tensor,
        masks: torch.Tensor,
        obj_ids: Sequence[int] | torch.Tensor,
        poses: torch.Tensor,
        observed: torch.Tensor | None,
        observed_mask: torch.Tensor | None,
        extra: torch.Tensor | None,
        extra_mask: torch.Tensor | None,
    ) -> Verification:
        """:meth:`verify` of the ``estimated`` instances; the others come back unverified."""
        B = poses.shape[0]
        idx = estimated.nonzero()[:, 0]
        if not len(idx):  # one hypothesis each, the estimate, unscored
            return self._unscored(poses[:, None])
        ids = torch.as_tensor(obj_ids).reshape(-1)[idx.cpu()]
        take = lambda t: None if t is None else t[idx]  # noqa: E731
        sub = self.verify(
            rgb, depth, K, masks[idx], ids, poses[idx], take(observed), take(observed_mask),
            extra=take(extra), extra_mask=take(extra_mask),
        )  # fmt: skip

        def spread(t: torch.Tensor, fill: torch.Tensor | None = None) -> torch.Tensor:
            out = t.new_zeros(B, *t.shape[1:]) if fill is None else fill.clone()
            out[idx] = t
            return out

        H = sub.hypotheses.shape[1]
        return Verification(
            poses=spread(sub.poses, poses),
            scores=spread(sub.scores),
            valid=spread(sub.valid),
            chosen=spread(sub.chosen),
            hypotheses=spread(sub.hypotheses, poses[:, None].expand(B, H, 4, 4)),
            score=VerifierScore(*(spread(getattr(sub.score, f.name)) for f in fields(sub.score))),
            statistic=spread(sub.statistic),
        )


def _empty_score(hypotheses: torch.Tensor, g: int) -> VerifierScore:
    """The score of ``(B, H, 4, 4)`` unscored hypotheses on ``g`` blocks: zeros, all invalid."""
    B, H = hypotheses.shape[:2]
    zeros = hypotheses.new_zeros(B, H)
    flags = torch.zeros(B, H, dtype=torch.bool, device=hypotheses.device)
    evidence, support = hypotheses.new_zeros(B, H, g), flags[..., None].expand(B, H, g)
    return VerifierScore(zeros, zeros, zeros, zeros, flags, evidence, support)


def _chosen(hypotheses: torch.Tensor, score: VerifierScore, significance: float) -> Verification:
    """The :class:`Verification` of scored ``hypotheses`` ``(B, H, 4, 4)``, incumbent first."""
    index, stat = select_hypotheses(score, significance=significance)
    rows = torch.arange(hypotheses.shape[0], device=hypotheses.device)
    total, valid = score.total[rows, index], score.valid[rows, index]
    return Verification(
        poses=hypotheses[rows, index],
        scores=torch.where(valid, total.clamp(0, 1), 0.0),
        valid=valid,
        chosen=index,
        hypotheses=hypotheses,
        score=score,
        statistic=stat,
    )
