"""Checkpoints as a safetensors file of tensors plus a JSON file of everything else.

A checkpoint ``step-00001000`` in a directory is two files: ``step-00001000.safetensors`` (named
tensors: weights, EMA weights, the optimiser state flattened to tensors) and
``step-00001000.json`` (step, configuration, optimiser hyper-parameters, RNG seeds, and the name
of the tensor file). Both are written by :func:`atomic_write` (a temporary file in the same
directory, flushed to disk and renamed into place), the tensors first: a JSON file therefore only
ever names a complete tensor file, and a crash leaves at worst a stray ``.tmp`` file. Loading reads
safetensors and JSON only; nothing is unpickled. A checkpoint damaged after the fact (a disk
that filled up, a copy cut short) is detected when read; :func:`load_checkpoint` of a directory
then falls back to the previous checkpoint with a warning.
"""

from __future__ import annotations

import json
import os
import re
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load_file, save_file

from poseflow._cache import atomic_write
from poseflow.errors import CheckpointError, MissingWeightsError, ShapeError

__all__ = [
    "atomic_write",
    "check_safetensors",
    "flatten_optimizer_state",
    "latest_checkpoint",
    "load_checkpoint",
    "load_safetensors",
    "prune_checkpoints",
    "save_checkpoint",
    "unflatten_optimizer_state",
]

_NAME = re.compile(r"^step-(\d+)\.json$")


