"""Point-to-point ICP, single- and multi-scale, batched over instances.

Each iteration pairs every valid source point (moved by the current estimate) with its nearest
valid target point, keeps the pairs closer than ``max_correspondence_distance`` and re-solves
Procrustes on them (the centroids and cross-covariance in float64). Instances stop
independently: an instance whose fitness and inlier RMSE both change less than
``relative_fitness`` and ``relative_rmse`` (Open3D's criteria) is frozen while the others go on.
The iterations at one distance run in :mod:`poseflow.registration._icp_loop`: an early-exit loop
of compiled passes on the CPU, fixed masked steps captured as CUDA graphs on CUDA.
"""

from __future__ import annotations

import itertools
import math
import numbers
from collections.abc import Sequence

import torch

from poseflow._api import Solver
from poseflow.errors import ValueRangeError
from poseflow.registration._icp_loop import (
    ICPProblem,
    Scale,
    ScaleState,
    run_scale,
    run_scale_fixed,
)
from poseflow.registration._threads import serial_cpu_ops
from poseflow.registration.result import RegistrationResult

__all__ = ["ICP", "MultiScaleICP", "icp", "multi_scale_icp"]


def icp(
    source: torch.Tensor,
    target: torch.Tensor,
    init: torch.Tensor | None = None,
    *,
    max_correspondence_distance: float,
    max_iterations: int = 30,
    relative_fitness: float = 1e-6,
    relative_rmse: float = 1e-6,
    source_mask: torch.Tensor | None = None,
    target_mask: torch.Tensor | None = None,
) -> RegistrationResult:
    """Refine the rigid transform mapping ``source`` onto ``target`` by point-to-point ICP.

    Same algorithm, defaults and stopping rule as Open3D's ``registration_icp`` with
    ``TransformationEstimationPointToPoint``, batched: every iteration re-solves Procrustes on
    the current nearest-neighbour pairs within ``max_correspondence_distance``, and an instance
    stops when both its fitness and inlier RMSE change by less than ``relative_fitness`` and
    ``relative_rmse`` (or after ``max_iterations`` updates).

    Args:
        source: source cloud, shape ``(B, N, 3)``.
        target: target cloud, shape ``(B, M, 3)``, same device and dtype (``M`` may differ).
        init: initial transforms ``(B, 4, 4)`` (source to target); identity by default.
        max_correspondence_distance: pairs farther apart than this are ignored.
        max_iterations: transform updates per instance, at most.
        relative_fitness: convergence threshold on the change of fitness.
        relative_rmse: convergence threshold on the change of inlier RMSE.
        source_mask: optional ``(B, N)`` bool, True for source points to use.
        target_mask: optional ``(B, M)`` bool, True for target points that may be matched.

    Returns:
        A :class:`~poseflow.registration.result.RegistrationResult` evaluated at the final
        transforms: ``inliers`` marks the source points with a target point within
        ``max_correspondence_distance``. Instances with fewer than 3 such pairs (at the start
        or the end), or whose pairs are collinear, get ``valid = False`` and the identity; so
        does an instance whose target has no valid point (``M = 0``, or ``target_mask`` all
        False).

    Raises:
        ShapeError: wrong shapes, mismatched devices or dtypes, non-bool masks.
        ValueRangeError: NaN/inf at valid points or in ``init``, or a hyper-parameter out of
            range.

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> cloud = torch.rand(2, 400, 3, generator=g)
        >>> result = icp(cloud, cloud + 0.02, max_correspondence_distance=0.1)
        >>> result.transformation[:, :3, 3]
        tensor([[0.0200, 0.0200, 0.0200],
                [0.0200, 0.0200, 0.0200]])
    """
    _check_distance(max_correspondence_distance, "max_correspondence_distance")
    _check_iterations(max_iterations)
    relative = _check_relative(relative_fitness, relative_rmse)
    scales = [Scale(float(max_correspondence_distance), max_iterations, *relative)]
    return _register(source, target, init, source_mask, target_mask, scales)


def multi_scale_icp(
    source: torch.Tensor,
    target: torch.Tensor,
    init: torch.Tensor | None = None,
    *,
    max_correspondence_distances: Sequence[float],
    max_iterations: int | Sequence[int] = 30,
    relative_fitness: float = 1e-6,
    relative_rmse: float = 1e-6,
    source_mask: torch.Tensor | None = None,
    target_mask: torch.Tensor | None = None,
) -> RegistrationResult:
    """Coarse-to-fine point-to-point ICP over decreasing correspondence distances.

    Runs :func:`icp` once per distance, from the coarsest (widest basin of convergence) to the
    finest (most accurate), each scale starting where the previous one ended; the target's search
    structure is built once. An instance with fewer than 3 pairs at some scale keeps its previous
    estimate for the next scale. The result is that of the last scale, with ``num_iterations``
    summed over the scales.

    Args:
        source: source cloud, shape ``(B, N, 3)``.
        target: target cloud, shape ``(B, M, 3)``.
        init: initial transforms ``(B, 4, 4)``; identity by default.
        max_correspondence_distances: one distance per scale, non-increasing.
        max_iterations: transform updates per scale: one int for all, or one per scale.
        relative_fitness: convergence threshold on the change of fitness, at every scale.
        relative_rmse: convergence threshold on the change of inlier RMSE, at every scale.
        source_mask: optional ``(B, N)`` bool, True for source points to use.
        target_mask: optional ``(B, M)`` bool, True for target points that may be matched.

    Returns:
        A :class:`~poseflow.registration.result.RegistrationResult` as :func:`icp` returns it,
        measured with the finest distance.

    Raises:
        ShapeError: wrong shapes, mismatched devices or dtypes, non-bool masks.
        ValueRangeError: NaN/inf at valid points, distances not positive or not coarse-to-fine,
            or a hyper-parameter out of range.

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> cloud = torch.rand(1, 400, 3, generator=g)
        >>> result = multi_scale_icp(cloud, cloud + 0.05, max_correspondence_distances=[0.2, 0.05])
        >>> result.transformation[0, :3, 3]
        tensor([0.0500, 0.0500, 0.0500])
    """
    distances, iterations = _check_scales(max_correspondence_distances, max_iterations)
    relative = _check_relative(relative_fitness, relative_rmse)
    scales = [Scale(d, it, *relative) for d, it in zip(distances, iterations)]
    return _register(source, target, init, source_mask, target_mask, scales)


