import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from poseflow.data.bop import (
    BOPDataset,
    BOPDataWarning,
    BOPDetectionDataset,
    BOPFormatError,
    BOPImageDataset,
    BOPInstanceDataset,
    BOPWriter,
    ContinuousSymmetry,
    Detection,
    MissingFileError,
    ModelInfo,
    TestTarget,
    collate_images,
    read_depth,
    read_detections,
    read_models_info,
    read_scene_camera,
    read_scene_gt,
    read_test_targets,
    write_depth,
    write_detections,
    write_model_ply,
    write_models_info,
    write_test_targets,
)
from poseflow.data.rle import rle_encode
from poseflow.errors import ShapeError
from poseflow.geometry.se3 import random_transform

H, W = 24, 32


def _image(g: torch.Generator, n: int):
    K = torch.tensor([[40.0, 0, 15.5], [0, 40.0, 11.5], [0, 0, 1]], dtype=torch.float64)
    rgb = torch.rand(3, H, W, generator=g)
    depth = 0.4 + 0.6 * torch.rand(H, W, generator=g, dtype=torch.float64)
    depth[0, :5] = 0.0  # missing pixels
    poses = random_transform(n, max_translation=0.5, generator=g, dtype=torch.float64)
    masks = torch.zeros(n, H, W, dtype=torch.bool)
    for i in range(n):
        masks[i, 2 + i : 12 + i, 3 + 2 * i : 15 + 2 * i] = True
    visib = masks.clone()
    visib[:, :, :5] = False
    return K, rgb, depth, poses, masks, visib


@pytest.fixture
def dataset(tmp_path: Path):
    """Two scenes with 1, 3, 2 instances in their images, written by BOPWriter."""
    g = torch.Generator().manual_seed(0)
    written = {}
    with BOPWriter(tmp_path, "test") as w:
        for scene_id, im_id, n in ((1, 0, 1), (1, 4, 3), (2, 0, 2)):
            K, rgb, depth, poses, masks, visib = _image(g, n)
            obj_ids = list(range(1, n + 1))
            w.add_image(
                scene_id, im_id, K=K, rgb=rgb, depth=depth, obj_ids=obj_ids, poses=poses,
                masks=masks, masks_visib=visib,
            )  # fmt: skip
            written[(scene_id, im_id)] = (K, rgb, depth, poses, masks, visib, obj_ids)
    return tmp_path, written


def test_round_trip_images(dataset):
    root, written = dataset
    ds = BOPImageDataset(root, "test")
    assert len(ds) == 3
    assert ds.index == [(1, 0), (1, 4), (2, 0)]
    for i, (key, (K, rgb, depth, poses, masks, visib, obj_ids)) in enumerate(written.items()):
        s = ds[i]
        assert (s["scene_id"], s["im_id"]) == key
        assert torch.allclose(s["K"].double(), K)
        # 8-bit colour quantisation, 0.1 mm depth quantisation (the writer's depth_scale)
        assert (s["rgb"] - rgb).abs().max() <= 0.5 / 255 + 1e-6
        assert (s["depth"].double() - depth).abs().max() <= 0.5e-4 + 1e-6
        assert bool((s["depth"][0, :5] == 0).all())
        assert torch.allclose(s["poses"].double(), poses, atol=1e-6)
        assert s["obj_ids"].tolist() == obj_ids
        assert torch.equal(s["masks"], masks) and torch.equal(s["masks_visib"], visib)
        expected = visib.flatten(1).sum(1) / masks.flatten(1).sum(1)
        assert torch.allclose(s["visib_fract"].double(), expected.double(), atol=1e-6)
        assert bool(s["valid"].all())


def test_file_units_are_mm(dataset):
    root, written = dataset
    poses = written[(1, 0)][3]
    raw = json.loads((root / "test" / "000001" / "scene_gt.json").read_text())
    assert np.allclose(raw["0"][0]["cam_t_m2c"], poses[0, :3, 3].numpy() * 1000)
    cam = read_scene_camera(root / "test" / "000001" / "scene_camera.json")
    assert cam[0].depth_scale == pytest.approx(0.1)


