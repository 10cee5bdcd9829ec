"""The objects of a synthetic dataset: meshes in metres with their BOP model info.

:func:`load_synthetic_objects` turns what :func:`~poseflow.data.synthetic.generate_dataset` takes
(nothing for the demo objects, a folder of meshes, a sequence or a mapping of meshes) into
checked :class:`SyntheticObject` records; :func:`write_synthetic_models` writes them as the
dataset's ``models/`` and ``models_eval/`` folders.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from poseflow._units import check_diameter_units
from poseflow.data.bop import ModelInfo, read_models_info, write_models_info
from poseflow.errors import ValueRangeError
from poseflow.geometry.pointcloud import cloud_diameter
from poseflow.render.mesh import TexturedMesh, as_textured_mesh

__all__ = ["SyntheticObject", "load_synthetic_objects", "write_synthetic_models"]


@dataclass(frozen=True)
class SyntheticObject:
    """An object to place in synthetic scenes: a mesh in metres and its BOP model info.

    Attributes:
        obj_id: BOP object id (1-based).
        mesh: the textured mesh, model frame, metres.
        info: diameter, bounding box and symmetries written to ``models_info.json``.
    """

    obj_id: int
    mesh: TexturedMesh
    info: ModelInfo


def _info_of(obj: Any, mesh: TexturedMesh) -> ModelInfo:
    """models_info entry of an object: its own (an ``ObjectModel``) or measured from the mesh."""
    if hasattr(obj, "model_info"):
        return obj.model_info()
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    return ModelInfo(diameter=_diameter(mesh), min_xyz=lo, size_xyz=hi - lo)


def load_synthetic_objects(objects: Any, mesh_scale: float = 1.0) -> list[SyntheticObject]:
    """The objects of a dataset, checked: ids distinct and >= 1, diameters plausible in metres.

    Args:
        objects: what :func:`~poseflow.data.synthetic.generate_dataset` takes as ``objects``.
        mesh_scale: factor to metres of the meshes read from a folder.

    Returns:
        One :class:`SyntheticObject` per object.

    Raises:
        ValueRangeError: no object, or ids that are not distinct and >= 1.
        UnitsError: an implausible diameter.
    """
    if objects is None:
        from poseflow.data.demo_objects import demo_objects

        objects = demo_objects(num_points=64)  # only the meshes and model infos are used
    from_folder = isinstance(objects, (str, Path))
    if from_folder:
        objects = _load_mesh_folder(Path(objects), mesh_scale)  # checked file by file
    items = list(objects.items()) if isinstance(objects, Mapping) else list(enumerate(objects, 1))
    if not items:
        raise ValueRangeError("generate_dataset needs at least one object")
    out = []
    for obj_id, obj in items:
        if isinstance(obj, SyntheticObject):
            out.append(obj)  # keeps its own id
            continue
        mesh = as_textured_mesh(obj)
        out.append(SyntheticObject(int(obj_id), mesh, _info_of(obj, mesh)))
    for o in [] if from_folder else out:
        where = f"object {o.obj_id} (a mesh passed in memory: scale it to metres first)"
        check_diameter_units(_diameter(o.mesh), scale_name="its scale", where=where)
    ids = [o.obj_id for o in out]
    if len(set(ids)) != len(ids) or min(ids) < 1:
        raise ValueRangeError(f"object ids must be distinct and >= 1, got {ids}")
    return out


def _diameter(mesh: TexturedMesh) -> float:
    """The exact diameter of the mesh's vertices, in the mesh's unit."""
    return float(cloud_diameter(torch.from_numpy(np.ascontiguousarray(mesh.vertices))[None])[0])


def _load_mesh_folder(folder: Path, scale: float) -> dict[int, Any]:
    """Meshes of a folder keyed by object id.

    Files named like BOP models (``obj_000005.ply``) keep their id, and their entry of a
    ``models_info.json`` beside them (symmetries, diameter) is used; other files are numbered
    1, 2, ... in name order.

    Raises:
        UnitsError: a scaled mesh has an implausible diameter (the message names the file and
            the ``--mesh-scale`` to set).
    """
    from poseflow.data.objects import load_mesh

    def load(p: Path) -> TexturedMesh:
        mesh = load_mesh(p, scale=scale)
        check_diameter_units(
            _diameter(mesh), scale_name="--mesh-scale", api_name="mesh_scale", scale=scale,
            where=str(p),
        )  # fmt: skip
        return mesh

    if not folder.is_dir():
        raise ValueRangeError(f"objects must be a folder of meshes, {folder} is not a folder")
    paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".ply", ".obj"))
    if not paths:
        raise ValueRangeError(f"no .ply or .obj meshes in {folder}")
    bop_ids = [re.fullmatch(r"obj_(\d+)", p.stem) for p in paths]
    if all(bop_ids):
        infos = {}
        if (folder / "models_info.json").is_file():
            infos = read_models_info(folder / "models_info.json")
        out: dict[int, Any] = {}
        for p, match in zip(paths, bop_ids):
            obj_id = int(match.group(1))  # type: ignore[union-attr]
            mesh = load(p)
            if obj_id in infos:
                out[obj_id] = SyntheticObject(obj_id, mesh, infos[obj_id])
            else:
                out[obj_id] = mesh
        return out
    return {i: load(p) for i, p in enumerate(paths, 1)}


def write_synthetic_models(root: Path, objects: Sequence[SyntheticObject]) -> None:
    """Write ``root``'s ``models/`` and ``models_eval/``: PLYs in mm, textures, model infos."""
    from poseflow.data.objects import write_bop_model

    infos = {o.obj_id: o.info for o in objects}
    for folder in ("models", "models_eval"):
        for o in objects:
            write_bop_model(root / folder / f"obj_{o.obj_id:06d}.ply", o.mesh)
        write_models_info(root / folder / "models_info.json", infos)
