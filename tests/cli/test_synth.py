import argparse
import json

import numpy as np
import pytest

from poseflow.cli import SUBCOMMANDS, add_command, main
from poseflow.cli import synth as synth_cli
from poseflow.data.bop import BOPImageDataset


def _parser():
    parser = argparse.ArgumentParser(prog="poseflow")
    add_command(parser.add_subparsers(dest="command"), "synth")
    return parser


@pytest.fixture
def mesh_folder(tmp_path):
    pytest.importorskip("open3d")
    from poseflow.data.objects import write_bop_model
    from poseflow.data.synthetic import _box_mesh, procedural_texture

    folder = tmp_path / "meshes"
    write_bop_model(
        folder / "a.ply", _box_mesh(np.array([0.08, 0.05, 0.04]), procedural_texture(0))
    )
    write_bop_model(folder / "b.ply", _box_mesh(np.array([0.03, 0.05, 0.1]), procedural_texture(1)))
    return folder


def test_parser_defaults():
    args = _parser().parse_args(["synth", "out"])
    assert args.run is synth_cli.run
    assert (args.train, args.test, args.seed, args.width, args.height) == (200, 50, 0, 640, 480)
    assert args.objects is None and args.objects_per_image == [3, 6]


def test_run_writes_a_dataset(tmp_path, mesh_folder, capsys):
    out = tmp_path / "ds"
    argv = ["synth", str(out), "--objects", str(mesh_folder)]
    argv += "--train 1 --test 2 --width 64 --height 48 --mesh-scale 0.001".split()
    argv += "--objects-per-image 2 --distractors 0 1 --images-per-scene 1 --seed 5".split()
    args = _parser().parse_args([*argv, "--no-progress"])
    assert args.run(args) == 0
    assert "wrote 1 train and 2 test images" in capsys.readouterr().out
    ds = BOPImageDataset(out, "test", load_masks=False)
    assert len(ds) == 2 and ds[0]["rgb"].shape == (3, 48, 64)
    assert sorted(ds[0]["obj_ids"].tolist()) == [1, 2]
    assert len(BOPImageDataset(out, "train", load_masks=False)) == 1
    info = json.loads((out / "models" / "models_info.json").read_text())
    assert info["1"]["size_x"] == pytest.approx(80.0)  # written back in mm


def test_bad_range_is_reported(tmp_path, mesh_folder):
    argv = ["synth", str(tmp_path / "x"), "--objects", str(mesh_folder), "--no-progress"]
    args = _parser().parse_args([*argv, "--objects-per-image", "1", "2", "3"])
    with pytest.raises(ValueError, match="objects-per-image"):
        args.run(args)


def test_registered_in_main(tmp_path, mesh_folder, capsys):
    if "synth" not in SUBCOMMANDS:
        pytest.skip("synth is not registered in poseflow.cli.SUBCOMMANDS yet")
    argv = ["synth", str(tmp_path / "y"), "--objects", str(tmp_path / "nothing")]
    code = main([*argv, *"--train 0 --test 1 --width 48 --height 40 --no-progress".split()])
    assert code == 2  # a PoseflowError (missing folder) becomes exit code 2 with a message
    assert "synth: error" in capsys.readouterr().err


def test_a_non_empty_folder_needs_overwrite(tmp_path, capsys, monkeypatch):
    out = tmp_path / "ds"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    calls = []
    monkeypatch.setattr(
        "poseflow.data.synthetic.generate_dataset", lambda root, *a, **k: calls.append(root) or root
    )
    argv = ["synth", str(out), "--train", "0", "--test", "1", "--no-progress"]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert "is not empty" in err and "--overwrite" in err
    assert calls == []
    assert main([*argv, "--overwrite"]) == 0
    assert len(calls) == 1
    assert main(["synth", str(tmp_path / "new"), "--train", "0", "--test", "1", "-q"]) == 0


def test_meshes_in_millimetres_need_mesh_scale(tmp_path, mesh_folder, capsys):
    argv = ["synth", str(tmp_path / "ds"), "--objects", str(mesh_folder), "--train", "0"]
    assert main([*argv, "--test", "1", "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert "a.ply has a diameter of" in err and "set --mesh-scale 0.001" in err


def test_a_log_gets_plain_progress_lines(tmp_path, mesh_folder, capsys):
    argv = ["--objects", str(mesh_folder), "--mesh-scale", "0.001", "--width", "48", "--height"]
    argv += ["40", "--train", "2", "--test", "1"]
    assert main(["synth", str(tmp_path / "z"), *argv]) == 0
    err = capsys.readouterr().err  # not a terminal: status lines, not a bar
    assert "synth: 3/3 (100%), elapsed" in err and "\x1b" not in err and "\r" not in err
    assert main(["synth", str(tmp_path / "q"), *argv, "--no-progress"]) == 0
    assert "synth:" not in capsys.readouterr().err
