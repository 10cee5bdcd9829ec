import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from poseflow.data.bop import (
    BOPDataset,
    BOPImageDataset,
    BOPInstanceDataset,
    read_mask,
    read_models_info,
    read_scene_gt_info,
    read_test_targets,
)
from poseflow.data.objects import ObjectModel, load_mesh
from poseflow.data.synthetic import (
    DepthNoise,
    _box_mesh,
    _cylinder_mesh,
    generate_dataset,
    procedural_texture,
)
from poseflow.errors import ValueRangeError
from poseflow.geometry.pointcloud import backproject_depth
from poseflow.geometry.se3 import inverse_transform, transform_points
from poseflow.render.raycast import Renderer

W, H = 160, 120


def _objects():
    o3d = pytest.importorskip("open3d")
    box = _box_mesh(np.array([0.09, 0.06, 0.05]), procedural_texture(1, 64))
    can = _cylinder_mesh(0.03, 0.1, procedural_texture(2, 64))
    torus = o3d.geometry.TriangleMesh.create_torus(0.04, 0.015, 30, 12)
    return [
        ObjectModel.from_mesh(box, num_points=64),
        ObjectModel.from_mesh(
            can, num_points=64, symmetries_continuous=[(np.array([0, 0, 1.0]), np.zeros(3))]
        ),
        ObjectModel.from_mesh(torus, num_points=64),
    ]


@pytest.fixture(scope="module")
def objects():
    return _objects()


def _generate(root, objects, **kw):
    args = dict(
        num_train_images=2,
        num_test_images=2,
        objects_per_image=(3, 4),
        width=W,
        height=H,
        images_per_scene=1,
        progress=False,
    )
    args.update(kw)
    return generate_dataset(root, objects, **args)


@pytest.fixture(scope="module")
def noisy(tmp_path_factory, objects):
    return _generate(tmp_path_factory.mktemp("noisy"), objects, seed=3)


@pytest.fixture(scope="module")
def clean(tmp_path_factory, objects):
    return _generate(tmp_path_factory.mktemp("clean"), objects, seed=3, depth_noise=None)


def test_layout_and_loading(noisy, objects):
    root = Path(noisy)
    for name in ("camera.json", "test_targets_bop19.json", "models/models_info.json"):
        assert (root / name).is_file()
    for split in ("train", "test"):
        ds = BOPImageDataset(root, split)
        assert len(ds) == 2
        s = ds[1]
        assert s["rgb"].shape == (3, H, W) and s["depth"].shape == (H, W)
        assert 3 <= len(s["obj_ids"]) <= 4 and s["masks"].shape[1:] == (H, W)
        assert set(s["obj_ids"].tolist()) <= {1, 2, 3}
        assert (s["depth"] > 0).float().mean() > 0.5  # the plane fills most of the view
    cam = json.loads((root / "camera.json").read_text())
    assert (cam["width"], cam["height"]) == (W, H)
    assert cam["fx"] == pytest.approx(572.4 * W / 640)


def test_models_round_trip(noisy, objects):
    root = Path(noisy)
    infos = read_models_info(root / "models" / "models_info.json")
    assert sorted(infos) == [1, 2, 3]
    for obj_id, obj in enumerate(objects, 1):
        assert infos[obj_id].diameter == pytest.approx(obj.diameter, rel=1e-6)
        mesh = load_mesh(BOPDataset(root, "test").model_path(obj_id), scale=0.001)
        assert np.allclose(mesh.vertices.min(0), obj.mesh.vertices.min(0), atol=1e-6)
        assert np.allclose(mesh.vertices.max(0), obj.mesh.vertices.max(0), atol=1e-6)
        assert mesh.has_texture == obj.mesh.has_texture
    assert len(infos[2].symmetries_continuous) == 1 and not infos[1].symmetries_continuous
    assert (root / "models_eval" / "obj_000002.ply").is_file()


