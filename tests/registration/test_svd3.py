"""The compiled 3 × 3 SVD against LAPACK's (``torch.linalg.svd``), and its use in Procrustes."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from poseflow.registration.procrustes import procrustes_moments, rigid_from_svd, svd3x3

KINDS = ("general", "rank2", "rank1", "zero", "repeated", "reflection", "diagonal")
f64 = torch.float64


def _matrix(kind: str, g: torch.Generator, scale: float) -> torch.Tensor:
    """One 3 × 3 float64 matrix of a kind."""
    a = torch.randn(3, 3, generator=g, dtype=f64)
    if kind == "rank2":  # e.g. the cross-covariance of three points
        x, y = torch.randn(2, 3, 3, generator=g, dtype=f64)
        a = x[:, :1] @ y[:1] + x[:, 1:2] @ y[1:2]
    elif kind == "rank1":
        a = torch.randn(3, 1, generator=g, dtype=f64) @ torch.randn(1, 3, generator=g, dtype=f64)
    elif kind == "zero":
        a = torch.zeros(3, 3, dtype=f64)
    elif kind == "repeated":  # two equal singular values
        q, _ = torch.linalg.qr(a)
        r, _ = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=f64))
        a = q @ torch.diag(torch.tensor([2.0, 2.0, 0.5], dtype=f64)) @ r
    elif kind == "reflection":
        q, _ = torch.linalg.qr(a)
        a = q * torch.sign(torch.linalg.det(q)) * torch.tensor([1.0, 1.0, -1.0], dtype=f64)
    elif kind == "diagonal":
        a = torch.diag(torch.randn(3, generator=g, dtype=f64))
    return a * scale


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    kinds=st.lists(st.sampled_from(KINDS), min_size=1, max_size=8),
    scale=st.sampled_from([1e-8, 1e-3, 1.0, 1e4]),
)
def test_factors_reproduce_the_matrix_and_lapacks_singular_values(seed, kinds, scale):
    g = torch.Generator().manual_seed(seed)
    A = torch.stack([_matrix(k, g, scale) for k in kinds])
    U, S, Vh = svd3x3(A)
    eye = torch.eye(3, dtype=f64).expand_as(A)
    tol = 1e-12 * max(float(A.abs().max()), 1e-300)
    torch.testing.assert_close(U.mT @ U, eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(Vh @ Vh.mT, eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(U @ torch.diag_embed(S) @ Vh, A, atol=tol, rtol=0)
    assert (S >= 0).all() and (S[:, :-1] >= S[:, 1:]).all()
    torch.testing.assert_close(S, torch.linalg.svdvals(A), atol=tol, rtol=0)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(3, 30), offset=st.sampled_from([0.0, 1e3]))
def test_procrustes_rotation_equals_lapacks(seed, n, offset):
    # Minimal samples (n = 3, rank-2 cross-covariance) and larger noisy ones, some reflected.
    g = torch.Generator().manual_seed(seed)
    src = torch.randn(8, n, 3, generator=g, dtype=f64) + offset
    R = torch.linalg.qr(torch.randn(8, 3, 3, generator=g, dtype=f64))[0]
    dst = src @ R.mT + 0.05 * torch.randn(8, n, 3, generator=g, dtype=f64)
    dst[::2, :, 2] *= -1  # the least-squares orthogonal map is a reflection there
    mu_s, mu_d, cov, _, _ = procrustes_moments(src, dst, torch.ones(8, n, dtype=f64))
    ok = torch.ones(8, dtype=torch.bool)
    fast = rigid_from_svd(mu_s, mu_d, *svd3x3(cov), ok, dtype=f64)
    lapack = rigid_from_svd(mu_s, mu_d, *torch.linalg.svd(cov), ok, dtype=f64)
    torch.testing.assert_close(fast, lapack, atol=1e-9 * (1 + offset), rtol=0)
    assert (torch.linalg.det(fast[:, :3, :3]) > 0).all()


def test_without_matrices_and_with_gradient_lapack_is_used():
    U, S, _ = svd3x3(torch.zeros(0, 3, 3, dtype=f64))
    assert U.shape == (0, 3, 3) and S.shape == (0, 3)
    A = torch.randn(2, 3, 3, dtype=f64, requires_grad=True)
    _, S, _ = svd3x3(A)
    S.sum().backward()
    assert A.grad is not None


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_on_cuda_lapack_is_used():
    A = torch.randn(4, 3, 3, dtype=f64, device="cuda")
    U, S, Vh = svd3x3(A)
    torch.testing.assert_close(U @ torch.diag_embed(S) @ Vh, A)
