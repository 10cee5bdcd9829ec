"""``poseflow prepare``, ``train`` and ``predict`` end to end on a tiny generated dataset."""

from __future__ import annotations

import argparse
import json
import shutil
import types

import numpy as np
import pytest
import torch

from poseflow.cli import SUBCOMMANDS, main
from poseflow.cli.common import resolve_device
from poseflow.cli.options import add_config_arguments, build_config, parse_set
from poseflow.cli.predict import select_targets
from poseflow.data.bop import BOPDataset, Detection, write_detections
from poseflow.data.object_folder import (
    check_dataset,
    load_object_models,
    models_fingerprint,
    object_cache_dir,
)
from poseflow.data.rle import rle_encode
from poseflow.data.synthetic import generate_dataset
from poseflow.errors import MissingFileError, UsageError, ValueRangeError
from poseflow.eval.results import read_results
from poseflow.models import FunFlow6D, NetOptions

NET = '{"fusion_heads": 2, "posenc_dim": 16, "posenc_frequencies": 2}'
#: The tiny configuration, as command-line options. ``pose_solver=svd`` always yields a pose, so
#: that an untrained model still writes rows (RANSAC finds no consensus in its noise).
TINY = [
    *("--num-points", "32", "--crop-size", "32", "--query-views", "2", "--preset", "tiny"),
    *("--set", "steps=2", "--set", "ransac_iterations=100", "--set", f"net={NET}"),
    *("--set", "pose_solver=svd"),
]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("bop") / "ds"
    return generate_dataset(
        root, num_train_images=2, num_test_images=1, width=160, height=120, progress=False
    )