def test_image_loader_pads_instances(dataset):
    root, _ = dataset
    loader = DataLoader(BOPImageDataset(root, "test"), batch_size=3, collate_fn=collate_images)
    batch = next(iter(loader))
    assert batch["rgb"].shape == (3, 3, H, W)
    assert batch["poses"].shape == (3, 3, 4, 4)
    assert batch["masks"].shape == (3, 3, H, W)
    assert batch["instance_mask"].tolist() == [
        [True, False, False],
        [True, True, True],
        [True, True, False],
    ]
    assert batch["obj_ids"][0].tolist() == [1, -1, -1]
    assert torch.equal(batch["poses"][0, 1], torch.eye(4))
    assert not bool(batch["valid"][0, 1:].any())


def test_instance_dataset_default_collate(dataset):
    root, written = dataset
    ds = BOPInstanceDataset(root, "test")
    assert len(ds) == 6
    batch = next(iter(DataLoader(ds, batch_size=6)))
    assert batch["pose"].shape == (6, 4, 4) and batch["mask"].shape == (6, H, W)
    assert batch["valid"].all()
    assert batch["obj_id"].tolist() == [1, 1, 2, 3, 1, 2]
    assert torch.allclose(batch["pose"][3].double(), written[(1, 4)][3][2], atol=1e-6)
    only2 = BOPInstanceDataset(root, "test", obj_ids=[2], scene_ids=[1])
    assert only2.index == [(1, 4, 1)]


def test_scene_level_and_dtype(dataset):
    root, _ = dataset
    scene = BOPDataset(root, "test", dtype=torch.float64, load_rgb=False).scene(1)
    assert scene.im_ids == [0, 4] and len(scene) == 2
    s = scene[-1]
    assert s["im_id"] == 4 and s["depth"].dtype == torch.float64 and "rgb" not in s
    with pytest.raises(IndexError):
        scene[2]


def test_targets_restrict_images_and_instances(dataset):
    root, _ = dataset
    targets = [TestTarget(1, 4, 3, 1), TestTarget(2, 0, 1, 1)]
    write_test_targets(root / "test_targets_bop19.json", targets)
    assert read_test_targets(root / "test_targets_bop19.json") == targets
    assert BOPImageDataset(root, "test", targets=True).index == [(1, 4), (2, 0)]
    assert BOPInstanceDataset(root, "test", targets=True).index == [(1, 4, 2), (2, 0, 0)]


def test_min_visib_fract(dataset):
    root, _ = dataset
    all_ = BOPInstanceDataset(root, "test")
    fr = [all_[i]["visib_fract"] for i in range(len(all_))]
    assert sorted(set(np.round(fr, 4))) == [round(10 / 12, 4), 1.0]
    kept = BOPInstanceDataset(root, "test", min_visib_fract=0.9)
    assert len(kept) == sum(f >= 0.9 for f in fr) == 3


def test_models_info_round_trip(tmp_path):
    sym = np.eye(4)
    sym[:3, :3] = np.diag([-1.0, -1.0, 1.0])
    sym[:3, 3] = [0.0, 0.0, 0.012]
    info = {
        3: ModelInfo(
            diameter=0.1234,
            min_xyz=np.array([-0.05, -0.04, -0.03]),
            size_xyz=np.array([0.1, 0.08, 0.06]),
            symmetries_discrete=(sym,),
            symmetries_continuous=(ContinuousSymmetry(np.array([0, 0, 1.0]), np.zeros(3)),),
        )
    }
    p = tmp_path / "models" / "models_info.json"
    write_models_info(p, info)
    raw = json.loads(p.read_text())["3"]
    assert raw["diameter"] == pytest.approx(123.4)
    assert raw["symmetries_discrete"][0][11] == pytest.approx(12.0)  # row-major, mm
    back = read_models_info(p)[3]
    assert back.diameter == pytest.approx(0.1234)
    assert np.allclose(back.symmetries_discrete[0], sym)
    assert np.allclose(back.symmetries_continuous[0].axis, [0, 0, 1])
    assert np.allclose(back.size_xyz, [0.1, 0.08, 0.06])


