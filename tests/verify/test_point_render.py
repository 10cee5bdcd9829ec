"""Tests of the point renderer and the observation crops of the verifier."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from poseflow.errors import ShapeError, ValueRangeError
from poseflow.geometry.pointcloud import crop_resize, pixels_to_crop, project_points
from poseflow.geometry.se3 import random_rotation
from poseflow.verify import box_sum, crop_intrinsics, crop_observation, render_points

K_IMG = torch.tensor([[300.0, 0.0, 80.0], [0.0, 320.0, 60.0], [0.0, 0.0, 1.0]])


def grid_plane(n: int, half: float, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """An ``n x n`` grid of points in the model's z=0 plane, ``(n * n, 3)``."""
    s = torch.linspace(-half, half, n, dtype=dtype)
    yy, xx = torch.meshgrid(s, s, indexing="ij")
    return torch.stack((xx, yy, torch.zeros_like(xx)), -1).reshape(-1, 3)


def facing(points: torch.Tensor, towards: float = -1.0) -> torch.Tensor:
    n = torch.zeros_like(points)
    n[:, 2] = towards
    return n


def pose_at(z: float, dtype: torch.dtype = torch.float64, x: float = 0.0) -> torch.Tensor:
    T = torch.eye(4, dtype=dtype)
    T[0, 3], T[2, 3] = x, z
    return T


@given(
    seed=st.integers(0, 2**31 - 1),
    B=st.integers(1, 3),
    N=st.integers(1, 20),
    size=st.integers(8, 64),
    double=st.booleans(),
)
def test_crop_intrinsics_match_pixels_to_crop(
    seed: int, B: int, N: int, size: int, double: bool
) -> None:
    """A point projects into the crop where pixels_to_crop maps its image projection."""
    dtype = torch.float64 if double else torch.float32
    g = torch.Generator().manual_seed(seed)
    K = K_IMG.to(dtype)
    pts = torch.rand(B, N, 3, generator=g, dtype=dtype) - 0.5
    pts[..., 2] = 0.5 + torch.rand(B, N, generator=g, dtype=dtype)
    centre = torch.rand(B, 2, generator=g, dtype=dtype) * 100
    side = 5 + 100 * torch.rand(B, 1, generator=g, dtype=dtype)
    boxes = torch.cat((centre - side / 2, centre + side / 2), -1)
    uv = project_points(pts, K)
    expected = pixels_to_crop(uv, boxes, size)
    got = project_points(pts, crop_intrinsics(K, boxes, size))
    tol = 1e-9 if double else 2e-3
    assert got.dtype == dtype
    torch.testing.assert_close(got, expected, atol=tol * size, rtol=0)


@given(
    seed=st.integers(0, 2**31 - 1),
    rows=st.integers(1, 20),
    cols=st.integers(1, 20),
    half=st.integers(0, 4),
    double=st.booleans(),
)
def test_box_sum_equals_pooling(seed: int, rows: int, cols: int, half: int, double: bool) -> None:
    dtype = torch.float64 if double else torch.float32
    x = torch.rand(3, 2, rows, cols, generator=torch.Generator().manual_seed(seed), dtype=dtype)
    window = 2 * half + 1
    padded = torch.nn.functional.pad(x, (half, half, half, half))
    expected = torch.nn.functional.avg_pool2d(padded, window, stride=1, divisor_override=1)
    torch.testing.assert_close(box_sum(x, window), expected)
    with pytest.raises(ValueRangeError):
        box_sum(x, 2)


