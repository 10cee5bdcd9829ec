"""Tests of the ray-casting renderer against analytic geometry."""

from __future__ import annotations

import math

import numpy as np
import open3d as o3d
import pytest
import torch

from poseflow.errors import ShapeError, ValueRangeError
from poseflow.geometry.se3 import random_rotation
from poseflow.render import Light, Renderer, TexturedMesh, as_textured_mesh, render, sample_texture

W, H = 64, 48
K = torch.tensor([[80.0, 0.0, 31.0], [0.0, 90.0, 23.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def quad(x0: float, x1: float, y0: float, y1: float, **kw: object) -> TexturedMesh:
    """A rectangle in the z=0 plane facing -z (toward a camera looking along +z)."""
    v = np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]])
    f = np.array([[0, 2, 1], [0, 3, 2]])
    return TexturedMesh(v, f, **kw)


def pose_at(z: float, R: np.ndarray | None = None) -> torch.Tensor:
    T = torch.eye(4, dtype=torch.float64)
    if R is not None:
        T[:3, :3] = torch.as_tensor(R)
    T[2, 3] = z
    return T


def pixel_rays() -> np.ndarray:
    uu, vv = np.meshgrid(np.arange(W), np.arange(H))
    pix = np.stack([uu, vv, np.ones_like(uu)], -1).astype(np.float64)
    return pix @ np.linalg.inv(K.numpy()).T


def test_plane_at_known_depth() -> None:
    out = render([quad(-5, 5, -5, 5)], pose_at(0.7)[None], K, W, H)
    assert out.depth.dtype == torch.float32 and out.depth.shape == (H, W)
    assert torch.allclose(out.depth, torch.full((H, W), 0.7), atol=1e-6)
    assert (out.instance == 0).all() and out.masks_full.all()
    assert out.rgb.shape == (H, W, 3) and out.rgb.dtype == torch.uint8
    assert torch.allclose(out.normals, torch.tensor([0.0, 0.0, -1.0]).expand(H, W, 3))


def test_tilted_plane_depth_and_backprojection() -> None:
    a = math.radians(35.0)
    R = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    out = render([quad(-5, 5, -5, 5)], pose_at(1.0, R)[None], K, W, H)
    # plane through (0, 0, 1) with normal R e_z: z(u, v) = d / (n . K^-1 [u, v, 1])
    n = R[:, 2]
    rays = pixel_rays()
    z = (n @ np.array([0, 0, 1.0])) / (rays @ n)
    np.testing.assert_allclose(out.depth.numpy(), z, rtol=1e-5)
    pts = rays * out.depth.numpy()[..., None]
    np.testing.assert_allclose((pts - [0, 0, 1.0]) @ n, 0.0, atol=1e-5)
    np.testing.assert_allclose(np.abs(out.normals.numpy() @ n), 1.0, atol=1e-5)


def test_pixel_centre_convention_at_an_edge() -> None:
    # the quad starts at x_e; pixel u's ray has x/z = (u - cx) / fx
    z, cx, fx = 1.0, K[0, 2].item(), K[0, 0].item()
    x_e = (40.3 - cx) / fx * z
    out = render([quad(x_e, 5, -5, 5)], pose_at(z)[None], K, W, H)
    assert not out.masks_full[0, :, :41].any()
    assert out.masks_full[0, :, 41:].all()


def test_sphere_silhouette_and_depth() -> None:
    r, d = 0.05, 0.6
    sphere = o3d.geometry.TriangleMesh.create_sphere(r, resolution=80)
    sphere.compute_vertex_normals()
    Kb = torch.tensor([[500.0, 0, 79.0], [0, 500.0, 79.0], [0, 0, 1]])
    out = render([sphere], pose_at(d)[None], Kb, 160, 160)
    # the silhouette of a sphere seen from its centre's ray is a disc of angular radius asin(r/d)
    radius_px = 500.0 * math.tan(math.asin(r / d))
    area = out.masks_full[0].sum().item()
    assert abs(area - math.pi * radius_px**2) < 0.02 * math.pi * radius_px**2
    assert abs(out.depth[79, 79].item() - (d - r)) < 2e-4
    mask = out.depth > 0
    vv, uu = torch.nonzero(mask, as_tuple=True)
    rays = torch.stack([uu, vv, torch.ones_like(uu)], 1).double() @ torch.linalg.inv(Kb.double()).T
    pts = rays * out.depth[mask].double()[:, None]
    dist = (pts - torch.tensor([0, 0, d], dtype=torch.float64)).norm(dim=1)
    assert (dist - r).abs().max() < 5e-4
    # smooth normals point away from the centre
    cos = (out.normals[mask].double() * (pts - torch.tensor([0, 0, d]).double())).sum(1) / dist
    assert cos.min() > 0.99


