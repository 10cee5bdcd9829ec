"""``poseflow predict`` under ``torchrun``: two gloo ranks write the CSV of one process.

The tests that start two processes, each loading the estimator (30-60 s on two busy cores), run
with ``make test-slow``; the protocol itself (merging, stopping, recovering) is tested with two
gloo ranks in ``make test`` by ``tests/eval/test_distributed_prediction.py``.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch

from poseflow.cli import main
from poseflow.cli.predict import select_targets
from poseflow.data.bop import BOPDataset
from poseflow.data.synthetic import generate_dataset
from poseflow.eval.distributed import shard_images
from poseflow.eval.results import HEADER, read_results


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("bop") / "ds"
    return generate_dataset(
        root,
        num_train_images=0,
        num_test_images=3,
        objects_per_image=2,
        width=160,
        height=120,
        progress=False,
    )


@pytest.fixture
def one_thread():
    """The reference process runs on one thread, as each rank does here."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _rows(path: Path) -> list[list[str]]:
    """The CSV's fields but the time, as written (scene, image, object, score, R, t)."""
    lines = path.read_text().splitlines()
    assert lines[0] == HEADER
    return [line.split(",")[:6] for line in lines[1:]]


def test_an_image_has_the_same_estimate_whatever_images_precede_it(dataset, tmp_path):
    targets = json.loads((dataset / "test_targets_bop19.json").read_text())
    last = max((t["scene_id"], t["im_id"]) for t in targets)
    alone = tmp_path / "last.json"
    alone.write_text(json.dumps([t for t in targets if (t["scene_id"], t["im_id"]) == last]))
    argv = ["predict", str(dataset), "--model", "demo", "--no-progress", "--hypotheses", "2"]
    assert main([*argv, "--out", str(tmp_path / "all.csv")]) == 0
    assert main([*argv, "--targets", str(alone), "--out", str(tmp_path / "last.csv")]) == 0
    after_others = [r for r in _rows(tmp_path / "all.csv") if (int(r[0]), int(r[1])) == last]
    assert len(after_others) == 2 and after_others == _rows(tmp_path / "last.csv")


@pytest.mark.slow
@pytest.mark.parametrize("method", ["baseline", "funflow6d"])
def test_two_ranks_write_the_csv_of_one_process(
    dataset, tmp_path, capsys, one_thread, method, torchrun
):
    chosen = ["--method", "baseline"] if method == "baseline" else ["--model", "demo"]
    argv = ["predict", str(dataset), *chosen, "--no-progress"]
    one, split = tmp_path / "one" / "r.csv", tmp_path / "split" / "r.csv"
    assert main([*argv, "--out", str(one), "--timing", str(one.with_suffix(".json"))]) == 0
    capsys.readouterr()
    proc = torchrun([*argv, "--out", str(split), "--timing", str(split.with_suffix(".json"))])
    assert proc.returncode == 0, proc.stderr[-4000:]
    assert proc.stdout.count("poses (") == 1 and "by 2 processes" in proc.stdout
    assert "rank 0 of 2: " in proc.stderr and "rank 1 of 2: " in proc.stderr

    rows = _rows(split)
    assert len(rows) >= 4 and rows == _rows(one)  # row for row, in the same order
    a, b = read_results(one), read_results(split)
    assert a.image_times().keys() == b.image_times().keys()
    assert all(t > 0 for t in b.image_times().values())  # every image keeps its own time
    assert sorted(p.name for p in split.parent.iterdir()) == ["r.csv", "r.json"]

    report, single = (
        json.loads(split.with_suffix(".json").read_text()),
        json.loads(one.with_suffix(".json").read_text()),
    )
    assert report["ranks"] == 2 and report["devices"] == ["cpu", "cpu"]
    assert report["num_images"] == single["num_images"] == 3
    assert sorted(report["images_per_rank"]) == [1, 2]
    assert report["stages_ms"].keys() == single["stages_ms"].keys()
    assert report["stages_ms"]["icp"] > 0 and report["verification"] is True
    assert report.get("config") == single.get("config")


@pytest.mark.slow
def test_a_failing_rank_stops_every_rank_and_writes_no_csv(dataset, tmp_path, torchrun):
    bad = tmp_path / "bad"
    shutil.copytree(dataset, bad)
    ds = BOPDataset(bad, "test")
    weights: dict[tuple[int, int], int] = {}
    for t in select_targets(ds, targets=True):
        weights[(t.scene_id, t.im_id)] = weights.get((t.scene_id, t.im_id), 0) + t.inst_count
    s, i = shard_images(list(weights), 2, weights=list(weights.values()))[1][0]
    depth = ds.scene(s).depth_path(i)
    depth.write_bytes(b"not an image")  # rank 1 cannot read one of its images
    out = tmp_path / "out" / "r.csv"
    argv = ["predict", str(bad), "--model", "demo", "--out", str(out), "--no-progress"]
    proc = torchrun(argv)
    assert proc.returncode != 0
    cause = f"rank 1 of 2 failed: cannot identify image file '{depth}'"
    assert f"poseflow predict: error: rank 0 of 2 stopped: {cause}" in proc.stderr
    assert cause in proc.stderr.replace(f"rank 0 of 2 stopped: {cause}", "")  # rank 1's own
    assert list(out.parent.iterdir()) == []  # no CSV, no temporary file