def save_checkpoint(
    directory: str | os.PathLike[str],
    step: int,
    tensors: Mapping[str, torch.Tensor],
    meta: Mapping[str, Any],
) -> Path:
    """Write checkpoint ``step`` (tensors + JSON metadata) atomically into ``directory``.

    Args:
        directory: the checkpoint directory (created if missing).
        step: the training step; names the files ``step-XXXXXXXX.{safetensors,json}``.
        tensors: named tensors; copied to contiguous CPU tensors (shared storage is fine).
        meta: JSON-serialisable metadata; ``step`` and ``tensors`` (the file name) are added.

    Returns:
        The path of the JSON file, which identifies the checkpoint.

    Raises:
        ShapeError: a value of ``tensors`` is not a tensor.

    Example:
        >>> import tempfile
        >>> d = tempfile.mkdtemp()
        >>> p = save_checkpoint(d, 7, {"w": torch.ones(2)}, {"note": "x"})
        >>> t, m = load_checkpoint(p)
        >>> t["w"].tolist(), m["step"], m["note"]
        ([1.0, 1.0], 7, 'x')
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    stem = f"step-{int(step):08d}"
    cpu: dict[str, torch.Tensor] = {}
    for name, value in tensors.items():
        if not isinstance(value, torch.Tensor):
            raise ShapeError(f"checkpoint entry {name!r} is a {type(value).__name__}, not a tensor")
        cpu[name] = value.detach().to("cpu", copy=True).contiguous()
    atomic_write(directory / f"{stem}.safetensors", lambda tmp: save_file(cpu, str(tmp)))
    record = {**meta, "step": int(step), "tensors": f"{stem}.safetensors"}
    text = json.dumps(record, indent=1, sort_keys=True)
    return atomic_write(directory / f"{stem}.json", lambda tmp: tmp.write_text(text))


def check_safetensors(path: str | os.PathLike[str]) -> Path:
    """Check that a safetensors file is complete: its header parses and covers the whole file.

    Reads the header only (the tensors are not loaded).

    Args:
        path: the file.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        MissingWeightsError: the file does not exist.
        CheckpointError: the file is truncated or is not a safetensors file.

    Example:
        >>> import tempfile, pathlib
        >>> p = pathlib.Path(tempfile.mkdtemp()) / "w.safetensors"
        >>> save_file({"w": torch.ones(4)}, str(p))
        >>> check_safetensors(p).name
        'w.safetensors'
        >>> _ = p.write_bytes(p.read_bytes()[:-3])
        >>> try:
        ...     check_safetensors(p)
        ... except CheckpointError as e:
        ...     print(str(e).split(" (")[0])
        w.safetensors is truncated or corrupt
    """
    path = Path(path)
    if not path.is_file():
        raise MissingWeightsError(f"{path} does not exist")
    size = path.stat().st_size
    try:
        with open(path, "rb") as f:
            head = f.read(8)
            if len(head) < 8:
                raise ValueError(f"{size} bytes, fewer than a header")
            n = int.from_bytes(head, "little")
            if n > size - 8:
                raise ValueError(f"the header claims {n} bytes, the file has {size - 8} after it")
            header = json.loads(f.read(n))
        if not isinstance(header, dict):
            raise ValueError("the header is not a JSON object")
        end = max(
            (int(v["data_offsets"][1]) for k, v in header.items() if k != "__metadata__"),
            default=0,
        )
    except (ValueError, KeyError, TypeError, IndexError) as exc:
        raise _corrupt(path, exc) from None
    if 8 + n + end != size:
        raise _corrupt(path, f"the header describes {8 + n + end} bytes, the file has {size}")
    return path


def load_safetensors(
    path: str | os.PathLike[str], *, device: torch.device | str = "cpu"
) -> dict[str, torch.Tensor]:
    """The tensors of a safetensors file, checked whole first (:func:`check_safetensors`).

    Raises:
        MissingWeightsError: the file does not exist.
        CheckpointError: the file is truncated, corrupt or not a safetensors file.

    Example:
        >>> import tempfile, pathlib
        >>> p = pathlib.Path(tempfile.mkdtemp()) / "w.safetensors"
        >>> save_file({"w": torch.ones(2)}, str(p))
        >>> load_safetensors(p)
        {'w': tensor([1., 1.])}
    """
    from safetensors import SafetensorError

    path = check_safetensors(path)
    try:
        return load_file(str(path), device=str(device))
    except (SafetensorError, ValueError, OSError) as exc:
        raise _corrupt(path, exc) from None


def _corrupt(path: Path, why: object) -> CheckpointError:
    """The error of a safetensors file that cannot be read whole, saying ``why``."""
    return CheckpointError(
        f"{path.name} is truncated or corrupt ({why}): {path}; restore it or write it again"
    )


def load_checkpoint(
    path: str | os.PathLike[str], *, device: torch.device | str = "cpu"
) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Read a checkpoint written by :func:`save_checkpoint`.

    Given a directory, its latest readable checkpoint is read: one whose JSON or tensor file is
    truncated or corrupt is skipped with a warning, for the one before it.

    Args:
        path: the checkpoint's JSON file, or a directory.
        device: where to put the tensors.

    Returns:
        ``(tensors, meta)``.

    Raises:
        MissingWeightsError: no checkpoint at ``path``.
        CheckpointError: the checkpoint named by ``path`` (or every checkpoint of the
            directory) is truncated or corrupt.
    """
    path = Path(path)
    if not path.is_dir():
        if not path.is_file():
            raise MissingWeightsError(f"checkpoint {path} does not exist")
        return _read_checkpoint(path, device)
    steps = _checkpoints(path)
    if not steps:
        raise MissingWeightsError(f"no checkpoint (step-*.json) in {path}")
    errors = []
    for step in sorted(steps, reverse=True):
        try:
            out = _read_checkpoint(steps[step], device)
        except (CheckpointError, MissingWeightsError) as exc:
            errors.append(str(exc))
            continue
        if errors:
            warnings.warn(
                f"skipped {len(errors)} unreadable checkpoint(s) in {path} ({errors[0]}); "
                f"resuming from step {step}",
                stacklevel=2,
            )
        return out
    raise CheckpointError(f"no readable checkpoint in {path}: {'; '.join(errors)}")


def _read_checkpoint(
    path: Path, device: torch.device | str
) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    try:
        meta = json.loads(path.read_text())
        tensor_name = meta["tensors"]
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError) as exc:
        raise CheckpointError(f"checkpoint {path} is truncated or corrupt ({exc})") from None
    tensor_file = path.parent / tensor_name
    if not tensor_file.is_file():
        raise MissingWeightsError(f"checkpoint {path} names {tensor_file}, which does not exist")
    check_safetensors(tensor_file)
    return load_file(tensor_file, device=str(device)), meta


