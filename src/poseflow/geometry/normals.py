"""Surface normals of point clouds by local PCA, with a closed-form 3 x 3 eigensolver."""

from __future__ import annotations

import math

import torch

from poseflow._checks import check_mask, check_tensor
from poseflow.errors import ValueRangeError
from poseflow.geometry.neighbors import NeighborIndex

__all__ = ["estimate_normals"]


def estimate_normals(
    points: torch.Tensor,
    mask: torch.Tensor | None = None,
    *,
    k: int = 30,
    viewpoint: torch.Tensor | tuple[float, float, float] | None = (0.0, 0.0, 0.0),
) -> torch.Tensor:
    """Unit normals by PCA over each point's ``k`` nearest valid neighbours (itself included).

    The normal is the eigenvector of the neighbourhood covariance with the smallest eigenvalue,
    turned to face ``viewpoint`` (the camera centre by default, right for camera-frame clouds).

    Args:
        points: clouds ``(B, N, 3)``.
        mask: ``(B, N)`` bool validity.
        k: neighbourhood size (at least 3).
        viewpoint: point ``(3,)`` or ``(B, 3)`` the normals should face, or None to leave the
            sign as the eigen-solver returns it.

    Returns:
        Normals ``(B, N, 3)``; zero at masked points and at points with fewer than 3 valid
        neighbours.

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> pts = torch.rand(1, 200, 3, generator=g) * torch.tensor([1.0, 1.0, 0.0]) + 2.0
        >>> n = estimate_normals(pts, k=10)
        >>> bool(torch.allclose(n[0, :, 2], torch.full((200,), -1.0), atol=1e-5))
        True
    """
    sizes = check_tensor(points, "points", ("B", "N", 3))
    B, N = sizes["B"], sizes["N"]
    if isinstance(k, bool) or not isinstance(k, int) or k < 3:
        raise ValueRangeError(f"k must be an integer >= 3, got {k!r}")
    if mask is not None:
        check_mask(mask, "mask", ("B", "N"), sizes)
    pts = points if mask is None else torch.where(mask.unsqueeze(-1), points, 0.0)
    if N == 0:
        return torch.zeros_like(points)
    dist, nn = NeighborIndex(pts, mask).neighbors_of_valid_points(min(k, N))
    found = torch.isfinite(dist)
    # one flat index_select (a gather with an expanded index is several times slower)
    rows = nn + N * torch.arange(B, device=nn.device).reshape(B, 1, 1)
    nbr64 = pts.to(torch.float64).reshape(B * N, 3)[rows.reshape(-1)].reshape(B, N, -1, 3)
    w = found.to(torch.float64).unsqueeze(-1)
    cnt = w.sum(2)
    mean = (nbr64 * w).sum(2) / cnt.clamp(min=1)
    dev = (nbr64 - mean.unsqueeze(2)) * w
    cov = dev.transpose(-1, -2) @ dev
    normals = _smallest_eigenvector(cov)
    ok = cnt.squeeze(-1) >= 3
    if mask is not None:
        ok &= mask
    if viewpoint is not None:
        vp = torch.as_tensor(viewpoint, dtype=torch.float64, device=points.device)
        vp = vp.reshape(-1, 1, 3) if vp.dim() == 2 else vp.reshape(1, 1, 3)
        flip = ((vp - pts.to(torch.float64)) * normals).sum(-1) < 0
        normals = torch.where(flip.unsqueeze(-1), -normals, normals)
    normals = torch.where(ok.unsqueeze(-1), normals, 0.0)
    return normals.to(points.dtype)


