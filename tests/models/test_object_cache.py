"""The prepared-object cache: one entry per object, mesh, scale and configuration, written whole."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import pytest
import torch

import poseflow
from poseflow.data.demo_objects import demo_objects
from poseflow.data.objects import ObjectModel
from poseflow.models import FunFlow6D, FunFlow6DConfig, load_prepared_object
from poseflow.models.objects import (
    PreparedObject,
    object_cache_entry,
    object_fingerprint,
    prepare_objects,
)

#: Geometric features only: preparing takes well under a second.
LIGHT = FunFlow6DConfig(num_points=32, appearance_encoder="none", verifier=None)


@pytest.fixture(scope="module")
def bracket():
    return demo_objects(num_points=512, names=["bracket"])[0]


@pytest.fixture(scope="module")
def larger(bracket):
    """The same mesh read with another scale (millimetres taken for half-millimetres)."""
    return ObjectModel.from_mesh(bracket.mesh.scaled(2.0), num_points=512)


@pytest.fixture(scope="module")
def box():
    return demo_objects(num_points=512, names=["labelled_box"])[0]


def _prepare(models, cache, config=LIGHT):
    model = FunFlow6D(config)
    return prepare_objects(
        models,
        config,
        geometric_encoder=model.geometric_encoder,
        appearance_encoder=model.appearance_encoder,
        cache_dir=cache,
        progress=False,
    )


def _entries(cache, obj_id=1, name="object.json"):
    """The complete entries (a write in progress is a hidden folder)."""
    files = (Path(cache) / f"obj_{obj_id:06d}").glob(f"*/{name}")
    return sorted(p.parent for p in files if not p.parent.name.startswith("."))


def test_another_mesh_or_scale_never_reads_the_first_entry(bracket, larger, box, tmp_path):
    first = _prepare({1: bracket}, tmp_path)[1]
    assert first.diameter == pytest.approx(bracket.diameter)
    for other in (larger, box):  # another scale, another mesh, under the same object id
        again = _prepare({1: other}, tmp_path)[1]
        assert again.diameter == pytest.approx(other.diameter)
        fresh = _prepare({1: other}, None)[1]
        assert torch.equal(again.points, fresh.points)
    # the three entries sit side by side, and each is read back by its own mesh
    entries = _entries(tmp_path)
    assert len(entries) == 3 and len({p.parent for p in entries}) == 1
    stamps = [(p / "object.safetensors").stat().st_mtime_ns for p in entries]
    for model in (bracket, larger, box):
        cached = load_prepared_object(tmp_path, 1, model, LIGHT)
        assert cached is not None and cached.diameter == pytest.approx(model.diameter)
        assert torch.equal(cached.points, _prepare({1: model}, tmp_path)[1].points)
    assert [(p / "object.safetensors").stat().st_mtime_ns for p in entries] == stamps
    # another configuration is another entry too
    _prepare({1: bracket}, tmp_path, LIGHT.replace(num_points=16))
    assert len(_entries(tmp_path)) == 4
    assert load_prepared_object(tmp_path, 1, bracket, LIGHT.replace(num_points=8)) is None


def test_an_entry_of_the_old_layout_is_not_read(bracket, box, tmp_path):
    fingerprint = object_fingerprint(LIGHT)
    old = _prepare({1: box}, None)[1]
    old.save(tmp_path / "obj_000001", fingerprint=fingerprint)  # files right in obj_000001/
    prepared = _prepare({1: bracket}, tmp_path)[1]
    assert prepared.diameter == pytest.approx(bracket.diameter)
    assert len(_entries(tmp_path)) == 1


def test_a_killed_write_leaves_no_entry_that_looks_complete(bracket, tmp_path):
    script = textwrap.dedent(
        """
        import os, signal, sys
        from pathlib import Path
        from poseflow.data.demo_objects import demo_objects
        from poseflow.models import FunFlow6D, FunFlow6DConfig
        from poseflow.models.objects import PreparedObject

        def save(self, folder, *, fingerprint):
            (Path(folder) / "object.json").write_text('{"diameter": 0.1, "config": ')
            os.kill(os.getpid(), signal.SIGKILL)  # killed while writing the entry

        PreparedObject.save = save
        config = FunFlow6DConfig(num_points=32, appearance_encoder="none", verifier=None)
        bracket = demo_objects(num_points=512, names=["bracket"])[0]
        FunFlow6D(config).prepare_objects({1: bracket}, cache_dir=sys.argv[1], progress=False)
        """
    )
    src = str(Path(poseflow.__file__).parents[1])
    env = {**os.environ, "PYTHONPATH": src, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(
        [sys.executable, "-c", script, str(tmp_path)], env=env, capture_output=True, check=False
    )
    assert proc.returncode == -signal.SIGKILL, proc.stderr.decode()[-2000:]
    folder = tmp_path / "obj_000001"
    assert folder.is_dir() and all(p.name.startswith(".") for p in folder.iterdir())
    assert load_prepared_object(tmp_path, 1, bracket, LIGHT) is None
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing looked damaged: prepared again, silently
        prepared = _prepare({1: bracket}, tmp_path)[1]
    assert prepared.diameter == pytest.approx(bracket.diameter)
    assert len(_entries(tmp_path)) == 1


def test_a_damaged_entry_is_prepared_again_with_a_warning(bracket, tmp_path):
    first = _prepare({1: bracket}, tmp_path)[1]
    (entry,) = _entries(tmp_path)
    assert entry == object_cache_entry(tmp_path, 1, bracket, object_fingerprint(LIGHT))
    data = entry / "object.safetensors"
    data.write_bytes(data.read_bytes()[:100])  # a copy cut short
    with pytest.warns(UserWarning, match="damaged"):
        again = _prepare({1: bracket}, tmp_path)[1]
    assert torch.equal(again.points, first.points)
    assert PreparedObject.load(entry, fingerprint=object_fingerprint(LIGHT)) is not None


def test_a_cache_that_cannot_be_written_warns_and_keeps_the_objects(bracket, tmp_path):
    blocked = tmp_path / "a_file"
    blocked.write_text("")
    with pytest.warns(UserWarning, match="object 1 is not cached"):
        prepared = _prepare({1: bracket}, blocked)
    assert prepared[1].diameter == pytest.approx(bracket.diameter)


def test_a_cached_preparation_equals_a_fresh_one_bit_for_bit(box, tmp_path):
    config = FunFlow6DConfig(num_points=32, query_views=2, crop_size=32, verifier=None)
    fresh = _prepare({1: box}, tmp_path, config)[1]  # cold: computed, then written
    cached = _prepare({1: box}, tmp_path, config)[1]  # warm: read back
    assert _entries(tmp_path) and fresh.bank is not None
    assert torch.equal(fresh.bank.features, cached.bank.features)
    rows = fresh.bank.features.flatten(0, -2)[:50]
    assert torch.equal(fresh.reducer.transform(rows), cached.reducer.transform(rows))


def test_an_encoder_retrained_in_place_gets_new_entries(box, tmp_path):
    from poseflow.features.learned import DescriptorNet, save_descriptor

    folder = tmp_path / "descriptor"
    config = FunFlow6DConfig(
        num_points=32, query_views=2, crop_size=32, verifier=None,
        appearance_encoder=f"learned:{folder}", feature_dim=4,
    )  # fmt: skip
    banks = []
    for seed in (0, 1, 0):  # trained, retrained into the same folder, back to the first
        torch.manual_seed(seed)
        save_descriptor(DescriptorNet(widths=(8, 16), dim=8, out_stride=2), folder, input_size=32)
        banks.append(_prepare({1: box}, tmp_path / "cache", config)[1].bank.features)
    assert len(_entries(tmp_path / "cache")) == 2  # one per weights, not per folder name
    assert not torch.equal(banks[0], banks[1]) and torch.equal(banks[0], banks[2])
