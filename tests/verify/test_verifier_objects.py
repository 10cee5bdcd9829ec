"""The verifier's prepared objects and their on-disk cache, keyed by the mesh and configuration."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import torch

import poseflow.verify.objects
from poseflow.data.demo_objects import demo_mesh
from poseflow.data.objects import ObjectModel
from poseflow.verify import PoseVerifier, VerifierConfig, VerifierObject

CONFIG = VerifierConfig(num_points=256, turn_steps=4, max_candidates=4)


@pytest.fixture(scope="module")
def box() -> ObjectModel:
    return ObjectModel.from_mesh(demo_mesh("labelled_box"), num_points=256)


def _equal(a: VerifierObject, b: VerifierObject) -> bool:
    return all(
        torch.equal(x, y) if isinstance(x, torch.Tensor) else x == y
        for x, y in zip(dataclasses.astuple(a), dataclasses.astuple(b), strict=True)
    )


def _never(*args, **kwargs):
    raise AssertionError("prepared again instead of read from the cache")


def test_prepared_objects_are_cached_on_disk(box, tmp_path, monkeypatch) -> None:
    first = PoseVerifier(CONFIG).prepare(1, box, cache_dir=tmp_path)
    (entry,) = (tmp_path / "obj_000001").iterdir()
    assert sorted(p.name for p in entry.iterdir()) == ["verifier.json", "verifier.safetensors"]
    with monkeypatch.context() as m:
        m.setattr(poseflow.verify.objects, "prepare_verifier_object", _never)
        again = PoseVerifier(CONFIG).prepare(1, box, cache_dir=tmp_path)
    assert _equal(first, again)
    # another configuration (or seed) gets an entry of its own beside it
    other = PoseVerifier(dataclasses.replace(CONFIG, num_points=128))
    assert len(other.prepare(1, box, cache_dir=tmp_path).points) == 128
    PoseVerifier(CONFIG, seed=1).prepare(1, box, cache_dir=tmp_path)
    assert len(list((tmp_path / "obj_000001").iterdir())) == 3


def test_another_mesh_in_the_same_cache_gets_its_own_points(box, tmp_path) -> None:
    """The entry is keyed by the mesh's content and scale, not only the object id."""
    first = PoseVerifier(CONFIG).prepare(1, box, cache_dir=tmp_path)
    larger = ObjectModel.from_mesh(box.mesh.scaled(1.5), num_points=256)
    can = ObjectModel.from_mesh(demo_mesh("labelled_can"), num_points=256)
    for changed in (larger, can):
        cached = PoseVerifier(CONFIG).prepare(1, changed, cache_dir=tmp_path)
        assert _equal(cached, PoseVerifier(CONFIG).prepare(1, changed))
        assert not torch.equal(cached.points, first.points)
        assert cached.diameter == pytest.approx(changed.diameter)
    assert len(list((tmp_path / "obj_000001").iterdir())) == 3
    assert _equal(PoseVerifier(CONFIG).prepare(1, box, cache_dir=tmp_path), first)


def test_a_damaged_entry_is_prepared_again(box, tmp_path) -> None:
    first = PoseVerifier(CONFIG).prepare(1, box, cache_dir=tmp_path)
    (entry,) = (tmp_path / "obj_000001").iterdir()
    (entry / "verifier.json").write_text("{")
    with pytest.warns(UserWarning, match="damaged"):
        again = PoseVerifier(CONFIG).prepare(1, box, cache_dir=tmp_path)
    assert _equal(first, again)
    assert (entry / "verifier.json").read_text().startswith("{\n")  # written again, whole


def test_a_cache_that_cannot_be_written_keeps_the_object_in_memory(box, tmp_path: Path) -> None:
    blocked = tmp_path / "a_file"
    blocked.write_text("")
    verifier = PoseVerifier(CONFIG)
    with pytest.warns(UserWarning, match="not cached"):
        kept = verifier.prepare(1, box, cache_dir=blocked / "cache")
    assert verifier.objects[1] is kept
    assert verifier.prepare(1, box) is kept  # held by id, nothing prepared again
