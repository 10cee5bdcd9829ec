"""Weighted orthogonal Procrustes (Kabsch, and Umeyama with scaling), batched and differentiable."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from poseflow._api import Solver
from poseflow._checks import check_mask, check_same, check_tensor
from poseflow.errors import ValueRangeError

__all__ = [
    "Procrustes",
    "ProcrustesResult",
    "check_pairs",
    "is_well_posed",
    "procrustes",
    "procrustes_moments",
    "rigid_from_svd",
    "solve_procrustes",
    "svd3x3",
    "zero_masked_points",
]


class ProcrustesResult(NamedTuple):
    """What :func:`procrustes` returns: the transforms and which instances were solvable.

    Unpacks as ``T, valid = procrustes(...)``.

    Attributes:
        transformation: ``(B, 4, 4)`` transforms mapping source to target, in the inputs' dtype;
            the identity where ``valid`` is False.
        valid: ``(B,)`` bool, False where the problem has no unique solution (fewer than 3
            pairs of positive weight, collinear or coincident points).
    """

    transformation: torch.Tensor
    valid: torch.Tensor


def procrustes(
    source: torch.Tensor,
    target: torch.Tensor,
    weights: torch.Tensor | None = None,
    mask: torch.Tensor | None = None,
    *,
    with_scaling: bool = False,
) -> torch.Tensor:
    """Rigid (or similarity) transform that best maps ``source`` onto ``target`` in least squares.

    Minimises ``sum_i w_i |c R s_i + t - d_i|^2`` over rotations ``R`` (``det R = +1``: reflections
    are never returned), translations ``t`` and, with ``with_scaling``, a scale ``c > 0``
    (Umeyama); otherwise ``c = 1`` (Kabsch). The SVD of the 3×3 cross-covariance runs in float64
    whatever the input dtype, and gradients flow to ``source``, ``target`` and ``weights``
    (they are undefined where two singular values coincide, e.g. symmetric point sets).

    An instance with fewer than 3 points of positive weight, or whose points are (numerically)
    collinear or coincident, has no unique solution: it gets the identity and ``valid = False``.
    Centroids and centred points are computed in float64, so a cloud far from the origin (float32
    coordinates in kilometres) is solved as well as one near it.

    Args:
        source: source points, shape ``(B, N, 3)``.
        target: corresponding target points, shape ``(B, N, 3)``, same device and dtype.
        weights: optional non-negative weights, shape ``(B, N)``; all ones by default.
        mask: optional ``(B, N)`` bool, True for pairs to use. Masked pairs may hold NaN.
        with_scaling: also estimate a uniform scale; the returned ``(B, 4, 4)`` then holds
            ``c R`` in its upper-left block.

    Returns:
        A :class:`ProcrustesResult`: ``transformation`` ``(B, 4, 4)`` mapping source to target
        (``d ≈ R s + t``) in the inputs' dtype, and ``valid`` ``(B,)`` bool.

    Raises:
        ShapeError: wrong shapes, mismatched devices or dtypes, a non-bool mask.
        ValueRangeError: NaN/inf at unmasked pairs, negative or non-finite weights.

    Example:
        >>> src = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]])
        >>> T, valid = procrustes(src, src + torch.tensor([1.0, 2.0, 3.0]))
        >>> T[0, :3, 3].round(decimals=4).tolist(), valid.tolist()
        ([1.0, 2.0, 3.0], [True])
        >>> procrustes(src[:, :2], src[:, :2]).valid  # two points: no unique rotation
        tensor([False])
    """
    source, target, w = check_pairs(source, target, weights, mask)
    return solve_procrustes(source, target, w, with_scaling=with_scaling)


class Procrustes(Solver[ProcrustesResult]):
    """Solver object for :func:`procrustes`: stores ``with_scaling`` and solves when called.

    ``Procrustes(with_scaling=...)(source, target, weights, mask)`` is :func:`procrustes`.

    Args:
        with_scaling: also estimate a uniform scale (Umeyama).

    Example:
        >>> solver = Procrustes()
        >>> src = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]])
        >>> solver(src, src).transformation.shape
        torch.Size([1, 4, 4])
    """

    function = staticmethod(procrustes)

    def __init__(self, *, with_scaling: bool = False) -> None:
        self.with_scaling = with_scaling


def check_pairs(
    source: torch.Tensor,
    target: torch.Tensor,
    weights: torch.Tensor | None,
    mask: torch.Tensor | None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Validate corresponding point sets, as :func:`procrustes` and RANSAC-Procrustes take them.

    Args:
        source: source points ``(B, N, 3)``.
        target: corresponding target points ``(B, N, 3)``, same device and dtype.
        weights: non-negative weights ``(B, N)``, or None for all ones.
        mask: ``(B, N)`` bool, True for pairs to use, or None; masked pairs may hold NaN.

    Returns:
        ``(source, target, weights)``: the points with masked pairs zeroed, and the weights
        ``(B, N)`` in the points' dtype, zero at masked pairs.

    Raises:
        ShapeError: wrong shapes, mismatched devices or dtypes, a non-bool mask.
        ValueRangeError: NaN/inf at unmasked pairs, negative or non-finite weights.
    """
    sizes = check_tensor(source, "source", ("B", "N", 3))
    check_tensor(target, "target", ("B", "N", 3), sizes=sizes)
    check_same(("source", source), ("target", target))
    if mask is not None:
        check_mask(mask, "mask", ("B", "N"), sizes)
        check_same(("source", source), ("mask", mask), dtype=False)
    source = zero_masked_points(source, mask, "source")
    target = zero_masked_points(target, mask, "target")
    if weights is None:
        w = torch.ones(source.shape[:2], dtype=source.dtype, device=source.device)
    else:
        check_tensor(weights, "weights", ("B", "N"), sizes=sizes)
        check_same(("source", source), ("weights", weights))
        w = weights if mask is None else torch.where(mask, weights, 0)
        if not bool(torch.isfinite(w).all()) or bool((w < 0).any()):
            raise ValueRangeError("weights must be finite and non-negative")
    if mask is not None:
        w = w * mask
    return source, target, w


