"""``poseflow estimate``: one RGB-D frame from image files and a mesh."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch
from PIL import Image

from poseflow.cli import main
from poseflow.geometry import translation_error


@pytest.fixture
def frame(box_frame_files):
    """The generated box frame (``box_frame_files`` of the tests' conftest)."""
    return box_frame_files


def _argv(frame, out, *extra):
    return [
        "estimate", "--rgb", str(frame["rgb"]), "--depth", str(frame["depth"]),
        "--K", str(frame["camera"]), "--mask", str(frame["mask"]),
        "--mesh", str(frame["mesh"]), "--mesh-scale", "0.001", "--out", str(out), *extra,
    ]  # fmt: skip


def test_estimate_writes_poses_and_an_overlay(frame, tmp_path, capsys):
    out = tmp_path / "out"
    assert main([*_argv(frame, out), "--no-progress"]) == 0
    data = json.loads((out / "poses.json").read_text())
    (pose,) = data["poses"]
    assert pose["obj_id"] == 1 and pose["valid"] and 0 < pose["score"] <= 1
    assert pose["t_mm"] == pytest.approx([1000 * x for x in pose["t_m"]])
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = torch.tensor(pose["R"], dtype=torch.float64)
    T[:3, 3] = torch.tensor(pose["t_m"], dtype=torch.float64)
    gt = torch.as_tensor(frame["pose"])
    assert translation_error(T, gt).item() < 0.02  # metres (a box looks alike turned over)
    assert data["method"] == "classic baseline" and data["depth_scale"] == pytest.approx(1e-4)
    with Image.open(out / "overlay.png") as im:
        assert im.size == (160, 120)
    assert "1 of 1 poses valid" in capsys.readouterr().out


def test_nine_numbers_and_a_float_depth_in_metres(frame, tmp_path):
    cam = json.loads(frame["camera"].read_text())["0"]
    depth = np.asarray(Image.open(frame["depth"]), dtype=np.float32) * cam["depth_scale"] / 1000
    np.save(tmp_path / "depth.npy", depth)
    argv = _argv(frame, tmp_path / "out")
    argv[argv.index("--depth") + 1] = str(tmp_path / "depth.npy")
    k = argv.index("--K")
    argv[k + 1 : k + 2] = [str(x) for x in cam["cam_K"]]
    assert main([*argv, "-q"]) == 0
    assert json.loads((tmp_path / "out" / "poses.json").read_text())["depth_scale"] == 1.0


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (("--depth-scale", "1"), "set --depth-scale 0.0001"),  # 0.1 mm units read as metres
        (("--mesh-scale", "1"), "set --mesh-scale 0.001"),  # a mesh in mm read as metres
    ],
)
def test_unit_mix_ups_stop_with_the_flag_to_set(frame, tmp_path, capsys, change, message):
    argv = _argv(frame, tmp_path / "out")
    if change[0] in argv:
        argv[argv.index(change[0]) + 1] = change[1]
    else:
        argv += list(change)
    assert main([*argv, "--no-progress"]) == 1
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()  # a failed run leaves no empty folder behind


def test_several_masks_after_one_mask_flag(frame, tmp_path):
    argv = _argv(frame, tmp_path / "out")
    argv.insert(argv.index("--mask") + 2, str(frame["mask"]))  # --mask a.png a.png
    assert main([*argv, "-q"]) == 0
    poses = json.loads((tmp_path / "out" / "poses.json").read_text())["poses"]
    assert [p["obj_id"] for p in poses] == [1, 1]


