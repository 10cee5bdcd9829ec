"""The SVD of 3 × 3 matrices on the CPU, compiled with numba, for Procrustes.

``torch.linalg.svd`` calls LAPACK's general SVD once per 3 × 3 matrix, which made it most of
RANSAC's time: every hypothesis is one Procrustes. This is the one-sided Jacobi method
(Hestenes): plane rotations applied to the columns of ``A`` until they are mutually orthogonal;
the rotations accumulate into ``V``, the column norms are the singular values and the normalised
columns are ``U``. For 3 × 3 it converges in a few sweeps, to full float64 accuracy, with a
relative accuracy of the small singular values that LAPACK's bidiagonalisation does not promise.

``U`` is returned orthonormal even where ``A`` is rank-deficient (a minimal sample of three
points always is): the second column is the second of ``A`` made orthogonal to the first, the
third the cross product of the first two, turned towards the third column of ``A``; so
``U diag(S) Vh`` reproduces ``A`` and ``det(U) det(Vh)`` decides a reflection as LAPACK's
factors do.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["svd3", "svd3_batch"]

_jit = numba.njit(cache=True, nogil=True)

#: The column pairs of a Jacobi sweep.
_PAIRS = ((0, 1), (0, 2), (1, 2))
_MAX_SWEEPS = 30


@_jit
def _rotate_columns(m, p, q, c, s):  # type: ignore[no-untyped-def]
    """Columns ``p, q`` of ``m`` (3 × 3) ← ``(c m_p − s m_q, s m_p + c m_q)``."""
    for i in range(3):
        mp, mq = m[i, p], m[i, q]
        m[i, p] = c * mp - s * mq
        m[i, q] = s * mp + c * mq


@_jit
def _swap_columns(m, p, q):  # type: ignore[no-untyped-def]
    for i in range(3):
        m[i, p], m[i, q] = m[i, q], m[i, p]


@_jit
def svd3(a, u, s, vh, w, v):  # type: ignore[no-untyped-def]
    """``a = u diag(s) vh`` of one float64 3 × 3 matrix, ``s`` in decreasing order.

    Args:
        a: ``(3, 3)``, finite (read only).
        u: ``(3, 3)``, out: orthonormal left singular vectors as columns.
        s: ``(3,)``, out: the singular values, non-negative, decreasing.
        vh: ``(3, 3)``, out: the right singular vectors as rows, orthonormal.
        w: ``(3, 3)`` work array (overwritten).
        v: ``(3, 3)`` work array (overwritten).
    """
    for r in range(3):
        for c in range(3):
            w[r, c] = a[r, c]
            v[r, c] = 1.0 if r == c else 0.0
    eps = 2.220446049250313e-16  # float64
    for _ in range(_MAX_SWEEPS):
        rotated = False
        for p, q in _PAIRS:
            alpha = w[0, p] ** 2 + w[1, p] ** 2 + w[2, p] ** 2
            beta = w[0, q] ** 2 + w[1, q] ** 2 + w[2, q] ** 2
            gamma = w[0, p] * w[0, q] + w[1, p] * w[1, q] + w[2, p] * w[2, q]
            if gamma == 0.0 or abs(gamma) <= eps * np.sqrt(alpha * beta):
                continue
            rotated = True
            zeta = (beta - alpha) / (2.0 * gamma)
            t = (1.0 if zeta >= 0.0 else -1.0) / (abs(zeta) + np.sqrt(1.0 + zeta * zeta))
            c = 1.0 / np.sqrt(1.0 + t * t)
            _rotate_columns(w, p, q, c, c * t)
            _rotate_columns(v, p, q, c, c * t)
        if not rotated:
            break
    for j in range(3):
        s[j] = np.sqrt(w[0, j] ** 2 + w[1, j] ** 2 + w[2, j] ** 2)
    for p, q in ((0, 1), (1, 2), (0, 1)):  # sort decreasing
        if s[q] > s[p]:
            s[p], s[q] = s[q], s[p]
            _swap_columns(w, p, q)
            _swap_columns(v, p, q)
    # u_1: the first column normalised (e_1 for the zero matrix)
    for i in range(3):
        u[i, 0] = w[i, 0] / s[0] if s[0] > 0.0 else (1.0 if i == 0 else 0.0)
    # u_2: the second column made orthogonal to u_1, or any unit vector orthogonal to it
    dot = u[0, 0] * w[0, 1] + u[1, 0] * w[1, 1] + u[2, 0] * w[2, 1]
    for i in range(3):
        u[i, 1] = w[i, 1] - dot * u[i, 0]
    norm = np.sqrt(u[0, 1] ** 2 + u[1, 1] ** 2 + u[2, 1] ** 2)
    if norm <= eps * s[0] or norm == 0.0:
        k = 0  # the axis least aligned with u_1
        for i in (1, 2):
            if abs(u[i, 0]) < abs(u[k, 0]):
                k = i
        for i in range(3):
            u[i, 1] = (1.0 if i == k else 0.0) - u[k, 0] * u[i, 0]
        norm = np.sqrt(u[0, 1] ** 2 + u[1, 1] ** 2 + u[2, 1] ** 2)
    for i in range(3):
        u[i, 1] /= norm
    # u_3 = ±u_1 × u_2, the sign of the third column of a
    u[0, 2] = u[1, 0] * u[2, 1] - u[2, 0] * u[1, 1]
    u[1, 2] = u[2, 0] * u[0, 1] - u[0, 0] * u[2, 1]
    u[2, 2] = u[0, 0] * u[1, 1] - u[1, 0] * u[0, 1]
    if u[0, 2] * w[0, 2] + u[1, 2] * w[1, 2] + u[2, 2] * w[2, 2] < 0.0:
        for i in range(3):
            u[i, 2] = -u[i, 2]
    for r in range(3):
        for c in range(3):
            vh[r, c] = v[c, r]


@_jit
def svd3_batch(a, u, s, vh):  # type: ignore[no-untyped-def]
    """:func:`svd3` of each matrix ``a[b]`` of ``(B, 3, 3)`` into ``u[b]``, ``s[b]``, ``vh[b]``."""
    w, v = np.empty((3, 3)), np.empty((3, 3))
    for b in range(a.shape[0]):
        svd3(a[b], u[b], s[b], vh[b], w, v)
