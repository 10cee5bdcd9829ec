"""The JSON-serialisable configuration of :class:`~poseflow.models.FunFlow6D` and its ablations.

Every part of the method is named by a string, so that each row of the paper's ablation table is a
configuration (:data:`ABLATIONS`) and ``benchmarks/ablation.py`` can rerun it.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from poseflow.errors import ValueRangeError
from poseflow.models.network import NetConfig

__all__ = ["ABLATIONS", "INFERENCE_FIELDS", "FunFlow6DConfig"]

_SOLVERS = ("ransac", "svd")
_ANCHORS = ("pinned", "noise")


@dataclass(kw_only=True)
class FunFlow6DConfig:
    """What FunFlow6D is made of, from the frozen encoders to the pose solver.

    Attributes:
        num_points: points ``N`` of the query cloud and of every target cloud (the flow state has
            ``2N`` points).
        dense_points: a target's back-projected cloud is first cut to a random subset of at most
            this many points (outlier removal and farthest-point sampling then run on it).
        geometric_encoder: ``"fpfh"`` (multi-scale FPFH, weight-free), ``"gedi:PATH"`` (GeDi
            weights from a local file) or ``"none"``.
        geometric_radii: FPFH/GeDi radii as fractions of the diameter (paper: 0.30 and 0.40).
        appearance_encoder: ``"dsift"`` (dense SIFT, weight-free), ``"dinov2:NAME_OR_PATH"``
            (e.g. ``dinov2:vits14`` or a local folder) or ``"none"``.
        crop_size: side of the square crop fed to the appearance encoder, pixels.
        query_views: viewpoints of the query's multi-view rendering.
        reducer: ``"umap"`` (paper), ``"pca"`` or ``"identity"``, fitted on the query features.
        feature_dim: fused channels ``D`` (paper: 64); also the reducer's output size.
        fusion: ``"gated"`` (paper), ``"cross"``, ``"concat_mlp"`` or ``"sum"``.
        dit_preset: ``"paper"``, ``"small"`` or ``"tiny"``.
        anchor: ``"pinned"``: the query sits at its canonical coordinates along the whole path
            in training and sampling; ``"noise"``: the paper's equations read literally (the
            anchor is interpolated in training and stays at its noise sample in sampling).
        noise_conditioning: give each point's noise coordinates ``X(0)`` to the positional
            encoder, as the paper does. With them, ``X(1) - X(0) = (X(t) - X(0)) / t`` can be read
            off the input for ``t > 0``, so training concentrates on small ``t``; False replaces
            them by zeros (see ``benchmarks/RESULTS.md`` for both).
        time_sampler: training-time distribution (``"uniform"`` is the paper's).
        solver: ODE solver (``"euler"`` is the paper's, also ``"midpoint"``, ``"heun"``,
            ``"rk4"``).
        steps: integration steps ``K`` (paper: 50).
        num_hypotheses: noise samples per instance; the pose with the best score is kept.
        pose_solver: ``"ransac"`` (RANSAC-Procrustes, paper) or ``"svd"`` (one Procrustes on all
            correspondences).
        ransac_iterations: RANSAC hypotheses (paper: 1,000).
        ransac_threshold: RANSAC inlier distance, fraction of the diameter.
        icp_thresholds: coarse-to-fine ICP distances, fractions of the diameter; empty: no ICP.
        icp_iterations: ICP iterations per threshold.
        net: sizes of the trainable network (derived fields are filled in by the model).
    """

    num_points: int = 256
    dense_points: int = 4096
    geometric_encoder: str = "fpfh"
    geometric_radii: tuple[float, ...] = (0.30, 0.40)
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
    num_hypotheses: int = 1
    pose_solver: str = "ransac"
    ransac_iterations: int = 1000
    ransac_threshold: float = 0.05
    icp_thresholds: tuple[float, ...] = (0.08, 0.04, 0.02)
    icp_iterations: int = 30
    net: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        """Validate the choices."""
        self.geometric_radii = tuple(float(r) for r in self.geometric_radii)
        self.icp_thresholds = tuple(float(r) for r in self.icp_thresholds)
        if self.num_points < 8:
            raise ValueRangeError(f"num_points must be at least 8, got {self.num_points}")
        if self.dense_points < self.num_points:
            raise ValueRangeError(
                f"dense_points ({self.dense_points}) must be at least num_points "
                f"({self.num_points})"
            )
        if self.pose_solver not in _SOLVERS:
            raise ValueRangeError(
                f"pose_solver must be one of {_SOLVERS}, got {self.pose_solver!r}"
            )
        if self.anchor not in _ANCHORS:
            raise ValueRangeError(f"anchor must be one of {_ANCHORS}, got {self.anchor!r}")
        if self.steps < 1 or self.num_hypotheses < 1 or self.ransac_iterations < 1:
            raise ValueRangeError("steps, num_hypotheses and ransac_iterations must be >= 1")
        if self.geometric_encoder == "none" and self.appearance_encoder == "none":
            raise ValueRangeError("at least one of the geometric and appearance encoders is needed")

    def replace(self, **changes: Any) -> FunFlow6DConfig:
        """A copy with some fields changed."""
        return dataclasses.replace(self, **changes)

    def net_config(self, *, geometric_dim: int, semantic_dim: int) -> NetConfig:
        """The network sizes for descriptors of the given widths."""
        base = {
            "geometric_dim": geometric_dim,
            "semantic_dim": semantic_dim,
            "feature_dim": self.feature_dim,
            "fusion": self.fusion,
            "dit_preset": self.dit_preset,
        }
        return NetConfig(**{**base, **self.net})

    def to_json(self) -> dict[str, Any]:
        """The configuration as a JSON-serialisable dict."""
        out = dataclasses.asdict(self)
        out["geometric_radii"] = list(self.geometric_radii)
        out["icp_thresholds"] = list(self.icp_thresholds)
        return out

    @classmethod
    def from_json(cls, data: dict[str, Any] | str | Path) -> FunFlow6DConfig:
        """Build from :meth:`to_json`'s dict or a JSON file; unknown keys are an error."""
        if not isinstance(data, dict):
            data = json.loads(Path(data).read_text())
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ValueRangeError(f"unknown FunFlow6D config keys: {unknown}")
        return cls(**data)


#: Fields a trained model may change at inference: the sampler, the hypotheses, the pose solver
#: and the dense-cloud cap (the network and its feature sizes stay valid).
INFERENCE_FIELDS: tuple[str, ...] = (
    "solver",
    "steps",
    "num_hypotheses",
    "dense_points",
    "pose_solver",
    "ransac_iterations",
    "ransac_threshold",
    "icp_thresholds",
    "icp_iterations",
)


#: The paper's ablation table (rows 3-8) in terms of the components poseflow ships. Rows differ
#: only in what is named here; encoders come from the base configuration a script passes in.
ABLATIONS: dict[str, dict[str, Any]] = {
    "3_pca_sum": {"reducer": "pca", "fusion": "sum"},
    "4_umap_sum": {"reducer": "umap", "fusion": "sum"},
    "5_umap_concat_mlp": {"reducer": "umap", "fusion": "concat_mlp"},
    "6_umap_cross": {"reducer": "umap", "fusion": "cross"},
    "7_umap_gated_no_icp": {"reducer": "umap", "fusion": "gated", "icp_thresholds": ()},
    "8_umap_gated": {"reducer": "umap", "fusion": "gated"},
}
