"""One RGB-D frame from plain files: ``poseflow.data.frame``."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import torch
from PIL import Image

from poseflow.data.bop import Detection, write_detections
from poseflow.data.frame import ImageInstances, read_frame, read_intrinsics, read_metric_depth
from poseflow.data.rle import rle_encode
from poseflow.errors import (
    BOPFormatError,
    MissingFileError,
    ShapeError,
    UnitsError,
    ValueRangeError,
)

W, H = 64, 48
K = [[60.0, 0.0, 31.5], [0.0, 60.0, 23.5], [0.0, 0.0, 1.0]]


@pytest.fixture
def files(tmp_path):
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[..., 0] = 200
    Image.fromarray(rgb).save(tmp_path / "rgb.png")
    depth_mm = np.full((H, W), 750, np.uint16)
    depth_mm[:4] = 0  # missing
    Image.fromarray(depth_mm).save(tmp_path / "depth.png")
    mask = np.zeros((H, W), np.uint8)
    mask[10:30, 20:40] = 255
    Image.fromarray(mask).save(tmp_path / "mask.png")
    return tmp_path


def test_reads_a_frame_with_a_millimetre_png(files):
    flat = [x for row in K for x in row]
    f = read_frame(files / "rgb.png", files / "depth.png", flat, masks=[files / "mask.png"])
    assert f.rgb.shape == (3, H, W) and f.rgb.dtype == torch.uint8 and int(f.rgb[0, 0, 0]) == 200
    assert f.depth.dtype == torch.float32 and float(f.depth[20, 20]) == pytest.approx(0.75)
    assert float(f.depth[0, 0]) == 0.0 and f.depth_scale == 0.001
    assert f.masks.shape == (1, H, W) and int(f.masks.sum()) == 400
    assert f.obj_ids.tolist() == [1] and f.scores.tolist() == [1.0] and len(f) == 1


def test_a_frame_gives_its_instances_as_the_estimators_take_them(files):
    f = read_frame(files / "rgb.png", files / "depth.png", K, masks=[files / "mask.png"] * 2)
    image = f.instances
    assert isinstance(image, ImageInstances)
    for got, want in zip(image, (f.rgb, f.depth, f.K, f.masks, f.obj_ids), strict=True):
        assert got is want  # estimate(*frame.instances), in the estimators' order
    checked = image.checked(torch.float32)
    assert checked.K.dtype == torch.float32 and checked.obj_ids.tolist() == [1, 1]
    twice = image.twice()
    assert twice.masks.shape == (4, H, W) and twice.obj_ids.tolist() == [1, 1, 1, 1]


def test_depth_scale_mistakes_name_the_flag(files):
    with pytest.raises(UnitsError, match=r"set --depth-scale 0\.001 \(depth_scale=0\.001"):
        read_metric_depth(files / "depth.png", depth_scale=1.0)  # mm read as metres
    np.save(files / "depth_m.npy", np.full((H, W), 0.75, np.float32))
    depth, scale = read_metric_depth(files / "depth_m.npy")  # float: metres
    assert scale == 1.0 and float(depth[0, 0]) == pytest.approx(0.75)
    np.save(files / "depth_mm.npy", np.full((H, W), 750.0, np.float32))
    with pytest.raises(UnitsError, match=r"--depth-scale 0\.001"):
        read_metric_depth(files / "depth_mm.npy")  # a float image in mm
    with pytest.raises(MissingFileError):
        read_metric_depth(files / "nothing.png")


@pytest.mark.parametrize(
    "spec",
    [
        json.dumps(K),
        json.dumps({"cam_K": [x for row in K for x in row], "depth_scale": 1.0}),
        json.dumps({"fx": 60.0, "fy": 60.0, "cx": 31.5, "cy": 23.5, "width": W}),
    ],
)
def test_intrinsics_from_json_text_and_files(files, spec):
    assert read_intrinsics(spec, W, H).tolist() == K
    (files / "camera.json").write_text(spec)
    assert read_intrinsics(files / "camera.json", W, H).tolist() == K


def test_scene_camera_entries_and_their_depth_scale(files):
    flat = [x for row in K for x in row]
    scene_camera = {"0": {"cam_K": flat, "depth_scale": 0.1}, "5": {"cam_K": flat}}
    (files / "scene_camera.json").write_text(json.dumps(scene_camera))
    with pytest.raises(ValueRangeError, match="--im-id"):
        read_intrinsics(files / "scene_camera.json", W, H)
    with pytest.raises(ValueRangeError, match="no camera of image 3"):
        read_intrinsics(files / "scene_camera.json", W, H, im_id=3)
    assert read_intrinsics(files / "scene_camera.json", W, H, im_id=5).tolist() == K
    # the BOP entry's depth_scale (0.1 mm per unit) is used: 750 units are 75 mm: implausible
    with pytest.raises(UnitsError, match=r"median depth of 0\.075 m"):
        read_frame(files / "rgb.png", files / "depth.png", files / "scene_camera.json", im_id=0,
                   masks=[files / "mask.png"])  # fmt: skip


def test_a_transposed_K_is_refused(files):
    with pytest.raises(ValueRangeError, match="transposed"):
        read_frame(files / "rgb.png", files / "depth.png", np.array(K).T.tolist(),
                   masks=[files / "mask.png"])  # fmt: skip


def test_masks_must_fit_and_instances_must_be_given(files):
    Image.fromarray(np.full((10, 10), 255, np.uint8)).save(files / "small.png")
    with pytest.raises(ShapeError, match="10x10, the image 64x48"):
        read_frame(files / "rgb.png", files / "depth.png", K, masks=[files / "small.png"])
    with pytest.raises(ValueRangeError, match="give the instances"):
        read_frame(files / "rgb.png", files / "depth.png", K)
    with pytest.raises(ShapeError, match="2 masks but 3 object ids"):
        read_frame(files / "rgb.png", files / "depth.png", K,
                   masks=[files / "mask.png"] * 2, obj_ids=[1, 2, 3])  # fmt: skip


def test_detections_of_one_image(files):
    mask = torch.zeros(H, W, dtype=torch.bool)
    mask[5:25, 5:25] = True
    dets = [
        Detection(2, 7, 4, 0.8, (5, 5, 20, 20), rle_encode(mask)),
        Detection(2, 7, 5, 0.1, (5, 5, 20, 20), rle_encode(mask)),
        Detection(2, 8, 4, 0.9, (5, 5, 20, 20), rle_encode(mask)),
    ]
    write_detections(files / "dets.json", dets)
    with pytest.raises(ValueRangeError, match="detections of 2 images"):
        read_frame(files / "rgb.png", files / "depth.png", K, detections=files / "dets.json")
    f = read_frame(files / "rgb.png", files / "depth.png", K, detections=files / "dets.json",
                   im_id=7, score_threshold=0.5)  # fmt: skip
    assert f.obj_ids.tolist() == [4] and f.scores.tolist() == [0.8]
    assert torch.equal(f.masks[0], mask)
    none = read_frame(files / "rgb.png", files / "depth.png", K, detections=files / "dets.json",
                      im_id=9)  # fmt: skip
    assert len(none) == 0 and none.masks.shape == (0, H, W)


@pytest.mark.parametrize("bad", ["transposed", "zero"])
def test_a_bad_cam_k_in_a_file_is_that_files_error_naming_the_image(files, bad):
    flat = (np.array(K).T if bad == "transposed" else np.zeros((3, 3))).reshape(-1).tolist()
    good = [x for row in K for x in row]
    scene_camera = {"3": {"cam_K": good, "depth_scale": 1.0}, "7": {"cam_K": flat}}
    path = files / "scene_camera.json"
    path.write_text(json.dumps(scene_camera))
    with pytest.raises(BOPFormatError, match=f"{path} \\(image 7\\): K") as err:
        read_frame(files / "rgb.png", files / "depth.png", path, im_id=7,
                   masks=[files / "mask.png"])  # fmt: skip
    assert not isinstance(err.value, ValueRangeError)  # a failed run, not a usage error
    assert read_intrinsics(path, W, H, im_id=3).tolist() == K


def test_a_depth_scale_that_overrides_the_camera_entry_warns_with_both_values(files):
    flat = [x for row in K for x in row]
    (files / "cam.json").write_text(json.dumps({"0": {"cam_K": flat, "depth_scale": 1.0}}))
    with pytest.warns(UserWarning, match=r"0\.002 .* overrides the depth_scale 1 \(mm per unit"):
        f = read_frame(files / "rgb.png", files / "depth.png", files / "cam.json",
                       masks=[files / "mask.png"], depth_scale=0.002)  # fmt: skip
    assert f.depth_scale == 0.002
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the same value in metres: nothing to say
        read_frame(files / "rgb.png", files / "depth.png", files / "cam.json",
                   masks=[files / "mask.png"], depth_scale=0.001)  # fmt: skip


def test_colour_and_depth_of_different_sizes_name_both_files(files):
    Image.fromarray(np.zeros((10, 12, 3), np.uint8)).save(files / "small_rgb.png")
    with pytest.raises(ShapeError, match=r"small_rgb\.png is 12x10, the depth image .*depth\.png"):
        read_frame(files / "small_rgb.png", files / "depth.png", K, masks=[files / "mask.png"])
