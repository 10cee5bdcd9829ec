"""The configuration of :class:`~poseflow.models.FunFlow6D`, its network and its ablations.

Frozen, typed dataclasses all the way down, each read and written by ``from_dict`` /
``to_dict``, one field per choice:

- :class:`FunFlow6DConfig`: the method, from the frozen encoders to the pose solver, with
- :class:`NetOptions` (its ``net`` field): the free sizes of the trainable network, with
- :class:`DiTOverrides` (``net.dit``): the fields of the DiT preset to change, and
- :class:`~poseflow.verify.VerifierConfig` (``verifier``): the render-and-compare verification.

:func:`apply_overrides` changes fields by dotted keys (``{"verifier.rank_top_k": 4}``), merging
into the nested configurations; :meth:`FunFlow6DConfig.with_inference` does so for a trained
model's inference settings (:data:`INFERENCE_FIELDS`) only. :data:`RECIPES` names the
configurations the recipe trains (``FunFlow6DConfig.recipe("learned_small")``);
``configs/NAME.json`` in the checkout are written from it by
``python -m poseflow.models --write-configs configs``.

Lengths are fractions of the object's diameter throughout (``ransac_distance``,
``icp_distances``, the verifier's); the registration functions they are passed to take
``max_correspondence_distance(s)`` in the points' own unit.

:class:`NetConfig` is the complete description of
:class:`~poseflow.models.network.FunFlow6DNet`: the :class:`NetOptions` plus what the method
fixes (descriptor widths, fused width, fusion variant, DiT preset).

Every named choice is checked against its registry when the configuration is built (an unknown
name raises :class:`~poseflow.errors.ValueRangeError` listing the allowed ones), so that each row
of the paper's ablation table is a valid configuration (:data:`ABLATIONS`) that
``benchmarks/ablation.py`` can rerun.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from poseflow._checks import check_field_types
from poseflow._config import apply_overrides, config_from_dict, config_to_dict
from poseflow.errors import MissingFileError, ValueRangeError
from poseflow.flows import PRECISIONS, PRESETS, SAMPLERS, TIME_SAMPLERS
from poseflow.flows.dit import AttentionMode, PointDiTConfig
from poseflow.fusion import FUSIONS
from poseflow.models.components import (
    APPEARANCE_ENCODERS,
    GEOMETRIC_ENCODERS,
    REDUCERS,
    check_name,
)
from poseflow.verify import VerifierConfig

__all__ = [
    "ABLATIONS",
    "ANCHORS",
    "INFERENCE_FIELDS",
    "POSE_SOLVERS",
    "RECIPES",
    "REMOVED_OPTIONS",
    "RENAMED_FIELDS",
    "DiTOverrides",
    "FunFlow6DConfig",
    "NetConfig",
    "NetOptions",
    "apply_overrides",
    "read_config_fields",
    "write_recipes",
]

#: Names of :attr:`FunFlow6DConfig.pose_solver`.
POSE_SOLVERS: tuple[str, ...] = ("ransac", "svd")
#: Names of :attr:`FunFlow6DConfig.anchor`.
ANCHORS: tuple[str, ...] = ("pinned",)


@dataclass(frozen=True, kw_only=True)
class DiTOverrides:
    """Fields of the DiT preset's :class:`~poseflow.flows.dit.PointDiTConfig` to change.

    None keeps the preset's value. The condition width ``cond_dim`` is not a choice: it is
    always ``D + d_P`` (fused plus positional channels).

    Attributes:
        hidden_dim: model width ``E``.
        depth: number of DiT blocks.
        num_heads: attention heads; must divide ``hidden_dim``.
        mlp_ratio: width of each block's MLP relative to ``E``.
        attention: ``"global"`` or ``"alternating"``.
        time_frequency_dim: channels of the sinusoidal time features.
        time_scale: factor applied to ``t`` before the sinusoids.

    Example:
        >>> dit = DiTOverrides(hidden_dim=64, depth=2)
        >>> dit.to_dict()
        {'hidden_dim': 64, 'depth': 2}
        >>> dit.resolve("small", cond_dim=96).num_heads  # the preset's
        4
    """

    hidden_dim: int | None = None
    depth: int | None = None
    num_heads: int | None = None
    mlp_ratio: float | None = None
    attention: AttentionMode | None = None
    time_frequency_dim: int | None = None
    time_scale: float | None = None

    def __post_init__(self) -> None:
        """Check the fields' types."""
        check_field_types(self)

    def resolve(self, preset: str, *, cond_dim: int) -> PointDiTConfig:
        """The preset's configuration with these fields changed and ``cond_dim`` set.

        Raises:
            ValueRangeError: an unknown preset, or values the DiT does not accept.
        """
        check_name("dit_preset", preset, tuple(PRESETS))
        return dataclasses.replace(PRESETS[preset], **self.to_dict(), cond_dim=cond_dim)

    def to_dict(self) -> dict[str, Any]:
        """The fields that are set (not None)."""
        return {k: v for k, v in config_to_dict(self).items() if v is not None}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> DiTOverrides:
        """Build from :meth:`to_dict`'s dict; unknown keys are an error."""
        return config_from_dict(cls, data)


