"""FPFH histograms of a few points of a cloud on the CPU, compiled with numba.

The kernel of :class:`~poseflow.features.geometric.FPFHEncoder`'s ``"numba"`` backend: Open3D's
``compute_fpfh_feature`` with a hybrid search (the ``max_nn`` nearest points closer than the
radius, the point itself included) for the first ``count`` points of one cloud, every scale
from one neighbour search at the largest radius (the nearest points within a smaller radius are
the first of those), the pair features computed once for all scales, and the SPFH histograms
only of the described points and their neighbours. The arithmetic is that of
:func:`~poseflow.features.fpfh.compute_fpfh`, whose results it equals to float64 rounding.
"""

from __future__ import annotations

import math

import numba
import numpy as np

#: FPFH bins per angle; a histogram is three blocks of this many bins.
BINS = 11
#: Cosines farther apart than this have angles farther apart than acos's rounding error.
_CLEAR = 1e-12


@numba.njit(cache=True, nogil=True)
def _bin(value: float, low: float, width: float) -> int:
    """The bin of ``value`` among ``BINS`` equal bins from ``low``, clamped to the ends."""
    x = BINS * (value - low) / width
    return int(min(max(x, 0.0), BINS - 1.0))


@numba.njit(cache=True, nogil=True)
def _pair_bins(
    points: np.ndarray, normals: np.ndarray, i: int, j: int
) -> tuple[int, int, int, bool]:
    """The three bins (offset 0, 11, 22) of Open3D's pair feature of points ``i`` and ``j``.

    As :func:`poseflow.features.fpfh._pair_bins`: the pair is ordered so that the source normal
    makes the smaller angle with ``d = p_j - p_i``; coincident points and ``d`` parallel to the
    source normal give zero features. The fourth value says whether the pair ``(j, i)`` has the
    same bins: always, unless both normals make the same angle with ``d``, or a cosine exceeds
    1 by rounding (then each order keeps its own source, as Open3D does).
    """
    d0 = points[j, 0] - points[i, 0]
    d1 = points[j, 1] - points[i, 1]
    d2 = points[j, 2] - points[i, 2]
    sq = d0 * d0 + d1 * d1 + d2 * d2
    angle = cos_v = cos_d = 0.0
    symmetric = True
    if sq != 0.0:
        length = math.sqrt(sq)
        n1, n2 = normals[i], normals[j]
        a1 = (n1[0] * d0 + n1[1] * d1 + n1[2] * d2) / length
        a2 = (n2[0] * d0 + n2[1] * d1 + n2[2] * d2) / length
        c1, c2 = abs(a1), abs(a2)
        if abs(c1 - c2) > _CLEAR and c1 <= 1.0 and c2 <= 1.0:
            swap = c1 < c2  # acos falls at least as fast as its argument rises
        else:  # close, or a cosine past 1 by rounding (acos NaN: no order swaps): as Open3D
            angle1, angle2 = math.acos(c1), math.acos(c2)
            swap = angle1 > angle2
            symmetric = angle1 < angle2 or angle1 > angle2
        u, t = (n2, n1) if swap else (n1, n2)
        if swap:
            d0, d1, d2 = -d0, -d1, -d2
        v0 = d1 * u[2] - d2 * u[1]
        v1 = d2 * u[0] - d0 * u[2]
        v2 = d0 * u[1] - d1 * u[0]
        v_norm = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
        if v_norm > 0.0:
            v0, v1, v2 = v0 / v_norm, v1 / v_norm, v2 / v_norm
            w0 = u[1] * v2 - u[2] * v1
            w1 = u[2] * v0 - u[0] * v2
            w2 = u[0] * v1 - u[1] * v0
            angle = math.atan2(
                w0 * t[0] + w1 * t[1] + w2 * t[2], u[0] * t[0] + u[1] * t[1] + u[2] * t[2]
            )
            cos_v = v0 * t[0] + v1 * t[1] + v2 * t[2]
            cos_d = -a2 if swap else a1
    return (
        _bin(angle, -math.pi, 2 * math.pi),
        _bin(cos_v, -1.0, 2.0) + BINS,
        _bin(cos_d, -1.0, 2.0) + 2 * BINS,
        symmetric,
    )


