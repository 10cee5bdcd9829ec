"""``poseflow calibrate`` and the rules it writes, as ``estimate`` and ``eval`` apply them."""

from __future__ import annotations

import json
import math
import shutil

import pytest

from poseflow.assets import DEMO_CHECKPOINT
from poseflow.cli import main
from poseflow.data.object_folder import load_object_models
from poseflow.data.synthetic import generate_dataset
from poseflow.eval.validity import ValidityRule, mesh_key, read_validity, write_validity


@pytest.fixture
def box_frame(box_frame_files):
    """The generated box frame's dataset and the baseline's ``estimate`` command of it."""
    frame = box_frame_files
    return frame["root"], [
        "estimate", "--rgb", str(frame["rgb"]), "--depth", str(frame["depth"]),
        "--K", str(frame["camera"]), "--mask", str(frame["mask"]), "--mesh", str(frame["mesh"]),
        "--mesh-scale", "0.001", "--method", "baseline", "--no-progress",
    ]  # fmt: skip


def _rule(root, threshold, *, key=None):
    (model,) = load_object_models(root).values()
    return ValidityRule(
        "baseline", 0.1, 0.95, {1: threshold}, {1: key or mesh_key(model)}, {1: (20, 19)}
    )


@pytest.mark.parametrize(
    ("threshold", "valid", "note"),
    [(0.0, True, ""), (1.5, False, "below 1.500"), (math.inf, False, "no score made poses")],
)
def test_estimate_marks_valid_by_the_models_rule(box_frame, tmp_path, threshold, valid, note):
    root, argv = box_frame
    model = tmp_path / "model"
    model.mkdir()
    write_validity(model, _rule(root, threshold))
    assert main([*argv, "--model", str(model), "--out", str(tmp_path / "out")]) == 0
    data = json.loads((tmp_path / "out" / "poses.json").read_text())
    (pose,) = data["poses"]
    assert pose["valid"] is valid and note in pose["note"]
    assert "precision of 95%" in data["valid_means"]


def test_estimate_without_a_rule_says_valid_is_not_calibrated(box_frame, tmp_path):
    _, argv = box_frame
    assert main([*argv, "--out", str(tmp_path / "out")]) == 0
    data = json.loads((tmp_path / "out" / "poses.json").read_text())
    assert data["poses"][0]["valid"] and "not calibrated" in data["valid_means"]


def test_a_rule_of_another_mesh_does_not_mark_valid(box_frame, tmp_path):
    root, argv = box_frame
    write_validity(tmp_path, _rule(root, 0.0, key="another mesh"))
    assert main([*argv, "--model", str(tmp_path), "--out", str(tmp_path / "out")]) == 0
    (pose,) = json.loads((tmp_path / "out" / "poses.json").read_text())["poses"]
    assert not pose["valid"] and "is not the one calibrated" in pose["note"]


@pytest.mark.parametrize(
    ("extra", "message"),
    [(["--precision", "1"], "--precision must lie"), (["--tolerance", "0"], "--tolerance must")],
)
def test_calibrate_usage_errors(box_frame, tmp_path, capsys, extra, message):
    root, _ = box_frame
    shutil.copytree(DEMO_CHECKPOINT, tmp_path / "model")
    argv = ["calibrate", str(root), "--model", str(tmp_path / "model"), *extra]
    assert main(argv) == 2
    assert message in capsys.readouterr().err


def test_calibrate_needs_a_model_folder(box_frame, tmp_path, capsys):
    root, _ = box_frame
    assert main(["calibrate", str(root), "--model", str(tmp_path)]) == 2
    assert "is not a model folder" in capsys.readouterr().err


@pytest.mark.slow
def test_calibrate_fits_every_method_and_estimate_applies_it(tmp_path, capsys):
    root = generate_dataset(
        tmp_path / "renders", num_train_images=0, num_test_images=2, width=160, height=120,
        progress=False, seed=5,
    )  # fmt: skip
    model = tmp_path / "model"
    shutil.copytree(DEMO_CHECKPOINT, model)
    (model / "validity.json").unlink(missing_ok=True)  # the shipped rules
    argv = ["calibrate", str(root), "--model", str(model), "--method", "funflow6d", "baseline"]
    assert main([*argv, "--no-progress", "--threads", "1"]) == 0
    out = capsys.readouterr().out
    assert "funflow6d:" in out and "baseline:" in out and "on these images: precision" in out
    for method in ("funflow6d", "baseline"):
        rule = read_validity(model, method)
        assert rule is not None and set(rule.thresholds) <= {1, 2, 3}
        assert (model / "calibration" / f"{method}.csv").is_file()
    assert read_validity(model, "hybrid") is None
    assert (model / "calibration" / "validity.png").stat().st_size > 1000
    flow = (model / "calibration" / "funflow6d_poses.csv").read_text().splitlines()
    classic = (model / "calibration" / "baseline_poses.csv").read_text().splitlines()
    assert flow[0] == "scene_id,im_id,obj_id,score,agreement,mssd" and len(flow) > 1
    assert all(line.split(",")[4] for line in flow[1:])  # the flow's hypotheses agree or not
    assert not any(line.split(",")[4] for line in classic[1:])  # the baseline samples none
    # --check measures the stored rules again without changing them
    rules = (model / "validity.json").read_text()
    assert main([*argv, "--check", "--no-progress", "--threads", "1"]) == 0
    assert "(not the calibration's)" in capsys.readouterr().out
    assert (model / "validity.json").read_text() == rules
    # ... into its own folder, leaving the calibration's files as they were
    assert (model / "check" / "funflow6d_poses.csv").is_file()
    assert (model / "calibration" / "funflow6d_poses.csv").read_text().splitlines() == flow


def test_check_needs_the_rules(box_frame, tmp_path, capsys):
    root, _ = box_frame
    shutil.copytree(DEMO_CHECKPOINT, tmp_path / "model")
    (tmp_path / "model" / "validity.json").unlink(missing_ok=True)  # the shipped rules
    argv = ["calibrate", str(root), "--model", str(tmp_path / "model"), "--check"]
    assert main([*argv, "--method", "baseline"]) == 1
    assert "holds no rule for baseline" in capsys.readouterr().err
