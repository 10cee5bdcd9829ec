"""``poseflow bench``: per-setting latency, stage breakdown, AR and the fastest equal setting."""

from __future__ import annotations

import argparse
import json

import pytest
import torch

from poseflow.cli import add_command, bench, main
from poseflow.cli.common import command_output, show_progress
from poseflow.data.synthetic import generate_dataset
from poseflow.errors import ValueRangeError
from poseflow.eval.results import read_results
from poseflow.models import FunFlow6D, FunFlow6DConfig, NetOptions


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory):
    torch.manual_seed(0)
    cfg = FunFlow6DConfig(
        num_points=32, crop_size=32, query_views=2, dit_preset="tiny", steps=2,
        ransac_iterations=100, pose_solver="svd",
        net=NetOptions(fusion_heads=2, posenc_dim=16, posenc_frequencies=2),
    )  # fmt: skip
    return FunFlow6D(cfg).save(tmp_path_factory.mktemp("bench") / "model")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return generate_dataset(
        tmp_path_factory.mktemp("bench_data") / "ds", num_train_images=0, num_test_images=1,
        objects_per_image=3, width=160, height=120, progress=False,
    )  # fmt: skip


def test_bench_times_every_setting_and_writes_results(model_dir, dataset, tmp_path, capsys):
    out = tmp_path / "out"
    argv = ["bench", str(dataset), "--model", str(model_dir), "--out", str(out),
            "--samplers", "euler:2", "heun:1", "--device", "cpu", "--no-progress"]  # fmt: skip
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "flow_net" in text and "euler:2" in text and "heun:1" in text
    assert "verification on" in text and "\nverification " in text  # the stage's row
    report = json.loads((out / "bench.json").read_text())
    rows = report["settings"]
    assert list(rows) == ["euler:2", "heun:1"]
    for name, row in rows.items():
        assert row["num_images"] == 1 and row["instances_per_image"] == 3
        assert row["ms_per_image"] == pytest.approx(sum(row["stages_ms"].values()))
        assert 0.0 <= row["AR"] <= 1.0
        results = read_results(out / f"results_{name.replace(':', '-')}.csv")
        assert len(results) == 3  # the svd solver gives every instance a pose
    assert report["fastest_equal_ar"] in rows


def test_fastest_equal_setting_respects_the_tolerance():
    rows = {
        "euler:50": {"AR": 0.70, "ms_per_image": 900.0},
        "euler:10": {"AR": 0.695, "ms_per_image": 300.0},
        "euler:2": {"AR": 0.60, "ms_per_image": 100.0},
    }
    assert bench.fastest_equal_setting(rows, 0.01) == "euler:10"
    assert bench.fastest_equal_setting(rows, 0.0) == "euler:50"
    assert bench.fastest_equal_setting(rows, 0.2) == "euler:2"
    assert bench.fastest_equal_setting({"euler:5": {"ms_per_image": 1.0}}, 0.01) is None


@pytest.mark.parametrize("text", ["euler", "euler:0", "euler:x", "warp:5"])
def test_bad_settings_are_clear_errors(text, model_dir, tmp_path, capsys):
    with pytest.raises(ValueRangeError):
        bench.parse_setting(text)
    argv = ["bench", "--model", str(model_dir), "--out", str(tmp_path), "--samplers", text]
    assert main(argv) == 2
    assert "poseflow bench: error" in capsys.readouterr().err


def test_set_changes_inference_fields_only(model_dir, dataset, tmp_path, capsys):
    out = tmp_path / "out"
    argv = ["bench", str(dataset), "--model", str(model_dir), "--out", str(out), "--samplers",
            "euler:1", "--set", "icp_iterations=3", "--set", "num_hypotheses=2", "--no-eval",
            "--no-progress", "--no-verify"]  # fmt: skip
    assert main(argv) == 0
    report = json.loads((out / "bench.json").read_text())
    config = report["config"]
    assert config["icp_iterations"] == 3 and config["num_hypotheses"] == 2
    assert config["verifier"] is None
    assert "verification" not in report["settings"]["euler:1"]["stages_ms"]
    assert "AR" not in report["settings"]["euler:1"]
    assert main([*argv, "--set", "num_points=64"]) == 2
    assert "num_points" in capsys.readouterr().err
    assert main([*argv, "--set", "verification=true"]) == 2  # it has its own flag
    assert "verification" in capsys.readouterr().err


def test_generated_split_is_made_once(monkeypatch, tmp_path):
    calls = []

    def fake(root, **kwargs):
        calls.append(kwargs)
        root.mkdir(parents=True)
        return root

    monkeypatch.setattr("poseflow.data.synthetic.generate_dataset", fake)
    for _ in range(2):
        bench.generated_split(tmp_path / "d", images=2, instances=8, seed=1, progress=False)
    assert len(calls) == 1 and calls[0]["objects_per_image"] == 8
    bench.generated_split(tmp_path / "e", images=3, instances=8, seed=1, progress=False)
    assert len(calls) == 2


def test_quiet_keeps_the_results_and_drops_the_status_lines(monkeypatch, tmp_path, capsys):
    def fake(root, **kwargs):
        root.mkdir(parents=True)
        return root

    monkeypatch.setattr("poseflow.data.synthetic.generate_dataset", fake)
    for quiet in (False, True):
        with command_output(argparse.Namespace(quiet=quiet)):
            bench.generated_split(tmp_path / "d", images=2, instances=8, seed=1, progress=False)
        out, err = capsys.readouterr()
        assert out == "" and ("generat" in err) is not quiet
    args = add_command(argparse.ArgumentParser().add_subparsers(), "bench").parse_args(["--quiet"])
    assert args.quiet and not show_progress(args)


def test_bench_runs_quietly(model_dir, dataset, tmp_path, capsys):
    argv = ["bench", str(dataset), "--model", str(model_dir), "--out", str(tmp_path / "out"),
            "--samplers", "euler:1", "--device", "cpu", "--quiet", "--no-verify"]  # fmt: skip
    assert main(argv) == 0
    out, err = capsys.readouterr()
    assert "euler:1" in out and "bench.json" in out  # the results
    assert err == ""
