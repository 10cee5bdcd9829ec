"""Configuration of the render-and-compare verifier: one typed field per choice."""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from poseflow._checks import check_field_types
from poseflow._config import config_from_dict, config_to_dict
from poseflow.errors import ValueRangeError

__all__ = ["VerifierConfig"]


#: The int fields of :class:`VerifierConfig` by their least value.
_INT_MINIMA: dict[int, tuple[str, ...]] = {
    0: ("max_candidates", "rank_top_k", "refine_top_k", "polish_levels"),
    1: ("block_size", "search_top_k", "icp_iterations", "polish_moves", "expand_top_k"),
    2: ("turn_steps",),
    3: ("appearance_window", "max_observed_points"),
    8: ("crop_size", "coarse_crop_size"),
    16: ("num_points",),
}


@dataclass(frozen=True)
class VerifierConfig:
    """Hyper-parameters of :class:`~poseflow.verify.PoseVerifier`.

    Lengths are fractions of the object's diameter unless named otherwise, so one configuration
    fits objects of every size.

    Args:
        num_points: surface points per object for rendering and as the ICP target.
        crop_size: side ``S`` of the square grid on which renderings and the observation are
            compared, in pixels.
        coarse_crop_size: side of the grid on which all candidates are first scored, to pick
            the ones refined by ICP and scored on the full grid.
        crop_margin: side of the compared crop over the object's projected diameter at the
            estimate's depth (1 fits the whole object).
        depth_tolerance: a rendered pixel agrees with the observed depth when they differ by less
            than this (VSD's tau).
        visibility_tolerance: a rendered pixel farther than the observed depth by more than this
            is hidden by something else and not compared (VSD's delta).
        occlusion_tolerance: a rendered point farther than the nearest point of its 3 x 3 pixel
            neighbourhood by more than this is a back surface seen through a gap of the sampling.
        appearance_window: side of the window of the local normalised cross-correlation, in
            crop pixels (odd).
        contrast_reference: relative contrast (standard deviation over mean) of the rendered
            colour in a window at which the window's correlation gets full weight; flatter
            windows get proportionally less.
        depth_weight: weight of the depth agreement in the total.
        silhouette_weight: weight of the silhouette IoU in the total.
        appearance_weight: weight of the appearance agreement in the total.
        block_size: side, in crop pixels, of the blocks over which the evidence of two
            hypotheses is compared by the selection test.
        significance: false-replacement rate of the selection test: a candidate replaces the
            estimate only where its gain exceeds what the blocks' own spread gives by chance at
            this level (Bonferroni-corrected over the candidates).
        max_candidates: most near-symmetry candidates kept per object (the most self-similar).
        min_self_overlap: a rotation of the model is a near-symmetry when at least this fraction
            of its points land within ``self_overlap_distance`` of the model after self-ICP.
        self_overlap_distance: see ``min_self_overlap``.
        min_candidate_angle: candidates closer than this (degrees, modulo the declared
            symmetries) to the identity or to a kept candidate are dropped.
        turn_steps: turns about each principal axis tried as near-symmetry seeds (every
            ``360 / turn_steps`` degrees); half-turns about axes perpendicular to each principal
            axis are tried every ``360 / turn_steps`` degrees too.
        rank_top_k: hypotheses of an instance that
            :meth:`~poseflow.verify.PoseVerifier.rank_hypotheses` scores again on the full grid,
            the best of its coarse scoring (the coarse grid barely resolves a thin part such as
            a mug's handle); 0 or 1 ranks on the coarse grid alone. Off by default: it helped a
            mug as much as it cost a printed cylinder (``benchmarks/LOG.md``).
        rank_hypotheses: an estimator that solves several hypotheses per instance (FunFlow6D's
            ``num_hypotheses``) gives them all to the verifier: its coarse score picks the one
            expanded with near-symmetric candidates, and the others are candidates
            (:meth:`~poseflow.verify.PoseVerifier.rank_hypotheses`); False verifies the
            estimator's own pick alone. The classic baseline has one pose per instance.
        refine_top_k: candidates (besides the estimate) refined by ICP and scored again, the best
            of the first, unrefined scoring.
        expand_top_k: hypotheses of an instance expanded with their near-symmetric candidates,
            the best of the verifier's ranking
            (:meth:`~poseflow.verify.PoseVerifier.rank_hypotheses`, which then orders them all
            by its score); 1 expands the estimate alone. Three gave no more AR than one on four
            models (``benchmarks/LOG.md``).
        search_below: a valid instance whose chosen pose scores below this is searched globally
            (:meth:`~poseflow.verify.PoseVerifier.search`): the pose turned by the
            :func:`~poseflow.verify.box_turns` and slid by ``search_slides``, the best
            ``search_top_k`` of them refined by
            ICP, one replacing the pose where it clearly explains the image better (the same
            test as the candidates'); 0 searches nothing. A wrong pose (a bunny upside down)
            scores well below a right one, which rarely scores under 0.45 (the estimators'
            tenth percentile on devbench).
        search_top_k: turned poses of a searched instance refined by ICP and scored again, the
            best of their coarse scoring.
        search_slides: a searched pose is also slid along each principal axis of its object by
            these fractions of its extent, either way (:func:`~poseflow.verify.box_slides`):
            an object seen only in part, placed centred on what is seen, is tried with the seen
            part elsewhere along it; empty slides nothing.
        refine_estimate: refine the estimate by the same ICP as the candidates before they are
            compared, so that they compete on equal terms (an estimator's own refinement may
            have used fewer points); the estimate is then returned refined where it is kept.
        icp_distances: ICP correspondence distances of the refinement, coarse to fine.
        icp_iterations: ICP iterations per scale, at most.
        icp_relative_rmse: a scale of ICP stops once its inlier RMSE changes by less than this
            (a fraction of the diameter) and its inlier count no longer changes.
        max_observed_points: the observed cloud is thinned to at most this many points for ICP.
        polish_levels: step sizes of the final pattern search of the chosen poses' full-grid
            score (:meth:`~poseflow.verify.PoseScorer.polish`), each half the previous; 0
            polishes nothing.
        polish_moves: moves of a pose per step size, at most.
        polish_rotation: the first turns of the search, in degrees, about the camera's axes
            through the model's origin.
        polish_translation: the first shifts of the search along the camera's axes, a fraction
            of the diameter.

    The refinement's defaults (20 iterations per scale on 600 observed points) are measured
    against fewer in ``benchmarks/LOG.md``.
    """

    num_points: int = 4096
    crop_size: int = 64
    coarse_crop_size: int = 32
    crop_margin: float = 1.2
    depth_tolerance: float = 0.03
    visibility_tolerance: float = 0.1
    occlusion_tolerance: float = 0.1
    appearance_window: int = 5
    contrast_reference: float = 0.1
    depth_weight: float = 1.0
    silhouette_weight: float = 1.0
    appearance_weight: float = 1.0
    block_size: int = 8
    significance: float = 0.05
    max_candidates: int = 12
    min_self_overlap: float = 0.6
    self_overlap_distance: float = 0.03
    min_candidate_angle: float = 15.0
    turn_steps: int = 12
    rank_top_k: int = 0
    rank_hypotheses: bool = True
    refine_top_k: int = 2
    expand_top_k: int = 1
    search_below: float = 0.45
    search_top_k: int = 4
    search_slides: tuple[float, ...] = (0.25, 0.5)
    refine_estimate: bool = True
    icp_distances: tuple[float, ...] = (0.1, 0.05, 0.02)
    icp_iterations: int = 20
    icp_relative_rmse: float = 1e-4
    max_observed_points: int = 600
    polish_levels: int = 4
    polish_moves: int = 3
    polish_rotation: float = 4.0
    polish_translation: float = 0.02

    def __post_init__(self) -> None:
        check_field_types(self)
        for low, names in _INT_MINIMA.items():
            for name in names:
                value = getattr(self, name)
                if isinstance(value, bool) or not isinstance(value, int) or value < low:
                    raise ValueRangeError(f"{name} must be an int >= {low}, got {value!r}")
        if self.appearance_window % 2 == 0:
            raise ValueRangeError(f"appearance_window must be odd, got {self.appearance_window}")
        if self.crop_size % self.block_size or self.coarse_crop_size % self.block_size:
            raise ValueRangeError(
                f"block_size ({self.block_size}) must divide crop_size ({self.crop_size}) and "
                f"coarse_crop_size ({self.coarse_crop_size})"
            )
        if self.coarse_crop_size > self.crop_size:
            raise ValueRangeError(
                f"coarse_crop_size ({self.coarse_crop_size}) must not exceed crop_size "
                f"({self.crop_size})"
            )
        positive = (
            "crop_margin",
            "depth_tolerance",
            "visibility_tolerance",
            "occlusion_tolerance",
            "contrast_reference",
            "self_overlap_distance",
            "icp_relative_rmse",
            "polish_rotation",
            "polish_translation",
        )
        for name in positive:
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueRangeError(f"{name} must be finite and > 0, got {value!r}")
        weights = (self.depth_weight, self.silhouette_weight, self.appearance_weight)
        if not all(math.isfinite(w) and w >= 0 for w in weights) or not sum(weights) > 0:
            raise ValueRangeError(f"the weights must be >= 0 and not all 0, got {weights}")
        below = self.search_below
        if isinstance(below, bool) or not (isinstance(below, int | float) and 0 <= below <= 1):
            raise ValueRangeError(f"search_below must lie in [0, 1], got {self.search_below!r}")
        if not 0 < self.significance < 1:
            raise ValueRangeError(f"significance must lie in (0, 1), got {self.significance}")
        if not 0 < self.min_self_overlap <= 1:
            raise ValueRangeError(
                f"min_self_overlap must lie in (0, 1], got {self.min_self_overlap}"
            )
        if not 0 <= self.min_candidate_angle < 180:
            raise ValueRangeError(
                f"min_candidate_angle must lie in [0, 180), got {self.min_candidate_angle}"
            )
        slides = tuple(float(f) for f in self.search_slides)
        if not all(0 < f <= 1 for f in slides):
            raise ValueRangeError(f"search_slides must lie in (0, 1], got {self.search_slides}")
        object.__setattr__(self, "search_slides", slides)
        distances = tuple(float(d) for d in self.icp_distances)
        if not distances or not all(math.isfinite(d) and d > 0 for d in distances):
            raise ValueRangeError(f"icp_distances must be positive, got {self.icp_distances}")
        if any(b > a for a, b in itertools.pairwise(distances)):
            raise ValueRangeError(f"icp_distances must go coarse to fine, got {distances}")
        object.__setattr__(self, "icp_distances", distances)

    def to_dict(self) -> dict[str, Any]:
        """The fields as a JSON-ready dict.

        Example:
            >>> VerifierConfig().to_dict()["crop_size"]
            64
        """
        return config_to_dict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> VerifierConfig:
        """Build a configuration from :meth:`to_dict`'s output, checking every name.

        Raises:
            ValueRangeError: an unknown field or a value out of range.

        Example:
            >>> VerifierConfig.from_dict({"crop_size": 48, "block_size": 8}).crop_size
            48
        """
        return config_from_dict(cls, data)
