"""Object models: mesh files, the canonical query cloud, diameter and symmetries.

Units are metres inside poseflow. Mesh files are read as they are and multiplied by ``scale``;
BOP model PLYs are in millimetres, so read them with ``scale=0.001``.

Meshes are read by :func:`poseflow.data.meshio.load_mesh` (re-exported here).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from poseflow._cache import arrays_key
from poseflow._units import check_diameter_units
from poseflow.data.meshio import load_mesh
from poseflow.errors import DegenerateInputError, ValueRangeError
from poseflow.geometry.pointcloud import cloud_diameter, farthest_point_sample
from poseflow.geometry.se3 import axis_angle_to_rotation
from poseflow.render.mesh import TexturedMesh

__all__ = [
    "ObjectModel",
    "discretize_symmetries",
    "load_mesh",
    "mesh_vertex_arrays",
    "sample_surface",
    "symmetries_from_info",
    "write_bop_model",
    "write_bop_models",
]


# ---------------------------------------------------------------------------------------------
# Writing meshes


def mesh_vertex_arrays(mesh: TexturedMesh) -> dict[str, np.ndarray | None]:
    """Per-vertex arrays of a mesh, vertices split where one position has several UVs.

    BOP model PLYs carry one texture coordinate per vertex; this unwelds vertices along texture
    seams so that a mesh with per-corner UVs can be written that way.

    Returns:
        A dict with ``vertices (V', 3)``, ``triangles (F, 3)``, ``normals (V', 3)`` or None,
        ``colors (V', 3)`` or None, ``uvs (V', 2)`` or None.

    Example:
        >>> m = TexturedMesh(np.eye(3), np.array([[0, 1, 2]]))
        >>> mesh_vertex_arrays(m)["vertices"].shape
        (3, 3)
    """
    v, f = mesh.vertices, mesh.triangles
    if mesh.triangle_uvs is None:
        return {
            "vertices": v,
            "triangles": f,
            "normals": mesh.vertex_normals,
            "colors": mesh.vertex_colors,
            "uvs": None,
        }
    uv = mesh.triangle_uvs.reshape(-1, 2).astype(np.float64)
    key = np.concatenate([f.reshape(-1, 1).astype(np.float64), uv], axis=1)
    uniq, inv = np.unique(key, axis=0, return_inverse=True)
    src = uniq[:, 0].astype(np.int64)
    return {
        "vertices": v[src],
        "triangles": inv.reshape(-1, 3),
        "normals": None if mesh.vertex_normals is None else mesh.vertex_normals[src],
        "colors": None if mesh.vertex_colors is None else mesh.vertex_colors[src],
        "uvs": uniq[:, 1:],
    }


def write_bop_model(path: str | Path, mesh: TexturedMesh) -> None:
    """Write a mesh as a BOP model PLY in mm, with its texture as a PNG beside it.

    The texture (if any) is written to ``path`` with the suffix ``.png`` and named in the PLY's
    ``comment TextureFile`` line; :func:`load_mesh` with ``scale=0.001`` reads it back.

    Args:
        path: the ``.ply`` to write (parents are created).
        mesh: the mesh, in metres.
    """
    from PIL import Image

    from poseflow.data.bop import write_model_ply

    path = Path(path)
    a = mesh_vertex_arrays(mesh)
    texture_file = None
    if mesh.texture is not None:
        texture_file = path.with_suffix(".png").name
        path.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(mesh.texture).save(path.with_suffix(".png"))
    write_model_ply(
        path,
        a["vertices"],
        a["triangles"],
        normals=a["normals"],
        colors=a["colors"],
        uvs=a["uvs"],
        texture_file=texture_file,
    )


def write_bop_models(
    folder: str | Path, models: Sequence[ObjectModel], *, obj_ids: Sequence[int] | None = None
) -> dict[int, Path]:
    """Write a BOP ``models/`` folder: ``obj_{id:06d}.ply`` (+ ``.png``) and ``models_info.json``.

    Args:
        folder: the folder to fill (created if needed).
        models: the object models.
        obj_ids: their BOP object ids; default ``1, 2, ...``.

    Returns:
        ``{obj_id: ply_path}``.
    """
    from poseflow.data.bop import write_models_info

    folder = Path(folder)
    ids = list(range(1, len(models) + 1)) if obj_ids is None else [int(i) for i in obj_ids]
    if len(ids) != len(models) or len(set(ids)) != len(ids):
        raise ValueRangeError(f"need one distinct obj_id per model, got {ids}")
    paths = {}
    for obj_id, model in zip(ids, models):
        p = folder / f"obj_{obj_id:06d}.ply"
        write_bop_model(p, model.mesh)
        paths[obj_id] = p
    write_models_info(folder / "models_info.json", {i: m.model_info() for i, m in zip(ids, models)})
    return paths


# ---------------------------------------------------------------------------------------------
# Symmetries


def discretize_symmetries(
    discrete: Sequence[np.ndarray] = (),
    continuous: Sequence[tuple[np.ndarray, np.ndarray]] = (),
    *,
    max_sym_disc_step: float = 0.01,
) -> np.ndarray:
    """All symmetry transformations of an object, continuous ones discretised as BOP does.

    As in the BOP toolkit (``misc.get_symmetry_transformations``): each continuous symmetry
    (a rotation axis through ``offset``) becomes ``n = ceil(pi / max_sym_disc_step)`` rotations
    by ``2 pi i / n`` (so that vertices move at most about ``max_sym_disc_step`` times the
    diameter between neighbours), and every discrete symmetry (the identity included) is
    composed with each of them. Unlike the toolkit, the step ``i = 0`` is kept, so the identity
    is always in the set.

    Args:
        discrete: ``(4, 4)`` symmetry transforms in metres (without the identity).
        continuous: ``(axis (3,), offset (3,))`` pairs, offset in metres.
        max_sym_disc_step: BOP's discretisation step (default 0.01, BOP's value).

    Returns:
        Transforms ``(S, 4, 4)`` float64, the identity first.

    Example:
        >>> discretize_symmetries(continuous=[(np.array([0, 0, 1.0]), np.zeros(3))]).shape
        (315, 4, 4)
    """
    if not max_sym_disc_step > 0:
        raise ValueRangeError(f"max_sym_disc_step must be positive, got {max_sym_disc_step}")
    disc = [np.eye(4)]
    for S in discrete:
        S = np.asarray(S, np.float64).reshape(4, 4)
        R = S[:3, :3]
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or not np.isclose(np.linalg.det(R), 1):
            raise ValueRangeError("a discrete symmetry's rotation block is not a rotation")
        if not np.allclose(S, np.eye(4)):
            disc.append(S)
    cont = []
    for axis, offset in continuous:
        axis = np.asarray(axis, np.float64).reshape(3)
        offset = np.asarray(offset, np.float64).reshape(3)
        if not np.linalg.norm(axis) > 0:
            raise ValueRangeError("a continuous symmetry has a zero axis")
        n = math.ceil(math.pi / max_sym_disc_step)
        angles = 2 * math.pi * np.arange(n) / n
        for R in axis_angle_to_rotation(angles[:, None] * (axis / np.linalg.norm(axis))):
            T = np.eye(4)
            T[:3, :3] = R
            T[:3, 3] = offset - R @ offset
            cont.append(T)
    if not cont:
        return np.stack(disc)
    return np.stack([C @ D for D in disc for C in cont])


def symmetries_from_info(info: Any, *, max_sym_disc_step: float = 0.01) -> np.ndarray:
    """Symmetry transformations from a ``models_info.json`` entry.

    Args:
        info: either the raw JSON entry of one object (a mapping in **mm**, with optional
            ``symmetries_discrete`` (row-major 4x4 lists) and ``symmetries_continuous``
            (``{"axis", "offset"}``)), or an object with ``symmetries_discrete`` /
            ``symmetries_continuous`` attributes already in metres
            (``poseflow.data.bop.ModelInfo``).
        max_sym_disc_step: see :func:`discretize_symmetries`.

    Returns:
        Transforms ``(S, 4, 4)`` float64 in metres, the identity first.

    Example:
        >>> entry = {"diameter": 100.0, "symmetries_discrete": [
        ...     [-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 20.0, 0, 0, 0, 1]]}
        >>> symmetries_from_info(entry)[1, :3, 3].tolist()
        [0.0, 0.0, 0.02]
    """
    disc, cont = _symmetry_specs(info)
    return discretize_symmetries(disc, cont, max_sym_disc_step=max_sym_disc_step)


def _symmetry_specs(info: Any) -> tuple[list[np.ndarray], list[tuple[np.ndarray, np.ndarray]]]:
    """Discrete and continuous symmetries (metres) from a raw entry (mm) or a ModelInfo."""
    disc: list[np.ndarray] = []
    cont: list[tuple[np.ndarray, np.ndarray]] = []
    if info is None:
        return disc, cont
    if isinstance(info, Mapping):
        for s in info.get("symmetries_discrete", []):
            S = np.asarray(s, np.float64)
            if S.size != 16:
                raise ValueRangeError(f"symmetries_discrete entries need 16 numbers, got {S.size}")
            S = S.reshape(4, 4).copy()
            S[:3, 3] *= 0.001
            disc.append(S)
        for s in info.get("symmetries_continuous", []):
            if "axis" not in s:
                raise ValueRangeError("a symmetries_continuous entry has no 'axis'")
            offset = np.asarray(s.get("offset", [0, 0, 0]), np.float64) * 0.001
            cont.append((np.asarray(s["axis"], np.float64), offset))
        return disc, cont
    disc = [np.asarray(S, np.float64) for S in getattr(info, "symmetries_discrete", ())]
    cont = [(c.axis, c.offset) for c in getattr(info, "symmetries_continuous", ())]
    return disc, cont


# ---------------------------------------------------------------------------------------------
# Surface sampling and the object model


def sample_surface(
    mesh: TexturedMesh, n: int, *, generator: torch.Generator | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Draw points uniformly (by area) on a mesh's surface.

    Args:
        mesh: the mesh.
        n: number of points.
        generator: seeded torch generator (CPU) for reproducible draws.

    Returns:
        ``(points (n, 3), normals (n, 3), colors (n, 3))`` numpy arrays (float64, float64,
        float32 in ``[0, 1]``).

    Example:
        >>> m = TexturedMesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]]), np.array([[0, 1, 2]]))
        >>> p, nrm, c = sample_surface(m, 5, generator=torch.Generator().manual_seed(0))
        >>> p.shape, bool((p[:, :2].sum(1) <= 1).all()), nrm[0].tolist()
        ((5, 3), True, [0.0, 0.0, 1.0])
    """
    areas = torch.from_numpy(mesh.triangle_areas)
    if not float(areas.sum()) > 0:
        raise DegenerateInputError("the mesh has zero surface area")
    face = torch.multinomial(areas, n, replacement=True, generator=generator).numpy()
    r = torch.rand(n, 2, generator=generator, dtype=torch.float64).numpy()
    s = np.sqrt(r[:, 0])
    bary = np.stack([s * (1 - r[:, 1]), s * r[:, 1]], axis=1)  # uniform in the triangle
    return (
        mesh.surface_points(face, bary),
        mesh.surface_normals(face, bary),
        mesh.surface_colors(face, bary),
    )


