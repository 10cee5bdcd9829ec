"""Read triangle meshes with their colours and textures: PLY and OBJ here, other formats by Open3D.

Mesh reading is done here rather than by Open3D because Open3D's PLY reader ignores texture
coordinates (BOP stores them as per-vertex ``texture_u``/``texture_v`` with a
``comment TextureFile`` line) and its OBJ reader silently drops faces that are not triangles.
Other formats (STL, OFF, glTF) go through ``open3d.io.read_triangle_mesh``.

UV convention: ``v`` grows upward from the bottom row of the texture image (PLY, OBJ, OpenGL),
the convention of :class:`poseflow.render.mesh.TexturedMesh`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from poseflow.errors import DegenerateInputError, MeshFormatError, ShapeError, ValueRangeError
from poseflow.render.mesh import TexturedMesh

__all__ = ["load_mesh"]


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
    from poseflow.render.backend import import_open3d

    o3d = import_open3d("reading this mesh format")

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
    """A PLY mesh, ASCII or binary, with the normals, colours and texture it holds."""
    fmt, texture_file, elements, body = _ply_header(path.read_bytes(), path)
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
    return _ply_mesh(tables["vertex"], tables["face"], texture_file, path)


def _ply_header(data: bytes, path: Path) -> tuple[str, str | None, list[_PlyElement], bytes]:
    """A PLY's format, texture file and elements, and the body that follows the header."""
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
    return fmt, texture_file, elements, body


def _ply_mesh(
    vert: dict[str, Any], face: dict[str, Any], texture_file: str | None, path: Path
) -> TexturedMesh:
    """The mesh of a PLY's ``vertex`` and ``face`` columns (by property name)."""
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
