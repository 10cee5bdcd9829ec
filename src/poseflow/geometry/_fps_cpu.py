"""Farthest-point sampling on the CPU, compiled with numba, with the torch loop's exact answers.

:func:`poseflow.geometry.sampling.farthest_point_sample` runs a loop of tensor ops over the
``M`` samples; on the CPU that loop costs one pass over every point per sample. This kernel
gives the same indices (bit for bit, ties included) with far less work:

- the valid points of a cloud are split into the leaves of a k-d tree (at most
  :data:`LEAF_SIZE` points each, stored contiguously), each leaf with its bounding box and the
  largest current distance of its points;
- after a new sample ``c`` is chosen, a leaf whose box is no nearer to ``c`` than its largest
  distance cannot change (the minimum keeps every old value) and is skipped; late samples touch
  only the few leaves around them;
- the next sample is the point of largest distance with the smallest index among ties, which is
  what ``torch.argmax`` returns.

The distances are computed as the torch loop computes them: ``dx * dx``, then two fused
multiply-adds (``torch.addcmul`` on the CPU is fused), in the points' own dtype, so the running
minima, and hence the argmax, are the same. The skip test is conservative by a relative margin
far above that arithmetic's rounding, so no leaf whose values could change is ever skipped.
"""

from __future__ import annotations

import numba
import numpy as np
from llvmlite import ir
from numba.extending import intrinsic

from poseflow.geometry._tracker_cpu import partition_at

__all__ = ["LEAF_SIZE", "fps_kernel"]

#: Largest number of points in a k-d tree leaf.
LEAF_SIZE = 64

_jit = numba.njit(cache=True, nogil=True)


@intrinsic
def _fma(typingctx, a, b, c):  # type: ignore[no-untyped-def]
    """``a * b + c`` with one rounding (LLVM's ``llvm.fma``), in ``a``'s float type."""
    sig = a(a, b, c)

    def codegen(context, builder, signature, args):  # type: ignore[no-untyped-def]
        ty = args[0].type
        fn = builder.module.declare_intrinsic("llvm.fma", [ty], ir.FunctionType(ty, [ty] * 3))
        return builder.call(fn, args)

    return sig, codegen


