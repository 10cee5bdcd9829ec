"""The CPU nearest-neighbour searches of :mod:`poseflow.geometry.neighbors`, compiled with numba.

:func:`knn` answers :meth:`~poseflow.geometry.neighbors.NeighborIndex.query` on the CPU.
:func:`track` is the work of :class:`~poseflow.geometry.neighbors.NeighborTracker`:
one call per query does what the tracker needs for every point: how far it moved from its
anchor, its nearest remembered candidate, whether that candidate is certainly its nearest
neighbour (or certainly nothing is in range) and, where not, a new search of a k-d tree of the
reference points, after which the point is anchored where it is now. Doing it in one compiled
pass removes the per-call cost of a tree library and the ``(K, B, N)`` temporaries of array code,
which dominated ICP on clouds of a few thousand points.

The tree: for each batch item, the valid reference points split at the median of their widest
coordinate until at most :data:`LEAF_SIZE` remain, every node with its bounding box. A search
visits the nearer child first and skips nodes whose box is farther than the ``k``-th best point
found so far (or than the search bound), so it is exact.
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = ["LEAF_SIZE", "build_trees", "knn", "partition_at", "track"]

#: Largest number of points in a leaf of the k-d tree.
LEAF_SIZE = 16

_jit = numba.njit(cache=True, nogil=True)


@_jit
def partition_at(perm, coord, lo, hi, kth):  # type: ignore[no-untyped-def]
    """Reorder ``perm[lo:hi]`` so that ``coord`` is no larger before ``kth`` than from it on."""
    while hi - lo > 1:
        a, b, c = coord[perm[lo]], coord[perm[(lo + hi) // 2]], coord[perm[hi - 1]]
        pivot = max(min(a, b), min(max(a, b), c))  # the median of the three
        i, j = lo, hi - 1
        while i <= j:
            while coord[perm[i]] < pivot:
                i += 1
            while coord[perm[j]] > pivot:
                j -= 1
            if i <= j:
                perm[i], perm[j] = perm[j], perm[i]
                i += 1
                j -= 1
        # now coord <= pivot on [lo, j], >= pivot on [i, hi), == pivot in between
        if kth <= j:
            hi = j + 1
        elif kth >= i:
            lo = i
        else:
            return


@_jit
def build_trees(columns, valid, M, leaf_size):  # type: ignore[no-untyped-def]
    """k-d trees over the valid reference points of each batch item.

    Args:
        columns: float64 ``(3, B * M + 1)`` reference points as columns (item ``b``'s point ``m``
            is column ``b * M + m``).
        valid: bool ``(B, M)``, True for points that may be returned.
        M: points per batch item.
        leaf_size: largest number of points in a leaf.

    Returns:
        ``(perm, points, root, (lo, hi, left, right, box))``: the columns of the valid points
        in tree order ``(P,)`` and the points themselves ``(P, 3)``; each item's root node
        ``(B,)`` (-1 for an item without valid points); per node, its range ``perm[lo:hi]``, its
        two children (-1 for a leaf) and its bounding box ``(n_nodes, 6)`` (minima, then
        maxima).
    """
    B = valid.shape[0]
    perm = _valid_columns(valid, M)
    P = perm.shape[0]
    cap = 2 * (P // max(1, leaf_size // 2)) + 2 * B + 2
    lo = np.empty(cap, np.int64)
    hi = np.empty(cap, np.int64)
    left = np.full(cap, -1, np.int64)
    right = np.full(cap, -1, np.int64)
    box = np.empty((cap, 6))
    root = np.full(B, -1, np.int64)
    n_nodes = 0
    stack = np.empty(128, np.int64)
    start = 0
    for b in range(B):
        count = 0
        for m in range(M):
            if valid[b, m]:
                count += 1
        if count == 0:
            continue
        root[b] = n_nodes
        lo[n_nodes], hi[n_nodes] = start, start + count
        n_nodes += 1
        start += count
        stack[0] = root[b]
        top = 1
        while top > 0:
            top -= 1
            node = stack[top]
            a, z = lo[node], hi[node]
            _fit_box(columns, perm, a, z, box[node])
            if z - a <= leaf_size:
                continue
            axis = _widest_axis(box[node])
            if box[node, 3 + axis] - box[node, axis] <= 0:
                continue  # all points coincide: a leaf, whatever its size
            mid = (a + z) // 2
            partition_at(perm, columns[axis], a, z, mid)
            left[node], right[node] = n_nodes, n_nodes + 1
            lo[n_nodes], hi[n_nodes] = a, mid
            lo[n_nodes + 1], hi[n_nodes + 1] = mid, z
            stack[top], stack[top + 1] = n_nodes + 1, n_nodes
            top += 2
            n_nodes += 2
    points = np.ascontiguousarray(columns[:, perm].T)
    nodes = (lo[:n_nodes], hi[:n_nodes], left[:n_nodes], right[:n_nodes], box[:n_nodes])
    return perm, points, root, nodes


@_jit
def _valid_columns(valid, M):  # type: ignore[no-untyped-def]
    """The columns ``b * M + m`` of the valid points ``(P,)``, item by item, in order."""
    perm = np.empty(valid.sum(), np.int64)
    P = 0
    for b in range(valid.shape[0]):
        for m in range(M):
            if valid[b, m]:
                perm[P] = b * M + m
                P += 1
    return perm


@_jit
def _fit_box(columns, perm, a, z, box):  # type: ignore[no-untyped-def]
    """Write into ``box`` ``(6,)`` the bounds (minima, then maxima) of the points ``perm[a:z]``."""
    for c in range(3):
        box[c] = np.inf
        box[3 + c] = -np.inf
    for k in range(a, z):
        for c in range(3):
            v = columns[c, perm[k]]
            box[c] = min(box[c], v)
            box[3 + c] = max(box[3 + c], v)


@_jit
def _widest_axis(box):  # type: ignore[no-untyped-def]
    """The coordinate along which the box ``(6,)`` (minima, then maxima) is widest."""
    axis = 0
    for c in range(1, 3):
        if box[3 + c] - box[c] > box[3 + axis] - box[axis]:
            axis = c
    return axis


@_jit
def _gap(v, low, high):  # type: ignore[no-untyped-def]
    """Distance from ``v`` to the interval ``[low, high]`` (0 inside)."""
    if v < low:
        return low - v
    if v > high:
        return v - high
    return 0.0


@_jit
def _box_d2(box, node, x, y, z):  # type: ignore[no-untyped-def]
    """Squared distance from ``(x, y, z)`` to a node's bounding box."""
    gx = _gap(x, box[node, 0], box[node, 3])
    gy = _gap(y, box[node, 1], box[node, 4])
    gz = _gap(z, box[node, 2], box[node, 5])
    return gx * gx + gy * gy + gz * gz


