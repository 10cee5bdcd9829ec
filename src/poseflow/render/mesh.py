"""Triangle meshes with vertex colours or a UV texture, the renderer's input.

A :class:`TexturedMesh` holds plain numpy arrays, in metres. Its UV convention is the one of
OBJ, PLY and OpenGL: ``(u, v) = (0, 0)`` is the bottom-left corner of the texture image and
``(1, 1)`` its top-right corner, while ``texture`` is stored as read from the image file (row 0
at the top). A texel centre at column ``x``, row ``y`` therefore has
``u = (x + 0.5) / W`` and ``v = 1 - (y + 0.5) / H``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from poseflow.errors import DegenerateInputError, ShapeError, ValueRangeError

__all__ = ["DEFAULT_COLOR", "TexturedMesh", "as_textured_mesh", "sample_texture"]

#: Albedo of a mesh that has neither vertex colours nor a texture (RGB in [0, 1]).
DEFAULT_COLOR = (0.7, 0.7, 0.7)


@dataclass(frozen=True, eq=False)
class TexturedMesh:
    """A triangle mesh with optional vertex colours, vertex normals and one UV texture.

    Args:
        vertices: vertex positions in metres, shape ``(V, 3)``.
        triangles: vertex indices of each triangle, shape ``(F, 3)``.
        vertex_colors: RGB in ``[0, 1]`` per vertex, shape ``(V, 3)``, or None.
        vertex_normals: unit normals per vertex, shape ``(V, 3)``, or None (flat shading).
        triangle_uvs: texture coordinates of each triangle corner, shape ``(F, 3, 2)``, or None.
        texture: the texture image, shape ``(Ht, Wt, 3)`` uint8, row 0 at the top, or None.

    A texture takes precedence over vertex colours when both are present.

    Example:
        >>> m = TexturedMesh(np.eye(3), np.array([[0, 1, 2]]))
        >>> m.num_vertices, m.num_triangles, m.has_texture
        (3, 1, False)
    """

    vertices: np.ndarray
    triangles: np.ndarray
    vertex_colors: np.ndarray | None = None
    vertex_normals: np.ndarray | None = None
    triangle_uvs: np.ndarray | None = None
    texture: np.ndarray | None = None
    _face_normals: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        v = np.ascontiguousarray(self.vertices, dtype=np.float64)
        f = np.ascontiguousarray(self.triangles, dtype=np.int64)
        if v.ndim != 2 or v.shape[1] != 3:
            raise ShapeError(f"vertices must have shape (V, 3), got {v.shape}")
        if f.ndim != 2 or f.shape[1] != 3:
            raise ShapeError(f"triangles must have shape (F, 3), got {f.shape}")
        if len(v) == 0 or len(f) == 0:
            raise DegenerateInputError("a mesh needs at least one vertex and one triangle")
        if not np.isfinite(v).all():
            raise ValueRangeError("vertices contain NaN or inf")
        if f.min() < 0 or f.max() >= len(v):
            raise ValueRangeError(
                f"triangle indices must lie in [0, {len(v)}), got {f.min()}..{f.max()}"
            )
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "triangles", f)
        if self.vertex_colors is not None:
            c = np.asarray(self.vertex_colors)
            c = c.astype(np.float32) / 255.0 if c.dtype == np.uint8 else c.astype(np.float32)
            if c.shape != v.shape:
                raise ShapeError(f"vertex_colors must have shape {v.shape}, got {c.shape}")
            object.__setattr__(self, "vertex_colors", np.clip(c, 0.0, 1.0))
        if self.vertex_normals is not None:
            n = np.asarray(self.vertex_normals, dtype=np.float64)
            if n.shape != v.shape:
                raise ShapeError(f"vertex_normals must have shape {v.shape}, got {n.shape}")
            norm = np.linalg.norm(n, axis=1, keepdims=True)
            object.__setattr__(self, "vertex_normals", n / np.maximum(norm, 1e-12))
        if (self.triangle_uvs is None) != (self.texture is None):
            raise ShapeError("triangle_uvs and texture must be given together")
        if self.triangle_uvs is not None:
            uv = np.asarray(self.triangle_uvs, dtype=np.float32)
            if uv.shape != (len(f), 3, 2):
                raise ShapeError(f"triangle_uvs must have shape ({len(f)}, 3, 2), got {uv.shape}")
            tex = np.asarray(self.texture)
            if tex.ndim == 2:
                tex = np.repeat(tex[:, :, None], 3, axis=2)
            if tex.ndim != 3 or tex.shape[2] not in (3, 4) or tex.dtype != np.uint8:
                raise ShapeError(f"texture must be (Ht, Wt, 3) uint8, got {tex.shape} {tex.dtype}")
            object.__setattr__(self, "triangle_uvs", uv)
            object.__setattr__(self, "texture", np.ascontiguousarray(tex[:, :, :3]))
        e1 = v[f[:, 1]] - v[f[:, 0]]
        e2 = v[f[:, 2]] - v[f[:, 0]]
        fn = np.cross(e1, e2)
        fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
        object.__setattr__(self, "_face_normals", fn)

    @property
    def num_vertices(self) -> int:
        """Number of vertices ``V``."""
        return int(self.vertices.shape[0])

    @property
    def num_triangles(self) -> int:
        """Number of triangles ``F``."""
        return int(self.triangles.shape[0])

    @property
    def has_texture(self) -> bool:
        """Whether the mesh carries a UV texture."""
        return self.texture is not None

    @property
    def has_vertex_colors(self) -> bool:
        """Whether the mesh carries vertex colours."""
        return self.vertex_colors is not None

    @property
    def face_normals(self) -> np.ndarray:
        """Unit normals of the triangles (right-hand rule on the vertex order), ``(F, 3)``."""
        return self._face_normals

    @property
    def triangle_areas(self) -> np.ndarray:
        """Areas of the triangles in square metres, ``(F,)``."""
        v, f = self.vertices, self.triangles
        return 0.5 * np.linalg.norm(
            np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1
        )

    def extent(self) -> np.ndarray:
        """Size of the axis-aligned bounding box along x, y, z in metres, ``(3,)``."""
        return self.vertices.max(axis=0) - self.vertices.min(axis=0)

    def bounding_box_corners(self) -> np.ndarray:
        """The 8 corners of the axis-aligned bounding box, ``(8, 3)``."""
        lo, hi = self.vertices.min(axis=0), self.vertices.max(axis=0)
        idx = np.array([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)])
        return np.where(idx == 1, hi, lo)

    def scaled(self, scale: float) -> TexturedMesh:
        """Return a copy with vertex positions multiplied by ``scale`` (e.g. 0.001 for mm)."""
        if not scale > 0:
            raise ValueRangeError(f"scale must be positive, got {scale}")
        return TexturedMesh(
            self.vertices * scale,
            self.triangles,
            self.vertex_colors,
            self.vertex_normals,
            self.triangle_uvs,
            self.texture,
        )

    def surface_points(self, face_ids: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """Points on triangles from barycentric coordinates.

        Args:
            face_ids: triangle indices, shape ``(P,)``.
            bary: coordinates ``(b1, b2)`` of each point, shape ``(P, 2)``; the point is
                ``(1 - b1 - b2) v0 + b1 v1 + b2 v2`` (Open3D's ``primitive_uvs`` convention).

        Returns:
            The points, shape ``(P, 3)``.
        """
        w = _weights(bary)
        tri = self.vertices[self.triangles[face_ids]]
        return np.einsum("pk,pkc->pc", w, tri)

    def surface_normals(self, face_ids: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """Unit normals at surface points (interpolated vertex normals, else face normals).

        Args:
            face_ids: triangle indices, shape ``(P,)``.
            bary: barycentric coordinates as in :meth:`surface_points`, shape ``(P, 2)``.

        Returns:
            The normals in the mesh frame, shape ``(P, 3)``.
        """
        if self.vertex_normals is None:
            return self._face_normals[face_ids]
        n = np.einsum("pk,pkc->pc", _weights(bary), self.vertex_normals[self.triangles[face_ids]])
        norm = np.linalg.norm(n, axis=1, keepdims=True)
        bad = norm[:, 0] < 1e-8
        n = n / np.maximum(norm, 1e-12)
        n[bad] = self._face_normals[face_ids[bad]]
        return n

    def surface_colors(self, face_ids: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """Albedo at surface points: bilinear texture lookup, else interpolated vertex colours.

        Args:
            face_ids: triangle indices, shape ``(P,)``.
            bary: barycentric coordinates as in :meth:`surface_points`, shape ``(P, 2)``.

        Returns:
            RGB in ``[0, 1]``, shape ``(P, 3)`` float32.
        """
        w = _weights(bary).astype(np.float32)
        if self.texture is not None and self.triangle_uvs is not None:
            uv = np.einsum("pk,pkc->pc", w, self.triangle_uvs[face_ids])
            return sample_texture(self.texture, uv)
        if self.vertex_colors is not None:
            return np.einsum("pk,pkc->pc", w, self.vertex_colors[self.triangles[face_ids]])
        return np.broadcast_to(np.asarray(DEFAULT_COLOR, np.float32), (len(face_ids), 3)).copy()

    def to_open3d(self) -> Any:
        """Convert to a legacy ``open3d.geometry.TriangleMesh`` (texture flipped for Open3D)."""
        from poseflow.render.backend import import_open3d

        o3d = import_open3d("converting meshes to Open3D")

        m = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(self.vertices), o3d.utility.Vector3iVector(self.triangles)
        )
        if self.vertex_colors is not None:
            m.vertex_colors = o3d.utility.Vector3dVector(self.vertex_colors.astype(np.float64))
        if self.vertex_normals is not None:
            m.vertex_normals = o3d.utility.Vector3dVector(self.vertex_normals)
        if self.texture is not None and self.triangle_uvs is not None:
            uv = self.triangle_uvs.reshape(-1, 2).astype(np.float64).copy()
            uv[:, 1] = 1.0 - uv[:, 1]
            m.triangle_uvs = o3d.utility.Vector2dVector(uv)
            m.textures = [o3d.geometry.Image(np.ascontiguousarray(self.texture))]
            m.triangle_material_ids = o3d.utility.IntVector([0] * self.num_triangles)
        return m

    @classmethod
    def from_open3d(cls, mesh: Any) -> TexturedMesh:
        """Convert a legacy ``open3d.geometry.TriangleMesh``.

        Open3D stores texture rows top-down with ``row = v * H`` (its readers flip the image
        on load); this undoes that so that the result follows this module's convention.
        Only the first texture is used.
        """
        v = np.asarray(mesh.vertices)
        f = np.asarray(mesh.triangles)
        colors = np.asarray(mesh.vertex_colors) if mesh.has_vertex_colors() else None
        normals = np.asarray(mesh.vertex_normals) if mesh.has_vertex_normals() else None
        uvs = tex = None
        textures = [np.asarray(t) for t in mesh.textures if np.asarray(t).ndim >= 2]
        if mesh.has_triangle_uvs() and textures:
            uvs = np.asarray(mesh.triangle_uvs).reshape(-1, 3, 2).copy()
            uvs[..., 1] = 1.0 - uvs[..., 1]
            tex = textures[0]
            if tex.dtype != np.uint8:
                tex = (np.clip(tex, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
        return cls(v, f, colors, normals, uvs, tex)


def as_textured_mesh(mesh: Any) -> TexturedMesh:
    """Return ``mesh`` as a :class:`TexturedMesh`.

    Accepts a :class:`TexturedMesh`, anything with a ``mesh`` attribute holding one (such as an
    ``ObjectModel``), or a legacy Open3D ``TriangleMesh``.

    Example:
        >>> import open3d as o3d
        >>> as_textured_mesh(o3d.geometry.TriangleMesh.create_box()).num_triangles
        12
    """
    if isinstance(mesh, TexturedMesh):
        return mesh
    inner = getattr(mesh, "mesh", None)
    if isinstance(inner, TexturedMesh):
        return inner
    if hasattr(mesh, "triangles") and hasattr(mesh, "has_triangle_uvs"):
        return TexturedMesh.from_open3d(mesh)
    raise ShapeError(f"cannot use {type(mesh).__name__} as a mesh")


def sample_texture(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup of a texture at UV coordinates (clamped at the borders).

    Args:
        texture: image, shape ``(Ht, Wt, 3)`` uint8, row 0 at the top.
        uv: coordinates with ``v`` pointing up, shape ``(P, 2)``.

    Returns:
        RGB in ``[0, 1]``, shape ``(P, 3)`` float32.

    Example:
        >>> tex = np.zeros((2, 1, 3), np.uint8); tex[0] = 255  # top row white
        >>> sample_texture(tex, np.array([[0.5, 0.9], [0.5, 0.1]]))[:, 0]
        array([1., 0.], dtype=float32)
    """
    h, w = texture.shape[:2]
    x = np.clip(uv[:, 0].astype(np.float64) * w - 0.5, 0.0, w - 1.0)
    y = np.clip((1.0 - uv[:, 1].astype(np.float64)) * h - 0.5, 0.0, h - 1.0)
    x0 = np.floor(x).astype(np.int64)
    y0 = np.floor(y).astype(np.int64)
    x1 = np.minimum(x0 + 1, w - 1)
    y1 = np.minimum(y0 + 1, h - 1)
    fx = (x - x0)[:, None].astype(np.float32)
    fy = (y - y0)[:, None].astype(np.float32)

    def texel(yy: np.ndarray, xx: np.ndarray) -> np.ndarray:
        return texture[yy, xx].astype(np.float32) * np.float32(1.0 / 255.0)

    top = texel(y0, x0) * (1 - fx) + texel(y0, x1) * fx
    bottom = texel(y1, x0) * (1 - fx) + texel(y1, x1) * fx
    return top * (1 - fy) + bottom * fy


def _weights(bary: np.ndarray) -> np.ndarray:
    b = np.asarray(bary, dtype=np.float64)
    return np.stack([1.0 - b[:, 0] - b[:, 1], b[:, 0], b[:, 1]], axis=1)
