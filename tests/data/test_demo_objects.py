"""Tests of the generated demo objects."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from poseflow.data.demo_objects import (
    DEMO_OBJECT_NAMES,
    _box_texture,
    _bracket_occupancy,
    demo_mesh,
    demo_objects,
    write_demo_models,
)
from poseflow.data.objects import load_mesh
from poseflow.errors import ValueRangeError
from poseflow.render import Light, Renderer, TexturedMesh

FLAT = Light(ambient=1.0, diffuse=0.0)


def signed_volume(m: TexturedMesh) -> float:
    t = m.vertices[m.triangles]
    return float(np.einsum("fi,fi->f", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6.0)


def edge_use(m: TexturedMesh) -> np.ndarray:
    """How many triangles use each undirected edge (vertices merged by position)."""
    _, ids = np.unique(np.round(m.vertices, 9), axis=0, return_inverse=True)
    f = ids.reshape(-1)[m.triangles]
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return counts


def pose(R: np.ndarray, z: float = 0.4) -> torch.Tensor:
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = torch.as_tensor(R)
    T[2, 3] = z
    return T


def rot(axis: int, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    i, j = [a for a in range(3) if a != axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


K = torch.tensor([[500.0, 0, 79.5], [0, 500.0, 79.5], [0, 0, 1]])


def test_sizes_appearance_and_determinism() -> None:
    meshes = {n: demo_mesh(n) for n in DEMO_OBJECT_NAMES}
    for m in meshes.values():
        ext = m.extent()
        assert 0.05 <= ext.max() <= 0.15 and ext.min() >= 0.03
        np.testing.assert_allclose(m.vertices.max(0) + m.vertices.min(0), 0.0, atol=1e-12)
    assert meshes["labelled_box"].has_texture and meshes["labelled_can"].has_texture
    bracket = meshes["bracket"]
    assert not bracket.has_texture and bracket.has_vertex_colors
    assert np.ptp(bracket.vertex_colors, axis=0).max() == 0  # one plain grey
    a, b = _box_texture(), _box_texture()
    np.testing.assert_array_equal(a, b)
    assert a.std() > 40  # rich artwork, not a flat colour
    with pytest.raises(ValueRangeError):
        demo_mesh("teapot")


@pytest.mark.parametrize("name", DEMO_OBJECT_NAMES)
def test_closed_outward_meshes_with_expected_volume(name: str) -> None:
    m = demo_mesh(name)
    assert (edge_use(m) == 2).all()  # closed, every edge between exactly two triangles
    vol = signed_volume(m)  # positive: triangles wound with outward normals
    if name == "labelled_box":
        expected = 0.09 * 0.12 * 0.04
    elif name == "labelled_can":
        n = 96  # the inscribed 96-gon prism
        expected = 0.5 * n * 0.033**2 * math.sin(2 * math.pi / n) * 0.115
    else:
        expected = _bracket_occupancy().sum() * 0.002**3
    assert math.isclose(vol, expected, rel_tol=1e-9)
    # stored vertex normals agree with the triangle winding
    fn = m.face_normals
    vn = m.vertex_normals[m.triangles].mean(1)
    assert (np.einsum("fi,fi->f", fn, vn) > 0.9).all()


def test_box_front_face_is_printed_upright() -> None:
    m = demo_mesh("labelled_box")
    # camera on the +z side looking at the front face, model +y up in the image
    out = Renderer([m]).render(pose(np.diag([1.0, -1.0, -1.0]))[None], K, 160, 160, light=FLAT)
    face = out.rgb.numpy().astype(np.float64)
    mask = out.instance.numpy() == 0
    rows, cols = np.nonzero(mask)
    crop = face[rows.min() + 2 : rows.max() - 1, cols.min() + 2 : cols.max() - 1]
    tex = m.texture
    cell = tex[: tex.shape[0] // 2, : tex.shape[1] // 3].astype(np.float64)
    ys = np.linspace(0, cell.shape[0] - 1, crop.shape[0]).round().astype(int)
    xs = np.linspace(0, cell.shape[1] - 1, crop.shape[1]).round().astype(int)
    ref = cell[ys][:, xs]

    def blocks(a: np.ndarray) -> np.ndarray:  # 6 x 6 block means: robust to small misalignment
        h, w = a.shape[0] // 6 * 6, a.shape[1] // 6 * 6
        return a[:h, :w].reshape(6, h // 6, 6, w // 6, 3).mean((1, 3))

    def err(a: np.ndarray) -> float:
        return float(np.abs(blocks(crop) - blocks(a)).mean())

    assert err(ref) < 0.5 * min(err(ref[::-1]), err(ref[:, ::-1]), err(ref[::-1, ::-1]))


def test_label_breaks_the_can_symmetry_but_not_its_shape() -> None:
    r = Renderer([demo_mesh("labelled_can")])
    side = rot(0, math.pi / 2)  # axis horizontal in the image
    a = r.render(pose(side)[None], K, 160, 160, light=FLAT)
    b = r.render(pose(side @ rot(2, math.pi / 2))[None], K, 160, 160, light=FLAT)
    same = a.masks_full[0] & b.masks_full[0]
    assert (a.depth - b.depth).abs()[same].max() < 2e-4  # same cylinder
    diff = (a.rgb.float() - b.rgb.float()).abs().sum(-1)[same]
    assert (diff > 60).float().mean() > 0.1  # a different part of the label
    again = r.render(pose(side)[None], K, 160, 160, light=FLAT)
    assert torch.equal(again.rgb, a.rgb)


def test_bracket_has_no_proper_symmetry() -> None:
    r = Renderer([demo_mesh("bracket")])
    view = rot(0, 0.7) @ rot(1, 0.4)
    ref = r.render(pose(view)[None], K, 160, 160)
    for axis in range(3):
        for angle in (math.pi / 2, math.pi, 3 * math.pi / 2):
            other = r.render(pose(view @ rot(axis, angle))[None], K, 160, 160)
            xor = (ref.masks_full[0] ^ other.masks_full[0]).sum().item()
            assert xor > 0.1 * ref.masks_full[0].sum().item()


def test_demo_objects_models_and_symmetries() -> None:
    plain = demo_objects(num_points=128, names=("labelled_box", "labelled_can"))
    assert [m.name for m in plain] == ["labelled_box", "labelled_can"]
    assert all(not m.is_symmetric and m.points.shape == (128, 3) for m in plain)
    box, can = demo_objects(
        num_points=128, names=("labelled_box", "labelled_can"), geometric_symmetries=True
    )
    assert box.symmetries.shape[0] == 4 and can.symmetries.shape[0] == 315
    corners = torch.from_numpy(box.mesh.bounding_box_corners()).float()
    for S in box.symmetries:  # each maps the box's corners onto themselves
        moved = corners @ S[:3, :3].T + S[:3, 3]
        assert torch.cdist(moved, corners).min(1).values.max() < 1e-6
    assert math.isclose(box.diameter, math.sqrt(0.09**2 + 0.12**2 + 0.04**2), rel_tol=1e-9)
    # texture colours reach the query cloud
    assert box.colors.std(0).min() > 0.1


def test_write_demo_models(tmp_path: Path) -> None:
    paths = write_demo_models(tmp_path / "models", num_points=32)
    assert sorted(paths) == [1, 2, 3]
    info = json.loads((tmp_path / "models" / "models_info.json").read_text())
    for obj_id, name in zip((1, 2, 3), DEMO_OBJECT_NAMES):
        e = info[str(obj_id)]
        assert "symmetries_discrete" not in e and "symmetries_continuous" not in e
        m = demo_mesh(name)
        assert 50 < e["diameter"] < 200  # mm
        back = load_mesh(paths[obj_id], scale=0.001)
        assert back.num_triangles == m.num_triangles and back.has_texture == m.has_texture
        np.testing.assert_allclose(back.extent(), m.extent(), atol=1e-6)
    assert (tmp_path / "models" / "obj_000001.png").is_file()
    assert not (tmp_path / "models" / "obj_000003.png").exists()
    sym = write_demo_models(tmp_path / "sym", num_points=32, geometric_symmetries=True)
    info = json.loads((sym[1].parent / "models_info.json").read_text())
    assert len(info["1"]["symmetries_discrete"]) == 3
    assert info["2"]["symmetries_continuous"][0]["axis"] == [0.0, 0.0, 1.0]
