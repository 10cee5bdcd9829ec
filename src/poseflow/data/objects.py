"""Object models: mesh files, the canonical query cloud, diameter and symmetries.

Units are metres inside poseflow. Mesh files are read as they are and multiplied by ``scale``;
BOP model PLYs are in millimetres, so read them with ``scale=0.001``.

Mesh reading is done here rather than by Open3D because Open3D's PLY reader ignores texture
coordinates (BOP stores them as per-vertex ``texture_u``/``texture_v`` with a
``comment TextureFile`` line) and its OBJ reader silently drops faces that are not triangles.
Other formats (STL, OFF, glTF) go through ``open3d.io.read_triangle_mesh``.

UV convention: ``v`` grows upward from the bottom row of the texture image (PLY, OBJ, OpenGL),
the convention of :class:`poseflow.render.mesh.TexturedMesh`.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from poseflow.errors import DegenerateInputError, MeshFormatError, ShapeError, ValueRangeError
from poseflow.geometry.pointcloud import cloud_diameter, farthest_point_sample
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
# Reading meshes


def load_mesh(path: str | Path, *, scale: float = 1.0) -> TexturedMesh:
    r"""Read a triangle mesh with its vertex colours or UV texture.

    Args:
        path: a ``.ply`` (ASCII or binary; vertex ``red/green/blue``, per-vertex
            ``texture_u/texture_v`` or per-face ``texcoord``, ``comment TextureFile``), an ``.obj``
            (``v``/``vt``/``vn``/``f`` with polygons fan-triangulated, ``v x y z r g b`` colours,
            ``mtllib`` + ``map_Kd`` texture) or any format Open3D reads.
        scale: factor applied to vertex positions to get metres (0.001 for BOP models in mm).

    Returns:
        The mesh, in metres.

    Raises:
        MeshFormatError: the file is missing, malformed, has no triangles, or uses more than one
            texture.

    Example:
        >>> import tempfile, pathlib
        >>> p = pathlib.Path(tempfile.mkdtemp()) / "quad.obj"
        >>> _ = p.write_text("v 0 0 0\nv 10 0 0\nv 10 10 0\nv 0 10 0\nf 1 2 3 4\n")
        >>> m = load_mesh(p, scale=0.001)
        >>> m.num_triangles, float(m.vertices.max())
        (2, 0.01)
    """
    path = Path(path)
    if not path.is_file():
        raise MeshFormatError(f"mesh file not found: {path}")
    if not scale > 0:
        raise ValueRangeError(f"scale must be positive, got {scale}")
    suffix = path.suffix.lower()
    try:
        if suffix == ".ply":
            mesh = _read_ply(path)
        elif suffix == ".obj":
            mesh = _read_obj(path)
        else:
            mesh = _read_open3d(path)
    except (ShapeError, ValueRangeError, DegenerateInputError) as e:
        if isinstance(e, MeshFormatError):
            raise
        raise MeshFormatError(f"{path}: {e}") from e
    return mesh if scale == 1.0 else mesh.scaled(scale)


def _read_open3d(path: Path) -> TexturedMesh:
    import open3d as o3d

    m = o3d.io.read_triangle_mesh(str(path), enable_post_processing=False)
    if len(m.triangles) == 0:
        raise MeshFormatError(f"{path}: Open3D read no triangles")
    return TexturedMesh.from_open3d(m)


_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}


@dataclass
class _PlyProperty:
    name: str
    dtype: str
    count_dtype: str | None = None  # set for list properties


@dataclass
class _PlyElement:
    name: str
    count: int
    props: list[_PlyProperty]


def _read_ply(path: Path) -> TexturedMesh:
    data = path.read_bytes()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise MeshFormatError(f"{path}: not a PLY file")
    nl = data.find(b"\n", end)
    header = data[:end].decode("ascii", errors="replace").splitlines()
    body = data[nl + 1 :]
    fmt, texture_file = None, None
    elements: list[_PlyElement] = []
    for line in header[1:]:
        tok = line.split()
        if not tok:
            continue
        if tok[0] == "format":
            fmt = tok[1]
        elif tok[0] == "comment" and len(tok) >= 3 and tok[1].lower() == "texturefile":
            texture_file = line.split(None, 2)[2].strip()
        elif tok[0] == "element":
            elements.append(_PlyElement(tok[1], int(tok[2]), []))
        elif tok[0] == "property":
            if not elements:
                raise MeshFormatError(f"{path}: property before any element")
            try:
                if tok[1] == "list":
                    prop = _PlyProperty(tok[4], _PLY_TYPES[tok[3]], _PLY_TYPES[tok[2]])
                else:
                    prop = _PlyProperty(tok[2], _PLY_TYPES[tok[1]])
            except (KeyError, IndexError) as e:
                raise MeshFormatError(f"{path}: bad property line {line!r}") from e
            elements[-1].props.append(prop)
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise MeshFormatError(f"{path}: unknown PLY format {fmt!r}")
    if fmt == "ascii":
        try:
            tables = _ply_ascii(body, elements, path)
        except (ValueError, IndexError) as e:
            raise MeshFormatError(f"{path}: malformed ASCII data ({e})") from e
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        try:
            tables = _ply_binary(body, elements, order, path)
        except ValueError as e:  # numpy: buffer too small
            raise MeshFormatError(f"{path}: truncated or malformed binary data ({e})") from e
    if "vertex" not in tables or "face" not in tables:
        raise MeshFormatError(f"{path}: a mesh PLY needs vertex and face elements")
    vert, face = tables["vertex"], tables["face"]
    try:
        v = np.stack([np.asarray(vert[a], np.float64) for a in "xyz"], axis=1)
    except KeyError as e:
        raise MeshFormatError(f"{path}: vertices need x, y, z") from e
    normals = None
    if all(a in vert for a in ("nx", "ny", "nz")):
        normals = np.stack([np.asarray(vert[a], np.float64) for a in ("nx", "ny", "nz")], axis=1)
        if not (np.linalg.norm(normals, axis=1) > 1e-8).all():
            normals = None
    colors = None
    names = [n for n in (("red", "green", "blue"), ("r", "g", "b")) if all(c in vert for c in n)]
    if names:
        c = np.stack([np.asarray(vert[a]) for a in names[0]], axis=1)
        colors = c / 255.0 if np.issubdtype(c.dtype, np.integer) else c.astype(np.float64)
    polys = face.get("vertex_indices", face.get("vertex_index"))
    if polys is None:
        raise MeshFormatError(f"{path}: faces need vertex_indices")
    tris, corner = _triangulate(polys)
    uvs = None
    uv_names = [n for n in (("texture_u", "texture_v"), ("u", "v"), ("s", "t")) if n[0] in vert]
    if "texcoord" in face:
        tc = face["texcoord"]
        flat = [np.asarray(t, np.float64).reshape(-1, 2) for t in tc]
        per_corner = np.concatenate(flat, axis=0)
        uvs = per_corner[corner]
    elif uv_names and uv_names[0][1] in vert:
        uv = np.stack([np.asarray(vert[a], np.float64) for a in uv_names[0]], axis=1)
        uvs = uv[tris]
    texture = None
    if uvs is not None and texture_file is not None:
        texture = _read_texture(path.parent / texture_file, path)
    if texture is None:
        uvs = None
    return TexturedMesh(v, tris, colors, normals, uvs, texture)


def _triangulate(polys: Any) -> tuple[np.ndarray, np.ndarray]:
    """Fan-triangulate polygons.

    Also returns, per triangle corner, its index in the flat list of polygon corners (to pick
    per-corner attributes).
    """
    if isinstance(polys, np.ndarray) and polys.ndim == 2:
        n = polys.shape[1]
        if n < 3:
            raise MeshFormatError("faces need at least 3 vertices")
        base = np.arange(polys.shape[0])[:, None] * n
        fan = np.array([[0, j, j + 1] for j in range(1, n - 1)])
        tris = polys[:, fan].reshape(-1, 3)
        corner = (base[:, None, :] + fan[None]).reshape(-1, 3)
        return tris.astype(np.int64), corner
    tris, corner, start = [], [], 0
    for p in polys:
        p = np.asarray(p, np.int64)
        if len(p) >= 3:
            for j in range(1, len(p) - 1):
                tris.append((p[0], p[j], p[j + 1]))
                corner.append((start, start + j, start + j + 1))
        start += len(p)
    if not tris:
        raise MeshFormatError("the mesh has no triangles")
    return np.asarray(tris, np.int64), np.asarray(corner, np.int64)


def _ply_binary(
    body: bytes, elements: list[_PlyElement], order: str, path: Path
) -> dict[str, dict[str, Any]]:
    tables: dict[str, dict[str, Any]] = {}
    pos = 0
    for el in elements:
        if all(p.count_dtype is None for p in el.props):
            dt = np.dtype([(p.name, order + p.dtype) for p in el.props])
            arr = np.frombuffer(body, dtype=dt, count=el.count, offset=pos)
            pos += dt.itemsize * el.count
            tables[el.name] = {p.name: arr[p.name] for p in el.props}
            continue
        # lists: try a fixed length per list (taken from the first record), then verify
        fixed, probe, fields = True, pos, []
        for p in el.props:
            if p.count_dtype is None:
                fields.append((p.name, order + p.dtype))
                probe += np.dtype(p.dtype).itemsize
            else:
                n = int(np.frombuffer(body, order + p.count_dtype, 1, probe)[0]) if el.count else 0
                fields.append((p.name + "#n", order + p.count_dtype))
                fields.append((p.name, order + p.dtype, (n,)))
                probe += np.dtype(p.count_dtype).itemsize + n * np.dtype(p.dtype).itemsize
        dt = np.dtype(fields)
        if pos + dt.itemsize * el.count <= len(body):
            arr = np.frombuffer(body, dtype=dt, count=el.count, offset=pos)
            for p in el.props:
                if (
                    p.count_dtype is not None
                    and not (arr[p.name + "#n"] == dt[p.name].shape[0]).all()
                ):
                    fixed = False
        else:
            fixed = False
        if fixed:
            pos += dt.itemsize * el.count
            tables[el.name] = {p.name: arr[p.name] for p in el.props}
            continue
        cols: dict[str, list[Any]] = {p.name: [] for p in el.props}
        for _ in range(el.count):
            for p in el.props:
                if p.count_dtype is None:
                    cols[p.name].append(np.frombuffer(body, order + p.dtype, 1, pos)[0])
                    pos += np.dtype(p.dtype).itemsize
                else:
                    n = int(np.frombuffer(body, order + p.count_dtype, 1, pos)[0])
                    pos += np.dtype(p.count_dtype).itemsize
                    cols[p.name].append(np.frombuffer(body, order + p.dtype, n, pos))
                    pos += n * np.dtype(p.dtype).itemsize
        tables[el.name] = {
            k: (np.asarray(c) if el.props[i].count_dtype is None else c)
            for i, (k, c) in enumerate(cols.items())
        }
    if pos > len(body):
        raise MeshFormatError(f"{path}: file is truncated")
    return tables


def _ply_ascii(body: bytes, elements: list[_PlyElement], path: Path) -> dict[str, dict[str, Any]]:
    lines = body.decode("ascii", errors="replace").splitlines()
    tables: dict[str, dict[str, Any]] = {}
    at = 0
    for el in elements:
        rows = lines[at : at + el.count]
        if len(rows) < el.count:
            raise MeshFormatError(f"{path}: file is truncated in element {el.name!r}")
        at += el.count
        if all(p.count_dtype is None for p in el.props):
            arr = np.loadtxt(rows, dtype=np.float64, ndmin=2) if rows else np.zeros((0, 0))
            tables[el.name] = {
                p.name: arr[:, i].astype(p.dtype) if rows else np.zeros(0, p.dtype)
                for i, p in enumerate(el.props)
            }
            continue
        cols: dict[str, list[Any]] = {p.name: [] for p in el.props}
        for row in rows:
            tok, i = row.split(), 0
            for p in el.props:
                if p.count_dtype is None:
                    cols[p.name].append(float(tok[i]))
                    i += 1
                else:
                    n = int(tok[i])
                    cols[p.name].append(
                        np.asarray(tok[i + 1 : i + 1 + n], np.float64).astype(p.dtype)
                    )
                    i += 1 + n
        tables[el.name] = {
            p.name: (np.asarray(cols[p.name]) if p.count_dtype is None else cols[p.name])
            for p in el.props
        }
    return tables


def _read_texture(path: Path, mesh_path: Path) -> np.ndarray:
    from PIL import Image

    if not path.is_file():
        raise MeshFormatError(f"{mesh_path}: texture file not found: {path}")
    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"), dtype=np.uint8).copy()


def _read_obj(path: Path) -> TexturedMesh:
    vs: list[list[float]] = []
    vts: list[list[float]] = []
    vns: list[list[float]] = []
    faces: list[list[tuple[int, int, int]]] = []
    materials: list[str | None] = []
    mtllibs: list[str] = []
    current: str | None = None
    for raw in path.read_text(errors="replace").splitlines():
        tok = raw.split("#", 1)[0].split()
        if not tok:
            continue
        key = tok[0]
        if key == "v":
            vs.append([float(x) for x in tok[1:7]])
        elif key == "vt":
            vts.append([float(x) for x in tok[1:3]])
        elif key == "vn":
            vns.append([float(x) for x in tok[1:4]])
        elif key == "f":
            corners = []
            for c in tok[1:]:
                parts = [*c.split("/"), "", ""][:3]
                idx = []
                for j, s in enumerate(parts):
                    if s == "":
                        idx.append(-1)
                        continue
                    i = int(s)
                    n = (len(vs), len(vts), len(vns))[j]
                    idx.append(i - 1 if i > 0 else n + i)
                corners.append((idx[0], idx[1], idx[2]))
            faces.append(corners)
            materials.append(current)
        elif key == "mtllib":
            mtllibs.append(raw.split(None, 1)[1].strip())
        elif key == "usemtl":
            current = raw.split(None, 1)[1].strip() if len(tok) > 1 else None
    if not vs or not faces:
        raise MeshFormatError(f"{path}: no vertices or faces")
    widths = {len(v) for v in vs}
    if not widths <= {3, 6}:
        raise MeshFormatError(f"{path}: vertices need 3 coordinates (and optionally 3 colours)")
    maps = _obj_texture_maps(path, mtllibs)
    used = {maps[m] for m in set(materials) if m in maps}
    if len(used) > 1:
        raise MeshFormatError(f"{path}: uses {len(used)} textures; only one is supported")
    tri_corners = []
    for corners in faces:
        for j in range(1, len(corners) - 1):
            tri_corners.append((corners[0], corners[j], corners[j + 1]))
    if not tri_corners:
        raise MeshFormatError(f"{path}: no triangles")
    c = np.asarray(tri_corners, np.int64)  # (F, 3, 3): v, vt, vn per corner
    if (c[..., 0] < 0).any() or c[..., 0].max() >= len(vs):
        raise MeshFormatError(f"{path}: face references a missing vertex")
    has_n = bool(vns) and (c[..., 2] >= 0).all()
    has_t = bool(vts) and (c[..., 1] >= 0).all() and bool(used)
    # vertices are shared per (position, normal) pair so that flat-shaded OBJs stay flat
    key = c[..., [0, 2]] if has_n else c[..., [0, 0]]
    uniq, inv = np.unique(key.reshape(-1, 2), axis=0, return_inverse=True)
    tris = inv.reshape(-1, 3)
    va = np.asarray(vs, np.float64)
    pos = va[uniq[:, 0], :3]
    colors = va[uniq[:, 0], 3:6] if va.shape[1] == 6 else None
    normals = np.asarray(vns, np.float64)[uniq[:, 1]] if has_n else None
    uvs = texture = None
    if has_t:
        uvs = np.asarray(vts, np.float64)[c[..., 1]]
        texture = _read_texture(next(iter(used)), path)
    return TexturedMesh(pos, tris, colors, normals, uvs, texture)


def _obj_texture_maps(path: Path, mtllibs: list[str]) -> dict[str, Path]:
    maps: dict[str, Path] = {}
    for lib in mtllibs:
        p = path.parent / lib
        if not p.is_file():
            continue
        name = None
        for raw in p.read_text(errors="replace").splitlines():
            tok = raw.split()
            if not tok:
                continue
            if tok[0] == "newmtl":
                name = raw.split(None, 1)[1].strip()
            elif tok[0] == "map_Kd" and name is not None:
                # the file name is the last token (options such as -s may precede it)
                maps[name] = (p.parent / re.split(r"\s+", raw.strip())[-1]).resolve()
    return maps


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


def _rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    a = axis / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * (K @ K)


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
        for i in range(n):
            T = np.eye(4)
            T[:3, :3] = _rotation_about(axis, 2 * math.pi * i / n)
            T[:3, 3] = offset - T[:3, :3] @ offset
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
    ) -> ObjectModel:
        """Load a mesh file and build its model (see :meth:`from_mesh`).

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

        Returns:
            The :class:`ObjectModel`.
        """
        mesh = load_mesh(path, scale=scale)
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
