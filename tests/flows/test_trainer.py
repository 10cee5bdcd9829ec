"""CFMTrainer: learning, bit-exact resume, checkpoints without pickle, logging, hooks."""

from __future__ import annotations

import itertools
import json
import logging
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from poseflow.errors import DegenerateInputError, MissingWeightsError, ValueRangeError
from poseflow.flows.objective import CFMObjective, FlowBatch
from poseflow.flows.trainer import CFMTrainer, TrainConfig


class Net(torch.nn.Module):
    def __init__(self, cond: int = 4, dropout: float = 0.1) -> None:
        super().__init__()
        self.inp = torch.nn.Linear(3 + 1 + cond, 32)
        self.drop = torch.nn.Dropout(dropout)
        self.out = torch.nn.Linear(32, 3)

    def forward(self, *, x, t, condition, mask=None):
        h = torch.cat([x, t[:, None, None].expand(*x.shape[:2], 1), condition], -1)
        return self.out(self.drop(torch.relu(self.inp(h))))


class Points(torch.utils.data.Dataset):
    """x_1 = a class-dependent offset plus small noise; condition = the one-hot class."""

    def __init__(self, n: int = 48, length: int = 8) -> None:
        g = torch.Generator().manual_seed(5)
        self.label = torch.randint(0, 4, (n,), generator=g)
        centres = torch.tensor([[2.0, 0, 0], [-2.0, 0, 0], [0, 2.0, 0], [0, -2.0, 0]])
        self.x = centres[self.label][:, None] + 0.1 * torch.randn(n, length, 3, generator=g)
        self.c = torch.nn.functional.one_hot(self.label, 4).float()[:, None].expand(n, length, 4)

    def __len__(self) -> int:
        return len(self.x)

    def __getitem__(self, i: int) -> dict:
        return {"x_1": self.x[i], "condition": self.c[i]}


def _trainer(out_dir=None, *, seed_model=0, **overrides) -> CFMTrainer:
    torch.manual_seed(seed_model)
    cfg = dict(steps=10, batch_size=8, warmup_steps=2, lr=3e-3, log_every=2, progress=False)
    cfg.update(overrides)
    return CFMTrainer(Net(), Points(), config=TrainConfig(**cfg), out_dir=out_dir, device="cpu")


def _state(trainer: CFMTrainer) -> dict[str, torch.Tensor]:
    out = {f"model.{k}": v for k, v in trainer.model.state_dict().items()}
    out.update({f"ema.{k}": v for k, v in trainer.ema.state_dict().items()})
    for pid, entries in trainer.optimizer.state_dict()["state"].items():
        out.update({f"optim.{pid}.{k}": v for k, v in entries.items()})
    return out


def test_resume_is_bit_exact(tmp_path: Path) -> None:
    straight = _trainer(tmp_path / "a")
    straight.fit()
    half = _trainer(tmp_path / "b")
    half.fit(until=5)  # 48 samples / 8 = 6 batches per epoch: 5 stops mid-epoch
    assert half.step == 5
    # a fresh process: different initial weights and global RNG, everything comes from disk
    resumed = _trainer(tmp_path / "b", seed_model=123)
    torch.manual_seed(999)
    assert resumed.resume()
    assert resumed.step == 5
    resumed.fit()
    a, b = _state(straight), _state(resumed)
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k
    assert straight.history[-1]["loss"] == resumed.history[-1]["loss"]
    # the log of the resumed run continues the first half without gaps or repeats
    steps = [
        json.loads(x)["step"] for x in (tmp_path / "b" / "metrics.jsonl").read_text().splitlines()
    ]
    assert steps == [2, 4, 5, 6, 8, 10]


