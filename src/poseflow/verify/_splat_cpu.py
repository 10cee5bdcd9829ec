"""The point splat of :func:`poseflow.verify.render.render_points` on the CPU, compiled with numba.

One pass over the points of each of the ``B x H`` renderings z-buffers them, a second averages
the colours of each pixel's front surface: the tensor version's answers, bit for bit. Both
evaluate every product and sum in the same order in the points' own dtype (``render._camera``
spells it out), take the same minimum, and add the colours of a pixel in the points' order, as
``index_add_`` does on the CPU.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["splat_kernel"]


@numba.njit(cache=True, nogil=True)
def splat_kernel(points, normals, colors, R, t, K, mask, surface, near, S, zbuf, csum, ccount):  # type: ignore[no-untyped-def]
    """Fill the z-buffer, then the colour sums and counts of each pixel's front surface.

    Args:
        points: model points ``(B, N, 3)``.
        normals: their unit normals ``(B, N, 3)``.
        colors: their colours ``(B, N, C)``.
        R: rotations ``(B, H, 3, 3)`` of the ``H`` poses.
        t: translations ``(B, H, 3)``.
        K: crop intrinsics ``(B, 3, 3)``.
        mask: ``(B, N)`` bool, the points to draw.
        surface: ``(B,)`` depth band of the front surface behind a pixel's nearest point.
        near: the smallest depth drawn (a scalar of the points' dtype).
        S: crop side.
        zbuf: ``(B H S S,)`` nearest depths, inf on entry.
        csum: ``(B H S S, C)`` colour sums, zero on entry.
        ccount: ``(B H S S,)`` front-surface counts, zero on entry.
    """
    B, N = points.shape[0], points.shape[1]
    H, C = R.shape[1], colors.shape[2]
    pixel = np.empty(N, dtype=np.int64)
    depth = np.empty(N, dtype=points.dtype)
    for b in range(B):
        for h in range(H):
            base = (b * H + h) * S * S
            r = R[b, h]
            for n in range(N):
                pixel[n] = -1
                if not mask[b, n]:
                    continue
                px, py, pz = points[b, n, 0], points[b, n, 1], points[b, n, 2]
                x = px * r[0, 0] + py * r[0, 1] + pz * r[0, 2] + t[b, h, 0]
                y = px * r[1, 0] + py * r[1, 1] + pz * r[1, 2] + t[b, h, 1]
                z = px * r[2, 0] + py * r[2, 1] + pz * r[2, 2] + t[b, h, 2]
                nx, ny, nz = normals[b, n, 0], normals[b, n, 1], normals[b, n, 2]
                mx = nx * r[0, 0] + ny * r[0, 1] + nz * r[0, 2]
                my = nx * r[1, 0] + ny * r[1, 1] + nz * r[1, 2]
                mz = nx * r[2, 0] + ny * r[2, 1] + nz * r[2, 2]
                if not (mx * x + my * y + mz * z < 0) or not z > near:
                    continue
                k = K[b]
                u = np.rint((x * k[0, 0] + y * k[0, 1] + z * k[0, 2]) / z)
                v = np.rint((x * k[1, 0] + y * k[1, 1] + z * k[1, 2]) / z)
                if not (u >= 0 and u < S and v >= 0 and v < S):
                    continue
                p = base + np.int64(v) * S + np.int64(u)
                pixel[n] = p
                depth[n] = z
                if z < zbuf[p]:
                    zbuf[p] = z
            for n in range(N):
                p = pixel[n]
                if p < 0 or not depth[n] <= zbuf[p] + surface[b]:
                    continue
                for c in range(C):
                    csum[p, c] += colors[b, n, c]
                ccount[p] += 1


@numba.njit(cache=True, nogil=True)
def _box3(image, i, j):  # type: ignore[no-untyped-def]
    """``box_sum(image, 3)`` at pixel ``(i, j)`` of an ``(S, S)`` image, in its order of sums."""
    S = image.shape[0]
    total = image.dtype.type(0)
    for a in range(i - 1, i + 2):
        row = image.dtype.type(0)
        for b in range(j - 1, j + 2):
            if 0 <= a < S and 0 <= b < S:
                row += image[a, b]
            else:
                row += image.dtype.type(0)
        total += row
    return total


@numba.njit(cache=True, nogil=True)
def close_gaps_kernel(zbuf, csum, ccount, occlusion, fill_passes, depth, color, drawn):  # type: ignore[no-untyped-def]
    """``render._close_gaps_tensors`` of ``R`` renderings, into ``depth``, ``color``, ``drawn``.

    A round fills every empty pixel with at least 5 drawn neighbours from the values before the
    round; a round that fills nothing ends the filling (the next ones would fill nothing either).

    Args:
        zbuf: ``(R, S, S)`` nearest depths, inf where empty.
        csum: ``(R, S, S, C)`` colour sums of the front surfaces.
        ccount: ``(R, S, S)`` their counts.
        occlusion: ``(R,)`` depth behind a neighbour's nearest beyond which a pixel is dropped.
        fill_passes: most rounds of filling.
        depth: ``(R, S, S)`` output depths, zero on entry.
        color: ``(R, C, S, S)`` output colours, zero on entry.
        drawn: ``(R, S, S)`` bool output mask, False on entry.
    """
    R, S, C = zbuf.shape[0], zbuf.shape[1], csum.shape[3]
    weight = np.zeros((S, S), dtype=zbuf.dtype)
    holes = np.empty((S * S, 2), dtype=np.int64)
    filled = np.empty((S * S, C + 1), dtype=zbuf.dtype)
    for r in range(R):
        z = zbuf[r]
        for i in range(S):
            for j in range(S):
                if not np.isfinite(z[i, j]):
                    continue
                near = z[i, j]
                for a in range(max(i - 1, 0), min(i + 2, S)):
                    for b in range(max(j - 1, 0), min(j + 2, S)):
                        near = min(near, z[a, b])
                if z[i, j] <= near + occlusion[r]:
                    drawn[r, i, j] = True
                    depth[r, i, j] = z[i, j]
                    count = max(ccount[r, i, j], 1)
                    for c in range(C):
                        color[r, c, i, j] = csum[r, i, j, c] / count
        for _ in range(fill_passes):
            for i in range(S):
                for j in range(S):
                    weight[i, j] = 1 if drawn[r, i, j] else 0
            found = 0
            for i in range(S):
                for j in range(S):
                    if drawn[r, i, j]:
                        continue
                    neighbours = _box3(weight, i, j) - weight[i, j]
                    if neighbours >= 5:
                        holes[found, 0], holes[found, 1] = i, j
                        filled[found, 0] = _box3(depth[r], i, j) / neighbours
                        for c in range(C):
                            filled[found, c + 1] = _box3(color[r, c], i, j) / neighbours
                        found += 1
            if found == 0:
                break
            for h in range(found):
                i, j = holes[h, 0], holes[h, 1]
                drawn[r, i, j] = True
                depth[r, i, j] = filled[h, 0]
                for c in range(C):
                    color[r, c, i, j] = filled[h, c + 1]
