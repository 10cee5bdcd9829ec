"""``poseflow train-detector``, ``detect``, and ``predict``/``estimate`` with the detector."""

from __future__ import annotations

import json

import pytest
import torch

from poseflow.cli import main
from poseflow.data.bop import Detection, read_detections, write_detections
from poseflow.data.rle import rle_encode
from poseflow.data.synthetic import generate_dataset
from poseflow.detect import Detector
from poseflow.eval.results import read_results


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("detcli") / "ds"
    return generate_dataset(
        root, num_train_images=2, num_test_images=1, width=160, height=120,
        objects_per_image=4, progress=False, seed=4,
    )  # fmt: skip


@pytest.fixture(scope="module")
def model_dir(dataset, tmp_path_factory):
    """A model folder holding only a detector trained three steps by the command.

    Its centre threshold is lowered below the untrained heatmaps' level, so that it reports
    instances: the commands' plumbing is under test here, not the detector's accuracy.
    """
    model = tmp_path_factory.mktemp("run") / "model"
    argv = ["train-detector", str(dataset), "--out", str(model / "detector"), "--steps", "3"]
    assert main([*argv, "--batch-size", "2", "--crop", "64", "--no-progress"]) == 0
    det = Detector.load(model / "detector")
    det.config.centre_threshold = 0.005
    det.save(model / "detector")
    return model


def test_train_detector_refuses_to_overwrite(dataset, model_dir, capsys):
    argv = ["train-detector", str(dataset), "--out", str(model_dir / "detector"), "--steps", "1"]
    assert main([*argv, "-q"]) == 1
    assert "--overwrite" in capsys.readouterr().err
    assert main([*argv[:-2], "--steps", "0", "-q"]) == 2


def test_detect_writes_bop_detections(dataset, model_dir, tmp_path):
    out = tmp_path / "dets.json"
    assert main(["detect", str(dataset), "--model", str(model_dir), "--out", str(out), "-q"]) == 0
    dets = read_detections(out)
    assert dets and {d.obj_id for d in dets} <= {1, 2, 3}
    assert all(tuple(d.mask().shape) == (120, 160) and d.time > 0 for d in dets)
    assert all(0 <= d.score <= 1 for d in dets)


def test_detect_errors(dataset, model_dir, tmp_path, capsys):
    out = str(tmp_path / "d.json")
    assert main(["detect", str(dataset), "--model", str(tmp_path), "--out", out, "-q"]) == 1
    assert "train-detector" in capsys.readouterr().err  # a model without a detector
    argv = ["detect", str(dataset), "--model", str(model_dir), "--out", out]
    assert main([*argv, "--score-threshold", "1.5", "-q"]) == 2
    assert "leaves no detection" in capsys.readouterr().err
    assert main(["detect", str(dataset), "--out", out, "-q"]) == 2  # no detector named


def test_predict_with_own_detections(dataset, model_dir, tmp_path):
    csv = tmp_path / "base_ds-test.csv"
    argv = ["predict", str(dataset), "--method", "baseline", "--detections", "own"]
    argv += ["--detector", str(model_dir / "detector"), "--no-verify", "--out", str(csv), "-q"]
    assert main(argv) == 0
    rows = read_results(csv)
    assert len(rows.obj_ids) > 0 and set(rows.obj_ids.tolist()) <= {1, 2, 3}
    assert (rows.times > 0).all()


def test_predict_refuses_detections_of_another_dataset(dataset, tmp_path, capsys):
    mask = torch.zeros(120, 160, dtype=torch.bool)
    mask[10:30, 10:30] = True
    write_detections(
        tmp_path / "d.json",
        [Detection(0, 0, 42, 0.9, (10.0, 10.0, 20.0, 20.0), rle_encode(mask))],
    )
    argv = ["predict", str(dataset), "--method", "baseline", "--detections"]
    argv += [str(tmp_path / "d.json"), "--out", str(tmp_path / "r.csv"), "-q"]
    assert main(argv) == 1
    assert "another dataset" in capsys.readouterr().err
    argv = ["predict", str(dataset), "--method", "baseline", "--detections", "own"]
    assert main([*argv, "--out", str(tmp_path / "r.csv"), "-q"]) == 2  # no detector named


def test_estimate_without_masks_uses_the_detector_and_lists_the_missed(
    dataset, model_dir, tmp_path, capsys
):
    scene = dataset / "test" / "000000"
    frame = [
        "estimate", "--rgb", str(scene / "rgb" / "000000.png"),
        "--depth", str(scene / "depth" / "000000.png"), "--K", str(scene / "scene_camera.json"),
        "--im-id", "0", "--mesh", str(dataset / "models" / "obj_000001.ply"),
        "--mesh-scale", "0.001", "--out", str(tmp_path / "out"),
    ]  # fmt: skip
    assert main([*frame, "-q"]) == 2  # no mask, no detector: a usage error naming the way
    assert "--detector" in capsys.readouterr().err
    argv = [*frame, "--detector", str(model_dir / "detector"), "--no-progress"]
    assert main(argv) == 0
    data = json.loads((tmp_path / "out" / "poses.json").read_text())
    found = {p["obj_id"] for p in data["poses"]}
    assert found <= {1} and set(data["missed"]) == {1} - found  # the one object given
    assert all(p["source"].startswith("detector") for p in data["poses"])
    assert (tmp_path / "out" / "overlay.png").is_file()