def test_resume_discards_log_records_after_the_checkpoint(tmp_path: Path) -> None:
    first = _trainer(tmp_path, ckpt_every=4)
    first.fit(until=6)  # checkpoints at 4 and 6
    (tmp_path / "step-00000006.json").unlink()  # as if the run died before writing step 6
    again = _trainer(tmp_path)
    again.resume()
    assert again.step == 4
    steps = [json.loads(x)["step"] for x in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert steps == [2, 4]


def test_seeded_runs_are_reproducible_and_seeds_matter() -> None:
    a, b = _trainer(), _trainer()
    a.fit()
    b.fit()
    c = _trainer(seed=1)
    c.fit()
    assert torch.equal(a.model.out.weight, b.model.out.weight)
    assert not torch.equal(a.model.out.weight, c.model.out.weight)


def test_training_learns_the_conditional_flow() -> None:
    trainer = _trainer(steps=150, lr=1e-2, warmup_steps=10, ema_decay=None, log_every=25)
    trainer.fit()
    losses = [r["loss"] for r in trainer.history]
    # at x_1 = const the best loss is E|x_1 - x_0|^2 / 3 - Var = about 1 (the noise), from ~2.4
    assert losses[-1] < 0.75 * losses[0]


def test_checkpoint_files_are_safetensors_and_json(tmp_path: Path) -> None:
    trainer = _trainer(tmp_path, ckpt_every=3, keep_checkpoints=2)
    trainer.fit()
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == [
        "metrics.jsonl",
        "step-00000009.json",
        "step-00000009.safetensors",
        "step-00000010.json",
        "step-00000010.safetensors",
    ]
    meta = json.loads((tmp_path / "step-00000010.json").read_text())
    assert meta["step"] == 10 and meta["rng"] == {"seed": 0, "step": 10}
    assert meta["config"]["batch_size"] == 8 and meta["world_size"] == 1
    tensors = load_file(tmp_path / meta["tensors"])
    assert torch.equal(tensors["model.out.weight"], trainer.model.out.weight.detach())
    assert torch.equal(tensors["ema.out.weight"], trainer.ema.module.out.weight)
    assert any(k.startswith("optim.") and k.endswith(".exp_avg_sq") for k in tensors)


def test_resume_never_unpickles(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    _trainer(tmp_path).fit(until=4)

    def refuse(*args, **kwargs):
        raise AssertionError("torch.load called")

    monkeypatch.setattr(torch, "load", refuse)
    trainer = _trainer(tmp_path)
    assert trainer.resume(tmp_path / "step-00000004.json")
    assert trainer.step == 4


def test_resume_without_checkpoint(tmp_path: Path) -> None:
    assert not _trainer(tmp_path).resume()
    assert not _trainer().resume()
    with pytest.raises(MissingWeightsError):
        _trainer().resume(tmp_path / "missing.json")


def test_validation_hook_runs_on_schedule(tmp_path: Path) -> None:
    calls = []

    def validate(trainer: CFMTrainer) -> dict[str, float]:
        assert not trainer.ema_model.training
        calls.append(trainer.step)
        return {"score": trainer.step * 1.5}

    trainer = _trainer(tmp_path, val_every=4)
    trainer.validate = validate
    last = trainer.fit()
    assert calls == [4, 8]
    assert trainer.model.training  # restored after validation
    records = [json.loads(x) for x in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert {"step": 8, "val/score": 12.0}.items() <= records[-2].items()
    assert last["loss"] > 0 and "val/score" not in last  # step 10 has no validation


def test_log_records_and_lr_schedule() -> None:
    trainer = _trainer(log_every=1, min_lr=1e-4)
    trainer.fit()
    recs = trainer.history
    assert [r["step"] for r in recs] == list(range(1, 11))
    lrs = [r["lr"] for r in recs]
    assert lrs[0] == pytest.approx(1.5e-3) and lrs[1] == pytest.approx(3e-3)
    assert all(a >= b for a, b in itertools.pairwise(lrs[1:]))  # cosine decay after warm-up
    assert lrs[-1] > 1e-4
    for r in recs:
        assert r["samples_per_s"] > 0 and r["grad_norm"] > 0


def test_gradient_clipping_bounds_the_applied_gradient() -> None:
    trainer = _trainer(grad_clip=1e-3, steps=3)
    trainer.fit()
    total = torch.sqrt(sum((p.grad**2).sum() for p in trainer.params))
    assert float(total) <= 1e-3 * (1 + 1e-4)
    assert trainer.history[-1]["grad_norm"] > 1e-3  # the logged norm is before clipping


def test_ema_tracks_the_weights() -> None:
    none = _trainer(ema_decay=None)
    none.fit()
    assert none.ema is None and none.ema_model is none.model
    zero = _trainer(ema_decay=0.0)
    zero.fit()
    assert torch.equal(zero.ema.module.out.weight, zero.model.out.weight.detach())
    slow = _trainer(ema_decay=0.999)
    slow.fit()
    assert not torch.equal(slow.ema.module.out.weight, slow.model.out.weight.detach())


def test_custom_objective_and_dataloader_input() -> None:
    seen = []

    def objective(model, batch, rng):
        x_1 = batch[0]
        fb = FlowBatch(x_1=x_1, cond={"condition": torch.zeros(*x_1.shape[:2], 4)})
        seen.append(x_1.shape)
        return CFMObjective(time_sampler="uniform")(model, fb, rng), {"extra": x_1.mean()}

    loader = torch.utils.data.DataLoader(
        torch.utils.data.TensorDataset(torch.randn(20, 6, 3)), batch_size=5
    )
    torch.manual_seed(0)
    cfg = TrainConfig(steps=6, batch_size=5, warmup_steps=0, log_every=3, progress=False)
    trainer = CFMTrainer(Net(), loader, config=cfg, objective=objective, device="cpu")
    trainer.fit()
    assert len(seen) == 6 and all(s == (5, 6, 3) for s in seen)
    assert "extra" in trainer.history[-1]


def test_dataloader_resume_skips_consumed_batches(tmp_path: Path) -> None:
    def run(split: bool) -> torch.Tensor:
        data = torch.utils.data.TensorDataset(torch.randn(20, 6, 3, generator=_g()))
        loader = torch.utils.data.DataLoader(data, batch_size=5, collate_fn=_stack)
        cfg = TrainConfig(steps=7, batch_size=5, warmup_steps=0, progress=False)
        make = lambda: CFMTrainer(  # noqa: E731
            _net(), loader, config=cfg, objective=_plain, out_dir=tmp_path / str(split)
        )
        trainer = make()
        if split:
            trainer.fit(until=3)
            trainer = make()
            trainer.resume()
        trainer.fit()
        return trainer.model.out.weight.detach()

    assert torch.equal(run(False), run(True))


def _g() -> torch.Generator:
    return torch.Generator().manual_seed(0)


def _stack(items):
    return torch.stack([x for (x,) in items])


def _net() -> Net:
    torch.manual_seed(0)
    return Net(dropout=0.0)


def _plain(model, x_1, rng):
    cond = torch.zeros(*x_1.shape[:2], 4)
    return CFMObjective()(model, {"x_1": x_1, "condition": cond}, rng)


def test_flow_batch_collate_with_anchor() -> None:
    data = Points()

    def collate(items):
        x_1 = torch.stack([it["x_1"] for it in items])
        frozen = torch.zeros(x_1.shape[:2], dtype=torch.bool)
        frozen[:, :2] = True
        cond = {"condition": torch.stack([it["condition"] for it in items])}
        return FlowBatch(x_1=x_1, cond=cond, frozen_mask=frozen)

    torch.manual_seed(0)
    cfg = TrainConfig(steps=3, batch_size=8, warmup_steps=0, progress=False)
    objective = CFMObjective(pin_frozen=True, noise_kwarg="noise")
    seen = []

    class Anchored(Net):
        def forward(self, *, x, t, condition, noise):
            seen.append((x[:, :2], noise))
            return super().forward(x=x, t=t, condition=condition)

    trainer = CFMTrainer(
        Anchored(), data, config=cfg, collate_fn=collate, objective=objective, device="cpu"
    )
    trainer.fit()
    assert len(seen) == 3
    anchors = {tuple(a.flatten().tolist()[:3]) for a, _ in seen}
    data_anchors = {tuple(x[:2].flatten().tolist()[:3]) for x in data.x}
    assert anchors <= data_anchors  # pinned: the anchors sit at their data coordinates


def test_non_finite_loss_raises() -> None:
    def nan_objective(model, batch, rng):
        return CFMObjective()(model, batch, rng) * float("nan")

    torch.manual_seed(0)
    cfg = TrainConfig(steps=4, batch_size=8, log_every=2, progress=False)
    trainer = CFMTrainer(Net(), Points(), config=cfg, objective=nan_objective, device="cpu")
    with pytest.raises(ValueRangeError):
        trainer.fit()


def test_bad_configuration_raises() -> None:
    with pytest.raises(ValueRangeError):
        TrainConfig(steps=0)
    with pytest.raises(ValueRangeError):
        TrainConfig(precision="int8")
    with pytest.raises(ValueRangeError):
        TrainConfig(ema_decay=1.5)
    with pytest.raises(ValueRangeError):
        TrainConfig(val_every=0)
    with pytest.raises(DegenerateInputError):
        _trainer(batch_size=64)  # 48 samples


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("precision", ["bf16", "fp16"])
def test_mixed_precision_on_cuda(precision: str, tmp_path: Path) -> None:
    torch.manual_seed(0)
    cfg = TrainConfig(
        steps=20,
        batch_size=8,
        warmup_steps=2,
        lr=3e-3,
        precision=precision,
        progress=False,
        log_every=5,
    )
    trainer = CFMTrainer(Net(), Points(), config=cfg, out_dir=tmp_path, device="cuda")
    trainer.fit()
    assert trainer.model.out.weight.dtype == torch.float32
    assert trainer.history[-1]["loss"] < trainer.history[0]["loss"] * 1.5
    again = CFMTrainer(Net(), Points(), config=cfg, out_dir=tmp_path, device="cuda")
    assert again.resume() and again.step == 20
    if precision == "fp16":
        assert again.scaler.get_scale() == trainer.scaler.get_scale()


def test_progress_is_a_status_line_in_a_log(caplog, monkeypatch) -> None:
    """Not on a terminal, the bar is one line through the ``poseflow`` logger per 30 s and at
    the end, with the loss and no escape codes; a resumed fit counts from its first step."""
    monkeypatch.setattr("sys.stderr.isatty", lambda: False, raising=False)
    trainer = _trainer(progress=True)
    with caplog.at_level(logging.INFO, logger="poseflow"):
        trainer.fit(until=4)
        trainer.fit()
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("cfm: ")]
    assert len(lines) == 2  # each fit takes well under 30 s: its last line only
    assert lines[0].startswith("cfm: 4/4 (100%)") and lines[1].startswith("cfm: 10/10 (100%)")
    assert all(", loss " in line and "\x1b" not in line for line in lines)
