"""On-disk caches that never lie: content keys, one folder per key, written aside then renamed.

A cache entry is only reused when everything that made it is the same, so its key hashes all of
its inputs: file contents, or the paths, sizes and modification times of files too many to read
(:func:`files_key`), arrays (:func:`arrays_key`) and the configuration (:func:`json_key`).
Entries live in one folder per key (:func:`cache_entry`), so several coexist, and each is written
into a temporary sibling folder that is renamed into place when complete
(:func:`atomic_directory`): a crash never leaves a half-written entry that a later run would read.
Single files (checkpoints, results, logs) are written the same way by :func:`atomic_write`.
:func:`read_entry` and :func:`write_entry` wrap both for a cache that is an optimisation only: an
entry damaged after the fact is dropped with a warning (and computed again), and a cache that
cannot be written gives a warning instead of failing the run.
"""

from __future__ import annotations

import contextlib
import hashlib
import itertools
import json
import os
import shutil
import tempfile
import warnings
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

__all__ = [
    "KEY_LENGTH",
    "arrays_key",
    "atomic_directory",
    "atomic_write",
    "cache_entry",
    "files_key",
    "json_key",
    "read_entry",
    "update_with_file",
    "write_entry",
]

T = TypeVar("T")

#: Hex digits of a cache key.
KEY_LENGTH = 16

#: Numbers the temporary files of :func:`atomic_write` within a process.
_WRITES = itertools.count()


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
            update_with_file(h, p)
        else:
            h.update(f"{st.st_mtime_ns}\0".encode())
    return h.hexdigest()[:KEY_LENGTH]


def update_with_file(h: Any, path: str | os.PathLike[str]) -> None:
    """Feed the bytes of the file at ``path`` to the hash ``h``, 1 MiB at a time.

    Example:
        >>> p = Path(tempfile.mkdtemp()) / "a.bin"; _ = p.write_bytes(b"abc")
        >>> h = hashlib.sha1(); update_with_file(h, p)
        >>> h.hexdigest() == hashlib.sha1(b"abc").hexdigest()
        True
    """
    with open(path, "rb") as f:
        while block := f.read(1 << 20):
            h.update(block)


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


def atomic_write(path: str | os.PathLike[str], write: Callable[[Path], Any]) -> Path:
    """Write a file atomically: ``write(tmp)`` fills a hidden sibling, then renamed onto ``path``.

    The temporary file is flushed to disk before the rename, so ``path`` only ever names a
    complete file; on an exception it is removed and ``path`` is left as it was. ``write``
    creates the file; it then gets the permissions umask gives any new file, even where the
    writer made it private (safetensors' ``save_file`` writes 0600, which would hide a model on a
    shared disk from the rest of the group).

    Args:
        path: the final file; its folder must exist.
        write: writes the whole file at the path it is given.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Example:
        >>> d = Path(tempfile.mkdtemp())
        >>> p = atomic_write(d / "a.txt", lambda tmp: tmp.write_text("hi"))
        >>> p.read_text(), sorted(x.name for x in d.iterdir())
        ('hi', ['a.txt'])
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}-{next(_WRITES)}.tmp")
    try:
        write(tmp)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def read_entry(
    folder: str | os.PathLike[str], read: Callable[[Path], T | None], *, what: str
) -> T | None:
    """Read a cache entry, or None when it is absent or damaged (a damaged one is removed).

    Entries are written whole by :func:`write_entry`, so a damaged one was broken after the fact
    (a disk that filled up, a copy cut short): it is removed with a warning, so that the caller
    computes the data again and writes a new entry in its place.

    Args:
        folder: the entry (see :func:`cache_entry`).
        read: reads the entry's folder; returns None for an entry that does not apply, raises
            ``OSError``, ``ValueError`` (JSON, CheckpointError), ``KeyError`` or a safetensors
            error for a damaged one.
        what: what the entry holds, for the warning (e.g. ``"object 5"``).

    Returns:
        What ``read`` returned, or None.

    Example:
        >>> d = Path(tempfile.mkdtemp()) / "entry"
        >>> read = lambda f: json.loads((f / "x.json").read_text())
        >>> read_entry(d, read, what="x") is None  # absent
        True
        >>> with atomic_directory(d) as tmp:
        ...     _ = (tmp / "x.json").write_text('{"a": 1}')
        >>> read_entry(d, read, what="x")
        {'a': 1}
    """
    from safetensors import SafetensorError

    folder = Path(folder)
    if not folder.is_dir():
        return None
    try:
        return read(folder)
    except (OSError, ValueError, KeyError, SafetensorError) as exc:
        warnings.warn(
            f"{what}: the cache entry {folder} is damaged ({exc}); it is computed again",
            stacklevel=2,
        )
        shutil.rmtree(folder, ignore_errors=True)
        return None


def write_entry(folder: str | os.PathLike[str], write: Callable[[Path], Any], *, what: str) -> bool:
    """Write a cache entry atomically (:func:`atomic_directory`); warn when it cannot be written.

    Args:
        folder: the entry (see :func:`cache_entry`).
        write: writes the entry's files into the folder it is given.
        what: what the entry holds, for the warning (e.g. ``"object 5"``).

    Returns:
        Whether the entry is on disk now (False: the cache folder cannot be written, and the data
        stays in memory only).

    Example:
        >>> d = Path(tempfile.mkdtemp()) / "entry"
        >>> write_entry(d, lambda tmp: (tmp / "x.json").write_text("{}"), what="x")
        True
        >>> sorted(p.name for p in d.iterdir())
        ['x.json']
    """
    try:
        with atomic_directory(folder) as tmp:
            write(tmp)
    except OSError as exc:
        warnings.warn(f"{what} is not cached ({exc})", stacklevel=2)
        return False
    return True
