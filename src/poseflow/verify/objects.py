"""What the verifier keeps per object, prepared once from the mesh and cached on disk.

:func:`prepare_verifier_object` samples the surface evenly (points, normals, albedo) and finds the
object's near-symmetries (:func:`~poseflow.verify.near_symmetries`). :func:`cached_verifier_object`
reads it from, or writes it to, an on-disk cache of one entry per key,
``CACHE/obj_XXXXXX/<key>/`` (``verifier.safetensors`` + ``verifier.json``), the key hashing the
mesh's content in metres (:meth:`~poseflow.data.objects.ObjectModel.content_key`, so its scale
too) and :func:`verifier_fingerprint`: another mesh, scale or configuration never reads an entry
it did not make. An entry is written aside and renamed into place whole
(:func:`poseflow._cache.write_entry`), so a crash never leaves half of one. FunFlow6D's prepared
objects sit in the same folders, in entries of their own.

Shape letters: ``N`` surface points, ``C`` near-symmetry candidates.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import torch

from poseflow._cache import cache_entry, json_key, read_entry, write_entry
from poseflow.data.objects import ObjectModel, sample_surface
from poseflow.geometry.pointcloud import farthest_point_sample
from poseflow.verify.config import VerifierConfig
from poseflow.verify.symmetry import near_symmetries

__all__ = [
    "PREPARED_FORMAT",
    "VerifierObject",
    "cached_verifier_object",
    "prepare_verifier_object",
    "verifier_fingerprint",
]

#: Version of what :func:`prepare_verifier_object` computes; part of the cache key, so that a
#: change of the near-symmetry search invalidates older entries.
PREPARED_FORMAT = 1

#: :class:`VerifierConfig` fields that a prepared object depends on.
_PREPARE_FIELDS = (
    "num_points",
    "max_candidates",
    "min_self_overlap",
    "self_overlap_distance",
    "min_candidate_angle",
    "turn_steps",
    "icp_distances",
    "icp_iterations",
    "icp_relative_rmse",
)

_TENSORS, _META = "verifier.safetensors", "verifier.json"


@dataclass
class VerifierObject:
    """What the verifier keeps per object (metres, model frame, float32 on the CPU).

    Attributes:
        points: evenly spread surface points ``(N, 3)``, drawn and ICP target, in
            farthest-point order (every prefix is spread evenly too).
        normals: outward unit normals ``(N, 3)``.
        colors: albedo ``(N, 3)`` in ``[0, 1]``.
        albedo: ``colors`` after a grey-world balance over the object ``(N, 3)`` (each channel
            divided by its mean over the points): what is drawn.
        centroid: centre of the points ``(3,)``.
        diameter: the object's diameter.
        candidates: near-symmetry transforms ``(C, 4, 4)``, ``C`` possibly 0.
        overlap: self-overlap of each candidate ``(C,)``.
    """

    points: torch.Tensor
    normals: torch.Tensor
    colors: torch.Tensor
    albedo: torch.Tensor
    centroid: torch.Tensor
    diameter: float
    candidates: torch.Tensor
    overlap: torch.Tensor


def verifier_fingerprint(config: VerifierConfig, *, seed: int = 0) -> dict[str, Any]:
    """What a prepared object depends on besides the mesh: part of its cache key.

    Example:
        >>> verifier_fingerprint(VerifierConfig())["num_points"]
        4096
    """
    out: dict[str, Any] = {"format": PREPARED_FORMAT, "seed": int(seed)}
    for name in _PREPARE_FIELDS:
        value = getattr(config, name)
        out[name] = list(value) if isinstance(value, tuple) else value
    return out


def prepare_verifier_object(
    model: ObjectModel, config: VerifierConfig, *, seed: int = 0
) -> VerifierObject:
    """Sample an object's surface and find its near-symmetries.

    Args:
        model: the object (metres); its declared symmetries are not returned as candidates.
        config: the verifier's configuration (see :func:`verifier_fingerprint` for the fields
            that count).
        seed: seed of the surface sampling.

    Returns:
        The :class:`VerifierObject` of ``config.num_points`` points.

    Raises:
        DegenerateInputError: the mesh has no surface.
    """
    g = torch.Generator().manual_seed(int(seed))
    pts, nrm, col = sample_surface(model.mesh, 4 * config.num_points, generator=g)
    P = torch.from_numpy(pts)
    idx, _ = farthest_point_sample(P[None], config.num_points, generator=g)
    keep = idx[0]
    points = P[keep]
    normals = torch.nn.functional.normalize(torch.from_numpy(nrm)[keep], dim=-1)
    colors = torch.from_numpy(col).to(torch.float64)[keep].clamp(0, 1)
    albedo = colors / colors.mean(0).clamp_min(1e-6)
    # self-ICP moves an eighth of the points (a random subset, still spread; at least 256)
    # onto all of them
    sub = torch.randperm(points.shape[0], generator=g)[: max(256, config.num_points // 8)]
    found = near_symmetries(
        points[sub],
        normals[sub],
        model.diameter,
        surface=points,
        declared=model.symmetries.to(torch.float64),
        turn_steps=config.turn_steps,
        min_overlap=config.min_self_overlap,
        overlap_distance=config.self_overlap_distance,
        icp_iterations=2 * config.icp_iterations,
        min_angle=config.min_candidate_angle,
        max_candidates=config.max_candidates,
        icp_distances=config.icp_distances,
        icp_relative_rmse=config.icp_relative_rmse,
    )
    return VerifierObject(
        points=points.float(),
        normals=normals.float(),
        colors=colors.float(),
        albedo=albedo.float(),
        centroid=points.mean(0).float(),
        diameter=float(model.diameter),
        candidates=found.transforms.float(),
        overlap=found.overlap.float(),
    )


def cached_verifier_object(
    model: ObjectModel,
    config: VerifierConfig,
    *,
    seed: int = 0,
    obj_id: int,
    cache_dir: str | Path | None,
) -> VerifierObject:
    """:func:`prepare_verifier_object`, through the cache entry of this mesh and configuration.

    Args:
        model: the object (metres).
        config: the verifier's configuration.
        seed: seed of the surface sampling.
        obj_id: the object's id (names the entry's folder, ``obj_XXXXXX``).
        cache_dir: the cache folder; None prepares without a cache. An entry that is damaged is
            removed with a warning and prepared again; a folder that cannot be written gives a
            warning, and the object is not cached.

    Returns:
        The prepared object, read from the entry of ``model``'s content and the fingerprint of
        ``config`` and ``seed`` when it holds one, else prepared (and written there).

    Example:
        >>> import tempfile, open3d as o3d
        >>> box = o3d.geometry.TriangleMesh.create_box(0.1, 0.06, 0.03)
        >>> model = ObjectModel.from_mesh(box, num_points=64)
        >>> cfg, cache = VerifierConfig(num_points=256, turn_steps=4), tempfile.mkdtemp()
        >>> a = cached_verifier_object(model, cfg, obj_id=1, cache_dir=cache)  # written
        >>> b = cached_verifier_object(model, cfg, obj_id=1, cache_dir=cache)  # read back
        >>> torch.equal(a.points, b.points), len(list(Path(cache, "obj_000001").iterdir()))
        (True, 1)
    """
    if cache_dir is None:
        return prepare_verifier_object(model, config, seed=seed)
    fingerprint = verifier_fingerprint(config, seed=seed)
    entry = cache_entry(
        cache_dir, f"obj_{int(obj_id):06d}", model.content_key(), json_key(fingerprint)
    )
    cached = read_entry(entry, lambda f: _read(f, fingerprint), what=f"object {obj_id}")
    if cached is not None:
        return cached
    prepared = prepare_verifier_object(model, config, seed=seed)
    write_entry(
        entry, lambda f: _write(prepared, f, fingerprint), what=f"object {obj_id}'s verifier data"
    )
    return prepared


def _write(obj: VerifierObject, folder: Path, fingerprint: Mapping[str, Any]) -> None:
    """Write ``obj`` into the (temporary) folder of a cache entry."""
    from safetensors.torch import save_file

    tensors = {f.name: getattr(obj, f.name) for f in fields(obj) if f.name != "diameter"}
    save_file({k: v.contiguous() for k, v in tensors.items()}, str(folder / _TENSORS))
    meta = {"diameter": obj.diameter, "config": dict(fingerprint)}
    (folder / _META).write_text(json.dumps(meta, indent=1))


def _read(folder: Path, fingerprint: Mapping[str, Any]) -> VerifierObject | None:
    """The object of a cache entry; None when it was made with another fingerprint."""
    from safetensors.torch import load_file

    meta = json.loads((folder / _META).read_text())
    if meta.get("config") != json.loads(json.dumps(dict(fingerprint))):
        return None
    return VerifierObject(diameter=float(meta["diameter"]), **load_file(str(folder / _TENSORS)))
