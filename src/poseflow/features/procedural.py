"""Procedural objects for training the learned descriptor: random meshes and solid textures.

- :func:`random_mesh`: one to four Open3D primitives (boxes, cylinders, cones, spheres,
  ellipsoids, tori, polyhedra, radially deformed blobs) joined, then scaled, twisted, bent or
  tapered; flat parts are shaded flat, round parts smooth;
- :func:`random_texture`: a :data:`SolidTexture`, a function of the model-frame point and normal
  (so that every view sees the same surface): plain or two-tone paint, 3D noise blotches,
  stripes, checks, dots, images mapped by triplanar projection (:func:`texture_images`:
  text-like prints, barcodes, tables, and photographs available offline such as matplotlib's
  sample images), or a patchwork of these in 3D Voronoi cells with dark seams.

None of it is a user's object: :mod:`poseflow.features.view_pairs` renders them for
:mod:`poseflow.features.descriptor_training`.
"""

from __future__ import annotations

import importlib.util
import math
import string
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from poseflow.errors import ValueRangeError
from poseflow.geometry.se3 import quaternion_to_rotation
from poseflow.render.mesh import TexturedMesh, sample_texture

__all__ = [
    "SolidTexture",
    "mix_colors",
    "random_color",
    "random_direction",
    "random_mesh",
    "random_texture",
    "texture_images",
    "value_noise",
]

#: A solid texture: albedo RGB in ``[0, 1]`` ``(P, 3)`` of model points ``(P, 3)`` (in diameters,
#: centred) with their unit normals ``(P, 3)``.
SolidTexture = Callable[[np.ndarray, np.ndarray], np.ndarray]


def _primitive(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, bool]:
    """One Open3D primitive of unit-ish size: ``(vertices, triangles, smooth)``."""
    from poseflow.render.backend import import_open3d

    o3d = import_open3d("generating descriptor training meshes")
    tm = o3d.geometry.TriangleMesh
    kinds = ("box", "box", "cylinder", "cylinder", "cone", "sphere", "ellipsoid", "torus")
    kind = rng.choice([*kinds, "poly", "blob", "blob"])
    s = rng.uniform(0.3, 1.0, size=3)
    if kind == "box":
        m = tm.create_box(*s).translate(-s / 2).subdivide_midpoint(2)
    elif kind == "cylinder":
        m = tm.create_cylinder(s[0] / 2, s[2], resolution=int(rng.integers(6, 40)), split=4)
    elif kind == "cone":
        m = tm.create_cone(s[0] / 2, s[2], resolution=int(rng.integers(6, 40)), split=4)
    elif kind in ("sphere", "ellipsoid", "blob"):
        m = tm.create_sphere(0.5, resolution=24)
    elif kind == "torus":
        m = tm.create_torus(0.4, float(rng.uniform(0.08, 0.25)), 40, 16)
    else:
        m = [tm.create_icosahedron, tm.create_octahedron, tm.create_tetrahedron][
            int(rng.integers(3))
        ](0.5)
        m = m.subdivide_midpoint(1)
    v = np.asarray(m.vertices).copy()
    f = np.asarray(m.triangles).copy()
    if kind == "ellipsoid":
        v *= s
    if kind == "blob":
        noise = value_noise(rng, float(rng.uniform(1.5, 4.0)))
        d = v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-9)
        v = d * (0.5 * (1 + rng.uniform(0.2, 0.7) * (noise(d * 0.5) - 0.5)))[:, None]
        v *= s
    return v, f, kind in ("sphere", "ellipsoid", "torus", "blob")


def _deform(rng: np.random.Generator, v: np.ndarray) -> np.ndarray:
    """Random global deformations: twist, bend, taper (each with some probability)."""
    v = v.copy()
    ext = np.ptp(v, axis=0).max() + 1e-9
    if rng.random() < 0.3:  # twist about z
        a = rng.uniform(-1.5, 1.5) * v[:, 2] / ext
        c, s = np.cos(a), np.sin(a)
        v[:, 0], v[:, 1] = c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1]
    if rng.random() < 0.3:  # bend in x along z
        v[:, 0] += rng.uniform(-0.8, 0.8) * (v[:, 2] / ext) ** 2 * ext
    if rng.random() < 0.3:  # taper along z
        v[:, :2] *= (1 + rng.uniform(-0.6, 0.6) * v[:, 2] / ext)[:, None]
    return v


