"""Helpers shared by ``poseflow prepare``, ``train`` and ``predict``.

- ``--device``: :func:`add_device_argument` and :func:`resolve_device`;
- the model configuration: :func:`add_config_arguments` registers ``--config`` (a JSON file of
  :class:`~poseflow.models.FunFlow6DConfig` fields), ``--preset`` and a few common fields as
  flags, and ``--set KEY=VALUE`` for any field; :func:`build_config` turns them into a config;
- the objects of a BOP dataset: :func:`check_dataset`, :func:`load_object_models` (``models/`` and
  ``models_info.json``, millimetres converted to metres) and :func:`object_cache_dir`, the folder
  where the prepared objects of one dataset's models are cached, keyed by the content of
  ``models/`` so that two datasets never share an object cache by mistake.

Everything heavy (torch, the model) is imported inside the functions, so that registering the
subcommands stays cheap.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

__all__ = [
    "CONFIG_FLAGS",
    "add_config_arguments",
    "add_device_argument",
    "build_config",
    "check_dataset",
    "config_requested",
    "dataset_fingerprint",
    "load_object_models",
    "models_fingerprint",
    "object_cache_dir",
    "parse_set",
    "resolve_device",
]

#: ``--flag`` name -> :class:`~poseflow.models.FunFlow6DConfig` field set by it.
CONFIG_FLAGS: dict[str, str] = {
    "preset": "dit_preset",
    "num_points": "num_points",
    "geometric_encoder": "geometric_encoder",
    "appearance_encoder": "appearance_encoder",
    "reducer": "reducer",
    "fusion": "fusion",
    "crop_size": "crop_size",
    "query_views": "query_views",
}


# ------------------------------------------------------------------------------ device


def add_device_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``--device`` (``auto``, ``cpu``, ``cuda``, ``cuda:1``, ...) to ``parser``."""
    parser.add_argument(
        "--device",
        default="auto",
        help="torch device: auto (this process's GPU when there is one, else cpu), cpu, cuda, "
        "cuda:N (default: auto)",
    )


