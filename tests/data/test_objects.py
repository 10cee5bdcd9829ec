"""Tests of mesh loading, object models and symmetries."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import torch
from PIL import Image
from scipy.spatial.transform import Rotation

from poseflow.data.bop import read_models_info
from poseflow.data.objects import (
    ObjectModel,
    discretize_symmetries,
    load_mesh,
    mesh_vertex_arrays,
    sample_surface,
    symmetries_from_info,
    write_bop_model,
    write_bop_models,
)
from poseflow.errors import MeshFormatError, ValueRangeError
from poseflow.render import Light, Renderer, TexturedMesh

HEADLIGHT_FLAT = Light(ambient=1.0, diffuse=0.0)


def quadrant_texture() -> np.ndarray:
    tex = np.zeros((8, 8, 3), np.uint8)
    tex[:4, :4] = (255, 0, 0)  # top-left red
    tex[:4, 4:] = (0, 255, 0)  # top-right green
    tex[4:, :4] = (0, 0, 255)  # bottom-left blue
    tex[4:, 4:] = (255, 255, 0)  # bottom-right yellow
    return tex


def render_front(mesh: TexturedMesh, size: int = 40) -> np.ndarray:
    """Render a unit square in the model's z=0 plane seen from +z, upright (model y up)."""
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
    T[2, 3] = 1.0
    f = size / 2.0
    K = torch.tensor([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1]])
    return Renderer([mesh]).render(T[None], K, size, size, light=HEADLIGHT_FLAT).rgb.numpy()


def assert_quadrants(rgb: np.ndarray) -> None:
    n = rgb.shape[0]
    a, b = n // 8, n - 1 - n // 8
    assert tuple(rgb[a, a]) == (255, 0, 0)
    assert tuple(rgb[a, b]) == (0, 255, 0)
    assert tuple(rgb[b, a]) == (0, 0, 255)
    assert tuple(rgb[b, b]) == (255, 255, 0)


def write_textured_obj(folder: Path, name: str = "quad") -> Path:
    Image.fromarray(quadrant_texture()).save(folder / "tex.png")
    (folder / f"{name}.mtl").write_text("newmtl paint\nKd 1 1 1\nmap_Kd tex.png\n")
    (folder / f"{name}.obj").write_text(
        f"mtllib {name}.mtl\n"
        "v -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\n"
        "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"
        "vn 0 0 1\n"
        "usemtl paint\n"
        "f 1/1/1 2/2/1 3/3/1 -1/-1/-1\n"  # a quad, with a negative (relative) index
    )
    return folder / f"{name}.obj"


def test_obj_quads_textures_and_orientation(tmp_path: Path) -> None:
    path = write_textured_obj(tmp_path)
    mesh = load_mesh(path)
    assert mesh.num_triangles == 2  # Open3D's OBJ reader would drop the quad
    assert mesh.has_texture and mesh.vertex_normals is not None
    assert_quadrants(render_front(mesh))


def test_obj_with_vertex_colours_and_scale(tmp_path: Path) -> None:
    p = tmp_path / "tri.obj"
    p.write_text("v 0 0 0 1 0 0\nv 10 0 0 0 1 0\nv 0 10 0 0 0 1\nf 1 2 3\n")
    m = load_mesh(p, scale=0.01)
    np.testing.assert_allclose(m.vertices.max(0), [0.1, 0.1, 0.0])
    np.testing.assert_allclose(m.vertex_colors, np.eye(3))


def test_ply_ascii_colours_and_polygons(tmp_path: Path) -> None:
    p = tmp_path / "a.ply"
    p.write_text(
        "ply\nformat ascii 1.0\nelement vertex 5\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        "element face 2\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0 255 0 0\n1 0 0 0 255 0\n1 1 0 0 0 255\n0 1 0 255 255 255\n2 2 0 0 0 0\n"
        "4 0 1 2 3\n3 1 4 2\n"
    )
    m = load_mesh(p)
    assert m.num_triangles == 3 and m.num_vertices == 5
    np.testing.assert_allclose(m.vertex_colors[0], [1, 0, 0])
    np.testing.assert_allclose(m.triangle_areas.sum(), 1.0 + 0.5)