@dataclass(eq=False)
class ObjectModel:
    """A rigid object: its mesh, canonical query cloud, diameter and symmetries (metres).

    Build one with :meth:`from_mesh` or :meth:`from_file`.

    Attributes:
        mesh: the textured mesh in the model frame.
        points: the canonical query cloud ``Q``, ``(N, 3)``, on the surface.
        normals: unit surface normals at ``points``, ``(N, 3)``.
        colors: albedo at ``points`` in ``[0, 1]``, ``(N, 3)``.
        diameter: largest distance between two mesh vertices (BOP's definition), metres.
        symmetries: the symmetry transformations, continuous ones discretised, ``(S, 4, 4)``
            float64 with the identity first.
        symmetries_discrete: the discrete symmetries as declared (``(4, 4)`` each, metres).
        symmetries_continuous: the continuous symmetries as declared (``(axis, offset)``).
        name: a human-readable name.
    """

    mesh: TexturedMesh
    points: torch.Tensor
    normals: torch.Tensor
    colors: torch.Tensor
    diameter: float
    symmetries: torch.Tensor
    symmetries_discrete: tuple[np.ndarray, ...] = ()
    symmetries_continuous: tuple[tuple[np.ndarray, np.ndarray], ...] = ()
    name: str = ""

    @classmethod
    def from_mesh(
        cls,
        mesh: Any,
        *,
        num_points: int = 2048,
        seed: int = 0,
        oversample: int = 8,
        symmetries_discrete: Sequence[np.ndarray] = (),
        symmetries_continuous: Sequence[tuple[np.ndarray, np.ndarray]] = (),
        max_sym_disc_step: float = 0.01,
        name: str = "",
        dtype: torch.dtype = torch.float32,
    ) -> ObjectModel:
        """Build the model of a mesh: sample the query cloud, measure the diameter.

        The query cloud is ``num_points`` farthest-point samples out of ``oversample *
        num_points`` points drawn uniformly on the surface, so it covers the surface evenly;
        it depends only on the mesh and ``seed``.

        Args:
            mesh: a :class:`~poseflow.render.mesh.TexturedMesh` (or legacy Open3D mesh) in metres.
            num_points: size ``N`` of the query cloud.
            seed: seed of the sampling.
            oversample: candidates per kept point for the farthest-point sampling (1: none).
            symmetries_discrete: ``(4, 4)`` symmetry transforms (metres).
            symmetries_continuous: ``(axis, offset)`` pairs (offset in metres).
            max_sym_disc_step: BOP's discretisation step of continuous symmetries.
            name: a name for messages and files.
            dtype: dtype of the tensors.

        Returns:
            The :class:`ObjectModel`.

        Example:
            >>> import open3d as o3d
            >>> box = o3d.geometry.TriangleMesh.create_box(0.1, 0.2, 0.3)
            >>> m = ObjectModel.from_mesh(box, num_points=256)
            >>> m.points.shape, round(m.diameter, 4)
            (torch.Size([256, 3]), 0.3742)
        """
        from poseflow.render.mesh import as_textured_mesh

        mesh = as_textured_mesh(mesh)
        if isinstance(num_points, bool) or num_points < 1 or oversample < 1:
            raise ValueRangeError(f"need num_points >= 1 and oversample >= 1, got {num_points}")
        g = torch.Generator().manual_seed(int(seed))
        pts, nrm, col = sample_surface(mesh, num_points * oversample, generator=g)
        if oversample > 1:
            idx, _ = farthest_point_sample(torch.from_numpy(pts)[None], num_points, generator=g)
            keep = idx[0].numpy()
            pts, nrm, col = pts[keep], nrm[keep], col[keep]
        verts = torch.from_numpy(mesh.vertices)[None]
        diameter = float(cloud_diameter(verts)[0])
        disc = tuple(np.asarray(s, np.float64).reshape(4, 4) for s in symmetries_discrete)
        cont = tuple(
            (np.asarray(a, np.float64).reshape(3), np.asarray(o, np.float64).reshape(3))
            for a, o in symmetries_continuous
        )
        syms = discretize_symmetries(disc, cont, max_sym_disc_step=max_sym_disc_step)
        return cls(
            mesh=mesh,
            points=torch.from_numpy(pts).to(dtype),
            normals=torch.from_numpy(nrm).to(dtype),
            colors=torch.from_numpy(np.ascontiguousarray(col)).to(dtype),
            diameter=diameter,
            symmetries=torch.from_numpy(syms).to(dtype),
            symmetries_discrete=disc,
            symmetries_continuous=cont,
            name=name,
        )

    @classmethod
    def from_file(
        cls,
        path: str | Path,
        *,
        scale: float = 1.0,
        info: Any = None,
        num_points: int = 2048,
        seed: int = 0,
        oversample: int = 8,
        max_sym_disc_step: float = 0.01,
        name: str | None = None,
        dtype: torch.dtype = torch.float32,
        scale_name: str = "scale=",
    ) -> ObjectModel:
        """Load a mesh file and build its model (see :meth:`from_mesh`).

        The scaled mesh must have a plausible diameter (5 mm to 5 m): a mesh in millimetres
        read with ``scale=1`` stops here rather than giving a 155 m object.

        Args:
            path: mesh file (see :func:`load_mesh`).
            scale: factor to metres (0.001 for BOP models in mm).
            info: the object's ``models_info.json`` entry, raw (mm) or a
                ``poseflow.data.bop.ModelInfo`` (metres); gives the symmetries.
            num_points: size of the query cloud.
            seed: seed of the sampling.
            oversample: candidates per kept point for the farthest-point sampling.
            max_sym_disc_step: discretisation step of continuous symmetries.
            name: defaults to the file's stem.
            dtype: dtype of the tensors.
            scale_name: the option that sets ``scale``, for the message of a wrong unit
                (e.g. ``--mesh-scale`` on a command line).

        Returns:
            The :class:`ObjectModel`.

        Raises:
            UnitsError: the scaled mesh's diameter is implausible (see
                :data:`poseflow._units.DIAMETER_RANGE`); the message says which scale to set.
        """
        mesh = load_mesh(path, scale=scale)
        verts = torch.from_numpy(np.ascontiguousarray(mesh.vertices))[None]
        check_diameter_units(
            float(cloud_diameter(verts)[0]), scale_name=scale_name, scale=scale, where=str(path)
        )
        disc, cont = _symmetry_specs(info)
        return cls.from_mesh(
            mesh,
            num_points=num_points,
            seed=seed,
            oversample=oversample,
            symmetries_discrete=disc,
            symmetries_continuous=cont,
            max_sym_disc_step=max_sym_disc_step,
            name=Path(path).stem if name is None else name,
            dtype=dtype,
        )

    def content_key(self) -> str:
        """A key of everything derived data of this object is computed from.

        The mesh in metres (so its scale as well as its geometry, texture and colours) and the
        sampled query cloud: two objects with the same key prepare to the same result, so a
        cache of prepared objects keyed by it (and the configuration) never serves the data of
        another mesh or scale.

        Example:
            >>> import open3d as o3d
            >>> box = o3d.geometry.TriangleMesh.create_box(0.1, 0.2, 0.3)
            >>> a = ObjectModel.from_mesh(box, num_points=16)
            >>> a.content_key() == ObjectModel.from_mesh(box, num_points=16).content_key()
            True
            >>> a.content_key() == ObjectModel.from_mesh(box.scale(2.0, [0, 0, 0]),
            ...                                          num_points=16).content_key()
            False
        """
        m = self.mesh
        return arrays_key(
            {
                "vertices": m.vertices,
                "triangles": m.triangles,
                "triangle_uvs": m.triangle_uvs,
                "texture": m.texture,
                "vertex_colors": m.vertex_colors,
                "vertex_normals": m.vertex_normals,
                "points": self.points,
                "normals": self.normals,
                "colors": self.colors,
            }
        )

    @property
    def num_points(self) -> int:
        """Size ``N`` of the query cloud."""
        return int(self.points.shape[0])

    @property
    def is_symmetric(self) -> bool:
        """Whether the object has any symmetry besides the identity."""
        return self.symmetries.shape[0] > 1

    def model_info(self) -> Any:
        """This object's ``models_info.json`` entry as a ``poseflow.data.bop.ModelInfo``."""
        from poseflow.data.bop import ContinuousSymmetry, ModelInfo

        lo = self.mesh.vertices.min(axis=0)
        return ModelInfo(
            diameter=self.diameter,
            min_xyz=lo,
            size_xyz=self.mesh.vertices.max(axis=0) - lo,
            symmetries_discrete=tuple(self.symmetries_discrete),
            symmetries_continuous=tuple(
                ContinuousSymmetry(axis=a / np.linalg.norm(a), offset=o)
                for a, o in self.symmetries_continuous
            ),
        )

    def __repr__(self) -> str:
        return (
            f"ObjectModel(name={self.name!r}, triangles={self.mesh.num_triangles}, "
            f"points={self.num_points}, diameter={self.diameter:.4f} m, "
            f"symmetries={self.symmetries.shape[0]}, texture={self.mesh.has_texture})"
        )
