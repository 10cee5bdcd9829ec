"""A generic trainer for conditional flow matching, single-process or under ``torchrun``.

:class:`CFMTrainer` trains any velocity model with an objective (by default
:class:`~poseflow.flows.objective.CFMObjective`): AdamW with linear warm-up and cosine decay,
gradient clipping, bf16/fp16 autocast on CUDA, an EMA of the weights, a progress bar with loss and
throughput (a status line every 30 s when stderr is not a terminal), a JSONL metrics log, a
periodic validation hook, and atomic safetensors + JSON checkpoints from which
:meth:`CFMTrainer.resume` continues bit-exactly.

Reproducibility. Every random draw of step ``s`` comes from generators seeded with a hash of
``(seed, s)``: the noise and times of the objective (:class:`~poseflow.flows.objective.StepRandom`,
identical on all ranks, each keeping its own rows of the global batch) and torch's global RNG
during the step (seeded with ``(seed, s, rank)``, for dropout; the caller's global RNG state is
restored afterwards). The data order is ``DistributedSampler``'s, a function of ``(seed, epoch)``.
The RNG state of a checkpoint is therefore ``(seed, step)``, and resuming replays the exact
stream. Two consequences: training with K processes and batch B sees the same samples, noise and
times as one process with batch ``K * B`` (equal up to floating-point summation order, provided
the loss is a mean over equally many terms on every rank: a masked loss is averaged per rank,
as DDP averages gradients, so ranks holding different numbers of valid points weigh them
slightly differently from one large batch); and a
dataset that draws random augmentations inside ``__getitem__`` should draw them from torch's
global RNG (seeded per step when ``num_workers=0``) or from the index.

Distributed. Under ``torchrun`` the trainer joins the process group
(:func:`~poseflow.flows.distributed.init_distributed`), wraps the model in
``DistributedDataParallel`` (which broadcasts rank 0's initial weights), shards the dataset with
``DistributedSampler``; only rank 0 logs, shows the bar and writes checkpoints. ``batch_size``
is per process.

Example:
    >>> import tempfile
    >>> class Net(torch.nn.Module):
    ...     def __init__(self):
    ...         super().__init__()
    ...         self.lin = torch.nn.Linear(4, 3)
    ...     def forward(self, *, x, t):
    ...         return self.lin(torch.cat([x, t[:, None, None].expand(*x.shape[:2], 1)], -1))
    >>> data = torch.utils.data.TensorDataset(torch.randn(64, 8, 3))
    >>> cfg = TrainConfig(steps=4, batch_size=16, warmup_steps=1, progress=False)
    >>> trainer = CFMTrainer(Net(), data, config=cfg, collate_fn=lambda items: torch.stack(
    ...     [x for (x,) in items]), out_dir=tempfile.mkdtemp())
    >>> result = trainer.fit()
    >>> trainer.step, sorted(p.suffix for p in trainer.out_dir.glob("step-*"))
    (4, ['.json', '.safetensors'])
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import itertools
import json
import os
import time
import warnings
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import nn
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader, Dataset, DistributedSampler, IterableDataset, Sampler

from poseflow._precision import PRECISIONS
from poseflow._progress import ProgressBar
from poseflow.errors import DegenerateInputError, MissingWeightsError, ValueRangeError
from poseflow.flows.checkpoint import (
    atomic_write,
    flatten_optimizer_state,
    latest_checkpoint,
    load_checkpoint,
    prune_checkpoints,
    save_checkpoint,
    unflatten_optimizer_state,
)
from poseflow.flows.distributed import (
    DistributedContext,
    all_reduce_mean,
    barrier,
    init_distributed,
)
from poseflow.flows.ema import EMA
from poseflow.flows.objective import CFMObjective, FlowBatch, StepRandom
from poseflow.flows.schedule import warmup_cosine_lr

__all__ = ["CFMTrainer", "Objective", "TrainConfig", "ValidateHook"]

#: ``objective(model, batch, rng) -> loss`` or ``(loss, {name: scalar tensor})``.
Objective = Callable[[nn.Module, Any, StepRandom], Any]
#: ``validate(trainer) -> {name: number}``, called on every rank at validation steps.
ValidateHook = Callable[["CFMTrainer"], Mapping[str, float]]

_FORMAT = "poseflow.flows.CFMTrainer/1"


@dataclass
class TrainConfig:
    """Hyper-parameters of :class:`CFMTrainer` (stored in every checkpoint).

    The paper gives no optimiser settings; these are common defaults for DiT-style flow models.

    Attributes:
        steps: total optimiser steps (also the length of the cosine schedule).
        batch_size: samples per process and step.
        lr: peak learning rate.
        min_lr: learning rate at the end of the cosine decay.
        warmup_steps: steps of linear warm-up.
        weight_decay: AdamW's decoupled weight decay.
        betas: AdamW's moment decays.
        grad_clip: maximum global gradient norm, or None for no clipping.
        ema_decay: decay of the weight EMA, or None for no EMA.
        precision: ``"bf16"``, ``"fp16"`` (with loss scaling) or ``"fp32"``: the autocast dtype
            on CUDA; CPU always trains in the model's own dtype.
        seed: seed of data order, noise, times and dropout.
        log_every: steps between log records (and the loss finiteness check).
        val_every: steps between validation calls, or None.
        ckpt_every: steps between checkpoints, or None (a checkpoint is still written at the
            end of :meth:`CFMTrainer.fit` when there is an output directory).
        keep_checkpoints: number of checkpoints kept on disk.
        num_workers: ``DataLoader`` worker processes (when the trainer builds the loader).
        progress: show a progress bar on rank 0.
        find_unused_parameters: passed to ``DistributedDataParallel``.
    """

    steps: int = 10_000
    batch_size: int = 32
    lr: float = 1e-4
    min_lr: float = 0.0
    warmup_steps: int = 500
    weight_decay: float = 0.01
    betas: tuple[float, float] = (0.9, 0.999)
    grad_clip: float | None = 1.0
    ema_decay: float | None = 0.999
    precision: str = "bf16"
    seed: int = 0
    log_every: int = 10
    val_every: int | None = None
    ckpt_every: int | None = None
    keep_checkpoints: int = 3
    num_workers: int = 0
    progress: bool = True
    find_unused_parameters: bool = False

    def __post_init__(self) -> None:
        """Validate the values."""
        if self.steps < 1 or self.batch_size < 1 or self.log_every < 1:
            raise ValueRangeError("steps, batch_size and log_every must be >= 1")
        if self.warmup_steps < 0 or self.lr <= 0 or self.keep_checkpoints < 1:
            raise ValueRangeError("need warmup_steps >= 0, lr > 0, keep_checkpoints >= 1")
        if self.precision not in PRECISIONS:
            raise ValueRangeError(f"precision must be one of {sorted(PRECISIONS)}")
        if self.ema_decay is not None and not 0.0 <= self.ema_decay <= 1.0:
            raise ValueRangeError(f"ema_decay must be in [0, 1], got {self.ema_decay}")
        for name in ("val_every", "ckpt_every", "grad_clip"):
            value = getattr(self, name)
            if value is not None and value <= 0:
                raise ValueRangeError(f"{name} must be positive or None, got {value}")
        self.betas = (float(self.betas[0]), float(self.betas[1]))

    def to_json(self) -> dict[str, Any]:
        """The configuration as a JSON-serialisable dict."""
        out = dataclasses.asdict(self)
        out["betas"] = list(self.betas)
        return out


class CFMTrainer:
    """Train a velocity model by flow matching; see the module docstring for the guarantees.

    Args:
        model: the model to train; moved to the trainer's device. Seed its initialisation
            yourself (``torch.manual_seed``); under DDP rank 0's weights are broadcast.
        data: a map-style ``Dataset`` (the trainer builds a seeded, resumable
            ``DataLoader`` with ``DistributedSampler``) or any other re-iterable of batches such
            as a ``DataLoader`` (used as is, so shard it yourself under DDP; its
            ``sampler.set_epoch`` is called when it exists, and on resume the first batches are
            drawn and skipped, so it must be deterministic).
        config: hyper-parameters.
        objective: ``objective(model, batch, rng) -> loss | (loss, metrics)``; default
            :class:`~poseflow.flows.objective.CFMObjective` with the paper's settings.
        collate_fn: the ``DataLoader`` collate function when ``data`` is a dataset.
        validate: optional hook ``validate(trainer) -> {name: value}`` run every
            ``config.val_every`` steps on every rank (it may shard its own work; only rank 0's
            values are logged). ``trainer.ema_model`` is the model to evaluate.
        out_dir: directory of checkpoints and ``metrics.jsonl``; None writes nothing.
        device: training device (default ``cuda:LOCAL_RANK`` when available, else CPU).
        backend: process-group backend under torchrun (default nccl on CUDA, gloo on CPU).
    """

    def __init__(
        self,
        model: nn.Module,
        data: Dataset | Any,
        *,
        config: TrainConfig | None = None,
        objective: Objective | None = None,
        collate_fn: Callable[[list[Any]], Any] | None = None,
        validate: ValidateHook | None = None,
        out_dir: str | os.PathLike[str] | None = None,
        device: torch.device | str | None = None,
        backend: str | None = None,
    ) -> None:
        self.config = config if config is not None else TrainConfig()
        self.ctx: DistributedContext = init_distributed(backend=backend, device=device)
        self.device = self.ctx.device
        self.model = model.to(self.device)
        self.objective: Objective = objective if objective is not None else CFMObjective()
        self.validate = validate
        self.out_dir = Path(out_dir) if out_dir is not None else None
        self.step = 0
        self.history: list[dict[str, Any]] = []
        cfg = self.config
        if self.ctx.is_distributed:
            ids = [self.device] if self.device.type == "cuda" else None
            self.net: nn.Module = DistributedDataParallel(
                self.model, device_ids=ids, find_unused_parameters=cfg.find_unused_parameters
            )
        else:
            self.net = self.model
        self.params = [p for p in self.model.parameters() if p.requires_grad]
        if not self.params:
            raise DegenerateInputError("the model has no trainable parameters")
        self.optimizer = torch.optim.AdamW(
            self.params, lr=cfg.lr, betas=cfg.betas, weight_decay=cfg.weight_decay
        )
        on_cuda = self.device.type == "cuda"
        self.amp_dtype = PRECISIONS[cfg.precision] if on_cuda else None
        self.scaler = torch.amp.GradScaler("cuda", enabled=self.amp_dtype == torch.float16)
        # after the DDP wrap, so that the average starts from rank 0's broadcast weights
        self.ema = EMA(self.model, decay=cfg.ema_decay) if cfg.ema_decay is not None else None
        self._data = data
        self._collate_fn = collate_fn
        self._loader = self._build_loader()

    # ------------------------------------------------------------------ public

    @property
    def ema_model(self) -> nn.Module:
        """The EMA of the weights (or the model itself when ``ema_decay`` is None)."""
        return self.ema.module if self.ema is not None else self.model

    def fit(self, *, until: int | None = None) -> dict[str, float]:
        """Train from the current step up to step ``until`` (default ``config.steps``).

        Returns:
            The last logged record (``loss``, ``lr``, ``grad_norm``, throughput, and the last
            validation values under ``val/``).

        Raises:
            ValueRangeError: the loss became NaN or inf.
            DegenerateInputError: the data holds fewer samples than one global batch.
        """
        cfg = self.config
        until = cfg.steps if until is None else min(int(until), cfg.steps)
        last: dict[str, float] = {}
        if self.step >= until:
            return last
        bar = ProgressBar(
            until, desc="cfm", initial=self.step, enabled=cfg.progress and self.ctx.is_main
        )
        batches = self._batches(self.step)
        loss_sum = torch.zeros((), dtype=torch.float64, device=self.device)
        extra_sums: dict[str, torch.Tensor] = {}
        window_steps, window_start = 0, time.perf_counter()
        global_batch = cfg.batch_size * self.ctx.world_size
        self.model.train()
        try:
            while self.step < until:
                loss, metrics, grad_norm = self._train_step(batches)
                loss_sum += loss.detach().to(torch.float64)
                for k, v in metrics.items():
                    extra_sums[k] = extra_sums.get(k, 0) + v.detach().to(torch.float64)
                window_steps += 1
                self.step += 1
                bar.update(1)
                if self.step % cfg.log_every == 0 or self.step == until:
                    elapsed = max(time.perf_counter() - window_start, 1e-9)
                    last = self._log_train(
                        loss_sum / window_steps,
                        {k: v / window_steps for k, v in extra_sums.items()},
                        grad_norm,
                        steps_per_s=window_steps / elapsed,
                        samples_per_s=window_steps * global_batch / elapsed,
                    )
                    bar.set_postfix(
                        loss=f"{last['loss']:.4f}", samples_s=f"{last['samples_per_s']:.0f}"
                    )
                    loss_sum.zero_()
                    extra_sums = {}
                    window_steps, window_start = 0, time.perf_counter()
                if cfg.val_every is not None and self.step % cfg.val_every == 0:
                    last.update(self.run_validation())
                if cfg.ckpt_every is not None and self.step % cfg.ckpt_every == 0:
                    self.save_checkpoint()
        finally:
            bar.close()
        if self.out_dir is not None and (cfg.ckpt_every is None or self.step % cfg.ckpt_every):
            self.save_checkpoint()
        return last

    def run_validation(self) -> dict[str, float]:
        """Call the validation hook now; log and return its values prefixed with ``val/``."""
        if self.validate is None:
            return {}
        was_training = self.model.training
        values = {f"val/{k}": float(v) for k, v in dict(self.validate(self)).items()}
        self.model.train(was_training)
        self._record({"step": self.step, **values})
        return values

    def save_checkpoint(self) -> Path | None:
        """Write a checkpoint of the current step to ``out_dir`` (rank 0; all ranks wait).

        Returns:
            The checkpoint's JSON path on rank 0, None on other ranks or without ``out_dir``.
        """
        if self.out_dir is None:
            return None
        path = None
        if self.ctx.is_main:
            tensors = {f"model.{k}": v for k, v in self.model.state_dict().items()}
            optim_tensors, optim_meta = flatten_optimizer_state(self.optimizer.state_dict())
            tensors.update(optim_tensors)
            if self.ema is not None:
                tensors.update({f"ema.{k}": v for k, v in self.ema.state_dict().items()})
            meta = {
                "format": _FORMAT,
                "config": self.config.to_json(),
                "world_size": self.ctx.world_size,
                "rng": {"seed": self.config.seed, "step": self.step},
                "optimizer": optim_meta,
                "scaler": self.scaler.state_dict() if self.scaler.is_enabled() else None,
                "ema_updates": self.ema.num_updates if self.ema is not None else None,
            }
            path = save_checkpoint(self.out_dir, self.step, tensors, meta)
            prune_checkpoints(self.out_dir, self.config.keep_checkpoints)
        barrier(self.ctx)
        return path

    def resume(self, path: str | os.PathLike[str] | None = None) -> bool:
        """Restore a checkpoint so that :meth:`fit` continues exactly where it stopped.

        Args:
            path: a checkpoint's JSON file or a directory; default the latest checkpoint in
                ``out_dir`` (and nothing happens when there is none).

        Returns:
            True when a checkpoint was loaded.

        Raises:
            MissingWeightsError: an explicit ``path`` holds no checkpoint.
        """
        if path is None:
            if self.out_dir is None or latest_checkpoint(self.out_dir) is None:
                return False
            path = self.out_dir
        tensors, meta = load_checkpoint(path, device=self.device)
        if meta.get("format") != _FORMAT:
            raise MissingWeightsError(f"{path} is not a CFMTrainer checkpoint")
        self.model.load_state_dict(_strip(tensors, "model."))
        self.optimizer.load_state_dict(unflatten_optimizer_state(tensors, meta["optimizer"]))
        if self.ema is not None:
            ema_state = _strip(tensors, "ema.")
            if ema_state:
                self.ema.load_state_dict(ema_state, num_updates=meta["ema_updates"])
            else:
                self.ema.load_state_dict(self.model.state_dict(), num_updates=0)
        if meta.get("scaler") and self.scaler.is_enabled():
            self.scaler.load_state_dict(meta["scaler"])
        self.step = int(meta["step"])
        if meta["rng"]["seed"] != self.config.seed:
            warnings.warn(
                f"resuming a run seeded {meta['rng']['seed']} with seed {self.config.seed}: "
                "the random streams differ from the original run",
                stacklevel=2,
            )
        if meta["world_size"] != self.ctx.world_size:
            warnings.warn(
                f"checkpoint written by {meta['world_size']} processes, resumed by "
                f"{self.ctx.world_size}: the data order differs from the original run",
                stacklevel=2,
            )
        self._truncate_log()
        return True

    # ------------------------------------------------------------------ internals

    def _train_step(
        self, batches: Iterator[Any]
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor], torch.Tensor]:
        cfg = self.config
        lr = warmup_cosine_lr(
            self.step,
            base_lr=cfg.lr,
            total_steps=cfg.steps,
            warmup_steps=cfg.warmup_steps,
            min_lr=cfg.min_lr,
        )
        for group in self.optimizer.param_groups:
            group["lr"] = lr
        devices = [self.device] if self.device.type == "cuda" else []
        with torch.random.fork_rng(devices=devices):
            torch.manual_seed(_derive(cfg.seed, self.step, f"global-rank{self.ctx.rank}"))
            batch = _to_device(next(batches), self.device)
            gen = torch.Generator(device=self.device)
            gen.manual_seed(_derive(cfg.seed, self.step, "objective"))
            rng = StepRandom(gen, rank=self.ctx.rank, world_size=self.ctx.world_size)
            autocast = (
                torch.autocast(device_type=self.device.type, dtype=self.amp_dtype)
                if self.amp_dtype is not None
                else contextlib.nullcontext()
            )
            with autocast:
                out = self.objective(self.net, batch, rng)
            loss, metrics = (out, {}) if isinstance(out, torch.Tensor) else out
            self.optimizer.zero_grad(set_to_none=True)
            self.scaler.scale(loss).backward()
        self.scaler.unscale_(self.optimizer)
        max_norm = cfg.grad_clip if cfg.grad_clip is not None else float("inf")
        grad_norm = torch.nn.utils.clip_grad_norm_(self.params, max_norm)
        self.scaler.step(self.optimizer)
        self.scaler.update()
        if self.ema is not None:
            self.ema.update(self.model)
        return loss, dict(metrics), grad_norm

    def _log_train(
        self,
        mean_loss: torch.Tensor,
        extras: dict[str, torch.Tensor],
        grad_norm: torch.Tensor,
        *,
        steps_per_s: float,
        samples_per_s: float,
    ) -> dict[str, float]:
        loss = float(all_reduce_mean(mean_loss, self.ctx))
        if loss != loss or loss in (float("inf"), float("-inf")):
            raise ValueRangeError(
                f"training loss is {loss} at step {self.step}: lower the learning rate, check "
                "the data for NaN, or use precision='bf16' instead of 'fp16'"
            )
        record = {
            "step": self.step,
            "loss": loss,
            "lr": self.optimizer.param_groups[0]["lr"],
            "grad_norm": float(grad_norm),
            "steps_per_s": steps_per_s,
            "samples_per_s": samples_per_s,
            **{k: float(all_reduce_mean(v, self.ctx)) for k, v in extras.items()},
        }
        self._record(record)
        return record

    def _record(self, record: dict[str, Any]) -> None:
        if not self.ctx.is_main:
            return
        self.history.append(record)
        if self.out_dir is not None:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            with open(self.out_dir / "metrics.jsonl", "a") as fh:
                fh.write(json.dumps({"time": time.time(), **record}) + "\n")

    def _truncate_log(self) -> None:
        """Drop log records written after the checkpoint being resumed (rank 0)."""
        if not self.ctx.is_main or self.out_dir is None:
            return
        log = self.out_dir / "metrics.jsonl"
        if not log.is_file():
            return
        kept = [
            line
            for line in log.read_text().splitlines()
            if line.strip() and json.loads(line).get("step", 0) <= self.step
        ]
        text = "".join(line + "\n" for line in kept)
        atomic_write(log, lambda tmp: Path(tmp).write_text(text))

    def _build_loader(self) -> DataLoader | None:
        data = self._data
        if not isinstance(data, Dataset) or isinstance(data, IterableDataset):
            return None
        cfg = self.config
        sampler = _ResumableSampler(
            DistributedSampler(
                data,
                num_replicas=self.ctx.world_size,
                rank=self.ctx.rank,
                shuffle=True,
                seed=cfg.seed,
                drop_last=True,
            )
        )
        if len(sampler.inner) < cfg.batch_size:
            raise DegenerateInputError(
                f"the dataset holds {len(data)} samples, fewer than one global batch of "
                f"{cfg.batch_size * self.ctx.world_size}"
            )
        return DataLoader(
            data,
            batch_size=cfg.batch_size,
            sampler=sampler,
            drop_last=True,
            collate_fn=self._collate_fn,
            num_workers=cfg.num_workers,
            generator=torch.Generator(),
            pin_memory=self.device.type == "cuda",
        )

    def _batches(self, start_step: int) -> Iterator[Any]:
        """Yield the batches of steps ``start_step, start_step + 1, ...``."""
        if self._loader is None:
            return self._user_batches(start_step)
        return self._own_batches(start_step)

    def _own_batches(self, start_step: int) -> Iterator[Any]:
        loader = self._loader
        sampler: _ResumableSampler = loader.sampler  # type: ignore[assignment]
        per_epoch = len(sampler.inner) // self.config.batch_size
        epoch, skip = divmod(start_step, per_epoch)
        while True:
            sampler.set_epoch(epoch)
            sampler.start = skip * self.config.batch_size
            loader.generator.manual_seed(_derive(self.config.seed, epoch, "loader"))
            yield from loader
            epoch, skip = epoch + 1, 0

    def _user_batches(self, start_step: int) -> Iterator[Any]:
        data = self._data
        epoch, seen = 0, 0
        while True:
            set_epoch = getattr(getattr(data, "sampler", None), "set_epoch", None)
            if callable(set_epoch):
                set_epoch(epoch)
            produced = False
            for batch in data:
                produced = True
                if seen >= start_step:
                    yield batch
                seen += 1
            if not produced:
                raise DegenerateInputError("the data yielded no batch")
            epoch += 1


class _ResumableSampler(Sampler[int]):
    """A ``DistributedSampler`` whose epoch can start after its first ``start`` indices."""

    def __init__(self, inner: DistributedSampler) -> None:
        self.inner = inner
        self.start = 0

    def set_epoch(self, epoch: int) -> None:
        self.inner.set_epoch(epoch)

    def __iter__(self) -> Iterator[int]:
        return itertools.islice(iter(self.inner), self.start, None)

    def __len__(self) -> int:
        return len(self.inner) - self.start


def _derive(seed: int, step: int, stream: str) -> int:
    """A 63-bit seed for one random stream of one step."""
    digest = hashlib.blake2b(f"{seed}:{step}:{stream}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "little") >> 1


def _strip(tensors: Mapping[str, torch.Tensor], prefix: str) -> dict[str, torch.Tensor]:
    return {k[len(prefix) :]: v for k, v in tensors.items() if k.startswith(prefix)}


def _to_device(batch: Any, device: torch.device) -> Any:
    if isinstance(batch, torch.Tensor):
        return batch.to(device, non_blocking=True)
    if isinstance(batch, FlowBatch):
        return FlowBatch(
            x_1=_to_device(batch.x_1, device),
            cond=_to_device(batch.cond, device),
            mask=_to_device(batch.mask, device),
            frozen_mask=_to_device(batch.frozen_mask, device),
        )
    if isinstance(batch, Mapping):
        return {k: _to_device(v, device) for k, v in batch.items()}
    if isinstance(batch, (list, tuple)):
        return type(batch)(_to_device(v, device) for v in batch)
    return batch
