from __future__ import annotations

import pytest
import torch

from poseflow.errors import ShapeError, ValueRangeError
from poseflow.eval.results import HEADER, PoseResults, read_results, write_results
from poseflow.geometry.se3 import random_transform


def _results(n: int = 5, seed: int = 0) -> PoseResults:
    gen = torch.Generator().manual_seed(seed)
    poses = random_transform(n, generator=gen, dtype=torch.float64)
    scenes = [1] * n
    ims = [i // 2 for i in range(n)]
    times = [0.1 * (i // 2 + 1) for i in range(n)]
    scores = torch.rand(n, generator=gen, dtype=torch.float64)
    return PoseResults.from_columns(scenes, ims, list(range(1, n + 1)), scores, poses, times)


def test_round_trip(tmp_path):
    r = _results()
    path = tmp_path / "method_dataset-test.csv"
    write_results(path, r)
    back = read_results(path)
    assert len(back) == len(r)
    for name in ("scene_ids", "im_ids", "obj_ids"):
        assert torch.equal(getattr(back, name), getattr(r, name))
    assert torch.equal(back.scores, r.scores)
    assert torch.equal(back.times, r.times)
    torch.testing.assert_close(back.poses, r.poses, atol=1e-15, rtol=0)
    assert torch.equal(back.poses[:, :3, :3], r.poses[:, :3, :3])


def test_file_layout_is_bop19(tmp_path):
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    T[:3, 3] = torch.tensor([0.1, -0.02, 0.5])
    path = tmp_path / "r.csv"
    write_results(path, PoseResults.from_columns([2], [7], [3], [0.5], T[None], [1.5]))
    lines = path.read_text().splitlines()
    assert lines[0] == HEADER == "scene_id,im_id,obj_id,score,R,t,time"
    fields = lines[1].split(",")
    assert fields[:4] == ["2", "7", "3", "0.5"]
    assert [float(x) for x in fields[4].split()] == [0, -1, 0, 1, 0, 0, 0, 0, 1]  # row-major
    assert [float(x) for x in fields[5].split()] == pytest.approx([100.0, -20.0, 500.0])  # mm
    assert float(fields[6]) == 1.5


def test_one_time_per_image(tmp_path):
    r = PoseResults.from_columns(
        [1, 1], [0, 0], [1, 2], [1.0, 1.0], torch.eye(4).repeat(2, 1, 1), [0.2, 0.3]
    )
    with pytest.raises(ValueRangeError):
        write_results(tmp_path / "r.csv", r)
    ok = PoseResults.from_columns(
        [1, 1, 1], [0, 0, 1], [1, 2, 1], [1.0] * 3, torch.eye(4).repeat(3, 1, 1), [0.2, 0.2, 0.4]
    )
    assert ok.image_times() == {(1, 0): 0.2, (1, 1): 0.4}
    assert ok.average_time() == pytest.approx(0.3)
    assert PoseResults.from_columns([1], [0], [1], [1.0], torch.eye(4)[None]).average_time() == -1.0


def test_reader_rejects_bad_files(tmp_path):
    bad_header = tmp_path / "a.csv"
    bad_header.write_text("scene_id,im_id,obj_id,score,R,t\n")
    with pytest.raises(ValueRangeError):
        read_results(bad_header)
    short = tmp_path / "b.csv"
    short.write_text(HEADER + "\n1,0,5,0.5,1 0 0 0 1 0 0 0 1,0 0 0\n")
    with pytest.raises(ValueRangeError):
        read_results(short)
    bad_r = tmp_path / "c.csv"
    bad_r.write_text(HEADER + "\n1,0,5,0.5,1 0 0 0 1 0 0 0,0 0 0,1\n")
    with pytest.raises(ValueRangeError):
        read_results(bad_r)
    nan = tmp_path / "d.csv"
    nan.write_text(HEADER + "\n1,0,5,nan,1 0 0 0 1 0 0 0 1,0 0 0,1\n")
    with pytest.raises(ValueRangeError):
        read_results(nan)
    times = tmp_path / "e.csv"
    times.write_text(
        HEADER + "\n1,0,5,1,1 0 0 0 1 0 0 0 1,0 0 0,1\n1,0,6,1,1 0 0 0 1 0 0 0 1,0 0 0,2\n"
    )
    with pytest.raises(ValueRangeError):
        read_results(times)


def test_empty_and_concat(tmp_path):
    path = tmp_path / "empty.csv"
    write_results(path, PoseResults.empty())
    assert path.read_text() == HEADER + "\n"
    assert len(read_results(path)) == 0
    both = PoseResults.concat([_results(2, 0), _results(3, 1)])
    assert len(both) == 5 and both.poses.shape == (5, 4, 4)


def test_columns_must_agree():
    with pytest.raises(ShapeError):
        PoseResults.from_columns([1, 2], [0], [1], [1.0], torch.eye(4)[None])
    with pytest.raises(ValueRangeError):
        PoseResults.from_columns([1], [0], [1], [float("nan")], torch.eye(4)[None])
