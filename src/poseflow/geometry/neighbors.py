"""Exact k-nearest-neighbour search between batched point clouds.

One entry point, :func:`nearest_neighbors`, picks the fastest exact backend for the device:

- CPU: a k-d tree per batch item, built once per index and searched by compiled code (numba,
  ``poseflow.geometry._tracker_cpu``; large searches run the batch items in parallel threads,
  one item per task) unless the problem is small enough (at most 16,384 query-reference pairs
  per item) that a brute-force distance matrix is cheaper;
- CUDA (and any other device): brute force, the distance matrix built in chunks of query points
  with one matrix multiply each, so memory stays bounded.

:class:`NeighborIndex` builds the search structure once and answers many queries against the same
reference cloud; :class:`NeighborTracker` answers the same queries for a cloud that moves a little
between calls (ICP) while searching again only the points whose answer may have changed.

Distances are Euclidean (not squared). Reference points masked out are never returned; where fewer
than ``k`` valid reference points exist (or none lies within ``max_distance``), the missing
neighbours have distance ``inf`` and index ``0``.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch

from poseflow._checks import check_mask, check_same, check_tensor
from poseflow._threads import get_num_threads
from poseflow.errors import ShapeError, ValueRangeError

__all__ = ["NeighborIndex", "NeighborTracker", "nearest_neighbors"]

#: Problems with at most this many query-reference pairs per batch item use brute force on CPU.
_CPU_BRUTE_FORCE_PAIRS = 1 << 14
#: KD-tree searches of fewer query points than this run on the calling thread.
_PARALLEL_POINTS = 8192
#: Entries of the distance matrix computed at once by the brute-force backend.
_CHUNK_ELEMENTS = 1 << 22


#: The KD-tree query threads by their number; emptied in a forked child, which has no threads.
_POOLS: dict[int, ThreadPoolExecutor] = {}
os.register_at_fork(after_in_child=_POOLS.clear)


def _pool() -> ThreadPoolExecutor | None:
    """The threads that run KD-tree queries of several batch items at once.

    As many as :func:`poseflow.get_num_threads`; None for one thread.
    """
    workers = get_num_threads()
    if workers <= 1:
        return None
    if workers not in _POOLS:
        _POOLS[workers] = ThreadPoolExecutor(workers, thread_name_prefix="poseflow-knn")
    return _POOLS[workers]


class NeighborIndex:
    """A search structure over a batch of reference clouds, built once and queried many times.

    Args:
        reference: reference points, shape ``(B, M, 3)``. Masked-out points may hold any value,
            NaN included; valid points must be finite.
        reference_mask: ``(B, M)`` bool, True for points that may be returned; all by default.
        backend: ``"auto"`` (KD-tree on CPU unless the clouds are tiny, brute force elsewhere),
            ``"kdtree"`` (CPU only) or ``"brute"``.

    Raises:
        ShapeError: wrong shape, dtype or device.
        ValueRangeError: a valid reference point is not finite, or an unknown backend.

    Example:
        >>> ref = torch.tensor([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]])
        >>> index = NeighborIndex(ref)
        >>> dist, idx = index.query(torch.tensor([[[0.9, 0.0, 0.0]]]))
        >>> idx.tolist(), round(dist.item(), 4)
        ([[[1]]], 0.1)
    """

    def __init__(
        self,
        reference: torch.Tensor,
        reference_mask: torch.Tensor | None = None,
        *,
        backend: str = "auto",
    ) -> None:
        sizes = check_tensor(reference, "reference", ("B", "M", 3))
        if reference_mask is not None:
            check_mask(reference_mask, "reference_mask", ("B", "M"), sizes)
            check_same(("reference", reference), ("reference_mask", reference_mask), dtype=False)
            finite_or_masked = torch.isfinite(reference).all(-1) | ~reference_mask
            if not bool(finite_or_masked.all()):
                raise ValueRangeError("reference contains NaN or inf at valid (unmasked) points")
            reference = torch.where(reference_mask[..., None], reference, 0)
        elif reference.numel() and not bool(torch.isfinite(reference).all()):
            raise ValueRangeError("reference contains NaN or inf")
        if backend not in ("auto", "kdtree", "brute"):
            raise ValueRangeError(f"backend must be 'auto', 'kdtree' or 'brute', got {backend!r}")
        if backend == "kdtree" and reference.device.type != "cpu":
            raise ValueRangeError("the 'kdtree' backend runs on CPU tensors only")
        self.reference = reference
        self.reference_mask = reference_mask
        self.backend = backend
        self._ref64: np.ndarray | None = None
        self._columns: np.ndarray | None = None
        self._max_abs: float | None = None
        self._tracker: tuple[np.ndarray, tuple[np.ndarray, ...], np.ndarray] | None = None

    @property
    def batch_size(self) -> int:
        """Number of reference clouds ``B``."""
        return self.reference.shape[0]

    def query(
        self, query: torch.Tensor, *, k: int = 1, max_distance: float | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Find the ``k`` nearest valid reference points of every query point.

        Args:
            query: query points, shape ``(B, N, 3)``, finite, with the reference's device and dtype.
            k: number of neighbours, at least 1.
            max_distance: if given, neighbours farther than this are reported missing (distance
                ``inf``, index ``0``); the KD-tree prunes its search with it, which is faster.

        Returns:
            ``(dist, idx)``: Euclidean distances ``(B, N, k)`` in the query dtype, sorted
            ascending, and indices ``(B, N, k)`` (int64) into the reference's ``M`` axis.

        Raises:
            ShapeError: wrong shape, dtype or device.
            ValueRangeError: NaN/inf query points, ``k < 1`` or ``max_distance <= 0``.
        """
        check_tensor(query, "query", ("B", "N", 3), sizes={"B": self.batch_size})
        check_same(("reference", self.reference), ("query", query))
        if isinstance(k, bool) or not isinstance(k, int) or k < 1:
            raise ValueRangeError(f"k must be an integer >= 1, got {k!r}")
        if max_distance is not None and not max_distance > 0:
            raise ValueRangeError(f"max_distance must be > 0, got {max_distance!r}")
        if query.numel() and not bool(torch.isfinite(query).all()):
            raise ValueRangeError("query contains NaN or inf")
        return self.query_unchecked(query, k, max_distance)

    def neighbors_of_valid_points(self, k: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The ``k`` nearest valid reference points of every valid reference point.

        What :meth:`query` answers for the reference cloud itself, each point among its own
        neighbours, with only the valid points searched for (padding can be most of an item).

        Args:
            k: number of neighbours, at least 1.

        Returns:
            ``(dist, idx)`` ``(B, M, k)`` as :meth:`query` returns them; padded rows have
            ``dist = inf`` and ``idx = 0``.

        Example:
            >>> ref = torch.tensor([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [9.0, 9.0, 9.0]]])
            >>> index = NeighborIndex(ref, torch.tensor([[True, True, False]]))
            >>> dist, idx = index.neighbors_of_valid_points(2)
            >>> idx[0].tolist(), dist[0, 2].tolist()
            ([[0, 1], [1, 0], [0, 0]], [inf, inf])
        """
        if isinstance(k, bool) or not isinstance(k, int) or k < 1:
            raise ValueRangeError(f"k must be an integer >= 1, got {k!r}")
        ref, mask = self.reference, self.reference_mask
        B, M = ref.shape[:2]
        # one batched search where nothing is padded, and on a GPU (which wants one call)
        if mask is None or ref.device.type != "cpu" or bool(mask.all()):
            dist, idx = self.query_unchecked(ref, k, None)
            if mask is not None:
                dist = dist.masked_fill(~mask[..., None], torch.inf)
                idx = idx.masked_fill(~mask[..., None], 0)
            return dist, idx
        dist = torch.full((B, M, k), torch.inf, dtype=ref.dtype)
        idx = torch.zeros(B, M, k, dtype=torch.long)
        rows = [mask[b].nonzero()[:, 0] for b in range(B)]
        items = [b for b in range(B) if len(rows[b])]

        def search(b: int) -> None:
            found = self.query_unchecked(ref[b : b + 1, rows[b]], k, None, torch.tensor([b]))
            dist[b, rows[b]], idx[b, rows[b]] = found[0][0], found[1][0]

        pool = _pool()
        if pool is not None and len(items) > 1 and int(mask.sum()) >= _PARALLEL_POINTS:
            self._tracker_tree()  # built before the threads share it
            list(pool.map(search, items))
        else:
            for b in items:
                search(b)
        return dist, idx

    def query_unchecked(
        self,
        query: torch.Tensor,
        k: int,
        max_distance: float | None,
        items: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`query` without the input checks, for callers that validated their points.

        Args:
            query: finite query points ``(B', N, 3)`` with the reference's device and dtype.
            k: number of neighbours, at least 1.
            max_distance: neighbours farther than this are reported missing, or None.
            items: int64 indices ``(B',)`` into the batch: ``query`` then holds only those batch
                items, in that order, and so does the answer; None for the whole batch.

        Returns:
            ``(dist, idx)`` as :meth:`query` returns them, ``(B', N, k)`` each.
        """
        B, N, M = query.shape[0], query.shape[1], self.reference.shape[1]
        if B == 0 or N == 0 or M == 0:
            dist = torch.full((B, N, k), torch.inf, dtype=query.dtype, device=query.device)
            return dist, torch.zeros(B, N, k, dtype=torch.long, device=query.device)
        if self._use_kdtree(N):
            return self._query_kdtree(query, k, max_distance, items)
        return self._query_brute(query, k, max_distance, items)

    def _use_kdtree(self, n_query: int) -> bool:
        if self.backend != "auto":
            return self.backend == "kdtree"
        if self.reference.device.type != "cpu":
            return False
        return n_query * self.reference.shape[1] > _CPU_BRUTE_FORCE_PAIRS

    def _extent(self) -> float:
        """Largest absolute coordinate of the (valid) reference points."""
        if self._max_abs is None:
            ref = self._reference64()
            self._max_abs = float(np.abs(ref).max(initial=0))
        return self._max_abs

    def _reference64(self) -> np.ndarray:
        """The reference as a float64 array ``(B, M, 3)`` (masked points zeroed)."""
        if self._ref64 is None:
            self._ref64 = self.reference.detach().to(torch.float64).numpy()
        return self._ref64

    def columns(self) -> np.ndarray:
        """The reference as float64 columns ``(3, B * M + 1)`` (CPU), the last one at infinity.

        Item ``b``'s point ``m`` is column ``b * M + m``; masked points are zero.
        """
        if self._columns is None:
            ref = self._reference64().reshape(-1, 3)
            columns = np.concatenate((ref, np.full((1, 3), np.inf))).T
            self._columns = np.ascontiguousarray(columns)
        return self._columns

    def _tracker_tree(self) -> tuple[np.ndarray, tuple[np.ndarray, ...], np.ndarray]:
        """The reference as float64 columns and the compiled tracker's k-d trees, built once.

        Batch items with the same points and mask (one model cloud repeated for each
        hypothesis) share one tree, whose answers are the columns of the first such item.

        Returns ``(columns, tree, root)`` as :func:`poseflow.geometry._tracker_cpu.track`
        takes them.
        """
        if self._tracker is None:
            from poseflow.geometry._tracker_cpu import LEAF_SIZE, build_trees

            columns = self.columns()
            B, M = self.reference.shape[:2]
            valid = (
                np.ones((B, M), dtype=bool)
                if self.reference_mask is None
                else self.reference_mask.cpu().numpy()
            )
            ref = self._reference64()
            first: dict[bytes, int] = {}
            owner = np.array(
                [first.setdefault(ref[b].tobytes() + valid[b].tobytes(), b) for b in range(B)],
                dtype=np.int64,
            )
            own = valid & (owner == np.arange(B))[:, None]  # trees of the first items only
            perm, points, root, nodes = build_trees(columns, own, M, LEAF_SIZE)
            self._tracker = (columns, (perm, points, *nodes), root[owner])
        return self._tracker

    def _query_kdtree(
        self,
        query: torch.Tensor,
        k: int,
        max_distance: float | None,
        items: torch.Tensor | None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        from poseflow.geometry._tracker_cpu import knn  # numba: imported when first needed

        _, tree, root = self._tracker_tree()
        q = np.ascontiguousarray(query.detach().to(torch.float64).numpy())
        ids = np.arange(q.shape[0]) if items is None else items.cpu().numpy().astype(np.int64)
        # points at exactly max_distance are in range: search a hair beyond, then cut
        bound2 = np.inf if max_distance is None else np.nextafter(float(max_distance) ** 2, np.inf)
        dist = np.empty((*q.shape[:2], k))
        idx = np.empty((*q.shape[:2], k), dtype=np.int64)
        M = self.reference.shape[1]

        def run(rows: slice) -> None:
            knn(tree, root, q[rows], ids[rows], bound2, M, dist[rows], idx[rows])

        # The compiled search releases the GIL: one task per batch item keeps the cores busy.
        if len(ids) > 1 and q.shape[0] * q.shape[1] >= _PARALLEL_POINTS and _pool() is not None:
            list(_pool().map(run, [slice(j, j + 1) for j in range(len(ids))]))  # type: ignore[union-attr]
        else:
            run(slice(None))
        if max_distance is not None:
            far = dist > max_distance
            dist[far], idx[far] = np.inf, 0
        return torch.from_numpy(dist).to(query.dtype), torch.from_numpy(idx)

    def _query_brute(
        self,
        query: torch.Tensor,
        k: int,
        max_distance: float | None,
        items: torch.Tensor | None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        ref, mask = self.reference.detach(), self.reference_mask
        if items is not None:
            ref = ref[items]
            mask = None if mask is None else mask[items]
        query = query.detach()
        B, N, M = query.shape[0], query.shape[1], ref.shape[1]
        # Centre on the reference's mean so that |q|^2 - 2 q.r + |r|^2 loses little precision.
        centre = ref.mean(1, keepdim=True)
        ref_c, query_c = ref - centre, query - centre
        ref_sq = ref_c.square().sum(-1)
        if mask is not None:
            ref_sq = ref_sq.masked_fill(~mask, torch.inf)
        kk = min(k, M)
        chunk = max(1, _CHUNK_ELEMENTS // max(1, B * M))
        idx_parts = []
        for start in range(0, N, chunk):
            q = query_c[:, start : start + chunk]
            d2 = torch.baddbmm(ref_sq.unsqueeze(1), q, ref_c.transpose(1, 2), alpha=-2)
            d2 = d2 + q.square().sum(-1, keepdim=True)
            if kk == 1:
                idx_parts.append(d2.argmin(-1, keepdim=True))
            else:
                idx_parts.append(d2.topk(kk, dim=-1, largest=False, sorted=True).indices)
        idx = torch.cat(idx_parts, 1)
        # Exact distances of the chosen neighbours; masked ones (only chosen when too few valid
        # points remain) are reported missing.
        picked = ref_c.gather(1, idx.reshape(B, N * kk, 1).expand(-1, -1, 3)).reshape(B, N, kk, 3)
        dist = (query_c.unsqueeze(2) - picked).norm(dim=-1)
        missing = torch.zeros_like(dist, dtype=torch.bool)
        if mask is not None:
            missing |= ~mask.gather(1, idx.reshape(B, N * kk)).reshape(B, N, kk)
        if max_distance is not None:
            missing |= dist > max_distance
        if kk > 1:
            # Exact distances may reorder near-ties; keep the output sorted.
            dist, order = dist.masked_fill(missing, torch.inf).sort(-1)
            idx, missing = idx.gather(-1, order), missing.gather(-1, order)
        dist = dist.masked_fill(missing, torch.inf)
        idx = idx.masked_fill(missing, 0)
        if kk < k:
            pad = (0, k - kk)
            dist = torch.nn.functional.pad(dist, pad, value=torch.inf)
            idx = torch.nn.functional.pad(idx, pad, value=0)
        return dist, idx


class NeighborTracker:
    """Exact nearest neighbours of a query cloud that moves a little between calls (as in ICP).

    Each call answers exactly what ``index.query(points, k=1, max_distance=max_distance)`` would,
    but on the KD-tree backend it searches the tree again only for the points whose answer may
    have changed. For every point it remembers where it was last searched (its anchor), the
    ``candidates`` nearest reference points there, and a lower bound ``L`` on the distance from
    the anchor to every other reference point. After the point moved by ``delta``, the other
    points are at least ``L - delta`` away, so the nearest candidate, if closer than that, is the
    nearest neighbour; if both are beyond ``max_distance``, nothing is in range. Only the other
    points are searched again. Late ICP iterations then search almost nothing. The test and the
    searches run in one compiled pass over the points (numba, ``poseflow.geometry._tracker_cpu``,
    with its own k-d tree built once per index). Other backends search every point at every
    call.

    Args:
        index: the reference clouds.
        max_distance: neighbours farther than this are reported missing (``inf``, index 0).
        candidates: reference points remembered per query point.
        margin: searches reach ``(1 + margin) * max_distance``, so that points just out of range
            are settled without a search too.

    Example:
        >>> ref = torch.tensor([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]])
        >>> tracker = NeighborTracker(NeighborIndex(ref), max_distance=0.5)
        >>> tracker.query(torch.tensor([[[0.1, 0.0, 0.0], [0.5, 0.9, 0.0]]]))[1].tolist()
        [[[0], [0]]]
        >>> tracker.query(torch.tensor([[[0.8, 0.0, 0.0], [0.5, 0.9, 0.0]]]))[0]
        tensor([[[0.2000],
                 [   inf]]])
    """

    def __init__(
        self,
        index: NeighborIndex,
        *,
        max_distance: float,
        candidates: int = 4,
        margin: float = 0.5,
    ) -> None:
        if not max_distance > 0 or not margin >= 0 or candidates < 1:
            raise ValueRangeError(
                "need max_distance > 0, candidates >= 1 and margin >= 0, got "
                f"{max_distance}, {candidates}, {margin}"
            )
        self.index = index
        self.max_distance = float(max_distance)
        self.candidates = int(candidates)
        self._bound = self.max_distance * (1 + margin)
        # Per batch item and query point: the anchor (3, B, N), the candidates (K, B, N) as columns
        # of the flattened reference (the last, at infinity, for none) and the bound L (B, N).
        self._anchor: np.ndarray | None = None
        self._cand = self._lower = np.empty(0)

    def query(
        self, points: torch.Tensor, items: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Nearest valid reference point of every point within ``max_distance``.

        Args:
            points: query points ``(B', N, 3)``: all ``B`` batch items, or those listed in
                ``items``, in that order.
            items: optional int64 ``(B',)`` batch indices of the rows of ``points``.

        Returns:
            ``(dist, idx)`` of shape ``(B', N, 1)``, as :meth:`NeighborIndex.query` returns them.
        """
        index = self.index
        check_tensor(points, "points", (None, "N", 3))
        check_same(("reference", index.reference), ("points", points))
        n_items = index.batch_size if items is None else len(items)
        if points.shape[0] != n_items:
            raise ShapeError(f"points has {points.shape[0]} batch items, expected {n_items}")
        if points.numel() and not bool(torch.isfinite(points).all()):
            raise ValueRangeError("points contains NaN or inf")
        if (
            points.shape[1] == 0
            or index.reference.shape[1] == 0
            or not index._use_kdtree(points.shape[1])
        ):
            return index.query_unchecked(points, 1, self.max_distance, items)

        # Coordinates first, (3, B', N), in float32 for float32 points (half the memory
        # traffic), else in float64; the compiled kernel computes in float64.
        work = torch.float32 if points.dtype == torch.float32 else torch.float64
        q = np.ascontiguousarray(np.moveaxis(points.detach().to(work).numpy(), -1, 0))
        B, M = index.batch_size, index.reference.shape[1]
        item_ids = np.arange(B) if items is None else items.cpu().numpy().astype(np.int64)
        dist, nearest = self.query_columns(q, item_ids)
        out = torch.from_numpy(dist).to(points.dtype).unsqueeze(-1)
        idx = np.where(np.isfinite(dist), nearest % M, 0)  # a column of this item or a twin
        return out, torch.from_numpy(idx).unsqueeze(-1)

    def query_columns(self, q: np.ndarray, items: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`query` for callers that hold their points as arrays, with no checks (CPU).

        Always searches the compiled k-d tree (whatever the backend and the size), and answers
        with columns of :meth:`NeighborIndex.columns`: item ``b``'s reference point ``m`` is
        column ``b * M + m``, the last column (at infinity) stands for none. An item whose
        points and mask equal those of an earlier item is answered with that item's columns
        (the same coordinates; point ``m`` is the column modulo ``M``).

        Args:
            q: finite query points, coordinates first: C-contiguous ``(3, B', N)``, float32 or
                float64.
            items: int64 ``(B',)``, the batch item of each row of ``q``.

        Returns:
            ``(dist, nearest)``: distances ``(B', N)`` in ``q``'s dtype, ``inf`` where nothing
            is within ``max_distance``, and the nearest reference columns ``(B', N)`` (int64).
        """
        index = self.index
        B, N, M, K = index.batch_size, q.shape[2], index.reference.shape[1], self.candidates
        columns, tree, root = index._tracker_tree()
        if self._anchor is None or self._anchor.shape[2] != N:
            self._anchor = np.zeros((3, B, N))
            self._cand = np.full((K, B, N), B * M, dtype=np.int64)
            self._lower = np.full((B, N), -np.inf)  # never searched
        from poseflow.geometry._tracker_cpu import track  # numba: imported when first needed

        # The bound L less the distance moved, less the rounding of the float64 arithmetic (a
        # few units in the last place of the coordinates).
        extent = max(float(np.abs(q).max(initial=0)), index._extent())
        slack = 16 * np.finfo(np.float64).eps * extent
        dist = np.empty(q.shape[1:], dtype=q.dtype)
        nearest = np.empty(q.shape[1:], dtype=np.int64)
        track(
            q, self._anchor, self._cand, self._lower, columns, tree, root, items,
            self.max_distance, self._bound, slack, dist, nearest,
        )  # fmt: skip
        return dist, nearest


def nearest_neighbors(
    query: torch.Tensor,
    reference: torch.Tensor,
    *,
    k: int = 1,
    reference_mask: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact k nearest neighbours of every query point among the valid reference points.

    The backend is chosen per device (see the module docstring); all give the same answer up to
    ties between equidistant points. Not differentiable: use the indices to gather points and
    compute differentiable distances from them.

    Args:
        query: query points, shape ``(B, N, 3)``, finite.
        reference: reference points, shape ``(B, M, 3)``; same device and dtype as ``query``.
            Masked-out points may hold any value (NaN included).
        k: number of neighbours per query point, at least 1.
        reference_mask: ``(B, M)`` bool, True where a reference point may be returned.

    Returns:
        ``(dist, idx)``, both of shape ``(B, N, k)``, sorted by increasing distance: ``dist``
        holds Euclidean distances (not squared) in the query's dtype, ``idx`` int64 indices into
        ``reference``'s ``M`` axis. Where fewer than ``k`` valid reference points exist, the
        missing neighbours have ``dist = inf`` and ``idx = 0``; masked points are never returned.

    Raises:
        ShapeError: wrong shapes, mismatched batch size, device or dtype, or a non-bool mask.
        ValueRangeError: NaN/inf in the query or at valid reference points, or ``k < 1``.

    Example:
        >>> ref = torch.tensor([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [5.0, 0.0, 0.0]]])
        >>> dist, idx = nearest_neighbors(torch.tensor([[[0.8, 0.0, 0.0]]]), ref, k=2)
        >>> idx.tolist()
        [[[1, 0]]]
        >>> dist
        tensor([[[0.2000, 0.8000]]])
    """
    return NeighborIndex(reference, reference_mask).query(query, k=k)