def latest_checkpoint(directory: str | os.PathLike[str]) -> Path | None:
    """The JSON file of the highest-step checkpoint in ``directory``, or None.

    Example:
        >>> import tempfile
        >>> latest_checkpoint(tempfile.mkdtemp()) is None
        True
    """
    steps = _checkpoints(Path(directory))
    return steps[max(steps)] if steps else None


def prune_checkpoints(directory: str | os.PathLike[str], keep: int) -> None:
    """Delete all but the ``keep`` highest-step checkpoints in ``directory`` (``keep >= 1``)."""
    steps = _checkpoints(Path(directory))
    for step in sorted(steps)[: max(0, len(steps) - max(1, keep))]:
        json_path = steps[step]
        json_path.unlink()
        json_path.with_suffix(".safetensors").unlink(missing_ok=True)


def flatten_optimizer_state(
    state: Mapping[str, Any], prefix: str = "optim."
) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Split ``optimizer.state_dict()`` into named tensors and JSON-serialisable metadata.

    Per-parameter tensors (Adam's ``exp_avg``, ``exp_avg_sq``, ``step``) become
    ``{prefix}{param_id}.{key}``; per-parameter non-tensor values and the parameter groups go
    to the metadata.

    Example:
        >>> p = torch.nn.Parameter(torch.ones(2))
        >>> opt = torch.optim.AdamW([p]); p.grad = torch.ones(2); opt.step()
        >>> tensors, meta = flatten_optimizer_state(opt.state_dict())
        >>> sorted(tensors)
        ['optim.0.exp_avg', 'optim.0.exp_avg_sq', 'optim.0.step']
    """
    tensors: dict[str, torch.Tensor] = {}
    scalars: dict[str, dict[str, Any]] = {}
    for pid, entries in state["state"].items():
        for key, value in entries.items():
            if isinstance(value, torch.Tensor):
                tensors[f"{prefix}{pid}.{key}"] = value
            else:
                scalars.setdefault(str(pid), {})[key] = value
    groups = [
        {k: (list(v) if isinstance(v, tuple) else v) for k, v in g.items()}
        for g in state["param_groups"]
    ]
    return tensors, {"param_groups": groups, "scalars": scalars, "prefix": prefix}


def unflatten_optimizer_state(
    tensors: Mapping[str, torch.Tensor], meta: Mapping[str, Any]
) -> dict[str, Any]:
    """Rebuild an ``optimizer.state_dict()`` from :func:`flatten_optimizer_state`'s output.

    Example:
        >>> p = torch.nn.Parameter(torch.ones(2))
        >>> opt = torch.optim.AdamW([p]); p.grad = torch.ones(2); opt.step()
        >>> sd = unflatten_optimizer_state(*flatten_optimizer_state(opt.state_dict()))
        >>> torch.equal(sd["state"][0]["exp_avg"], opt.state_dict()["state"][0]["exp_avg"])
        True
    """
    prefix = meta["prefix"]
    state: dict[int, dict[str, Any]] = {}
    for name, value in tensors.items():
        if not name.startswith(prefix):
            continue
        pid, key = name[len(prefix) :].split(".", 1)
        state.setdefault(int(pid), {})[key] = value
    for pid, entries in meta["scalars"].items():
        state.setdefault(int(pid), {}).update(entries)
    groups = [
        {k: (tuple(v) if isinstance(v, list) and k != "params" else v) for k, v in g.items()}
        for g in meta["param_groups"]
    ]
    return {"state": state, "param_groups": groups}


def _checkpoints(directory: Path) -> dict[int, Path]:
    if not directory.is_dir():
        return {}
    found = {}
    for p in directory.iterdir():
        m = _NAME.match(p.name)
        if m:
            found[int(m.group(1))] = p
    return found
