"""Shared fixtures: devices, dtypes, tolerances, the hypothesis profile and a torchrun runner."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from hypothesis import HealthCheck, settings

settings.register_profile(
    "ci",
    derandomize=True,
    deadline=None,
    max_examples=25,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.differing_executors],
)
settings.register_profile("dev", deadline=None, max_examples=50)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))

DEVICES = ["cpu"] + (["cuda:0"] if torch.cuda.is_available() else [])
DTYPES = [torch.float32, torch.float64]

#: Absolute tolerance of exact-in-theory results, keyed by dtype.
TOL = {torch.float32: 1e-4, torch.float64: 1e-9}


@pytest.fixture(params=DEVICES)
def device(request: pytest.FixtureRequest) -> torch.device:
    return torch.device(request.param)


@pytest.fixture(params=DTYPES, ids=["float32", "float64"])
def dtype(request: pytest.FixtureRequest) -> torch.dtype:
    return request.param


@pytest.fixture
def tol(dtype: torch.dtype) -> float:
    return TOL[dtype]


@pytest.fixture(scope="session")
def o3d():
    """Open3D, for tests that compare with it (skipped on machines without it, e.g. GPU hosts)."""
    return pytest.importorskip("open3d")


SRC = Path(__file__).resolve().parents[1] / "src"


def _run_torchrun(argv: list[str], *, timeout: float = 400) -> subprocess.CompletedProcess:
    """``torchrun --standalone --nproc_per_node=2 -m poseflow.cli ARGV``, one OpenMP thread per
    rank, this checkout's sources first; torchrun and its workers are killed after ``timeout``."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(SRC)}
    for key in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        env.pop(key, None)
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2"]
    proc = subprocess.Popen(
        [*cmd, "-m", "poseflow.cli", *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        start_new_session=True,
    )
    try:
        stdout, stderr = proc.communicate(timeout=timeout)
    finally:
        if proc.poll() is None:  # timed out: stop torchrun and its workers
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    return subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr)


@pytest.fixture
def torchrun() -> Callable[..., subprocess.CompletedProcess]:
    """Run a ``poseflow`` command on two ranks: ``torchrun(argv, timeout=400)``."""
    return _run_torchrun


@pytest.fixture(scope="module")
def box_frame_files(tmp_path_factory):
    """A generated frame of one box: the paths ``estimate`` takes, and its ground truth."""
    import open3d as o3d

    from poseflow.data.bop import BOPDataset
    from poseflow.data.synthetic import generate_dataset

    box = o3d.geometry.TriangleMesh.create_box(0.1, 0.07, 0.05).translate((-0.05, -0.035, -0.025))
    root = generate_dataset(
        tmp_path_factory.mktemp("frame") / "ds", [box], num_train_images=0, num_test_images=1,
        objects_per_image=1, distractors_per_image=0, width=160, height=120, progress=False,
        seed=3,
    )  # fmt: skip
    scene = root / "test" / "000000"
    gt = BOPDataset(root, "test").scene(0).gt_of(0)[0]
    return {
        "root": root,
        "rgb": scene / "rgb" / "000000.png",
        "depth": scene / "depth" / "000000.png",
        "camera": scene / "scene_camera.json",
        "mask": scene / "mask_visib" / "000000_000000.png",
        "mesh": root / "models" / "obj_000001.ply",  # in mm, as BOP models are
        "pose": gt.pose,
    }
