from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from poseflow.errors import ShapeError, ValueRangeError
from poseflow.eval.errors import (
    MSPD_THRESHOLDS,
    MSSD_THRESHOLDS,
    VSD_TAUS,
    depth_to_distance,
    mspd,
    mssd,
    project_points,
    vsd_from_depth,
)
from poseflow.eval.symmetry import symmetry_transforms
from poseflow.geometry.se3 import random_transform

K = [[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]]


def _box(n: int, gen: torch.Generator, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """Vertices of an asymmetric box-like cloud, 0.2 x 0.1 x 0.05 m."""
    scale = torch.tensor([0.2, 0.1, 0.05], dtype=torch.float64)
    pts = (torch.rand(n, 3, generator=gen, dtype=torch.float64) - 0.5) * scale
    return pts.to(dtype=dtype, device=device)


def _rot_z(angle: float, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=dtype)


def _brute_mssd(T_est, T_gt, pts, S):
    G = T_gt[:, None] @ S[None]
    pe = pts @ T_est[:, :3, :3].transpose(1, 2) + T_est[:, None, :3, 3]
    pg = torch.einsum("bsij,nj->bsni", G[..., :3, :3], pts) + G[:, :, None, :3, 3]
    return (pe[:, None] - pg).norm(dim=-1).amax(-1).amin(-1)


def _brute_mspd(T_est, T_gt, K_, pts, S):
    ue = project_points(T_est, K_, pts)
    ug = project_points(T_gt[:, None] @ S[None], K_, pts)
    return (ue[:, None] - ug).norm(dim=-1).amax(-1).amin(-1)


def test_thresholds_are_the_bop_ones():
    assert len(VSD_TAUS) == len(MSSD_THRESHOLDS) == len(MSPD_THRESHOLDS) == 10
    assert VSD_TAUS[0] == pytest.approx(0.05) and VSD_TAUS[-1] == pytest.approx(0.5)
    assert MSPD_THRESHOLDS == (5.0, 10.0, 15.0, 20.0, 25.0, 30.0, 35.0, 40.0, 45.0, 50.0)


def test_mssd_exact_gt_is_zero(dtype, device, tol):
    gen = torch.Generator().manual_seed(0)
    pts = _box(200, gen, dtype, device)
    T = random_transform(4, generator=gen, dtype=dtype).to(device)
    e = mssd(T, T, pts)
    assert e.shape == (4,) and e.dtype == dtype and e.device == device
    assert float(e.abs().max()) < tol * 10


def test_mssd_translation_offset_is_its_length(dtype, device):
    gen = torch.Generator().manual_seed(1)
    pts = _box(100, gen, dtype, device)
    T = random_transform(3, generator=gen, dtype=dtype).to(device)
    T2 = T.clone()
    T2[:, :3, 3] += torch.tensor([0.03, -0.04, 0.0], dtype=dtype, device=device)
    torch.testing.assert_close(mssd(T2, T, pts), torch.full((3,), 0.05, dtype=dtype, device=device))


def test_mssd_flip_symmetric_vs_asymmetric(dtype, device, tol):
    """180 deg about z: correct for an object with that symmetry, wrong for an asymmetric one."""
    gen = torch.Generator().manual_seed(2)
    pts = _box(300, gen, dtype, device)
    flip = torch.eye(4, dtype=dtype, device=device)
    flip[:3, :3] = _rot_z(math.pi, dtype).to(device)
    T = random_transform(2, generator=gen, dtype=dtype).to(device)
    T_flip = T @ flip
    S = symmetry_transforms(flip[None], dtype=dtype, device=device)
    assert float(mssd(T_flip, T, pts, S).max()) < tol * 10
    e = mssd(T_flip, T, pts)
    # The flip moves the corner at (0.1, 0.05) to (-0.1, -0.05): about 2 * 0.11 m.
    assert bool((e > 0.2).all())
    diameter = 2 * math.sqrt(0.1**2 + 0.05**2 + 0.025**2)
    assert bool((e / diameter > MSSD_THRESHOLDS[-1]).all())


def test_mssd_continuous_symmetry_any_angle(dtype, device):
    gen = torch.Generator().manual_seed(3)
    # A cylinder's vertices: rings about z.
    ang = torch.linspace(0, 2 * math.pi, 65, dtype=torch.float64)[:-1]
    ring = torch.stack((0.05 * ang.cos(), 0.05 * ang.sin(), torch.zeros_like(ang)), -1)
    pts = torch.cat([ring + torch.tensor([0, 0, z]) for z in (-0.05, 0.05)]).to(dtype).to(device)
    S = (
        symmetry_transforms(None, [(torch.tensor([0.0, 0, 1]), torch.zeros(3))])
        .to(dtype)
        .to(device)
    )
    T = random_transform(3, generator=gen, dtype=dtype).to(device)
    spin = torch.eye(4, dtype=dtype, device=device)
    spin[:3, :3] = _rot_z(1.234, dtype).to(device)
    e = mssd(T @ spin, T, pts, S)
    # Sampling step 2 pi / 315: the nearest sample is within pi / 315 rad, i.e. <= r * pi / 315.
    assert float(e.max()) <= 0.05 * math.pi / 315 + 1e-5
    assert float(mssd(T @ spin, T, pts).min()) > 0.05  # without the symmetry it is wrong


@given(
    seed=st.integers(0, 2**16), n=st.integers(1, 60), sym=st.sampled_from(["none", "disc", "cont"])
)
def test_mssd_and_mspd_match_brute_force(seed, n, sym):
    gen = torch.Generator().manual_seed(seed)
    pts = _box(n, gen, torch.float64, torch.device("cpu"))
    T_gt = random_transform(5, generator=gen, dtype=torch.float64, max_translation=0.1)
    T_gt[:, 2, 3] += 1.0
    T_est = random_transform(
        5, generator=gen, dtype=torch.float64, max_angle=1.0, max_translation=0.1
    )
    T_est = T_gt @ T_est
    if sym == "none":
        S = torch.eye(4, dtype=torch.float64)[None]
    elif sym == "disc":
        S = symmetry_transforms(random_transform(3, generator=gen, dtype=torch.float64))
    else:
        S = symmetry_transforms(
            None,
            [
                (
                    torch.randn(3, generator=gen, dtype=torch.float64),
                    0.01 * torch.randn(3, generator=gen, dtype=torch.float64),
                )
            ],
            max_sym_disc_step=0.2,
        )
    K_ = torch.tensor(K, dtype=torch.float64)
    torch.testing.assert_close(mssd(T_est, T_gt, pts, S), _brute_mssd(T_est, T_gt, pts, S))
    torch.testing.assert_close(mspd(T_est, T_gt, K_, pts, S), _brute_mspd(T_est, T_gt, K_, pts, S))


def test_mspd_pruned_search_is_exact_with_many_vertices():
    gen = torch.Generator().manual_seed(4)
    pts = _box(500, gen, torch.float64, torch.device("cpu"))
    S = symmetry_transforms(None, [(torch.tensor([0.0, 0.3, 1.0]), torch.tensor([0.01, 0.0, 0.0]))])
    T_gt = random_transform(20, generator=gen, dtype=torch.float64, max_translation=0.1)
    T_gt[:, 2, 3] += 0.8
    T_est = T_gt @ random_transform(
        20, generator=gen, dtype=torch.float64, max_angle=0.5, max_translation=0.02
    )
    T_est[:5] = T_gt[:5] @ S[torch.tensor([3, 50, 100, 200, 314])]
    K_ = torch.tensor(K, dtype=torch.float64)
    e = mspd(T_est, T_gt, K_, pts, S)
    torch.testing.assert_close(e, _brute_mspd(T_est, T_gt, K_, pts, S))
    assert float(e[:5].max()) < 1e-6


def test_mspd_hand_computed(dtype, device):
    K_ = torch.tensor(K, dtype=dtype, device=device)
    pts = torch.tensor([[0.05, 0.0, 0.0], [0.0, 0.05, 0.0]], dtype=dtype, device=device)
    T = torch.eye(4, dtype=dtype, device=device)[None].repeat(2, 1, 1)
    T[:, 2, 3] = 1.0
    T2 = T.clone()
    T2[0, 0, 3] = 0.01  # 1 cm sideways at 1 m with f = 500: 5 px
    T2[1, 2, 3] = 2.0  # twice as far: (0.05, 0) projects 25 px -> 12.5 px from the centre
    torch.testing.assert_close(
        mspd(T2, T, K_, pts), torch.tensor([5.0, 12.5], dtype=dtype, device=device)
    )


def test_mspd_batched_intrinsics_equal_loop():
    gen = torch.Generator().manual_seed(5)
    pts = _box(50, gen, torch.float64, torch.device("cpu"))
    T = random_transform(3, generator=gen, dtype=torch.float64, max_translation=0.1)
    T[:, 2, 3] += 1
    T2 = T @ random_transform(
        3, generator=gen, dtype=torch.float64, max_angle=0.2, max_translation=0.01
    )
    Ks = torch.tensor(K, dtype=torch.float64).repeat(3, 1, 1)
    Ks[1, 0, 0] = 700
    Ks[2, 1, 2] = 100
    batched = mspd(T2, T, Ks, pts)
    loop = torch.cat([mspd(T2[i : i + 1], T[i : i + 1], Ks[i], pts) for i in range(3)])
    torch.testing.assert_close(batched, loop)


def test_bad_inputs_raise():
    T = torch.eye(4)[None]
    pts = torch.zeros(3, 3)
    with pytest.raises(ShapeError):
        mssd(T, torch.eye(4)[None].repeat(2, 1, 1), pts)
    with pytest.raises(ShapeError):
        mssd(T, T, torch.zeros(0, 3))
    with pytest.raises(ValueRangeError):
        mssd(T * float("nan"), T, pts)
    with pytest.raises(ShapeError):
        mspd(T, T, torch.eye(3).repeat(2, 1, 1), pts)
    with pytest.raises(ShapeError):
        mssd(T, T.double(), pts)


def test_depth_to_distance_hand_computed(dtype):
    K_ = torch.tensor([[2.0, 0.0, 1.0], [0.0, 2.0, 0.0], [0.0, 0.0, 1.0]], dtype=dtype)
    depth = torch.tensor([[1.0, 2.0, 0.0]], dtype=dtype)
    d = depth_to_distance(depth, K_)
    # Columns 0, 1, 2 with cx = 1, fx = 2: rays (-0.5, 0, 1), (0, 0, 1), (0.5, 0, 1).
    expected = torch.tensor([[math.sqrt(1.25), 2.0, 0.0]], dtype=dtype)
    torch.testing.assert_close(d, expected)


def _square(h, w, box, z, dtype=torch.float64):
    img = torch.zeros(h, w, dtype=dtype)
    r0, r1, c0, c1 = box
    img[r0:r1, c0:c1] = z
    return img


def test_vsd_exact_gt_is_zero_and_disjoint_is_one(dtype):
    K_ = torch.tensor([[100.0, 0, 10], [0, 100.0, 10], [0, 0, 1]], dtype=dtype)
    gt = _square(20, 20, (5, 10, 5, 10), 1.0, dtype)
    far = _square(20, 20, (12, 17, 12, 17), 1.0, dtype)
    est = torch.stack((gt, far))
    e = vsd_from_depth(est, torch.stack((gt, gt)), gt, K_, 0.1)
    assert e.shape == (2, 10) and e.dtype == dtype
    assert float(e[0].abs().max()) == 0.0
    assert float(e[1].min()) == 1.0


def test_vsd_partial_overlap_hand_computed():
    """Estimate shifted by one column: union 30 px, intersection 10 px, same depth: 20 / 30."""
    K_ = torch.tensor([[100.0, 0, 10], [0, 100.0, 10], [0, 0, 1]], dtype=torch.float64)
    gt = _square(20, 20, (0, 10, 0, 2), 1.0)  # columns 0-1
    est = _square(20, 20, (0, 10, 1, 3), 1.0)  # columns 1-2
    test = gt.clone()  # the scene shows the object in the GT pose, background missing
    e = vsd_from_depth(est[None], gt[None], test, K_, 0.1)
    # Missing test depth counts as visible (bop19): est visible on columns 1-2, GT on 0-1.
    torch.testing.assert_close(e, torch.full((1, 10), 20 / 30, dtype=torch.float64))


def test_vsd_depth_error_against_tau():
    """Same silhouette, estimate 0.012 m deeper on a 0.1 m object: 0.12 diameters."""
    K_ = torch.tensor([[100.0, 0, 0], [0, 100.0, 0], [0, 0, 1]], dtype=torch.float64)
    gt = _square(4, 4, (0, 1, 0, 1), 1.0)  # one pixel on the optical axis
    est = _square(4, 4, (0, 1, 0, 1), 1.012)
    e = vsd_from_depth(est[None], gt[None], gt, K_, 0.1)[0]
    taus = torch.tensor(VSD_TAUS, dtype=torch.float64)
    torch.testing.assert_close(e, (taus <= 0.12).to(torch.float64))


def test_vsd_occluded_estimate_is_invisible():
    """An estimate behind the measured surface by more than delta is not visible there."""
    K_ = torch.tensor([[100.0, 0, 0], [0, 100.0, 0], [0, 0, 1]], dtype=torch.float64)
    gt = _square(4, 4, (0, 2, 0, 2), 1.0)
    est = _square(4, 4, (2, 4, 2, 4), 1.5)
    test = torch.ones(4, 4, dtype=torch.float64)  # a wall at 1 m everywhere
    e = vsd_from_depth(est[None], gt[None], test, K_, 0.1)
    # GT visible on 4 px, estimate hidden (0.5 m behind the wall): union 4, intersection 0.
    assert float(e.min()) == 1.0
    # The same estimate where the wall has no depth becomes visible: union 8, still no overlap.
    test[2:, 2:] = 0.0
    assert float(vsd_from_depth(est[None], gt[None], test, K_, 0.1).min()) == 1.0


def test_vsd_nan_test_depth_is_missing():
    K_ = torch.tensor([[100.0, 0, 0], [0, 100.0, 0], [0, 0, 1]], dtype=torch.float64)
    gt = _square(4, 4, (0, 2, 0, 2), 1.0)
    nan_test = torch.full((4, 4), float("nan"), dtype=torch.float64)
    zero_test = torch.zeros(4, 4, dtype=torch.float64)
    a = vsd_from_depth(gt[None], gt[None], nan_test, K_, 0.1)
    b = vsd_from_depth(gt[None], gt[None], zero_test, K_, 0.1)
    torch.testing.assert_close(a, b)
    assert not bool(a.isnan().any())


def test_vsd_empty_union_is_one():
    K_ = torch.eye(3, dtype=torch.float64)
    z = torch.zeros(1, 3, 3, dtype=torch.float64)
    assert float(vsd_from_depth(z, z, z[0], K_, 0.1).min()) == 1.0


def test_vsd_bad_arguments():
    K_ = torch.eye(3, dtype=torch.float64)
    z = torch.zeros(1, 3, 3, dtype=torch.float64)
    with pytest.raises(ValueRangeError):
        vsd_from_depth(z, z, z[0], K_, 0.1, delta=0.0)
    with pytest.raises(ValueRangeError):
        vsd_from_depth(z, z, z[0], K_, 0.0)
    with pytest.raises(ShapeError):
        vsd_from_depth(z, torch.zeros(1, 3, 4, dtype=torch.float64), z[0], K_, 0.1)


def test_vsd_batched_equals_loop():
    gen = torch.Generator().manual_seed(6)
    K_ = torch.tensor([[50.0, 0, 8], [0, 50.0, 8], [0, 0, 1]], dtype=torch.float64)
    est = torch.rand(4, 16, 16, generator=gen, dtype=torch.float64) + 0.5
    est[est < 0.8] = 0
    gt = torch.rand(4, 16, 16, generator=gen, dtype=torch.float64) + 0.5
    gt[gt < 0.8] = 0
    test = torch.rand(16, 16, generator=gen, dtype=torch.float64) + 0.5
    diam = torch.tensor([0.1, 0.2, 0.3, 0.4], dtype=torch.float64)
    batched = vsd_from_depth(est, gt, test, K_, diam)
    loop = torch.cat(
        [vsd_from_depth(est[i : i + 1], gt[i : i + 1], test, K_, diam[i]) for i in range(4)]
    )
    torch.testing.assert_close(batched, loop)
