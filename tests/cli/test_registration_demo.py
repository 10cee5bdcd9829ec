"""``poseflow demo registration``: the registration demo runs end to end on a tiny setting."""

from __future__ import annotations

import argparse

import pytest

from poseflow.cli import add_command
from poseflow.cli import registration_demo as demo
from poseflow.errors import ValueRangeError


def _parse(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="poseflow")
    add_command(parser.add_subparsers(dest="command"), "demo")
    return parser.parse_args(["demo", "registration", *argv])


TINY = ("--instances", "2", "--points", "150", "--model-points", "1000", "--iterations", "200",
        "--flow-noise", "0.002")  # fmt: skip


@pytest.mark.parametrize("open3d", [False, True])
def test_demo_runs_and_prints_a_table(capsys, open3d):
    args = _parse(*TINY, *(() if open3d else ("--no-open3d",)))
    assert args.run(args) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert "2 objects, 150 correspondences" in lines[0]
    rows = [line.split() for line in lines[2:4]]
    assert [row[0] for row in rows] == ["0", "1"]
    # RANSAC then ICP recover the generated poses to a few degrees at most (small clouds).
    assert all(float(row[2]) < 2.0 and float(row[4]) < 3.0 for row in rows), out
    assert ("Open3D" in out) == open3d
    assert "median rotation error" in out and "time for all 2" in out


def test_scenes_are_consistent():
    scenes = demo.make_scenes(3, 100, model_points=300, outliers=0.3, noise=0.0, seed=1)
    assert scenes.observed.shape == scenes.predicted.shape == (3, 100, 3)
    assert scenes.model.shape == (3, 300, 3) and scenes.pose.shape == (3, 4, 4)
    assert (scenes.outlier.sum(-1) == 30).all()
    # Without noise, the inlier predictions are exactly the observations in the object frame.
    from poseflow.geometry.se3 import inverse_transform, transform_points

    back = transform_points(inverse_transform(scenes.pose), scenes.observed)
    good = ~scenes.outlier
    assert (back - scenes.predicted)[good].abs().max() < 1e-9
    assert (back - scenes.predicted)[~good].norm(dim=-1).median() > 0.01


def test_bad_arguments_raise():
    with pytest.raises(ValueRangeError):
        demo.run(_parse("--instances", "0"))