def test_model_ply_in_mm(tmp_path):
    o3d = pytest.importorskip("open3d")
    v = np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.2, 0]], dtype=np.float64)
    write_model_ply(tmp_path / "obj_000001.ply", v, [[0, 1, 2]], colors=np.full((3, 3), 0.5))
    mesh = o3d.io.read_triangle_mesh(str(tmp_path / "obj_000001.ply"))
    assert np.allclose(np.asarray(mesh.vertices), v * 1000, atol=1e-3)
    assert np.asarray(mesh.triangles).tolist() == [[0, 1, 2]]
    assert np.allclose(np.asarray(mesh.vertex_colors), 128 / 255, atol=1e-6)


def _detections(written):
    dets = []
    for (scene_id, im_id), (*_, _masks, visib, obj_ids) in written.items():
        for i, o in enumerate(obj_ids):
            rle = rle_encode(visib[i], compressed=bool(i % 2))
            dets.append(Detection(scene_id, im_id, o, 0.9 - 0.1 * i, (3.0, 2.0, 12.0, 10.0), rle))
    return dets


def test_detections_round_trip_and_dataset(dataset):
    root, written = dataset
    dets = _detections(written)
    path = root / "dets.json"
    write_detections(path, dets)
    back = read_detections(path)
    assert [(d.scene_id, d.im_id, d.obj_id) for d in back] == [
        (d.scene_id, d.im_id, d.obj_id) for d in dets
    ]
    ds = BOPDetectionDataset(root, "test", path, score_threshold=0.75)
    assert len(ds) == 5  # the third instance of (1, 4) scores 0.7
    for item in ds:
        vis = written[(item["scene_id"], item["im_id"])][5]
        assert torch.equal(item["mask"], vis[item["obj_id"] - 1])
        assert item["valid"]
    write_test_targets(root / "test_targets_bop19.json", [TestTarget(1, 4, 2, 1)])
    only = BOPDetectionDataset(root, "test", path, targets=True)
    assert [(d.scene_id, d.im_id, d.obj_id) for d in only.detections] == [(1, 4, 2)]


def test_read_detections_list_rle_from_json(tmp_path):
    entry = {
        "scene_id": 1,
        "image_id": 0,
        "category_id": 5,
        "score": 0.5,
        "bbox": [0, 0, 2, 2],
        "segmentation": {"size": [2, 3], "counts": [1, 2, 3]},
        "time": 0.1,
    }
    (tmp_path / "d.json").write_text(json.dumps([entry]))
    (d,) = read_detections(tmp_path / "d.json")
    assert d.mask().int().tolist() == [[0, 1, 0], [1, 0, 0]]
    assert d.obj_id == 5 and d.im_id == 0


# ---------------------------------------------------------------------------- bad input


def test_missing_split_and_scene_camera(dataset):
    root, _ = dataset
    with pytest.raises(MissingFileError, match="val"):
        BOPImageDataset(root, "val")
    (root / "test" / "000002" / "scene_camera.json").unlink()
    with pytest.raises(MissingFileError, match=r"000002.*scene_camera\.json"):
        BOPImageDataset(root, "test")


def test_missing_key_names_scene_and_image(dataset):
    root, _ = dataset
    p = root / "test" / "000001" / "scene_camera.json"
    raw = json.loads(p.read_text())
    del raw["4"]["cam_K"]
    p.write_text(json.dumps(raw))
    with pytest.raises(BOPFormatError, match=r"scene 000001, image 4\).*cam_K"):
        BOPImageDataset(root, "test")
    p = root / "test" / "000002" / "scene_gt.json"
    raw = json.loads(p.read_text())
    del raw["0"][1]["obj_id"]
    p.write_text(json.dumps(raw))
    with pytest.raises(BOPFormatError, match=r"image 0, instance 1.*obj_id"):
        read_scene_gt(p)


def test_missing_files_name_image(dataset):
    root, _ = dataset
    (root / "test" / "000001" / "mask" / "000004_000002.png").unlink()
    (root / "test" / "000001" / "depth" / "000000.png").unlink()
    ds = BOPImageDataset(root, "test")
    with pytest.raises(MissingFileError, match="scene 1 image 0"):
        ds[0]
    with pytest.raises(MissingFileError, match="scene 1 image 4 instance 2"):
        ds[1]


