"""FunFlow6D checkpoints: ``config.json`` plus ``model.safetensors`` (trainable weights only).

No pickle is ever read: the weights are safetensors and the configuration is JSON, read by
:meth:`~poseflow.models.FunFlow6DConfig.from_json` (which also reads older files).
"""

from __future__ import annotations

import json
from pathlib import Path

import torch

from poseflow.errors import MissingWeightsError
from poseflow.models.config import FunFlow6DConfig

__all__ = ["CHECKPOINT_FORMAT", "is_checkpoint", "read_checkpoint", "write_checkpoint"]

#: The ``format`` metadata of the weights file.
CHECKPOINT_FORMAT = "poseflow.FunFlow6D/1"


def is_checkpoint(folder: str | Path) -> bool:
    """Whether ``folder`` holds a checkpoint (``config.json`` and ``model.safetensors``)."""
    folder = Path(folder)
    return (folder / "config.json").is_file() and (folder / "model.safetensors").is_file()


def write_checkpoint(
    folder: str | Path, config: FunFlow6DConfig, state: dict[str, torch.Tensor]
) -> Path:
    """Write a configuration and the network's ``state_dict`` to ``folder`` (created).

    Returns:
        The folder.
    """
    from safetensors.torch import save_file

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    tensors = {k: v.detach().cpu().contiguous() for k, v in state.items()}
    tmp = folder / "model.safetensors.tmp"
    save_file(tensors, str(tmp), metadata={"format": CHECKPOINT_FORMAT})
    tmp.replace(folder / "model.safetensors")
    (folder / "config.json").write_text(json.dumps(config.to_json(), indent=1))
    return folder


def read_checkpoint(folder: str | Path) -> tuple[FunFlow6DConfig, dict[str, torch.Tensor]]:
    """The configuration and the network's ``state_dict`` written by :func:`write_checkpoint`.

    Raises:
        MissingWeightsError: ``folder`` holds no checkpoint.
    """
    from safetensors.torch import load_file

    folder = Path(folder)
    if not is_checkpoint(folder):
        raise MissingWeightsError(
            f"{folder} holds no FunFlow6D checkpoint (config.json + model.safetensors); "
            "train one with `poseflow train`"
        )
    config = FunFlow6DConfig.from_json(folder / "config.json")
    return config, load_file(str(folder / "model.safetensors"))
