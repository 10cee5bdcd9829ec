"""``poseflow demo``: the pose demo runs end to end with a tiny model and writes its outputs."""

from __future__ import annotations

import warnings

import pytest
import torch

from poseflow.cli import main
from poseflow.eval import read_results
from poseflow.models import FunFlow6D, FunFlow6DConfig, NetOptions


@pytest.mark.slow
def test_pose_demo_writes_results_timing_and_overlays(tmp_path, capsys):
    torch.manual_seed(0)
    cfg = FunFlow6DConfig(
        num_points=32, crop_size=32, query_views=2, dit_preset="tiny", steps=2,
        ransac_iterations=100, net=NetOptions(fusion_heads=2, posenc_dim=16, posenc_frequencies=2),
    )  # fmt: skip
    FunFlow6D(cfg).save(tmp_path / "model")
    out = tmp_path / "out"
    code = main(
        ["demo", "--model", str(tmp_path / "model"), "--images", "1", "--out", str(out),
         "--no-baseline"]
    )  # fmt: skip
    assert code == 0
    text = capsys.readouterr().out
    assert "FunFlow6D" in text and "AR_MSSD" in text and "flow_net" in text
    assert "FunFlow6D: first image" in text and "time per image (warm)" in text
    results = read_results(out / "funflow6d.csv")  # parses as a BOP results file
    assert set(results.obj_ids.tolist()) <= {1, 2, 3}
    assert (out / "funflow6d.csv").read_text().startswith("scene_id,im_id,obj_id,score,R,t,time")
    assert (out / "timing.json").is_file() and (out / "timing.png").is_file()
    assert len(list((out / "overlays").glob("*.png"))) == 1


def test_the_shipped_model_has_the_demo_objects_prepared(tmp_path, monkeypatch):
    """The demo (and predict, bench) read every object of the shipped model from its cache."""
    import poseflow.models.objects
    import poseflow.verify.objects
    from poseflow.assets import DEMO_CHECKPOINT
    from poseflow.data.object_folder import load_object_models, object_cache_dir
    from poseflow.data.synthetic import generate_dataset

    def never(*args, **kwargs):
        raise AssertionError("an object of the shipped demo model was prepared again")

    root = generate_dataset(
        tmp_path / "ds", num_train_images=0, num_test_images=0, progress=False
    )  # the demo's models/, no images
    cache = object_cache_dir(DEMO_CHECKPOINT, root)
    assert cache.is_dir()
    monkeypatch.setattr(poseflow.models.objects, "prepare_object", never)
    monkeypatch.setattr(poseflow.verify.objects, "prepare_verifier_object", never)
    model = FunFlow6D.load(DEMO_CHECKPOINT)
    assert model.config.verifier is not None
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no damaged entry, nothing to write
        model.prepare_objects(load_object_models(root), cache_dir=cache, progress=False)
    assert sorted(model.objects) == sorted(model.verifier.objects) == [1, 2, 3]


def test_missing_model_is_a_clear_error(tmp_path, capsys):
    code = main(["demo", "--model", str(tmp_path / "none"), "--images", "1", "--out",
                 str(tmp_path / "o")])  # fmt: skip
    assert code == 1  # a failed run: exit code 2 is for usage errors
    assert "poseflow train" in capsys.readouterr().err


def test_the_timing_chart_is_optional(tmp_path, monkeypatch, capsys):
    import argparse

    from poseflow.cli.common import command_output
    from poseflow.cli.demo import write_timing_chart
    from poseflow.eval import StageTimer

    ticks = iter(range(100))
    timer = StageTimer(clock=lambda: float(next(ticks)))
    with timer.image(), timer.stage("flow_net"):
        pass
    for name in ("matplotlib", "matplotlib.figure"):
        monkeypatch.setitem(__import__("sys").modules, name, None)  # as on a plain install
    with command_output(argparse.Namespace(quiet=False)):
        assert write_timing_chart(timer, tmp_path / "timing.png") is False
    assert not (tmp_path / "timing.png").exists()
    err = capsys.readouterr().err
    assert "timing.png skipped" in err and "pip install 'poseflow[viz]'" in err
    assert len(err.strip().splitlines()) == 1


def test_model_demo_and_images_are_checked_as_usage(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["demo", "--images", "0", "--out", str(tmp_path / "o")])
    assert exc.value.code == 2
    assert "must be at least 1" in capsys.readouterr().err