@dataclass(frozen=True, kw_only=True)
class NetOptions:
    """The free sizes of the trainable network (the rest follows from the method's choices).

    Attributes:
        fusion_heads: attention heads of the fusion block (paper: 4).
        dropout: dropout of the fusion block (paper: 0.1).
        posenc_dim: positional channels ``d_P``.
        posenc_frequencies: octaves of the sinusoidal embedding of each attribute.
        dit: changes to the DiT preset (a mapping is read with :meth:`DiTOverrides.from_dict`).
    """

    fusion_heads: int = 4
    dropout: float = 0.1
    posenc_dim: int = 64
    posenc_frequencies: int = 6
    dit: DiTOverrides = field(default_factory=DiTOverrides)

    def __post_init__(self) -> None:
        """Read a mapping ``dit``; validate the types and sizes."""
        check_field_types(self)
        if isinstance(self.dit, Mapping):
            object.__setattr__(self, "dit", DiTOverrides.from_dict(self.dit))
        if not isinstance(self.dit, DiTOverrides):
            raise ValueRangeError(f"dit must be a DiTOverrides, got {type(self.dit).__name__}")
        if self.fusion_heads < 1 or self.posenc_dim < 1 or self.posenc_frequencies < 0:
            raise ValueRangeError(
                "fusion_heads and posenc_dim must be >= 1 and posenc_frequencies >= 0"
            )
        if not 0.0 <= self.dropout < 1.0:
            raise ValueRangeError(f"dropout must be in [0, 1), got {self.dropout}")

    def to_dict(self) -> dict[str, Any]:
        """The options as a JSON-serialisable dict."""
        return config_to_dict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> NetOptions:
        """Build from :meth:`to_dict`'s dict; unknown keys are an error."""
        return config_from_dict(cls, data)


@dataclass(frozen=True, kw_only=True)
class NetConfig(NetOptions):
    """Everything :class:`~poseflow.models.network.FunFlow6DNet` is built from.

    The :class:`NetOptions` fields, and:

    Attributes:
        geometric_dim: channels ``Dg`` of the frozen geometric descriptors.
        semantic_dim: channels ``Ds`` of the (reduced) semantic descriptors.
        feature_dim: fused channels ``D`` (paper: 64). A stream whose width differs from ``D``
            goes through a learned linear adapter first.
        fusion: a name of :data:`~poseflow.fusion.FUSIONS` (``"gated"`` is the paper's).
        dit_preset: a name of :data:`~poseflow.flows.PRESETS`.
        noise_conditioning: the positional encoder reads each point's noise ``X(0)``
            (False: zeros in its place); see :attr:`FunFlow6DConfig.noise_conditioning`.
    """

    geometric_dim: int = 64
    semantic_dim: int = 64
    feature_dim: int = 64
    fusion: str = "gated"
    dit_preset: str = "small"
    noise_conditioning: bool = True

    def __post_init__(self) -> None:
        """Validate the names and the DiT it describes."""
        super().__post_init__()
        check_name("fusion", self.fusion, tuple(FUSIONS))
        if min(self.geometric_dim, self.semantic_dim, self.feature_dim) < 1:
            raise ValueRangeError("geometric_dim, semantic_dim and feature_dim must be >= 1")
        self.dit_config()

    def dit_config(self) -> PointDiTConfig:
        """The DiT's configuration: the preset, the overrides and ``cond_dim = D + d_P``."""
        return self.dit.resolve(self.dit_preset, cond_dim=self.feature_dim + self.posenc_dim)