def test_visib_fract_matches_rendered_masks(clean, objects):
    """gt_info agrees with the mask PNGs, and mask/ is each object rendered alone at its GT pose."""
    root = Path(clean)
    renderer = Renderer(objects)
    ds = BOPDataset(root, "test")
    checked = 0
    for scene_id in ds.scene_ids:
        scene = ds.scene(scene_id)
        infos = read_scene_gt_info(scene.path / "scene_gt_info.json")
        for im_id in scene.im_ids:
            K = scene.camera[im_id].K
            for gt_idx, gt in enumerate(scene.gt_of(im_id)):
                full = read_mask(scene.mask_path(im_id, gt_idx, visible=False))
                vis = read_mask(scene.mask_path(im_id, gt_idx, visible=True))
                info = infos[im_id][gt_idx]
                assert info.px_count_all == int(full.sum())
                assert info.px_count_visib == int(vis.sum())
                assert bool((vis <= full).all())
                expected = int(vis.sum()) / max(int(full.sum()), 1)
                assert info.visib_fract == pytest.approx(expected)
                alone = renderer.render(gt.pose[None], K, W, H, object_ids=[gt.obj_id - 1])
                differ = int((alone.masks_full[0] != full).sum())
                assert differ <= 0.01 * max(int(full.sum()), 1) + 2  # pose written as floats
                checked += 1
    assert checked >= 6


def test_some_occlusion_is_generated(tmp_path, objects):
    root = _generate(
        tmp_path, objects, num_train_images=0, num_test_images=6, objects_per_image=5,
        clutter=0.8, seed=1,
    )  # fmt: skip
    fr = [i["visib_fract"] for i in BOPInstanceDataset(root, "test", load_rgb=False)]
    assert min(fr) < 0.9


def _surface_distance(objects, sample, cloud):
    import open3d as o3d

    pts = transform_points(inverse_transform(sample["pose"].double()), cloud.double())
    mesh = objects[sample["obj_id"] - 1].mesh
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(mesh.vertices.astype(np.float32)),
        o3d.core.Tensor(mesh.triangles.astype(np.uint32)),
    )
    return scene.compute_distance(o3d.core.Tensor(pts.numpy().astype(np.float32))).numpy()


@pytest.mark.parametrize("which", ["clean", "noisy"])
def test_lifted_targets_lie_on_the_model(which, request, objects):
    root = request.getfixturevalue(which)
    ds = BOPInstanceDataset(root, "test", min_visib_fract=0.2)
    assert len(ds) >= 3
    for i in range(len(ds)):
        s = ds[i]
        assert s["valid"]
        cloud = backproject_depth(s["depth"][None], s["K"].double(), s["mask"][None])
        d = _surface_distance(objects, s, cloud.points[0][cloud.mask[0]])
        z = float(s["pose"][2, 3])
        if which == "clean":
            assert d.max() < 2e-4  # 0.1 mm depth quantisation and float32
        else:
            sigma = DepthNoise().sigma(np.array(z), np.array(0.0))
            assert np.median(d) < 2 * sigma
            assert np.quantile(d, 0.9) < 5 * sigma + 1e-3


def test_targets_count_visible_instances(noisy):
    root = Path(noisy)
    targets = read_test_targets(root / "test_targets_bop19.json")
    ds = BOPDataset(root, "test")
    expected = {}
    for scene_id in ds.scene_ids:
        scene = ds.scene(scene_id)
        for im_id in scene.im_ids:
            for g, info in zip(scene.gt_of(im_id), scene.gt_info[im_id]):
                if info.visib_fract >= 0.1:
                    key = (scene_id, im_id, g.obj_id)
                    expected[key] = expected.get(key, 0) + 1
    assert {(t.scene_id, t.im_id, t.obj_id): t.inst_count for t in targets} == expected
    assert len(targets) > 0