def test_a_label_image_given_as_a_mask_is_refused(frame, tmp_path, capsys):
    mask = np.asarray(Image.open(frame["mask"])) > 0
    labels = np.zeros(mask.shape, np.uint8)
    rows = np.nonzero(mask.any(axis=1))[0]
    middle = rows[len(rows) // 2]
    labels[:middle][mask[:middle]] = 1
    labels[middle:][mask[middle:]] = 2  # two instances, one value each
    Image.fromarray(labels).save(tmp_path / "labels.png")
    argv = _argv(frame, tmp_path / "out")
    argv[argv.index("--mask") + 1] = str(tmp_path / "labels.png")
    assert main(argv) == 1
    assert "holds 2 labels (1, 2): a label image" in capsys.readouterr().err
    soft = np.where(mask, 255, 0).astype(np.uint8)
    edge = mask & ~np.roll(mask, 1, axis=0)
    soft[edge] = 128  # anti-aliased edge pixels: still one instance
    Image.fromarray(soft).save(tmp_path / "soft.png")
    argv[argv.index("--mask") + 1] = str(tmp_path / "soft.png")
    assert main([*argv, "-q"]) == 0


def test_funflow6d_and_hybrid_need_a_model(frame, tmp_path, capsys):
    for method in ("funflow6d", "hybrid"):
        assert main([*_argv(frame, tmp_path / "out"), "--method", method]) == 2
        assert f"--method {method} needs --model" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_a_transposed_K_is_refused(frame, tmp_path, capsys):
    cam = json.loads(frame["camera"].read_text())["0"]
    K = np.array(cam["cam_K"]).reshape(3, 3).T.reshape(-1)
    argv = _argv(frame, tmp_path / "out")
    k = argv.index("--K")
    argv[k + 1 : k + 2] = [str(x) for x in K]
    assert main(argv) == 2  # an argument out of its range
    assert "is K transposed?" in capsys.readouterr().err


def test_usage_errors(frame, tmp_path, capsys):
    argv = _argv(frame, tmp_path / "out")
    two = [*argv, "--mesh", str(frame["mesh"])]
    assert main(two) == 2  # the same object twice
    assert "two meshes are object 1" in capsys.readouterr().err
    no_masks = [a for a in argv if a not in (str(frame["mask"]),)]
    no_masks.remove("--mask")
    assert main(no_masks) == 2
    assert "give the instances" in capsys.readouterr().err
    assert main([*argv, "--obj-id", "4"]) == 2
    assert "--obj-id [4] has no --mesh" in capsys.readouterr().err


def test_a_broken_model_is_a_failed_run_with_what_to_do(frame, tmp_path, capsys):
    from poseflow.assets import DEMO_CHECKPOINT

    model = tmp_path / "model"
    shutil.copytree(DEMO_CHECKPOINT, model, ignore=shutil.ignore_patterns("objects"))
    weights = model / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[: weights.stat().st_size // 2])
    argv = [*_argv(frame, tmp_path / "out"), "--model", str(model)]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert "model.safetensors is truncated or corrupt" in err and "Traceback" not in err
    shutil.copy(DEMO_CHECKPOINT / "model.safetensors", weights)
    config = json.loads((model / "config.json").read_text())
    config["num_points"] = "many"
    (model / "config.json").write_text(json.dumps(config))
    assert main(argv) == 1
    assert "config.json" in capsys.readouterr().err


def test_no_detection_for_the_image_writes_empty_poses(frame, tmp_path, capsys):
    from poseflow.data.bop import Detection, write_detections
    from poseflow.data.rle import rle_encode

    mask = np.asarray(Image.open(frame["mask"])) > 0
    write_detections(
        tmp_path / "dets.json",
        [Detection(0, 5, 1, 0.9, (0, 0, 1, 1), rle_encode(torch.from_numpy(mask)))],
    )
    argv = _argv(frame, tmp_path / "out")
    argv[argv.index("--mask") : argv.index("--mask") + 2] = [
        "--detections",
        str(tmp_path / "dets.json"),
    ]
    assert main([*argv, "--im-id", "0"]) == 0
    assert json.loads((tmp_path / "out" / "poses.json").read_text())["poses"] == []
    assert "warning: no instance to estimate" in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.parametrize(("method", "name"), [("funflow6d", "FunFlow6D"), ("hybrid", "hybrid")])
def test_estimate_with_the_demo_model_caches_the_prepared_mesh(
    frame, tmp_path, capsys, method, name
):
    argv = [*_argv(frame, tmp_path / "out"), "--model", "demo", "--cache", str(tmp_path / "c")]
    assert main([*argv, "--method", method, "--no-progress"]) == 0
    data = json.loads((tmp_path / "out" / "poses.json").read_text())
    (pose,) = data["poses"]
    assert pose["t_m"][2] > 0 and 0 <= pose["agreement"] <= 1
    # the demo model's calibration knows its own three objects, not this box
    assert not pose["valid"] and "is not the one calibrated" in pose["note"]
    assert "precision of 95%" in data["valid_means"]
    assert data["method"].startswith(name)
    assert len(list((tmp_path / "c" / "objects").glob("obj_000001/*/object.json"))) == 1
    assert name in capsys.readouterr().out


def test_bop_depth_in_tenths_of_a_millimetre_read_as_millimetres_stops(frame, tmp_path, capsys):
    argv = _argv(frame, tmp_path / "out")
    with pytest.warns(UserWarning, match=r"0\.001 .* overrides the depth_scale 0\.1 \(mm per"):
        assert main([*argv, "--depth-scale", "0.001", "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert "10 times too large? set --depth-scale 0.0001" in err
    assert str(frame["depth"]) in err and not (tmp_path / "out" / "poses.json").exists()


@pytest.mark.parametrize("bad", ["transposed", "zero"])
def test_a_bad_cam_k_in_scene_camera_is_a_failed_run_naming_file_and_image(
    frame, tmp_path, capsys, bad
):
    cameras = json.loads(frame["camera"].read_text())
    K = np.array(cameras["0"]["cam_K"]).reshape(3, 3)
    cameras["0"]["cam_K"] = (K.T if bad == "transposed" else 0 * K).reshape(-1).tolist()
    path = tmp_path / "scene_camera.json"
    path.write_text(json.dumps(cameras))
    argv = _argv(frame, tmp_path / "out")
    argv[argv.index("--K") + 1] = str(path)
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert f"{path} (image 0)" in err and "usage:" not in err


def test_view_writes_the_frame_in_3d(frame, tmp_path, capsys):
    trimesh = pytest.importorskip("trimesh")
    pytest.importorskip("rerun")
    from poseflow.eval import GLTF_FROM_CAMERA

    out = tmp_path / "out"
    assert main([*_argv(frame, out), "--view", "--no-progress"]) == 0
    assert (out / "scene.rrd").stat().st_size > 0
    (pose,) = json.loads((out / "poses.json").read_text())["poses"]
    scene = trimesh.load(out / "scene.glb", process=False)
    transform, geom = scene.graph["est_0_obj_000001"]
    np.testing.assert_allclose(transform, GLTF_FROM_CAMERA)
    mesh = trimesh.load(frame["mesh"], process=False)  # millimetres
    R, t = np.asarray(pose["R"]), np.asarray(pose["t_m"])
    expected = (1e-3 * np.asarray(mesh.vertices)) @ R.T + t
    np.testing.assert_allclose(scene.geometry[geom].vertices, expected, atol=1e-5)
    assert "observed" in scene.graph.nodes_geometry
    assert "scene.rrd" in capsys.readouterr().out