@dataclass(frozen=True, kw_only=True)
class FunFlow6DConfig:
    """What FunFlow6D is made of, from the frozen encoders to the pose solver.

    The defaults are the offline ones; the configuration the recipe trains is
    :meth:`recipe` (``"learned_small"``, or ``"demo_small"`` of the shipped checkpoint), which
    samples 24 hypotheses of one midpoint step (``learned_small``) or 12 at Euler 4
    (``demo_small``) where the defaults sample 1 in 50 Euler steps.

    Attributes:
        num_points: points ``N`` of the query cloud and of every target cloud (the flow state has
            ``2N`` points).
        dense_points: a target's back-projected cloud is first cut to a random subset of at most
            this many points (outlier removal and farthest-point sampling then run on it).
        geometric_encoder: ``"fpfh"`` (multi-scale FPFH, weight-free), ``"gedi:PATH"`` (GeDi
            weights from a local file) or ``"none"``.
        geometric_radii: FPFH/GeDi radii as fractions of the diameter (paper: 0.30 and 0.40).
        geometric_support_voxel: the geometric descriptors of the ``N`` points take their
            neighbourhoods from a denser cloud of the same surface, thinned on a grid of this
            many diameters (the target's cleaned back-projected cloud, the object's surface
            sample; see :func:`~poseflow.features.encode_on_support`); 0: from the ``N`` points
            alone, as checkpoints written before the field did.
        appearance_encoder: ``"dsift"`` (dense SIFT, weight-free), ``"dinov2:NAME_OR_PATH"``
            (e.g. ``dinov2:vits14`` or a local folder), ``"learned"`` / ``"learned:FOLDER"``
            (poseflow's own descriptor network, see :mod:`poseflow.features.learned`) or
            ``"none"``.
        crop_size: side of the square crop fed to the appearance encoder, pixels.
        query_views: viewpoints of the query's multi-view rendering.
        reducer: ``"umap"`` (paper), ``"pca"`` or ``"identity"``, fitted on the query features.
        feature_dim: fused channels ``D`` (paper: 64); also the reducer's output size.
        fusion: ``"gated"`` (paper), ``"cross"``, ``"concat_mlp"`` or ``"sum"``.
        dit_preset: ``"paper"``, ``"small"`` or ``"tiny"``.
        anchor: ``"pinned"`` (the only value): the query sits at its canonical coordinates
            along the whole path in training and sampling (see :data:`REMOVED_OPTIONS`).
        noise_conditioning: give each point's noise coordinates ``X(0)`` to the positional
            encoder, as the paper does. With them, ``X(1) - X(0) = (X(t) - X(0)) / t`` can be read
            off the input for ``t > 0``, so training concentrates on small ``t``; False replaces
            them by zeros (both are measured in ``benchmarks/LOG.md``).
        time_sampler: training-time distribution, ``"uniform"`` (the paper's and the only
            value; see :data:`~poseflow.flows.TIME_SAMPLERS` and :data:`REMOVED_OPTIONS`).
        solver: ODE solver (``"euler"`` is the paper's, also ``"midpoint"``, ``"heun"``,
            ``"rk4"``).
        steps: integration steps ``K`` (paper: 50).
        flow_precision: what the DiT computes in while sampling: ``"auto"`` (bfloat16 where
            the device multiplies it natively, else float32; see
            :func:`~poseflow.flows.autocast_dtype`), ``"bf16"``, ``"fp16"`` or ``"fp32"``
            (the same poses on every machine; checkpoints written before the field read so).
        appearance_precision: what the appearance encoder computes an image's features in,
            when it is a network (the learned descriptor, DINOv2): the same names as
            ``flow_precision``; the objects' view features and the training set's stay float32.
        num_hypotheses: noise samples per instance; the pose with the best score is kept.
        match_hypothesis: with a surface embedding as the appearance encoder
            (``"surface:FOLDER"``, which describes every surface point), one more hypothesis
            per instance: each target point paired with the dense surface point whose key its
            descriptor matches best, solved and verified like a flow sample
            (:func:`~poseflow.models.proposals.surface_match_positions`). No effect with other
            encoders.
        pose_solver: ``"ransac"`` (RANSAC-Procrustes, paper) or ``"svd"`` (one Procrustes on all
            correspondences).
        ransac_iterations: RANSAC hypotheses (paper: 1,000).
        ransac_distance: RANSAC inlier distance, a fraction of the diameter.
        icp_distances: coarse-to-fine ICP correspondence distances, fractions of the diameter;
            empty: no ICP.
        icp_iterations: ICP iterations per distance.
        verifier: check each chosen pose by rendering and comparing
            (:class:`~poseflow.verify.PoseVerifier`) with this configuration, None for no check:
            its near-symmetric candidates (and, with ``verifier.rank_hypotheses``, the other
            hypotheses) replace it only where they clearly explain the image better, and the
            verifier's score becomes the estimate's score. Training-free, so it applies to any
            checkpoint; a checkpoint whose ``config.json`` predates verification loads with None
            (see :data:`~poseflow.models.checkpoint.CHECKPOINT_FIELDS_ADDED`). A mapping is read
            with :meth:`VerifierConfig.from_dict`.
        net: the free sizes of the trainable network (a mapping is read with
            :meth:`NetOptions.from_dict`).

    Raises:
        ValueRangeError: an unknown name (the message lists the allowed ones), a value of the
            wrong type (the message names the field, its type and the value) or a bad value.
    """

    num_points: int = 256
    dense_points: int = 4096
    geometric_encoder: str = "fpfh"
    geometric_radii: tuple[float, ...] = (0.30, 0.40)
    geometric_support_voxel: float = 0.04
    appearance_encoder: str = "dsift"
    crop_size: int = 128
    query_views: int = 20
    reducer: str = "pca"
    feature_dim: int = 64
    fusion: str = "gated"
    dit_preset: str = "small"
    anchor: str = "pinned"
    noise_conditioning: bool = True
    time_sampler: str = "uniform"
    solver: str = "euler"
    steps: int = 50
    flow_precision: str = "auto"
    appearance_precision: str = "auto"
    num_hypotheses: int = 1
    match_hypothesis: bool = True
    pose_solver: str = "ransac"
    ransac_iterations: int = 1000
    ransac_distance: float = 0.05
    icp_distances: tuple[float, ...] = (0.08, 0.04, 0.02)
    icp_iterations: int = 30
    verifier: VerifierConfig | None = field(default_factory=VerifierConfig)
    net: NetOptions = field(default_factory=NetOptions)

    def __post_init__(self) -> None:
        """Validate the types (once, against the annotations) and the choices."""
        check_field_types(self)
        object.__setattr__(self, "geometric_radii", tuple(float(r) for r in self.geometric_radii))
        object.__setattr__(self, "icp_distances", tuple(float(d) for d in self.icp_distances))
        if isinstance(self.net, Mapping):
            object.__setattr__(self, "net", NetOptions.from_dict(self.net))
        if isinstance(self.verifier, Mapping):
            object.__setattr__(self, "verifier", VerifierConfig.from_dict(self.verifier))
        for name, allowed, takes_argument in (
            ("geometric_encoder", GEOMETRIC_ENCODERS, True),
            ("appearance_encoder", APPEARANCE_ENCODERS, True),
            ("reducer", REDUCERS, False),
            ("fusion", tuple(FUSIONS), False),
            ("dit_preset", tuple(PRESETS), False),
            ("anchor", ANCHORS, False),
            ("time_sampler", tuple(TIME_SAMPLERS), False),
            ("solver", tuple(SAMPLERS), False),
            ("pose_solver", POSE_SOLVERS, False),
            ("flow_precision", (*PRECISIONS, "auto"), False),
            ("appearance_precision", (*PRECISIONS, "auto"), False),
        ):
            check_name(name, getattr(self, name), allowed, takes_argument=takes_argument)
        if self.num_points < 8:
            raise ValueRangeError(f"num_points must be at least 8, got {self.num_points}")
        if self.dense_points < self.num_points:
            raise ValueRangeError(
                f"dense_points ({self.dense_points}) must be at least num_points "
                f"({self.num_points})"
            )
        if not 0.0 <= self.geometric_support_voxel < 0.5:
            raise ValueRangeError(
                f"geometric_support_voxel must be in [0, 0.5), got {self.geometric_support_voxel}"
            )
        if self.steps < 1 or self.num_hypotheses < 1 or self.ransac_iterations < 1:
            raise ValueRangeError("steps, num_hypotheses and ransac_iterations must be >= 1")
        if self.geometric_encoder == "none" and self.appearance_encoder == "none":
            raise ValueRangeError("at least one of the geometric and appearance encoders is needed")
        self.net.dit.resolve(self.dit_preset, cond_dim=self.feature_dim + self.net.posenc_dim)

    @classmethod
    def recipe(cls, name: str) -> FunFlow6DConfig:
        """The named configuration of :data:`RECIPES` (what ``configs/NAME.json`` holds).

        Raises:
            ValueRangeError: an unknown name; the message lists the known ones.

        Example:
            >>> cfg = FunFlow6DConfig.recipe("learned_small")
            >>> cfg.appearance_encoder, cfg.num_hypotheses, cfg.solver, cfg.steps
            ('learned', 24, 'midpoint', 1)
        """
        check_name("recipe", name, tuple(RECIPES))
        return cls.from_dict(RECIPES[name])

    @classmethod
    def load(cls, source: str | Path) -> FunFlow6DConfig:
        """A named configuration (:meth:`recipe`) or a JSON file of fields (:meth:`from_dict`).

        Raises:
            MissingFileError: ``source`` is neither a name of :data:`RECIPES` nor a file.
            ValueRangeError: the file is not a JSON object of valid fields.
        """
        if str(source) in RECIPES:
            return cls.recipe(str(source))
        path = Path(source)
        if not path.is_file():
            raise MissingFileError(
                f"{path}: no such file, nor a recipe name ({', '.join(sorted(RECIPES))})"
            )
        return cls.from_dict(read_config_fields(path))

    def replace(self, **changes: Any) -> FunFlow6DConfig:
        """A copy with whole fields replaced (validated again); :func:`apply_overrides` merges."""
        return dataclasses.replace(self, **changes)

    def with_inference(
        self, overrides: Mapping[str, Any] | None = None, /, **changes: Any
    ) -> FunFlow6DConfig:
        """A copy with inference settings changed: what a trained model may change.

        Args:
            overrides: ``{key: value}`` merged by :func:`apply_overrides`; a key is a field of
                :data:`INFERENCE_FIELDS` or, with dots, a field below one
                (``"verifier.rank_top_k"``).
            changes: more overrides as keywords, applied after ``overrides``.

        Raises:
            ValueRangeError: a key outside :data:`INFERENCE_FIELDS` (the message lists them),
                or a value the configuration does not accept.

        Example:
            >>> cfg = FunFlow6DConfig.recipe("demo_small")
            >>> cfg = cfg.with_inference({"verifier.rank_top_k": 4}, steps=8)
            >>> cfg.steps, cfg.verifier.rank_top_k, cfg.num_points
            (8, 4, 64)
            >>> try:
            ...     cfg.with_inference(num_points=32)
            ... except ValueRangeError as e:
            ...     print(str(e).split(";")[0])
            num_points: not an inference setting
        """
        changes = {**(overrides or {}), **changes}
        fixed = sorted({key.split(".")[0] for key in changes} - set(INFERENCE_FIELDS))
        if fixed:
            raise ValueRangeError(
                f"{', '.join(fixed)}: not an inference setting; a trained model can change only "
                f"{', '.join(INFERENCE_FIELDS)}"
            )
        return apply_overrides(self, changes)

    def net_config(self, geometric_dim: int | None, semantic_dim: int | None) -> NetConfig:
        """The network's configuration for descriptors of the given widths.

        Args:
            geometric_dim: width of the geometric descriptors, None without an encoder.
            semantic_dim: width of the (reduced) semantic descriptors, None without an encoder.
                A missing stream is fed the other one's descriptors, so it takes its width.
        """
        if geometric_dim is None:
            geometric_dim = semantic_dim
        if semantic_dim is None:
            semantic_dim = geometric_dim
        if geometric_dim is None or semantic_dim is None:
            raise ValueRangeError("the network needs the width of at least one descriptor")
        options = {f.name: getattr(self.net, f.name) for f in dataclasses.fields(NetOptions)}
        return NetConfig(
            **options,
            geometric_dim=geometric_dim,
            semantic_dim=semantic_dim,
            feature_dim=self.feature_dim,
            fusion=self.fusion,
            dit_preset=self.dit_preset,
            noise_conditioning=self.noise_conditioning,
        )

    def to_dict(self) -> dict[str, Any]:
        """The configuration as a JSON-serialisable dict."""
        return config_to_dict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> FunFlow6DConfig:
        """Build from :meth:`to_dict`'s dict; unknown keys are an error.

        Files written by older versions load as they were meant, silently (checkpoints are
        data): the keys of :data:`RENAMED_FIELDS` under their new names, ``verification: false``
        as ``verifier: null``, ``verify_hypotheses`` as ``verifier.rank_hypotheses``, the
        network options of files from before they were typed, and the options of
        :data:`REMOVED_OPTIONS` at the value every configuration now has.

        Raises:
            ValueRangeError: an unknown key, a bad value, or a removed option set to another
                value than the kept one (the message names the option).
        """
        return config_from_dict(cls, _upgrade(data))