def test_deterministic(tmp_path, objects):
    kw = dict(num_train_images=1, num_test_images=1, objects_per_image=2, width=48, height=40)
    a = _generate(tmp_path / "a", objects, seed=7, **kw)
    b = _generate(tmp_path / "b", objects, seed=7, **kw)
    c = _generate(tmp_path / "c", objects, seed=8, **kw)
    rel = Path("test/000000")
    for name in ("scene_gt.json", "depth/000000.png", "rgb/000000.png"):
        assert (a / rel / name).read_bytes() == (b / rel / name).read_bytes()
    assert (a / rel / "scene_gt.json").read_bytes() != (c / rel / "scene_gt.json").read_bytes()


def test_images_rendered_in_workers_are_the_same_files(tmp_path, objects):
    kw = dict(num_train_images=2, num_test_images=3, images_per_scene=2, width=48, height=40)
    one = _generate(tmp_path / "one", objects, seed=5, **kw)
    two = _generate(tmp_path / "two", objects, seed=5, workers=2, **kw)
    files = sorted(p.relative_to(one) for p in one.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(two) for p in two.rglob("*") if p.is_file())
    assert len([f for f in files if f.parent.name == "rgb"]) == 5
    for f in files:
        assert (one / f).read_bytes() == (two / f).read_bytes(), f


def test_default_demo_objects(tmp_path):
    pytest.importorskip("poseflow.data.demo_objects")
    root = generate_dataset(
        tmp_path, num_train_images=0, num_test_images=1, objects_per_image=2, width=64,
        height=48, progress=False,
    )  # fmt: skip
    assert len(BOPImageDataset(root, "test", load_masks=False)[0]["obj_ids"]) == 2
    assert len(read_models_info(root / "models" / "models_info.json")) >= 3


@pytest.mark.parametrize(
    "kw",
    [
        {"num_train_images": -1},
        {"objects_per_image": 0},
        {"objects_per_image": (3, 2)},
        {"width": 4},
        {"clutter": 0.0},
        {"camera_distance": (0.0, 1.0)},
    ],
)
def test_bad_arguments(tmp_path, objects, kw):
    with pytest.raises(ValueRangeError):
        _generate(tmp_path, objects, **kw)


def test_no_objects(tmp_path):
    with pytest.raises(ValueRangeError):
        _generate(tmp_path, [])
    with pytest.raises(ValueRangeError, match=r"no \.ply"):
        _generate(tmp_path, tmp_path)


def test_objects_from_folder(tmp_path, objects):
    from poseflow.data.objects import write_bop_model

    for i, o in enumerate(objects[:2]):
        write_bop_model(tmp_path / "meshes" / f"m{i}.ply", o.mesh)  # in mm
    root = _generate(
        tmp_path / "out", tmp_path / "meshes", mesh_scale=0.001, num_train_images=0,
        num_test_images=1, objects_per_image=2, width=48, height=40,
    )  # fmt: skip
    info = read_models_info(root / "models" / "models_info.json")
    assert info[1].diameter == pytest.approx(objects[0].diameter, rel=1e-3)


# ----------------------------------------------------------------------------- depth noise


def _plane(z: float, n: int = 120):
    depth = torch.full((n, n), z)
    normals = torch.zeros(n, n, 3)
    normals[..., 2] = -1.0
    K = torch.tensor([[500.0, 0, (n - 1) / 2], [0, 500.0, (n - 1) / 2], [0, 0, 1]])
    return depth, normals, K


@pytest.mark.parametrize("z", [0.5, 1.2])
def test_noise_std_follows_the_model(z):
    noise = DepthNoise(random_dropout=0.0)
    depth, normals, K = _plane(z)
    out = noise.apply(depth, normals, K, rng=0)
    inner = out[2:-2, 2:-2]  # away from the image border
    assert bool((inner > 0).all())
    # rays are within ~7 degrees of the normal here, so the angle term is negligible
    expected = float(noise.sigma(np.array(z), np.array(0.0)))
    assert float((inner - z).std()) == pytest.approx(expected, rel=0.08)
    assert abs(float((inner - z).mean())) < 3 * expected / math.sqrt(inner.numel())


