"""On-disk caches that never lie: content keys, one folder per key, written aside then renamed.

A cache entry is only reused when everything that made it is the same, so its key hashes all of
its inputs: file contents, or the paths, sizes and modification times of files too many to read
(:func:`files_key`), arrays (:func:`arrays_key`) and the configuration (:func:`json_key`).
Entries live in one folder per key (:func:`cache_entry`), so several coexist, and each is written
into a temporary sibling folder that is renamed into place when complete
(:func:`atomic_directory`): a crash never leaves a half-written entry that a later run would read.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "KEY_LENGTH",
    "arrays_key",
    "atomic_directory",
    "cache_entry",
    "files_key",
    "json_key",
]

#: Hex digits of a cache key.
KEY_LENGTH = 16


def json_key(data: Any) -> str:
    """A key of JSON-serialisable data (dict keys sorted, so their order does not matter).

    Example:
        >>> json_key({"a": 1, "b": [2, 3]}) == json_key({"b": [2, 3], "a": 1})
        True
        >>> len(json_key({}))
        16
    """
    text = json.dumps(data, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha1(text.encode()).hexdigest()[:KEY_LENGTH]


def arrays_key(arrays: Mapping[str, Any]) -> str:
    """A key of named arrays (numpy arrays, tensors or None): names, dtypes, shapes and bytes.

    Example:
        >>> a = {"v": np.zeros((2, 3)), "uv": None}
        >>> arrays_key(a) == arrays_key({"v": np.zeros((2, 3)), "uv": None})
        True
        >>> arrays_key(a) == arrays_key({"v": np.ones((2, 3)), "uv": None})
        False
    """
    h = hashlib.sha1()
    for name in sorted(arrays):
        value = arrays[name]
        h.update(name.encode() + b"\0")
        if value is None:
            h.update(b"none\0")
            continue
        if hasattr(value, "detach"):  # a torch tensor
            value = value.detach().cpu().numpy()
        a = np.ascontiguousarray(value)
        h.update(f"{a.dtype.str}{a.shape}\0".encode())
        h.update(a.tobytes())
    return h.hexdigest()[:KEY_LENGTH]


def files_key(paths: Iterable[str | os.PathLike[str]], *, content: bool = False) -> str:
    """A key of files: each one's resolved path, size and modification time (or its bytes).

    Args:
        paths: the files (their order does not matter).
        content: hash the bytes instead of the modification time (slower, but survives a copy).

    Returns:
        The key; it changes when a file is added, removed, moved, resized or rewritten.

    Example:
        >>> d = Path(tempfile.mkdtemp())
        >>> _ = (d / "a.png").write_bytes(b"1")
        >>> k = files_key([d / "a.png"])
        >>> _ = (d / "b.png").write_bytes(b"22")
        >>> k == files_key([d / "a.png"]), k == files_key([d / "a.png", d / "b.png"])
        (True, False)
    """
    h = hashlib.sha1()
    for p in sorted(Path(p).resolve() for p in paths):
        st = p.stat()
        h.update(f"{p}\0{st.st_size}\0".encode())
        if content:
            with open(p, "rb") as f:
                while block := f.read(1 << 20):
                    h.update(block)
        else:
            h.update(f"{st.st_mtime_ns}\0".encode())
    return h.hexdigest()[:KEY_LENGTH]


def cache_entry(base: str | os.PathLike[str], name: str, *keys: str) -> Path:
    """The folder of one cache entry: ``base/name/<key of keys>``.

    Args:
        base: the cache folder.
        name: the entry's name (e.g. ``obj_000001``); entries of other keys sit beside it.
        keys: the keys of everything the entry depends on.

    Example:
        >>> cache_entry("cache", "obj_000001", "ab", "cd").parent
        PosixPath('cache/obj_000001')
    """
    return Path(base) / name / json_key(list(keys))


@contextlib.contextmanager
def atomic_directory(folder: str | os.PathLike[str]) -> Iterator[Path]:
    """Write a folder atomically: fill the yielded temporary folder, it is renamed on success.

    The temporary folder is a hidden sibling of ``folder``; on an exception it is removed and
    ``folder`` is left as it was. When ``folder`` already exists at the end (another process
    wrote the same entry meanwhile), it is kept and the new copy is dropped.

    Args:
        folder: the final folder (its parents are created).

    Yields:
        The temporary folder to write into.

    Example:
        >>> d = Path(tempfile.mkdtemp()) / "entry"
        >>> with atomic_directory(d) as tmp:
        ...     _ = (tmp / "x.json").write_text("{}")
        >>> sorted(p.name for p in d.iterdir()), sorted(p.name for p in d.parent.iterdir())
        (['x.json'], ['entry'])
    """
    folder = Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", suffix=".tmp", dir=folder.parent))
    try:
        yield tmp
        try:
            os.replace(tmp, folder)
        except OSError:
            if not folder.is_dir():
                raise
            shutil.rmtree(tmp, ignore_errors=True)  # written meanwhile by someone else: keep it
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