#: Options removed from the configuration, by dotted key, with the value every configuration now
#: has: a field removed (``net.soft_match``, measured and not adopted) or a field whose other
#: values were removed (never measured). A file that holds one at this value loads as before
#: (a removed field is dropped); another value raises :class:`~poseflow.errors.ValueRangeError`
#: naming the option. ``benchmarks/LOG.md`` ("2026-12-07: configuration options removed") says
#: why, and names the last commit that had them.
REMOVED_OPTIONS: dict[str, Any] = {
    "net.soft_match": False,
    "anchor": "pinned",
    "time_sampler": "uniform",
}

#: The last commit whose configuration had the options of :data:`REMOVED_OPTIONS`.
_REMOVED_AFTER = "4448b08"


#: Keys of configuration files written before a field was renamed, and the field they are read
#: as (checkpoints on disk keep their ``config.json``).
RENAMED_FIELDS: dict[str, str] = {
    "ransac_threshold": "ransac_distance",
    "icp_thresholds": "icp_distances",
}


def read_config_fields(path: Path) -> dict[str, Any]:
    """The configuration fields of a JSON file, not yet checked (:meth:`FunFlow6DConfig.from_dict`).

    Raises:
        ValueRangeError: the file is not valid JSON, or not a JSON object.
    """
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueRangeError(f"{path} is not valid JSON: {exc}") from None
    if not isinstance(data, dict):
        raise ValueRangeError(f"{path} must hold a JSON object of config fields")
    return data


