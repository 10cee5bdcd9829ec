"""The classic, training-free baseline: FPFH matching, RANSAC and ICP.

What a practitioner would try first to register a known object model to a segmented depth image,
built from poseflow's own parts, and the floor FunFlow6D has to clear:

1. lift the masked depth to the target cloud ``T`` (camera frame), drop statistical outliers and
   thin it on a voxel grid;
2. describe it with multi-scale FPFH (:class:`~poseflow.features.FPFHEncoder`, radii 0.30 and
   0.40 of the diameter as in the paper), normals estimated and turned toward the camera;
3. describe the model the same way, but from *partial views*: the mesh is rendered from
   ``num_views`` viewpoints once per object, each depth image lifted, thinned and described like
   ``T``, and the descriptors are kept with their points in the model frame. Descriptors of the
   complete model cloud would mix in surfaces the camera cannot see, and at FPFH's radii they
   then match an observed view no better than chance;
4. match by mutual nearest neighbours in feature space (each target point's nearest model
   descriptor is added when there are too few mutual pairs);
5. RANSAC-Procrustes (:func:`~poseflow.registration.ransac_procrustes`) on the pairs gives
   model-to-camera hypotheses; it runs ``restarts`` times on the same instance, batched;
6. coarse-to-fine ICP of ``T`` onto ``Q`` (:func:`~poseflow.registration.multi_scale_icp`, the
   paper's direction) refines every hypothesis, and the one that explains most of ``T`` wins;
   its ICP fitness is the estimate's score;
7. with a ``verifier`` (the default), the poses of the image are checked by rendering and
   comparing (:class:`~poseflow.verify.PoseVerifier`): each is expanded with its object's
   near-symmetric candidates, the best are refined by ICP of ``T``, and a candidate replaces the
   pose only where it explains the depth, the mask and the colour image clearly better. The
   verifier's score becomes the estimate's score.

:meth:`ClassicBaseline.predict` runs it over a BOP split (ground-truth or given masks) and returns
:class:`~poseflow.eval.results.PoseResults`, to be written with
:func:`~poseflow.eval.results.write_results` and scored with
:func:`~poseflow.eval.evaluate.evaluate_bop`, exactly like FunFlow6D's predictions.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch

from poseflow._checks import check_field_types, check_mask, check_tensor
from poseflow._config import apply_overrides, config_from_dict, config_to_dict
from poseflow._units import check_depth_extent, check_intrinsics
from poseflow.data.bop import BOPDataset
from poseflow.data.objects import ObjectModel, sample_surface
from poseflow.errors import DegenerateInputError, ValueRangeError
from poseflow.eval.inliers import mutual_nearest_neighbors
from poseflow.eval.predict import Estimator, PoseEstimate, invalidate_implausible, predict_dataset
from poseflow.eval.recall import Target
from poseflow.eval.results import PoseResults
from poseflow.eval.timing import StageTimer, stage
from poseflow.features.geometric import FPFHEncoder
from poseflow.features.lifting import viewpoint_poses
from poseflow.geometry.pointcloud import (
    backproject_depth,
    estimate_normals,
    remove_statistical_outliers,
    voxel_downsample,
)
from poseflow.geometry.se3 import inverse_transform
from poseflow.registration.icp import multi_scale_icp
from poseflow.registration.ransac import ransac_procrustes
from poseflow.render.raycast import Renderer
from poseflow.verify import PoseVerifier, VerifierConfig

__all__ = ["BASELINE_VERIFIER", "BaselineConfig", "ClassicBaseline"]

#: The baseline's default verifier configuration: :class:`VerifierConfig()` but for
#: ``refine_estimate``, off because the baseline's own ICP (up to 500 points, four scales of 30
#: iterations) is finer than the verifier's, so its estimate competes as it is (refining it again
#: was measured no better, ``benchmarks/LOG.md``).
BASELINE_VERIFIER = VerifierConfig(refine_estimate=False)


@dataclass(frozen=True, kw_only=True)
class BaselineConfig:
    """The settings of :class:`ClassicBaseline`; lengths are fractions of the object's diameter.

    Attributes:
        num_views: rendered viewpoints of each model for its descriptor bank.
        voxel_size: voxel size of the thinning.
        max_target_points: cap on the thinned target cloud (a random subset is kept).
        min_mutual: when mutual matching yields fewer pairs, every target point's nearest model
            descriptor is used as well.
        ransac_distance: RANSAC inlier distance.
        ransac_iterations: hypotheses per RANSAC run (the paper's Open3D setting: 1k).
        restarts: independent RANSAC runs per instance, each refined and verified by ICP.
        icp_distances: ICP correspondence distances, coarse to fine.
        icp_iterations: ICP iterations per scale.
        min_points: instances with fewer valid target points are reported invalid.
        verifier: check the poses by rendering and comparing (step 7) with this configuration,
            None for no check; its appearance term needs the colour image (without one, depth
            and silhouette are compared). A mapping is read with
            :meth:`VerifierConfig.from_dict`.
        seed: seed of every random draw (estimates are reproducible).

    Example:
        >>> BaselineConfig(restarts=4, verifier=None).to_dict()["icp_distances"]
        [0.2, 0.1, 0.05, 0.02]
    """

    num_views: int = 24
    voxel_size: float = 0.04
    max_target_points: int = 500
    min_mutual: int = 30
    ransac_distance: float = 0.05
    ransac_iterations: int = 1000
    restarts: int = 16
    icp_distances: tuple[float, ...] = (0.2, 0.1, 0.05, 0.02)
    icp_iterations: int = 30
    min_points: int = 30
    verifier: VerifierConfig | None = BASELINE_VERIFIER
    seed: int = 0

    def __post_init__(self) -> None:
        """Validate the types and the values."""
        check_field_types(self)
        object.__setattr__(self, "icp_distances", tuple(float(d) for d in self.icp_distances))
        if isinstance(self.verifier, Mapping):
            object.__setattr__(self, "verifier", VerifierConfig.from_dict(self.verifier))
        if not all(d > 0 for d in (self.voxel_size, self.ransac_distance, *self.icp_distances)):
            raise ValueRangeError("voxel_size, ransac_distance and icp_distances must be positive")
        if not self.icp_distances:
            raise ValueRangeError("icp_distances needs at least one distance")
        small = min(self.max_target_points, self.min_points)
        if min(self.num_views, self.restarts) < 1 or small < 3:
            raise ValueRangeError(
                "num_views and restarts must be >= 1, max_target_points and min_points >= 3"
            )

    def to_dict(self) -> dict[str, Any]:
        """The settings as a JSON-serialisable dict."""
        return config_to_dict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> BaselineConfig:
        """Build from :meth:`to_dict`'s dict; unknown keys are an error."""
        return config_from_dict(cls, data)


def _metres(depth: torch.Tensor) -> torch.Tensor:
    """The depth in float64 with every missing value (NaN, ±inf) set to 0."""
    return torch.nan_to_num(depth.to(torch.float64), nan=0.0, posinf=0.0, neginf=0.0)


class ClassicBaseline:
    """FPFH on partial views + mutual-NN matching + RANSAC + multi-scale ICP, for known objects.

    Args:
        models: object id -> :class:`~poseflow.data.objects.ObjectModel` (metres).
        config: the settings (default: :class:`BaselineConfig`'s defaults).
        encoder: the geometric descriptor; default :class:`~poseflow.features.FPFHEncoder` with
            the paper's radii (0.30 and 0.40 of the diameter).
        changes: settings changed from ``config`` (keys of :class:`BaselineConfig`, dotted ones
            too), merged by :func:`~poseflow.models.apply_overrides`: ``verifier=None`` turns
            verification off, ``verifier={"crop_size": 48}`` changes one field of
            :data:`BASELINE_VERIFIER`.

    Attributes:
        config: the :class:`BaselineConfig` in use.

    The stages ``lifting``, ``geometric_encoder``, ``matching``, ``ransac``, ``icp`` and
    ``verification`` are charged to the active :class:`~poseflow.eval.timing.StageTimer` (see
    :meth:`predict`), if any.

    Example:
        >>> import open3d as o3d
        >>> from poseflow.render import Renderer
        >>> box = o3d.geometry.TriangleMesh.create_box(0.1, 0.06, 0.03)
        >>> mesh = box.translate((-0.05, -0.03, -0.015))
        >>> model = ObjectModel.from_mesh(mesh, num_points=512)
        >>> K = torch.tensor([[300.0, 0, 80], [0, 300.0, 60], [0, 0, 1]], dtype=torch.float64)
        >>> from poseflow.eval.symmetry import axis_angle_rotation
        >>> pose = torch.eye(4, dtype=torch.float64); pose[2, 3] = 0.4  # three faces in view:
        >>> axis, angle = torch.tensor([1.0, 1.0, 0.2]), torch.tensor([0.8])
        >>> pose[:3, :3] = axis_angle_rotation(axis, angle)[0]
        >>> out = Renderer([mesh]).render(pose[None], K, 160, 120, rgb=False)
        >>> baseline = ClassicBaseline({1: model}, num_views=6, restarts=4, verifier=None)
        >>> est = baseline.estimate(out.depth, K, out.masks_full, [1])
        >>> bool(est.valid[0]), round(float(est.poses[0, 2, 3]), 2)
        (True, 0.4)
    """

    def __init__(
        self,
        models: Mapping[int, ObjectModel],
        config: BaselineConfig | None = None,
        *,
        encoder: FPFHEncoder | None = None,
        **changes: Any,
    ) -> None:
        if not models:
            raise ValueRangeError("ClassicBaseline needs at least one object model")
        config = BaselineConfig() if config is None else config
        if not isinstance(config, BaselineConfig):
            raise ValueRangeError(f"config must be a BaselineConfig, got {type(config).__name__}")
        self.config = apply_overrides(config, changes)
        self.models = dict(models)
        self.encoder = FPFHEncoder() if encoder is None else encoder
        self.verifier = PoseVerifier(self.config.verifier, seed=self.config.seed)
        self._banks: dict[int, tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = {}

    def _describe(
        self,
        depth: torch.Tensor,
        K: torch.Tensor,
        mask: torch.Tensor,
        diameter: float,
        generator: torch.Generator,
    ) -> tuple[torch.Tensor, torch.Tensor] | None:
        """Lift, clean, thin and describe one masked depth image: points ``(M, 3)``, FPFH."""
        with stage("lifting"):
            cloud = backproject_depth(depth[None], K, mask[None])
            pts, ok = cloud.points, cloud.mask
            if int(ok.sum()) < self.config.min_points:
                return None
            ok = ok & remove_statistical_outliers(pts, ok)
            idx, vok = voxel_downsample(pts, self.config.voxel_size * diameter, ok)
            t = pts[0, idx[0][vok[0]]]
            if t.shape[0] > self.config.max_target_points:
                pick = torch.randperm(t.shape[0], generator=generator)
                pick = pick[: self.config.max_target_points]
                t = t[pick.sort().values]
            if t.shape[0] < self.config.min_points:
                return None
            normals = estimate_normals(t[None], k=min(30, t.shape[0]))
        with stage("geometric_encoder"):
            feats = self.encoder.encode(t[None], normals, None, diameter)[0]
        return t, feats

    def prepare(self, obj_ids: Sequence[int] | None = None) -> None:
        """Build the descriptor banks now, and prepare the objects for the verifier when it is on.

        Else each is done on the object's first use.

        Args:
            obj_ids: the objects (default: all), e.g. so that timed estimates leave the banks out.
        """
        for obj_id in sorted(self.models) if obj_ids is None else obj_ids:
            self.bank(int(obj_id))
            if self.config.verifier is not None:
                self.verifier.prepare(int(obj_id), self.models[int(obj_id)])

    def bank(self, obj_id: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Descriptor bank of a model, built once per object from rendered views.

        Returns:
            Points ``(P, 3)`` in the model frame, their FPFH ``(P, D)``, and the dense model
            cloud ICP registers to.
        """
        if obj_id not in self._banks:
            m = self.models[obj_id]
            size, focal = 256, 500.0
            K = torch.tensor(
                [[focal, 0, (size - 1) / 2], [0, focal, (size - 1) / 2], [0, 0, 1]],
                dtype=torch.float64,
            )
            # The object spans about 60 % of the image.
            distance = focal * m.diameter / (0.6 * size)
            poses = viewpoint_poses(self.config.num_views, distance=distance)
            renderer = Renderer([m.mesh])
            gen = torch.Generator().manual_seed(self.config.seed)
            points, feats = [], []
            for T in poses:
                view = renderer.render(T[None], K, size, size, rgb=False)
                got = self._describe(
                    view.depth.to(torch.float64), K, view.masks_full[0], m.diameter, gen
                )
                if got is None:
                    continue
                t, f = got
                points.append((t - T[:3, 3]) @ T[:3, :3])  # back to the model frame
                feats.append(f)
            if not points:
                raise DegenerateInputError(f"object {obj_id}: no view of the model is usable")
            # ICP needs a dense model: surface samples thinned to a fine grid.
            dense, _, _ = sample_surface(m.mesh, 50_000, generator=gen)
            full = torch.from_numpy(dense)[None]
            idx, ok = voxel_downsample(full, 0.75 * self.config.icp_distances[-1] * m.diameter)
            self._banks[obj_id] = (torch.cat(points), torch.cat(feats), full[0, idx[0][ok[0]]])
        return self._banks[obj_id]

    def estimate(
        self,
        depth: torch.Tensor,
        K: torch.Tensor,
        masks: torch.Tensor,
        obj_ids: Sequence[int] | torch.Tensor,
        *,
        rgb: torch.Tensor | None = None,
    ) -> PoseEstimate:
        """Estimate the pose of every masked instance of one image.

        Args:
            depth: depth in metres, ``(H, W)``, 0 (or NaN) where missing.
            K: intrinsics ``(3, 3)``: a tensor, an array, nested lists or 9 numbers.
            masks: instance masks ``(n, H, W)`` bool (``n`` may be 0).
            obj_ids: object id of each instance, ``(n,)``.
            rgb: the colour image ``(3, H, W)`` (uint8, or float in ``[0, 1]``) for the
                verifier's appearance term; unused without verification.

        Returns:
            A :class:`PoseEstimate` (float64); with verification, the verified poses
            with the verifier's scores. A pose that is not finite or puts the object behind the
            camera is flagged invalid (:func:`~poseflow.eval.predict.invalidate_implausible`).

        Raises:
            ShapeError: bad shapes, or ``K`` not 9 numbers.
            ValueRangeError: an object id without a model, or a ``K`` that is not a pinhole
                matrix of this image.
        """
        Kd, ids = self._checked(depth, K, masks, obj_ids)
        d = _metres(depth)
        estimate, clouds = self._solve(d, Kd, masks, ids)
        if self.config.verifier is None or not bool(estimate.valid.any()):
            return estimate
        return invalidate_implausible(self._verify(rgb, d, Kd, masks, ids, estimate, clouds))

    def solve(
        self,
        depth: torch.Tensor,
        K: torch.Tensor,
        masks: torch.Tensor,
        obj_ids: Sequence[int] | torch.Tensor,
    ) -> tuple[PoseEstimate, list[torch.Tensor]]:
        """The pose of every masked instance of one image, before verification (steps 1-6).

        Args: as :meth:`estimate`.

        Returns:
            The :class:`PoseEstimate` (float64; implausible poses flagged invalid) and each
            instance's lifted, cleaned and thinned target cloud ``(M_i, 3)`` (empty where the
            mask holds too few points).

        Raises:
            ShapeError: bad shapes, or ``K`` not 9 numbers.
            ValueRangeError: an object id without a model, or a ``K`` that is not a pinhole
                matrix of this image.
            UnitsError: the masked depth spans far more or far less than the objects (a depth
                in the wrong unit).
        """
        Kd, ids = self._checked(depth, K, masks, obj_ids)
        return self._solve(_metres(depth), Kd, masks, ids)

    def _checked(
        self,
        depth: torch.Tensor,
        K: torch.Tensor,
        masks: torch.Tensor,
        obj_ids: Sequence[int] | torch.Tensor,
    ) -> tuple[torch.Tensor, list[int]]:
        """Check the inputs of :meth:`solve`; the float64 ``K`` and the ids as ints."""
        sizes = check_tensor(depth, "depth", ("H", "W"))
        check_mask(masks, "masks", ("n", "H", "W"), sizes)
        Kd = check_intrinsics(K, sizes["W"], sizes["H"], dtype=torch.float64, device=depth.device)
        ids = [int(o) for o in torch.as_tensor(obj_ids).reshape(-1).tolist()]
        n = masks.shape[0]
        if len(ids) != n:
            raise ValueRangeError(f"got {n} masks but {len(ids)} object ids")
        missing = sorted(set(ids) - set(self.models))
        if missing:
            raise ValueRangeError(f"no model for object ids {missing}")
        with stage("lifting"):  # the check back-projects every mask
            check_depth_extent(depth, Kd, masks, [self.models[o].diameter for o in ids])
        return Kd, ids

    def _solve(
        self, depth: torch.Tensor, K: torch.Tensor, masks: torch.Tensor, ids: list[int]
    ) -> tuple[PoseEstimate, list[torch.Tensor]]:
        """:meth:`solve` of checked inputs: depth in metres, float64, 0 where missing."""
        n = len(ids)
        poses = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
        scores = torch.zeros(n, dtype=torch.float64)
        valid = torch.zeros(n, dtype=torch.bool)
        clouds = []
        for i in range(n):
            pose, score, cloud = self._estimate_one(depth, K, masks[i], ids[i], i)
            clouds.append(cloud)
            if pose is not None:
                poses[i], scores[i], valid[i] = pose, score, True
        return invalidate_implausible(PoseEstimate(poses, scores, valid)), clouds

    def _verify(
        self,
        rgb: torch.Tensor | None,
        depth: torch.Tensor,
        K: torch.Tensor,
        masks: torch.Tensor,
        ids: list[int],
        estimate: PoseEstimate,
        clouds: list[torch.Tensor],
    ) -> PoseEstimate:
        """Verify the estimates, ICP of the verifier registering the lifted clouds ``(M_i, 3)``."""
        for obj_id in sorted(set(ids)):
            self.verifier.prepare(obj_id, self.models[obj_id])
        M = max(3, max(len(c) for c in clouds))
        observed = torch.zeros(len(clouds), M, 3, dtype=torch.float32)
        observed_mask = torch.zeros(len(clouds), M, dtype=torch.bool)
        for i, c in enumerate(clouds):
            observed[i, : len(c)], observed_mask[i, : len(c)] = c, True
        # the verifier runs in the poses' dtype: float32 is twice as fast as float64
        with stage("verification"):
            out = self.verifier.verify(
                rgb, depth.float(), K.float(), masks, ids, estimate.poses.float(), observed,
                observed_mask, estimated=estimate.valid,
            )  # fmt: skip
        # an estimate kept as it was: at its full precision
        kept = (out.chosen == 0) & (not self.verifier.config.refine_estimate)
        poses = torch.where(kept[:, None, None], estimate.poses, out.poses.to(estimate.poses.dtype))
        return PoseEstimate(poses, out.scores.to(estimate.scores.dtype), estimate.valid)

    def _estimate_one(
        self, depth: torch.Tensor, K: torch.Tensor, mask: torch.Tensor, obj_id: int, index: int
    ) -> tuple[torch.Tensor | None, float, torch.Tensor]:
        """The pose, score and lifted target cloud ``(M, 3)`` (empty if too small) of one mask."""
        diam = self.models[obj_id].diameter
        bank_pts, bank_feats, model_pts = self.bank(obj_id)
        cfg = self.config
        gen = torch.Generator().manual_seed(cfg.seed * 1_000_003 + index)
        got = self._describe(depth, K, mask, diam, gen)
        if got is None:
            return None, 0.0, depth.new_zeros(0, 3)
        t, ft = got
        with stage("matching"):
            mutual = mutual_nearest_neighbors(bank_feats[None], ft[None])[0]  # (M,) or -1
            has = mutual >= 0
            src, dst = bank_pts[mutual[has]], t[has]  # model points, their observed partners
            if src.shape[0] < cfg.min_mutual:
                nearest = torch.cdist(ft, bank_feats).argmin(-1)
                src, dst = torch.cat((src, bank_pts[nearest])), torch.cat((dst, t))
            R = cfg.restarts
            # Each restart sees a random half of the pairs (the first sees all): the hypotheses
            # differ, and ICP picks the one that explains the observation best.
            subset = torch.rand(R, src.shape[0], generator=gen) < 0.5
            subset[0] = True
        with stage("ransac"):
            hyp = ransac_procrustes(
                src[None].expand(R, -1, -1),
                dst[None].expand(R, -1, -1),
                subset,
                max_correspondence_distance=cfg.ransac_distance * diam,
                max_iterations=cfg.ransac_iterations,
                generator=gen,
            )
        with stage("icp"):
            # The paper's direction: the observed cloud onto the model, then invert.
            refined = multi_scale_icp(
                t[None].expand(R, -1, -1),
                model_pts[None].expand(R, -1, -1),
                inverse_transform(hyp.transformation),
                max_correspondence_distances=[f * diam for f in cfg.icp_distances],
                max_iterations=cfg.icp_iterations,
            )
        fitness = torch.where(hyp.valid & refined.valid, refined.fitness, -1.0)
        best = int(fitness.argmax())
        if float(fitness[best]) < 0:
            return None, 0.0, t
        pose = inverse_transform(refined.transformation[best : best + 1])[0]
        return pose, float(fitness[best]), t

    def estimator(self) -> Estimator:
        """This baseline as an :data:`~poseflow.eval.predict.Estimator`.

        The colour image is used by the verification only.
        """
        return lambda rgb, depth, K, masks, obj_ids: self.estimate(
            depth, K, masks, obj_ids, rgb=rgb
        )

    def predict(
        self,
        dataset: str | os.PathLike[str] | BOPDataset,
        *,
        split: str = "test",
        targets: Sequence[Target] | None = None,
        detections: Sequence[Any] | None = None,
        max_images: int | None = None,
        timer: StageTimer | None = None,
        progress: bool = False,
    ) -> PoseResults:
        """Estimate every target instance of a split (:func:`~poseflow.eval.predict_dataset`).

        Args:
            dataset: the dataset folder or a :class:`~poseflow.data.bop.BOPDataset`.
            split: the split folder, when ``dataset`` is a path.
            targets: restrict to these targets; default the dataset's ``test_targets_bop19.json``
                when present, else every GT instance.
            detections: masks from a BOP segmentation file instead of the ground truth.
            max_images: stop after this many images.
            timer: optional :class:`~poseflow.eval.timing.StageTimer`, active while each image
                is estimated.
            progress: show a progress bar.

        Returns:
            :class:`~poseflow.eval.results.PoseResults` with one estimate per valid instance of
            a target object, and the wall-clock time of each image (image loading and the
            objects' one-time preparation, done first, excluded).
            The colour images are read only with verification on.
        """
        self.prepare()  # the banks (and the verifier's objects) are not any image's time
        return predict_dataset(
            self.estimator(),
            dataset,
            split=split,
            object_ids=sorted(self.models),
            targets=targets,
            detections=detections,
            load_rgb=self.config.verifier is not None,
            max_images=max_images,
            timer=timer,
            progress=progress,
        )
