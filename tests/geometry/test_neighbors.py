"""Exact nearest neighbours: every backend against brute force and scipy, masks, the tracker."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from poseflow.errors import ShapeError, ValueRangeError
from poseflow.geometry.neighbors import NeighborIndex, NeighborTracker, nearest_neighbors

FIXTURES = settings(
    suppress_health_check=[*settings().suppress_health_check, HealthCheck.function_scoped_fixture]
)
seeds = st.integers(0, 2**31 - 1)
BACKENDS = ["auto", "kdtree", "brute"]


def _cloud(g, B, N, dtype=torch.float64):
    return torch.rand(B, N, 3, generator=g, dtype=torch.float64).to(dtype)


def _brute(query, reference, k, mask=None, max_distance=None):
    """Reference answer in float64: sorted distances and the distances of returned indices."""
    d = torch.cdist(query.double(), reference.double())
    if mask is not None:
        d = d.masked_fill(~mask[:, None, :], torch.inf)
    if max_distance is not None:
        d = d.masked_fill(d > max_distance, torch.inf)
    kk = min(k, d.shape[-1])
    vals = d.topk(kk, dim=-1, largest=False).values
    return torch.nn.functional.pad(vals, (0, k - kk), value=torch.inf)


def _check(dist, idx, query, reference, expected, mask, tol):
    assert dist.shape == idx.shape == expected.shape and idx.dtype == torch.int64
    found = torch.isfinite(expected)
    assert torch.equal(torch.isfinite(dist), found)
    torch.testing.assert_close(dist[found].double(), expected[found], atol=tol, rtol=0)
    assert (idx[~found] == 0).all() and (dist[~found] == torch.inf).all()
    # Returned indices are valid points at the returned (Euclidean) distances.
    B, N, k = idx.shape
    picked = reference.double().gather(1, idx.reshape(B, N * k, 1).expand(-1, -1, 3))
    actual = (query.double().unsqueeze(2) - picked.reshape(B, N, k, 3)).norm(dim=-1)
    torch.testing.assert_close(actual[found], expected[found], atol=tol, rtol=0)
    if mask is not None:
        assert mask.gather(1, idx.reshape(B, -1)).reshape(B, N, k)[found].all()
    assert (dist[..., 1:] >= dist[..., :-1]).all()  # sorted


@FIXTURES
@given(
    seed=seeds,
    B=st.integers(1, 3),
    N=st.integers(0, 60),
    M=st.integers(0, 300),
    k=st.integers(1, 5),
    masked=st.booleans(),
    backend=st.sampled_from(BACKENDS),
)
def test_matches_brute_force(seed, B, N, M, k, masked, backend, device, dtype):
    if backend == "kdtree" and device.type != "cpu":
        return
    g = torch.Generator().manual_seed(seed)
    query, reference = _cloud(g, B, N), _cloud(g, B, M)
    mask = torch.rand(B, M, generator=g) < 0.6 if masked else None
    expected = _brute(query, reference, k, mask)
    index = NeighborIndex(
        reference.to(device, dtype), None if mask is None else mask.to(device), backend=backend
    )
    dist, idx = index.query(query.to(device, dtype), k=k)
    assert dist.dtype == dtype and dist.device.type == device.type
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    _check(dist.cpu(), idx.cpu(), query, reference, expected, mask, tol)


@settings(FIXTURES, max_examples=30, deadline=None)
@given(
    seed=seeds,
    B=st.integers(1, 4),
    M=st.integers(0, 3000),
    k=st.integers(1, 5),
    masked=st.booleans(),
    threads=st.sampled_from([1, 2]),
    backend=st.sampled_from(BACKENDS),
)
def test_neighbors_of_valid_points_are_the_query_of_the_cloud_itself(
    seed, B, M, k, masked, threads, backend, device, dtype
):
    """Valid rows answer as a query of the whole cloud would; padded rows are missing."""
    import poseflow

    if backend == "kdtree" and device.type != "cpu":
        return
    g = torch.Generator().manual_seed(seed)
    reference = _cloud(g, B, M)
    mask = torch.rand(B, M, generator=g) < torch.rand(B, 1, generator=g) if masked else None
    d = torch.cdist(reference, reference, compute_mode="donot_use_mm_for_euclid_dist")
    if mask is not None:
        d = d.masked_fill(~mask[:, None, :] | ~mask[..., None], torch.inf)
    kk = min(k, M)
    expected = torch.nn.functional.pad(
        d.topk(kk, dim=-1, largest=False).values, (0, k - kk), value=torch.inf
    )
    index = NeighborIndex(
        reference.to(device, dtype), None if mask is None else mask.to(device), backend=backend
    )
    with poseflow.num_threads(threads):
        dist, idx = index.neighbors_of_valid_points(k)
    assert dist.dtype == dtype and dist.device.type == device.type
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    _check(dist.cpu(), idx.cpu(), reference, reference, expected, mask, tol)
    with pytest.raises(ValueRangeError, match="k must"):
        index.neighbors_of_valid_points(0)


@given(seed=seeds, k=st.integers(1, 4), bound=st.floats(0.01, 0.5))
def test_kdtree_backend_matches_scipy_and_bound(seed, k, bound):
    g = torch.Generator().manual_seed(seed)
    query, reference = _cloud(g, 2, 500), _cloud(g, 2, 700)
    for backend in BACKENDS:
        dist, idx = NeighborIndex(reference, backend=backend).query(query, k=k, max_distance=bound)
        _check(dist, idx, query, reference, _brute(query, reference, k, None, bound), None, 1e-12)
    dist, idx = nearest_neighbors(query, reference, k=k)
    for b in range(2):
        d, i = cKDTree(reference[b].numpy()).query(query[b].numpy(), k=k)
        np.testing.assert_allclose(dist[b].numpy(), np.reshape(d, (500, k)), atol=1e-12)
        same = np.reshape(i, (500, k)) == idx[b].numpy()
        assert same.mean() > 0.99  # ties aside


def test_masked_points_may_hold_nan_and_are_never_returned():
    ref = torch.tensor([[[0.0, 0, 0], [float("nan"), 0, 0], [1.0, 0, 0]]])
    mask = torch.tensor([[True, False, True]])
    for backend in BACKENDS:
        index = NeighborIndex(ref, mask, backend=backend)
        dist, idx = index.query(torch.tensor([[[0.9, 0.0, 0.0], [0.2, 0.0, 0.0]]]), k=3)
        assert idx[..., :2].tolist() == [[[2, 0], [0, 2]]]
        assert torch.isinf(dist[..., 2]).all() and (idx[..., 2] == 0).all()
        torch.testing.assert_close(dist[0, :, :2], torch.tensor([[0.1, 0.9], [0.2, 0.8]]))


def test_empty_reference_and_query():
    dist, idx = nearest_neighbors(torch.rand(2, 4, 3), torch.rand(2, 0, 3), k=2)
    assert dist.shape == (2, 4, 2) and torch.isinf(dist).all() and (idx == 0).all()
    dist, idx = nearest_neighbors(torch.rand(2, 0, 3), torch.rand(2, 5, 3))
    assert dist.shape == idx.shape == (2, 0, 1)
    none = torch.zeros(1, 5, dtype=torch.bool)
    for backend in BACKENDS:
        dist, idx = NeighborIndex(torch.rand(1, 5, 3), none, backend=backend).query(
            torch.rand(1, 3, 3)
        )
        assert torch.isinf(dist).all() and (idx == 0).all()


@FIXTURES
@given(seed=seeds, steps=st.integers(1, 8), scale=st.sampled_from([1e-4, 1e-2, 0.1]))
def test_tracker_equals_fresh_queries(seed, steps, scale, dtype):
    g = torch.Generator().manual_seed(seed)
    B, N, M = 3, 400, 600
    reference = _cloud(g, B, M, dtype) + 1.0  # away from the origin: rounding matters
    mask = torch.rand(B, M, generator=g) < 0.8
    index = NeighborIndex(reference, mask)
    tracker = NeighborTracker(index, max_distance=0.05)
    points = _cloud(g, B, N, dtype) + 1.0
    for step in range(steps):
        points = points + scale * torch.randn(B, N, 3, generator=g, dtype=torch.float64).to(dtype)
        items = None if step % 2 == 0 else torch.tensor([2, 0])
        sub = points if items is None else points[items]
        dist, idx = tracker.query(sub, items)
        assert dist.dtype == dtype and dist.shape == idx.shape == (len(sub), N, 1)
        fresh = NeighborIndex(reference[items] if items is not None else reference,
                              mask[items] if items is not None else mask)  # fmt: skip
        expected_dist, expected_idx = fresh.query(sub, k=1, max_distance=0.05)
        # Same points found (the bound aside: a distance within rounding of it may flip).
        near_bound = (expected_dist - 0.05).abs() < 1e-5
        assert (torch.isfinite(dist) == torch.isfinite(expected_dist))[~near_bound].all()
        both = torch.isfinite(dist) & torch.isfinite(expected_dist)
        atol = 1e-6 if dtype == torch.float32 else 1e-12
        torch.testing.assert_close(dist[both], expected_dist[both], atol=atol, rtol=0)
        assert (idx == expected_idx)[both].float().mean() > 0.999  # ties aside


def test_bad_inputs():
    ref = torch.rand(2, 5, 3)
    with pytest.raises(ShapeError):
        nearest_neighbors(torch.rand(2, 4, 2), ref)
    with pytest.raises(ShapeError):
        nearest_neighbors(torch.rand(3, 4, 3), ref)
    with pytest.raises(ShapeError):
        nearest_neighbors(torch.rand(2, 4, 3, dtype=torch.float64), ref)
    with pytest.raises(ShapeError):
        nearest_neighbors(torch.rand(2, 4, 3), ref, reference_mask=torch.ones(2, 5))
    with pytest.raises(ShapeError):
        nearest_neighbors(torch.rand(2, 4, 3), ref, reference_mask=torch.ones(2, 4, dtype=bool))
    with pytest.raises(ValueRangeError):
        nearest_neighbors(torch.rand(2, 4, 3), ref, k=0)
    with pytest.raises(ValueRangeError):
        nearest_neighbors(torch.full((2, 4, 3), float("nan")), ref)
    with pytest.raises(ValueRangeError):
        nearest_neighbors(
            torch.rand(2, 4, 3), ref.clone().index_fill_(1, torch.tensor([0]), float("inf"))
        )
    with pytest.raises(ValueRangeError):
        NeighborIndex(ref, backend="faiss")
    with pytest.raises(ValueRangeError):
        NeighborIndex(ref).query(torch.rand(2, 4, 3), max_distance=0.0)
    with pytest.raises(ShapeError):
        NeighborTracker(NeighborIndex(ref), max_distance=0.1).query(torch.rand(1, 4, 3))


@FIXTURES
@given(seed=seeds, k=st.integers(1, 4))
def test_repeated_batch_items_share_a_tree_and_answer_as_their_own(seed, k, dtype):
    """One cloud repeated (one hypothesis per row): each row answers with its own indices."""
    g = torch.Generator().manual_seed(seed)
    M, N = 700, 300
    cloud = _cloud(g, 1, M, dtype) + 1.0
    other = _cloud(g, 1, M, dtype) + 1.0
    # rows 0, 2, 3 the same cloud and mask; row 4 the same cloud with another mask; row 1 another
    reference = torch.cat((cloud, other, cloud, cloud, cloud))
    mask = (torch.rand(1, M, generator=g) < 0.8).repeat(5, 1)
    mask[4] = torch.rand(M, generator=g) < 0.5
    index = NeighborIndex(reference, mask, backend="kdtree")
    roots = index._tracker_tree()[2]
    assert roots[0] == roots[2] == roots[3] and len({int(roots[i]) for i in (0, 1, 4)}) == 3
    query = _cloud(g, 5, N, dtype) + 1.0
    dist, idx = index.query(query, k=k, max_distance=0.2)
    expected = _brute(query, reference, k, mask, 0.2)
    _check(dist, idx, query, reference, expected, mask, 1e-6 if dtype == torch.float32 else 1e-12)
    tracker = NeighborTracker(NeighborIndex(reference, mask), max_distance=0.05)
    for items in (None, torch.tensor([3, 4, 1])):
        sub = query if items is None else query[items]
        dist, idx = tracker.query(sub, items)
        fresh = NeighborIndex(reference if items is None else reference[items],
                              mask if items is None else mask[items], backend="brute")  # fmt: skip
        expected_dist, expected_idx = fresh.query(sub, k=1, max_distance=0.05)
        found = torch.isfinite(expected_dist)
        assert torch.equal(torch.isfinite(dist), found)
        assert (idx == expected_idx)[found].float().mean() > 0.999  # ties aside


def test_neighbors_of_valid_points_with_an_all_valid_mask_equal_those_without_one():
    g = torch.Generator().manual_seed(3)
    ref = _cloud(g, 3, 700)
    every = torch.ones(3, 700, dtype=torch.bool)
    with_mask = NeighborIndex(ref, every).neighbors_of_valid_points(6)
    without = NeighborIndex(ref).neighbors_of_valid_points(6)
    assert torch.equal(with_mask[0], without[0]) and torch.equal(with_mask[1], without[1])
    assert torch.equal(without[1][:, :, 0], torch.arange(700).expand(3, -1))  # itself first