def test_ply_binary_face_texcoords(tmp_path: Path) -> None:
    Image.fromarray(quadrant_texture()).save(tmp_path / "t.png")
    v = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float32)
    faces = [(0, 1, 2), (0, 2, 3)]
    uv = {0: (0, 0), 1: (1, 0), 2: (1, 1), 3: (0, 1)}
    header = (
        "ply\nformat binary_big_endian 1.0\ncomment TextureFile t.png\nelement vertex 4\n"
        "property float x\nproperty float y\nproperty float z\nelement face 2\n"
        "property list uchar int vertex_indices\nproperty list uchar float texcoord\nend_header\n"
    )
    body = v.astype(">f4").tobytes()
    for f in faces:
        body += np.uint8(3).tobytes() + np.asarray(f, ">i4").tobytes()
        body += np.uint8(6).tobytes() + np.asarray([uv[i] for i in f], ">f4").tobytes()
    (tmp_path / "b.ply").write_bytes(header.encode() + body)
    mesh = load_mesh(tmp_path / "b.ply")
    assert mesh.num_triangles == 2 and mesh.has_texture
    assert_quadrants(render_front(mesh))


def test_bop_ply_round_trip_in_mm(tmp_path: Path) -> None:
    obj = load_mesh(write_textured_obj(tmp_path))
    colours = np.random.default_rng(0).random((obj.num_vertices, 3))
    mesh = TexturedMesh(
        obj.vertices * 0.05,
        obj.triangles,
        colours,
        obj.vertex_normals,
        obj.triangle_uvs,
        obj.texture,
    )
    write_bop_model(tmp_path / "models" / "obj_000001.ply", mesh)
    header = (tmp_path / "models" / "obj_000001.ply").read_bytes()[:400]
    assert b"comment TextureFile obj_000001.png" in header
    back = load_mesh(tmp_path / "models" / "obj_000001.ply", scale=0.001)
    assert back.num_triangles == mesh.num_triangles
    corners = back.vertices[back.triangles]
    np.testing.assert_allclose(corners, mesh.vertices[mesh.triangles], atol=1e-7)
    np.testing.assert_allclose(back.triangle_uvs, mesh.triangle_uvs, atol=1e-6)
    np.testing.assert_array_equal(back.texture, mesh.texture)
    assert (
        np.abs(back.vertex_colors[back.triangles] - colours[mesh.triangles]).max()
        <= 0.5 / 255 + 1e-6
    )
    assert_quadrants(render_front(back.scaled(20.0)))


def test_mesh_vertex_arrays_splits_seams() -> None:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.0]])
    f = np.array([[0, 1, 2], [1, 3, 2]])
    uvs = np.array([[[0, 0], [1, 0], [0, 1]], [[0.5, 0.5], [1, 1], [0, 1]]], np.float32)
    m = TexturedMesh(v, f, triangle_uvs=uvs, texture=np.zeros((2, 2, 3), np.uint8))
    a = mesh_vertex_arrays(m)
    assert len(a["vertices"]) == 5  # vertex 1 has two different uvs
    np.testing.assert_allclose(a["vertices"][a["triangles"]], v[f])
    np.testing.assert_allclose(a["uvs"][a["triangles"]], uvs)


def test_open3d_fallback_and_errors(tmp_path: Path) -> None:
    box = o3d.geometry.TriangleMesh.create_box(0.1, 0.2, 0.3)
    box.compute_triangle_normals()
    o3d.io.write_triangle_mesh(str(tmp_path / "box.stl"), box)
    m = load_mesh(tmp_path / "box.stl")
    assert m.num_triangles == 12
    np.testing.assert_allclose(m.extent(), [0.1, 0.2, 0.3], atol=1e-6)
    with pytest.raises(MeshFormatError):
        load_mesh(tmp_path / "missing.ply")
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n")
    with pytest.raises(MeshFormatError):
        load_mesh(tmp_path / "bad.ply")
    (tmp_path / "trunc.ply").write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 30\nproperty float x\n"
        b"property float y\nproperty float z\nelement face 1\n"
        b"property list uchar int vertex_indices\nend_header\n" + b"\0" * 20
    )
    with pytest.raises(MeshFormatError):
        load_mesh(tmp_path / "trunc.ply")
    (tmp_path / "empty.obj").write_text("v 0 0 0\n")
    with pytest.raises(MeshFormatError):
        load_mesh(tmp_path / "empty.obj")


def rotation_angle(T: np.ndarray) -> float:
    return math.acos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1, 1))


def test_discretised_continuous_symmetry() -> None:
    offset = np.array([0.01, -0.02, 0.0])
    S = discretize_symmetries(continuous=[(np.array([0, 0, 2.0]), offset)], max_sym_disc_step=0.1)
    n = math.ceil(math.pi / 0.1)
    assert S.shape == (n, 4, 4)
    np.testing.assert_allclose(S[0], np.eye(4), atol=1e-12)
    for T in S:
        np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(T[:3, :3] @ offset + T[:3, 3], offset, atol=1e-12)  # axis fixed
    steps = sorted(rotation_angle(T) for T in S)
    assert math.isclose(steps[1], 2 * math.pi / n, rel_tol=1e-9)


