from __future__ import annotations

import argparse
import json

import open3d as o3d
import pytest

from poseflow.cli import add_command
from poseflow.data.synthetic import generate_dataset
from poseflow.eval.evaluate import gt_results
from poseflow.eval.results import write_results


def _parse(argv):
    parser = argparse.ArgumentParser(prog="poseflow")
    add_command(parser.add_subparsers(dest="command"), "eval")
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


def test_a_missing_results_file_is_a_failed_run(dataset, tmp_path, capsys):
    from poseflow.cli import main

    assert main(["eval", str(dataset), str(tmp_path / "none.csv")]) == 1
    err = capsys.readouterr().err
    assert "none.csv does not exist" in err and "--run-baseline" in err


def test_bad_rows_name_file_and_line_and_a_bom_is_read(dataset, tmp_path, capsys):
    from poseflow.cli import main

    csv = tmp_path / "r.csv"
    write_results(csv, gt_results(dataset))
    lines = csv.read_text().splitlines()
    csv.write_bytes(("\ufeff" + "\r\n".join(lines) + "\r\n").encode("utf-8"))  # a spreadsheet's
    assert main(["eval", str(dataset), str(csv), "--metrics", "mssd", "-q"]) == 0
    assert "report written to" in capsys.readouterr().out
    fields = lines[1].split(",")
    fields[4] = "0 0 0 0 0 0 0 0 0"
    csv.write_text("\n".join([lines[0], ",".join(fields), *lines[2:]]) + "\n")
    assert main(["eval", str(dataset), str(csv), "--metrics", "mssd", "-q"]) == 1
    assert f"{csv}:2: R is not a rotation" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["eval", str(dataset), str(csv), "--progress"])  # the flag is --no-progress now
    assert main(["eval", str(dataset), str(csv), "--metrics", "add"]) == 2


def test_run_baseline_does_not_overwrite_without_asking(dataset, tmp_path, capsys):
    from poseflow.cli import main

    csv = tmp_path / "mine.csv"
    csv.write_text("my own results\n")
    assert main(["eval", str(dataset), str(csv), "--run-baseline", "--no-progress"]) == 1
    assert "pass --overwrite" in capsys.readouterr().err
    assert csv.read_text() == "my own results\n"


def test_warnings_print_as_one_line(dataset, tmp_path):
    import subprocess
    import sys

    res = gt_results(dataset)
    res.obj_ids[:] = 9  # no model
    csv = tmp_path / "r.csv"
    write_results(csv, res)
    proc = subprocess.run(
        [sys.executable, "-m", "poseflow.cli", "eval", str(dataset), str(csv), "--metrics",
         "mssd", "--quiet"],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    warning = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(warning) == 1 and warning[0].startswith("warning: 2 results rows name objects")
