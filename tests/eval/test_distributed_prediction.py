"""Prediction split over ranks: shards, merging, and two gloo ranks under torchrun."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from poseflow.errors import RankFailedError, ValueRangeError
from poseflow.eval.distributed import (
    PredictionPart,
    image_seed,
    join_ranks,
    merge_parts,
    merge_results,
    merge_timers,
    shard_images,
)
from poseflow.eval.results import PoseResults
from poseflow.eval.timing import StageTimer

# ------------------------------------------------------------------------------ shards


@given(
    n=st.integers(0, 40),
    world=st.integers(1, 6),
    seed=st.integers(0, 2**31 - 1),
    equal=st.booleans(),
)
def test_shards_partition_the_images_and_balance_the_weights(n, world, seed, equal):
    g = torch.Generator().manual_seed(seed)
    keys = sorted({(int(s), int(i)) for s, i in torch.randint(0, 50, (n, 2), generator=g)})
    weights = None if equal else torch.randint(0, 9, (len(keys),), generator=g).tolist()
    shards = shard_images(keys, world, weights=weights)
    assert len(shards) == world
    assert sorted(k for s in shards for k in s) == keys  # every image once
    assert all(s == sorted(s) for s in shards)
    assert shards == shard_images(list(reversed(keys)), world, weights=_rev(weights))
    w = dict(zip(keys, [1] * len(keys) if weights is None else weights))
    loads = [sum(w[k] for k in s) for s in shards]
    if keys:  # greedy: no rank above the mean by more than the heaviest image
        assert max(loads) <= sum(loads) / world + max(w.values())
    if weights is None:  # equal weights: round-robin
        assert shards == [keys[r::world] for r in range(world)]


def _rev(weights):
    return None if weights is None else list(reversed(weights))


def test_heavy_images_are_spread():
    keys = [(0, i) for i in range(6)]
    shards = shard_images(keys, 3, weights=[9, 9, 9, 1, 1, 1])
    assert [sorted(w for w in s if w[1] < 3) for s in shards] == [[(0, 0)], [(0, 1)], [(0, 2)]]


@pytest.mark.parametrize(
    ("images", "world", "weights", "match"),
    [
        ([(0, 0)], 0, None, "world_size"),
        ([(0, 0), (0, 0)], 2, None, "repeat"),
        ([(0, 0)], 2, [1, 2], "2 weights for 1 images"),
        ([(0, 0)], 2, [-1], "non-negative"),
        ([(0, 0)], 2, [float("nan")], "non-negative"),
    ],
)
def test_bad_shards_are_refused(images, world, weights, match):
    with pytest.raises(ValueRangeError, match=match):
        shard_images(images, world, weights=weights)


def test_image_seeds_make_draws_independent_of_the_images_before():
    g = torch.Generator()
    draws = {}
    for order in ([(0, 1), (0, 2), (3, 4)], [(3, 4), (0, 2), (0, 1)]):
        for s, i in order:
            g.manual_seed(image_seed(7, s, i))
            draws.setdefault((s, i), []).append(torch.rand(4, generator=g))
    assert all(torch.equal(a, b) for a, b in draws.values())
    assert not torch.equal(draws[(0, 1)][0], draws[(0, 2)][0])
    seeds = {image_seed(seed, s, i) for seed in range(3) for s in range(5) for i in range(5)}
    assert len(seeds) == 75 and all(0 <= x < 2**63 for x in seeds)


# ------------------------------------------------------------------------------ merging


def _results(rows):
    """Results with one row per ``(scene, image, object)``, their values drawn from the ids."""
    n = len(rows)
    poses = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    ids = torch.tensor(rows, dtype=torch.float64).reshape(n, 3)
    poses[:, :3, 3] = ids / 10 + 0.5
    keys = [(s, i) for s, i, _ in rows]
    times = [0.1 * s + 0.01 * i for s, i in keys]
    return PoseResults.from_columns(
        [s for s, _, _ in rows],
        [i for _, i, _ in rows],
        [o for _, _, o in rows],
        [1 / (1 + o) for _, _, o in rows],
        poses,
        times,
    )


@given(seed=st.integers(0, 2**31 - 1), world=st.integers(1, 4))
def test_merged_parts_have_the_rows_of_one_process_in_its_order(seed, world):
    g = torch.Generator().manual_seed(seed)
    images = sorted({(int(s), int(i)) for s, i in torch.randint(0, 6, (8, 2), generator=g)})
    rows = []  # one process: images in sorted order, each image's rows as the estimator gave
    for s, i in images:
        k = int(torch.randint(1, 4, (), generator=g))
        rows += [(s, i, int(o)) for o in torch.randperm(9, generator=g)[:k] + 1]
    owner = torch.randint(0, world, (len(images),), generator=g).tolist()
    parts = [
        _results([r for r in rows if owner[images.index(r[:2])] == rank]) for rank in range(world)
    ]
    merged, single = merge_results(parts), _results(rows)
    for name in ("scene_ids", "im_ids", "obj_ids", "scores", "poses", "times"):
        assert torch.equal(getattr(merged, name), getattr(single, name)), name


def test_an_image_in_two_parts_is_refused():
    with pytest.raises(ValueRangeError, match="scene 0 image 1 has results in parts 0 and 1"):
        merge_results([_results([(0, 1, 2)]), _results([(0, 1, 3)])])


class _Clock:
    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


def _timed(timer, clock, images):
    for ms in images:
        with timer.image():
            clock.now += 0.001
            with timer.stage("icp"):
                clock.now += ms / 1000
            with timer.stage("segmentation"):
                clock.now += 0.05


def test_merged_timers_equal_one_timer_over_all_images():
    clock = _Clock()
    one = StageTimer(clock=clock, synchronize=False)
    _timed(one, clock, [3, 5, 9])
    ranks = [StageTimer(clock=clock, synchronize=False) for _ in range(2)]
    _timed(ranks[0], clock, [3, 9])
    _timed(ranks[1], clock, [5])
    merged = merge_timers(ranks)
    a, b = merged.breakdown(), one.breakdown()
    assert a["num_images"] == 3 and a.keys() == b.keys()
    for key in ("stages_ms", "percent", "excluded_ms"):
        assert a[key] == pytest.approx(b[key])
    assert a["total_ms"] == pytest.approx(b["total_ms"]) and merged.counts == one.counts
    with pytest.raises(ValueRangeError, match="exclude different stages"):
        merge_timers([one, StageTimer(excluded=())])
    with pytest.raises(ValueRangeError, match="no timer"):
        merge_timers([])


def test_merged_part_keeps_every_rank_in_order():
    parts = [
        PredictionPart(_results([(0, 2, 1)]), StageTimer(), 2, ["cuda:0"], [1], {"steps": 3}),
        PredictionPart(_results([(0, 1, 4)]), StageTimer(), 1, ["cuda:1"], [1], {"steps": 3}),
    ]
    m = merge_parts(parts)
    assert m.results.im_ids.tolist() == [1, 2] and m.instances == 3
    assert m.devices == ["cuda:0", "cuda:1"] and m.images == [1, 1] and m.config == {"steps": 3}
    with pytest.raises(ValueRangeError, match="no part"):
        merge_parts([])


# ------------------------------------------------------------------------------ the environment


def test_one_process_without_torchrun(monkeypatch):
    for name in ("WORLD_SIZE", "RANK", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        monkeypatch.delenv(name, raising=False)
    assert join_ranks("cpu") is None
    monkeypatch.setenv("WORLD_SIZE", "1")  # torchrun --nproc_per_node=1: one process too
    assert join_ranks("cpu") is None


def test_an_incomplete_environment_is_refused(monkeypatch):
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "0")
    monkeypatch.setenv("LOCAL_RANK", "0")
    monkeypatch.delenv("MASTER_ADDR", raising=False)
    monkeypatch.setenv("MASTER_PORT", "29500")
    with pytest.raises(ValueRangeError, match="MASTER_ADDR not set: start the job with torchrun"):
        join_ranks("cpu")
    monkeypatch.setenv("MASTER_ADDR", "127.0.0.1")
    monkeypatch.setenv("RANK", "2")
    with pytest.raises(ValueRangeError, match=r"RANK=2 is outside 0\.\.1"):
        join_ranks("cpu")
    monkeypatch.setenv("WORLD_SIZE", "two")
    with pytest.raises(ValueRangeError, match="not an integer"):
        join_ranks("cpu")


# ------------------------------------------------------------------------------ two gloo ranks

# Four runs in one job: all ranks succeed; rank 1 fails at once while rank 0 works through many
# images (it must stop early); rank 0 fails to finish; all succeed again.
JOB = textwrap.dedent(
    """
    import json, sys, time

    import torch

    from poseflow.errors import RankFailedError
    from poseflow.eval.distributed import PredictionPart, join_ranks
    from poseflow.eval.results import PoseResults
    from poseflow.eval.timing import StageTimer

    IMAGES = [(0, i) for i in range(5)] + [(2, i) for i in range(4)]
    WEIGHTS = [1 + (s + i) % 3 for s, i in IMAGES]


    def part(ranks, images):
        timer = StageTimer(synchronize=False)
        rows = []
        for s, i in images:
            ranks.check_peers()
            with timer.image():
                rows += [(s, i, 3 + (s + i) % 2), (s, i, 1)]
        n = len(rows)
        poses = torch.eye(4).repeat(n, 1, 1)
        poses[:, 2, 3] = torch.tensor([s + i / 10 for s, i, _ in rows])
        results = PoseResults.from_columns(
            *zip(*rows), [0.5] * n, poses, [0.1 * s for s, _, _ in rows]
        ) if rows else PoseResults.empty()
        return PredictionPart(results, timer, n, [str(ranks.device)], [timer.num_images])


    def summary(merged):
        r = merged.results
        return {
            "rows": list(zip(r.scene_ids.tolist(), r.im_ids.tolist(), r.obj_ids.tolist())),
            "z": r.poses[:, 2, 3].tolist(),
            "images": merged.timer.num_images,
            "images_per_rank": merged.images,
            "instances": merged.instances,
        }


    def fail_at_once_or_work_long(ranks, mine):
        if ranks.rank == 1:
            raise OSError("disk on fire")
        for _ in range(400):  # 10 s unless stopped
            ranks.check_peers()
            time.sleep(0.025)
        return part(ranks, mine)


    def cannot_write(merged):
        raise OSError("disk full")


    with join_ranks("cpu") as ranks, open(f"{sys.argv[1]}/rank{ranks.rank}.jsonl", "w") as out:
        mine = ranks.shard(IMAGES, WEIGHTS)
        runs = {
            "merge": (lambda: part(ranks, mine), summary),
            "work fails": (lambda: fail_at_once_or_work_long(ranks, mine), summary),
            "finish fails": (lambda: part(ranks, mine), cannot_write),
            "again": (lambda: part(ranks, mine), summary),
        }
        for name, (work, finish) in runs.items():
            start = time.perf_counter()
            try:
                line = {"value": ranks.run(work, finish)}
            except RankFailedError as exc:
                line = {"error": str(exc)}
            line.update(case=name, rank=ranks.rank, seconds=time.perf_counter() - start)
            print(json.dumps(line), file=out)
        print(json.dumps({"rank": ranks.rank, "threads": ranks.threads, "mine": mine}), file=out)
    """
)


def test_two_gloo_ranks_merge_stop_each_other_and_recover(tmp_path: Path) -> None:
    job = tmp_path / "job.py"
    job.write_text(JOB)
    env = {
        **os.environ,
        "OMP_NUM_THREADS": "8",
        "PYTHONPATH": str(Path(__file__).parents[2] / "src"),
    }
    for key in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        env.pop(key, None)
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2"]
    proc = subprocess.run(
        [*cmd, str(job), str(tmp_path)], env=env, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr[-4000:]
    lines = [json.loads(x) for r in (0, 1) for x in (tmp_path / f"rank{r}.jsonl").open()]
    runs = {(x["case"], x["rank"]): x for x in lines if "case" in x}
    info = {x["rank"]: x for x in lines if "threads" in x}

    images = [(0, i) for i in range(5)] + [(2, i) for i in range(4)]
    expected = [(s, i, o) for s, i in images for o in (3 + (s + i) % 2, 1)]
    for case in ("merge", "again"):
        merged = runs[(case, 0)]["value"]
        assert [tuple(r) for r in merged["rows"]] == expected  # one process's rows and order
        assert merged["z"] == pytest.approx([s + i / 10 for s, i, _ in expected])
        assert merged["images"] == 9 and merged["instances"] == 18
        assert merged["images_per_rank"] == [len(info[0]["mine"]), len(info[1]["mine"])]
        assert runs[(case, 1)]["value"] is None  # only rank 0 finishes
    assert sorted(map(tuple, info[0]["mine"] + info[1]["mine"])) == images

    cause = "rank 1 of 2 failed: disk on fire"
    assert runs[("work fails", 1)]["error"] == cause
    assert runs[("work fails", 0)]["error"] == f"rank 0 of 2 stopped: {cause}"
    assert runs[("work fails", 0)]["seconds"] < 5  # stopped between images, not after 400
    cause = "rank 0 of 2 failed: disk full"
    assert runs[("finish fails", 0)]["error"] == cause
    assert runs[("finish fails", 1)]["error"] == f"rank 1 of 2 stopped: {cause}"

    cores = len(os.sched_getaffinity(0))  # each rank: at most its share of the cores
    assert info[0]["threads"] == info[1]["threads"] == min(8, max(1, cores // 2))


def test_rank_failed_error_is_a_poseflow_error():
    from poseflow.errors import PoseflowError

    assert issubclass(RankFailedError, PoseflowError) and issubclass(RankFailedError, RuntimeError)