@_jit
def _search(tree, root, x, y, z, bound2, best_d2, best_i, stack, stack_d2):  # type: ignore[no-untyped-def]
    """The ``K = len(best_d2)`` nearest points to ``(x, y, z)`` closer than ``sqrt(bound2)``.

    Fills ``best_d2`` (ascending squared distances, ``inf`` where missing) and ``best_i``
    (their columns, untouched where missing).
    """
    perm, points, lo, hi, left, right, box = tree
    K = best_d2.shape[0]
    best_d2[:] = np.inf
    worst = bound2
    stack[0] = root
    stack_d2[0] = _box_d2(box, root, x, y, z)
    top = 1
    while top > 0:
        top -= 1
        if stack_d2[top] >= worst:
            continue
        node = stack[top]
        if left[node] < 0:
            for k in range(lo[node], hi[node]):
                ex, ey, ez = points[k, 0] - x, points[k, 1] - y, points[k, 2] - z
                d2 = ex * ex + ey * ey + ez * ez
                if d2 < worst:
                    j = K - 1
                    while j > 0 and best_d2[j - 1] > d2:
                        best_d2[j] = best_d2[j - 1]
                        best_i[j] = best_i[j - 1]
                        j -= 1
                    best_d2[j] = d2
                    best_i[j] = perm[k]
                    if best_d2[K - 1] < bound2:
                        worst = best_d2[K - 1]
            continue
        a, b = left[node], right[node]
        da, db = _box_d2(box, a, x, y, z), _box_d2(box, b, x, y, z)
        if da > db:
            a, b, da, db = b, a, db, da
        stack[top], stack_d2[top] = b, db  # the farther child is visited last
        stack[top + 1], stack_d2[top + 1] = a, da
        top += 2


