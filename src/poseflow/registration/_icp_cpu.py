"""The per-iteration array work of ICP on the CPU, compiled with numba.

An ICP iteration moves the source by the current transform, pairs every point with its nearest
target point (:meth:`poseflow.geometry.neighbors.NeighborTracker.query_columns`) and solves
Procrustes on the pairs in range. Here the moving and, after the search, the pairing with the
weighted moments that Procrustes needs (:func:`poseflow.registration.procrustes.procrustes_moments`
with 0/1 weights) are each one pass over the points in float64, and the solve from those moments
is one pass over the batch, so that an iteration costs a few small calls instead of some sixty
tensor operations.
"""

from __future__ import annotations

import numba
import numpy as np

from poseflow.registration._svd3_cpu import svd3

__all__ = ["move", "pair_moments", "rigid_from_moments"]

_jit = numba.njit(cache=True, nogil=True)


@_jit
def move(source, T, items, out):  # type: ignore[no-untyped-def]
    """``out[:, j, n] = R_j source[items[j], n] + t_j``, coordinates first.

    Args:
        source: float64 ``(B, N, 3)``.
        T: float64 ``(B', 4, 4)`` transforms.
        items: int64 ``(B',)``, the batch item of each transform.
        out: float64 ``(3, B', N)``, written.
    """
    for j in range(T.shape[0]):
        b = items[j]
        for n in range(source.shape[1]):
            x, y, z = source[b, n, 0], source[b, n, 1], source[b, n, 2]
            for c in range(3):
                out[c, j, n] = T[j, c, 0] * x + T[j, c, 1] * y + T[j, c, 2] * z + T[j, c, 3]


@_jit
def pair_moments(  # type: ignore[no-untyped-def]
    source, valid, columns, nearest, dist, items, max_distance, inliers, stats, mu, cov
):
    """The pairs in range and their Procrustes moments, per batch item.

    Args:
        source: float64 ``(B, N, 3)`` source points.
        valid: bool ``(B, N)``, the source points to use.
        columns: float64 ``(3, C)`` target points as columns.
        nearest: int64 ``(B', N)``, each moved source point's nearest target column.
        dist: ``(B', N)`` its distance (``inf`` where none is in range).
        items: int64 ``(B',)``, the batch item of each row.
        max_distance: pairs farther apart are ignored.
        inliers: bool ``(B', N)``, out: valid points with a pair in range.
        stats: float64 ``(B', 2)``, out: the number of inliers and the sum of their squared
            distances.
        mu: float64 ``(B', 2, 3)``, out: the inliers' source and target centroids (0 if none).
        cov: float64 ``(B', 3, 3)``, out: ``sum_i xd_i xs_i^T / count`` over the inliers, of
            the centred target and source points.
    """
    for j in range(nearest.shape[0]):
        b = items[j]
        count = 0
        d2 = 0.0
        ms = np.zeros(3)
        md = np.zeros(3)
        for n in range(nearest.shape[1]):
            pair = valid[b, n] and dist[j, n] <= max_distance
            inliers[j, n] = pair
            if pair:
                count += 1
                d = np.float64(dist[j, n])
                d2 += d * d
                col = nearest[j, n]
                for c in range(3):
                    ms[c] += source[b, n, c]
                    md[c] += columns[c, col]
        scale = 1.0 / count if count > 0 else 0.0
        for c in range(3):
            ms[c] *= scale
            md[c] *= scale
        acc = np.zeros((3, 3))
        for n in range(nearest.shape[1]):
            if inliers[j, n]:
                col = nearest[j, n]
                for r in range(3):
                    xd = columns[r, col] - md[r]
                    for c in range(3):
                        acc[r, c] += xd * (source[b, n, c] - ms[c])
        stats[j, 0] = count
        stats[j, 1] = d2
        for c in range(3):
            mu[j, 0, c] = ms[c]
            mu[j, 1, c] = md[c]
            for r in range(3):
                cov[j, r, c] = acc[r, c] * scale


@_jit
def rigid_from_moments(mu, cov, stats, eps, T, ok):  # type: ignore[no-untyped-def]
    """Procrustes from the moments of :func:`pair_moments`, where the rotation is unique.

    :func:`poseflow.registration.procrustes.is_well_posed` and
    :func:`~poseflow.registration.procrustes.rigid_from_svd` (rigid) with 0/1 weights: the
    rotation ``U diag(1, 1, d) Vh`` from the SVD ``U diag(S) Vh`` of the cross-covariance, with
    ``d`` the sign of ``det U det Vh``, and the translation ``mu_d - R mu_s``.

    Args:
        mu: float64 ``(B', 2, 3)``, the source and target centroids.
        cov: float64 ``(B', 3, 3)``, the cross-covariance.
        stats: float64 ``(B', 2)``, the number of pairs first.
        eps: the machine epsilon of the points' dtype.
        T: float64 ``(B', 4, 4)``, the current transforms; overwritten with the solution where
            ``ok``.
        ok: bool ``(B',)``, out: at least 3 pairs, the cross-covariance of rank >= 2 (beyond the
            rounding of the points' dtype) and a finite SVD.
    """
    a = np.empty((3, 3))
    R = np.empty((3, 3))
    U, S, Vh = np.empty((3, 3)), np.empty(3), np.empty((3, 3))
    work = np.empty((2, 3, 3))
    for j in range(cov.shape[0]):
        finite = True
        for r in range(3):
            for c in range(3):
                a[r, c] = cov[j, r, c]
                finite = finite and np.isfinite(cov[j, r, c])
        ok[j] = False
        if not finite:
            continue
        svd3(a, U, S, Vh, work[0], work[1])
        ulp2 = eps**2 * (
            (mu[j, 0, 0] ** 2 + mu[j, 0, 1] ** 2 + mu[j, 0, 2] ** 2)
            + (mu[j, 1, 0] ** 2 + mu[j, 1, 1] ** 2 + mu[j, 1, 2] ** 2)
        )
        ok[j] = (
            stats[j, 0] >= 3
            and S[1] > eps**0.5 * S[0]
            and S[0] > ulp2
            and np.isfinite(S[0])
            and np.isfinite(S[1])
            and np.isfinite(S[2])
        )
        if not ok[j]:
            continue
        d = -1.0 if _det3(U) * _det3(Vh) < 0 else 1.0
        for r in range(3):
            for c in range(3):
                R[r, c] = U[r, 0] * Vh[0, c] + U[r, 1] * Vh[1, c] + d * U[r, 2] * Vh[2, c]
        for r in range(3):
            T[j, r, 3] = mu[j, 1, r] - (
                R[r, 0] * mu[j, 0, 0] + R[r, 1] * mu[j, 0, 1] + R[r, 2] * mu[j, 0, 2]
            )
            for c in range(3):
                T[j, r, c] = R[r, c]
            T[j, 3, r] = 0.0
        T[j, 3, 3] = 1.0


@_jit
def _det3(M):  # type: ignore[no-untyped-def]
    """The determinant of a 3 x 3 matrix, the triple product of its rows."""
    return (
        (M[0, 1] * M[1, 2] - M[0, 2] * M[1, 1]) * M[2, 0]
        + (M[0, 2] * M[1, 0] - M[0, 0] * M[1, 2]) * M[2, 1]
        + (M[0, 0] * M[1, 1] - M[0, 1] * M[1, 0]) * M[2, 2]
    )
