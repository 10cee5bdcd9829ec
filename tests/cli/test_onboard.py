"""``poseflow onboard``: the recipe's phases in one command, skipped when done, resumable."""

from __future__ import annotations

import json
import shutil

import pytest

from poseflow.cli import main
from poseflow.data.synthetic import generate_dataset
from poseflow.models import FunFlow6D

TINY = ["--images", "4", "--surface-steps", "3", "--surface-images", "4", "--detector-steps", "3",
        "--steps", "3", "--config", "demo_small", "--calibration-images", "1"]  # fmt: skip


@pytest.fixture(scope="module")
def user_dataset(tmp_path_factory):
    """A user's BOP dataset: the demo objects' models and one test image."""
    root = tmp_path_factory.mktemp("user") / "mine"
    return generate_dataset(
        root, num_train_images=0, num_test_images=1, width=160, height=120, progress=False
    )


def test_meshes_must_be_a_models_folder(tmp_path, capsys):
    assert main(["onboard", str(tmp_path), "--out", str(tmp_path / "run")]) == 1
    assert "is not a BOP models folder" in capsys.readouterr().err


def test_a_run_onboarded_with_other_settings_is_refused(user_dataset, tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "onboard.json").write_text(json.dumps({"settings": {"steps": 5}, "done": {}}))
    assert main(["onboard", str(user_dataset), "--out", str(run), *TINY]) == 2
    assert "was onboarded with other settings" in capsys.readouterr().err


@pytest.mark.slow
def test_onboard_runs_every_phase_once_and_the_model_moves(user_dataset, tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["onboard", str(user_dataset), "--out", str(run), *TINY, "--threads", "1"]) == 0
    record = json.loads((run / "onboard.json").read_text())
    assert list(record["done"]) == [
        "synth", "surface", "detector", "train", "prepare", "calibrate"
    ]  # fmt: skip
    model = run / "model"
    for part in ("config.json", "model.safetensors", "surface/model.safetensors",
                 "detector/model.safetensors", "validity.json"):  # fmt: skip
        assert (model / part).is_file(), part
    assert (
        json.loads((model / "config.json").read_text())["appearance_encoder"] == "surface:surface"
    )
    capsys.readouterr()
    # a second run skips every phase; an interrupted phase (not recorded) is done again
    del record["done"]["prepare"]
    (run / "onboard.json").write_text(json.dumps(record))
    assert main(["onboard", str(user_dataset), "--out", str(run), *TINY]) == 0
    err = capsys.readouterr().err
    assert err.count("done before, skipped") == 5 and "onboard 5/6 prepare:" in err
    # the model folder holds its embedding: moved elsewhere, it loads from there
    moved = tmp_path / "elsewhere" / "model"
    shutil.copytree(model, moved)
    shutil.rmtree(run)
    loaded = FunFlow6D.load(moved)
    assert loaded.appearance_encoder.source == str((moved / "surface").resolve())
    assert loaded.detector is not None


def test_a_run_recorded_before_a_setting_existed_goes_on(user_dataset, tmp_path, capsys):
    from poseflow.cli import build_parser
    from poseflow.cli.onboard import PHASES, _models_folder, _settings

    run = tmp_path / "run"
    argv = ["onboard", str(user_dataset), "--out", str(run), *TINY, "--calibration-images", "0"]
    settings = _settings(build_parser().parse_args(argv), _models_folder(str(user_dataset)))
    del settings["calibration_images"]  # a run onboarded before calibration existed
    run.mkdir()
    done = {phase: {"minutes": 1.0} for phase in PHASES[:-1]}
    (run / "onboard.json").write_text(json.dumps({"settings": settings, "done": done}))
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert err.count("done before, skipped") == 5 and "calibrate: not made" in err
    # another value of an existing setting is still refused
    assert main([*argv, "--steps", "4"]) == 2
