"""UMAP's out-of-sample transform in torch: new points embedded beside a fitted embedding.

The steps of :meth:`~poseflow.features.reducers.UMAPReducer.transform`, on the CPU or CUDA:

1. :func:`nearest_training_points`: exact k nearest neighbours of each new point among the
   training points (one matrix product per chunk, cosine or Euclidean);
2. :func:`fuzzy_membership`: UMAP's membership weights ``exp(−d / σ)``, ``σ`` found per point by
   a vectorised bisection so that the weights sum to ``log2(k)`` (umap-learn's rule for new
   points); the initial position is the membership-weighted mean of the neighbours' embeddings;
3. :func:`refine_embedding` (optional): epochs of UMAP's cross-entropy layout optimisation,
   vectorised: per epoch every new point takes one step along the *expected* SGD update of an
   umap-learn epoch (attraction to its strongest neighbours' embeddings at the rate umap-learn
   samples each edge, ``w / max w``, and ``negative_sample_rate`` repulsions per sampled edge
   estimated from a few random embedded training points, both with UMAP's ``1 / (1 + a d^{2b})``
   kernel and gradient clipping), the training embedding held fixed.
"""

from __future__ import annotations

import torch
from torch.nn import functional as F

__all__ = ["fuzzy_membership", "nearest_training_points", "refine_embedding"]


