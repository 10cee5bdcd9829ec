"""The per-iteration array work of ICP on the CPU, compiled with numba.

An ICP iteration moves the source by the current transform, pairs every point with its nearest
target point (:meth:`poseflow.geometry.neighbors.NeighborTracker.query_columns`) and solves
Procrustes on the pairs in range. Here the moving and, after the search, the pairing with the
weighted moments that Procrustes needs (:func:`poseflow.registration.procrustes.procrustes_moments`
with 0/1 weights) are each one pass over the points in float64, so that an iteration costs a few
small calls instead of some forty tensor operations; only the 3 x 3 SVDs and the stopping rule
stay in torch.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["move", "pair_moments"]

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
