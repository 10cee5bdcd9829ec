from __future__ import annotations

import sys

import numpy as np
import pytest
import torch

from poseflow.errors import MissingDependencyError, ShapeError, ValueRangeError
from poseflow.eval.scene import (
    GLTF_FROM_CAMERA,
    backproject_rgbd,
    build_scene,
    export_scene,
    place_mesh,
    write_recording,
)
from poseflow.geometry import random_rotation
from poseflow.render import TexturedMesh

K = np.array([[60.0, 0.0, 16.0], [0.0, 60.0, 12.0], [0.0, 0.0, 1.0]])
H, W = 24, 32


def _box(size: float = 0.06, seed: int = 0) -> TexturedMesh:
    """A closed box in metres centred at the origin, a random colour per vertex."""
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    faces = np.array(
        [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
         [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    )  # fmt: skip
    colors = np.random.default_rng(seed).integers(0, 256, (8, 3)).astype(np.uint8)
    return TexturedMesh((corners - 0.5) * size, faces, vertex_colors=colors)


def _pose(seed: int, z: float = 0.5) -> np.ndarray:
    g = torch.Generator().manual_seed(seed)
    T = np.eye(4)
    T[:3, :3] = random_rotation(1, generator=g, dtype=torch.float64)[0].numpy()
    T[:3, 3] = [0.01 * seed, -0.01, z]
    return T


def _frame() -> tuple[np.ndarray, np.ndarray]:
    rgb = np.random.default_rng(1).integers(0, 256, (H, W, 3)).astype(np.uint8)
    depth = np.full((H, W), 0.6, np.float32)
    depth[0, :] = 0.0  # missing
    return rgb, depth


@pytest.fixture(scope="module")
def view():
    rgb, depth = _frame()
    meshes = {1: _box(seed=1), 5: _box(0.04, seed=5)}
    est = np.stack([_pose(1), _pose(2), _pose(3, z=-0.4)])
    return build_scene(
        rgb, depth, K, meshes, est, [1, 5, 1],
        scores=[0.9, 0.5, 0.0], valid=[True, True, False],
        gt_poses=np.stack([_pose(4), _pose(5)]), gt_obj_ids=[1, 5],
        method="FunFlow6D", name="scene 1 image 0", stride=1,
    )  # fmt: skip


def test_place_mesh_transforms_vertices_and_keeps_colours():
    mesh = _box(seed=3)
    T = _pose(7)
    placed = place_mesh(mesh, torch.as_tensor(T), obj_id=2, score=0.25, valid=False)
    np.testing.assert_allclose(placed.vertices, mesh.vertices @ T[:3, :3].T + T[:3, 3])
    np.testing.assert_array_equal(placed.triangles, mesh.triangles)
    np.testing.assert_array_equal(placed.colors, np.round(mesh.vertex_colors * 255))
    assert placed.label == "obj 2: score 0.250, INVALID"
    solid = place_mesh(mesh, T, color=(1, 2, 3))
    assert (solid.colors == [1, 2, 3]).all() and solid.score is None
    with pytest.raises(ShapeError):
        place_mesh(mesh, np.eye(3))
    bad = T.copy()
    bad[0, 3] = np.nan
    with pytest.raises(ValueRangeError):
        place_mesh(mesh, bad)


def test_place_mesh_samples_the_texture_at_each_vertex():
    tex = np.zeros((4, 4, 3), np.uint8)
    tex[:2] = (255, 0, 0)  # top half red (v > 0.5), bottom half blue
    tex[2:] = (0, 0, 255)
    uvs = np.array([[[0.5, 0.9], [0.5, 0.1], [0.6, 0.9]]])
    mesh = TexturedMesh(np.eye(3), np.array([[0, 1, 2]]), triangle_uvs=uvs, texture=tex)
    colors = place_mesh(mesh, np.eye(4)).colors
    assert colors.tolist() == [[255, 0, 0], [0, 0, 255], [255, 0, 0]]


def test_backproject_rgbd_lifts_valid_pixels_with_their_colours():
    rgb, depth = _frame()
    cloud = backproject_rgbd(rgb, depth, K)
    assert len(cloud) == (H - 1) * W  # row 0 has no depth
    u, v = cloud.pixels[:, 0], cloud.pixels[:, 1]
    np.testing.assert_array_equal(cloud.colors, rgb[v, u])
    np.testing.assert_allclose(cloud.points[:, 2], 0.6, rtol=1e-6)
    np.testing.assert_allclose(cloud.points[:, 0], (u - K[0, 2]) / K[0, 0] * 0.6, rtol=1e-5)
    np.testing.assert_allclose(cloud.points[:, 1], (v - K[1, 2]) / K[1, 1] * 0.6, rtol=1e-5)
    # channels-first float image, every 2nd pixel, a cap on the count
    chw = torch.as_tensor(rgb).permute(2, 0, 1).float() / 255
    strided = backproject_rgbd(chw, torch.as_tensor(depth), torch.as_tensor(K), stride=2)
    assert len(strided) == (H // 2 - 1) * (W // 2)
    assert ((strided.pixels % 2) == 0).all()
    np.testing.assert_array_equal(strided.colors, rgb[strided.pixels[:, 1], strided.pixels[:, 0]])
    assert len(backproject_rgbd(rgb, depth, K, max_points=10)) == 10
    with pytest.raises(ShapeError):
        backproject_rgbd(rgb, depth[:-1], K)
    with pytest.raises(ValueRangeError):
        backproject_rgbd(rgb, depth, K, stride=0)


def test_build_scene_holds_estimates_and_ground_truth(view):
    assert [m.name for m in view.estimates] == [
        "est_0_obj_000001",
        "est_1_obj_000005",
        "est_2_obj_000001",
    ]
    assert [m.valid for m in view.estimates] == [True, True, False]
    assert [m.score for m in view.estimates] == [0.9, 0.5, 0.0]
    assert [m.name for m in view.ground_truth] == ["gt_0_obj_000001", "gt_1_obj_000005"]
    assert all(m.score is None and (m.colors == [50, 220, 50]).all() for m in view.ground_truth)
    assert view.size == (W, H) and len(view.cloud) == (H - 1) * W
    rgb, depth = _frame()
    with pytest.raises(ValueRangeError, match="no mesh"):
        build_scene(rgb, depth, K, {1: _box()}, _pose(1)[None], [2])
    with pytest.raises(ShapeError):
        build_scene(rgb, depth, K, {1: _box()}, _pose(1)[None], [1], scores=[0.1, 0.2])


def test_glb_holds_every_mesh_under_its_pose_and_the_cloud(view, tmp_path):
    trimesh = pytest.importorskip("trimesh")
    path = tmp_path / "scene.glb"
    assert export_scene(view, path) == [path]
    loaded = trimesh.load(path, process=False)
    names = {m.name for m in view.estimates + view.ground_truth} | {"observed"}
    assert set(loaded.graph.nodes_geometry) == names
    back = np.linalg.inv(GLTF_FROM_CAMERA)  # the nodes turn the camera frame to glTF's
    for m in view.estimates + view.ground_truth:
        transform, geom = loaded.graph[m.name]
        np.testing.assert_allclose(transform, GLTF_FROM_CAMERA)
        mesh = loaded.geometry[geom]
        world = trimesh.transform_points(mesh.vertices, back @ transform)
        np.testing.assert_allclose(world, m.vertices, atol=1e-6)
        np.testing.assert_array_equal(mesh.faces, m.triangles)
        np.testing.assert_array_equal(mesh.visual.vertex_colors[:, :3], m.colors)
    cloud = loaded.geometry[loaded.graph["observed"][1]]
    np.testing.assert_allclose(cloud.vertices, view.cloud.points, atol=1e-6)
    # the estimate's vertices are the mesh under the pose
    first = view.estimates[0]
    box = _box(seed=1)
    T = first.pose
    mesh = loaded.geometry[loaded.graph[first.name][1]]
    np.testing.assert_allclose(mesh.vertices, box.vertices @ T[:3, :3].T + T[:3, 3], atol=1e-6)


def test_ply_export_writes_the_meshes_and_the_cloud(view, tmp_path):
    trimesh = pytest.importorskip("trimesh")
    written = export_scene(view, tmp_path / "scene.ply", ground_truth=False)
    assert [p.name for p in written] == ["scene.ply", "scene_cloud.ply"]
    meshes = trimesh.load(written[0], process=False)
    expected = np.concatenate([m.vertices for m in view.estimates])
    np.testing.assert_allclose(meshes.vertices, expected, atol=1e-6)
    cloud = trimesh.load(written[1], process=False)
    assert len(cloud.vertices) == len(view.cloud)
    with pytest.raises(ValueRangeError):
        export_scene(view, tmp_path / "scene.obj")


def _entities(path):
    from rerun.chunk import RrdReader

    found = {}
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()
        found.setdefault(chunk.entity_path, {}).update(
            {name: batch.column(name).to_pylist() for name in batch.schema.names}
        )
    return found


def test_recording_read_back_holds_the_entities(view, tmp_path):
    pytest.importorskip("rerun")
    path = write_recording(view, tmp_path / "scene.rrd")
    found = _entities(path)
    for entity in ("/world", "/world/camera", "/world/camera/image", "/world/observed",
                   "/description"):  # fmt: skip
        assert entity in found, entity
    pinhole = np.array(found["/world/camera"]["Pinhole:image_from_camera"][0])
    np.testing.assert_allclose(pinhole.reshape(3, 3).T, K)  # stored column-major
    assert found["/world/camera"]["Pinhole:resolution"][0] == [[W, H]]
    points = np.array(found["/world/observed"]["Points3D:positions"][0])
    np.testing.assert_allclose(points, view.cloud.points)
    for m in view.estimates:
        entity = found[f"/world/estimates/{m.name}"]
        np.testing.assert_allclose(
            np.array(entity["Mesh3D:vertex_positions"][0]), m.vertices, atol=1e-6
        )
        assert entity["score"][0] == [pytest.approx(m.score)]
        assert entity["valid"][0] == [m.valid]
        assert entity["obj_id"][0] == [m.obj_id]
        label = found[f"/world/estimates/{m.name}/label"]["Points3D:labels"][0]
        assert label == [m.label]
    for m in view.ground_truth:
        assert f"/world/ground_truth/{m.name}" in found
    assert "FunFlow6D" in found["/description"]["TextDocument:text"][0][0]


def test_missing_viewers_name_the_extra(view, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "rerun", None)
    monkeypatch.setitem(sys.modules, "trimesh", None)
    with pytest.raises(MissingDependencyError, match=r"poseflow\[viz\]"):
        write_recording(view, tmp_path / "x.rrd")
    with pytest.raises(MissingDependencyError, match=r"poseflow\[viz\]"):
        export_scene(view, tmp_path / "x.glb")
