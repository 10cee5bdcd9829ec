"""Cache keys and atomic cache entries (``poseflow._cache``)."""

from __future__ import annotations

import json
import os
import stat

import numpy as np
import pytest
import torch

from poseflow._cache import (
    arrays_key,
    atomic_directory,
    atomic_write,
    cache_entry,
    files_key,
    json_key,
    read_entry,
    write_entry,
)


def test_files_key_changes_with_content_size_mtime_and_place(tmp_path):
    a = tmp_path / "rgb" / "000000.png"
    a.parent.mkdir()
    a.write_bytes(b"abcd")
    key = files_key([a])
    assert files_key([a]) == key
    os.utime(a, ns=(1, 1))
    assert files_key([a]) != key  # rewritten in place: another mtime
    stamp = files_key([a])
    a.write_bytes(b"abcde")
    os.utime(a, ns=(1, 1))
    assert files_key([a]) != stamp  # another size
    before = files_key([a], content=True)
    a.write_bytes(b"abcdf")
    os.utime(a, ns=(1, 1))
    assert files_key([a], content=True) != before  # same size and mtime, other bytes
    b = tmp_path / "other" / "000000.png"
    b.parent.mkdir()
    b.write_bytes(a.read_bytes())
    assert files_key([b], content=True) != files_key([a], content=True)  # another path
    assert files_key([a, b]) == files_key([b, a])


def test_json_and_array_keys():
    assert json_key({"a": 1, "b": 2}) == json_key({"b": 2, "a": 1})
    assert json_key({"a": 1}) != json_key({"a": 2})
    v = np.arange(6.0).reshape(2, 3)
    assert arrays_key({"v": v}) == arrays_key({"v": v.copy()})
    assert arrays_key({"v": v}) != arrays_key({"v": v * 0.001})  # another scale
    assert arrays_key({"v": v}) != arrays_key({"v": v.astype(np.float32)})


def test_entries_of_other_keys_sit_side_by_side(tmp_path):
    one = cache_entry(tmp_path, "obj_000001", "mesh-a", "config")
    two = cache_entry(tmp_path, "obj_000001", "mesh-b", "config")
    assert one != two and one.parent == two.parent == tmp_path / "obj_000001"
    assert cache_entry(tmp_path, "obj_000001", "mesh-a", "config") == one


def test_atomic_directory_leaves_nothing_behind_on_failure(tmp_path):
    entry = tmp_path / "obj_000001" / "k"
    with pytest.raises(RuntimeError):
        with atomic_directory(entry) as tmp:
            (tmp / "object.json").write_text("{")
            raise RuntimeError("killed while writing")
    assert not entry.exists()
    assert list(entry.parent.iterdir()) == []  # no half-written folder
    with atomic_directory(entry) as tmp:
        (tmp / "object.json").write_text("{}")
    assert (entry / "object.json").read_text() == "{}"
    with atomic_directory(entry) as tmp:  # written meanwhile by another process: kept
        (tmp / "object.json").write_text('{"second": 1}')
    assert (entry / "object.json").read_text() == "{}"
    assert [p.name for p in entry.parent.iterdir()] == ["k"]


def test_a_damaged_entry_is_dropped_with_a_warning_and_written_again(tmp_path):
    entry = tmp_path / "obj_000001" / "k"

    def read(folder):
        return json.loads((folder / "object.json").read_text())

    assert read_entry(entry, read, what="object 1") is None  # absent: no warning
    assert write_entry(entry, lambda tmp: (tmp / "object.json").write_text('{"a": 1}'), what="x")
    assert read_entry(entry, read, what="object 1") == {"a": 1}
    (entry / "object.json").write_text('{"a": ')  # damaged after the fact
    with pytest.warns(UserWarning, match="object 1: the cache entry .* is damaged"):
        assert read_entry(entry, read, what="object 1") is None
    assert not entry.exists()  # so that a new entry takes its place
    assert write_entry(entry, lambda tmp: (tmp / "object.json").write_text('{"a": 2}'), what="x")
    assert read_entry(entry, read, what="object 1") == {"a": 2}


def test_a_cache_that_cannot_be_written_is_a_warning(tmp_path):
    blocked = tmp_path / "a_file"
    blocked.write_text("")
    with pytest.warns(UserWarning, match="object 1 is not cached"):
        assert not write_entry(blocked / "obj_000001" / "k", lambda tmp: None, what="object 1")
    with pytest.raises(ZeroDivisionError):  # an error of the writer itself is not hidden
        write_entry(tmp_path / "e", lambda tmp: 1 / 0, what="object 1")
    assert not (tmp_path / "e").exists()


def test_atomic_write_gives_the_file_the_permissions_of_the_umask(tmp_path):
    """A writer that makes its file private (safetensors' 0600) still leaves it group-readable."""
    from safetensors.torch import save_file

    old = os.umask(0o022)
    try:
        path = atomic_write(
            tmp_path / "w.safetensors", lambda t: save_file({"x": torch.ones(1)}, t)
        )
    finally:
        os.umask(old)
    assert stat.S_IMODE(path.stat().st_mode) == 0o644
