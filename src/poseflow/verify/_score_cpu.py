"""The appearance agreement of :mod:`poseflow.verify.score` on the CPU, compiled with numba.

The kernel computes what :func:`~poseflow.verify.score.appearance_agreement`'s tensor version
does, in the same order: the window sums are separable shifted additions in
:func:`~poseflow.verify.render.box_sum`'s order (a row's terms from left to right, then the rows
from top to bottom, bit for bit), every product and quotient is taken in the images' own dtype,
and the channels are averaged as a sum divided by their count. Only the square roots differ by
rounding: the kernel's are correctly rounded, PyTorch's vectorised ones are not always (a last
bit in about one value of five in float32), so the two agree to a few units in the last place.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["appearance_kernel"]


@numba.njit(cache=True, nogil=True)
def _box_sums(planes, half, i0, i1, j0, j1, rows, out):  # type: ignore[no-untyped-def]
    """Window sums ``out`` of ``planes`` ``(P, S, S)`` in the box ``[i0, i1] x [j0, j1]``.

    The planes are zero outside the box, so the terms from outside it are left out (adding a
    zero changes no sum).
    """
    zero = planes.dtype.type(0)
    for p in range(planes.shape[0]):
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                total = zero
                for b in range(max(j - half, j0), min(j + half, j1) + 1):
                    total += planes[p, i, b]
                rows[p, i, j] = total
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                total = zero
                for a in range(max(i - half, i0), min(i + half, i1) + 1):
                    total += rows[p, a, j]
                out[p, i, j] = total


@numba.njit(cache=True, nogil=True)
def appearance_kernel(rendered, observed, both, window, floor, reference, least, tiny, out):  # type: ignore[no-untyped-def]
    """Fill ``out`` ``(B, H, S, S)`` (zero on entry) with the texture-weighted local NCC.

    Args:
        rendered: rendered colour ``(B, H, C, S, S)``.
        observed: observed colour ``(B, C, S, S)``.
        both: ``(B, H, S, S)`` bool, the pixels both images cover.
        window: odd window side.
        floor: the contrast floor (a scalar of the images' dtype).
        reference: the relative contrast that gets full weight (of the images' dtype).
        least: the smallest mean the contrast divides by (of the images' dtype).
        tiny: the dtype's smallest normal number.
        out: the agreement ``(B, H, S, S)``.
    """
    B, H, C, S = rendered.shape[0], rendered.shape[1], rendered.shape[2], rendered.shape[3]
    dtype = rendered.dtype
    zero, one = dtype.type(0), dtype.type(1)
    channels = dtype.type(C)
    planes = np.empty((1 + 5 * C, S, S), dtype=dtype)
    rows = np.empty((1 + 5 * C, S, S), dtype=dtype)
    sums = np.empty((1 + 5 * C, S, S), dtype=dtype)
    enough = (window * window + 1) // 2
    for b in range(B):
        for h in range(H):
            i0, i1, j0, j1 = S, -1, S, -1  # the box of the covered pixels
            for i in range(S):
                for j in range(S):
                    if both[b, h, i, j]:
                        i0, i1, j0, j1 = min(i0, i), max(i1, i), min(j0, j), max(j1, j)
            if i1 < 0:
                continue
            for i in range(i0, i1 + 1):
                for j in range(j0, j1 + 1):
                    w = one if both[b, h, i, j] else zero
                    planes[0, i, j] = w
                    for c in range(C):
                        x = rendered[b, h, c, i, j] * w
                        y = observed[b, c, i, j] * w
                        planes[1 + c, i, j] = x
                        planes[1 + C + c, i, j] = y
                        planes[1 + 2 * C + c, i, j] = x * x
                        planes[1 + 3 * C + c, i, j] = y * y
                        planes[1 + 4 * C + c, i, j] = x * y
            _box_sums(planes, window // 2, i0, i1, j0, j1, rows, sums)
            for i in range(i0, i1 + 1):
                for j in range(j0, j1 + 1):
                    n = sums[0, i, j]
                    if not (both[b, h, i, j] and n >= enough):
                        continue
                    n_safe = max(n, one)
                    total = zero
                    for c in range(C):
                        mx = sums[1 + c, i, j] / n_safe
                        my = sums[1 + C + c, i, j] / n_safe
                        vx = max(sums[1 + 2 * C + c, i, j] / n_safe - mx * mx, zero)
                        vy = max(sums[1 + 3 * C + c, i, j] / n_safe - my * my, zero)
                        cov = sums[1 + 4 * C + c, i, j] / n_safe - mx * my
                        fx, fy = floor * mx, floor * my
                        denom = np.sqrt((vx + fx * fx) * (vy + fy * fy))
                        ncc = cov / max(denom, tiny) if denom > 0 else zero
                        ncc = min(max(ncc, -one), one)
                        contrast = np.sqrt(vx) / max(abs(mx), least)
                        total += min(contrast / reference, one) * ncc
                    out[b, h, i, j] = total / channels
