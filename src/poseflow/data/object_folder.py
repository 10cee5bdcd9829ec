"""The objects of a BOP dataset folder: the folder's check, its models, their fingerprints.

:func:`check_dataset` says early and clearly when a folder is not a BOP dataset;
:func:`load_object_models` reads ``models/`` (meshes and ``models_info.json``, millimetres
converted to metres) as ``{obj_id: ObjectModel}``. :func:`models_fingerprint` and
:func:`dataset_fingerprint` are short hashes of the content of ``models/`` and of a split's
annotations, and :func:`object_cache_dir` is the folder where the prepared objects of one
dataset's models are cached, keyed by that content so that two datasets never share an object
cache by mistake.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from poseflow._cache import update_with_file
from poseflow._progress import progress as progress_loop
from poseflow.data.bop import read_models_info
from poseflow.data.objects import ObjectModel
from poseflow.errors import MissingFileError, ValueRangeError

__all__ = [
    "FINGERPRINT_LENGTH",
    "check_dataset",
    "dataset_fingerprint",
    "load_object_models",
    "models_fingerprint",
    "object_cache_dir",
]

#: Hex digits of a fingerprint.
FINGERPRINT_LENGTH = 12


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
) -> dict[int, ObjectModel]:
    """Load the object models of a BOP dataset folder as ``{obj_id: ObjectModel}`` in metres.

    Args:
        root: the dataset folder (``models/obj_XXXXXX.ply`` and ``models/models_info.json``).
        obj_ids: load only these objects (default: every object of ``models_info.json``).
        num_points: points ``P`` of each model's surface sample (the ICP target of FunFlow6D).
        progress: show a progress bar.

    Returns:
        ``{obj_id: ObjectModel}`` with the symmetries of ``models_info.json``.

    Raises:
        MissingFileError: the folder, ``models_info.json`` or a model file is missing.
        ValueRangeError: an object id of ``obj_ids`` has no entry in ``models_info.json``.
    """
    root = check_dataset(root)
    infos = read_models_info(root / "models" / "models_info.json")
    wanted = sorted(infos) if obj_ids is None else sorted({int(o) for o in obj_ids})
    unknown = [o for o in wanted if o not in infos]
    if unknown:
        raise ValueRangeError(f"objects {unknown} are not in {root / 'models/models_info.json'}")
    out = {}
    for obj_id in progress_loop(wanted, total=len(wanted), desc="load models", enabled=progress):
        path = root / "models" / f"obj_{obj_id:06d}.ply"
        if not path.is_file():
            raise MissingFileError(f"missing model of obj {obj_id}: {path}")
        out[obj_id] = ObjectModel.from_file(
            path, scale=1e-3, info=infos[obj_id], num_points=num_points, name=f"obj_{obj_id:06d}"
        )
    return out


def _update_with_named_files(h: Any, paths: Iterable[Path]) -> None:
    """Feed each file's name, then its bytes, to the hash ``h``."""
    for p in paths:
        h.update(p.name.encode())
        update_with_file(h, p)


def models_fingerprint(root: str | Path) -> str:
    """A short hash of the content of ``root/models`` (meshes, textures, ``models_info.json``).

    File names and bytes count, not their paths or times, so a copied dataset keeps its
    fingerprint.

    Example:
        >>> import tempfile
        >>> d = Path(tempfile.mkdtemp()); (d / "models").mkdir()
        >>> _ = (d / "models" / "models_info.json").write_text("{}")
        >>> len(models_fingerprint(d))
        12
    """
    folder = Path(root) / "models"
    h = hashlib.sha1()
    _update_with_named_files(h, sorted(p for p in folder.iterdir() if p.is_file()))
    return h.hexdigest()[:FINGERPRINT_LENGTH]


def dataset_fingerprint(root: str | Path, split: str) -> str:
    """A short hash of the models and a split's annotations (each scene's GT and camera files).

    The images are not read: a regenerated split almost always changes its poses.
    """
    split_path = Path(root) / split
    h = hashlib.sha1(models_fingerprint(root).encode())
    for scene in sorted(p for p in split_path.iterdir() if p.is_dir() and p.name.isdigit()):
        h.update(scene.name.encode())
        files = [scene / n for n in ("scene_camera.json", "scene_gt.json")]
        _update_with_named_files(h, [p for p in files if p.is_file()])
    return h.hexdigest()[:FINGERPRINT_LENGTH]


def object_cache_dir(base: str | Path, root: str | Path) -> Path:
    """Where the prepared objects of dataset ``root`` are cached under ``base``.

    ``base/objects/<models_fingerprint(root)>``; :meth:`FunFlow6D.prepare_objects
    <poseflow.models.FunFlow6D.prepare_objects>` then keys each object's entry by its mesh
    (content and scale) and the configuration fields it depends on (``obj_XXXXXX/<key>/``).

    Example:
        >>> import tempfile
        >>> d = Path(tempfile.mkdtemp()); (d / "models").mkdir()
        >>> object_cache_dir("run/model", d).parent
        PosixPath('run/model/objects')
    """
    return Path(base) / "objects" / models_fingerprint(root)