@_jit
def _build_leaves(x, y, z, perm, leaf_size):  # type: ignore[no-untyped-def]
    """Reorder ``perm`` (indices of valid points) into k-d tree leaves; their bounds."""
    n = perm.shape[0]
    bounds = np.empty((max(1, 2 * (n // max(1, leaf_size // 2)) + 2), 2), np.int64)
    n_leaves = 0
    stack = np.empty((64, 2), np.int64)
    stack[0, 0], stack[0, 1] = 0, n
    top = 1
    while top > 0:
        top -= 1
        lo, hi = stack[top, 0], stack[top, 1]
        split = False
        if hi - lo > leaf_size:
            mn = np.full(3, np.inf)
            mx = np.full(3, -np.inf)
            for k in range(lo, hi):
                p = perm[k]
                for a, v in enumerate((x[p], y[p], z[p])):
                    mn[a] = min(mn[a], v)
                    mx[a] = max(mx[a], v)
            ext = mx - mn
            axis = int(np.argmax(ext))
            if ext[axis] > 0:
                coord = x if axis == 0 else (y if axis == 1 else z)
                mid = (lo + hi) // 2
                partition_at(perm, coord, lo, hi, mid)
                stack[top, 0], stack[top, 1] = lo, mid
                stack[top + 1, 0], stack[top + 1, 1] = mid, hi
                top += 2
                split = True
        if not split and hi > lo:
            bounds[n_leaves, 0], bounds[n_leaves, 1] = lo, hi
            n_leaves += 1
    return bounds[:n_leaves]


@_jit
def _one_cloud(x, y, z, valid, start, idx, leaf_size):  # type: ignore[no-untyped-def]
    """:func:`fps_kernel` for one cloud: coordinates, validity ``(N,)``, samples ``(M,)``."""
    M = idx.shape[0]
    perm = np.flatnonzero(valid)
    n = perm.shape[0]
    idx[:] = 0
    if n == 0:
        return
    leaves = _build_leaves(x, y, z, perm, leaf_size)
    L = leaves.shape[0]
    px, py, pz = x[perm], y[perm], z[perm]
    dist = np.full(n, np.inf, dtype=x.dtype)
    box = np.empty((L, 6))
    leaf_of = np.empty(n, np.int64)
    pos = np.full(x.shape[0], -1, np.int64)
    top = np.full(L, np.inf)  # largest distance in each leaf
    arg = np.empty(L, np.int64)  # smallest index among the points at that distance
    for leaf in range(L):
        lo, hi = leaves[leaf, 0], leaves[leaf, 1]
        box[leaf, :3] = np.inf
        box[leaf, 3:] = -np.inf
        arg[leaf] = perm[lo]
        for k in range(lo, hi):
            leaf_of[k] = leaf
            pos[perm[k]] = k
            arg[leaf] = min(arg[leaf], perm[k])
            for a, v in enumerate((px[k], py[k], pz[k])):
                box[leaf, a] = min(box[leaf, a], v)
                box[leaf, 3 + a] = max(box[leaf, 3 + a], v)
    # A leaf is skipped when its box's squared distance, less this relative margin (far
    # above the rounding of three squares and two additions) and an absolute one (for
    # underflow), is still no smaller than its largest distance.
    keep = 1.0 - 1e-5
    slack = 64.0 * np.finfo(x.dtype).tiny
    cur = start
    for i in range(M):
        if i == n:
            break  # every valid point is chosen: the torch loop's argmax is 0 from here
        idx[i] = cur
        dist[pos[cur]] = -1
        own = leaf_of[pos[cur]]
        cx, cy, cz = x[cur], y[cur], z[cur]
        for leaf in range(L):
            if top[leaf] < 0:
                continue  # all chosen: their distance stays -1
            if leaf != own:
                lb = 0.0
                for a, c in enumerate((cx, cy, cz)):
                    if c < box[leaf, a]:
                        lb += (box[leaf, a] - c) ** 2
                    elif c > box[leaf, 3 + a]:
                        lb += (c - box[leaf, 3 + a]) ** 2
                if lb * keep - slack >= top[leaf]:
                    continue
            best = -np.inf
            best_arg = 0
            for k in range(leaves[leaf, 0], leaves[leaf, 1]):
                dx = px[k] - cx
                dy = py[k] - cy
                dz = pz[k] - cz
                d = _fma(dz, dz, _fma(dy, dy, dx * dx))
                v = dist[k]
                if d < v:
                    v = d
                    dist[k] = d
                if v > best or (v == best and perm[k] < best_arg):
                    best = v
                    best_arg = perm[k]
            top[leaf] = best
            arg[leaf] = best_arg
        best = -np.inf
        cur = 0
        for leaf in range(L):
            if top[leaf] > best or (top[leaf] == best and arg[leaf] < cur):
                best = top[leaf]
                cur = arg[leaf]


@_jit
def fps_kernel(x, y, z, valid, start, idx):  # type: ignore[no-untyped-def]
    """Farthest-point samples of a batch of ``B`` clouds of ``N`` points, written to ``idx``.

    Args:
        x: C-contiguous x coordinates ``(B, N)``, float32 or float64 (``y``, ``z`` alike).
        y: y coordinates ``(B, N)``.
        z: z coordinates ``(B, N)``.
        valid: bool ``(B, N)``, True for valid points.
        start: int64 ``(B,)``, the first sample of each cloud (a valid point, or 0 for a cloud
            without one).
        idx: int64 ``(B, M)``, filled in place with the samples in the order the torch loop
            picks them (index 0 once a cloud has run out of valid points).
    """
    for b in range(x.shape[0]):
        _one_cloud(x[b], y[b], z[b], valid[b], start[b], idx[b], LEAF_SIZE)
