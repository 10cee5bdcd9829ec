"""FunFlow6D: the model class that composes poseflow's parts into the paper's method.

Each job has its module: :mod:`~poseflow.models.objects` prepares and caches the known objects,
:mod:`~poseflow.models.observe` lifts an RGBD image to target clouds with their frozen features,
:mod:`~poseflow.models.inputs` pairs them with the query clouds as :class:`FlowInputs`, the
trainable :class:`~poseflow.models.network.FunFlow6DNet` and a sampler of
:mod:`poseflow.flows` carry the targets to the canonical frame, :mod:`~poseflow.models.pose`
turns the result into poses and :mod:`~poseflow.models.verification` checks them by rendering and
comparing (:class:`~poseflow.verify.PoseVerifier`). Time is reported to the caller's active
:class:`~poseflow.eval.timing.StageTimer` (see :func:`~poseflow.eval.timing.stage`).

Shape letters: ``B`` instances, ``N`` points per cloud, ``H`` hypotheses per instance.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import nn

from poseflow._checks import check_tensor
from poseflow._units import check_depth_extent, check_intrinsics
from poseflow.data.objects import ObjectModel
from poseflow.errors import CheckpointError, ValueRangeError
from poseflow.eval.predict import (
    Estimator,
    PoseEstimate,
    invalidate_implausible,
    on_device,
    predict_dataset,
)
from poseflow.eval.results import PoseResults
from poseflow.eval.timing import StageTimer, stage
from poseflow.flows import get_sampler
from poseflow.models.checkpoint import read_checkpoint, write_checkpoint
from poseflow.models.components import build_appearance_encoder, build_geometric_encoder
from poseflow.models.config import FunFlow6DConfig
from poseflow.models.inputs import FlowInputs
from poseflow.models.network import FunFlow6DNet, NetInputs
from poseflow.models.objects import PreparedObject, prepare_objects, select_objects
from poseflow.models.observe import Observation, observe
from poseflow.models.pose import select_hypotheses, solve_pose
from poseflow.models.verification import (
    Proposals,
    other_hypotheses,
    prepare_verification,
    verify_proposals,
)
from poseflow.verify import PoseVerifier

__all__ = ["FunFlow6D", "predict_seeded"]


class FunFlow6D(nn.Module):
    """Model-based 6D pose estimation by conditional flow matching on fused frozen features.

    Args:
        config: the configuration (default: the offline defaults, FPFH + dense SIFT + PCA,
            gated fusion, ``small`` DiT, render-and-compare verification).

    Attributes:
        objects: the prepared objects, ``{obj_id: PreparedObject}``.
        verifier: the :class:`~poseflow.verify.PoseVerifier` of ``config.verifier``, with the
            objects prepared for it (when ``config.verifier`` was set at
            :meth:`prepare_objects`).

    Example:
        >>> model = FunFlow6D(FunFlow6DConfig(num_points=32, dit_preset="tiny", crop_size=48))
        >>> sum(p.numel() for p in model.parameters()) > 0
        True
    """

    def __init__(self, config: FunFlow6DConfig | None = None) -> None:
        super().__init__()
        self.config = cfg = FunFlow6DConfig() if config is None else config
        self.geometric_encoder = build_geometric_encoder(
            cfg.geometric_encoder, radii=cfg.geometric_radii
        )
        self.appearance_encoder = build_appearance_encoder(
            cfg.appearance_encoder, crop_size=cfg.crop_size
        )
        appearance = self.appearance_encoder
        semantic_dim = None  # the reducer's output, or the raw features without reduction
        if appearance is not None:
            semantic_dim = appearance.dim if cfg.reducer == "identity" else cfg.feature_dim
        geometric_dim = getattr(self.geometric_encoder, "dim", None)
        self.net = FunFlow6DNet(cfg.net_config(geometric_dim, semantic_dim))
        self.objects: dict[int, PreparedObject] = {}
        self.verifier = PoseVerifier(cfg.verifier)

    def prepare_objects(
        self,
        models: Mapping[int, ObjectModel],
        *,
        cache_dir: str | Path | None = None,
        progress: bool = True,
    ) -> None:
        """Prepare every object (:func:`~poseflow.models.objects.prepare_objects`) for inference.

        With ``config.verifier`` set, the objects are prepared for the verifier too
        (:func:`~poseflow.models.verification.prepare_verification`, cached beside them); a
        verifier of another configuration than ``config.verifier`` is replaced.

        Args:
            models: ``{obj_id: ObjectModel}`` (metres, textured meshes for appearance).
            cache_dir: where prepared objects are stored and looked up (safetensors + JSON), one
                entry per object, mesh content (and scale) and configuration
                (:func:`~poseflow.models.objects.object_cache_entry`), each written whole; None
                computes everything in memory.
            progress: show a progress bar.
        """
        self.objects.update(
            prepare_objects(
                models,
                self.config,
                geometric_encoder=self.geometric_encoder,
                appearance_encoder=self.appearance_encoder,
                cache_dir=cache_dir,
                progress=progress,
            )
        )
        if self.config.verifier is not None:
            if self.verifier.config != self.config.verifier:
                self.verifier = PoseVerifier(self.config.verifier)
            prepare_verification(self.verifier, models, cache_dir=cache_dir, progress=progress)

    @torch.no_grad()
    def observe(
        self,
        rgb: torch.Tensor,
        depth: torch.Tensor,
        K: torch.Tensor,
        masks: torch.Tensor,
        obj_ids: torch.Tensor | Sequence[int],
        *,
        generator: torch.Generator | None = None,
        crop_jitter: float = 0.0,
    ) -> Observation:
        """The target clouds of an image; see :func:`~poseflow.models.observe.observe`.

        ``K`` may be a tensor, an array, nested lists or 9 numbers; without masks (``B = 0``)
        the observation is empty. Without a ``generator``, the draws come from one seeded 0,
        as in :meth:`estimate`.

        Raises:
            ShapeError: inconsistent shapes, or ``K`` not 9 numbers.
            ValueRangeError: an object id that is not prepared, or a ``K`` that is not a pinhole
                matrix of this image.
        """
        diameters = [o.diameter for o in select_objects(self.objects, obj_ids)]
        if generator is None:
            generator = torch.Generator(device=depth.device).manual_seed(0)
        return observe(
            rgb, depth, K, masks, obj_ids, diameters,
            num_points=self.config.num_points, dense_points=self.config.dense_points,
            geometric_encoder=self.geometric_encoder, appearance_encoder=self.appearance_encoder,
            geometric_support_voxel=self.config.geometric_support_voxel,
            generator=generator, crop_jitter=crop_jitter,
        )  # fmt: skip

    def flow_inputs(self, obs: Observation, poses: torch.Tensor | None = None) -> FlowInputs:
        """The :class:`FlowInputs` of an observation (with ``x_1`` when poses are given)."""
        return FlowInputs.from_observation(
            obs,
            select_objects(self.objects, obs.obj_ids),
            poses,
            query_pooling=getattr(self.appearance_encoder, "query_pooling", "mean"),
        )

    def velocity(
        self, *, x: torch.Tensor, t: torch.Tensor, x_0: torch.Tensor, **inputs: torch.Tensor
    ) -> torch.Tensor:
        """``Ψ(t, X(t) | C)`` ``(B, 2N, 3)``; ``inputs`` are named as :class:`NetInputs`' fields."""
        return self.net(x=x, t=t, inputs=NetInputs.from_kwargs(inputs), x_0=x_0)

    def forward(self, **kwargs: Any) -> torch.Tensor:
        """Same as :meth:`velocity`, so the model plugs into :class:`~poseflow.flows.CFMTrainer`."""
        return self.velocity(**kwargs)

    @torch.no_grad()
    def estimate(
        self,
        rgb: torch.Tensor,
        depth: torch.Tensor,
        K: torch.Tensor,
        masks: torch.Tensor,
        obj_ids: torch.Tensor | Sequence[int],
        *,
        generator: torch.Generator | None = None,
    ) -> PoseEstimate:
        """Estimate the pose of every masked instance of one RGBD image, in one batch.

        :meth:`propose`, then, with ``config.verifier`` set, :meth:`verify`: the verifier's
        ICP registers the observation's cleaned cloud and its scores become the estimate's.
        Stages are charged to the active :class:`~poseflow.eval.timing.StageTimer`, if any.

        Args:
            rgb: the image ``(3, H, W)``, uint8 or float in ``[0, 1]``.
            depth: depth ``(H, W)`` in metres.
            K: intrinsics ``(3, 3)``: a tensor, an array, nested lists or 9 numbers.
            masks: instance masks ``(B, H, W)`` bool (``B`` may be 0).
            obj_ids: object id of each mask ``(B,)``; every id must be prepared.
            generator: seeds the noise, the sampling of the clouds and RANSAC; None: a generator
                seeded 0, so that the same call gives the same poses (pass a generator seeded
                at random for independent draws).

        Returns:
            A :class:`PoseEstimate` (of ``B`` instances, float32 on the depth's device); a pose
            that is not finite or puts the object behind the camera is flagged invalid
            (:func:`~poseflow.eval.predict.invalidate_implausible`).

        Raises:
            ShapeError: inconsistent shapes, or ``K`` not 9 numbers.
            ValueRangeError: an object id that is not prepared (for verification too, when on),
                a verifier prepared for another ``config.verifier``, or a ``K`` that is not a
                pinhole matrix of this image.
            UnitsError: the masked depth spans far more or far less than the objects (a depth
                in the wrong unit; :func:`~poseflow._units.check_depth_extent`).
        """
        proposals = self.propose(rgb, depth, K, masks, obj_ids, generator=generator)
        if self.config.verifier is None or proposals.estimate.poses.shape[0] == 0:
            return proposals.estimate
        return self.verify(proposals, rgb, depth, K, masks, obj_ids)

    @torch.no_grad()
    def propose(
        self,
        rgb: torch.Tensor,
        depth: torch.Tensor,
        K: torch.Tensor,
        masks: torch.Tensor,
        obj_ids: torch.Tensor | Sequence[int],
        *,
        generator: torch.Generator | None = None,
    ) -> Proposals:
        """The flow's poses of every instance of one image, before verification.

        Samples ``config.num_hypotheses`` flows per instance and solves each for a pose; the
        best by the solver's score is the incumbent, and with
        ``config.verifier.rank_hypotheses`` the others are candidates that the verifier ranks
        (:class:`Proposals` with ``rank`` on). Arguments as :meth:`estimate`.

        Returns:
            :class:`~poseflow.models.verification.Proposals` of the ``B`` instances, with the
            observation's cleaned clouds for the verifier's ICP.
        """
        cfg = self.config
        if cfg.verifier is not None and self.verifier.config != cfg.verifier:
            raise ValueRangeError(
                "config.verifier changed after the objects were prepared for verification; "
                "call prepare_objects again"
            )
        sizes = check_tensor(depth, "depth", ("H", "W"), floating=False)
        K = check_intrinsics(K, sizes["W"], sizes["H"], dtype=torch.float32, device=depth.device)
        diameters = [o.diameter for o in select_objects(self.objects, obj_ids)]
        with stage("lifting"):  # the check back-projects every mask
            check_depth_extent(depth, K, masks, diameters, where="the depth")
        if generator is None:
            generator = torch.Generator(device=depth.device).manual_seed(0)
        was_training = self.training
        self.eval()
        try:
            obs = self.observe(rgb, depth, K, masks, obj_ids, generator=generator)
            H = cfg.num_hypotheses
            if obs.points.shape[0] == 0:
                est = PoseEstimate.empty(device=depth.device)
                return Proposals(est, est.poses[:, None][:, :0], est.valid[:, None][:, :0])
            with stage("flow_inputs"):
                inputs = self.flow_inputs(obs)
            x_1 = self.net.sample(
                inputs,
                get_sampler(cfg.solver, steps=cfg.steps),
                frozen_mask=inputs.frozen_mask,
                x_frozen=inputs.anchor if cfg.anchor == "pinned" else None,
                generator=generator,
                num_samples=H,
            )
            rep = inputs.repeat_interleave(H)
            dense = [o.dense_points for o in select_objects(self.objects, rep.obj_ids)]
            n = rep.points.shape[1] // 2
            solved = solve_pose(rep, x_1[:, n:], dense, cfg, generator=generator)
            est = select_hypotheses(*solved, obs.valid, H)
            est = invalidate_implausible(est)  # nothing behind the camera is verified
            rank = cfg.verifier is not None and cfg.verifier.rank_hypotheses and H > 1
            if rank:
                others, others_mask = other_hypotheses(*solved, H)
            else:
                others, others_mask = est.poses[:, None][:, :0], est.valid[:, None][:, :0]
            return Proposals(est, others, others_mask, obs.cloud, obs.cloud_mask, rank=rank)
        finally:
            self.train(was_training)

    def verify(
        self,
        proposals: Proposals,
        rgb: torch.Tensor,
        depth: torch.Tensor,
        K: torch.Tensor,
        masks: torch.Tensor,
        obj_ids: torch.Tensor | Sequence[int],
    ) -> PoseEstimate:
        """Choose and verify each instance's pose among ``proposals`` with :attr:`verifier`.

        See :func:`~poseflow.models.verification.verify_proposals`; arguments as
        :meth:`estimate`.

        Raises:
            ValueRangeError: an object the verifier has not prepared.
        """
        sizes = check_tensor(depth, "depth", ("H", "W"), floating=False)
        K = check_intrinsics(K, sizes["W"], sizes["H"], dtype=torch.float32, device=depth.device)
        obj_ids = torch.as_tensor(obj_ids).reshape(-1)
        verified = verify_proposals(self.verifier, proposals, rgb, depth, K, masks, obj_ids)
        return invalidate_implausible(verified)

    def estimator(self, *, seed: int = 0, generator: torch.Generator | None = None) -> Estimator:
        """This model as an :data:`~poseflow.eval.predict.Estimator` of :func:`predict_dataset`.

        Inputs are moved to the network's device; one generator serves all calls: ``generator``
        (on the network's device), e.g. to be reseeded per image, or a new one seeded ``seed``,
        so that a sequence of images gives the same estimates on every run.
        """
        device = next(self.net.parameters()).device
        if generator is None:
            generator = torch.Generator(device=device).manual_seed(seed)
        return on_device(functools.partial(self.estimate, generator=generator), device)

    def predict(
        self,
        dataset: str | Path | Any,
        *,
        split: str = "test",
        targets: Sequence[Any] | None = None,
        detections: Sequence[Any] | None = None,
        max_images: int | None = None,
        seed: int = 0,
        timer: StageTimer | None = None,
        progress: bool = False,
    ) -> PoseResults:
        """Estimate every target instance of a BOP split; see :func:`poseflow.eval.predict_dataset`.

        Args:
            dataset: the dataset folder or a :class:`~poseflow.data.bop.BOPDataset`.
            split: the split folder.
            targets: :class:`~poseflow.eval.recall.Target` records to estimate (default: the
                split's ``test_targets_bop19.json`` when present, else every instance).
            detections: masks from a BOP segmentation file instead of the ground truth.
            max_images: stop after this many images.
            seed: seeds the noise, sampling and RANSAC: each image's draws come from ``seed`` and
                its ids (:func:`~poseflow.eval.distributed.image_seed`), as in ``poseflow
                predict``, so an image's estimate does not depend on the images before it.
            timer: optional :class:`~poseflow.eval.timing.StageTimer`, active while each image
                is estimated.
            progress: show a progress bar.

        Returns:
            :class:`~poseflow.eval.results.PoseResults`, one row per valid estimate.
        """
        return predict_seeded(
            lambda generator: self.estimator(generator=generator),
            next(self.net.parameters()).device,
            dataset,
            object_ids=sorted(self.objects),
            split=split,
            targets=targets,
            detections=detections,
            max_images=max_images,
            seed=seed,
            timer=timer,
            progress=progress,
        )

    def save(self, folder: str | Path) -> Path:
        """Write ``config.json`` and ``model.safetensors`` (trainable weights only)."""
        return write_checkpoint(folder, self.config, self.net.state_dict())

    @classmethod
    def load(cls, folder: str | Path, *, device: str | torch.device = "cpu") -> FunFlow6D:
        """Load a model written by :meth:`save` (no pickle is ever read).

        Raises:
            MissingWeightsError: ``folder`` holds no checkpoint.
            CheckpointError: a file of the checkpoint is truncated, corrupt or of the wrong
                type, or the weights do not fit the configuration (the file is named).
        """
        config, state = read_checkpoint(folder)
        model = cls(config)
        try:
            model.net.load_state_dict(state)
        except RuntimeError as exc:
            lines = str(exc).strip().splitlines()  # a title, then one line per problem
            detail = (lines[1] if len(lines) > 1 else lines[0]).strip()[:200]
            raise CheckpointError(
                f"{Path(folder) / 'model.safetensors'} does not fit its config.json ({detail}); "
                "restore the pair or train again"
            ) from None
        return model.to(device)


def predict_seeded(
    make_estimator: Callable[[torch.Generator], Estimator],
    device: torch.device | str,
    dataset: str | Path | Any,
    *,
    object_ids: Sequence[int],
    seed: int,
    **options: Any,
) -> PoseResults:
    """:func:`~poseflow.eval.predict_dataset` with one generator reseeded before each image.

    Each image's draws come from ``seed`` and its ids
    (:func:`~poseflow.eval.distributed.image_seed`), as in ``poseflow predict``, so that an
    image's estimate does not depend on the images before it.

    Args:
        make_estimator: builds the estimator that draws from the given generator.
        device: the generator's device.
        dataset: the dataset folder or a :class:`~poseflow.data.bop.BOPDataset`.
        object_ids: the objects to estimate.
        seed: the run's seed.
        options: more keyword arguments of :func:`~poseflow.eval.predict_dataset`.
    """
    from poseflow.eval.distributed import image_seed

    generator = torch.Generator(device=device)

    def reseed(scene_id: int, im_id: int) -> None:
        generator.manual_seed(image_seed(seed, scene_id, im_id))

    return predict_dataset(
        make_estimator(generator), dataset, object_ids=object_ids, before_image=reseed, **options
    )