def test_occlusion_masks_and_visib_fract() -> None:
    front = quad(-0.05, 0.05, -0.05, 0.05)
    back = quad(-0.1, 0.1, -0.1, 0.1)
    poses = torch.stack([pose_at(0.5), pose_at(1.0)])
    r = Renderer([front, back])
    out = r.render(poses, K, W, H)
    alone = [r.render(poses[i : i + 1], K, W, H, object_ids=[i]) for i in range(2)]
    for i in range(2):
        assert torch.equal(out.masks_full[i], alone[i].masks_full[0])
    vis = out.masks_visible
    assert torch.equal(vis[0], out.masks_full[0])
    assert torch.equal(vis[1], out.masks_full[1] & ~out.masks_full[0])
    assert torch.allclose(out.depth[out.instance == 0], torch.tensor(0.5))
    assert torch.allclose(out.depth[out.instance == 1], torch.tensor(1.0))
    frac = out.visib_fract
    expected = vis[1].sum().item() / out.masks_full[1].sum().item()
    assert frac[0].item() == 1.0 and abs(frac[1].item() - expected) < 1e-12 and frac[1] < 1


def test_same_mesh_twice_and_out_of_view() -> None:
    box = o3d.geometry.TriangleMesh.create_box(0.05, 0.05, 0.05)
    r = Renderer([box])
    left, right, behind = pose_at(0.5), pose_at(0.5), pose_at(-0.5)
    left[0, 3], right[0, 3] = -0.1, 0.1
    out = r.render(torch.stack([left, right, behind]), K, W, H, object_ids=[0, 0, 0])
    assert out.masks_full[0].any() and out.masks_full[1].any() and not out.masks_full[2].any()
    assert out.visib_fract[2].item() == 0.0
    cols = torch.nonzero(out.masks_full[0])[:, 1]
    assert cols.max() < W // 2 <= torch.nonzero(out.masks_full[1])[:, 1].min()


def test_texture_orientation_matches_image() -> None:
    # asymmetric texture: three distinct quadrant colours and a white top-left corner texel
    tex = np.zeros((8, 8, 3), np.uint8)
    tex[:4, :4] = (255, 0, 0)
    tex[:4, 4:] = (0, 255, 0)
    tex[4:, :4] = (0, 0, 255)
    tex[4:, 4:] = (255, 255, 0)
    # camera: x right, y down; the quad's top-left corner (-a, -a) carries uv (0, 1)
    a = 1.0
    uv_of = {(-a, -a): (0, 1), (a, -a): (1, 1), (a, a): (1, 0), (-a, a): (0, 0)}
    m0 = quad(-a, a, -a, a)
    uvs = np.array([[uv_of[tuple(m0.vertices[i, :2])] for i in tri] for tri in m0.triangles])
    m = quad(-a, a, -a, a, triangle_uvs=uvs, texture=tex)
    light = Light(ambient=1.0, diffuse=0.0)
    Kq = torch.tensor([[20.0, 0, 19.5], [0, 20.0, 19.5], [0, 0, 1]])
    out = render([m], pose_at(1.0)[None], Kq, 40, 40, light=light)
    rgb = out.rgb.numpy()
    assert tuple(rgb[5, 5]) == (255, 0, 0)
    assert tuple(rgb[5, 34]) == (0, 255, 0)
    assert tuple(rgb[34, 5]) == (0, 0, 255)
    assert tuple(rgb[34, 34]) == (255, 255, 0)


def test_texture_survives_open3d_conversion() -> None:
    tex = np.zeros((4, 4, 3), np.uint8)
    tex[0] = 255
    m = quad(0, 1, 0, 1, triangle_uvs=np.full((2, 3, 2), 0.5), texture=tex)
    back = TexturedMesh.from_open3d(m.to_open3d())
    np.testing.assert_array_equal(back.texture, m.texture)
    np.testing.assert_allclose(back.triangle_uvs, m.triangle_uvs)


def test_vertex_colours_and_lambert_shading() -> None:
    a = math.radians(60.0)
    R = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    colours = np.array([[1.0, 0.5, 0.25]] * 4)
    m = quad(-5, 5, -5, 5, vertex_colors=colours)
    light = Light(ambient=0.2, diffuse=0.6)
    out = render([m], pose_at(1.0, R)[None], K, W, H, light=light)
    shade = 0.2 + 0.6 * math.cos(a)
    expected = np.round(colours[0] * shade * 255.0)
    np.testing.assert_allclose(
        out.rgb.numpy().reshape(-1, 3), expected[None].repeat(W * H, 0), atol=1
    )