@numba.njit(cache=True, nogil=True)
def _kth_smallest(values: np.ndarray, n: int, k: int) -> float:
    """The ``k``-th smallest (0-based) of ``values[:n]``, which it reorders (quickselect)."""
    lo, hi = 0, n - 1
    while lo < hi:
        pivot = values[(lo + hi) // 2]
        a, b = lo, hi
        while a <= b:
            while values[a] < pivot:
                a += 1
            while values[b] > pivot:
                b -= 1
            if a <= b:
                values[a], values[b] = values[b], values[a]
                a += 1
                b -= 1
        if k <= b:
            hi = b
        elif k >= a:
            lo = a
        else:
            break
    return values[k]


@numba.njit(cache=True, nogil=True)
def _squared_distance(points: np.ndarray, i: int, j: int) -> float:
    e0 = points[j, 0] - points[i, 0]
    e1 = points[j, 1] - points[i, 1]
    e2 = points[j, 2] - points[i, 2]
    return e0 * e0 + e1 * e1 + e2 * e2


@numba.njit(cache=True, nogil=True)
def _nearest(
    points: np.ndarray,
    i: int,
    bound: float,
    k: int,
    index: np.ndarray,
    dist2: np.ndarray,
    scratch: np.ndarray,
    scratch_index: np.ndarray,
) -> int:
    """The ``k`` nearest other points of point ``i`` closer than ``sqrt(bound)``.

    Writes their indices and squared distances into ``index`` and ``dist2`` in index order
    (ties at the ``k``-th distance go to the lower indices) and returns how many were found;
    ``scratch`` ``(2 P,)`` float64 and ``scratch_index`` ``(P,)`` int64 are workspace.
    """
    P = points.shape[0]
    x, y, z = points[i, 0], points[i, 1], points[i, 2]
    n = 0
    for j in range(P):
        e0 = points[j, 0] - x
        e1 = points[j, 1] - y
        e2 = points[j, 2] - z
        sq = e0 * e0 + e1 * e1 + e2 * e2
        if sq < bound and j != i:
            scratch[n] = sq
            scratch_index[n] = j
            n += 1
    if n <= k:
        index[:n] = scratch_index[:n]
        dist2[:n] = scratch[:n]
        return n
    values = scratch[P : P + n]
    values[:] = scratch[:n]
    kth = _kth_smallest(values, n, k - 1)
    ties = k  # how many candidates at exactly the k-th distance still fit
    for c in range(n):
        if scratch[c] < kth:
            ties -= 1
    m = 0
    for c in range(n):
        sq = scratch[c]
        if sq > kth:
            continue
        if sq == kth:
            if ties == 0:
                continue
            ties -= 1
        index[m] = scratch_index[c]
        dist2[m] = sq
        m += 1
    return m


@numba.njit(cache=True, nogil=True)
def _position(row: np.ndarray, length: int, value: int) -> int:
    """Where ``value`` is in the ascending ``row[:length]``, or -1."""
    lo, hi = 0, length
    while lo < hi:
        mid = (lo + hi) // 2
        if row[mid] < value:
            lo = mid + 1
        else:
            hi = mid
    return lo if lo < length and row[lo] == value else -1


@numba.njit(cache=True, nogil=True)
def fpfh_first_kernel(
    points: np.ndarray, normals: np.ndarray, count: int, bounds: np.ndarray, max_nn: int
) -> np.ndarray:
    """Open3D's raw FPFH histograms of the first ``count`` points of one cloud.

    Args:
        points: the cloud ``(P, 3)`` float64, every point valid.
        normals: its unit normals ``(P, 3)`` float64.
        count: how many of the first points to describe.
        bounds: the squared radii ``(S,)``, one per scale.
        max_nn: neighbours per search at most, the point itself included.

    Returns:
        ``(count, S * 33)`` float64, scale after scale (zero for a point without neighbours).
    """
    P = points.shape[0]
    S = bounds.shape[0]
    D = 3 * BINS
    largest = bounds.max()
    k = max(min(max_nn - 1, P - 1), 0)
    index = np.empty((P, k), dtype=np.int64)
    dist2 = np.empty((P, k))
    found = np.zeros(P, dtype=np.int64)
    needed = np.zeros(P, dtype=np.bool_)
    scratch = np.empty(2 * P)
    scratch_index = np.empty(P, dtype=np.int64)
    for i in range(count):
        needed[i] = True
        found[i] = _nearest(points, i, largest, k, index[i], dist2[i], scratch, scratch_index)
        for m in range(found[i]):
            needed[index[i, m]] = True
    for i in range(count, P):
        if needed[i]:
            found[i] = _nearest(points, i, largest, k, index[i], dist2[i], scratch, scratch_index)

    # A pair's feature does not depend on its order (the source is the point whose normal makes
    # the smaller angle with the line) unless the angles tie, so a pair met again from its other
    # end reuses its bins: code b0 * 121 + (b1 - 11) * 11 + b2 - 22, per neighbour slot.
    codes = np.empty((P, k), dtype=np.int16)
    reusable = np.zeros((P, k), dtype=np.bool_)
    spfh = np.zeros((S, P, D))
    within = np.zeros(S, dtype=np.int64)
    for i in range(P):
        if not needed[i]:
            continue
        within[:] = 0
        for m in range(found[i]):
            for s in range(S):
                if dist2[i, m] < bounds[s]:
                    within[s] += 1
        for m in range(found[i]):
            j = index[i, m]
            at = _position(index[j], found[j], i) if j < i and needed[j] else -1
            if at >= 0 and reusable[j, at]:
                code = codes[j, at]
            else:
                b0, b1, b2, symmetric = _pair_bins(points, normals, i, j)
                code = b0 * BINS * BINS + (b1 - BINS) * BINS + b2 - 2 * BINS
                reusable[i, m] = symmetric
            codes[i, m] = code
            b0 = code // (BINS * BINS)
            b1 = (code // BINS) % BINS + BINS
            b2 = code % BINS + 2 * BINS
            for s in range(S):
                if dist2[i, m] < bounds[s]:
                    incr = 100.0 / within[s]
                    spfh[s, i, b0] += incr
                    spfh[s, i, b1] += incr
                    spfh[s, i, b2] += incr

    out = np.zeros((count, S * D))
    summed = np.zeros(D)
    for i in range(count):
        for s in range(S):
            summed[:] = 0.0
            for m in range(found[i]):
                sq = dist2[i, m]
                if sq < bounds[s] and sq != 0.0:
                    w = 1.0 / sq
                    j = index[i, m]
                    for b in range(D):
                        summed[b] += spfh[s, j, b] * w
            for block in range(3):
                total = 0.0
                for b in range(block * BINS, (block + 1) * BINS):
                    total += summed[b]
                norm = 100.0 / total if total != 0.0 else 0.0
                for b in range(block * BINS, (block + 1) * BINS):
                    out[i, s * D + b] = summed[b] * norm + spfh[s, i, b]
    return out
