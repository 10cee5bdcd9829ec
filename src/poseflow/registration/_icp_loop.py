"""ICP at one correspondence distance: an early-exit loop on the CPU, fixed steps elsewhere.

On the CPU the batch shrinks as instances stop, and an iteration is two compiled passes over the
points (:mod:`poseflow.registration._icp_cpu`: moving the source; pairing it with the moments
Procrustes needs) around a :class:`~poseflow.geometry.neighbors.NeighborTracker` search, which
searches its k-d tree again only for the points whose nearest neighbour may have changed (same
answers), then a compiled pass over the batch that solves Procrustes from the moments; the
stopping rule and the bookkeeping are numpy, computing as the tensor ops would (float32 and
float64 points need one tensor op per iteration, a square root). On CUDA, where small clouds
make ICP launch-bound, every iteration is the same masked step on a brute-force search, captured
once as CUDA graphs and replayed (same results as the early-exit loop).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
import torch

from poseflow._checks import check_mask, check_same, check_tensor
from poseflow.geometry.neighbors import NeighborIndex, NeighborTracker
from poseflow.registration.procrustes import (
    is_well_posed,
    procrustes_moments,
    rigid_from_svd,
    zero_masked_points,
)
from poseflow.registration.result import RegistrationResult

__all__ = [
    "Arithmetic",
    "ICPProblem",
    "Pairs",
    "Scale",
    "ScaleState",
    "goes_on",
    "run_scale",
    "run_scale_fixed",
]


class Scale(NamedTuple):
    """One scale of ICP: its correspondence distance, iteration cap and stopping thresholds."""

    distance: float
    max_iterations: int
    relative_fitness: float
    relative_rmse: float


@dataclass
class ScaleState:
    """Per-instance ICP state at the current transforms."""

    T: torch.Tensor  # (B, 4, 4)
    inliers: torch.Tensor  # (B, N) bool
    fitness: torch.Tensor  # (B,)
    rmse: torch.Tensor  # (B,)
    iterations: torch.Tensor  # (B,) int64
    valid: torch.Tensor  # (B,) bool


class Pairs(NamedTuple):
    """The pairs in range of some batch items under their transforms, as numpy arrays (CPU)."""

    inliers: np.ndarray  # (B', N) bool
    fitness: np.ndarray  # (B',) in the points' dtype (see Arithmetic)
    rmse: np.ndarray  # (B',) likewise
    stats: np.ndarray  # (B', 2) float64: the number of pairs and their sum of squared distances
    mu: np.ndarray  # (B', 2, 3) float64: the source and target centroids of the pairs
    cov: np.ndarray  # (B', 3, 3) float64: their cross-covariance

    def select(self, keep: np.ndarray) -> Pairs:
        """The pairs of the batch items where ``keep`` ``(B',)`` is True."""
        return Pairs(*(x[keep] for x in self))


class Arithmetic:
    """Tensor arithmetic in a floating-point dtype, reproduced on numpy arrays.

    Calling it rounds an array to the dtype; applied after each numpy operation, it gives what
    the tensor operation in that dtype gives. numpy computes in float16, float32 and float64
    itself (the rounding then only converts); bfloat16 is computed in float32 and rounded by
    torch, as torch's CPU kernels compute it. Square roots are torch's (:meth:`sqrt`).
    """

    def __init__(self, dtype: torch.dtype) -> None:
        self.dtype = dtype
        self.eps = torch.finfo(dtype).eps
        bf16 = dtype == torch.bfloat16
        self.array_dtype = (
            np.dtype(np.float32) if bf16 else torch.empty(0, dtype=dtype).numpy().dtype
        )

    def __call__(self, x: np.ndarray | float) -> np.ndarray:
        """``x`` rounded to the dtype, as an array of :attr:`array_dtype`."""
        if self.dtype != torch.bfloat16:
            return np.asarray(x, dtype=self.array_dtype)
        return torch.from_numpy(np.asarray(x)).to(self.dtype).to(torch.float32).numpy()

    def sqrt(self, x: np.ndarray) -> np.ndarray:
        """The square roots of ``x`` (values of the dtype) as the tensor op computes them.

        Its CPU kernels are not always correctly rounded (numpy's are), and the stopping rule
        compares RMSEs.
        """
        root = torch.from_numpy(x).to(self.dtype).sqrt()
        return root.to(torch.float32).numpy() if self.dtype == torch.bfloat16 else root.numpy()


@dataclass
class ICPProblem:
    """Validated inputs shared by all scales, with the target's search structure."""

    source: torch.Tensor  # (B, N, 3), masked points zeroed
    target: torch.Tensor  # (B, M, 3), masked points zeroed
    source_valid: torch.Tensor  # (B, N) bool
    n_valid: torch.Tensor  # (B,) valid source points, as the dtype
    init: torch.Tensor  # (B, 4, 4)
    index: NeighborIndex
    _source64: np.ndarray | None = None

    @property
    def B(self) -> int:
        return self.source.shape[0]

    @classmethod
    def make(
        cls,
        source: torch.Tensor,
        target: torch.Tensor,
        init: torch.Tensor | None,
        source_mask: torch.Tensor | None,
        target_mask: torch.Tensor | None,
    ) -> ICPProblem:
        sizes = check_tensor(source, "source", ("B", "N", 3))
        check_tensor(target, "target", ("B", "M", 3), sizes=sizes)
        check_same(("source", source), ("target", target))
        B, N = sizes["B"], sizes["N"]
        if init is None:
            init = torch.eye(4, dtype=source.dtype, device=source.device).expand(B, 4, 4)
        check_tensor(init, "init", ("B", 4, 4), finite=True, sizes=sizes)
        check_same(("source", source), ("init", init))
        for mask, name, letter in (
            (source_mask, "source_mask", "N"),
            (target_mask, "target_mask", "M"),
        ):
            if mask is not None:
                check_mask(mask, name, ("B", letter), sizes)
                check_same(("source", source), (name, mask), dtype=False)
        source = zero_masked_points(source, source_mask, "source")
        target = zero_masked_points(target, target_mask, "target")
        if target.shape[1] == 0:
            # No target point at all: one masked stand-in, so that every instance finds no pair
            # and is reported invalid, as an instance whose target mask is all False is.
            target = target.new_zeros(B, 1, 3)
            target_mask = torch.zeros(B, 1, dtype=torch.bool, device=target.device)
        if source_mask is None:
            source_mask = torch.ones(B, N, dtype=torch.bool, device=source.device)
        return cls(
            source=source.detach(),
            target=target.detach(),
            source_valid=source_mask,
            n_valid=source_mask.sum(-1).to(source.dtype),
            init=init.detach(),
            index=NeighborIndex(target.detach(), target_mask),
        )

    def evaluate_cpu(
        self, T: np.ndarray, items: np.ndarray, tracker: NeighborTracker, real: Arithmetic
    ) -> Pairs:
        """The pairs in range of the batch items ``items`` ``(B',)`` under ``T`` ``(B', 4, 4)``.

        ``T`` holds values of the points' dtype; the fitness and RMSE are computed as tensor ops
        in that dtype would compute them (``real``).
        """
        from poseflow.registration._icp_cpu import move, pair_moments  # numba: when needed

        source, valid = self.source64(), self.source_valid.numpy()
        Bq, N = len(items), source.shape[1]
        q = np.empty((3, Bq, N))
        move(source, T.astype(np.float64), items, q)
        dist, nearest = tracker.query_columns(q, items)
        inliers = np.empty((Bq, N), dtype=bool)
        stats, mu, cov = np.empty((Bq, 2)), np.empty((Bq, 2, 3)), np.empty((Bq, 3, 3))
        pair_moments(
            source, valid, self.index.columns(), nearest, dist, items, tracker.max_distance,
            inliers, stats, mu, cov,
        )  # fmt: skip
        count, d2 = real(stats).T
        n_valid = real(valid[items].sum(-1))
        fitness = real(count / np.maximum(n_valid, 1))
        rmse = real.sqrt(real(d2 / np.maximum(count, 1)))
        return Pairs(inliers, fitness, rmse, stats, mu, cov)

    def source64(self) -> np.ndarray:
        """The source as a float64 array ``(B, N, 3)``, made once."""
        if self._source64 is None:
            self._source64 = np.ascontiguousarray(self.source.to(torch.float64).numpy())
        return self._source64

    def evaluate_unchecked(
        self, T: torch.Tensor, distance: float
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`evaluate` for the whole batch with no check and no host synchronisation."""
        moved = torch.baddbmm(T[:, None, :3, 3], self.source, T[:, :3, :3].transpose(1, 2))
        dist, idx = self.index.query_unchecked(moved, 1, distance)
        return self._pairs(slice(None), dist, idx, distance)

    def _pairs(
        self, sel: slice | torch.Tensor, dist: torch.Tensor, idx: torch.Tensor, distance: float
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        inliers = (dist[..., 0] <= distance) & self.source_valid[sel]
        matched = self.target[sel].gather(1, idx.expand(-1, -1, 3))
        count = inliers.sum(-1).to(dist.dtype)
        fitness = count / self.n_valid[sel].clamp_min(1)
        d2 = torch.where(inliers, dist[..., 0], 0).square().sum(-1)
        return inliers, matched, fitness, (d2 / count.clamp_min(1)).sqrt()

    def result(self, state: ScaleState) -> RegistrationResult:
        """Final record: hopeless instances get the identity, zero fitness and no inliers."""
        ok = state.valid
        eye = torch.eye(4, dtype=state.T.dtype, device=state.T.device).expand(self.B, 4, 4)
        return RegistrationResult(
            transformation=torch.where(ok[:, None, None], state.T, eye),
            fitness=torch.where(ok, state.fitness, 0),
            inlier_rmse=torch.where(ok, state.rmse, 0),
            inliers=state.inliers & ok[:, None],
            num_iterations=state.iterations,
            valid=ok,
        )


def run_scale(problem: ICPProblem, T: torch.Tensor, scale: Scale) -> ScaleState:
    """Iterate ICP at one correspondence distance from ``T`` on the CPU; the state at the end.

    The transforms, fitness and RMSE are held in the points' dtype as numpy arrays, computed as
    the tensor ops would (see :class:`Arithmetic`); the stopping rule is :func:`goes_on`.
    """
    from poseflow.registration._icp_cpu import rigid_from_moments  # numba: when needed

    distance, max_iterations, relative_fitness, relative_rmse = scale
    real = Arithmetic(T.dtype)
    relative_fitness, relative_rmse = real(relative_fitness), real(relative_rmse)
    tracker = NeighborTracker(problem.index, max_distance=distance)
    B = problem.B
    items = np.arange(B)
    T_now = real(T.detach().to(torch.float64).numpy().copy())  # (B, 4, 4)
    now = problem.evaluate_cpu(T_now, items, tracker, real)
    inliers, fitness, rmse = now.inliers, now.fitness, now.rmse
    iterations = np.zeros(B, dtype=np.int64)
    solvable = np.ones(B, dtype=bool)
    going = now.stats[:, 0] >= 3
    for _ in range(max_iterations):
        if not going.any():
            break
        # Only the instances still iterating are solved and searched.
        items, now = items[going], now.select(going)
        T_new = T_now[items].astype(np.float64)
        ok = np.empty(len(items), dtype=bool)
        rigid_from_moments(now.mu, now.cov, now.stats, real.eps, T_new, ok)
        T_new = real(T_new)
        new = problem.evaluate_cpu(T_new, items, tracker, real)
        going = goes_on(
            ok, new.stats[:, 0], fitness[items], rmse[items], new.fitness, new.rmse,
            relative_fitness, relative_rmse, rounded=real,
        )  # fmt: skip
        T_now[items], inliers[items] = T_new, new.inliers
        fitness[items], rmse[items] = new.fitness, new.rmse
        iterations[items] += ok
        solvable[items] = ok
        now = new
    return ScaleState(
        T=torch.from_numpy(T_now).to(real.dtype),
        inliers=torch.from_numpy(inliers),
        fitness=torch.from_numpy(fitness).to(real.dtype),
        rmse=torch.from_numpy(rmse).to(real.dtype),
        iterations=torch.from_numpy(iterations),
        valid=torch.from_numpy(solvable & (inliers.sum(-1) >= 3)),
    )


def goes_on(
    ok: Any,
    pairs: Any,
    fitness: Any,
    rmse: Any,
    new_fitness: Any,
    new_rmse: Any,
    relative_fitness: Any,
    relative_rmse: Any,
    *,
    rounded: Callable[[Any], Any] | None = None,
) -> Any:
    """Which instances iterate on, ``(B,)`` bool: Open3D's stopping rule, on tensors or arrays.

    An instance goes on when its step was solvable (``ok``), its fitness or inlier RMSE still
    moved by at least the relative thresholds, and at least 3 ``pairs`` remain. ``rounded``
    rounds the two changes to the points' dtype where the arrays hold it wider (bfloat16 in
    float32, :class:`Arithmetic`).
    """
    change_fitness, change_rmse = new_fitness - fitness, new_rmse - rmse
    if rounded is not None:
        change_fitness, change_rmse = rounded(change_fitness), rounded(change_rmse)
    converged = (abs(change_fitness) < relative_fitness) & (abs(change_rmse) < relative_rmse)
    return ok & ~converged & (pairs >= 3)


def run_scale_fixed(
    problem: ICPProblem, T: torch.Tensor, scale: Scale, *, capture: bool
) -> ScaleState:
    """:func:`run_scale` as ``max_iterations`` identical masked steps on fixed buffers.

    Instances that stop are frozen by masks instead of leaving the batch, so every step runs the
    same kernels on the same buffers. On CUDA (``capture``) the two halves of a step, before and
    after the 3 x 3 SVDs (which cannot be captured), are captured once as CUDA graphs and
    replayed, which removes most of the launch overhead that dominates ICP on small clouds
    there. Same results as :func:`run_scale`.
    """
    distance, max_iterations, relative_fitness, relative_rmse = scale
    dtype, B = T.dtype, problem.B
    T = T.clone()
    inliers, matched, fitness, rmse = problem.evaluate_unchecked(T, distance)
    iterations = torch.zeros(B, dtype=torch.int64, device=T.device)
    solvable = torch.ones(B, dtype=torch.bool, device=T.device)
    active = inliers.sum(-1) >= 3
    state = (T, inliers, matched, fitness, rmse, iterations, solvable, active)
    f64 = {"dtype": torch.float64, "device": T.device}
    mu_s, mu_d = torch.zeros(B, 3, **f64), torch.zeros(B, 3, **f64)
    cov, U, Vh = (torch.zeros(B, 3, 3, **f64) for _ in range(3))
    S = torch.zeros(B, 3, **f64)

    def moments() -> None:
        m_s, m_d, c, _, _ = procrustes_moments(problem.source, matched, inliers.to(dtype))
        mu_s.copy_(m_s)
        mu_d.copy_(m_d)
        cov.copy_(c)

    def svd() -> None:
        for out, value in zip((U, S, Vh), torch.linalg.svd(cov)):
            out.copy_(value)

    def finish() -> None:
        ok = is_well_posed(inliers.to(dtype), mu_s, mu_d, S)
        T_new = rigid_from_svd(mu_s, mu_d, U, S, Vh, ok, dtype=dtype)
        T_new = torch.where(ok[:, None, None], T_new, T)
        new_inliers, new_matched, new_fitness, new_rmse = problem.evaluate_unchecked(
            T_new, distance
        )
        going = goes_on(
            ok, new_inliers.sum(-1), fitness, rmse, new_fitness, new_rmse, relative_fitness,
            relative_rmse,
        )  # fmt: skip
        now = active.clone()
        T.copy_(torch.where(now[:, None, None], T_new, T))
        inliers.copy_(torch.where(now[:, None], new_inliers, inliers))
        matched.copy_(torch.where(now[:, None, None], new_matched, matched))
        fitness.copy_(torch.where(now, new_fitness, fitness))
        rmse.copy_(torch.where(now, new_rmse, rmse))
        iterations.add_((now & ok).to(torch.int64))
        solvable.copy_(torch.where(now, ok, solvable))
        active.copy_(now & going)

    def step() -> None:
        moments()
        svd()
        finish()

    graphs = _capture((moments, finish), step, state) if capture else None
    for _ in range(max_iterations):
        if graphs is None:
            step()
        else:
            graphs[0].replay()
            svd()
            graphs[1].replay()
    valid = solvable & (inliers.sum(-1) >= 3)
    return ScaleState(T, inliers, fitness, rmse, iterations, valid)


#: Set False after a failed capture (e.g. a library call that cannot be captured), so that ICP
#: runs its fixed steps eagerly from then on.
_CUDA_GRAPHS = {"usable": True}


def _capture(
    parts: Sequence[Callable[[], None]], warm_up: Callable[[], None], state: Sequence[torch.Tensor]
) -> list[Any] | None:
    """Each of ``parts`` captured as a CUDA graph, or None where capturing failed.

    ``warm_up`` runs once first, outside the capture (workspaces, library handles); ``state`` is
    restored afterwards, so the tensors hold what they held before.
    """
    if not _CUDA_GRAPHS["usable"]:
        return None
    saved = [t.clone() for t in state]
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        warm_up()
    torch.cuda.current_stream().wait_stream(side)
    graphs: list[Any] | None = []
    try:
        for part in parts:
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph):
                part()
            graphs.append(graph)  # type: ignore[union-attr]
    except RuntimeError:
        _CUDA_GRAPHS["usable"] = False
        graphs = None
    for t, value in zip(state, saved):
        t.copy_(value)
    return graphs