def _upgrade(data: Mapping[str, Any]) -> dict[str, Any]:
    """The keys of older configuration files read as they were meant, silently.

    - :data:`RENAMED_FIELDS` are read under their new names;
    - ``verification: false`` is ``verifier: null``; ``verification: true`` keeps ``verifier``
      (its default when absent); ``verify_hypotheses`` is ``verifier.rank_hypotheses``;
    - a ``fusion`` or ``dit_preset`` inside ``net`` (which then overrode the top-level field)
      becomes the top-level field, and a ``cond_dim`` inside ``net.dit`` (always replaced by
      ``D + d_P``) is dropped;
    - an option of :data:`REMOVED_OPTIONS` at its kept value is dropped if its field was
      removed; at another value it raises :class:`~poseflow.errors.ValueRangeError`.
    """
    data = dict(data)
    for old, new in RENAMED_FIELDS.items():
        if old in data:
            data.setdefault(new, data.pop(old))
    if "verification" in data or "verify_hypotheses" in data:
        verify = data.pop("verification", True)
        rank = data.pop("verify_hypotheses", None)
        if not isinstance(verify, bool):
            raise ValueRangeError(f"verification must be true or false, got {verify!r}")
        verifier = data.get("verifier")
        if isinstance(verifier, VerifierConfig):
            verifier = verifier.to_dict()
        verifier = dict(verifier or {})
        if rank is not None:
            verifier["rank_hypotheses"] = rank
        data["verifier"] = verifier if verify else None
    if isinstance(data.get("net"), Mapping):
        net = dict(data["net"])
        for name in ("fusion", "dit_preset"):
            if name in net:
                data[name] = net.pop(name)
        if isinstance(net.get("dit"), Mapping):
            net["dit"] = {k: v for k, v in net["dit"].items() if k != "cond_dim"}
        data["net"] = net
    return _drop_removed(data)