def _normals(
    v: np.ndarray, f: np.ndarray, smooth: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertex normals; flat parts get their own vertices per triangle (face normals)."""
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    if smooth:
        n = np.zeros_like(v)
        for k in range(3):
            np.add.at(n, f[:, k], fn)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        return v, f, n
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-12)
    return v[f].reshape(-1, 3), np.arange(3 * len(f)).reshape(-1, 3), np.repeat(fn, 3, axis=0)


def random_mesh(
    rng: np.random.Generator, *, diameter: float = 0.15, max_parts: int = 4
) -> TexturedMesh:
    """A procedural mesh: joined, deformed Open3D primitives, centred, of a given diameter.

    Args:
        rng: the random generator.
        diameter: the diagonal of the bounding box, metres.
        max_parts: most primitives joined.

    Returns:
        The mesh (vertex normals, no colours), centred on its bounding box.

    Example:
        >>> m = random_mesh(np.random.default_rng(0))
        >>> bool(abs(np.linalg.norm(m.extent()) - 0.15) < 1e-9)
        True
    """
    if not diameter > 0 or max_parts < 1:
        raise ValueRangeError("diameter must be positive and max_parts at least 1")
    n_parts = 1 + int(rng.binomial(max_parts - 1, 0.4))
    parts = []
    for k in range(n_parts):
        v, f, smooth = _primitive(rng)
        v = (
            v
            @ quaternion_to_rotation(rng.normal(size=4)).T
            * (1.0 if k == 0 else rng.uniform(0.4, 0.9))
        )
        if k:
            v = v + rng.uniform(-0.4, 0.4, size=3)
        parts.append((v, f, smooth))
    allv = np.concatenate([p[0] for p in parts])
    deformed = _deform(rng, allv) * rng.uniform(0.5, 1.5, size=3)
    verts, tris, normals, start = [], [], [], 0
    offset = 0
    for v, f, smooth in parts:
        dv = deformed[start : start + len(v)]
        start += len(v)
        nv, nf, nn = _normals(dv, f, smooth)
        verts.append(nv)
        tris.append(nf + offset)
        normals.append(nn)
        offset += len(nv)
    v = np.concatenate(verts)
    lo, hi = v.min(axis=0), v.max(axis=0)
    v = (v - (lo + hi) / 2) * (diameter / np.linalg.norm(hi - lo))
    return TexturedMesh(v, np.concatenate(tris), vertex_normals=np.concatenate(normals))


# --------------------------------------------------------------------------------------------
# Solid textures
# --------------------------------------------------------------------------------------------


def value_noise(rng: np.random.Generator, freq: float) -> Callable[[np.ndarray], np.ndarray]:
    """Smooth 3D value noise in ``[0, 1]`` with about ``freq`` cells per unit."""
    n = math.ceil(2 * freq) + 3
    grid = rng.random((n, n, n))

    def noise(p: np.ndarray) -> np.ndarray:
        q = np.clip((p + 1.0) * freq, 0.0, n - 1.001)
        i = np.floor(q).astype(np.int64)
        t = q - i
        t = t * t * (3 - 2 * t)
        out = np.zeros(len(p))
        for dx in (0, 1):
            wx = t[:, 0] if dx else 1 - t[:, 0]
            for dy in (0, 1):
                wy = t[:, 1] if dy else 1 - t[:, 1]
                for dz in (0, 1):
                    wz = t[:, 2] if dz else 1 - t[:, 2]
                    out += wx * wy * wz * grid[i[:, 0] + dx, i[:, 1] + dy, i[:, 2] + dz]
        return out

    return noise


def random_color(rng: np.random.Generator) -> np.ndarray:
    """A random RGB colour (HSV drawn to favour both vivid and greyish paints)."""
    h, s, v = rng.random(), rng.uniform(0, 1) ** 0.7, rng.uniform(0.15, 1.0)
    k = (np.array([5.0, 3.0, 1.0]) + h * 6) % 6
    return (v - v * s * np.clip(np.minimum(k, 4 - k), 0, 1)).astype(np.float32)


def mix_colors(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``(P, 3)`` colours between ``a`` and ``b`` ``(3,)`` at weights ``t`` ``(P,)`` in [0, 1]."""
    return (a[None] * (1 - t[:, None]) + b[None] * t[:, None]).astype(np.float32)


def random_direction(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random unit vector ``(3,)``."""
    d = rng.normal(size=3)
    return d / np.linalg.norm(d)


def _basic_texture(rng: np.random.Generator, images: Sequence[np.ndarray]) -> SolidTexture:
    """One non-patchwork texture."""
    kind = rng.choice(["plain", "two_tone", "noise", "stripes", "checks", "dots", "image", "image"])
    c1, c2 = random_color(rng), random_color(rng)
    if kind == "plain":
        return lambda p, n: np.broadcast_to(c1, p.shape).copy()
    if kind == "two_tone":
        d, off = random_direction(rng), rng.uniform(-0.2, 0.2)
        return lambda p, n: np.where(((p @ d) > off)[:, None], c1, c2).astype(np.float32)
    if kind == "noise":
        noise = value_noise(rng, float(rng.uniform(1.5, 10.0)))
        sharp = rng.uniform(1.0, 12.0)
        c3 = random_color(rng)

        def blotches(p: np.ndarray, n: np.ndarray) -> np.ndarray:
            t = 1 / (1 + np.exp(-sharp * (noise(p) - 0.5)))
            out = mix_colors(c1, c2, t)
            return np.where((t > 0.85)[:, None], c3, out).astype(np.float32)

        return blotches
    if kind == "stripes":
        d, freq = random_direction(rng), rng.uniform(3.0, 25.0)
        duty, zig = rng.uniform(0.2, 0.8), rng.uniform(0, 0.15) * (rng.random() < 0.4)
        e = random_direction(rng)
        return lambda p, n: np.where(
            ((p @ d + zig * np.abs(((p @ e) * freq * 2) % 2 - 1)) * freq % 1.0 < duty)[:, None],
            c1,
            c2,
        ).astype(np.float32)
    if kind == "checks":
        freq, R = rng.uniform(3.0, 15.0), quaternion_to_rotation(rng.normal(size=4))
        return lambda p, n: np.where(
            (np.floor((p @ R.T) * freq).sum(axis=1) % 2 == 0)[:, None], c1, c2
        ).astype(np.float32)
    if kind == "dots":
        freq, rad, R = (
            rng.uniform(4.0, 15.0),
            rng.uniform(0.15, 0.45),
            quaternion_to_rotation(rng.normal(size=4)),
        )

        def dots(p: np.ndarray, n: np.ndarray) -> np.ndarray:
            q = (p @ R.T) * freq
            d = np.linalg.norm(q - np.round(q), axis=1)
            return np.where((d < rad)[:, None], c1, c2).astype(np.float32)

        return dots
    return _triplanar(rng, images[int(rng.integers(len(images)))])


def _triplanar(rng: np.random.Generator, image: np.ndarray) -> SolidTexture:
    """An image projected along the model axis closest to each point's normal (tiled)."""
    scale = rng.uniform(0.6, 3.0)
    offset = rng.random((3, 2))
    R = quaternion_to_rotation(rng.normal(size=4))
    pairs = ((1, 2), (0, 2), (0, 1))

    def project(p: np.ndarray, n: np.ndarray) -> np.ndarray:
        q, m = p @ R.T, n @ R.T
        axis = np.abs(m).argmax(axis=1)
        out = np.empty((len(p), 3), np.float32)
        for a, (i, j) in enumerate(pairs):
            sel = axis == a
            if sel.any():
                uv = (q[sel][:, [i, j]] * scale + offset[a]) % 1.0
                out[sel] = sample_texture(image, uv)
        return out

    return project


def random_texture(
    rng: np.random.Generator, images: Sequence[np.ndarray], *, patchwork: float = 0.3
) -> SolidTexture:
    """A random solid texture (see the module docstring for the kinds).

    Args:
        rng: the random generator.
        images: texture images ``(Ht, Wt, 3)`` uint8 for the triplanar prints
            (:func:`texture_images`).
        patchwork: probability of a patchwork of several textures in 3D Voronoi cells.

    Returns:
        The texture: ``(points (P, 3), normals (P, 3)) -> albedo (P, 3)``.

    Example:
        >>> rng = np.random.default_rng(0)
        >>> tex = random_texture(rng, [np.zeros((4, 4, 3), np.uint8)])
        >>> tex(rng.random((5, 3)) - 0.5, np.tile([0.0, 0.0, 1.0], (5, 1))).shape
        (5, 3)
    """
    if not images:
        raise ValueRangeError("random_texture needs at least one texture image")
    if rng.random() >= patchwork:
        return _basic_texture(rng, images)
    k = int(rng.integers(4, 16))
    seeds = rng.uniform(-0.5, 0.5, size=(k, 3))
    cells = [_basic_texture(rng, images) for _ in range(k)]
    seam, seam_color = rng.uniform(0.0, 0.03), random_color(rng) * rng.uniform(0.0, 0.5)

    def patch(p: np.ndarray, n: np.ndarray) -> np.ndarray:
        d = np.linalg.norm(p[:, None] - seeds[None], axis=2)
        order = np.argsort(d, axis=1)[:, :2]
        first = order[:, 0]
        gap = np.take_along_axis(d, order, axis=1)
        out = np.empty((len(p), 3), np.float32)
        for c in np.unique(first):
            sel = first == c
            out[sel] = cells[c](p[sel], n[sel])
        edge = (gap[:, 1] - gap[:, 0]) < seam
        out[edge] = seam_color
        return out

    return patch


def _text_image(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """A print-like image: text lines, boxes, bars, tables and discs in random colours."""
    from PIL import Image, ImageDraw, ImageFont

    bg = tuple(int(c) for c in (random_color(rng) * 255))
    img = Image.new("RGB", (size, size), bg)
    draw = ImageDraw.Draw(img)
    alphabet = string.ascii_letters + string.digits + "  %-.,/"
    for _ in range(int(rng.integers(3, 9))):
        ink = tuple(int(c) for c in (random_color(rng) * 255))
        what = rng.random()
        x, y = (int(v) for v in rng.integers(-20, size, size=2))
        if what < 0.45:
            font = ImageFont.load_default(size=int(rng.integers(9, 48)))
            text = "".join(rng.choice(list(alphabet), size=int(rng.integers(3, 16))))
            draw.text((x, y), text, fill=ink, font=font)
        elif what < 0.6:  # barcode
            w = int(rng.integers(40, 120))
            h = int(rng.integers(20, 80))
            xs = x + np.cumsum(rng.integers(1, 5, size=60))
            for k, xx in enumerate(xs[xs < x + w]):
                if k % 2 == 0:
                    draw.rectangle([int(xx), y, int(xx) + int(rng.integers(1, 3)), y + h], ink)
        elif what < 0.75:  # table
            rows, cols = (int(v) for v in rng.integers(2, 7, size=2))
            cw, ch = (int(v) for v in rng.integers(12, 40, size=2))
            for r in range(rows + 1):
                draw.line([x, y + r * ch, x + cols * cw, y + r * ch], ink, 1)
            for c in range(cols + 1):
                draw.line([x + c * cw, y, x + c * cw, y + rows * ch], ink, 1)
        elif what < 0.9:
            w, h = (int(v) for v in rng.integers(10, 120, size=2))
            draw.rectangle([x, y, x + w, y + h], ink)
        else:
            r = int(rng.integers(5, 60))
            draw.ellipse([x, y, x + r, y + r], ink)
    return np.asarray(img, dtype=np.uint8).copy()


def texture_images(
    rng: np.random.Generator, *, count: int = 24, photos: bool = True
) -> list[np.ndarray]:
    """Images for the triplanar prints: generated print-like images plus offline photographs.

    The photographs are matplotlib's sample images (a portrait, a packaging photo, a logo, a
    shaded relief map) when matplotlib is installed; nothing is downloaded.

    Args:
        rng: the random generator.
        count: generated print-like images.
        photos: add the photographs.

    Returns:
        RGB images ``(Ht, Wt, 3)`` uint8.
    """
    out = [_text_image(rng) for _ in range(count)]
    if photos:
        out.extend(_photos())
    return out


def _photos() -> list[np.ndarray]:
    from PIL import Image

    spec = importlib.util.find_spec("matplotlib")
    if spec is None or spec.origin is None:
        return []
    folder = Path(spec.origin).parent / "mpl-data" / "sample_data"
    out = []
    for name in ("grace_hopper.jpg", "Minduka_Present_Blue_Pack.png", "logo2.png"):
        path = folder / name
        if path.is_file():
            img = Image.open(path).convert("RGB")
            img.thumbnail((384, 384))
            out.append(np.asarray(img, dtype=np.uint8).copy())
    relief = folder / "topobathy.npz"
    if relief.is_file():
        z = np.load(relief)["topo"].astype(np.float64)
        z = (z - z.min()) / max(np.ptp(z), 1e-9)
        rgb = np.stack([z, 0.5 + 0.5 * np.sin(6 * z), 1 - z], axis=-1)
        out.append((rgb * 255).astype(np.uint8))
    return out
