"""``poseflow onboard``: the recipe's phases in one command, skipped when done, resumable."""

from __future__ import annotations

import json
import shutil

import pytest

from poseflow.cli import main
from poseflow.data.synthetic import generate_dataset
from poseflow.models import FunFlow6D

TINY = ["--images", "4", "--surface-steps", "3", "--surface-images", "4", "--detector-steps", "3",
        "--steps", "3", "--config", "demo_small"]  # fmt: skip


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
    assert list(record["done"]) == ["synth", "surface", "detector", "train", "prepare"]
    model = run / "model"
    for part in ("config.json", "model.safetensors", "surface/model.safetensors",
                 "detector/model.safetensors"):  # fmt: skip
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
    assert err.count("done before, skipped") == 4 and "onboard 5/5 prepare:" in err
    # the model folder holds its embedding: moved elsewhere, it loads from there
    moved = tmp_path / "elsewhere" / "model"
    shutil.copytree(model, moved)
    shutil.rmtree(run)
    loaded = FunFlow6D.load(moved)
    assert loaded.appearance_encoder.source == str((moved / "surface").resolve())
    assert loaded.detector is not None