def test_discretised_rotations_match_scipy() -> None:
    axis, offset = np.array([0.3, -1.2, 0.5]), np.array([0.02, 0.01, -0.03])
    S = discretize_symmetries(continuous=[(axis, offset)], max_sym_disc_step=0.05)
    n = math.ceil(math.pi / 0.05)
    rotvecs = (2 * math.pi * np.arange(n) / n)[:, None] * (axis / np.linalg.norm(axis))
    expected = Rotation.from_rotvec(rotvecs).as_matrix()
    assert np.abs(S[:, :3, :3] - expected).max() <= 1e-12
    assert np.abs(S[:, :3, 3] - (offset - expected @ offset)).max() <= 1e-12


def test_discrete_times_continuous() -> None:
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    S = discretize_symmetries([flip], [(np.array([0, 0, 1.0]), np.zeros(3))], max_sym_disc_step=0.5)
    assert S.shape == (2 * math.ceil(math.pi / 0.5), 4, 4)
    dets = np.linalg.det(S[:, :3, :3])
    np.testing.assert_allclose(dets, 1.0)
    assert any(np.allclose(T, flip) for T in S) and np.allclose(S[0], np.eye(4))
    with pytest.raises(ValueRangeError):
        discretize_symmetries([np.diag([-1.0, 1, 1, 1])])


def test_symmetries_from_raw_entry_and_model_info(tmp_path: Path) -> None:
    entry = {
        "diameter": 120.0,
        "min_x": -50, "min_y": -50, "min_z": -20, "size_x": 100, "size_y": 100, "size_z": 40,
        "symmetries_discrete": [[0, -1, 0, 0, 1, 0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]],
        "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 10.0, 0]}],
    }  # fmt: skip
    (tmp_path / "models_info.json").write_text(json.dumps({"1": entry}))
    info = read_models_info(tmp_path / "models_info.json")[1]
    raw = symmetries_from_info(entry, max_sym_disc_step=0.2)
    parsed = symmetries_from_info(info, max_sym_disc_step=0.2)
    np.testing.assert_allclose(raw, parsed, atol=1e-12)
    p = np.array([0.0, 0.01, 0.5])  # on the continuous axis (offset 10 mm in y)
    moved = raw[:, :3, :3] @ p + raw[:, :3, 3]
    # the continuous part keeps p; the discrete one (90° about z through the origin) moves it to
    # (-0.01, 0), which the continuous part then turns around the axis
    n = math.ceil(math.pi / 0.2)
    np.testing.assert_allclose(moved[:n], np.tile(p, (n, 1)), atol=1e-12)
    radius = np.linalg.norm(moved[n:, :2] - [0.0, 0.01], axis=1)
    np.testing.assert_allclose(radius, math.hypot(0.01, 0.01), atol=1e-12)
    assert raw.shape == (2 * n, 4, 4)


def test_sample_surface_uniform_by_area() -> None:
    # two triangles, one with 3x the area of the other
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 0, 0], [8, 0, 0], [5, 2, 0.0]])
    m = TexturedMesh(v, np.array([[0, 1, 2], [3, 4, 5]]))
    p, n, c = sample_surface(m, 8000, generator=torch.Generator().manual_seed(0))
    frac = (p[:, 0] >= 5).mean()
    assert abs(frac - 6 / 7) < 0.02
    np.testing.assert_allclose(n, np.tile([0, 0, 1.0], (8000, 1)))
    assert c.shape == (8000, 3) and np.allclose(c, 0.7)


def test_object_model_cloud_on_surface_and_deterministic() -> None:
    box = o3d.geometry.TriangleMesh.create_box(0.05, 0.08, 0.12).translate((-0.025, -0.04, -0.06))
    box.vertex_colors = o3d.utility.Vector3dVector(np.tile([0.2, 0.4, 0.6], (8, 1)))
    a = ObjectModel.from_mesh(box, num_points=300, seed=1)
    b = ObjectModel.from_mesh(box, num_points=300, seed=1)
    c = ObjectModel.from_mesh(box, num_points=300, seed=2)
    assert torch.equal(a.points, b.points) and not torch.equal(a.points, c.points)
    assert a.points.dtype == torch.float32 and a.points.shape == (300, 3)
    half = torch.tensor([0.025, 0.04, 0.06])
    # every point lies on a face of the box and its normal is that face's outward axis
    on_face = ((a.points.abs() - half).abs() < 1e-6) & (a.normals.abs() > 0.999)
    assert on_face.any(-1).all()
    assert ((a.points * a.normals).sum(-1) > 0).all()
    assert torch.allclose(a.colors, torch.tensor([0.2, 0.4, 0.6]).expand(300, 3))
    assert math.isclose(a.diameter, math.sqrt(0.05**2 + 0.08**2 + 0.12**2), rel_tol=1e-9)
    assert not a.is_symmetric and a.symmetries.shape == (1, 4, 4)
    # farthest-point sampling spreads points more evenly than plain random sampling
    rnd = torch.from_numpy(
        sample_surface(a.mesh, 300, generator=torch.Generator().manual_seed(1))[0]
    )
    gap = lambda p: torch.cdist(p, p).fill_diagonal_(1.0).min(1).values.min()  # noqa: E731
    assert gap(a.points.double()) > 2 * gap(rnd)