@given(z=st.floats(0.3, 3.0), tilt=st.floats(-0.6, 0.6), size=st.integers(16, 48))
def test_plane_depth_is_exact(z: float, tilt: float, size: int) -> None:
    """Every drawn pixel of a tilted plane holds a depth on that plane."""
    pts = grid_plane(120, 0.2)
    R = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    c, s = torch.cos(torch.tensor(tilt)), torch.sin(torch.tensor(tilt))
    R[0, 0], R[0, 2], R[2, 0], R[2, 2] = c, s, -s, c
    T = pose_at(z)
    T[:3, :3] = R
    f = 2.0 * size * z  # the plane spans most of the crop at any distance
    K = torch.tensor([[f, 0.0, size / 2], [0.0, f, size / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)
    out = render_points(
        pts[None], facing(pts)[None], torch.ones(1, pts.shape[0], 1, dtype=torch.float64),
        T[None, None], K[None], size, surface_tolerance=1e-3, occlusion_tolerance=0.05,
    )  # fmt: skip
    drawn = out.mask[0, 0]
    assert drawn.float().mean() > 0.2
    v, u = drawn.nonzero(as_tuple=True)
    rays = torch.stack((u.double(), v.double(), torch.ones_like(u.double())), -1) @ K.inverse().T
    points = rays * out.depth[0, 0][drawn][:, None]
    n, origin = R[:, 2], T[:3, 3]
    # a pixel shows the nearest sample falling in it: within a pixel's footprint of the plane
    footprint = z / f * (1 + abs(float(s)) / float(c)) * 2
    assert ((points - origin) @ n).abs().max() < footprint


def test_backfaces_zbuffer_and_front_colour() -> None:
    pts = grid_plane(80, 0.05)
    N = pts.shape[0]
    K = torch.tensor(
        [[[200.0, 0.0, 16.0], [0.0, 200.0, 16.0], [0.0, 0.0, 1.0]]], dtype=torch.float64
    )
    near = torch.full((1, N, 1), 0.25, dtype=torch.float64)
    args = {"surface_tolerance": 1e-3, "occlusion_tolerance": 0.02}
    # facing away from the camera: culled
    away = render_points(
        pts[None], facing(pts, 1.0)[None], near, pose_at(1.0)[None, None], K, 32, **args
    )
    assert not away.mask.any() and (away.depth == 0).all()
    # two planes, the nearer one (value 0.25) hides the farther one (value 0.75)
    both = torch.cat((pts, pts))
    both_T = torch.cat((pts, pts + torch.tensor([0.0, 0.0, 0.1], dtype=torch.float64)))
    values = torch.cat((near[0], torch.full((N, 1), 0.75, dtype=torch.float64)))[None]
    out = render_points(
        both_T[None], facing(both)[None], values, pose_at(1.0)[None, None], K, 32, **args
    )
    drawn = out.mask[0, 0]
    assert drawn.any()
    torch.testing.assert_close(
        out.depth[0, 0][drawn], torch.ones(int(drawn.sum()), dtype=torch.float64)
    )
    torch.testing.assert_close(
        out.color[0, 0, 0][drawn], torch.full((int(drawn.sum()),), 0.25, dtype=torch.float64)
    )


def test_sparse_samples_leave_no_holes_inside() -> None:
    """Samples sparser than the pixels are filled; the silhouette does not grow."""
    g = torch.Generator().manual_seed(0)
    pts = (torch.rand(2000, 3, generator=g, dtype=torch.float64) - 0.5) * 0.1
    pts[:, 2] = 0.0
    K = torch.tensor(
        [[[400.0, 0.0, 31.5], [0.0, 400.0, 31.5], [0.0, 0.0, 1.0]]], dtype=torch.float64
    )
    args = (pts[None], facing(pts)[None], torch.ones(1, 2000, 1, dtype=torch.float64))
    kw = {"surface_tolerance": 1e-3, "occlusion_tolerance": 0.01}
    inner = (0, 0, slice(15, 48), slice(15, 48))  # the square spans pixels 12..51

    def holes(passes: int) -> int:
        out = render_points(*args, pose_at(1.0)[None, None], K, 64, fill_passes=passes, **kw)
        return int((~out.mask[inner]).sum())

    counts = [holes(p) for p in (0, 1, 3)]
    assert counts[0] > 100 and counts[0] > counts[1] > counts[2] == 0
    out = render_points(*args, pose_at(1.0)[None, None], K, 64, **kw)
    assert not out.mask[0, 0, :10].any() and not out.mask[0, 0, :, 54:].any()


def test_back_surface_through_gaps_is_dropped() -> None:
    """A far surface seen between sparse front samples does not show through."""
    g = torch.Generator().manual_seed(1)
    front = (torch.rand(2500, 3, generator=g, dtype=torch.float64) - 0.5) * 0.1
    front[:, 2] = 0.0
    back = grid_plane(200, 0.05) + torch.tensor([0.0, 0.0, 0.2], dtype=torch.float64)
    pts = torch.cat((front, back))
    vals = torch.cat((torch.zeros(2500, 1), torch.ones(back.shape[0], 1))).double()
    K = torch.tensor(
        [[[400.0, 0.0, 31.5], [0.0, 400.0, 31.5], [0.0, 0.0, 1.0]]], dtype=torch.float64
    )
    out = render_points(
        pts[None], facing(pts)[None], vals[None], pose_at(1.0)[None, None], K, 64,
        surface_tolerance=1e-3, occlusion_tolerance=0.05,
    )  # fmt: skip
    inner = (slice(18, 46), slice(18, 46))
    drawn = out.mask[0, 0][inner]
    assert drawn.float().mean() > 0.9
    assert (out.depth[0, 0][inner][drawn] < 1.1).all()  # never the back plane at 1.2
    assert (out.color[0, 0, 0][inner] == 0).all()
    # without the occlusion test the back plane shows through the gaps
    seen = render_points(
        pts[None], facing(pts)[None], vals[None], pose_at(1.0)[None, None], K, 64,
        surface_tolerance=1e-3, occlusion_tolerance=1.0,
    )  # fmt: skip
    assert (seen.depth[0, 0][inner] > 1.1).any()


@given(seed=st.integers(0, 2**31 - 1), B=st.integers(1, 3), H=st.integers(1, 4))
def test_batched_equals_per_item(seed: int, B: int, H: int) -> None:
    g = torch.Generator().manual_seed(seed)
    N = 500
    pts = (torch.rand(B, N, 3, generator=g) - 0.5) * 0.1
    nrm = torch.nn.functional.normalize(torch.randn(B, N, 3, generator=g), dim=-1)
    col = torch.rand(B, N, 2, generator=g)
    poses = torch.eye(4).repeat(B, H, 1, 1)
    poses[..., :3, :3] = random_rotation(B * H, generator=g).reshape(B, H, 3, 3)
    poses[..., 2, 3] = 0.5 + torch.rand(B, H, generator=g)
    K = torch.tensor([[100.0, 0.0, 12.0], [0.0, 100.0, 12.0], [0.0, 0.0, 1.0]]).repeat(B, 1, 1)
    surf, occl = torch.rand(B, generator=g) * 0.01, torch.rand(B, generator=g) * 0.05
    out = render_points(
        pts, nrm, col, poses, K, 24, surface_tolerance=surf, occlusion_tolerance=occl
    )
    for b in range(B):
        for h in range(H):
            one = render_points(
                pts[b : b + 1], nrm[b : b + 1], col[b : b + 1], poses[b : b + 1, h : h + 1],
                K[b : b + 1], 24, surface_tolerance=surf[b : b + 1],
                occlusion_tolerance=occl[b : b + 1],
            )  # fmt: skip
            assert torch.equal(one.mask[0, 0], out.mask[b, h])
            torch.testing.assert_close(one.depth[0, 0], out.depth[b, h])
            torch.testing.assert_close(one.color[0, 0], out.color[b, h])


@given(
    seed=st.integers(0, 2**31 - 1),
    B=st.integers(1, 3),
    H=st.integers(1, 4),
    double=st.booleans(),
    masked=st.booleans(),
)
def test_compiled_splat_equals_the_tensor_splat_bit_for_bit(
    seed: int, B: int, H: int, double: bool, masked: bool
) -> None:
    from poseflow.verify.render import _splat_compiled, _splat_tensors

    dtype = torch.float64 if double else torch.float32
    g = torch.Generator().manual_seed(seed)
    N, S = 700, 20
    pts = ((torch.rand(B, N, 3, generator=g) - 0.5) * 0.1).to(dtype)
    pts[:, :50] = pts[:, 50:100]  # coincident points: ties in the z-buffer
    nrm = torch.nn.functional.normalize(torch.randn(B, N, 3, generator=g), dim=-1).to(dtype)
    col = torch.rand(B, N, 3, generator=g).to(dtype)
    R = random_rotation(B * H, generator=g).reshape(B, H, 3, 3).to(dtype)
    t = torch.stack(
        (0.02 * torch.randn(B, H, generator=g), 0.02 * torch.randn(B, H, generator=g),
         0.04 + torch.rand(B, H, generator=g)), -1,
    ).to(dtype)  # fmt: skip
    K = torch.tensor([[60.0, 0.5, 10.0], [0.0, 60.0, 10.0], [0.0, 0.0, 1.0]], dtype=dtype)
    mask = torch.rand(B, N, generator=g) > 0.2 if masked else None
    surface = (torch.rand(B, generator=g) * 0.01).to(dtype)
    args = (pts, nrm, col, R, t, K.repeat(B, 1, 1), S, mask, surface)
    compiled, tensors = _splat_compiled(*args), _splat_tensors(*args)
    assert torch.isfinite(tensors[0]).sum() > 0
    for a, b in zip(compiled, tensors, strict=True):
        assert a.dtype == b.dtype == dtype and torch.equal(a, b)


@given(
    seed=st.integers(0, 2**31 - 1),
    B=st.integers(1, 2),
    H=st.integers(1, 3),
    passes=st.integers(0, 3),
    double=st.booleans(),
)
def test_compiled_gap_closing_equals_the_tensor_one_bit_for_bit(
    seed: int, B: int, H: int, passes: int, double: bool
) -> None:
    from poseflow.verify.render import _close_gaps_compiled, _close_gaps_tensors

    dtype = torch.float64 if double else torch.float32
    g = torch.Generator().manual_seed(seed)
    S, C = 16, 3
    size = B * H * S * S
    zbuf = (0.5 + 0.1 * torch.rand(size, generator=g)).to(dtype)
    zbuf[torch.rand(size, generator=g) < 0.35] = torch.inf  # gaps of every width
    count = torch.randint(0, 4, (size,), generator=g).to(dtype)
    csum = (torch.rand(size, C, generator=g) * count[:, None]).to(dtype)
    occlusion = (0.05 * torch.rand(B, generator=g)).to(dtype)
    args = (zbuf, csum, count, occlusion, H, S, passes)
    compiled, tensors = _close_gaps_compiled(*args), _close_gaps_tensors(*args)
    assert torch.equal(compiled.mask, tensors.mask)
    assert torch.equal(compiled.depth, tensors.depth) and torch.equal(compiled.color, tensors.color)
    assert compiled.depth.dtype == dtype


def test_point_mask_hides_padding() -> None:
    pts = grid_plane(40, 0.05)
    vals = torch.ones(1, pts.shape[0], 1, dtype=torch.float64)
    K = torch.tensor(
        [[[200.0, 0.0, 16.0], [0.0, 200.0, 16.0], [0.0, 0.0, 1.0]]], dtype=torch.float64
    )
    mask = torch.zeros(1, pts.shape[0], dtype=torch.bool)
    out = render_points(
        pts[None], facing(pts)[None], vals, pose_at(1.0)[None, None], K, 32,
        point_mask=mask, surface_tolerance=1e-3, occlusion_tolerance=0.02,
    )  # fmt: skip
    assert not out.mask.any()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cpu_and_cuda_agree() -> None:
    g = torch.Generator().manual_seed(3)
    B, H, N = 2, 3, 2000
    pts = (torch.rand(B, N, 3, generator=g, dtype=torch.float64) - 0.5) * 0.1
    nrm = torch.nn.functional.normalize(
        torch.randn(B, N, 3, generator=g, dtype=torch.float64), dim=-1
    )
    col = torch.rand(B, N, 1, generator=g, dtype=torch.float64)
    poses = torch.eye(4, dtype=torch.float64).repeat(B, H, 1, 1)
    poses[..., :3, :3] = random_rotation(B * H, generator=g, dtype=torch.float64).reshape(
        B, H, 3, 3
    )
    poses[..., 2, 3] = 0.6
    K = torch.tensor([[120.0, 0.0, 16.0], [0.0, 120.0, 16.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    args = {"surface_tolerance": 0.003, "occlusion_tolerance": 0.02}
    cpu = render_points(pts, nrm, col, poses, K.repeat(B, 1, 1), 32, **args)
    gpu = render_points(
        pts.cuda(), nrm.cuda(), col.cuda(), poses.cuda(), K.repeat(B, 1, 1).cuda(), 32, **args
    )
    assert torch.equal(cpu.mask, gpu.mask.cpu())
    torch.testing.assert_close(cpu.depth, gpu.depth.cpu())
    torch.testing.assert_close(cpu.color, gpu.color.cpu())


def test_crop_observation_matches_crop_resize() -> None:
    g = torch.Generator().manual_seed(0)
    Hi, Wi = 40, 50
    depth = torch.rand(Hi, Wi, generator=g, dtype=torch.float64)
    masks = torch.rand(2, Hi, Wi, generator=g) > 0.5
    rgb = torch.rand(3, Hi, Wi, generator=g, dtype=torch.float64)
    boxes = torch.tensor([[3.5, 2.5, 19.5, 18.5], [-4.5, 30.5, 11.5, 46.5]], dtype=torch.float64)
    crops = crop_observation(depth, masks, boxes, 16, rgb)  # pixel size 1: no supersampling
    near_d = crop_resize(depth.expand(2, 1, Hi, Wi), boxes, 16, mode="nearest")[:, 0]
    near_m = crop_resize(masks[:, None].double(), boxes, 16, mode="nearest")[:, 0] > 0.5
    lin = crop_resize(rgb.expand(2, 3, Hi, Wi), boxes, 16)
    torch.testing.assert_close(crops.depth, near_d)
    assert torch.equal(crops.mask, near_m)
    torch.testing.assert_close(crops.color, lin)
    assert not crops.mask[1, -4:].any()  # rows below the image


def test_crop_observation_area_averages_when_shrinking() -> None:
    rgb = torch.zeros(3, 64, 64)
    rgb[:, :, ::2] = 1.0  # one-pixel stripes: aliasing would give 0 or 1
    crops = crop_observation(
        torch.ones(64, 64), torch.ones(1, 64, 64, dtype=torch.bool),
        torch.tensor([[-0.5, -0.5, 63.5, 63.5]]), 16, rgb,
    )  # fmt: skip
    torch.testing.assert_close(crops.color, torch.full((1, 3, 16, 16), 0.5))


def test_crop_observation_uint8_and_nan_depth() -> None:
    depth = torch.full((10, 10), float("nan"))
    rgb = torch.full((3, 10, 10), 255, dtype=torch.uint8)
    crops = crop_observation(
        depth,
        torch.ones(1, 10, 10, dtype=torch.bool),
        torch.tensor([[-0.5, -0.5, 9.5, 9.5]]),
        5,
        rgb,
    )
    assert (crops.depth == 0).all()
    torch.testing.assert_close(crops.color, torch.ones(1, 3, 5, 5))


def test_bad_inputs_raise() -> None:
    pts = torch.zeros(1, 4, 3)
    K = torch.eye(3)[None]
    with pytest.raises(ShapeError):
        render_points(pts, pts, torch.zeros(1, 5, 1), torch.eye(4)[None, None], K, 8,
                      surface_tolerance=0.1, occlusion_tolerance=0.1)  # fmt: skip
    with pytest.raises(ValueRangeError):
        render_points(pts, pts, torch.zeros(1, 4, 1), torch.eye(4)[None, None], K, 0,
                      surface_tolerance=0.1, occlusion_tolerance=0.1)  # fmt: skip
    with pytest.raises(ShapeError):
        render_points(pts, pts, torch.zeros(1, 4, 1), torch.eye(4)[None, None], K, 8,
                      surface_tolerance=torch.zeros(2), occlusion_tolerance=0.1)  # fmt: skip
    with pytest.raises(ValueRangeError):
        render_points(pts, pts, torch.zeros(1, 4, 1), torch.eye(4)[None, None], K, 8,
                      surface_tolerance=0.1, occlusion_tolerance=0.1, fill_passes=-1)  # fmt: skip
    with pytest.raises(ValueRangeError):
        crop_intrinsics(torch.eye(3), torch.tensor([[1.0, 1.0, 1.0, 2.0]]), 8)
    with pytest.raises(ShapeError):
        crop_observation(torch.zeros(4, 4), torch.ones(1, 5, 4, dtype=torch.bool),
                         torch.tensor([[0.0, 0.0, 2.0, 2.0]]), 4)  # fmt: skip