def _smallest_eigenvector(A: torch.Tensor) -> torch.Tensor:
    """Unit eigenvectors of the smallest eigenvalue of symmetric 3 x 3 matrices, in closed form.

    Eberly's non-iterative solver ("A Robust Eigensolver for 3 x 3 Symmetric Matrices", Geometric
    Tools, 2014; Open3D's normals use it too): the eigenvalues from the trigonometric solution of
    the characteristic cubic of the matrix scaled to entries in ``[-1, 1]``; the eigenvector of
    the eigenvalue farther from the other two from cross products of rows of ``A - lambda I``,
    the middle one in that vector's orthogonal complement, the third their cross product. Where
    the smallest eigenvalue is repeated, any unit vector of its eigenspace is an answer.
    Elementwise tensor work only, an order of magnitude faster than ``torch.linalg.eigh`` on
    many small matrices.

    Args:
        A: symmetric matrices ``(..., 3, 3)``.

    Returns:
        Unit vectors ``(..., 3)``, ``A v = lambda_min v``; ``(0, 0, 1)`` for multiples of the
        identity (zero included).
    """
    scale = A.abs().amax((-1, -2), keepdim=True)
    A = A / torch.where(scale > 0, scale, 1.0)
    a00, a01, a02 = A[..., 0, 0], A[..., 0, 1], A[..., 0, 2]
    a11, a12, a22 = A[..., 1, 1], A[..., 1, 2], A[..., 2, 2]
    q = (a00 + a11 + a22) / 3
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p = ((b00**2 + b11**2 + b22**2 + 2 * (a01**2 + a02**2 + a12**2)) / 6).sqrt()
    round_ = p > 0  # False: A is a multiple of the identity, every vector an eigenvector
    p_safe = torch.where(round_, p, 1.0)
    c00 = b11 * b22 - a12 * a12
    c01 = a01 * b22 - a12 * a02
    c02 = a01 * a12 - b11 * a02
    half_det = ((b00 * c00 - a01 * c01 + a02 * c02) / p_safe**3 / 2).clamp(-1.0, 1.0)
    angle = torch.acos(half_det) / 3
    beta = torch.stack(  # ascending: 2 cos(angle + 2 pi / 3) <= middle <= 2 cos(angle)
        (2 * torch.cos(angle + 2 * math.pi / 3), torch.zeros_like(angle), 2 * torch.cos(angle)),
        dim=-1,
    )
    beta[..., 1] = -(beta[..., 0] + beta[..., 2])
    lam = q.unsqueeze(-1) + p.unsqueeze(-1) * beta  # (..., 3) ascending
    # The eigenvalue farther from the other two: the largest when half_det >= 0, else the least.
    far_is_top = half_det >= 0
    far = _eigenvector_by_cross(A, torch.where(far_is_top, lam[..., 2], lam[..., 0]))
    mid = _middle_eigenvector(A, far, lam[..., 1])
    third = torch.linalg.cross(mid, far)  # for far = top: the smallest's; else unused
    v = torch.where(far_is_top.unsqueeze(-1), third, far)
    v = v / v.norm(dim=-1, keepdim=True)
    z_axis = torch.tensor([0.0, 0.0, 1.0], dtype=A.dtype, device=A.device)
    return torch.where(round_.unsqueeze(-1), v, z_axis)


def _eigenvector_by_cross(A: torch.Tensor, lam: torch.Tensor) -> torch.Tensor:
    """Unit null vector of ``A - lam I`` (rank 2): the longest cross product of two rows."""
    M = A - lam[..., None, None] * torch.eye(3, dtype=A.dtype, device=A.device)
    r0, r1, r2 = M[..., 0, :], M[..., 1, :], M[..., 2, :]
    crosses = torch.stack(
        (torch.linalg.cross(r0, r1), torch.linalg.cross(r0, r2), torch.linalg.cross(r1, r2)), -2
    )
    sq = crosses.square().sum(-1)  # (..., 3)
    best = sq.argmax(-1, keepdim=True)
    pick = crosses.gather(-2, best.unsqueeze(-1).expand(*best.shape, 3)).squeeze(-2)
    length = sq.gather(-1, best).sqrt()
    return pick / torch.where(length > 0, length, 1.0)


def _middle_eigenvector(A: torch.Tensor, w: torch.Tensor, lam: torch.Tensor) -> torch.Tensor:
    """Unit eigenvector of ``lam`` orthogonal to the unit eigenvector ``w`` (Eberly's method).

    ``A`` restricted to the plane orthogonal to ``w`` is a symmetric 2 x 2 matrix in a basis
    ``(u, v)`` of that plane; the eigenvector is the null vector of that matrix less ``lam``.
    """
    w0, w1, w2 = w[..., 0], w[..., 1], w[..., 2]
    zero = torch.zeros_like(w0)
    first = w0.abs() > w1.abs()
    u = torch.where(
        first.unsqueeze(-1),
        torch.stack((-w2, zero, w0), -1),
        torch.stack((zero, w2, -w1), -1),
    )
    u = u / u.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(A.dtype).tiny)
    v = torch.linalg.cross(w, u)
    Au, Av = (A @ u.unsqueeze(-1)).squeeze(-1), (A @ v.unsqueeze(-1)).squeeze(-1)
    m00 = (u * Au).sum(-1) - lam
    m01 = (u * Av).sum(-1)
    m11 = (v * Av).sum(-1) - lam
    # The null vector of [[m00, m01], [m01, m11]] from its larger row, (m01, -m00) or (m11, -m01).
    use_first = m00.abs() >= m11.abs()
    x = torch.where(use_first, m01, m11)
    y = torch.where(use_first, -m00, -m01)
    length = (x * x + y * y).sqrt()
    degenerate = length == 0  # lam is a double eigenvalue in that plane: any vector of it
    x = torch.where(degenerate, 1.0, x / torch.where(degenerate, 1.0, length))
    y = torch.where(degenerate, 0.0, y / torch.where(degenerate, 1.0, length))
    return x.unsqueeze(-1) * u + y.unsqueeze(-1) * v