def test_object_model_from_file_and_bop_folder(tmp_path: Path) -> None:
    box = o3d.geometry.TriangleMesh.create_box(0.05, 0.05, 0.1).translate((-0.025, -0.025, -0.05))
    sym = {"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]}
    plain = ObjectModel.from_mesh(box, num_points=64, name="plain")
    symmetric = ObjectModel.from_mesh(
        box, num_points=64, symmetries_continuous=[(np.array([0, 0, 1.0]), np.zeros(3))]
    )
    paths = write_bop_models(tmp_path / "models", [plain, symmetric], obj_ids=[3, 7])
    assert sorted(paths) == [3, 7] and all(p.is_file() for p in paths.values())
    infos = read_models_info(tmp_path / "models" / "models_info.json")
    assert math.isclose(infos[3].diameter, plain.diameter, rel_tol=1e-6)
    assert not infos[3].symmetries_continuous and len(infos[7].symmetries_continuous) == 1
    np.testing.assert_allclose(infos[3].size_xyz, [0.05, 0.05, 0.1], atol=1e-9)
    raw = json.loads((tmp_path / "models" / "models_info.json").read_text())
    assert math.isclose(raw["3"]["diameter"], plain.diameter * 1000, rel_tol=1e-6)
    loaded = ObjectModel.from_file(paths[7], scale=0.001, info=sym, num_points=64)
    assert loaded.name == "obj_000007" and loaded.symmetries.shape[0] == 315
    assert math.isclose(loaded.diameter, plain.diameter, rel_tol=1e-6)
    again = ObjectModel.from_file(paths[7], scale=0.001, info=infos[7], num_points=64)
    assert torch.allclose(again.symmetries, loaded.symmetries)
    assert "obj_000007" in repr(loaded)


def test_from_file_refuses_an_implausible_scale(tmp_path: Path) -> None:
    from poseflow.errors import UnitsError

    box = o3d.geometry.TriangleMesh.create_box(0.1, 0.05, 0.04)
    write_bop_model(tmp_path / "box.ply", TexturedMesh.from_open3d(box))  # written in mm
    with pytest.raises(UnitsError, match=r"box\.ply has a diameter of 118\.7.* set scale=0\.001"):
        ObjectModel.from_file(tmp_path / "box.ply", num_points=32)
    with pytest.raises(UnitsError, match=r"--mesh-scale 0\.001"):
        ObjectModel.from_file(tmp_path / "box.ply", num_points=32, scale_name="--mesh-scale")
    model = ObjectModel.from_file(tmp_path / "box.ply", scale=0.001, num_points=32)
    assert model.diameter == pytest.approx(math.sqrt(0.1**2 + 0.05**2 + 0.04**2), rel=1e-6)


def test_content_key_follows_the_mesh_and_its_scale(tmp_path: Path) -> None:
    box = o3d.geometry.TriangleMesh.create_box(0.1, 0.05, 0.04)
    write_bop_model(tmp_path / "box.ply", TexturedMesh.from_open3d(box))
    a = ObjectModel.from_file(tmp_path / "box.ply", scale=0.001, num_points=32)
    same = ObjectModel.from_file(tmp_path / "box.ply", scale=0.001, num_points=32)
    bigger = ObjectModel.from_file(tmp_path / "box.ply", scale=0.002, num_points=32)
    other = ObjectModel.from_mesh(
        o3d.geometry.TriangleMesh.create_box(0.1, 0.05, 0.05), num_points=32
    )
    denser = ObjectModel.from_file(tmp_path / "box.ply", scale=0.001, num_points=64)
    assert a.content_key() == same.content_key()
    assert (
        len({a.content_key(), bigger.content_key(), other.content_key(), denser.content_key()}) == 4
    )
