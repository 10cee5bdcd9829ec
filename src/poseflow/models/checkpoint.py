"""FunFlow6D checkpoints: ``config.json`` plus ``model.safetensors`` (trainable weights only).

No pickle is ever read: the weights are safetensors and the configuration is JSON, read by
:meth:`~poseflow.models.FunFlow6DConfig.from_dict` (which also reads older files). A checkpoint's
``config.json`` is written whole, so a field it lacks was added to the configuration after the
checkpoint was saved; such a field is read as :data:`CHECKPOINT_FIELDS_ADDED` says, the value that
keeps the checkpoint's behaviour, rather than as the default of new configurations.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from poseflow._cache import atomic_write
from poseflow.errors import CheckpointError, MissingWeightsError, PoseflowError, ValueRangeError
from poseflow.models.config import FunFlow6DConfig, read_config_fields

__all__ = [
    "CHECKPOINT_FIELDS_ADDED",
    "CHECKPOINT_FORMAT",
    "is_checkpoint",
    "read_checkpoint",
    "read_model_config",
    "write_checkpoint",
]

#: The ``format`` metadata of the weights file.
CHECKPOINT_FORMAT = "poseflow.FunFlow6D/1"

#: Configuration fields added after checkpoints were first written, with the value a checkpoint
#: whose ``config.json`` lacks them is read with: what it did before the field existed (no
#: render-and-compare verification, geometric descriptors from the sampled points alone, the
#: flow and the appearance encoder in float32). New configurations take the fields' defaults.
CHECKPOINT_FIELDS_ADDED: dict[str, Any] = {
    "verifier": None,
    "geometric_support_voxel": 0.0,
    "flow_precision": "fp32",
    "appearance_precision": "fp32",
}


def is_checkpoint(folder: str | Path) -> bool:
    """Whether ``folder`` holds a checkpoint (``config.json`` and ``model.safetensors``)."""
    folder = Path(folder)
    return (folder / "config.json").is_file() and (folder / "model.safetensors").is_file()


def write_checkpoint(
    folder: str | Path, config: FunFlow6DConfig, state: dict[str, torch.Tensor]
) -> Path:
    """Write a configuration and the network's ``state_dict`` to ``folder`` (created).

    Encoder folders inside ``folder`` (the onboarding's surface embedding) are recorded relative
    to it, so that the folder works copied or moved (:func:`read_checkpoint` resolves them).

    Returns:
        The folder.
    """
    from safetensors.torch import save_file

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    tensors = {k: v.detach().cpu().contiguous() for k, v in state.items()}
    metadata = {"format": CHECKPOINT_FORMAT}
    atomic_write(folder / "model.safetensors", lambda tmp: save_file(tensors, tmp, metadata))
    text = json.dumps(_encoders_relative(config, folder).to_dict(), indent=1)
    atomic_write(folder / "config.json", lambda tmp: tmp.write_text(text))
    return folder


def read_checkpoint(folder: str | Path) -> tuple[FunFlow6DConfig, dict[str, torch.Tensor]]:
    """The configuration and the network's ``state_dict`` written by :func:`write_checkpoint`.

    Fields the ``config.json`` lacks take the values of :data:`CHECKPOINT_FIELDS_ADDED`, then the
    configuration's defaults. Both files are checked before any weight is read, and every
    problem is a :class:`~poseflow.errors.CheckpointError` that names the file.

    Raises:
        MissingWeightsError: ``folder`` holds no checkpoint.
        CheckpointError: ``config.json`` is not valid JSON, not a JSON object, or holds a field
            of the wrong type or value; ``model.safetensors`` is truncated or corrupt
            (:func:`~poseflow.flows.checkpoint.load_safetensors`).

    Example:
        >>> import tempfile
        >>> folder = write_checkpoint(tempfile.mkdtemp(), FunFlow6DConfig(), {"w": torch.ones(3)})
        >>> read_checkpoint(folder)[1]["w"].tolist()
        [1.0, 1.0, 1.0]
    """
    from poseflow.flows.checkpoint import load_safetensors

    folder = Path(folder)
    if not is_checkpoint(folder):
        raise MissingWeightsError(
            f"{folder} holds no FunFlow6D checkpoint (config.json + model.safetensors); "
            "train one with `poseflow train`"
        )
    return read_model_config(folder), load_safetensors(folder / "model.safetensors")


def read_model_config(folder: str | Path) -> FunFlow6DConfig:
    """The configuration of a model folder's ``config.json``, its encoder folders resolved.

    An encoder path relative to the folder (written so by :func:`write_checkpoint`) that exists
    there is made absolute; other relative paths stay relative to the working directory.

    Raises:
        CheckpointError: ``config.json`` is not valid JSON or holds a field of the wrong type.
    """
    folder = Path(folder)
    return _encoders_resolved(_read_config(folder / "config.json"), folder)


def _read_config(path: Path) -> FunFlow6DConfig:
    """The configuration of a checkpoint's ``config.json``, every problem a CheckpointError."""
    try:
        data = read_config_fields(path)
    except ValueRangeError as exc:
        raise CheckpointError(f"{exc}; restore it") from None
    try:
        return FunFlow6DConfig.from_dict({**CHECKPOINT_FIELDS_ADDED, **data})
    except PoseflowError as exc:
        raise CheckpointError(f"{path}: {exc}") from None
    except (TypeError, KeyError, AttributeError, ValueError) as exc:
        raise CheckpointError(
            f"{path} holds a value of the wrong type ({exc}); restore it or train again"
        ) from None


#: The encoder fields whose ``kind:PATH`` may name a folder inside the model folder.
_ENCODER_FIELDS = ("appearance_encoder", "geometric_encoder")


def _encoders_relative(config: FunFlow6DConfig, folder: Path) -> FunFlow6DConfig:
    """``config`` with its encoder folders written so that they are found from anywhere.

    A folder inside ``folder`` is written relative to it (a model folder that holds its encoders,
    as the onboarding's does, then works copied or moved: :func:`_encoders_resolved` reads it
    back); another folder given relative to the working directory is written absolute.

    Example:
        >>> cfg = FunFlow6DConfig(appearance_encoder="surface:/runs/a/model/surface")
        >>> _encoders_relative(cfg, Path("/runs/a/model")).appearance_encoder
        'surface:surface'
    """

    def place(given: Path) -> str | None:
        if not (given.is_absolute() or given.exists()):
            return None  # a name (dinov2:vits14), or already relative to the model folder
        try:
            return given.resolve().relative_to(folder.resolve()).as_posix()
        except ValueError:
            return str(given.resolve())

    return _replace_encoder_paths(config, place)


def _encoders_resolved(config: FunFlow6DConfig, folder: Path) -> FunFlow6DConfig:
    """``config`` with relative encoder paths that exist inside ``folder`` made absolute.

    Other relative paths stay as written (relative to the working directory).
    """

    def place(given: Path) -> str | None:
        inside = folder / given
        return str(inside.resolve()) if not given.is_absolute() and inside.exists() else None

    return _replace_encoder_paths(config, place)


def _replace_encoder_paths(
    config: FunFlow6DConfig, place: Callable[[Path], str | None]
) -> FunFlow6DConfig:
    """``config`` with each encoder's ``kind:PATH`` given the path ``place(PATH)`` (None: kept)."""
    changes = {}
    for name in _ENCODER_FIELDS:
        kind, _, path = getattr(config, name).partition(":")
        new = place(Path(path)) if path else None
        if new is not None:
            changes[name] = f"{kind}:{new}"
    return dataclasses.replace(config, **changes) if changes else config
