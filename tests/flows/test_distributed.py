"""DDP: two CPU processes under torchrun (gloo) against one process with the doubled batch."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from poseflow.errors import ValueRangeError
from poseflow.flows.distributed import (
    DistributedContext,
    all_reduce_mean,
    barrier,
    destroy_distributed,
    init_distributed,
    main_rank_succeeded,
)

# The job a user would launch with `torchrun --nproc_per_node=K job.py OUT BATCH`: nothing in it
# is specific to the number of processes.
JOB = textwrap.dedent(
    '''
    """Train a tiny conditional velocity model; every rank saves its final weights."""
    import sys

    import torch
    from safetensors.torch import save_file

    from poseflow.flows import CFMTrainer, TrainConfig, destroy_distributed


    class Net(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.inp = torch.nn.Linear(3 + 1 + 4, 32)
            self.out = torch.nn.Linear(32, 3)

        def forward(self, *, x, t, condition, mask=None):
            h = torch.cat([x, t[:, None, None].expand(*x.shape[:2], 1), condition], -1)
            return self.out(torch.tanh(self.inp(h)))


    class Points(torch.utils.data.Dataset):
        def __init__(self, n=32):
            g = torch.Generator().manual_seed(7)
            self.x = torch.randn(n, 10, 3, generator=g)
            self.c = torch.randn(n, 10, 4, generator=g)
            # the same number of valid points in every sample: the per-rank masked means then
            # average to the global one (see CFMTrainer's docstring)
            self.m = torch.arange(10).expand(n, 10) < 8

        def __len__(self):
            return len(self.x)

        def __getitem__(self, i):
            return {"x_1": self.x[i], "condition": self.c[i], "mask": self.m[i]}


    def main(out_dir, batch_size, steps=6):
        torch.manual_seed(0)
        cfg = TrainConfig(steps=steps, batch_size=batch_size, warmup_steps=2, lr=1e-2,
                          log_every=2, progress=False, ema_decay=0.9, seed=3)
        trainer = CFMTrainer(Net(), Points(), config=cfg, out_dir=out_dir, device="cpu")
        trainer.fit()
        state = {k: v.contiguous() for k, v in trainer.model.state_dict().items()}
        save_file(state, f"{out_dir}/weights-rank{trainer.ctx.rank}.safetensors")
        return trainer


    if __name__ == "__main__":
        main(sys.argv[1], int(sys.argv[2]))
        destroy_distributed()
    '''
)


def _load_job(path: Path):
    spec = importlib.util.spec_from_file_location("poseflow_ddp_job", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_two_gloo_ranks_match_one_process_with_the_doubled_batch(tmp_path: Path) -> None:
    job = tmp_path / "job.py"
    job.write_text(JOB)
    ddp_dir, single_dir = tmp_path / "ddp", tmp_path / "single"
    ddp_dir.mkdir()
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    for key in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        env.pop(key, None)
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2"]
    proc = subprocess.run(
        [*cmd, str(job), str(ddp_dir), "4"], env=env, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr[-4000:]

    rank0 = load_file(ddp_dir / "weights-rank0.safetensors")
    rank1 = load_file(ddp_dir / "weights-rank1.safetensors")
    assert rank0.keys() == rank1.keys()
    for k in rank0:
        assert torch.equal(rank0[k], rank1[k]), k

    reference = _load_job(job).main(str(single_dir), 8)
    assert reference.ctx.world_size == 1
    single = reference.model.state_dict()
    moved = 0.0
    for k in rank0:
        assert torch.allclose(rank0[k], single[k], atol=1e-5, rtol=1e-4), k
        moved += float((rank0[k] - reference.ema_model.state_dict()[k]).abs().sum())
    assert moved > 0  # the EMA lags the weights: training did move them

    # rank 0 alone logged and checkpointed: one record per log step, one checkpoint
    records = [json.loads(x) for x in (ddp_dir / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records] == [2, 4, 6]
    assert sorted(p.name for p in ddp_dir.glob("step-*")) == [
        "step-00000006.json",
        "step-00000006.safetensors",
    ]
    meta = json.loads((ddp_dir / "step-00000006.json").read_text())
    assert meta["world_size"] == 2
    single_records = [
        json.loads(x) for x in (single_dir / "metrics.jsonl").read_text().splitlines()
    ]
    for a, b in zip(records, single_records):
        assert abs(a["loss"] - b["loss"]) < 1e-5 * max(1.0, abs(b["loss"]))


def test_single_process_context(monkeypatch: pytest.MonkeyPatch) -> None:
    for key in ("RANK", "WORLD_SIZE", "LOCAL_RANK"):
        monkeypatch.delenv(key, raising=False)
    ctx = init_distributed(device="cpu")
    assert ctx == DistributedContext(device=torch.device("cpu"))
    assert ctx.is_main and not ctx.is_distributed
    x = torch.tensor([1.0, 3.0])
    reduced = all_reduce_mean(x, ctx)
    assert torch.equal(reduced, x) and reduced is not x
    barrier(ctx)
    destroy_distributed()


def test_malformed_environment_raises(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("WORLD_SIZE", "two")
    with pytest.raises(ValueRangeError):
        init_distributed(device="cpu")
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "5")
    with pytest.raises(ValueRangeError):
        init_distributed(device="cpu")


OUTCOME_JOB = textwrap.dedent(
    """
    import sys

    from poseflow.flows import destroy_distributed, init_distributed, main_rank_succeeded

    ctx = init_distributed(device="cpu")
    first = main_rank_succeeded(ctx, True)
    second = main_rank_succeeded(ctx, not ctx.is_main)  # rank 0 fails, the others "succeed"
    print(f"rank {ctx.rank}: {first} {second}", flush=True)
    destroy_distributed()
    """
)


@pytest.mark.slow
def test_every_rank_learns_the_main_ranks_outcome(tmp_path: Path) -> None:
    job = tmp_path / "outcome.py"
    job.write_text(OUTCOME_JOB)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    for key in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        env.pop(key, None)
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2"]
    proc = subprocess.run([*cmd, str(job)], env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-4000:]
    assert "rank 0: True False" in proc.stdout and "rank 1: True False" in proc.stdout


def test_single_process_outcome_is_its_own() -> None:
    assert main_rank_succeeded(DistributedContext(), True)
    assert not main_rank_succeeded(DistributedContext(), False)
