"""Checkpoints as a safetensors file of tensors plus a JSON file of everything else.

A checkpoint ``step-00001000`` in a directory is two files: ``step-00001000.safetensors`` (named
tensors: weights, EMA weights, the optimiser state flattened to tensors) and
``step-00001000.json`` (step, configuration, optimiser hyper-parameters, RNG seeds, and the name
of the tensor file). Both are written to a temporary file in the same directory, flushed to disk
and moved into place with ``os.replace``, the tensors first: a JSON file therefore only ever
names a complete tensor file, and a crash leaves at worst a stray ``.tmp`` file. Loading reads
safetensors and JSON only; nothing is unpickled.
"""

from __future__ import annotations

import json
import os
import re
import tempfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load_file, save_file

from poseflow.errors import MissingWeightsError, ShapeError

__all__ = [
    "atomic_write",
    "flatten_optimizer_state",
    "latest_checkpoint",
    "load_checkpoint",
    "prune_checkpoints",
    "save_checkpoint",
    "unflatten_optimizer_state",
]

_NAME = re.compile(r"^step-(\d+)\.json$")


def atomic_write(path: str | os.PathLike[str], write: Callable[[str], None]) -> Path:
    """Write a file atomically: ``write(tmp_path)`` fills a temporary file, then it is renamed.

    Args:
        path: the final file path; its directory must exist.
        write: a function that writes the whole file at the path it is given.

    Returns:
        The final path.

    Example:
        >>> import tempfile, pathlib
        >>> d = tempfile.mkdtemp()
        >>> write = lambda tmp: pathlib.Path(tmp).write_text("hi")
        >>> p = atomic_write(pathlib.Path(d) / "a.txt", write)
        >>> p.read_text(), sorted(x.name for x in pathlib.Path(d).iterdir())
        ('hi', ['a.txt'])
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        write(tmp)
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


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
    atomic_write(directory / f"{stem}.safetensors", lambda tmp: save_file(cpu, tmp))
    record = {**meta, "step": int(step), "tensors": f"{stem}.safetensors"}
    text = json.dumps(record, indent=1, sort_keys=True)
    return atomic_write(directory / f"{stem}.json", lambda tmp: Path(tmp).write_text(text))


def load_checkpoint(
    path: str | os.PathLike[str], *, device: torch.device | str = "cpu"
) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Read a checkpoint written by :func:`save_checkpoint`.

    Args:
        path: the checkpoint's JSON file, or a directory (its latest checkpoint is read).
        device: where to put the tensors.

    Returns:
        ``(tensors, meta)``.

    Raises:
        MissingWeightsError: no checkpoint at ``path``.
    """
    path = Path(path)
    if path.is_dir():
        latest = latest_checkpoint(path)
        if latest is None:
            raise MissingWeightsError(f"no checkpoint (step-*.json) in {path}")
        path = latest
    if not path.is_file():
        raise MissingWeightsError(f"checkpoint {path} does not exist")
    meta = json.loads(path.read_text())
    tensor_file = path.parent / meta["tensors"]
    if not tensor_file.is_file():
        raise MissingWeightsError(f"checkpoint {path} names {tensor_file}, which does not exist")
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