@_jit
def track(  # type: ignore[no-untyped-def]
    q, anchor, cand, lower, columns, tree, root, items, max_distance, bound, slack, dist, nearest
):
    """The tracker's answer for every query point; searches and re-anchors where needed.

    Args:
        q: query points as coordinates first, ``(3, B', N)``, float32 or float64.
        anchor: float64 ``(3, B, N)``, where each point was last searched (updated in place).
        cand: int64 ``(K, B, N)`` remembered candidates as columns of ``columns``, the last
            column (at infinity) for none (updated in place).
        lower: float64 ``(B, N)``, a lower bound on the distance from the anchor to every
            reference point that is not a candidate (updated in place).
        columns: float64 ``(3, B * M + 1)`` reference points, the last column at infinity.
        tree: ``(perm, points, lo, hi, left, right, box)`` from :func:`build_trees`.
        root: int64 ``(B,)`` root node of each item (-1: no valid point).
        items: int64 ``(B',)``, the batch item of each row of ``q``.
        max_distance: neighbours farther than this are missing.
        bound: searches reach this far (``>= max_distance``).
        slack: the rounding allowance subtracted from the bound ``L``.
        dist: ``(B', N)``, out: distance to the nearest reference point, ``inf`` if none is
            within ``max_distance``.
        nearest: int64 ``(B', N)``, out: its column (the last column if none).

    Returns:
        The number of points searched again.
    """
    K = cand.shape[0]
    none = columns.shape[1] - 1
    best_d2 = np.empty(K)
    best_i = np.empty(K, np.int64)
    stack = np.empty(256, np.int64)
    stack_d2 = np.empty(256)
    searched = 0
    for j in range(q.shape[1]):
        b = items[j]
        for n in range(q.shape[2]):
            x, y, z = np.float64(q[0, j, n]), np.float64(q[1, j, n]), np.float64(q[2, j, n])
            dx, dy, dz = x - anchor[0, b, n], y - anchor[1, b, n], z - anchor[2, b, n]
            moved = math.sqrt(dx * dx + dy * dy + dz * dz)
            near = cand[0, b, n]
            best = math.inf
            for k in range(K):
                c = cand[k, b, n]
                ex, ey, ez = columns[0, c] - x, columns[1, c] - y, columns[2, c] - z
                d2 = ex * ex + ey * ey + ez * ez
                if d2 < best:
                    best = d2
                    near = c
            d = math.sqrt(best)
            others = lower[b, n] - moved - slack
            if not (d < others or (d > max_distance and others > max_distance)):
                searched += 1
                if root[b] >= 0:
                    _search(tree, root[b], x, y, z, bound * bound, best_d2, best_i, stack, stack_d2)
                else:
                    best_d2[:] = np.inf
                anchor[0, b, n], anchor[1, b, n], anchor[2, b, n] = x, y, z
                for k in range(K):
                    cand[k, b, n] = best_i[k] if best_d2[k] < math.inf else none
                # Points not listed lie beyond the K-th candidate, or beyond the search bound
                # when fewer were found; a hair less, against rounding.
                lower[b, n] = min(math.sqrt(best_d2[K - 1]), bound) * (1 - 1e-12)
                near = cand[0, b, n]
                d = math.sqrt(best_d2[0])
            if d <= max_distance:
                dist[j, n] = d
                nearest[j, n] = near
            else:
                dist[j, n] = math.inf
                nearest[j, n] = none
    return searched


@_jit
def knn(tree, root, q, items, bound2, M, out_d, out_i):  # type: ignore[no-untyped-def]
    """The ``k`` nearest valid reference points of every query point, exact.

    Args:
        tree: ``(perm, points, lo, hi, left, right, box)`` from :func:`build_trees`.
        root: int64 ``(B,)`` root node of each item (-1: no valid point).
        q: float64 ``(B', N, 3)`` query points.
        items: int64 ``(B',)``, the batch item of each row of ``q``.
        bound2: only points at a squared distance below this are returned.
        M: reference points per batch item.
        out_d: float64 ``(B', N, k)``, out: ascending distances, ``inf`` where missing.
        out_i: int64 ``(B', N, k)``, out: indices into the item's ``M`` points, 0 where missing
            (an item may search the tree of an earlier item with the same points).
    """
    k = out_d.shape[2]
    best_d2 = np.empty(k)
    best_i = np.empty(k, np.int64)
    stack = np.empty(256, np.int64)
    stack_d2 = np.empty(256)
    for j in range(q.shape[0]):
        b = items[j]
        for n in range(q.shape[1]):
            if root[b] >= 0:
                x, y, z = q[j, n, 0], q[j, n, 1], q[j, n, 2]
                _search(tree, root[b], x, y, z, bound2, best_d2, best_i, stack, stack_d2)
            else:
                best_d2[:] = np.inf
            for r in range(k):
                if best_d2[r] < math.inf:
                    out_d[j, n, r] = math.sqrt(best_d2[r])
                    out_i[j, n, r] = best_i[r] % M  # the item's own tree or a twin's
                else:
                    out_d[j, n, r] = math.inf
                    out_i[j, n, r] = 0
