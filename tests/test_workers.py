"""``poseflow._workers``: items mapped over forked processes of one thread, in order."""

from __future__ import annotations

import os

import pytest
import torch

from poseflow._workers import check_workers, map_forked
from poseflow.errors import UnitsError, ValueRangeError


def test_items_come_back_in_order_from_other_processes():
    parent = os.getpid()
    out = list(map_forked(lambda n: (n * n, os.getpid(), torch.get_num_threads()), 7, workers=2))
    assert [v for v, _, _ in out] == [n * n for n in range(7)]
    assert all(pid != parent for _, pid, _ in out)  # estimated in the workers
    assert {threads for _, _, threads in out} == {1}


def test_one_worker_or_one_item_runs_here():
    parent = os.getpid()
    assert list(map_forked(lambda n: os.getpid(), 3, workers=1)) == [parent] * 3
    assert list(map_forked(lambda n: os.getpid(), 1, workers=4)) == [parent]
    assert list(map_forked(lambda n: n, 0, workers=2)) == []


def test_a_workers_error_is_raised_here_with_its_type():
    def task(n):
        if n == 3:
            raise UnitsError(f"image {n}: depth in millimetres")
        return n

    with pytest.raises(UnitsError, match="image 3"):
        list(map_forked(task, 5, workers=2))


def test_what_a_worker_changes_stays_in_the_worker():
    seen = []
    results = list(map_forked(lambda n: seen.append(n) or len(seen), 4, workers=2))
    assert seen == [] and all(r >= 1 for r in results)


@pytest.mark.parametrize("bad", [0, -1, 1.5, True, "2"])
def test_bad_worker_counts_are_refused(bad):
    with pytest.raises(ValueRangeError, match="workers"):
        check_workers(bad)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_workers_are_refused_once_cuda_is_initialised():
    torch.zeros(1, device="cuda")
    with pytest.raises(ValueRangeError, match="CUDA"):
        check_workers(2)
    assert check_workers(1) == 1


def test_a_worker_does_not_inherit_the_parents_knn_threads():
    from poseflow import num_threads
    from poseflow.geometry import neighbors

    with num_threads(2):
        assert neighbors._pool().submit(int, "7").result() == 7  # the parent's threads started
    assert neighbors._POOLS  # a pool whose threads a forked child would not have
    assert list(map_forked(lambda n: len(neighbors._POOLS), 2, workers=2)) == [0, 0]
