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


def test_a_byte_order_mark_and_windows_line_ends_are_accepted(tmp_path):
    path = tmp_path / "bom.csv"
    row = "1,0,5,0.5,1 0 0 0 1 0 0 0 1,10 20 500,0.25"
    path.write_bytes(("\ufeff" + HEADER + "\r\n" + row + "\r\n").encode("utf-8"))
    back = read_results(path)
    assert back.obj_ids.tolist() == [5] and back.poses[0, 2, 3].item() == pytest.approx(0.5)


@pytest.mark.parametrize(
    ("line", "match"),
    [
        ("1,0,5,high,1 0 0 0 1 0 0 0 1,0 0 500,1", r"r\.csv:3: score 'high' is not a number"),
        ("1,0,x,0.5,1 0 0 0 1 0 0 0 1,0 0 500,1", r"r\.csv:3: obj_id 'x' is not an integer"),
        ("1,0,5,0.5,0 0 0 0 0 0 0 0 0,0 0 500,1", r"r\.csv:3: R is not a rotation"),
        ("1,0,5,0.5,2 0 0 0 2 0 0 0 2,0 0 500,1", r"r\.csv:3: R is not a rotation"),
        ("1,0,5,0.5,1 0 0 0 1 0 0 0 -1,0 0 500,1", r"r\.csv:3: R is a reflection \(det -1\)"),
    ],
)
def test_bad_lines_are_named_by_file_and_line(tmp_path, line, match):
    from poseflow.errors import ResultsFormatError

    path = tmp_path / "r.csv"
    path.write_text(HEADER + "\n1,0,4,0.5,1 0 0 0 1 0 0 0 1,0 0 500,1\n" + line + "\n")
    with pytest.raises(ResultsFormatError, match=match):
        read_results(path)


def test_rotations_written_with_four_decimals_are_accepted(tmp_path):
    from poseflow.geometry.se3 import random_transform

    R = random_transform(1, generator=torch.Generator().manual_seed(3), dtype=torch.float64)[0]
    text = " ".join(f"{x:.4f}" for x in R[:3, :3].reshape(-1).tolist())
    path = tmp_path / "r.csv"
    path.write_text(HEADER + f"\n1,0,4,0.5,{text},0 0 500,1\n")
    assert len(read_results(path)) == 1


def test_a_missing_file_says_how_to_make_one(tmp_path):
    from poseflow.errors import MissingFileError

    with pytest.raises(MissingFileError, match="poseflow predict"):
        read_results(tmp_path / "none.csv")


def test_the_file_is_written_aside_and_renamed(tmp_path, monkeypatch):
    path = tmp_path / "r.csv"
    path.write_text("an earlier run\n")
    r = _results()

    def interrupted(src, dst):
        assert path.read_text() == "an earlier run\n"  # untouched until the rename
        assert read_results(src).obj_ids.tolist() == r.obj_ids.tolist()  # complete aside
        raise KeyboardInterrupt

    monkeypatch.setattr("poseflow.eval.results.os.replace", interrupted)
    with pytest.raises(KeyboardInterrupt):
        write_results(path, r)
    assert [p.name for p in tmp_path.iterdir()] == ["r.csv"]  # no temporary file left
    assert path.read_text() == "an earlier run\n"
    monkeypatch.undo()
    write_results(path, r)
    assert [p.name for p in tmp_path.iterdir()] == ["r.csv"]
    assert torch.equal(read_results(path).obj_ids, r.obj_ids)


def test_exact_duplicate_lines_are_named_in_a_warning(tmp_path, recwarn):
    path = tmp_path / "dup.csv"
    rows = [
        "1,0,5,0.5,1 0 0 0 1 0 0 0 1,10 20 500,0.25",
        "1,0,6,0.4,1 0 0 0 1 0 0 0 1,0 0 400,0.25",
    ]
    path.write_text("\n".join([HEADER, *rows]) + "\n")
    read_results(path)
    assert not recwarn.list  # distinct lines: no word
    path.write_text("\n".join([HEADER, *rows, rows[0], rows[0]]) + "\n")
    repeat = r"2 line\(s\) repeat an earlier one exactly \(line 4 is line 2\)"
    with pytest.warns(UserWarning, match=repeat):
        back = read_results(path)
    assert len(back) == 4  # still read as written: BOP's rule scores them
