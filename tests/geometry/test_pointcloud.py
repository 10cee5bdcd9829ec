"""Tests of the point-cloud primitives."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from poseflow.errors import DegenerateInputError, ShapeError, ValueRangeError
from poseflow.geometry.normals import _smallest_eigenvector
from poseflow.geometry.pointcloud import (
    backproject_depth,
    cloud_diameter,
    crop_box_around,
    crop_resize,
    crop_to_pixels,
    estimate_normals,
    farthest_point_sample,
    pixels_to_crop,
    project_points,
    remove_statistical_outliers,
    voxel_downsample,
)
from poseflow.geometry.sampling import _lexicographic_codes


def make_K(g: torch.Generator, B: int, dtype: torch.dtype, skew: bool = False) -> torch.Tensor:
    K = torch.zeros(B, 3, 3, dtype=dtype)
    K[:, 0, 0] = 300 + 400 * torch.rand(B, generator=g, dtype=dtype)
    K[:, 1, 1] = 300 + 400 * torch.rand(B, generator=g, dtype=dtype)
    K[:, 0, 2] = 10 + 20 * torch.rand(B, generator=g, dtype=dtype)
    K[:, 1, 2] = 10 + 20 * torch.rand(B, generator=g, dtype=dtype)
    if skew:
        K[:, 0, 1] = torch.rand(B, generator=g, dtype=dtype) - 0.5
    K[:, 2, 2] = 1
    return K


def random_depth(g: torch.Generator, B: int, H: int, W: int, dtype: torch.dtype, hole: float):
    depth = (0.3 + 1.5 * torch.rand(B, H, W, generator=g, dtype=torch.float64)).to(dtype)
    mask = torch.rand(B, H, W, generator=g) > hole
    return depth, mask


@given(
    seed=st.integers(0, 2**31 - 1),
    B=st.integers(1, 3),
    H=st.integers(1, 12),
    W=st.integers(1, 12),
    hole=st.floats(0.0, 0.9),
    skew=st.booleans(),
)
def test_projection_inverts_backprojection(seed, B, H, W, hole, skew) -> None:
    for dtype in (torch.float32, torch.float64):
        g = torch.Generator().manual_seed(seed)
        depth, mask = random_depth(g, B, H, W, dtype, hole)
        K = make_K(g, B, dtype, skew)
        cloud = backproject_depth(depth, K, mask)
        assert cloud.points.dtype == dtype and cloud.pixels.dtype == torch.long
        assert torch.equal(cloud.mask.sum(1), mask.flatten(1).sum(1))
        uv = project_points(cloud.points, K, cloud.mask)
        tol = 1e-3 if dtype == torch.float32 else 1e-9
        assert torch.allclose(uv[cloud.mask], cloud.pixels[cloud.mask].to(dtype), atol=tol)
        b = torch.arange(B)[:, None].expand_as(cloud.mask)[cloud.mask]
        u, v = cloud.pixels[cloud.mask].unbind(-1)
        assert torch.equal(cloud.points[cloud.mask][:, 2], depth[b, v, u])
        assert mask[b, v, u].all()
        assert (cloud.points[~cloud.mask] == 0).all() and (cloud.pixels[~cloud.mask] == 0).all()


def test_backprojection_matches_open3d(o3d) -> None:
    g = torch.Generator().manual_seed(1)
    depth = (0.5 + torch.rand(1, 30, 40, generator=g)).float()
    depth[0, 5:9, 3:20] = 0
    K = torch.tensor([[500.0, 0, 19.3], [0, 480.0, 14.6], [0, 0, 1]])
    ours = backproject_depth(depth, K)
    intr = o3d.camera.PinholeCameraIntrinsic(40, 30, 500.0, 480.0, 19.3, 14.6)
    pcd = o3d.geometry.PointCloud.create_from_depth_image(
        o3d.geometry.Image(depth[0].numpy()), intr, depth_scale=1.0, depth_trunc=10.0
    )
    np.testing.assert_allclose(ours.points[0].numpy(), np.asarray(pcd.points), atol=1e-6)


def test_backprojection_batched_equals_loop(dtype, device) -> None:
    g = torch.Generator().manual_seed(2)
    depth, mask = random_depth(g, 3, 9, 11, dtype, 0.5)
    K = make_K(g, 3, dtype).to(device)
    cloud = backproject_depth(depth.to(device), K, mask.to(device))
    assert cloud.points.device.type == device.type
    for b in range(3):
        one = backproject_depth(depth[b : b + 1].to(device), K[b], mask[b : b + 1].to(device))
        n = int(one.mask.sum())
        assert torch.equal(cloud.points[b, :n], one.points[0, :n])
        assert torch.equal(cloud.pixels[b, :n], one.pixels[0, :n])
        assert not cloud.mask[b, n:].any()
        # raster order
        flat = one.pixels[0, :n, 1] * 11 + one.pixels[0, :n, 0]
        assert (flat.diff() > 0).all()


def test_backprojection_depth_scale_and_invalid_depth() -> None:
    raw = torch.tensor([[[0, 1000, 2000], [65535, 10, 0]]], dtype=torch.int32)
    K = torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1]], dtype=torch.float64)
    cloud = backproject_depth(raw, K, depth_scale=0.1 / 1000)  # BOP depth_scale 0.1 (mm/unit)
    assert cloud.points.dtype == torch.float64
    assert torch.allclose(cloud.points[0, :, 2], torch.tensor([0.1, 0.2, 6.5535, 0.001]).double())
    png = torch.from_numpy(np.array([[[0, 1000], [2000, 65535]]], dtype=np.uint16))
    assert torch.allclose(
        backproject_depth(png, K, depth_scale=1e-4).points[0, :, 2],
        torch.tensor([0.1, 0.2, 6.5535], dtype=torch.float64),
    )
    d = torch.tensor([[[float("nan"), 1.0], [float("inf"), -1.0]]])
    out = backproject_depth(d, K.float())
    assert out.mask.sum() == 1 and out.pixels[0, 0].tolist() == [1, 0]


def test_backprojection_max_points_subsample() -> None:
    g = torch.Generator().manual_seed(3)
    depth, mask = random_depth(g, 2, 20, 20, torch.float32, 0.3)
    mask[1] = False
    mask[1, 0, :5] = True
    K = make_K(g, 2, torch.float32)
    full = backproject_depth(depth, K, mask)
    sub = backproject_depth(
        depth, K, mask, max_points=50, generator=torch.Generator().manual_seed(0)
    )
    again = backproject_depth(
        depth, K, mask, max_points=50, generator=torch.Generator().manual_seed(0)
    )
    assert sub.points.shape[1] == 50 and sub.mask[0].all() and sub.mask[1].sum() == 5
    assert torch.equal(sub.pixels, again.pixels)
    full_set = {tuple(p) for p in full.pixels[0][full.mask[0]].tolist()}
    assert {tuple(p) for p in sub.pixels[0].tolist()} <= full_set
    assert len({tuple(p) for p in sub.pixels[0].tolist()}) == 50


def test_project_points_rejects_points_behind_camera() -> None:
    K = torch.eye(3)
    with pytest.raises(ValueRangeError):
        project_points(torch.tensor([[[0.0, 0.0, -1.0]]]), K)
    out = project_points(
        torch.tensor([[[0.0, 0.0, -1.0], [1.0, 2.0, 2.0]]]), K, torch.tensor([[False, True]])
    )
    assert out.tolist() == [[[0.0, 0.0], [0.5, 1.0]]]


@given(seed=st.integers(0, 2**31 - 1), N=st.integers(1, 60), margin=st.floats(1.0, 2.0))
def test_crop_box_contains_cloud(seed, N, margin) -> None:
    g = torch.Generator().manual_seed(seed)
    K = make_K(g, 2, torch.float64)
    pts = torch.randn(2, N, 3, generator=g, dtype=torch.float64) * 0.05
    pts[..., 2] += 1.0
    mask = torch.rand(2, N, generator=g) > 0.3
    mask[:, 0] = True
    box = crop_box_around(pts, K, mask, margin=margin, min_size=4.0)
    assert torch.allclose(box[:, 2] - box[:, 0], box[:, 3] - box[:, 1])
    uv = project_points(pts, K, mask)
    for b in range(2):
        p = uv[b][mask[b]]
        assert (p - 0.5 >= box[b, :2] - 1e-9).all() and (p + 0.5 <= box[b, 2:] + 1e-9).all()
        centre = pts[b][mask[b]].mean(0, keepdim=True)
        c_uv = project_points(centre[None], K[b])[0, 0]
        assert torch.allclose((box[b, :2] + box[b, 2:]) / 2, c_uv)
    size = 32
    crop = pixels_to_crop(uv, box, size)
    assert (crop[mask] >= -0.5 - 1e-9).all() and (crop[mask] <= size - 0.5 + 1e-9).all()
    assert torch.allclose(crop_to_pixels(crop, box, size), uv)


def test_crop_resize_samples_where_pixels_to_crop_says(dtype) -> None:
    H, W = 40, 50
    vv, uu = torch.meshgrid(
        torch.arange(H, dtype=dtype), torch.arange(W, dtype=dtype), indexing="ij"
    )
    image = torch.stack([uu, vv])[None].expand(2, 2, H, W)  # channel 0 = u, channel 1 = v
    box = torch.tensor([[5.2, 3.1, 25.2, 23.1], [10.0, 8.0, 40.0, 38.0]], dtype=dtype)
    crop = crop_resize(image, box, 16)
    ii, jj = torch.meshgrid(torch.arange(16), torch.arange(16), indexing="ij")
    coords = torch.stack([jj, ii], -1).reshape(1, -1, 2).expand(2, -1, -1).to(dtype)
    where = crop_to_pixels(coords, box, 16).reshape(2, 16, 16, 2)
    tol = 1e-4 if dtype == torch.float32 else 1e-9
    assert torch.allclose(crop[:, 0], where[..., 0], atol=tol)
    assert torch.allclose(crop[:, 1], where[..., 1], atol=tol)


def test_crop_empty_cloud_raises() -> None:
    with pytest.raises(DegenerateInputError):
        crop_box_around(torch.ones(1, 3, 3), torch.eye(3), torch.zeros(1, 3, dtype=torch.bool))


def reference_fps(p: torch.Tensor, M: int, start: int) -> list[int]:
    chosen = [start]
    d = (p - p[start]).norm(dim=1)
    for _ in range(M - 1):
        nxt = int(d.argmax())
        chosen.append(nxt)
        d = torch.minimum(d, (p - p[nxt]).norm(dim=1))
    return chosen


@given(seed=st.integers(0, 2**31 - 1), N=st.integers(2, 80), M=st.integers(1, 30))
def test_fps_matches_reference_and_is_batched(seed, N, M) -> None:
    g = torch.Generator().manual_seed(seed)
    pts = torch.rand(3, N, 3, generator=g, dtype=torch.float64)
    mask = torch.rand(3, N, generator=g) > 0.4
    mask[:, 0] = True
    idx, valid = farthest_point_sample(pts, M, mask)
    for b in range(3):
        sub = torch.nonzero(mask[b]).flatten()
        n = len(sub)
        assert valid[b].sum() == min(n, M)
        ref = sub[reference_fps(pts[b, sub], min(M, n), 0)]
        assert idx[b, : min(n, M)].tolist() == ref.tolist()
        assert mask[b, idx[b]].all()
        assert len(set(idx[b, : min(n, M)].tolist())) == min(n, M)


# dtype and device fixtures hold no state: they may be shared by hypothesis' examples
FIXTURES = settings(
    suppress_health_check=[*settings().suppress_health_check, HealthCheck.function_scoped_fixture]
)


def fps_as_released(points, M, mask, generator):
    """Farthest-point sampling exactly as poseflow 0.1.0 computed it (a loop of tensor ops)."""
    B, N = points.shape[:2]
    device = points.device
    count = mask.sum(1)
    idx = torch.zeros(B, M, dtype=torch.long, device=device)
    pts = torch.where(mask.unsqueeze(-1), points, torch.zeros_like(points))
    if generator is None:
        cur = mask.to(torch.int8).argmax(1)
    else:
        r = torch.rand(B, N, generator=generator, device=generator.device).to(device)
        cur = r.masked_fill(~mask, -1.0).argmax(1)
    x, y, z = (pts[..., c].contiguous() for c in range(3))
    dist = torch.full((B, N), torch.inf, dtype=points.dtype, device=device)
    dist = dist.masked_fill(~mask, -1.0)
    d, tmp = torch.empty_like(x), torch.empty_like(x)
    rows = torch.arange(B, device=device)
    for i in range(M):
        idx[:, i] = cur
        dist[rows, cur] = -1.0
        torch.sub(x, x[rows, cur].unsqueeze(1), out=d)
        d.mul_(d)
        torch.sub(y, y[rows, cur].unsqueeze(1), out=tmp)
        d.addcmul_(tmp, tmp)
        torch.sub(z, z[rows, cur].unsqueeze(1), out=tmp)
        d.addcmul_(tmp, tmp)
        torch.minimum(dist, d, out=dist)
        cur = dist.argmax(1)
    valid = torch.arange(M, device=device)[None] < count[:, None]
    return torch.where(valid, idx, idx[:, :1]), valid


@FIXTURES
@given(
    seed=st.integers(0, 2**31 - 1),
    B=st.integers(1, 4),
    N=st.integers(1, 400),
    M=st.integers(1, 300),
    layout=st.sampled_from(["uniform", "grid", "plane", "duplicates", "far", "tiny"]),
    keep=st.floats(0.0, 1.0),
    seeded=st.booleans(),
)
def test_fps_gives_the_released_samples(dtype, device, seed, B, N, M, layout, keep, seeded) -> None:
    """Same indices as the released loop, ties (grids, duplicates) and every layout included."""
    g = torch.Generator().manual_seed(seed)
    pts = torch.rand(B, N, 3, generator=g, dtype=torch.float64)
    if layout == "grid":  # many exactly equal distances
        pts = (pts * 4).round() / 4
    elif layout == "plane":
        pts[..., 2] = 0.5
    elif layout == "duplicates":
        pts = pts[:, torch.randint(0, max(1, N // 4), (N,), generator=g)]
    elif layout == "far":  # 10 km away, float32 spacing ~1 mm
        pts = pts * 0.5 + 1e4
    elif layout == "tiny":
        pts = pts * 1e-20
    pts = pts.to(dtype).to(device)
    mask = (torch.rand(B, N, generator=g) < keep).to(device)
    got = farthest_point_sample(
        pts, M, mask, generator=torch.Generator().manual_seed(seed) if seeded else None
    )
    want = fps_as_released(pts, M, mask, torch.Generator().manual_seed(seed) if seeded else None)
    assert torch.equal(got[0], want[0])
    assert torch.equal(got[1], want[1])


def test_fps_rounds_distances_as_the_released_loop() -> None:
    """Offsets (a, b, c) and (c, b, a) are equally far; only the rounding of the squared sum
    (fused multiply-adds, as torch.addcmul does) decides which comes second."""
    a = [0.9337689280509949, 0.684050440788269, 0.8237813711166382]
    pts = torch.tensor([[[0.0, 0.0, 0.0], a, a[::-1]]])
    mask = torch.ones(1, 3, dtype=torch.bool)
    got, _ = farthest_point_sample(pts, 2, mask)
    want, _ = fps_as_released(pts, 2, mask, None)
    assert torch.equal(got, want)


def test_fps_compiled_kernel_on_a_lifted_cloud() -> None:
    """The CPU kernel prunes most of the work on a real-sized cloud and still agrees."""
    g = torch.Generator().manual_seed(3)
    u = torch.rand(2, 3000, 2, generator=g, dtype=torch.float32)
    pts = torch.stack([u[..., 0], u[..., 1], 0.7 + 0.1 * torch.sin(6 * u[..., 0])], -1)
    mask = torch.rand(2, 3000, generator=g) > 0.2
    got = farthest_point_sample(pts, 700, mask, generator=torch.Generator().manual_seed(1))
    want = fps_as_released(pts, 700, mask, torch.Generator().manual_seed(1))
    assert torch.equal(got[0], want[0]) and bool(got[1].all())


def test_fps_seeded_start_and_dtype(dtype, device) -> None:
    pts = torch.rand(2, 100, 3, generator=torch.Generator().manual_seed(0), dtype=dtype).to(device)
    a = farthest_point_sample(pts, 10, generator=torch.Generator().manual_seed(5))
    b = farthest_point_sample(pts, 10, generator=torch.Generator().manual_seed(5))
    assert torch.equal(a[0], b[0]) and a[0].device.type == device.type
    # FPS covering radius: every point is within the last selection distance of a sample
    p = pts[0]
    chosen = p[a[0][0]]
    cover = torch.cdist(p, chosen).min(1).values.max()
    spread = torch.pdist(chosen).min()
    assert cover <= spread + 1e-6


@given(
    seed=st.integers(0, 2**31 - 1),
    spectrum=st.lists(
        st.sampled_from([0.0, 1e-12, 1e-6, 0.3, 1.0, 1.0 + 1e-9, 5.0]), min_size=3, max_size=3
    ),
    scale=st.sampled_from([1e-8, 1.0, 1e6]),
)
def test_smallest_eigenvector_matches_eigh(seed, spectrum, scale) -> None:
    """The closed form finds a unit vector of the smallest eigenvalue's eigenspace, repeated
    eigenvalues, zero and multiples of the identity included; where the two smallest are
    nearly equal (within 1e-6 of the largest), a vector of their joint eigenspace."""
    g = torch.Generator().manual_seed(seed)
    Q, _ = torch.linalg.qr(torch.randn(4, 3, 3, generator=g, dtype=torch.float64))
    lam = torch.tensor(spectrum, dtype=torch.float64) * scale
    A = Q @ torch.diag(lam) @ Q.transpose(1, 2)
    A = (A + A.transpose(1, 2)) / 2
    v = _smallest_eigenvector(A)
    assert torch.allclose(v.norm(dim=-1), torch.ones(4, dtype=torch.float64), atol=1e-12)
    rayleigh = (v.unsqueeze(-2) @ A @ v.unsqueeze(-1)).reshape(4)
    top = lam.abs().max()
    low, gap = lam.min(), lam.sort().values[1] - lam.min()
    excess = rayleigh - low
    assert bool((excess >= -1e-10 * top).all())
    bound = 1e-10 * top + (gap if gap <= 1e-6 * top else 0.0)
    assert bool((excess <= bound + 1e-300).all())


@given(seed=st.integers(0, 2**31 - 1), voxel=st.floats(0.05, 0.5))
def test_voxel_downsample_one_point_per_voxel(seed, voxel) -> None:
    g = torch.Generator().manual_seed(seed)
    pts = torch.rand(2, 60, 3, generator=g, dtype=torch.float64)
    mask = torch.rand(2, 60, generator=g) > 0.3
    idx, valid = voxel_downsample(pts, voxel, mask)
    for b in range(2):
        p = pts[b][mask[b]]
        cells = torch.floor(p / voxel).long()
        occupied = {tuple(c) for c in cells.tolist()}
        kept = idx[b][valid[b]]
        assert mask[b, kept].all()
        kept_cells = [tuple(c) for c in torch.floor(pts[b, kept] / voxel).long().tolist()]
        assert len(kept_cells) == len(set(kept_cells)) and set(kept_cells) == occupied
        for i, c in zip(kept.tolist(), kept_cells):
            members = p[(cells == torch.tensor(c)).all(1)]
            d = (members - members.mean(0)).norm(dim=1)
            assert (pts[b, i] - members.mean(0)).norm() <= d.min() + 1e-12


@given(
    rows=st.lists(
        st.tuples(*[st.integers(-(2**40), 2**40)] * 3) | st.tuples(*[st.integers(-3, 3)] * 3),
        min_size=1,
        max_size=30,
    )
)
def test_lexicographic_codes_order_as_the_rows(rows) -> None:
    keys = torch.tensor(rows, dtype=torch.long)
    codes = _lexicographic_codes(keys)
    for i in range(len(rows)):
        for j in range(len(rows)):
            assert (codes[i] < codes[j]) == (rows[i] < rows[j])
            assert (codes[i] == codes[j]) == (rows[i] == rows[j])


def test_voxel_downsample_keeps_lexicographic_voxel_order() -> None:
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(2, 300, 3, generator=g, dtype=torch.float64) * 2 - 1
    idx, valid = voxel_downsample(pts, 0.25)
    for b in range(2):
        cells = torch.floor(pts[b, idx[b][valid[b]]] / 0.25).long().tolist()
        assert cells == sorted(cells) and len(cells) == len({tuple(c) for c in cells})


def test_voxel_downsample_empty() -> None:
    idx, valid = voxel_downsample(torch.zeros(2, 3, 3), 0.1, torch.zeros(2, 3, dtype=torch.bool))
    assert idx.shape == (2, 0) and valid.shape == (2, 0)


def test_normals_plane_and_sphere(dtype, device) -> None:
    g = torch.Generator().manual_seed(0)
    xy = torch.rand(1, 300, 2, generator=g, dtype=dtype)
    plane = torch.cat([xy, torch.full((1, 300, 1), 0.5, dtype=dtype)], -1).to(device)
    n = estimate_normals(plane, k=10)
    assert n.dtype == dtype and n.device.type == device.type
    tol = 1e-4 if dtype == torch.float32 else 1e-9
    assert torch.allclose(n[..., 2], torch.full_like(n[..., 2], -1.0), atol=tol)  # faces origin
    dirs = torch.randn(1, 2000, 3, generator=g, dtype=dtype)
    sphere = dirs / dirs.norm(dim=-1, keepdim=True) * 0.1 + torch.tensor([0, 0, 1.0], dtype=dtype)
    n = estimate_normals(sphere.to(device), k=12, viewpoint=(0.0, 0.0, 1.0))  # centre: inward
    radial = (sphere - torch.tensor([0, 0, 1.0], dtype=dtype)) / 0.1
    assert ((n.cpu() * radial).sum(-1) < -0.98).all()


def test_normals_match_open3d_and_respect_mask(o3d) -> None:
    g = torch.Generator().manual_seed(4)
    pts = torch.rand(1, 500, 3, generator=g, dtype=torch.float64) * torch.tensor([1.0, 1.0, 0.05])
    pts[..., 2] += torch.sin(pts[..., 0] * 3)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[0].numpy()))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(15))
    ref = torch.from_numpy(np.asarray(pcd.normals))
    ours = estimate_normals(pts, k=15, viewpoint=None)[0]
    assert ((ours * ref).sum(-1).abs() > 0.999).all()
    mask = torch.ones(1, 500, dtype=torch.bool)
    mask[0, ::2] = False
    masked = estimate_normals(pts, mask, k=15)
    assert (masked[~mask] == 0).all() and (masked[mask].norm(dim=-1) - 1).abs().max() < 1e-9
    few = estimate_normals(pts[:, :2], k=3)
    assert (few == 0).all()


def test_statistical_outliers_match_open3d(o3d) -> None:
    g = torch.Generator().manual_seed(5)
    pts = torch.randn(1, 400, 3, generator=g, dtype=torch.float64) * 0.02
    pts[0, :20] += torch.randn(20, 3, generator=g, dtype=torch.float64) * 0.5
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[0].numpy()))
    _, kept = pcd.remove_statistical_outlier(nb_neighbors=20, std_ratio=2.0)
    ours = remove_statistical_outliers(pts, k=20, std_ratio=2.0)
    assert sorted(kept) == torch.nonzero(ours[0]).flatten().tolist()
    assert not ours[0, :20].all() and ours[0, 20:].sum() > 370


def test_statistical_outliers_batched_equals_loop() -> None:
    g = torch.Generator().manual_seed(6)
    pts = torch.randn(3, 100, 3, generator=g)
    mask = torch.rand(3, 100, generator=g) > 0.2
    out = remove_statistical_outliers(pts, mask, k=8)
    assert not (out & ~mask).any()
    for b in range(3):
        one = remove_statistical_outliers(pts[b : b + 1][:, mask[b]], k=8)
        assert torch.equal(out[b][mask[b]], one[0])


def test_statistical_outliers_ignore_padding_and_refuse_nan_at_valid_points() -> None:
    g = torch.Generator().manual_seed(7)
    pts = torch.randn(3, 60, 3, generator=g)
    mask = torch.rand(3, 60, generator=g) > 0.5
    mask[2] = False  # an item without any valid point
    out = remove_statistical_outliers(pts, mask, k=6)
    junk = pts.clone()
    junk[~mask] = torch.nan  # padding may hold anything
    assert torch.equal(remove_statistical_outliers(junk, mask, k=6), out)
    assert not out[2].any() and out[0].sum() > 0
    bad = pts.clone()
    bad[0, mask[0].nonzero()[0, 0]] = torch.inf
    with pytest.raises(ValueRangeError, match="NaN or inf"):
        remove_statistical_outliers(bad, mask, k=6)


@given(seed=st.integers(0, 2**31 - 1), N=st.integers(0, 300))
def test_cloud_diameter_exact(seed, N) -> None:
    g = torch.Generator().manual_seed(seed)
    pts = torch.randn(2, N, 3, generator=g, dtype=torch.float64) * torch.tensor([1.0, 0.3, 0.1])
    mask = torch.rand(2, N, generator=g) > 0.2
    d = cloud_diameter(pts, mask, chunk=17)
    for b in range(2):
        p = pts[b][mask[b]]
        ref = torch.pdist(p).max() if len(p) >= 2 else torch.tensor(0.0, dtype=torch.float64)
        assert math.isclose(d[b].item(), ref.item(), rel_tol=1e-12, abs_tol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape", ["sphere", "flat", "line"])
def test_cloud_diameter_exact_on_large_and_degenerate_clouds(shape, dtype) -> None:
    """Hull pruning on a cloud whose points are nearly all extreme, and the flat fallbacks."""
    g = torch.Generator().manual_seed(3)
    pts = torch.randn(1, 3000, 3, generator=g, dtype=torch.float64)
    if shape == "sphere":  # every point is on the hull: nothing prunes before it
        pts = pts / pts.norm(dim=-1, keepdim=True)
    elif shape == "flat":  # no 3-D hull
        pts[..., 2] = 0.5
    else:
        pts = pts[..., :1] * torch.tensor([1.0, 2.0, -0.5], dtype=torch.float64)
    pts = pts.to(dtype)
    ref = torch.pdist(pts[0].double()).max().item()
    assert math.isclose(
        cloud_diameter(pts)[0].item(), ref, rel_tol=1e-6 if dtype == torch.float32 else 1e-12
    )


def test_bad_input() -> None:
    K = torch.eye(3)
    with pytest.raises(ShapeError):
        backproject_depth(torch.ones(4, 4), K)
    with pytest.raises(ShapeError):
        backproject_depth(torch.ones(1, 4, 4), K, torch.ones(1, 4, 4))
    with pytest.raises(ShapeError):
        backproject_depth(torch.ones(1, 4, 4), torch.eye(3, dtype=torch.long))
    with pytest.raises(ValueRangeError):
        backproject_depth(torch.ones(1, 4, 4), K, depth_scale=0.0)
    with pytest.raises(ValueRangeError):
        backproject_depth(torch.ones(1, 4, 4), torch.full((3, 3), float("nan")))
    with pytest.raises(ValueRangeError):
        farthest_point_sample(torch.ones(1, 4, 3), 0)
    with pytest.raises(ValueRangeError):
        farthest_point_sample(torch.full((1, 4, 3), float("nan")), 2)
    with pytest.raises(ValueRangeError):
        voxel_downsample(torch.ones(1, 4, 3), -1.0)
    with pytest.raises(ValueRangeError):
        estimate_normals(torch.ones(1, 4, 3), k=2)
    with pytest.raises(ValueRangeError):
        remove_statistical_outliers(torch.ones(1, 4, 3), std_ratio=0.0)
    with pytest.raises(ValueRangeError):
        crop_resize(torch.ones(1, 1, 4, 4), torch.tensor([[2.0, 0.0, 1.0, 3.0]]), 4)