def _register(
    source: torch.Tensor,
    target: torch.Tensor,
    init: torch.Tensor | None,
    source_mask: torch.Tensor | None,
    target_mask: torch.Tensor | None,
    scales: Sequence[Scale],
) -> RegistrationResult:
    """ICP over checked scales, coarse to fine."""
    with serial_cpu_ops(source):
        problem = ICPProblem.make(source, target, init, source_mask, target_mask)
        T, counts = problem.init, []
        for scale in scales[:-1]:
            state = _scale(problem, T, scale)
            counts.append(state.iterations)
            # An instance that found too few pairs at this scale keeps its previous estimate.
            T = torch.where(state.valid[:, None, None], state.T, T)
        state = _scale(problem, T, scales[-1])
        for count in counts:
            state.iterations += count
        return problem.result(state)


class ICP(Solver[RegistrationResult]):
    """Point-to-point ICP solver: stores the hyper-parameters, registers when called.

    ``ICP(**hyper)(source, target, init, source_mask=..., target_mask=...)`` is
    :func:`icp` with those hyper-parameters; see it for the algorithm, arguments and result.

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> cloud = torch.rand(1, 300, 3, generator=g)
        >>> result = ICP(max_correspondence_distance=0.2)(cloud, cloud + 0.01)
        >>> result.transformation[0, :3, 3]
        tensor([0.0100, 0.0100, 0.0100])
    """

    function = staticmethod(icp)

    def __init__(
        self,
        *,
        max_correspondence_distance: float,
        max_iterations: int = 30,
        relative_fitness: float = 1e-6,
        relative_rmse: float = 1e-6,
    ) -> None:
        _check_distance(max_correspondence_distance, "max_correspondence_distance")
        _check_iterations(max_iterations)
        self.max_correspondence_distance = float(max_correspondence_distance)
        self.max_iterations = max_iterations
        self.relative_fitness, self.relative_rmse = _check_relative(relative_fitness, relative_rmse)


class MultiScaleICP(Solver[RegistrationResult]):
    """Coarse-to-fine point-to-point ICP solver; calling it runs :func:`multi_scale_icp`.

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> cloud = torch.rand(1, 300, 3, generator=g)
        >>> solver = MultiScaleICP(max_correspondence_distances=[0.3, 0.1, 0.03])
        >>> solver(cloud, cloud + 0.02).transformation[0, :3, 3]
        tensor([0.0200, 0.0200, 0.0200])
    """

    function = staticmethod(multi_scale_icp)

    def __init__(
        self,
        *,
        max_correspondence_distances: Sequence[float],
        max_iterations: int | Sequence[int] = 30,
        relative_fitness: float = 1e-6,
        relative_rmse: float = 1e-6,
    ) -> None:
        self.max_correspondence_distances, self.max_iterations = _check_scales(
            max_correspondence_distances, max_iterations
        )
        self.relative_fitness, self.relative_rmse = _check_relative(relative_fitness, relative_rmse)


def _scale(problem: ICPProblem, T: torch.Tensor, scale: Scale) -> ScaleState:
    """One scale of ICP: the early-exit loop on the CPU, fixed masked steps elsewhere."""
    if T.device.type == "cpu":
        return run_scale(problem, T, scale)
    return run_scale_fixed(problem, T, scale, capture=T.device.type == "cuda")


def _check_distance(value: float, name: str) -> None:
    if not (isinstance(value, numbers.Real) and math.isfinite(value) and value > 0):
        raise ValueRangeError(f"{name} must be finite and > 0, got {value!r}")


def _check_iterations(value: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueRangeError(f"max_iterations must be an int >= 1, got {value!r}")


def _check_scales(
    max_correspondence_distances: Sequence[float], max_iterations: int | Sequence[int]
) -> tuple[list[float], list[int]]:
    """The scales' distances (floats, coarse to fine) and iterations, one per scale, checked."""
    distances = [float(d) for d in max_correspondence_distances]
    if not distances:
        raise ValueRangeError("max_correspondence_distances must not be empty")
    for d in distances:
        _check_distance(d, "max_correspondence_distances")
    if any(b > a for a, b in itertools.pairwise(distances)):
        raise ValueRangeError(
            f"max_correspondence_distances must go from coarse to fine (non-increasing), "
            f"got {distances}"
        )
    if isinstance(max_iterations, int) and not isinstance(max_iterations, bool):
        iterations = [max_iterations] * len(distances)
    else:
        iterations = list(max_iterations)
        if len(iterations) != len(distances):
            raise ValueRangeError(
                f"max_iterations has {len(iterations)} entries for {len(distances)} scales"
            )
    for it in iterations:
        _check_iterations(it)
    return distances, iterations


def _check_relative(relative_fitness: float, relative_rmse: float) -> tuple[float, float]:
    """The two convergence thresholds as floats, checked to be >= 0."""
    if not (relative_fitness >= 0 and relative_rmse >= 0):
        raise ValueRangeError(
            f"relative_fitness and relative_rmse must be >= 0, got {relative_fitness}, "
            f"{relative_rmse}"
        )
    return float(relative_fitness), float(relative_rmse)