def nearest_training_points(
    x: torch.Tensor, train: torch.Tensor, k: int, metric: str, chunk_size: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact k nearest training points of new points, chunk by chunk.

    Args:
        x: new points ``(Q, G)``.
        train: training points ``(N, G)``.
        k: neighbours per point (at most ``N`` are returned).
        metric: ``"cosine"`` (distance ``1 - cos``) or ``"euclidean"``.
        chunk_size: new points per block (bounds memory to ``chunk_size × N`` scores).

    Returns:
        Distances ``(Q, k)`` in ascending order and training indices ``(Q, k)``: the top-k of one
        score matrix per chunk, the distances recomputed on the k kept.
    """
    k = min(k, train.shape[0])
    dists, idx = [], []
    if metric == "cosine":
        ref = F.normalize(train, dim=-1)
    else:
        ref = train
        half_sq = 0.5 * train.pow(2).sum(dim=1)
    for start in range(0, x.shape[0], chunk_size):
        block = x[start : start + chunk_size]
        if metric == "cosine":
            block = F.normalize(block, dim=-1)
            sim, ids = (block @ ref.T).topk(k, dim=1)
            d = (1.0 - sim).clamp_min(0.0)
        else:
            _, ids = (block @ ref.T - half_sq).topk(k, dim=1)  # max x·t − |t|²/2
            d = (block[:, None, :] - ref[ids]).norm(dim=-1)
            d, order = d.sort(dim=1)
            ids = ids.gather(1, order)
        dists.append(d)
        idx.append(ids)
    return torch.cat(dists), torch.cat(idx)


def fuzzy_membership(dist: torch.Tensor, target: float, iterations: int = 32) -> torch.Tensor:
    """UMAP's fuzzy membership of new points: ``exp(−d / σ)`` with ``Σ = target`` per row.

    ``σ`` is found by bisection on all rows of ``dist`` ``(Q, k)`` at once (umap-learn uses no
    local-connectivity offset for new points); rows whose distances are all zero get uniform
    weights. Returns the weights ``(Q, k)``.
    """
    lo = torch.zeros(dist.shape[0], 1, dtype=dist.dtype, device=dist.device)
    hi = torch.full_like(lo, float("inf"))
    mid = torch.ones_like(lo)
    for _ in range(iterations):
        total = torch.exp(-dist / mid).sum(dim=1, keepdim=True)
        too_big = total > target
        hi = torch.where(too_big, mid, hi)
        lo = torch.where(too_big, lo, mid)
        mid = torch.where(torch.isinf(hi), mid * 2.0, (lo + hi) / 2.0)
    w = torch.exp(-dist / mid)
    return torch.where(w.sum(dim=1, keepdim=True) > 0, w, torch.ones_like(w))


def refine_embedding(
    y: torch.Tensor,
    embedding: torch.Tensor,
    idx: torch.Tensor,
    weights: torch.Tensor,
    *,
    a: float,
    b: float,
    epochs: int,
    learning_rate: float,
    negative_sample_rate: float,
    negative_draws: int,
    optimize_neighbors: int,
    seed: int,
) -> torch.Tensor:
    """Epochs of UMAP's layout optimisation of new points, the training embedding held fixed.

    Args:
        y: the new points' initial embedding ``(Q, D)``.
        embedding: the training embedding ``(N, D)``.
        idx: each new point's neighbours among the training points ``(Q, k)``.
        weights: their membership weights ``(Q, k)`` (:func:`fuzzy_membership`).
        a: the low-dimensional kernel's ``a``.
        b: its ``b``.
        epochs: optimisation epochs; the step decays linearly from ``learning_rate`` to 0.
        learning_rate: the first epoch's step.
        negative_sample_rate: repulsive samples per unit of membership, as in umap-learn.
        negative_draws: random training points per new point and epoch estimating the repulsion.
        optimize_neighbors: strongest edges per new point kept in the optimisation.
        seed: seeds the negative draws (on ``y``'s device).

    Returns:
        The refined embedding ``(Q, D)``.
    """
    emb = embedding
    # umap-learn samples edge (i, j) every max(w) / w_ij epochs and draws
    # negative_sample_rate negatives per sample; one step here is that expectation. Forces are
    # sums c_j (y - e_j) = (sum c_j) y - sum c_j e_j, computed with batched matrix products on
    # (Q, k) coefficients (no (Q, k, D) temporaries); each edge's force is clipped to norm 4.
    rate = weights / weights.max()
    rate = torch.where(rate >= 1.0 / 100.0, rate, torch.zeros_like(rate))
    keep = min(optimize_neighbors, rate.shape[1])
    rate, order = rate.topk(keep, dim=1)
    neighbours = emb[idx.gather(1, order)]  # (Q, k', D)
    nb_sq = neighbours.pow(2).sum(-1)
    emb_sq = emb.pow(2).sum(-1)
    neg_weight = rate.sum(dim=1, keepdim=True) * (negative_sample_rate / negative_draws)
    gen = torch.Generator(device=y.device)
    gen.manual_seed(seed)
    Q, S = y.shape[0], negative_draws
    for epoch in range(epochs):
        alpha = learning_rate * (1.0 - epoch / epochs)
        y_sq = y.pow(2).sum(-1, keepdim=True)
        d2 = (y_sq + nb_sq - 2.0 * (neighbours @ y[..., None])[..., 0]).clamp_min(1e-12)
        d2b1 = d2.pow(b - 1.0)
        c = (2.0 * a * b) * d2b1 / (1.0 + a * d2b1 * d2)  # attraction pulls y to e_j
        c = c * (4.0 / (c * d2.sqrt())).clamp(max=1.0) * rate
        pull = (c[:, None, :] @ neighbours)[:, 0] - c.sum(1, keepdim=True) * y
        neg = torch.randint(0, emb.shape[0], (Q * S,), generator=gen, device=y.device)
        e_neg = emb[neg].view(Q, S, -1)
        d2n = (y_sq + emb_sq[neg].view(Q, S) - 2.0 * (e_neg @ y[..., None])[..., 0]).clamp_min(0)
        cn = (2.0 * b) / ((0.001 + d2n) * (1.0 + a * d2n.pow(b)))
        cn = cn * (4.0 / (cn * d2n.sqrt()).clamp_min(1e-12)).clamp(max=1.0) * neg_weight
        push = cn.sum(1, keepdim=True) * y - (cn[:, None, :] @ e_neg)[:, 0]
        y = y + alpha * (pull + push).clamp(-4.0, 4.0)  # umap-learn's step bound
    return y