def test_barycentric_colour_interpolation() -> None:
    v = np.array([[-1.0, -1.0, 0.0], [3.0, -1.0, 0.0], [-1.0, 3.0, 0.0]])
    c = np.eye(3)
    m = TexturedMesh(v, np.array([[0, 2, 1]]), vertex_colors=c)
    Kq = torch.tensor([[10.0, 0, 10.0], [0, 10.0, 10.0], [0, 0, 1]])
    out = render([m], pose_at(1.0)[None], Kq, 21, 21, light=Light(ambient=1.0, diffuse=0.0))
    # pixel (10, 10) sees the point (0, 0): weights 1/2, 1/4, 1/4 for vertices 0, 1, 2
    np.testing.assert_allclose(out.rgb[10, 10].numpy(), [127.5, 63.75, 63.75], atol=1.0)


def test_background_image_kept() -> None:
    bg = torch.randint(
        0, 256, (H, W, 3), dtype=torch.uint8, generator=torch.Generator().manual_seed(0)
    )
    out = render([quad(-0.01, 0.01, -0.01, 0.01)], pose_at(1.0)[None], K, W, H, background=bg)
    keep = out.instance < 0
    assert keep.any() and torch.equal(out.rgb[keep], bg[keep])
    out2 = render(
        [quad(-0.01, 0.01, -0.01, 0.01)], pose_at(1.0)[None], K, W, H, background=(1, 2, 3)
    )
    assert tuple(out2.rgb[0, 0].tolist()) == (1, 2, 3)


def test_as_textured_mesh_accepts_wrappers() -> None:
    m = quad(0, 1, 0, 1)

    class Wrapper:
        mesh = m

    assert as_textured_mesh(Wrapper()) is m
    with pytest.raises(ShapeError):
        as_textured_mesh("not a mesh")


def test_sample_texture_bilinear_centre() -> None:
    tex = np.zeros((1, 2, 3), np.uint8)
    tex[0, 1] = 200
    np.testing.assert_allclose(sample_texture(tex, np.array([[0.5, 0.5]]))[0], 100 / 255, atol=1e-6)


def test_bad_input() -> None:
    r = Renderer([quad(0, 1, 0, 1)])
    with pytest.raises(ShapeError):
        r.render(torch.eye(4), K, W, H)
    with pytest.raises(ShapeError):
        r.render(torch.eye(4)[None], K[:2], W, H)
    with pytest.raises(ShapeError):
        r.render(torch.eye(4)[None], K, W, H, object_ids=[3])
    with pytest.raises(ValueRangeError):
        r.render(torch.full((1, 4, 4), float("nan")), K, W, H)
    with pytest.raises(ValueRangeError):
        r.render(torch.eye(4)[None], K, 0, H)
    with pytest.raises(ShapeError):
        r.render(torch.eye(4)[None], K, W, H, background=np.zeros((2, 2, 3), np.uint8))
    with pytest.raises(ShapeError):
        TexturedMesh(np.zeros((3, 2)), np.array([[0, 1, 2]]))
    with pytest.raises(ValueRangeError):
        TexturedMesh(np.zeros((3, 3)), np.array([[0, 1, 3]]))
    with pytest.raises(ShapeError):
        Renderer([])


def test_depth_matches_open3d_full_scene_cast() -> None:
    box = o3d.geometry.TriangleMesh.create_box(0.1, 0.06, 0.04).translate((-0.05, -0.03, -0.02))
    sphere = o3d.geometry.TriangleMesh.create_sphere(0.04, resolution=20)
    g = torch.Generator().manual_seed(0)
    poses = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    poses[:, :3, :3] = random_rotation(2, generator=g, dtype=torch.float64)
    poses[:, :3, 3] = torch.tensor([[-0.03, 0.0, 0.5], [0.03, 0.01, 0.55]], dtype=torch.float64)
    out = render([box, sphere], poses, K, W, H)
    scene = o3d.t.geometry.RaycastingScene()
    for m, T in zip((box, sphere), poses.numpy()):
        posed = o3d.geometry.TriangleMesh(m).transform(T)
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(posed))
    # Open3D's pinhole rays pass through (u + 0.5, v + 0.5): shift the principal point by +0.5
    shift = np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])
    rays = scene.create_rays_pinhole(
        o3d.core.Tensor(K.numpy() + shift), o3d.core.Tensor(np.eye(4)), W, H
    )
    hit = scene.cast_rays(rays)
    z = hit["t_hit"].numpy() * rays.numpy()[..., 5]
    seen = np.isfinite(z)
    assert np.array_equal(seen, out.depth.numpy() > 0)
    np.testing.assert_allclose(out.depth.numpy()[seen], z[seen], atol=1e-5)
    ids = hit["geometry_ids"].numpy().astype(np.int64)
    assert np.array_equal(np.where(seen, ids, -1), out.instance.numpy())
