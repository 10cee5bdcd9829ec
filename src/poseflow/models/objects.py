"""Prepared objects: what inference needs of each known object, computed once and cached on disk.

Preparing an object samples its query cloud ``Q`` (farthest-point sampling of the model's
surface, seeded), describes it with the frozen encoders (``Φ(Q)`` and the multi-view appearance
bank) and fits the reducer on the bank. A prepared object is stored as ``object.safetensors``
plus ``object.json`` (its diameter and the :func:`object_fingerprint` of the configuration that
made it) and a reducer folder.

The on-disk cache holds one folder per object id and, in it, one entry per key
(:func:`object_cache_entry`: ``CACHE/obj_XXXXXX/<key>/``), the key hashing the mesh's content in
metres (so its scale too, :meth:`~poseflow.data.objects.ObjectModel.content_key`) and the
fingerprint: another mesh, scale or configuration never reads an entry it did not make, and
entries of several meshes or configurations sit side by side. Each entry is written aside and
renamed into place when complete (:func:`poseflow._cache.write_entry`); the render-and-compare
verifier keeps its own entries beside them (:mod:`~poseflow.models.verification`).

Shape letters: ``N`` query points, ``Nd`` dense surface points, ``Dg`` geometric channels.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from poseflow._cache import atomic_write, cache_entry, json_key, read_entry, write_entry
from poseflow._progress import progress as progress_loop
from poseflow.data.objects import ObjectModel, sample_surface
from poseflow.errors import ValueRangeError
from poseflow.features import (
    AppearanceEncoder,
    GeometricEncoder,
    QueryFeatureBank,
    Reducer,
    encode_on_support,
    lift_query_features,
    load_reducer,
)
from poseflow.geometry.pointcloud import farthest_point_sample, voxel_downsample
from poseflow.models.components import build_reducer
from poseflow.models.config import FunFlow6DConfig

__all__ = [
    "PreparedObject",
    "load_prepared_object",
    "object_cache_entry",
    "object_fingerprint",
    "prepare_object",
    "prepare_objects",
    "select_objects",
]

#: Rows of the appearance bank the reducer is fitted on, at most.
_REDUCER_FIT_ROWS = 4096

#: Surface samples drawn for the query's descriptor support before the grid thinning (enough to
#: fill a grid of 0.02 diameters on a compact object).
_SUPPORT_SAMPLES = 30_000


@dataclass
class PreparedObject:
    """What inference needs of one object, computed once by :func:`prepare_object`.

    Attributes:
        points: the query cloud ``Q`` ``(N, 3)``, canonical frame, metres.
        normals: its unit normals ``(N, 3)``.
        dense_points: a denser surface sample ``(Nd, 3)``, the ICP target.
        diameter: the object's diameter, metres.
        geometric: ``Φ(Q)`` ``(N, Dg)``, or None without a geometric encoder.
        bank: the multi-view appearance bank of ``Q``, or None without an appearance encoder.
        reducer: the reducer fitted on the query's appearance features, or None.
        dense_keys: the appearance encoder's keys of ``dense_points`` ``(Nd, G)`` when it
            describes surface points itself (a surface embedding, whose matches give a pose
            hypothesis: :func:`~poseflow.models.proposals.surface_match_positions`), else None.
    """

    points: torch.Tensor
    normals: torch.Tensor
    dense_points: torch.Tensor
    diameter: float
    geometric: torch.Tensor | None
    bank: QueryFeatureBank | None
    reducer: Reducer | None
    dense_keys: torch.Tensor | None = None

    def save(self, folder: str | Path, *, fingerprint: Mapping[str, Any]) -> Path:
        """Write the object to ``folder`` (safetensors + JSON + reducer), tagged ``fingerprint``."""
        from safetensors.torch import save_file

        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        tensors = {
            "points": self.points,
            "normals": self.normals,
            "dense_points": self.dense_points,
        }
        if self.geometric is not None:
            tensors["geometric"] = self.geometric
        if self.bank is not None:
            tensors.update({f"bank.{k}": v for k, v in self.bank.state().items()})
        if self.dense_keys is not None:
            tensors["dense_keys"] = self.dense_keys
        if self.reducer is not None:
            self.reducer.save(folder / "reducer")
        tensors = {k: v.contiguous() for k, v in tensors.items()}
        atomic_write(folder / "object.safetensors", lambda tmp: save_file(tensors, tmp))
        meta = {"diameter": self.diameter, "config": dict(fingerprint)}
        (folder / "object.json").write_text(json.dumps(meta, indent=1))
        return folder

    @classmethod
    def load(cls, folder: str | Path, *, fingerprint: Mapping[str, Any]) -> PreparedObject | None:
        """Read an object written by :meth:`save`; None when absent or of another fingerprint."""
        from safetensors.torch import load_file

        folder = Path(folder)
        meta_path = folder / "object.json"
        if not meta_path.is_file():
            return None
        meta = json.loads(meta_path.read_text())
        if meta.get("config") != dict(fingerprint):
            return None
        t = load_file(str(folder / "object.safetensors"))
        bank_state = {k[5:]: v for k, v in t.items() if k.startswith("bank.")}
        return cls(
            points=t["points"],
            normals=t["normals"],
            dense_points=t["dense_points"],
            diameter=float(meta["diameter"]),
            geometric=t.get("geometric"),
            bank=QueryFeatureBank.from_state(bank_state) if bank_state else None,
            reducer=load_reducer(folder / "reducer") if (folder / "reducer").exists() else None,
            dense_keys=t.get("dense_keys"),
        )


def object_fingerprint(
    config: FunFlow6DConfig, appearance_encoder: AppearanceEncoder | None = None
) -> dict[str, Any]:
    """What a prepared object depends on besides its mesh (the key of the on-disk cache).

    The configuration fields, and for a network encoder (one with a ``weights_key``: the learned
    descriptor, a surface embedding) the hash of its weights in place of its folder: an
    embedding retrained in place gets new entries, a model folder moved elsewhere keeps its own.

    Example:
        >>> sorted(object_fingerprint(FunFlow6DConfig()))[:3]
        ['appearance_encoder', 'crop_size', 'feature_dim']
    """
    appearance = config.appearance_encoder
    weights = getattr(appearance_encoder, "weights_key", None)
    if weights is not None:
        appearance = f"{appearance.partition(':')[0]}@{weights}"
    out = {
        "num_points": config.num_points,
        "geometric_encoder": config.geometric_encoder,
        "geometric_radii": list(config.geometric_radii),
        "appearance_encoder": appearance,
        "crop_size": config.crop_size,
        "query_views": config.query_views,
        "reducer": config.reducer,
        "feature_dim": config.feature_dim,
    }
    if config.geometric_support_voxel:  # absent when 0, so that older caches stay valid
        out["geometric_support_voxel"] = config.geometric_support_voxel
    if config.appearance_encoder.startswith("surface"):  # entries with the dense points' keys
        out["dense_keys"] = True
    return out


def object_cache_entry(
    cache_dir: str | Path, obj_id: int, model: ObjectModel, fingerprint: Mapping[str, Any]
) -> Path:
    """The cache entry of one object: ``cache_dir/obj_XXXXXX/<key>``.

    Args:
        cache_dir: the cache folder.
        obj_id: the object's id.
        model: the object; its :meth:`~poseflow.data.objects.ObjectModel.content_key` (mesh and
            scale) is part of the key.
        fingerprint: what the prepared data depends on besides the mesh (e.g.
            :func:`object_fingerprint`, or the verifier's fingerprint).

    Returns:
        The entry's folder (it may not exist).

    Example:
        >>> import open3d as o3d
        >>> box = o3d.geometry.TriangleMesh.create_box(0.1, 0.2, 0.3)
        >>> small = ObjectModel.from_mesh(box, num_points=16)
        >>> large = ObjectModel.from_mesh(box.scale(2.0, [0, 0, 0]), num_points=16)
        >>> fp = object_fingerprint(FunFlow6DConfig())
        >>> a, b = (object_cache_entry("cache", 1, m, fp) for m in (small, large))
        >>> a != b, a.parent == b.parent, a.parent.name
        (True, True, 'obj_000001')
    """
    return cache_entry(
        cache_dir, f"obj_{int(obj_id):06d}", model.content_key(), json_key(dict(fingerprint))
    )


def load_prepared_object(
    cache_dir: str | Path,
    obj_id: int,
    model: ObjectModel,
    config: FunFlow6DConfig,
    appearance_encoder: AppearanceEncoder | None = None,
) -> PreparedObject | None:
    """The cached preparation of ``model`` for ``config``, or None; never prepares.

    Args:
        cache_dir: the cache folder of :func:`prepare_objects`.
        obj_id: the object's id.
        model: the object.
        config: the model configuration.
        appearance_encoder: the model's appearance encoder (its weights are part of the key).

    Returns:
        The :class:`PreparedObject`, or None when the cache holds none for this mesh, scale,
        configuration and encoder weights (a damaged entry is removed with a warning).
    """
    fingerprint = object_fingerprint(config, appearance_encoder)
    entry = object_cache_entry(cache_dir, obj_id, model, fingerprint)
    read = functools.partial(PreparedObject.load, fingerprint=fingerprint)
    return read_entry(entry, read, what=f"object {obj_id}")


def prepare_object(
    model: ObjectModel,
    config: FunFlow6DConfig,
    *,
    geometric_encoder: GeometricEncoder | None,
    appearance_encoder: AppearanceEncoder | None,
    obj_id: int | None = None,
) -> PreparedObject:
    """Sample the query cloud of one object, describe it and fit its reducer.

    Args:
        model: the object (metres; a textured mesh for appearance).
        config: the model configuration (``num_points``, ``query_views``, ``reducer``,
            ``feature_dim``).
        geometric_encoder: the frozen geometric encoder, or None.
        appearance_encoder: the frozen appearance encoder, or None. One with a ``point_keys``
            method (a :class:`~poseflow.features.SurfaceEmbeddingEncoder`) describes the dense
            surface points itself, given ``obj_id`` (the query points' keys are then their
            one-view bank); the others describe the query points from renderings of the mesh.
        obj_id: the object's id (needed by encoders with ``point_keys``).

    Returns:
        The :class:`PreparedObject` (on the CPU, float32).
    """
    dense = model.points.detach().cpu().float()
    dense_normals = model.normals.detach().cpu().float()
    g = torch.Generator().manual_seed(0)
    idx, _ = farthest_point_sample(dense[None], config.num_points, generator=g)
    points, normals = dense[idx[0]], dense_normals[idx[0]]
    geometric = None
    if geometric_encoder is not None:
        geometric = _describe_query(model, points, normals, config, geometric_encoder)
    bank, reducer, dense_keys = None, None, None
    if appearance_encoder is not None:
        point_keys = getattr(appearance_encoder, "point_keys", None)
        if point_keys is not None:
            if obj_id is None:
                raise ValueRangeError(f"{appearance_encoder!r} needs the object's id")
            dense_keys = point_keys(obj_id, dense, model.diameter)
            bank = QueryFeatureBank.one_view(points, dense_keys[idx[0]])
        else:
            bank = lift_query_features(
                appearance_encoder, model, points, model.diameter, num_views=config.query_views
            )
        if config.reducer != "identity" and config.feature_dim > bank.dim:
            raise ValueRangeError(
                f"feature_dim={config.feature_dim} exceeds the {bank.dim} channels of "
                f"{appearance_encoder!r}: set feature_dim to at most {bank.dim}"
            )
        reducer = build_reducer(config.reducer, n_components=config.feature_dim)
        reducer.fit(_bank_rows(bank, max_rows=_REDUCER_FIT_ROWS))
    return PreparedObject(
        points=points,
        normals=normals,
        dense_points=dense,
        diameter=float(model.diameter),
        geometric=geometric,
        bank=bank,
        reducer=reducer,
        dense_keys=dense_keys,
    )


def _describe_query(
    model: ObjectModel,
    points: torch.Tensor,
    normals: torch.Tensor,
    config: FunFlow6DConfig,
    encoder: GeometricEncoder,
) -> torch.Tensor:
    """``Φ(Q)`` ``(N, Dg)``, on a grid-thinned dense surface sample when the config asks."""
    if not config.geometric_support_voxel:
        return encoder.encode(points[None], normals[None], None, model.diameter)[0]
    surface, surface_normals, _ = sample_surface(
        model.mesh, _SUPPORT_SAMPLES, generator=torch.Generator().manual_seed(0)
    )
    support = torch.from_numpy(surface).float()[None]
    idx, ok = voxel_downsample(support, config.geometric_support_voxel * model.diameter)
    keep = idx[0][ok[0]]
    return encode_on_support(
        encoder,
        points[None],
        normals[None],
        None,
        support[:, keep],
        torch.from_numpy(surface_normals).float()[None, keep],
        None,
        model.diameter,
    )[0]


def prepare_objects(
    models: Mapping[int, ObjectModel],
    config: FunFlow6DConfig,
    *,
    geometric_encoder: GeometricEncoder | None,
    appearance_encoder: AppearanceEncoder | None,
    cache_dir: str | Path | None = None,
    progress: bool = True,
) -> dict[int, PreparedObject]:
    """:func:`prepare_object` for every object, through the on-disk cache.

    Args:
        models: ``{obj_id: ObjectModel}``.
        config: the model configuration.
        geometric_encoder: the frozen geometric encoder, or None.
        appearance_encoder: the frozen appearance encoder, or None.
        cache_dir: where prepared objects are stored and looked up (one entry per object, mesh,
            scale and configuration: :func:`object_cache_entry`); None computes everything in
            memory. A cache folder that cannot be written gives a warning.
        progress: show a progress bar.

    Returns:
        ``{obj_id: PreparedObject}``.
    """
    fingerprint = object_fingerprint(config, appearance_encoder)
    out: dict[int, PreparedObject] = {}
    items = sorted(models.items())
    for obj_id, model in progress_loop(
        items, total=len(items), desc="prepare objects", enabled=progress
    ):
        prepared = None
        if cache_dir is not None:
            prepared = load_prepared_object(cache_dir, obj_id, model, config, appearance_encoder)
        if prepared is None:
            prepared = prepare_object(
                model,
                config,
                geometric_encoder=geometric_encoder,
                appearance_encoder=appearance_encoder,
                obj_id=obj_id,
            )
            if cache_dir is not None:
                write_entry(
                    object_cache_entry(cache_dir, obj_id, model, fingerprint),
                    functools.partial(prepared.save, fingerprint=fingerprint),
                    what=f"object {obj_id}",
                )
        out[int(obj_id)] = prepared
    return out


def select_objects(
    objects: Mapping[int, PreparedObject], obj_ids: torch.Tensor | Sequence[int]
) -> list[PreparedObject]:
    """The prepared object of every instance.

    Args:
        objects: ``{obj_id: PreparedObject}``.
        obj_ids: object id of each instance ``(B,)``.

    Returns:
        ``B`` prepared objects (the same object repeats for instances of one object).

    Raises:
        ValueRangeError: an id is not prepared.
    """
    ids = torch.as_tensor(obj_ids).reshape(-1).tolist()
    missing = sorted({int(i) for i in ids} - set(objects))
    if missing:
        raise ValueRangeError(
            f"object {missing[0]} is not prepared; call prepare_objects first "
            f"(prepared: {sorted(objects)})"
        )
    return [objects[int(i)] for i in ids]


def _bank_rows(bank: QueryFeatureBank, *, max_rows: int) -> torch.Tensor:
    """Visible per-view features of a bank, evenly subsampled to at most ``max_rows`` rows."""
    rows = bank.features[bank.visible].float()
    if len(rows) > max_rows:
        rows = rows[torch.linspace(0, len(rows) - 1, max_rows).round().long()]
    return rows
