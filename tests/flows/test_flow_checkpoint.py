"""Checkpoint files: atomic writes, pruning, optimiser flattening, loading without pickle."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from poseflow.errors import MissingWeightsError, ShapeError
from poseflow.flows.checkpoint import (
    atomic_write,
    flatten_optimizer_state,
    latest_checkpoint,
    load_checkpoint,
    prune_checkpoints,
    save_checkpoint,
    unflatten_optimizer_state,
)


def test_round_trip_with_shared_storage(tmp_path: Path) -> None:
    w = torch.randn(4, 3)
    tensors = {"a": w, "b": w, "c": w[1:], "d": torch.arange(5)}
    path = save_checkpoint(tmp_path, 12, tensors, {"cfg": {"lr": 0.1}})
    assert path.name == "step-00000012.json"
    loaded, meta = load_checkpoint(tmp_path)
    for k, v in tensors.items():
        assert torch.equal(loaded[k], v)
    assert meta == {"cfg": {"lr": 0.1}, "step": 12, "tensors": "step-00000012.safetensors"}
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "step-00000012.json",
        "step-00000012.safetensors",
    ]


def test_failed_write_leaves_the_old_file(tmp_path: Path) -> None:
    target = tmp_path / "f.txt"
    target.write_text("old")

    def broken(tmp: str) -> None:
        Path(tmp).write_text("partial")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError):
        atomic_write(target, broken)
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["f.txt"]


def test_latest_and_prune(tmp_path: Path) -> None:
    assert latest_checkpoint(tmp_path / "missing") is None
    for step in (3, 10, 7):
        save_checkpoint(tmp_path, step, {"x": torch.zeros(1)}, {})
    (tmp_path / "notes.json").write_text("{}")
    assert latest_checkpoint(tmp_path).name == "step-00000010.json"
    prune_checkpoints(tmp_path, keep=2)
    assert sorted(p.name for p in tmp_path.glob("step-*")) == [
        "step-00000007.json",
        "step-00000007.safetensors",
        "step-00000010.json",
        "step-00000010.safetensors",
    ]


def test_optimizer_state_round_trip_continues_identically() -> None:
    def make():
        torch.manual_seed(0)
        p = torch.nn.Parameter(torch.randn(5))
        return p, torch.optim.AdamW([p], lr=0.1, betas=(0.8, 0.95), amsgrad=True)

    p, opt = make()
    for _ in range(3):
        p.grad = p.detach() ** 2
        opt.step()
    tensors, meta = flatten_optimizer_state(opt.state_dict())
    tensors = {k: v.clone() for k, v in tensors.items()}  # as if read from disk
    meta = json.loads(json.dumps(meta))  # really JSON
    q, opt2 = make()
    with torch.no_grad():
        q.copy_(p)
    opt2.load_state_dict(unflatten_optimizer_state(tensors, meta))
    assert opt2.param_groups[0]["betas"] == (0.8, 0.95)
    for param, o in ((p, opt), (q, opt2)):
        param.grad = param.detach() ** 2
        o.step()
    assert torch.equal(p, q)


def test_errors(tmp_path: Path) -> None:
    with pytest.raises(MissingWeightsError):
        load_checkpoint(tmp_path)
    with pytest.raises(MissingWeightsError):
        load_checkpoint(tmp_path / "step-00000001.json")
    with pytest.raises(ShapeError):
        save_checkpoint(tmp_path, 1, {"x": 3}, {})  # type: ignore[dict-item]
    path = save_checkpoint(tmp_path, 2, {"x": torch.zeros(1)}, {})
    path.with_suffix(".safetensors").unlink()
    with pytest.raises(MissingWeightsError):
        load_checkpoint(path)


def test_a_truncated_latest_checkpoint_falls_back_to_the_previous_one(tmp_path):
    import warnings

    from poseflow.errors import CheckpointError
    from poseflow.flows.checkpoint import load_checkpoint, save_checkpoint

    for step in (1, 2, 3):
        save_checkpoint(tmp_path, step, {"w": torch.full((64,), float(step))}, {"note": step})
    tensors = tmp_path / "step-00000003.safetensors"
    tensors.write_bytes(tensors.read_bytes()[:-40])  # a copy cut short
    with pytest.warns(UserWarning, match=r"skipped 1 unreadable checkpoint.*resuming from step 2"):
        t, meta = load_checkpoint(tmp_path)
    assert meta["step"] == 2 and t["w"][0].item() == 2.0
    (tmp_path / "step-00000002.json").write_text('{"step": 2, "tens')  # a truncated JSON
    with pytest.warns(UserWarning, match="skipped 2 unreadable"):
        assert load_checkpoint(tmp_path)[1]["step"] == 1
    with pytest.raises(CheckpointError, match="truncated or corrupt"):
        load_checkpoint(tmp_path / "step-00000003.json")  # asked for by name: no fallback
    (tmp_path / "step-00000001.safetensors").write_bytes(b"\x01")
    with pytest.raises(CheckpointError, match="no readable checkpoint"), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        load_checkpoint(tmp_path)
