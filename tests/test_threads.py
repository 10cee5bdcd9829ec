"""poseflow.set_num_threads: one count for torch, numba, BLAS/OpenMP and Open3D's ray casting."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numba
import pytest
import torch

import poseflow
from poseflow import _threads
from poseflow.errors import ValueRangeError

threadpoolctl = pytest.importorskip("threadpoolctl")

SRC = Path(__file__).resolve().parents[1] / "src"


@pytest.fixture(autouse=True)
def _restored():
    """Every test leaves the counts (and poseflow's setting) as it found them."""
    with poseflow.num_threads(torch.get_num_threads()):
        saved = _threads._requested
        _threads._requested = None
        yield
        _threads._requested = saved


def _blas_threads() -> set[int]:
    return {i["num_threads"] for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas"}


@pytest.mark.parametrize("n", [1, 2])
def test_setter_sets_every_pool(n):
    poseflow.set_num_threads(n)
    assert poseflow.get_num_threads() == n
    assert torch.get_num_threads() == n
    assert numba.get_num_threads() == min(n, numba.config.NUMBA_NUM_THREADS)
    assert _blas_threads() <= {n}


def test_setting_round_trips():
    poseflow.set_num_threads(2)
    poseflow.set_num_threads(1)
    assert (poseflow.get_num_threads(), torch.get_num_threads(), numba.get_num_threads()) == (
        1,
        1,
        1,
    )
    poseflow.set_num_threads(2)
    assert poseflow.get_num_threads() == torch.get_num_threads() == 2


def test_unset_setting_is_torchs_count():
    torch.set_num_threads(1)
    assert poseflow.get_num_threads() == 1


def test_context_restores_every_pool():
    poseflow.set_num_threads(2)
    before = (torch.get_num_threads(), numba.get_num_threads(), _blas_threads())
    with poseflow.num_threads(1):
        assert (poseflow.get_num_threads(), torch.get_num_threads()) == (1, 1)
        assert numba.get_num_threads() == 1 and _blas_threads() <= {1}
    assert (torch.get_num_threads(), numba.get_num_threads(), _blas_threads()) == before
    assert poseflow.get_num_threads() == 2


def test_more_threads_than_numba_has_are_capped_there():
    poseflow.set_num_threads(numba.config.NUMBA_NUM_THREADS + 1)
    assert torch.get_num_threads() == numba.config.NUMBA_NUM_THREADS + 1
    assert numba.get_num_threads() == numba.config.NUMBA_NUM_THREADS


@pytest.mark.parametrize("bad", [0, -1, 1.5, "2", None, True])
def test_bad_counts_are_clear_errors(bad):
    before = torch.get_num_threads()
    with pytest.raises(ValueRangeError, match="number of threads must be"):
        poseflow.set_num_threads(bad)
    with pytest.raises(ValueRangeError, match="number of threads must be"):
        with poseflow.num_threads(bad):
            pass
    assert torch.get_num_threads() == before


def test_default_rule_reads_omp_num_threads(monkeypatch):
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert _threads.default_num_threads() == 1
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert _threads.default_num_threads() == 3
    for bad in ("0", "two", "-2"):
        monkeypatch.setenv("OMP_NUM_THREADS", bad)
        with pytest.raises(ValueRangeError, match="OMP_NUM_THREADS"):
            _threads.default_num_threads()


class _Scene:
    """Stands in for an Open3D RaycastingScene: records the threads of each cast."""

    def __init__(self, scene):
        self.scene, self.nthreads = scene, []

    def cast_rays(self, rays, nthreads):
        self.nthreads.append(nthreads)
        return self.scene.cast_rays(rays, nthreads=nthreads)


def test_renderer_casts_with_the_setting():
    o3d = pytest.importorskip("open3d")
    from poseflow.render import Renderer

    box = o3d.geometry.TriangleMesh.create_box(0.1, 0.1, 0.1).translate((-0.05, -0.05, -0.05))
    K = torch.tensor([[100.0, 0, 16], [0, 100.0, 12], [0, 0, 1]])
    pose = torch.eye(4)
    pose[2, 3] = 0.5
    follows, fixed = Renderer([box]), Renderer([box], nthreads=3)
    assert follows.nthreads is None
    for r in (follows, fixed):
        r._scenes = [_Scene(s) for s in r._scenes]
    for n in (1, 2):
        poseflow.set_num_threads(n)
        for r in (follows, fixed):
            assert r.render(pose[None], K, 32, 24).instance[12, 16].item() == 0
    assert follows._scenes[0].nthreads == [1, 2]
    assert fixed._scenes[0].nthreads == [3, 3]


def test_import_is_cheap_and_numba_start_keeps_the_setting():
    """``import poseflow`` loads neither torch nor numba; numba's pool started later (umap-learn
    does) leaves torch's count alone, where it would reset it to NUMBA_NUM_THREADS."""
    code = (
        "import json, sys, poseflow\n"
        "lazy = not {'torch', 'numba'} & set(sys.modules)\n"
        "import torch\n"
        "torch.get_num_threads()\n"  # without poseflow's setter, the start below would reset it
        "poseflow.set_num_threads(1)\n"
        "import numba\n"
        "numba.np.ufunc.parallel._launch_threads()\n"
        "print(json.dumps([lazy, torch.get_num_threads(), numba.get_num_threads()]))\n"
    )
    env = {**os.environ, "PYTHONPATH": str(SRC), "NUMBA_NUM_THREADS": "3", "OMP_NUM_THREADS": "1"}
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    )
    assert json.loads(out.stdout.splitlines()[-1]) == [True, 1, 1]