def test_depth_in_metres_is_detected(tmp_path):
    d = np.full((4, 4), 0.8)
    write_depth(tmp_path / "mm.png", d, depth_scale=1.0)
    assert float(read_depth(tmp_path / "mm.png", 1.0)[0, 0]) == pytest.approx(0.8)
    # a depth map holding metres (values 0..2) while depth_scale declares mm per unit
    from PIL import Image

    Image.fromarray(np.full((4, 4), 1, dtype=np.uint16)).save(tmp_path / "m.png")
    with pytest.raises(BOPFormatError, match="metres"):
        read_depth(tmp_path / "m.png", 1.0)
    assert float(read_depth(tmp_path / "m.png", 1.0, check_units=False)[0, 0]) == pytest.approx(
        0.001
    )
    Image.fromarray(np.zeros((4, 4, 3), dtype=np.uint8)).save(tmp_path / "rgb.png")
    with pytest.raises(BOPFormatError, match="16-bit"):
        read_depth(tmp_path / "rgb.png")


def test_depth_too_deep_for_16_bits(tmp_path):
    with pytest.raises(ValueError, match="16 bits"):
        write_depth(tmp_path / "d.png", np.full((2, 2), 10.0), depth_scale=0.1)


def test_invalid_instances_are_flagged_not_raised(tmp_path):
    K = torch.eye(3)
    depth = torch.full((H, W), 0.5)
    depth[:, W // 2 :] = 0.0  # right half missing
    depth[0, 0] = float("nan")  # written as missing
    masks = torch.zeros(3, H, W, dtype=torch.bool)
    masks[0, 5:15, 2:12] = True  # fine
    masks[1, 5:15, W // 2 + 2 :] = True  # only missing depth
    # masks[2] empty
    with BOPWriter(tmp_path, "test") as w:
        w.add_image(
            1, 0, K=K, depth=depth, obj_ids=[1, 2, 3], poses=torch.eye(4).repeat(3, 1, 1),
            masks=masks, masks_visib=masks,
        )  # fmt: skip
    ds = BOPInstanceDataset(tmp_path, "test", load_rgb=False)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        items = [ds[i] for i in range(3)]
    assert [it["valid"] for it in items] == [True, False, False]
    assert items[0]["num_valid_pixels"] == 100
    assert items[1]["num_valid_pixels"] == 0
    msgs = [str(r.message) for r in rec if issubclass(r.category, BOPDataWarning)]
    assert any("scene 1 image 0 instance 1" in m and "valid" in m for m in msgs)
    assert any("scene 1 image 0 instance 2" in m and "empty" in m for m in msgs)
    info = json.loads((tmp_path / "test" / "000001" / "scene_gt_info.json").read_text())["0"]
    assert info[2]["visib_fract"] == 0.0 and info[2]["bbox_obj"] == [-1, -1, -1, -1]
    assert info[1]["px_count_valid"] == 0 and info[0]["px_count_valid"] == 100


def test_nan_depth_in_mask_flags_instance(tmp_path):
    """A depth tensor handed to the validity check with NaN counts those pixels as invalid."""
    depth = torch.full((H, W), float("nan"))
    depth[:2, :2] = 1.0
    mask = torch.ones(H, W, dtype=torch.bool)
    with BOPWriter(tmp_path, "test") as w:
        w.add_image(1, 0, K=torch.eye(3), depth=depth, obj_ids=[1], poses=torch.eye(4)[None],
                    masks=mask[None], masks_visib=mask[None])  # fmt: skip
    with pytest.warns(BOPDataWarning, match="only 4 pixels"):
        item = BOPInstanceDataset(tmp_path, "test", load_rgb=False)[0]
    assert not item["valid"]


def test_bad_detections(dataset):
    root, written = dataset
    good = _detections(written)[:1]
    with pytest.raises(BOPFormatError, match="scene 7 image 0"):
        BOPDetectionDataset(
            root, "test", [Detection(7, 0, 1, 1.0, (0, 0, 1, 1), good[0].segmentation)]
        )
    with pytest.raises(BOPFormatError, match="scene 1 image 99"):
        BOPDetectionDataset(
            root, "test", [Detection(1, 99, 1, 1.0, (0, 0, 1, 1), good[0].segmentation)]
        )
    wrong_size = Detection(1, 0, 1, 1.0, (0, 0, 1, 1), rle_encode(torch.ones(5, 5)))
    empty = Detection(1, 0, 1, 0.5, (0, 0, 1, 1), rle_encode(torch.zeros(H, W)))
    broken = Detection(1, 0, 1, 0.4, (0, 0, 1, 1), {"size": [H, W], "counts": [3]})
    ds = BOPDetectionDataset(root, "test", [wrong_size, empty, broken])
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        items = [ds[i] for i in range(3)]
    assert not any(it["valid"] for it in items)
    assert all(it["mask"].shape == (H, W) for it in items)
    assert len([r for r in rec if issubclass(r.category, BOPDataWarning)]) >= 3
    (root / "bad.json").write_text(json.dumps([{"scene_id": 1, "image_id": 0, "score": 1.0}]))
    with pytest.raises(BOPFormatError, match=r"entry 0, scene 1, image 0.*category_id"):
        read_detections(root / "bad.json")


def test_jpg_and_gray_images(tmp_path):
    from PIL import Image

    ramp = torch.linspace(0, 1, W).expand(H, W)
    rgb = torch.stack([ramp, ramp.flip(1), torch.full((H, W), 0.3)])  # smooth: JPEG-friendly
    with BOPWriter(tmp_path, "train_pbr", image_ext=".jpg") as w:
        w.add_image(0, 0, K=torch.eye(3), rgb=rgb, depth=torch.full((H, W), 0.7))
    s = BOPDataset(tmp_path, "train_pbr", load_masks=False).scene(0)
    assert s.rgb_path(0).suffix == ".jpg"
    assert (s[0]["rgb"] - rgb).abs().mean() < 0.02  # lossy
    gray = (np.arange(H * W).reshape(H, W) % 256).astype(np.uint8)
    (s.path / "rgb" / "000000.jpg").unlink()
    (s.path / "gray").mkdir()
    Image.fromarray(gray).save(s.path / "gray" / "000000.png")
    img = s[0]["rgb"]
    assert img.shape == (3, H, W) and torch.equal(img[0], img[2])
    assert torch.allclose(img[1] * 255, torch.from_numpy(gray).float())


def test_loader_with_worker_processes(dataset):
    root, _ = dataset
    loader = DataLoader(BOPInstanceDataset(root, "test"), batch_size=2, num_workers=2)
    assert sum(len(b["obj_id"]) for b in loader) == 6


@pytest.mark.parametrize(
    ("key", "value"), [("score", "high"), ("score", None), ("category_id", 1.5), ("time", "x")]
)
def test_detection_numbers_must_be_numbers(tmp_path, key, value):
    entry = {"scene_id": 1, "image_id": 0, "category_id": 1, "score": 0.9, "time": 0.1}
    entry[key] = value
    (tmp_path / "d.json").write_text(json.dumps([entry]))
    with pytest.raises(BOPFormatError, match=rf"entry 0, scene 1, image 0\): '{key}' must be"):
        read_detections(tmp_path / "d.json")


@pytest.mark.parametrize("bad", ["transposed", "zero"])
def test_a_bad_cam_k_names_the_file_scene_and_image(dataset, bad):
    root, _ = dataset
    p = root / "test" / "000001" / "scene_camera.json"
    raw = json.loads(p.read_text())
    K = np.asarray(raw["4"]["cam_K"]).reshape(3, 3)
    raw["4"]["cam_K"] = (K.T if bad == "transposed" else 0 * K).reshape(-1).tolist()
    p.write_text(json.dumps(raw))
    with pytest.raises(BOPFormatError, match=r"scene_camera\.json \(scene 000001, image 4\)"):
        read_scene_camera(p)


def test_files_of_different_sizes_are_named(dataset):
    from PIL import Image

    root, _ = dataset
    scene = BOPDataset(root, "test").scene(1)
    mask = scene.mask_path(4, 1, visible=True)
    Image.fromarray(np.zeros((10, 12), np.uint8)).save(mask)
    with pytest.raises(ShapeError, match="scene 1 image 4") as err:
        scene.image_sample(4)
    assert f"{mask} is 12x10 but {scene.depth_path(4)} is {W}x{H}" in str(err.value)
    Image.fromarray(np.zeros((10, 12, 3), np.uint8)).save(scene.rgb_path(0))
    with pytest.raises(ShapeError, match=r"rgb/000000\.png is 12x10"):
        scene.image_sample(0)
