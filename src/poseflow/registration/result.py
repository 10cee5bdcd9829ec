"""The record every registration solver returns."""

from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["RegistrationResult"]


@dataclass
class RegistrationResult:
    """Batched outcome of a registration solver; every field follows the inputs' device.

    The transformation maps the source onto the target (``target ≈ R @ source + t``), as in
    Open3D. An instance whose data was hopeless (fewer than 3 valid pairs, no consensus, only
    collinear points) has ``valid = False``, the identity transformation, ``fitness = 0``,
    ``inlier_rmse = 0`` and no inliers: never NaN.

    Attributes:
        transformation: ``(B, 4, 4)`` rigid transforms, source to target, in the inputs' dtype.
        fitness: ``(B,)`` fraction of the *valid* source points that are inliers, in ``[0, 1]``
            (Open3D divides by all source points; masked points do not count here).
        inlier_rmse: ``(B,)`` root mean square distance of the inlier pairs (0 without inliers).
        inliers: ``(B, N)`` bool, the source points within the correspondence distance under
            ``transformation``.
        num_iterations: ``(B,)`` int64, iterations each instance actually ran (RANSAC: hypotheses
            drawn before the confidence was reached; ICP: transform updates; summed over scales
            for multi-scale ICP).
        valid: ``(B,)`` bool, False where the data was hopeless (see above).
    """

    transformation: torch.Tensor
    fitness: torch.Tensor
    inlier_rmse: torch.Tensor
    inliers: torch.Tensor
    num_iterations: torch.Tensor
    valid: torch.Tensor

    def __len__(self) -> int:
        return self.transformation.shape[0]