def _drop_removed(data: dict[str, Any]) -> dict[str, Any]:
    """``data`` without the removed fields of :data:`REMOVED_OPTIONS` (at their kept value).

    Raises:
        ValueRangeError: a removed option at another value than the kept one.
    """
    for key, kept in REMOVED_OPTIONS.items():
        *parents, name = key.split(".")
        holder: Any = data
        for parent in parents:  # _upgrade made data["net"] a dict of its own
            holder = holder.get(parent) if isinstance(holder, dict) else None
        if not isinstance(holder, dict) or name not in holder:
            continue
        if holder[name] != kept:
            raise ValueRangeError(
                f"{key}={holder[name]!r}: this option was removed (only {kept!r} remains; see "
                f"benchmarks/LOG.md, 2026-12-07); a model trained with it needs poseflow at "
                f"commit {_REMOVED_AFTER} or earlier"
            )
        cls = NetOptions if parents else FunFlow6DConfig
        if name not in {f.name for f in dataclasses.fields(cls)}:
            del holder[name]
    return data


#: Fields a trained model may change at inference: the sampler and its precision, the hypotheses,
#: the pose solver, the verifier and the dense-cloud cap (the network and its feature sizes stay
#: valid). Changed through :meth:`FunFlow6DConfig.with_inference`.
INFERENCE_FIELDS: tuple[str, ...] = (
    "solver",
    "steps",
    "flow_precision",
    "appearance_precision",
    "num_hypotheses",
    "match_hypothesis",
    "dense_points",
    "pose_solver",
    "ransac_iterations",
    "ransac_distance",
    "icp_distances",
    "icp_iterations",
    "verifier",
)

