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

import contextlib
from collections.abc import Iterator, Mapping
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch
from torch import nn

from poseflow._units import check_depth_extent
from poseflow.data.frame import ImageInstances
from poseflow.data.objects import ObjectModel
from poseflow.detect import DetectedObjects, Detector
from poseflow.errors import CheckpointError, MissingWeightsError, ValueRangeError
from poseflow.eval.predict import PoseEstimate, SeededEstimator, invalidate_implausible
from poseflow.eval.timing import stage
from poseflow.features import AppearanceEncoder, GeometricEncoder
from poseflow.models.checkpoint import read_checkpoint, write_checkpoint
from poseflow.models.components import (
    build_appearance_encoder,
    build_geometric_encoder,
    encoder_networks,
)
from poseflow.models.config import FunFlow6DConfig
from poseflow.models.inputs import FlowInputs
from poseflow.models.network import FunFlow6DNet, NetInputs
from poseflow.models.objects import PreparedObject, prepare_objects, select_objects
from poseflow.models.observe import Observation, observe
from poseflow.models.proposals import flow_proposals, no_proposals
from poseflow.models.verification import Proposals, prepare_verification, verify_proposals
from poseflow.verify import PoseVerifier

__all__ = ["FunFlow6D"]


class FunFlow6D(nn.Module, SeededEstimator):
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
        self.geometric_encoder, self.appearance_encoder, self.net = _build_parts(cfg)
        #: The detector of the model's objects (``MODEL_DIR/detector``), or None.
        self.detector: Detector | None = None
        self.objects: dict[int, PreparedObject] = {}
        self.verifier = PoseVerifier(cfg.verifier)

    def _apply(self, fn: Any, recurse: bool = True) -> FunFlow6D:
        """``.to()``, ``.cuda()``, ``.double()``, ...: the frozen encoders' networks move too.

        They are not submodules: their weights stay in their own folders, out of
        ``state_dict()``, the training checkpoints and the EMA (they never change).
        """
        super()._apply(fn, recurse)
        encoders = encoder_networks(
            geometric=self.geometric_encoder, appearance=self.appearance_encoder
        )
        for network in encoders.values():
            network._apply(fn, recurse)
        return self

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
            cache_dir: where prepared objects are stored and looked up, one entry per object,
                mesh and configuration (:func:`~poseflow.models.objects.object_cache_entry`);
                None computes everything in memory.
            progress: show a progress bar.
        """
        prepared = prepare_objects(
            models, self.config, geometric_encoder=self.geometric_encoder,
            appearance_encoder=self.appearance_encoder, cache_dir=cache_dir, progress=progress,
        )  # fmt: skip
        self.objects.update(prepared)
        if self.config.verifier is not None:
            if self.verifier.config != self.config.verifier:
                self.verifier = PoseVerifier(self.config.verifier)
            prepare_verification(self.verifier, models, cache_dir=cache_dir, progress=progress)

    @torch.no_grad()
    def observe(
        self,
        image: ImageInstances,
        *,
        generator: torch.Generator | None = None,
        crop_jitter: float = 0.0,
        appearance_precision: str = "fp32",
    ) -> Observation:
        """The target clouds of an image: :func:`~poseflow.models.observe.observe`.

        Args:
            image: the image and its ``B`` instances, as :meth:`estimate` takes them one by one;
                without masks (``B = 0``) the observation is empty.
            generator: seeds the dense-cloud cap and the farthest-point sampling; None: a
                generator seeded 0.
            crop_jitter: training augmentation of the appearance crop; 0 at inference.
            appearance_precision: what a network appearance encoder computes in (inference:
                ``config.appearance_precision``; the training set's features: float32).

        Raises:
            ShapeError: inconsistent shapes, or ``K`` not 9 numbers.
            ValueRangeError: an object id that is not prepared, or a ``K`` that is not a pinhole
                matrix of this image.
        """
        diameters = [o.diameter for o in select_objects(self.objects, image.obj_ids)]
        if generator is None:
            generator = torch.Generator(device=image.depth.device).manual_seed(0)
        return observe(
            *image, diameters,
            num_points=self.config.num_points, dense_points=self.config.dense_points,
            geometric_encoder=self.geometric_encoder, appearance_encoder=self.appearance_encoder,
            geometric_support_voxel=self.config.geometric_support_voxel,
            generator=generator, crop_jitter=crop_jitter, appearance_precision=appearance_precision,
        )  # fmt: skip

    def flow_inputs(self, obs: Observation, poses: torch.Tensor | None = None) -> FlowInputs:
        """The :class:`FlowInputs` of an observation (with ``x_1`` when poses are given)."""
        return FlowInputs.from_observation(
            obs,
            select_objects(self.objects, obs.obj_ids),
            poses,
            query_pooling=getattr(self.appearance_encoder, "query_pooling", "mean"),
        )

    def forward(
        self, *, x: torch.Tensor, t: torch.Tensor, x_0: torch.Tensor, **inputs: torch.Tensor
    ) -> torch.Tensor:
        """``Ψ(t, X(t) | C)`` ``(B, 2N, 3)``; ``inputs`` are named as :class:`NetInputs`' fields.

        The model plugs into :class:`~poseflow.flows.CFMTrainer`; :meth:`velocity` is the same.
        """
        return self.net(x=x, t=t, inputs=NetInputs.from_kwargs(inputs), x_0=x_0)

    velocity = forward

    def _estimate(self, image: ImageInstances, generator: torch.Generator | None) -> PoseEstimate:
        """:meth:`propose`, then, with ``config.verifier`` set, :meth:`verify`.

        The verifier's ICP registers the observation's cleaned cloud and its scores become the
        estimate's. Raises, besides :meth:`estimate`'s errors, ValueRangeError for a verifier
        prepared for another ``config.verifier``.
        """
        proposals = self.propose(image, generator=generator)
        if proposals.estimate.poses.shape[0] == 0:
            return proposals.estimate
        est = proposals.estimate if self.config.verifier is None else self.verify(proposals, image)
        return replace(est, agreement=self.agreement(proposals, est.poses, image.obj_ids))

    def agreement(self, proposals: Proposals, poses: torch.Tensor, obj_ids: object) -> torch.Tensor:
        """``(B,)`` the share of the flow's proposals that agree with the chosen ``poses``.

        :meth:`Proposals.agreement <poseflow.models.verification.Proposals.agreement>` with
        the prepared objects' query clouds and diameters.
        """
        objects = [self.objects[int(o)] for o in torch.as_tensor(obj_ids).reshape(-1).tolist()]
        points = torch.stack([o.points for o in objects]).to(poses.device)  # (B, N, 3)
        diameters = torch.tensor([o.diameter for o in objects], device=poses.device)
        return proposals.agreement(poses, points, diameters)

    @torch.no_grad()
    def propose(
        self, image: ImageInstances, *, generator: torch.Generator | None = None
    ) -> Proposals:
        """The flow's poses of every instance of one image, before verification.

        Samples ``config.num_hypotheses`` flows per instance and solves each for a pose; the
        best by the solver's score is the incumbent, and with
        ``config.verifier.rank_hypotheses`` the others are candidates that the verifier ranks
        (:class:`Proposals` with ``rank`` on). Arguments as :meth:`estimate`'s, the image's
        five as one :class:`~poseflow.data.ImageInstances`.

        Returns:
            :class:`~poseflow.models.verification.Proposals` of the ``B`` instances, with the
            observation's cleaned clouds for the verifier's ICP.
        """
        image = _checked_image(self, image)
        if generator is None:
            generator = torch.Generator(device=image.depth.device).manual_seed(0)
        with _evaluating(self):
            obs = self.observe(
                image, generator=generator, appearance_precision=self.config.appearance_precision
            )
            if obs.points.shape[0] == 0:
                return no_proposals(image.depth.device)
            with stage("flow_inputs"):
                inputs = self.flow_inputs(obs)
            return flow_proposals(self.net, inputs, obs, self.objects, self.config, generator)

    def verify(self, proposals: Proposals, image: ImageInstances) -> PoseEstimate:
        """Choose and verify each instance's pose among ``proposals`` with :attr:`verifier`.

        :func:`~poseflow.models.verification.verify_proposals`; ``image`` as :meth:`propose`'s.

        Raises:
            ValueRangeError: an object the verifier has not prepared.
        """
        verified = verify_proposals(self.verifier, proposals, image.checked(torch.float32))
        return invalidate_implausible(verified)

    def _object_ids(self) -> list[int]:
        return sorted(self.objects)

    @property
    def device(self) -> torch.device:
        """The device of the network's weights."""
        return next(self.net.parameters()).device

    @torch.no_grad()
    def detect(self, rgb: torch.Tensor, depth: torch.Tensor, K: torch.Tensor) -> DetectedObjects:
        """The instances of the model's objects in one image, by :attr:`detector`.

        ``found = model.detect(rgb, depth, K)`` then ``model.estimate(rgb, depth, K,
        found.masks, found.obj_ids)`` estimates an image that comes without masks.

        Raises:
            MissingWeightsError: the model has no detector.
        """
        if self.detector is None:
            raise MissingWeightsError(
                "this model has no detector: train one with `poseflow train-detector "
                "SYNTH_DATASET --out MODEL_DIR/detector` and load the model again"
            )
        return self.detector.detect(rgb, depth, K)

    def save(self, folder: str | Path) -> Path:
        """Write ``config.json``, ``model.safetensors`` (trainable weights), any ``detector/``."""
        out = write_checkpoint(folder, self.config, self.net.state_dict())
        if self.detector is not None:
            self.detector.save(Path(folder) / "detector")
        return out

    @classmethod
    def load(cls, folder: str | Path, *, device: str | torch.device = "cpu") -> FunFlow6D:
        """Load a model written by :meth:`save` (no pickle is ever read), with its detector.

        Raises:
            MissingWeightsError: ``folder`` holds no checkpoint.
            CheckpointError: a file of the checkpoint is truncated, corrupt or of the wrong
                type, or the weights do not fit the configuration (the file is named).
        """
        config, state = read_checkpoint(folder)
        model = cls(config)
        _load_weights(model.net, state, Path(folder) / "model.safetensors")
        if (Path(folder) / "detector").is_dir():
            model.detector = Detector.load(Path(folder) / "detector")
        return model.to(device)


def _checked_image(model: FunFlow6D, image: ImageInstances) -> ImageInstances:
    """``image`` checked in float32 (:meth:`~poseflow.data.ImageInstances.checked`).

    The model's verifier and the masked depth's extent are checked too.

    Raises:
        ValueRangeError: ``config.verifier`` changed since the objects were prepared for it, an
            object id that is not prepared, or a ``K`` that is not a pinhole matrix of the image.
        UnitsError: the masked depth spans far more or far less than the objects.
    """
    if model.config.verifier is not None and model.verifier.config != model.config.verifier:
        raise ValueRangeError(
            "config.verifier changed after the objects were prepared for verification; "
            "call prepare_objects again"
        )
    image = image.checked(torch.float32)
    diameters = [o.diameter for o in select_objects(model.objects, image.obj_ids)]
    with stage("lifting"):  # the check back-projects every mask
        check_depth_extent(image.depth, image.K, image.masks, diameters, where="the depth")
    return image


@contextlib.contextmanager
def _evaluating(module: nn.Module) -> Iterator[None]:
    """``module`` in evaluation mode, then back in the mode it was in."""
    was_training = module.training
    module.eval()
    try:
        yield
    finally:
        module.train(was_training)


def _build_parts(
    config: FunFlow6DConfig,
) -> tuple[GeometricEncoder | None, AppearanceEncoder | None, FunFlow6DNet]:
    """The frozen encoders of ``config`` and the network for the widths of their descriptors.

    The semantic width is the reducer's output, or the raw appearance features' without
    reduction; None without an encoder.
    """
    geometric = build_geometric_encoder(config.geometric_encoder, radii=config.geometric_radii)
    appearance = build_appearance_encoder(config.appearance_encoder, crop_size=config.crop_size)
    semantic_dim = None
    if appearance is not None:
        semantic_dim = appearance.dim if config.reducer == "identity" else config.feature_dim
    net_config = config.net_config(getattr(geometric, "dim", None), semantic_dim)
    return geometric, appearance, FunFlow6DNet(net_config)


def _load_weights(net: nn.Module, state: dict[str, torch.Tensor], path: Path) -> None:
    """Load ``state`` into ``net``, or say which weight of the file ``path`` does not fit.

    Raises:
        CheckpointError: the weights do not fit the network.
    """
    try:
        net.load_state_dict(state)
    except RuntimeError as exc:
        lines = str(exc).strip().splitlines()  # a title, then one line per problem
        detail = (lines[1] if len(lines) > 1 else lines[0]).strip()[:200]
        raise CheckpointError(
            f"{path} does not fit its config.json ({detail}); restore the pair or train again"
        ) from None