def zero_masked_points(points: torch.Tensor, mask: torch.Tensor | None, name: str) -> torch.Tensor:
    """Check that the valid points are finite and set the masked ones to zero.

    Args:
        points: points ``(B, N, 3)``.
        mask: ``(B, N)`` bool, True for valid points, or None (all valid).
        name: the argument's name, used in the error message.

    Returns:
        ``points`` ``(B, N, 3)``, zero where ``mask`` is False.

    Raises:
        ValueRangeError: NaN or inf at a valid point.
    """
    if mask is None:
        if points.numel() and not bool(torch.isfinite(points).all()):
            raise ValueRangeError(f"{name} contains NaN or inf")
        return points
    if not bool((torch.isfinite(points).all(-1) | ~mask).all()):
        raise ValueRangeError(f"{name} contains NaN or inf at valid (unmasked) points")
    return torch.where(mask[..., None], points, 0)


def solve_procrustes(
    source: torch.Tensor,
    target: torch.Tensor,
    weights: torch.Tensor,
    *,
    with_scaling: bool = False,
) -> ProcrustesResult:
    """:func:`procrustes` without the input checks.

    Args:
        source: source points ``(B, N, 3)``, finite.
        target: corresponding target points ``(B, N, 3)``, finite, same device and dtype.
        weights: non-negative weights ``(B, N)`` in the points' dtype (0 = unused pair).
        with_scaling: also estimate a uniform scale (Umeyama).

    Returns:
        A :class:`ProcrustesResult`: transforms ``(B, 4, 4)`` in the points' dtype, the identity
        where ``valid`` ``(B,)`` is False (fewer than 3 weighted points, collinear or coincident
        points).
    """
    mu_s, mu_d, cov64, xs, xs_w = procrustes_moments(source, target, weights)
    U, S, Vh = svd3x3(cov64.detach())
    ok = is_well_posed(weights, mu_s, mu_d, S)
    if cov64.requires_grad:
        # Differentiate a well-conditioned stand-in where the solution is not unique, so that the
        # SVD's backward stays finite there (those instances get the identity and zero gradient).
        stand_in = torch.diag(torch.tensor([3.0, 2.0, 1.0], dtype=torch.float64, device=U.device))
        U, S, Vh = torch.linalg.svd(torch.where(ok[:, None, None], cov64, stand_in))
    spread = (xs * xs_w).sum((1, 2)) if with_scaling else None
    T = rigid_from_svd(mu_s, mu_d, U, S, Vh, ok, dtype=source.dtype, spread=spread)
    return ProcrustesResult(T, ok)