def test_grazing_angles_and_edges_are_dropped():
    noise = DepthNoise(sigma_base=0.0, sigma_quadratic=0.0, sigma_angle=0.0, random_dropout=0.0,
                       edge_dropout=1.0, edge_width=2)  # fmt: skip
    depth, normals, K = _plane(1.0, 60)
    depth[:, 30:] = 1.2  # a 20 cm step between columns 29 and 30
    depth[:10] = 0.0  # background above row 10
    out = noise.apply(depth, normals, K, rng=0)
    assert bool((out[:, 28:32] == 0).all())  # 2-pixel band on both sides of the step
    assert bool((out[10:12] == 0).all())  # band along the background
    assert bool((out[20:, :27] == 1.0).all()) and bool((out[20:, 33:] == 1.2).all())
    grazing = normals.clone()
    grazing[..., 2] = 0.0
    grazing[..., 0] = 1.0  # surface seen edge-on
    assert bool((noise.apply(depth, grazing, K, rng=0) == 0).all())


def test_noise_is_seeded_and_validated():
    depth, normals, K = _plane(0.8, 20)
    a = DepthNoise().apply(depth, normals, K, rng=3)
    assert torch.equal(a, DepthNoise().apply(depth, normals, K, rng=3))
    assert not torch.equal(a, DepthNoise().apply(depth, normals, K, rng=4))
    with pytest.raises(ValueRangeError):
        DepthNoise(edge_dropout=1.5)
    with pytest.raises(ValueRangeError):
        DepthNoise(grazing_start_deg=80, grazing_end_deg=70)


def test_procedural_textures_vary():
    texs = [procedural_texture(s, 32) for s in range(8)]
    assert all(t.shape == (32, 32, 3) and t.dtype == np.uint8 for t in texs)
    assert len({t.tobytes() for t in texs}) == 8


def test_objects_from_a_bop_models_folder(noisy, tmp_path):
    """Pointing the generator at a BOP models/ folder keeps the ids and the symmetries."""
    models = Path(noisy) / "models"
    root = _generate(
        tmp_path, models, mesh_scale=0.001, num_train_images=0, num_test_images=1,
        objects_per_image=3, width=48, height=40,
    )  # fmt: skip
    info = read_models_info(root / "models" / "models_info.json")
    before = read_models_info(models / "models_info.json")
    assert sorted(info) == [1, 2, 3]
    assert len(info[2].symmetries_continuous) == 1
    assert info[3].diameter == pytest.approx(before[3].diameter)


def test_meshes_in_millimetres_without_mesh_scale_are_refused(tmp_path, objects):
    from poseflow.data.objects import write_bop_model
    from poseflow.errors import UnitsError

    write_bop_model(tmp_path / "meshes" / "m0.ply", objects[0].mesh)  # in mm
    with pytest.raises(UnitsError, match=r"m0\.ply has a diameter of .* set --mesh-scale 0\.001"):
        _generate(tmp_path / "out", tmp_path / "meshes", num_train_images=0, num_test_images=1)
    assert not (tmp_path / "out").exists()  # refused before anything is written
    huge = objects[0].mesh.scaled(1000.0)  # a mesh in memory, in mm
    with pytest.raises(UnitsError, match="scale it to metres"):
        _generate(tmp_path / "out", [huge], num_train_images=0, num_test_images=1)


def test_a_non_empty_folder_is_refused_unless_overwrite(tmp_path, objects):
    from poseflow.errors import OutputExistsError

    kw = dict(num_train_images=0, num_test_images=1, objects_per_image=1, width=48, height=40)
    root = _generate(tmp_path / "ds", objects, **kw)
    before = sorted(p.relative_to(root) for p in root.rglob("*"))
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    for folder in (root, tmp_path / "other"):
        with pytest.raises(OutputExistsError, match=r"not empty.*overwrite=True"):
            _generate(folder, objects, **kw)
    assert sorted(p.relative_to(root) for p in root.rglob("*")) == before  # nothing written
    assert _generate(root, objects, seed=5, overwrite=True, **kw) == root
