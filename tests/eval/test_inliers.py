from __future__ import annotations

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from poseflow.errors import ShapeError, ValueRangeError
from poseflow.eval.inliers import correspondence_inliers, mutual_nearest_neighbors
from poseflow.geometry.se3 import random_rotation
from poseflow.models.inputs import equivalent_maps


def _brute_mnn(a: torch.Tensor, b: torch.Tensor) -> list[int]:
    d = torch.cdist(b.double(), a.double())
    out = []
    for m in range(b.shape[0]):
        n = int(d[m].argmin())
        out.append(n if int(d[:, n].argmin()) == m else -1)
    return out


@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 30), m=st.integers(1, 30))
def test_mutual_nn_matches_brute_force(seed: int, n: int, m: int) -> None:
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(1, n, 4, generator=g, dtype=torch.float64)
    b = torch.randn(1, m, 4, generator=g, dtype=torch.float64)
    assert mutual_nearest_neighbors(a, b)[0].tolist() == _brute_mnn(a[0], b[0])


@given(seed=st.integers(0, 2**31 - 1), n=st.integers(3, 40), noise=st.floats(0.0, 0.005))
def test_identical_features_under_gt_are_all_inliers(seed: int, n: int, noise: float) -> None:
    g = torch.Generator().manual_seed(seed)
    q = torch.rand(n, 3, generator=g, dtype=torch.float64)
    feats = torch.randn(n, 16, generator=g, dtype=torch.float64)
    perm = torch.randperm(n, generator=g)
    t_canon = q[perm] + noise * torch.randn(n, 3, generator=g, dtype=torch.float64)
    res = correspondence_inliers(feats, feats[perm], q, t_canon, 1.0, 0.03)
    assert int(res.num_matches) == n
    assert int(res.num_inliers) == n
    assert float(res.inlier_ratio) == 1.0
    assert res.match.tolist() == perm.tolist()


def test_threshold_scales_with_diameter(device: torch.device, dtype: torch.dtype) -> None:
    q = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], dtype=dtype, device=device)
    f = torch.eye(2, dtype=dtype, device=device)
    t = q + torch.tensor([0.05, 0.0, 0.0], dtype=dtype, device=device)
    assert int(correspondence_inliers(f, f, q, t, 1.0).num_inliers) == 0  # 0.05 > 0.03
    assert int(correspondence_inliers(f, f, q, t, 2.0).num_inliers) == 2  # 0.05 < 0.06
    res = correspondence_inliers(f, f, q, t, torch.tensor(2.0, dtype=dtype, device=device))
    assert res.num_inliers.device.type == device.type


def test_batched_with_masks_equals_loop(device: torch.device, dtype: torch.dtype) -> None:
    g = torch.Generator().manual_seed(3)
    B, N, M = 3, 20, 15
    fq = torch.randn(B, N, 8, generator=g, dtype=dtype).to(device)
    q = torch.rand(B, N, 3, generator=g, dtype=dtype).to(device)
    sel = torch.randint(0, N, (B, M), generator=g).to(device)
    ft = fq.gather(1, sel[..., None].expand(-1, -1, 8)) + 0.01
    t = q.gather(1, sel[..., None].expand(-1, -1, 3))
    qm = torch.rand(B, N, generator=g).to(device) > 0.2
    tm = torch.rand(B, M, generator=g).to(device) > 0.2
    diam = torch.tensor([1.0, 0.5, 2.0], dtype=dtype, device=device)
    res = correspondence_inliers(fq, ft, q, t, diam, q_mask=qm, t_mask=tm)
    for b in range(B):
        one = correspondence_inliers(fq[b][qm[b]], ft[b][tm[b]], q[b][qm[b]], t[b][tm[b]], diam[b])
        assert int(res.num_inliers[b]) == int(one.num_inliers)
        assert int(res.num_matches[b]) == int(one.num_matches)
    assert bool((res.match[~tm] == -1).all())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(2, 30))
def test_equivalents_count_the_best_single_symmetric_truth(
    seed: int, n: int, dtype: torch.dtype
) -> None:
    """Matches one symmetric truth confirms count with it, never mixed; the identity alone
    changes nothing."""
    g = torch.Generator().manual_seed(seed)
    q = torch.rand(n, 3, generator=g, dtype=torch.float64) * 2 - 1
    feats = torch.randn(n, 16, generator=g, dtype=torch.float64)
    sym = torch.eye(4, dtype=torch.float64)
    sym[:3, :3] = random_rotation(1, generator=g, dtype=torch.float64)[0]
    sym[:3, 3] = torch.rand(3, generator=g, dtype=torch.float64)
    half = n // 2  # the first half seen through the symmetry, the rest as annotated
    seen = q[:half] @ sym[:3, :3].T + sym[:3, 3]
    t_canon = torch.cat((seen, q[half:]))
    maps = equivalent_maps(torch.stack((torch.eye(4, dtype=torch.float64), sym)), 1.0)
    th = 1e-2
    args = (feats.to(dtype), feats.to(dtype), q.to(dtype), t_canon.to(dtype), 1.0, th)
    plain = correspondence_inliers(*args)
    same = correspondence_inliers(*args, equivalents=maps[:1].to(dtype))
    both = correspondence_inliers(*args, equivalents=maps.to(dtype))
    back = (q[half:] - sym[:3, 3]) @ sym[:3, :3]  # the rest through the inverse symmetry
    by_identity = n - half + int(((seen - q[:half]).norm(dim=-1) < th).sum())
    by_symmetry = half + int(((back - q[half:]).norm(dim=-1) < th).sum())
    assert int(plain.num_inliers) == by_identity
    assert torch.equal(same.inlier, plain.inlier)
    assert int(both.num_inliers) == max(by_identity, by_symmetry)
    assert int(both.num_matches) == n


def test_cosine_metric_ignores_scale() -> None:
    q = torch.rand(5, 3, generator=torch.Generator().manual_seed(0))
    f = torch.randn(5, 6, generator=torch.Generator().manual_seed(1))
    res = correspondence_inliers(f, 7.0 * f, q, q, 1.0, metric="cosine")
    assert int(res.num_inliers) == 5


def test_bad_input_raises() -> None:
    f, p = torch.zeros(2, 4), torch.zeros(2, 3)
    with pytest.raises(ShapeError):
        correspondence_inliers(f, torch.zeros(2, 5), p, p, 1.0)
    with pytest.raises(ValueRangeError):
        correspondence_inliers(f, f, p, p, -1.0)
    with pytest.raises(ValueRangeError):
        correspondence_inliers(f, f, p, p, 1.0, metric="l1")
    with pytest.raises(ValueRangeError):
        correspondence_inliers(f, torch.full((2, 4), float("nan")), p, p, 1.0)
    with pytest.raises(ShapeError):
        correspondence_inliers(f, f, p, p, 1.0, equivalents=torch.zeros(2, 3, 3))