def svd3x3(matrices: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``U diag(S) Vh`` of float64 3 × 3 matrices ``(B, 3, 3)``, ``S`` ``(B, 3)`` decreasing.

    On the CPU, without gradient, the compiled one-sided Jacobi SVD of
    :mod:`poseflow.registration._svd3_cpu` (LAPACK's general SVD costs far more per small
    matrix), whose ``U`` stays orthonormal where a matrix is rank-deficient; elsewhere
    ``torch.linalg.svd``. Either way ``U diag(1, 1, det U det Vh) Vh`` is the Procrustes
    rotation.

    Example:
        >>> A = torch.tensor([[[2.0, 0, 0], [0, 0, 3], [0, 1, 0]]], dtype=torch.float64)
        >>> U, S, Vh = svd3x3(A)
        >>> S.tolist(), torch.allclose(U @ torch.diag_embed(S) @ Vh, A)
        ([[3.0, 2.0, 1.0]], True)
    """
    if matrices.device.type != "cpu" or matrices.requires_grad or not len(matrices):
        return torch.linalg.svd(matrices)
    from poseflow.registration._svd3_cpu import svd3_batch  # numba: when needed

    a = matrices.contiguous().numpy()
    U, S, Vh = np.empty_like(a), np.empty(a.shape[:2]), np.empty_like(a)
    svd3_batch(a, U, S, Vh)
    return torch.from_numpy(U), torch.from_numpy(S), torch.from_numpy(Vh)


def procrustes_moments(
    source: torch.Tensor, target: torch.Tensor, weights: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Weighted moments of corresponding points, the first step of :func:`solve_procrustes`.

    Everything is computed in float64: far from the origin, float32 centroids and centring
    would lose the cloud's extent to rounding.

    Args:
        source: source points ``(B, N, 3)``.
        target: corresponding target points ``(B, N, 3)``.
        weights: non-negative weights ``(B, N)`` in the points' dtype.

    Returns:
        ``(mu_s, mu_d, cov, xs, xs_w)``, all float64: the weighted centroids ``(B, 3)`` of source
        and target, the cross-covariance ``(B, 3, 3)`` (``sum_i w_i xd_i xs_i^T`` of the centred
        points, weights normalised to sum to 1), the centred source ``(B, N, 3)`` and its
        weighted copy ``(B, N, 3)``.
    """
    f64 = torch.float64
    w = weights.to(f64)
    total = w.sum(-1, keepdim=True)  # (B, 1)
    wn = (w / total.clamp_min(torch.finfo(f64).tiny)).unsqueeze(1)  # (B, 1, N)
    source, target = source.to(f64), target.to(f64)
    mu_s = (wn @ source).squeeze(1)  # (B, 3)
    mu_d = (wn @ target).squeeze(1)
    xs = source - mu_s.unsqueeze(1)
    xd = target - mu_d.unsqueeze(1)
    xs_w = xs * wn.transpose(1, 2)
    cov = xd.transpose(1, 2) @ xs_w  # (B, 3, 3) = sum_i w_i xd_i xs_i^T
    return mu_s, mu_d, cov, xs, xs_w


def is_well_posed(
    weights: torch.Tensor, mu_s: torch.Tensor, mu_d: torch.Tensor, S: torch.Tensor
) -> torch.Tensor:
    """Which instances have a unique Procrustes rotation, from the cross-covariance's SVD.

    Unique iff the cross-covariance of the centred points has rank >= 2: the second singular
    value must stand out of the first by more than the rounding of the points' dtype, and the
    first must exceed the square of one unit in the last place of the coordinates (a cloud
    whose extent is below the resolution of its own coordinates is a point); at least 3 pairs
    must have weight. Only the extent is judged, never the distance from the origin.

    Args:
        weights: the weights ``(B, N)`` of the pairs, in the points' dtype.
        mu_s: source centroids ``(B, 3)``.
        mu_d: target centroids ``(B, 3)``.
        S: singular values ``(B, 3)`` of the float64 cross-covariance, in decreasing order.

    Returns:
        ``(B,)`` bool, True where the rotation is unique.
    """
    eps = torch.finfo(weights.dtype).eps
    ulp2 = eps**2 * (mu_s.square().sum(-1) + mu_d.square().sum(-1)).detach().to(torch.float64)
    return (
        ((weights > 0).sum(-1) >= 3)
        & (S[:, 1] > eps**0.5 * S[:, 0])
        & (S[:, 0] > ulp2)
        & torch.isfinite(S).all(-1)
    )


def rigid_from_svd(
    mu_s: torch.Tensor,
    mu_d: torch.Tensor,
    U: torch.Tensor,
    S: torch.Tensor,
    Vh: torch.Tensor,
    ok: torch.Tensor,
    *,
    dtype: torch.dtype,
    spread: torch.Tensor | None = None,
) -> torch.Tensor:
    """The Procrustes transforms from the SVD ``U diag(S) Vh`` of the cross-covariance.

    The rotation is ``U diag(1, 1, d) Vh`` with ``d = det(U Vh)`` (never a reflection) and the
    translation maps the source centroid onto the target centroid.

    Args:
        mu_s: source centroids ``(B, 3)``, float64.
        mu_d: target centroids ``(B, 3)``, float64.
        U: left singular vectors ``(B, 3, 3)``, float64.
        S: singular values ``(B, 3)``, float64.
        Vh: right singular vectors, transposed, ``(B, 3, 3)``, float64.
        ok: ``(B,)`` bool; instances where it is False get the identity.
        dtype: the result's dtype (the points').
        spread: the weighted sum of squared centred source norms ``(B,)`` (float64) to also
            estimate a uniform scale (Umeyama), or None for a rigid transform.

    Returns:
        Transforms ``(B, 4, 4)`` in ``dtype``.
    """
    # det(U Vh) = det(U) det(Vh), each the triple product of its columns (or rows).
    sign = (_det3(U.detach()) * _det3(Vh.detach())).sign()
    D = torch.cat((torch.ones_like(S[:, :2]), torch.where(sign < 0, -1.0, 1.0)[:, None]), -1)
    R = (U * D.unsqueeze(1)) @ Vh  # U diag(D) Vh
    if spread is not None:
        R = R * ((S * D).sum(-1) / torch.where(ok, spread, 1.0))[:, None, None]
    t = mu_d - (R @ mu_s.unsqueeze(-1)).squeeze(-1)

    B = mu_s.shape[0]
    T = torch.zeros(B, 4, 4, dtype=dtype, device=mu_s.device)
    T[:, 3, 3] = 1
    T[:, :3, :3] = torch.where(
        ok[:, None, None], R, torch.eye(3, dtype=torch.float64, device=R.device)
    ).to(dtype)
    T[:, :3, 3] = torch.where(ok[:, None], t, 0).to(dtype)
    return T


def _det3(M: torch.Tensor) -> torch.Tensor:
    """Determinants of ``(B, 3, 3)`` matrices as triple products."""
    return (torch.linalg.cross(M[:, 0], M[:, 1]) * M[:, 2]).sum(-1)
