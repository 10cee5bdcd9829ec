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
from dataclasses import dataclass, replace
from typing import Any

import torch

from poseflow._checks import check_field_types, check_mask, check_tensor
from poseflow._config import apply_overrides, config_from_dict, config_to_dict
from poseflow._units import check_depth_extent, check_intrinsics
from poseflow._workers import map_forked
from poseflow.data.bop import BOPDataset
from poseflow.data.frame import ImageInstances
from poseflow.data.objects import ObjectModel, sample_surface
from poseflow.errors import DegenerateInputError, ValueRangeError
from poseflow.eval.inliers import mutual_nearest_neighbors
from poseflow.eval.predict import Estimator, PoseEstimate, invalidate_implausible, predict_seeded
from poseflow.eval.results import PoseResults
from poseflow.eval.timing import stage
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

__all__ = [
    "BASELINE_VERIFIER",
    "BaselineConfig",
    "ClassicBaseline",
    "build_bank",
    "describe_target",
    "register_target",
    "verify_estimates",
]

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
        >>> from poseflow.geometry.se3 import axis_angle_to_rotation
        >>> pose = torch.eye(4, dtype=torch.float64); pose[2, 3] = 0.4  # three faces in view:
        >>> axis, angle = torch.tensor([1.0, 1.0, 0.2]), torch.tensor([0.8])
        >>> pose[:3, :3] = axis_angle_to_rotation(axis, angle)[0]
        >>> out = Renderer([mesh]).render(pose[None], K, 160, 120, rgb=False)
        >>> baseline = ClassicBaseline({1: model}, num_views=6, restarts=4, verifier=None)
        >>> est = baseline.estimate(None, out.depth, K, out.masks_full, [1])
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

    def prepare(self, obj_ids: Sequence[int] | None = None, *, workers: int = 1) -> None:
        """Build the descriptor banks now, and prepare the objects for the verifier when it is on.

        Else each is done on the object's first use.

        Args:
            obj_ids: the objects (default: all), e.g. so that timed estimates leave the banks out.
            workers: prepare the objects in this many forked processes of one thread each
                (``poseflow._workers.map_forked``): the same banks.
        """
        ids = [int(o) for o in (sorted(self.models) if obj_ids is None else obj_ids)]
        verify = self.config.verifier is not None

        def prepare_one(n: int) -> tuple[Any, Any]:
            bank = self.bank(ids[n])
            return bank, self.verifier.prepare(ids[n], self.models[ids[n]]) if verify else None

        for obj_id, (bank, prepared) in zip(ids, map_forked(prepare_one, len(ids), workers)):
            self._banks[obj_id] = bank
            if prepared is not None:
                self.verifier.objects[obj_id] = prepared

    def bank(self, obj_id: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Descriptor bank of a model, built once per object from rendered views.

        Returns:
            Points ``(P, 3)`` in the model frame, their FPFH ``(P, D)``, and the dense model
            cloud ICP registers to.
        """
        if obj_id not in self._banks:
            m = self.models[obj_id]
            self._banks[obj_id] = build_bank(m, self.encoder, self.config, name=f"object {obj_id}")
        return self._banks[obj_id]

    def estimate(
        self,
        rgb: torch.Tensor | None,
        depth: torch.Tensor,
        K: torch.Tensor,
        masks: torch.Tensor,
        obj_ids: Sequence[int] | torch.Tensor,
    ) -> PoseEstimate:
        """Estimate the pose of every masked instance of one image.

        The arguments of every estimator (:data:`~poseflow.eval.predict.Estimator`), in its order.

        Args:
            rgb: the colour image ``(3, H, W)`` (uint8, or float in ``[0, 1]``) for the
                verifier's appearance term, or None (depth and silhouette are compared); unused
                without verification.
            depth: depth in metres, ``(H, W)``, 0 (or NaN) where missing.
            K: intrinsics ``(3, 3)``: a tensor, an array, nested lists or 9 numbers.
            masks: instance masks ``(n, H, W)`` bool (``n`` may be 0).
            obj_ids: object id of each instance, ``(n,)``.

        Returns:
            A :class:`PoseEstimate` (float64); with verification, the verified poses
            with the verifier's scores. A pose that is not finite or puts the object behind the
            camera is flagged invalid (:func:`~poseflow.eval.predict.invalidate_implausible`).

        Raises:
            ShapeError: bad shapes, or ``K`` not 9 numbers.
            ValueRangeError: an object id without a model, or a ``K`` that is not a pinhole
                matrix of this image.
        """
        image = self._checked(ImageInstances(rgb, depth, K, masks, obj_ids))
        estimate, clouds = self._solve(image)
        if self.config.verifier is None or not bool(estimate.valid.any()):
            return estimate
        for obj_id in sorted(set(image.obj_ids)):
            self.verifier.prepare(obj_id, self.models[obj_id])
        verified = verify_estimates(self.verifier, image, estimate, clouds)
        return invalidate_implausible(verified)

    def solve(self, image: ImageInstances) -> tuple[PoseEstimate, list[torch.Tensor]]:
        """The pose of every masked instance of one image, before verification (steps 1-6).

        Args:
            image: the depth, intrinsics, masks and object ids as :meth:`estimate` takes them
                (the colour image is not used), on the CPU.

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
        return self._solve(self._checked(image))

    def _checked(self, image: ImageInstances) -> ImageInstances:
        """``image`` checked, ready for :meth:`_solve`.

        Its depth in metres as :func:`_metres` gives it (float64, 0 where missing), ``K``
        ``(3, 3)`` float64 and the object ids a list of ints.
        """
        depth, masks = image.depth, image.masks
        sizes = check_tensor(depth, "depth", ("H", "W"))
        check_mask(masks, "masks", ("n", "H", "W"), sizes)
        Kd = check_intrinsics(
            image.K, sizes["W"], sizes["H"], dtype=torch.float64, device=depth.device
        )
        ids = [int(o) for o in torch.as_tensor(image.obj_ids).reshape(-1).tolist()]
        n = masks.shape[0]
        if len(ids) != n:
            raise ValueRangeError(f"got {n} masks but {len(ids)} object ids")
        missing = sorted(set(ids) - set(self.models))
        if missing:
            raise ValueRangeError(f"no model for object ids {missing}")
        with stage("lifting"):  # the check back-projects every mask
            check_depth_extent(depth, Kd, masks, [self.models[o].diameter for o in ids])
        return replace(image, depth=_metres(depth), K=Kd, obj_ids=ids)

    def _solve(self, image: ImageInstances) -> tuple[PoseEstimate, list[torch.Tensor]]:
        """:meth:`solve` of a :meth:`_checked` image."""
        depth, K, masks, ids = image.depth, image.K, image.masks, image.obj_ids
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

    def _estimate_one(
        self, depth: torch.Tensor, K: torch.Tensor, mask: torch.Tensor, obj_id: int, index: int
    ) -> tuple[torch.Tensor | None, float, torch.Tensor]:
        """The pose, score and lifted target cloud ``(M, 3)`` (empty if too small) of one mask."""
        diameter = self.models[obj_id].diameter
        bank = self.bank(obj_id)
        gen = torch.Generator().manual_seed(self.config.seed * 1_000_003 + index)
        got = describe_target(depth, K, mask, diameter, self.encoder, self.config, gen)
        if got is None:
            return None, 0.0, depth.new_zeros(0, 3)
        t, ft = got
        pose, score = register_target(t, ft, bank, diameter, self.config, gen)
        return pose, score, t

    def estimator(self) -> Estimator:
        """This baseline as an :data:`~poseflow.eval.predict.Estimator`: its :meth:`estimate`.

        The colour image is used by the verification only.
        """
        return self.estimate

    def predict(self, dataset: str | os.PathLike[str] | BOPDataset, **options: Any) -> PoseResults:
        """Estimate every target instance of a BOP split: :func:`~poseflow.eval.predict_seeded`.

        ``options`` as for :meth:`FunFlow6D.predict <poseflow.models.FunFlow6D.predict>` but
        ``seed``: the baseline seeds each instance from ``config.seed``. The objects are
        prepared first, so that no image's time includes them; the colour images are read only
        with a verifier. Returns :class:`~poseflow.eval.results.PoseResults`, one row per valid
        estimate.
        """
        self.prepare(workers=options.get("workers", 1))  # not any image's time
        return predict_seeded(
            lambda _: self.estimator(),
            dataset,
            device="cpu",
            object_ids=sorted(self.models),
            load_rgb=self.config.verifier is not None,
            **options,
        )


def describe_target(
    depth: torch.Tensor,
    K: torch.Tensor,
    mask: torch.Tensor,
    diameter: float,
    encoder: FPFHEncoder,
    config: BaselineConfig,
    generator: torch.Generator,
) -> tuple[torch.Tensor, torch.Tensor] | None:
    """Lift, clean, thin and describe one masked depth image (steps 1 and 2).

    Args:
        depth: depth ``(H, W)`` in metres, float64, 0 where missing.
        K: intrinsics ``(3, 3)``, float64.
        mask: the instance's mask ``(H, W)``.
        diameter: its object's diameter, metres.
        encoder: the geometric descriptor.
        config: the thinning (``voxel_size``, ``max_target_points``, ``min_points``).
        generator: draws the subset of a cloud above ``max_target_points``.

    Returns:
        The points ``(M, 3)`` and their descriptors ``(M, D)``, or None with fewer than
        ``config.min_points`` points.
    """
    with stage("lifting"):
        cloud = backproject_depth(depth[None], K, mask[None])
        pts, ok = cloud.points, cloud.mask
        if int(ok.sum()) < config.min_points:
            return None
        ok = ok & remove_statistical_outliers(pts, ok)
        idx, vok = voxel_downsample(pts, config.voxel_size * diameter, ok)
        t = pts[0, idx[0][vok[0]]]
        if t.shape[0] > config.max_target_points:
            pick = torch.randperm(t.shape[0], generator=generator)
            pick = pick[: config.max_target_points]
            t = t[pick.sort().values]
        if t.shape[0] < config.min_points:
            return None
        normals = estimate_normals(t[None], k=min(30, t.shape[0]))
    with stage("geometric_encoder"):
        feats = encoder.encode(t[None], normals, None, diameter)[0]
    return t, feats


def build_bank(
    model: ObjectModel, encoder: FPFHEncoder, config: BaselineConfig, *, name: str = "object"
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The descriptor bank of a model, from ``config.num_views`` rendered partial views (step 3).

    Each view's depth is lifted, thinned and described like a target (:func:`describe_target`).

    Args:
        model: the object model (metres).
        encoder: the geometric descriptor.
        config: the views, the thinning and the finest ICP distance (the dense cloud's grid).
        name: the object, for the error.

    Returns:
        Points ``(P, 3)`` in the model frame, their descriptors ``(P, D)``, and the dense model
        cloud ``(Q, 3)`` that ICP registers to.

    Raises:
        DegenerateInputError: no view of the model is usable.
    """
    size, focal = 256, 500.0
    K = torch.tensor(
        [[focal, 0, (size - 1) / 2], [0, focal, (size - 1) / 2], [0, 0, 1]],
        dtype=torch.float64,
    )
    # The object spans about 60 % of the image.
    distance = focal * model.diameter / (0.6 * size)
    poses = viewpoint_poses(config.num_views, distance=distance)
    renderer = Renderer([model.mesh])
    gen = torch.Generator().manual_seed(config.seed)
    points, feats = [], []
    for T in poses:
        view = renderer.render(T[None], K, size, size, rgb=False)
        depth = view.depth.to(torch.float64)
        got = describe_target(depth, K, view.masks_full[0], model.diameter, encoder, config, gen)
        if got is None:
            continue
        t, f = got
        points.append((t - T[:3, 3]) @ T[:3, :3])  # back to the model frame
        feats.append(f)
    if not points:
        raise DegenerateInputError(f"{name}: no view of the model is usable")
    # ICP needs a dense model: surface samples thinned to a fine grid.
    dense, _, _ = sample_surface(model.mesh, 50_000, generator=gen)
    full = torch.from_numpy(dense)[None]
    idx, ok = voxel_downsample(full, 0.75 * config.icp_distances[-1] * model.diameter)
    return torch.cat(points), torch.cat(feats), full[0, idx[0][ok[0]]]


def register_target(
    t: torch.Tensor,
    ft: torch.Tensor,
    bank: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    diameter: float,
    config: BaselineConfig,
    generator: torch.Generator,
) -> tuple[torch.Tensor | None, float]:
    """The pose of a described target cloud: matching, RANSAC restarts and ICP (steps 4 to 6).

    Args:
        t: the target cloud ``(M, 3)``, camera frame.
        ft: its descriptors ``(M, D)``.
        bank: the object's bank (:func:`build_bank`).
        diameter: the object's diameter, metres.
        config: matching, RANSAC and ICP settings.
        generator: draws the restarts' pairs and RANSAC's samples.

    Returns:
        The model-to-camera pose ``(4, 4)`` that explains most of ``t`` and its ICP fitness, or
        None and 0 where no hypothesis is valid.
    """
    bank_pts, bank_feats, model_pts = bank
    with stage("matching"):
        mutual = mutual_nearest_neighbors(bank_feats[None], ft[None])[0]  # (M,) or -1
        has = mutual >= 0
        src, dst = bank_pts[mutual[has]], t[has]  # model points, their observed partners
        if src.shape[0] < config.min_mutual:
            nearest = torch.cdist(ft, bank_feats).argmin(-1)
            src, dst = torch.cat((src, bank_pts[nearest])), torch.cat((dst, t))
        R = config.restarts
        # Each restart sees a random half of the pairs (the first sees all): the hypotheses
        # differ, and ICP picks the one that explains the observation best.
        subset = torch.rand(R, src.shape[0], generator=generator) < 0.5
        subset[0] = True
    with stage("ransac"):
        hyp = ransac_procrustes(
            src[None].expand(R, -1, -1),
            dst[None].expand(R, -1, -1),
            subset,
            max_correspondence_distance=config.ransac_distance * diameter,
            max_iterations=config.ransac_iterations,
            generator=generator,
        )
    with stage("icp"):
        # The paper's direction: the observed cloud onto the model, then invert.
        refined = multi_scale_icp(
            t[None].expand(R, -1, -1),
            model_pts[None].expand(R, -1, -1),
            inverse_transform(hyp.transformation),
            max_correspondence_distances=[f * diameter for f in config.icp_distances],
            max_iterations=config.icp_iterations,
        )
    fitness = torch.where(hyp.valid & refined.valid, refined.fitness, -1.0)
    best = int(fitness.argmax())
    if float(fitness[best]) < 0:
        return None, 0.0
    return inverse_transform(refined.transformation[best : best + 1])[0], float(fitness[best])


def verify_estimates(
    verifier: PoseVerifier,
    image: ImageInstances,
    estimate: PoseEstimate,
    clouds: list[torch.Tensor],
) -> PoseEstimate:
    """Verify an image's estimates, the verifier's ICP registering the lifted clouds (step 7).

    Args:
        verifier: the verifier, its objects prepared.
        image: the colour image ``(3, H, W)`` or None, depth ``(H, W)`` in metres, ``K``
            ``(3, 3)``, and the ``n`` instances' masks ``(n, H, W)`` and object ids.
        estimate: the estimates (float64).
        clouds: each instance's lifted target cloud ``(M_i, 3)``.

    Returns:
        The verified poses (an estimate kept as it was at its full precision), the verifier's
        scores, the estimate's validity.
    """
    M = max(3, max(len(c) for c in clouds))
    observed = torch.zeros(len(clouds), M, 3, dtype=torch.float32)
    observed_mask = torch.zeros(len(clouds), M, dtype=torch.bool)
    for i, c in enumerate(clouds):
        observed[i, : len(c)], observed_mask[i, : len(c)] = c, True
    # the verifier runs in the poses' dtype: float32 is twice as fast as float64
    with stage("verification"):
        out = verifier.verify(
            replace(image, depth=image.depth.float(), K=image.K.float()),
            estimate.poses.float(), (observed, observed_mask), estimated=estimate.valid,
        )  # fmt: skip
    # an estimate kept as it was (neither refined nor polished): at its full precision
    unchanged = (out.poses == out.hypotheses[:, 0]).flatten(1).all(1)
    kept = (out.chosen == 0) & unchanged & (not verifier.config.refine_estimate)
    poses = torch.where(kept[:, None, None], estimate.poses, out.poses.to(estimate.poses.dtype))
    return PoseEstimate(poses, out.scores.to(estimate.scores.dtype), estimate.valid)
