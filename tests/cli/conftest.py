"""Fixtures of the command-line tests."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[2] / "src"


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