def resolve_device(name: str) -> Any:
    """The ``torch.device`` that ``--device NAME`` asks for.

    ``auto`` and a bare ``cuda`` pick the GPU of this process (``cuda:LOCAL_RANK`` under
    ``torchrun``); ``auto`` falls back to the CPU.

    Args:
        name: the option's value.

    Returns:
        The ``torch.device``.

    Raises:
        ValueRangeError: a malformed name, or a GPU asked for where CUDA is not available.

    Example:
        >>> resolve_device("cpu")
        device(type='cpu')
    """
    import torch

    from poseflow.errors import ValueRangeError

    local = int(os.environ.get("LOCAL_RANK", "0") or 0)
    if name == "auto":
        return torch.device(f"cuda:{local}" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except (RuntimeError, ValueError) as exc:
        raise ValueRangeError(f"--device {name!r} is not a torch device ({exc})") from None
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueRangeError(
                f"--device {name}: CUDA is not available here; use --device cpu (or auto)"
            )
        if device.index is None:
            device = torch.device(f"cuda:{local}")
        if device.index >= torch.cuda.device_count():
            raise ValueRangeError(
                f"--device {device}: only {torch.cuda.device_count()} CUDA device(s) here"
            )
    return device


# ------------------------------------------------------------------------------ configuration


def add_config_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--config``, ``--preset``, the common field flags and ``--set`` to ``parser``."""
    group = parser.add_argument_group(
        "model configuration",
        "Start from --config (a JSON file of FunFlow6DConfig fields; default: the offline "
        "defaults FPFH + dense SIFT + PCA, gated fusion, small DiT), then apply the flags below "
        "and every --set in order.",
    )
    group.add_argument(
        "--config", type=Path, default=None, metavar="JSON", help="FunFlow6DConfig JSON file"
    )
    group.add_argument(
        "--preset", default=None, help="DiT preset: paper, small or tiny (dit_preset)"
    )
    group.add_argument("--num-points", type=int, default=None, help="points per cloud N")
    group.add_argument(
        "--geometric-encoder", default=None, help="fpfh, gedi:PATH or none (geometric_encoder)"
    )
    group.add_argument(
        "--appearance-encoder",
        default=None,
        help="dsift, dinov2:NAME_OR_PATH or none (appearance_encoder)",
    )
    group.add_argument("--reducer", default=None, help="umap, pca or identity")
    group.add_argument("--fusion", default=None, help="gated, cross, concat_mlp or sum")
    group.add_argument("--crop-size", type=int, default=None, help="appearance crop side, px")
    group.add_argument("--query-views", type=int, default=None, help="views rendered per object")
    group.add_argument(
        "--set",
        dest="set_fields",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="any config field, VALUE read as JSON when it parses (e.g. --set steps=10 --set "
        "'net={\"fusion_heads\": 2}' --set icp_thresholds=[]); repeatable",
    )


def parse_set(items: Iterable[str]) -> dict[str, Any]:
    """Parse ``--set KEY=VALUE`` items; a VALUE that is valid JSON is decoded, else kept a string.

    Raises:
        ValueRangeError: an item without ``=`` or with an empty key.

    Example:
        >>> parse_set(["steps=10", "fusion=sum", 'net={"fusion_heads": 2}'])
        {'steps': 10, 'fusion': 'sum', 'net': {'fusion_heads': 2}}
    """
    from poseflow.errors import ValueRangeError

    out: dict[str, Any] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ValueRangeError(f"--set takes KEY=VALUE, got {item!r}")
        try:
            out[key] = json.loads(raw)
        except json.JSONDecodeError:
            out[key] = raw
    return out


def config_requested(args: argparse.Namespace) -> bool:
    """Whether the command line names any part of the configuration."""
    flags = any(getattr(args, f, None) is not None for f in CONFIG_FLAGS)
    return args.config is not None or flags or bool(args.set_fields)


def build_config(args: argparse.Namespace) -> Any:
    """The :class:`~poseflow.models.FunFlow6DConfig` described by the configuration options.

    Args:
        args: parsed arguments of a parser given :func:`add_config_arguments`.

    Returns:
        The validated configuration.

    Raises:
        MissingFileError: ``--config`` names no file.
        ValueRangeError: the file is not valid JSON, or a field name or value is invalid.
    """
    from poseflow.errors import MissingFileError, ValueRangeError
    from poseflow.models import FunFlow6DConfig

    data: dict[str, Any] = {}
    if args.config is not None:
        path = Path(args.config)
        if not path.is_file():
            raise MissingFileError(f"--config {path}: no such file")
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise ValueRangeError(f"--config {path} is not valid JSON: {exc}") from None
        if not isinstance(data, dict):
            raise ValueRangeError(f"--config {path} must hold a JSON object of config fields")
    for flag, field_name in CONFIG_FLAGS.items():
        value = getattr(args, flag, None)
        if value is not None:
            data[field_name] = value
    data.update(parse_set(args.set_fields))
    try:
        return FunFlow6DConfig.from_json(data)
    except TypeError as exc:  # a value of the wrong kind reaching the dataclass
        raise ValueRangeError(f"invalid FunFlow6D configuration: {exc}") from None


# ------------------------------------------------------------------------------ datasets


def check_dataset(root: str | Path, split: str | None = None) -> Path:
    """Check that ``root`` looks like a BOP dataset folder (and holds ``split``).

    Args:
        root: the dataset folder.
        split: a split folder that must exist, or None.

    Returns:
        ``root`` as a :class:`~pathlib.Path`.

    Raises:
        MissingFileError: the folder, its ``models/models_info.json`` or the split is missing.
    """
    from poseflow.errors import MissingFileError

    root = Path(root)
    if not root.is_dir():
        raise MissingFileError(f"dataset folder {root} does not exist")
    if not (root / "models" / "models_info.json").is_file():
        raise MissingFileError(
            f"{root} is not a BOP dataset folder: {root / 'models' / 'models_info.json'} is "
            "missing (generate one with `poseflow synth` or download a BOP dataset)"
        )
    if split is not None and not (root / split).is_dir():
        have = sorted(p.name for p in root.iterdir() if p.is_dir() and p.name != "models")
        raise MissingFileError(f"{root} has no split {split!r} (folders: {', '.join(have)})")
    return root


def load_object_models(
    root: str | Path,
    *,
    obj_ids: Iterable[int] | None = None,
    num_points: int = 2048,
    progress: bool = False,
) -> dict[int, Any]:
    """Load the object models of a BOP dataset folder as ``{obj_id: ObjectModel}`` in metres.

    Args:
        root: the dataset folder (``models/obj_XXXXXX.ply`` and ``models/models_info.json``).
        obj_ids: load only these objects (default: every object of ``models_info.json``).
        num_points: points of each model's surface sample (the ICP target of FunFlow6D).
        progress: show a progress bar.

    Returns:
        ``{obj_id: ObjectModel}`` with the symmetries of ``models_info.json``.

    Raises:
        MissingFileError: the folder, ``models_info.json`` or a model file is missing.
        ValueRangeError: an object id of ``obj_ids`` has no entry in ``models_info.json``.
    """
    from tqdm.auto import tqdm

    from poseflow.data.bop import read_models_info
    from poseflow.data.objects import ObjectModel
    from poseflow.errors import MissingFileError, ValueRangeError

    root = check_dataset(root)
    infos = read_models_info(root / "models" / "models_info.json")
    wanted = sorted(infos) if obj_ids is None else sorted({int(o) for o in obj_ids})
    unknown = [o for o in wanted if o not in infos]
    if unknown:
        raise ValueRangeError(f"objects {unknown} are not in {root / 'models/models_info.json'}")
    out = {}
    for obj_id in tqdm(wanted, desc="load models", disable=not progress):
        path = root / "models" / f"obj_{obj_id:06d}.ply"
        if not path.is_file():
            raise MissingFileError(f"missing model of obj {obj_id}: {path}")
        out[obj_id] = ObjectModel.from_file(
            path, scale=1e-3, info=infos[obj_id], num_points=num_points, name=f"obj_{obj_id:06d}"
        )
    return out


def _hash_files(paths: Iterable[Path], h: Any) -> None:
    for p in paths:
        h.update(p.name.encode())
        with open(p, "rb") as f:
            while block := f.read(1 << 20):
                h.update(block)


def models_fingerprint(root: str | Path) -> str:
    """A short hash of the content of ``root/models`` (meshes, textures, ``models_info.json``).

    Example:
        >>> import tempfile
        >>> d = Path(tempfile.mkdtemp()); (d / "models").mkdir()
        >>> _ = (d / "models" / "models_info.json").write_text("{}")
        >>> len(models_fingerprint(d))
        12
    """
    folder = Path(root) / "models"
    h = hashlib.sha1()
    _hash_files(sorted(p for p in folder.iterdir() if p.is_file()), h)
    return h.hexdigest()[:12]


def dataset_fingerprint(root: str | Path, split: str) -> str:
    """A short hash of a split's annotations (every scene's ``scene_gt.json`` and camera file).

    The images are not read: a regenerated split almost always changes its poses.
    """
    split_path = Path(root) / split
    h = hashlib.sha1(models_fingerprint(root).encode())
    for scene in sorted(p for p in split_path.iterdir() if p.is_dir() and p.name.isdigit()):
        h.update(scene.name.encode())
        files = [scene / n for n in ("scene_camera.json", "scene_gt.json")]
        _hash_files([p for p in files if p.is_file()], h)
    return h.hexdigest()[:12]


def object_cache_dir(base: str | Path, root: str | Path) -> Path:
    """Where the prepared objects of dataset ``root`` are cached under ``base``.

    ``base/objects/<hash of root/models>``; :meth:`~poseflow.models.FunFlow6D.prepare_objects`
    then keys each object by the configuration fields it depends on.
    """
    return Path(base) / "objects" / models_fingerprint(root)