_SMALL: dict[str, Any] = {
    "num_points": 64,
    "crop_size": 96,
    "query_views": 12,
    "dit_preset": "small",
    "net": {
        "dit": {"hidden_dim": 64, "num_heads": 4, "depth": 4, "time_frequency_dim": 64},
        "posenc_dim": 32,
        "posenc_frequencies": 4,
    },
    "noise_conditioning": False,
    "num_hypotheses": 12,
    "steps": 4,
}

#: The named configurations, as changes of the defaults (:meth:`FunFlow6DConfig.recipe`):
#: ``demo_small``, the shipped demo checkpoint's (dense SIFT), and ``learned_small``, the recipe
#: for new objects (poseflow's learned appearance descriptors). ``configs/NAME.json`` are
#: written from them (:func:`write_recipes`).
RECIPES: dict[str, dict[str, Any]] = {
    "demo_small": _SMALL,
    # one midpoint step (two network evaluations per hypothesis, half of Euler 4's): the same AR
    # on both new-object sets of benchmarks/RESULTS.md in half the network time; 24 hypotheses
    # (of 12): +0.009 AR on average over seven trained models of the two sets (one −0.002), for
    # 0.1 s per image; an instance draws 300 RANSAC samples per hypothesis and the verifier
    # searches the turns of its best two candidates
    "learned_small": {
        **_SMALL,
        "num_hypotheses": 24,
        "appearance_encoder": "learned",
        "solver": "midpoint",
        "steps": 1,
        "ransac_iterations": 300,
        "verifier": {"search_top_k": 2},
    },
}


def write_recipes(folder: str | Path) -> list[Path]:
    """Write each of :data:`RECIPES` to ``folder/NAME.json``; the paths written."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, changes in RECIPES.items():
        path = folder / f"{name}.json"
        path.write_text(json.dumps(changes, indent=1) + "\n")
        paths.append(path)
    return paths


#: The paper's ablation table (rows 3-8) in terms of the components poseflow ships. Rows differ
#: only in what is named here; encoders come from the base configuration a script passes in.
ABLATIONS: dict[str, dict[str, Any]] = {
    "3_pca_sum": {"reducer": "pca", "fusion": "sum"},
    "4_umap_sum": {"reducer": "umap", "fusion": "sum"},
    "5_umap_concat_mlp": {"reducer": "umap", "fusion": "concat_mlp"},
    "6_umap_cross": {"reducer": "umap", "fusion": "cross"},
    "7_umap_gated_no_icp": {"reducer": "umap", "fusion": "gated", "icp_distances": ()},
    "8_umap_gated": {"reducer": "umap", "fusion": "gated"},
}