@pytest.fixture(scope="module")
def run_dir(dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    prep = ["prepare", str(dataset), "--out", str(out / "model"), *TINY, "--no-progress"]
    assert main(prep) == 0
    argv = ["train", str(dataset), "--out", str(out), "--steps", "3", "--batch-size", "4"]
    assert main([*argv, *TINY, "--device", "cpu", "--no-progress"]) == 0
    return out


def _object_files(out, dataset):
    return sorted(object_cache_dir(out, dataset).glob("obj_*/*/object.safetensors"))


# ------------------------------------------------------------------------------ the pipeline


def test_subcommands_are_registered(capsys):
    assert {"synth", "prepare", "train", "predict", "eval"} <= set(SUBCOMMANDS)
    for name in ("prepare", "train", "predict"):
        with pytest.raises(SystemExit) as exc:
            main([name, "--help"])
        assert exc.value.code == 0
        out = capsys.readouterr().out
        assert f"usage: poseflow {name}" in out and "DATASET" in out.upper()
        assert ("--device" in out) == (name != "prepare")


def test_prepare_caches_every_object_and_the_model_reuses_the_cache(run_dir, dataset, capsys):
    files = _object_files(run_dir / "model", dataset)
    assert [f.parent.parent.name for f in files] == ["obj_000001", "obj_000002", "obj_000003"]
    stamps = [f.stat().st_mtime_ns for f in files]
    # Preparing again into the trained model's folder takes its config.json: every object is a
    # cache hit, nothing is rewritten.
    capsys.readouterr()
    assert main(["prepare", str(dataset), "--out", str(run_dir / "model"), "--no-progress"]) == 0
    assert [f.stat().st_mtime_ns for f in files] == stamps
    out = capsys.readouterr().out
    assert "num_points=32" in out and "obj_000002" in out


def test_prepare_refuses_config_options_for_a_trained_model(run_dir, dataset, capsys):
    argv = ["prepare", str(dataset), "--out", str(run_dir / "model"), "--num-points", "64"]
    assert main(argv) == 2
    assert "fixes the configuration" in capsys.readouterr().err


def test_train_saves_a_loadable_model_and_its_run(run_dir):
    model = FunFlow6D.load(run_dir / "model")
    cfg = model.config
    assert (cfg.num_points, cfg.dit_preset, cfg.steps, cfg.pose_solver) == (32, "tiny", 2, "svd")
    assert cfg.net == NetOptions.from_dict(json.loads(NET))
    run = json.loads((run_dir / "run.json").read_text())
    assert run["config"] == cfg.to_dict() and run["train"]["steps"] == 3
    assert (run_dir / "checkpoints" / "step-00000003.json").is_file()
    key = json.loads((run_dir / "train_set.json").read_text())
    assert key["split"] == "train" and "fusion" not in key["features"]


def test_resume_reuses_the_training_set_and_continues(run_dir, dataset, tmp_path, capsys):
    out = tmp_path / "run"
    shutil.copytree(run_dir, out)
    data_stamp = (out / "train_set.safetensors").stat().st_mtime_ns
    capsys.readouterr()
    argv = ["train", str(dataset), "--out", str(out), "--steps", "4", "--batch-size", "4"]
    with pytest.warns(UserWarning, match=r"steps 4 \(was 3\)"):  # more steps: told, allowed
        assert main([*argv, "--resume", "--no-progress"]) == 0  # config from run.json
    text = capsys.readouterr().out
    assert "training set reused: " in text and "trained 4 steps" in text
    assert (out / "train_set.safetensors").stat().st_mtime_ns == data_stamp
    assert (out / "checkpoints" / "step-00000004.json").is_file()
    # Without --resume an existing run is not overwritten; a changed config does not resume.
    assert main([*argv, "--no-progress"]) == 2
    assert "--resume" in capsys.readouterr().err
    assert main([*argv, "--resume", *TINY[:-2], "--no-progress"]) == 2  # not svd any more
    assert "differs from that of the run" in capsys.readouterr().err


def test_distill_from_a_trained_model_makes_a_one_step_sampler(run_dir, dataset, tmp_path, capsys):
    out = tmp_path / "distilled"
    capsys.readouterr()
    argv = ["train", str(dataset), "--out", str(out), "--steps", "2", "--batch-size", "4"]
    argv += ["--distill-from", str(run_dir / "model"), "--device", "cpu", "--no-progress"]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "training set reused: " in text  # the teacher's run folder's set
    assert "distilled into a one-step sampler in 2 steps" in text
    assert not (out / "train_set.safetensors").exists()
    teacher, student = FunFlow6D.load(run_dir / "model"), FunFlow6D.load(out / "model")
    assert (student.config.steps, student.config.solver) == (1, "euler")
    assert teacher.config.with_inference(steps=1, solver="euler") == student.config
    moved = [
        not torch.equal(a, b)
        for a, b in zip(teacher.state_dict().values(), student.state_dict().values(), strict=True)
    ]
    assert any(moved)  # trained from the teacher's weights
    run = json.loads((out / "run.json").read_text())
    assert run["distilled_from"] == str((run_dir / "model").resolve())
    # the student keeps the teacher's configuration: no configuration options
    assert main([*argv[:2], "--out", str(tmp_path / "other"), *argv[4:], *TINY[:2]]) == 2
    assert "teacher's configuration" in capsys.readouterr().err
    # --resume finds the teacher in run.json and keeps distilling; another teacher is refused
    resume = [*argv[:4], "--steps", "3", "--batch-size", "4", "--resume", "--no-progress"]
    with pytest.warns(UserWarning, match=r"steps 3 \(was 2\)"):
        assert main(resume) == 0
    assert "distilled into a one-step sampler in 3 steps" in capsys.readouterr().out
    assert FunFlow6D.load(out / "model").config.solver == "euler"
    assert main([*resume, "--distill-from", str(out / "model")]) == 2
    assert f"distils {(run_dir / 'model').resolve()}" in capsys.readouterr().err
    # a flow-matching run cannot be resumed as a distillation
    plain = tmp_path / "plain"
    shutil.copytree(run_dir, plain)
    joined = [*argv[:2], "--out", str(plain), *argv[4:], "--resume"]
    assert main(joined) == 2
    assert "trains by flow matching" in capsys.readouterr().err


def test_changed_features_rebuild_the_training_set(run_dir, dataset, tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    for name in ("train_set.safetensors", "train_set.json"):
        shutil.copy(run_dir / name, out / name)
    shutil.copytree(run_dir / "model" / "objects", out / "model" / "objects")
    capsys.readouterr()
    base = ["train", str(dataset), "--out", str(out), *TINY, "--no-progress", "--data-only"]
    assert main(base) == 0
    assert "training set reused" in capsys.readouterr().out  # same key
    assert main([*base, "--set", "fusion=sum"]) == 0  # a network-only field: still reused
    assert "training set reused" in capsys.readouterr().out
    assert main([*base, "--copies", "2"]) == 0
    text = capsys.readouterr().out
    assert "training set built" in text
    key = json.loads((out / "train_set.json").read_text())
    assert key["copies"] == 2 and "occlusion" not in key  # keys without it are unchanged
    assert main([*base, "--copies", "2", "--occlusion", "0.5"]) == 0
    assert "training set built" in capsys.readouterr().out
    assert json.loads((out / "train_set.json").read_text())["occlusion"] == 0.5
    assert main([*base, "--occlusion", "1.5"]) == 2
    assert "--occlusion must lie in [0, 1]" in capsys.readouterr().err
    assert not (out / "checkpoints").exists()  # --data-only trains nothing


def test_two_threads_build_the_same_training_set_in_two_processes(dataset, tmp_path, capsys):
    from poseflow.models.training import FlowTrainingSet

    sets = {}
    for threads in ("1", "2"):
        out = tmp_path / threads
        argv = ["train", str(dataset), "--out", str(out), *TINY, "--copies", "2", "--no-progress"]
        assert main([*argv, "--data-only", "--threads", threads]) == 0
        assert "training set built" in capsys.readouterr().out
        sets[threads] = FlowTrainingSet.load(out / "train_set.safetensors")
        key = json.loads((out / "train_set.json").read_text())
        assert "threads" not in key and "workers" not in key
    for k, v in sets["1"].tensors.items():
        assert torch.equal(v, sets["2"].tensors[k]), k


def test_predict_writes_a_bop_csv_and_the_stage_timing(run_dir, dataset, tmp_path, capsys):
    csv, timing = tmp_path / "res" / "ff_synth-test.csv", tmp_path / "timing.json"
    argv = ["predict", str(dataset), "--model", str(run_dir / "model"), "--out", str(csv)]
    assert main([*argv, "--timing", str(timing), "--no-progress", "--device", "cpu"]) == 0
    results = read_results(csv)
    ds = BOPDataset(dataset, "test")
    wanted = {t.obj_id for t in select_targets(ds, targets=True)}
    expected = sorted(g.obj_id for g in ds.scene(0).gt_of(0) if g.obj_id in wanted)
    assert sorted(results.obj_ids.tolist()) == expected  # svd: every instance has a pose
    assert set(results.scene_ids.tolist()) == {0} and set(results.im_ids.tolist()) == {0}
    assert torch.isfinite(results.poses).all() and (results.times > 0).all()
    R = results.poses[:, :3, :3]
    eye = torch.eye(3, dtype=R.dtype).expand_as(R)
    assert torch.allclose(R @ R.transpose(1, 2), eye, atol=1e-6)
    # translations were written in mm and read back in metres: objects 0.3-1.5 m away
    assert ((results.poses[:, 2, 3] > 0.2) & (results.poses[:, 2, 3] < 2.0)).all()
    report = json.loads(timing.read_text())
    assert report["num_images"] == 1 and report["method"] == "funflow6d"
    for stage in ("geometric_encoder", "appearance_encoder", "flow_net", "icp"):
        assert report["stages_ms"][stage] > 0
    assert "written to" in capsys.readouterr().out


def test_predict_from_detections_with_sampler_options(run_dir, dataset, tmp_path):
    ds = BOPDataset(dataset, "test")
    scene = ds.scene(0)
    dets = [
        Detection(0, 0, g.obj_id, 0.5, (0, 0, 1, 1), rle_encode(scene.load_mask(0, k)), 0.25)
        for k, g in enumerate(scene.gt_of(0))
    ]
    dets.append(Detection(0, 0, 1, 0.9, (0, 0, 1, 1), rle_encode(torch.zeros(7, 9)), 0.25))
    path = tmp_path / "dets.json"
    write_detections(path, dets)
    csv = tmp_path / "det.csv"
    argv = ["predict", str(dataset), "--model", str(run_dir / "model"), "--out", str(csv)]
    argv += ["--detections", str(path), "--all-instances", "--hypotheses", "2"]
    argv += ["--steps", "3", "--solver", "heun", "--no-progress", "--seed", "1"]
    with pytest.warns(UserWarning, match="differs from the image"):
        assert main(argv) == 0
    results = read_results(csv)
    assert len(results) == len(dets) - 1  # the mask of the wrong size is skipped
    assert ((results.scores >= 0) & (results.scores <= 1)).all()
    assert (results.times >= 0.25).all()  # the detector's time is added to the image's


def test_predict_options_are_checked_before_any_work(run_dir, dataset, tmp_path, capsys):
    base = ["predict", str(dataset), "--out", str(tmp_path / "r.csv"), "--no-progress"]
    assert main([*base, "--model", str(tmp_path / "nothing")]) == 1  # a failed run
    assert "holds no FunFlow6D checkpoint" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:  # a usage error, from the option's type
        main([*base, "--model", str(run_dir / "model"), "--solver", "leapfrog"])
    assert exc.value.code == 2
    assert "'leapfrog' is not one of euler" in capsys.readouterr().err
    model = ["--model", str(run_dir / "model")]
    assert main([*base, *model, "--set", 'verifier={"crop_size": 60}']) == 2
    assert "block_size" in capsys.readouterr().err
    assert main([*base, *model, "--set", "fusion=sum"]) == 2
    assert "fusion: not an inference setting" in capsys.readouterr().err
    assert main([*base, *model, "--set", "verification=false"]) == 2  # --no-verify or verifier
    assert "can change only" in capsys.readouterr().err
    baseline = [*base, "--method", "baseline"]
    assert main([*baseline, "--set", "num_hypotheses=2"]) == 2
    assert "only verifier with --method baseline" in capsys.readouterr().err
    assert main([*baseline, "--set", "verifier=3"]) == 2
    assert "verifier must be a VerifierConfig" in capsys.readouterr().err
    assert not (tmp_path / "r.csv").exists()


def test_predict_verifies_unless_told_not_to(run_dir, dataset, tmp_path, capsys):
    runs = {}
    no_verify = ["--no-verify", "--clock", "cpu"]
    for flags in ([], no_verify, ["--set", "verifier.rank_hypotheses=false", "--hypotheses", "2"]):
        csv, timing = tmp_path / f"{len(flags)}.csv", tmp_path / f"{len(flags)}.json"
        argv = ["predict", str(dataset), "--model", str(run_dir / "model"), "--out", str(csv)]
        assert main([*argv, "--timing", str(timing), "--no-progress", *flags]) == 0
        runs[len(flags)] = (read_results(csv), json.loads(timing.read_text()))
    (verified, on), (plain, off) = runs[0], runs[3]
    assert on["clock"] == "wall" and off["clock"] == "cpu" and off["total_ms"] > 0
    assert on["verification"] is True and on["config"]["verifier"] is not None
    assert on["stages_ms"]["verification"] > 0
    assert off["verification"] is False and off["config"]["verifier"] is None
    assert "verification" not in off["stages_ms"]
    assert len(verified) == len(plain)  # svd: every instance has a pose either way
    assert not torch.allclose(verified.scores, plain.scores)  # the verifier's scores
    assert runs[4][1]["config"]["verifier"]["rank_hypotheses"] is False
    assert "funflow6d + verification" in capsys.readouterr().out


def test_predict_checks_that_out_is_writable_before_any_work(
    dataset, tmp_path, capsys, monkeypatch
):
    def never(*args, **kwargs):
        raise AssertionError("predict_dataset ran although --out cannot be written")

    monkeypatch.setattr("poseflow.eval.predict.predict_dataset", never)
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    argv = ["predict", str(dataset), "--method", "baseline", "--out", str(blocker / "r.csv")]
    assert main([*argv, "--no-progress"]) == 1
    assert "cannot write in" in capsys.readouterr().err


def test_predict_names_the_apt_package_of_a_missing_open3d_library(
    dataset, tmp_path, capsys, monkeypatch
):
    from poseflow.render import backend

    def import_module(name, package=None):
        raise ImportError("libGL.so.1: cannot open shared object file: No such file or directory")

    monkeypatch.setattr(backend, "importlib", types.SimpleNamespace(import_module=import_module))
    monkeypatch.setattr("poseflow.baselines.ClassicBaseline.prepare", _never)
    monkeypatch.setattr("poseflow.eval.predict.predict_dataset", _never)
    argv = ["predict", str(dataset), "--method", "baseline", "--out", str(tmp_path / "r.csv")]
    assert main([*argv, "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert "libGL.so.1" in err and "sudo apt-get install libgl1" in err and "Traceback" not in err


def _never(*args, **kwargs):
    raise AssertionError("ran although Open3D cannot be imported")


@pytest.mark.parametrize("command", ["prepare", "train", "predict"])
def test_missing_dataset_is_a_clear_error(command, tmp_path, capsys):
    missing = tmp_path / "no_such_dataset"
    argv = [command, str(missing), "--out", str(tmp_path / "o")]
    if command == "predict":
        argv += ["--method", "baseline"]
    assert main(argv) == 1  # a failed run, not a usage error
    err = capsys.readouterr().err
    assert f"poseflow {command}: error: dataset folder {missing} does not exist" in err


def test_missing_split_and_models_are_clear_errors(dataset, tmp_path, capsys):
    assert main(["train", str(dataset), "--out", str(tmp_path), "--split", "train_pbr"]) == 1
    assert "has no split 'train_pbr'" in capsys.readouterr().err
    empty = tmp_path / "empty"
    (empty / "test").mkdir(parents=True)
    out = str(tmp_path / "x.csv")
    assert main(["predict", str(empty), "--method", "baseline", "--out", out]) == 1
    assert "models_info.json is missing" in capsys.readouterr().err


@pytest.mark.slow
def test_hybrid_predicts_with_the_model_and_the_baseline(run_dir, dataset, tmp_path, capsys):
    csv, timing = tmp_path / "hybrid.csv", tmp_path / "t.json"
    argv = ["predict", str(dataset), "--method", "hybrid", "--model", str(run_dir / "model")]
    assert main([*argv, "--out", str(csv), "--timing", str(timing), "--no-progress"]) == 0
    results = read_results(csv)
    assert len(results) >= 3 and (results.scores > 0).all()
    report = json.loads(timing.read_text())
    assert report["method"] == "hybrid" and report["config"]["verifier"] is not None
    verifier = report["config"]["verifier"]
    assert verifier["coarse_crop_size"] == verifier["crop_size"]  # every candidate on the full grid
    for name in ("integration", "geometric_encoder", "ransac", "icp", "verification"):
        assert report["stages_ms"][name] > 0, name
    coarse = ["--set", "verifier.coarse_crop_size=16", "--max-images", "1"]
    assert main([*argv, *coarse, "--out", str(csv), "--timing", str(timing), "--no-progress"]) == 0
    assert json.loads(timing.read_text())["config"]["verifier"]["coarse_crop_size"] == 16
    assert main([*argv, "--out", str(csv), "--no-verify"]) == 2
    assert "chooses by verification" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main([*argv, "--out", str(csv), "--max-images", "-1"])
    assert exc.value.code == 2


def test_baseline_predicts_without_a_model(dataset, tmp_path, capsys):
    csv, timing = tmp_path / "base.csv", tmp_path / "t.json"
    argv = ["predict", str(dataset), "--method", "baseline", "--out", str(csv)]
    overlays = tmp_path / "pictures"
    assert main([*argv, "--timing", str(timing), "--overlays", str(overlays), "--no-progress"]) == 0
    results = read_results(csv)
    pictures = sorted(overlays.glob("*.png"))
    images = sorted(set(zip(results.scene_ids.tolist(), results.im_ids.tolist())))
    assert [p.name for p in pictures] == [f"{s:06d}_{i:06d}.png" for s, i in images]
    assert "overlay pictures written" in capsys.readouterr().out
    assert len(results) >= 3 and (results.scores > 0).all()
    report = json.loads(timing.read_text())
    assert report["method"] == "baseline" and report["stages_ms"]["icp"] > 0
    assert report["verification"] is True and report["stages_ms"]["verification"] > 0


def test_two_threads_predict_the_images_in_two_processes_with_the_same_rows(tmp_path, capsys):
    root = generate_dataset(
        tmp_path / "ds", num_train_images=0, num_test_images=3, width=160, height=120,
        progress=False,
    )  # fmt: skip
    rows, pictures = {}, {}
    for threads in ("1", "2"):
        csv, overlays = tmp_path / f"base{threads}.csv", tmp_path / f"pictures{threads}"
        argv = ["predict", str(root), "--method", "baseline", "--out", str(csv), "--no-progress"]
        assert main([*argv, "--overlays", str(overlays), "--threads", threads]) == 0
        rows[threads], summary = read_results(csv), capsys.readouterr().out
        assert ("by 2 worker processes" in summary) == (threads == "2")
        assert "3 images" in summary
        pictures[threads] = {p.name: p.read_bytes() for p in overlays.glob("*.png")}
    for name in ("scene_ids", "im_ids", "obj_ids", "scores", "poses"):
        assert torch.equal(getattr(rows["1"], name), getattr(rows["2"], name)), name
    assert len(rows["1"]) >= 3 and pictures["1"] == pictures["2"] and len(pictures["1"]) == 3


@pytest.mark.slow
def test_train_under_torchrun(dataset, tmp_path, torchrun):
    out = tmp_path / "ddp"
    argv = ["train", str(dataset), "--out", str(out), "--steps", "2", "--batch-size", "2"]
    proc = torchrun([*argv, *TINY, "--device", "cpu", "--no-progress"], timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "on 2 processes" in proc.stdout
    assert proc.stdout.count("model saved to") == 1  # only rank 0 writes and reports
    assert FunFlow6D.load(out / "model").config.num_points == 32


# ------------------------------------------------------------------------------ helpers


def _config_args(argv):
    parser = argparse.ArgumentParser()
    add_config_arguments(parser)
    return parser.parse_args(argv)


def test_build_config_applies_file_then_flags_then_set(tmp_path):
    path = tmp_path / "cfg.json"
    path.write_text(json.dumps({"num_points": 64, "fusion": "cross", "steps": 7}))
    args = _config_args(["--config", str(path), "--fusion", "sum", "--set", "steps=9"])
    cfg = build_config(args)
    assert (cfg.num_points, cfg.fusion, cfg.steps) == (64, "sum", 9)
    assert build_config(_config_args(["--set", "icp_distances=[]"])).icp_distances == ()
    named = build_config(_config_args(["--config", "learned_small", "--set", "net.dit.depth=2"]))
    assert named.appearance_encoder == "learned" and named.num_hypotheses == 24
    assert (named.net.dit.depth, named.net.dit.hidden_dim) == (2, 64)  # merged, not reset


@pytest.mark.parametrize(
    ("argv", "error", "match"),
    [
        (["--set", "colour=red"], ValueRangeError, "unknown FunFlow6DConfig field 'colour'"),
        (["--set", "steps"], ValueRangeError, "KEY=VALUE"),
        (["--num-points", "4"], ValueRangeError, "num_points"),
        (["--set", "num_points=many"], ValueRangeError, "invalid FunFlow6D configuration"),
        (["--set", "num_points=abc"], UsageError, r"num_points must be an int, got 'abc' \(str\)"),
        (["--set", 'verifier={"crop_size": "x"}'], UsageError, r"VerifierConfig\.crop_size must"),
        (["--config", "/no/such/cfg.json"], MissingFileError, "no such file"),
    ],
)
def test_bad_configuration_is_reported(argv, error, match):
    with pytest.raises(error, match=match):
        build_config(_config_args(argv))


def test_bad_config_file_is_reported(tmp_path):
    path = tmp_path / "cfg.json"
    path.write_text("{num_points: 3")
    with pytest.raises(ValueRangeError, match="not valid JSON"):
        build_config(_config_args(["--config", str(path)]))


def test_parse_set_keeps_non_json_values_as_strings():
    assert parse_set(["appearance_encoder=dinov2:vits14", "a=1.5", "b=[1, 2]"]) == {
        "appearance_encoder": "dinov2:vits14",
        "a": 1.5,
        "b": [1, 2],
    }


def test_resolve_device():
    assert resolve_device("cpu") == torch.device("cpu")
    with pytest.raises(ValueRangeError, match="not a torch device"):
        resolve_device("abacus")
    if not torch.cuda.is_available():
        assert resolve_device("auto") == torch.device("cpu")
        with pytest.raises(ValueRangeError, match="CUDA is not available"):
            resolve_device("cuda")
    else:
        assert resolve_device("cuda").type == "cuda"


def test_object_models_are_in_metres_with_their_ids(dataset):
    models = load_object_models(dataset, obj_ids=[2])
    info = BOPDataset(dataset, "test").models_info()[2]
    assert list(models) == [2] and models[2].name == "obj_000002"
    assert models[2].diameter == pytest.approx(info.diameter, rel=1e-3)
    with pytest.raises(ValueRangeError, match=r"objects \[9\]"):
        load_object_models(dataset, obj_ids=[9])


def test_models_fingerprint_follows_the_content(dataset, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(dataset / "models", copy / "models")
    assert models_fingerprint(copy) == models_fingerprint(dataset)
    with open(copy / "models" / "obj_000001.ply", "ab") as f:
        f.write(b"\n")
    assert models_fingerprint(copy) != models_fingerprint(dataset)
    assert check_dataset(copy) == copy


def test_select_targets_from_the_file_the_ground_truth_or_the_detections(dataset):
    ds = BOPDataset(dataset, "train")
    everything = select_targets(ds)
    gts = [g for s in ds.scene_ids for i in ds.scene(s).im_ids for g in ds.scene(s).gt_of(i)]
    assert sum(t.inst_count for t in everything) == len(gts)
    test = BOPDataset(dataset, "test")
    from_file = select_targets(test, targets=True)
    targets = json.loads((dataset / "test_targets_bop19.json").read_text())
    assert [(t.obj_id, t.inst_count) for t in from_file] == sorted(
        (t["obj_id"], t["inst_count"]) for t in targets
    )
    dets = [Detection(0, 0, 2, 0.9, (0, 0, 1, 1)), Detection(0, 0, 2, 0.8, (0, 0, 1, 1))]
    assert [(t.obj_id, t.inst_count) for t in select_targets(test, detections=dets)] == [(2, 2)]


# ------------------------------------------------------------------------------ caches and resume


def test_the_training_set_cache_follows_the_images(run_dir, dataset, tmp_path, capsys):
    from PIL import Image

    copy = tmp_path / "copy"
    shutil.copytree(dataset, copy)  # the same content in another place
    out = tmp_path / "run"
    out.mkdir()
    for name in ("train_set.safetensors", "train_set.json"):
        shutil.copy(run_dir / name, out / name)
    base = ["train", str(copy), "--out", str(out), *TINY, "--no-progress", "--data-only"]
    capsys.readouterr()
    assert main(base) == 0
    assert "training set built" in capsys.readouterr().out  # another dataset path
    assert main(base) == 0
    assert "training set reused" in capsys.readouterr().out
    image = copy / "train" / "000000" / "rgb" / "000000.png"
    with Image.open(image) as im:
        pixels = np.asarray(im).copy()
    Image.fromarray(255 - pixels).save(image)  # other images, same annotations
    assert main(base) == 0
    assert "training set built" in capsys.readouterr().out


def test_a_corrupt_training_set_cache_is_rebuilt_with_a_warning(run_dir, dataset, tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    for name in ("train_set.safetensors", "train_set.json"):
        shutil.copy(run_dir / name, out / name)
    base = ["train", str(dataset), "--out", str(out), *TINY, "--no-progress", "--data-only"]
    (out / "train_set.json").write_text('{"dataset": "ab')  # cut short
    capsys.readouterr()
    with pytest.warns(UserWarning, match=r"train_set\.json is corrupt"):
        assert main(base) == 0
    assert "training set built" in capsys.readouterr().out
    assert json.loads((out / "train_set.json").read_text())["split"] == "train"  # whole again
    data = out / "train_set.safetensors"
    data.write_bytes(data.read_bytes()[:-100])
    with pytest.warns(UserWarning, match=r"train_set\.safetensors is truncated or corrupt"):
        assert main(base) == 0
    assert "training set built" in capsys.readouterr().out
    assert not list(out.glob("*.tmp")) and not list(out.glob(".*.tmp"))


def test_resume_with_other_settings_warns_and_keeps_the_original_record(run_dir, dataset, tmp_path):
    out = tmp_path / "run"
    shutil.copytree(run_dir, out)
    original = json.loads((out / "run.json").read_text())
    argv = ["train", str(dataset), "--out", str(out), "--steps", "4", "--batch-size", "2"]
    with pytest.warns(UserWarning, match=r"steps 4 \(was 3\), batch_size 2 \(was 4\)"):
        assert main([*argv, "--resume", "--no-progress"]) == 0
    record = json.loads((out / "run.json").read_text())
    assert record["train"] == original["train"] and record["config"] == original["config"]
    assert [r["train"]["batch_size"] for r in record["resumed"]] == [2]


def test_predict_defaults_to_the_demo_model_with_a_note(dataset, tmp_path, capsys):
    csv = tmp_path / "r.csv"
    argv = ["predict", str(dataset), "--out", str(csv), "--max-images", "1", "--no-progress"]
    assert main(argv) == 0
    assert "note: no --model given: using the demo model" in capsys.readouterr().err
    assert len(read_results(csv)) >= 1


@pytest.mark.parametrize("command", ["prepare", "train"])
def test_an_unwritable_out_fails_before_any_work(command, dataset, tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    assert main([command, str(dataset), "--out", str(blocker / "run"), *TINY, "-q"]) == 1
    assert "cannot write in" in capsys.readouterr().err
