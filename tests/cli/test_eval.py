from __future__ import annotations

import argparse
import json

import open3d as o3d
import pytest

from poseflow.cli import eval as eval_cli
from poseflow.data.synthetic import generate_dataset
from poseflow.eval.evaluate import gt_results
from poseflow.eval.results import write_results


def _parse(argv):
    parser = argparse.ArgumentParser(prog="poseflow")
    eval_cli.add_parser(parser.add_subparsers(dest="command"))
    return parser.parse_args(argv)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    box = o3d.geometry.TriangleMesh.create_box(0.08, 0.06, 0.04).translate((-0.04, -0.03, -0.02))
    root = tmp_path_factory.mktemp("bop")
    generate_dataset(
        root,
        [box],
        num_train_images=0,
        num_test_images=2,
        objects_per_image=1,
        distractors_per_image=0,
        width=96,
        height=72,
        progress=False,
    )
    return root


def test_eval_prints_table_and_writes_json(dataset, tmp_path, capsys):
    csv = tmp_path / "gt_synth-test.csv"
    write_results(csv, gt_results(dataset))
    args = _parse(["eval", str(dataset), str(csv)])
    assert args.run(args) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert lines[0].split() == ["object", "targets", "AR_VSD", "AR_MSSD", "AR_MSPD", "AR"]
    assert lines[1].split()[0] == "1" and lines[2].split()[0] == "all"
    assert lines[2].split()[-1] == "1.000"
    report = json.loads((tmp_path / "gt_synth-test_scores.json").read_text())
    assert report["AR"] == 1.0 and report["metrics"] == ["vsd", "mssd", "mspd"]


def test_eval_metric_subset_and_json_path(dataset, tmp_path, capsys):
    csv = tmp_path / "r.csv"
    write_results(csv, gt_results(dataset))
    out_json = tmp_path / "sub" / "report.json"
    out_json.parent.mkdir()
    args = _parse(["eval", str(dataset), str(csv), "--metrics", "mssd", "--json", str(out_json)])
    args.run(args)
    assert capsys.readouterr().out.splitlines()[0].split() == ["object", "targets", "AR_MSSD", "AR"]
    assert json.loads(out_json.read_text())["metrics"] == ["mssd"]
