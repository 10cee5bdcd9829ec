"""Training the learned appearance descriptor on generated renders of procedural objects.

The data never contains a user's object. Every training pair is made as follows:

1. a procedural mesh (:func:`random_mesh`): one to four Open3D primitives (boxes, cylinders,
   cones, spheres, ellipsoids, tori, polyhedra, radially deformed blobs) joined, then scaled,
   twisted, bent or tapered; flat parts are shaded flat, round parts smooth;
2. a random solid texture (:func:`random_texture`): a function of the model-frame point and
   normal, so that both views see the same surface: plain or two-tone paint, 3D noise blotches,
   stripes, checks, dots, images mapped by triplanar projection (text-like prints, barcodes,
   tables, and photographs available offline such as matplotlib's sample images), or a
   patchwork of these in 3D Voronoi cells with dark seams;
3. two renderings (:func:`render_pair`) with poseflow's ray caster from viewpoints that differ by
   up to ``max_view_angle`` plus an arbitrary in-plane roll (the rotation augmentation), each at
   its own scale (the object spans 32 to 192 pixels before the crop is resized to
   ``input_size``, the scale augmentation), its own light (ambient, Lambertian and specular
   terms), background, optional clutter object (occluding or behind), blur and noise; each is
   cropped exactly as FunFlow6D crops a target (the square around the projection of the visible
   points' barycentre, with a random margin and jitter) and resized; in half of the pairs view
   A is instead rendered the way the query's views are (black background, headlight, no
   clutter, blur or noise, the lifting's crop), since FunFlow6D matches those renderings
   against observed crops;
4. the ground-truth correspondences: every object pixel of crop A is lifted with its depth to the
   model frame, projected into view B, and kept where B's depth at that pixel agrees (visible,
   not occluded).

The loss (:func:`descriptor_loss`) is InfoNCE over those correspondences in both directions: the
descriptor of a pixel in one view is scored against every feature cell of the other view (object
and background), with a soft target on the true match and the cells around it (Gaussian in the
surface distance, ``sigma`` diameters), so that descriptors vary smoothly over the surface at the
scale at which FunFlow6D's sparse clouds are matched. Colour jitter is applied independently to
each view.

:func:`train_descriptor` trains a :class:`~poseflow.features.learned.DescriptorNet` with AdamW
and a cosine schedule, one CPU thread friendly, seeded, and writes ``model.safetensors`` +
``config.json`` atomically (also every ``save_every`` steps). The shipped weights are made by::

    python -m poseflow.features.descriptor_training --out src/poseflow/assets/descriptor --steps N
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import string
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F

from poseflow.errors import DegenerateInputError, ValueRangeError
from poseflow.features.appearance import sample_features
from poseflow.features.learned import DescriptorNet, save_descriptor
from poseflow.features.lifting import jitter_boxes
from poseflow.geometry.pointcloud import crop_box_around, crop_resize, pixels_to_crop
from poseflow.render.mesh import TexturedMesh, sample_texture
from poseflow.render.raycast import Light, Renderer, RenderOutput

__all__ = [
    "DescriptorTrainingConfig",
    "PairBatch",
    "PairGenerator",
    "SolidTexture",
    "ViewPair",
    "descriptor_loss",
    "main",
    "random_mesh",
    "random_texture",
    "render_pair",
    "texture_images",
    "train_descriptor",
]

#: A solid texture: albedo RGB in ``[0, 1]`` ``(P, 3)`` of model points ``(P, 3)`` (in diameters,
#: centred) with their unit normals ``(P, 3)``.
SolidTexture = Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclass(frozen=True)
class DescriptorTrainingConfig:
    """Settings of :func:`train_descriptor` (written to ``config.json`` under ``training``).

    Attributes:
        steps: optimiser steps.
        batch_size: view pairs per step.
        input_size: side of the square crops, pixels (FunFlow6D's ``crop_size``).
        widths: channels per level of the network.
        dim: descriptor channels ``G``.
        out_stride: output stride of the descriptor map.
        lr: peak AdamW learning rate (linear warm-up over 5 % of the steps, cosine decay).
        weight_decay: AdamW weight decay.
        temperature: InfoNCE temperature.
        anchors: correspondences per pair and direction.
        exclusion: feature cells whose surface point is closer than this (fraction of the
            diameter) to the true match are not negatives (with ``sigma = 0``).
        sigma: width of the loss's soft target around the match, fraction of the diameter (see
            :func:`descriptor_loss`); 0: hard InfoNCE.
        fresh_pairs: new pairs rendered per step; the rest of the batch is drawn from a pool of
            ``pool_size`` recent pairs (with new colour jitter).
        pool_size: pairs kept for reuse.
        max_view_angle: largest out-of-plane angle between the two views, degrees (the in-plane
            roll is uniform over 360°).
        clutter: probability of a second object in a view (occluding or behind).
        seed: seeds the data and the network.
    """

    steps: int = 2000
    batch_size: int = 8
    input_size: int = 96
    widths: tuple[int, ...] = (32, 48, 96, 128)
    dim: int = 64
    out_stride: int = 4
    lr: float = 2e-3
    weight_decay: float = 1e-4
    temperature: float = 0.07
    anchors: int = 128
    exclusion: float = 0.05
    sigma: float = 0.06
    fresh_pairs: int = 4
    pool_size: int = 64
    max_view_angle: float = 80.0
    clutter: float = 0.5
    seed: int = 0

    def __post_init__(self) -> None:
        """Validate the values."""
        if self.steps < 1 or self.batch_size < 1 or self.anchors < 1:
            raise ValueRangeError("steps, batch_size and anchors must be positive")
        if self.input_size < 16:
            raise ValueRangeError(f"input_size must be at least 16, got {self.input_size}")
        if not 1 <= self.fresh_pairs <= self.batch_size <= self.pool_size:
            raise ValueRangeError("need 1 <= fresh_pairs <= batch_size <= pool_size")
        if not (self.lr > 0 and self.temperature > 0 and 0 <= self.exclusion < 1):
            raise ValueRangeError("lr and temperature must be positive, exclusion in [0, 1)")
        if not 0 <= self.sigma < 1:
            raise ValueRangeError(f"sigma must be in [0, 1), got {self.sigma}")
        if not 0 <= self.max_view_angle <= 180 or not 0 <= self.clutter <= 1:
            raise ValueRangeError("max_view_angle must be in [0, 180] and clutter in [0, 1]")
        object.__setattr__(self, "widths", tuple(int(w) for w in self.widths))


# --------------------------------------------------------------------------------------------
# Procedural meshes
# --------------------------------------------------------------------------------------------


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    a = axis / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


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
        noise = _value_noise(rng, float(rng.uniform(1.5, 4.0)))
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
        v = v @ _random_rotation(rng).T * (1.0 if k == 0 else rng.uniform(0.4, 0.9))
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


def _value_noise(rng: np.random.Generator, freq: float) -> Callable[[np.ndarray], np.ndarray]:
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


def _color(rng: np.random.Generator) -> np.ndarray:
    """A random RGB colour (HSV drawn to favour both vivid and greyish paints)."""
    h, s, v = rng.random(), rng.uniform(0, 1) ** 0.7, rng.uniform(0.15, 1.0)
    k = (np.array([5.0, 3.0, 1.0]) + h * 6) % 6
    return (v - v * s * np.clip(np.minimum(k, 4 - k), 0, 1)).astype(np.float32)


def _mix(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    return (a[None] * (1 - t[:, None]) + b[None] * t[:, None]).astype(np.float32)


def _random_direction(rng: np.random.Generator) -> np.ndarray:
    d = rng.normal(size=3)
    return d / np.linalg.norm(d)


def _basic_texture(rng: np.random.Generator, images: Sequence[np.ndarray]) -> SolidTexture:
    """One non-patchwork texture."""
    kind = rng.choice(["plain", "two_tone", "noise", "stripes", "checks", "dots", "image", "image"])
    c1, c2 = _color(rng), _color(rng)
    if kind == "plain":
        return lambda p, n: np.broadcast_to(c1, p.shape).copy()
    if kind == "two_tone":
        d, off = _random_direction(rng), rng.uniform(-0.2, 0.2)
        return lambda p, n: np.where(((p @ d) > off)[:, None], c1, c2).astype(np.float32)
    if kind == "noise":
        noise = _value_noise(rng, float(rng.uniform(1.5, 10.0)))
        sharp = rng.uniform(1.0, 12.0)
        c3 = _color(rng)

        def blotches(p: np.ndarray, n: np.ndarray) -> np.ndarray:
            t = 1 / (1 + np.exp(-sharp * (noise(p) - 0.5)))
            out = _mix(c1, c2, t)
            return np.where((t > 0.85)[:, None], c3, out).astype(np.float32)

        return blotches
    if kind == "stripes":
        d, freq = _random_direction(rng), rng.uniform(3.0, 25.0)
        duty, zig = rng.uniform(0.2, 0.8), rng.uniform(0, 0.15) * (rng.random() < 0.4)
        e = _random_direction(rng)
        return lambda p, n: np.where(
            ((p @ d + zig * np.abs(((p @ e) * freq * 2) % 2 - 1)) * freq % 1.0 < duty)[:, None],
            c1,
            c2,
        ).astype(np.float32)
    if kind == "checks":
        freq, R = rng.uniform(3.0, 15.0), _random_rotation(rng)
        return lambda p, n: np.where(
            (np.floor((p @ R.T) * freq).sum(axis=1) % 2 == 0)[:, None], c1, c2
        ).astype(np.float32)
    if kind == "dots":
        freq, rad, R = rng.uniform(4.0, 15.0), rng.uniform(0.15, 0.45), _random_rotation(rng)

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
    R = _random_rotation(rng)
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
    seam, seam_color = rng.uniform(0.0, 0.03), _color(rng) * rng.uniform(0.0, 0.5)

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

    bg = tuple(int(c) for c in (_color(rng) * 255))
    img = Image.new("RGB", (size, size), bg)
    draw = ImageDraw.Draw(img)
    alphabet = string.ascii_letters + string.digits + "  %-.,/"
    for _ in range(int(rng.integers(3, 9))):
        ink = tuple(int(c) for c in (_color(rng) * 255))
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


# --------------------------------------------------------------------------------------------
# Rendering pairs
# --------------------------------------------------------------------------------------------


@dataclass
class ViewPair:
    """Two crops of one procedural object and their ground-truth correspondences.

    Attributes:
        images: the crops ``(2, 3, S, S)`` in ``[0, 1]``, float32.
        coords: each crop pixel's model point ``(2, S, S, 3)`` in diameters (0 off the object).
        mask: crop pixels showing the object ``(2, S, S)`` bool.
        uv_a: object pixels of crop A ``(P, 2)`` (crop coordinates, pixel centres).
        uv_b: their matches in crop B ``(P, 2)`` (sub-pixel crop coordinates).
        points: their model points ``(P, 3)`` in diameters.
        styled: whether each view is rendered in the query's style (no colour jitter then).
    """

    images: torch.Tensor
    coords: torch.Tensor
    mask: torch.Tensor
    uv_a: torch.Tensor
    uv_b: torch.Tensor
    points: torch.Tensor
    styled: tuple[bool, bool] = (False, False)


def _background(rng: np.random.Generator, side: int, images: Sequence[np.ndarray]) -> np.ndarray:
    """A random background ``(side, side, 3)`` float32 in ``[0, 1]``."""
    kind = rng.random()
    if kind < 0.25:
        bg = np.broadcast_to(_color(rng), (side, side, 3)).copy()
    elif kind < 0.5:
        noise = _value_noise(rng, float(rng.uniform(1.0, 6.0)))
        yy, xx = np.mgrid[0:side, 0:side] / side - 0.5
        t = noise(np.stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)], axis=1))
        bg = _mix(_color(rng), _color(rng), t).reshape(side, side, 3)
    else:
        from PIL import Image

        src = images[int(rng.integers(len(images)))]
        h, w = src.shape[:2]
        c = int(rng.integers(max(8, min(h, w) // 4), min(h, w) + 1))
        y0, x0 = int(rng.integers(0, h - c + 1)), int(rng.integers(0, w - c + 1))
        patch = Image.fromarray(src[y0 : y0 + c, x0 : x0 + c]).resize((side, side))
        bg = np.asarray(patch, dtype=np.float32) / 255.0
        bg = bg * rng.uniform(0.4, 1.0) + rng.uniform(0, 0.3)
    return np.clip(bg, 0, 1).astype(np.float32)


def _blur(img: torch.Tensor, sigma: float) -> torch.Tensor:
    """Gaussian blur of ``(3, H, W)``."""
    r = max(1, math.ceil(2.5 * sigma))
    x = torch.arange(-r, r + 1, dtype=img.dtype)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    k = k / k.sum()
    out = F.conv2d(F.pad(img[:, None], (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1))
    out = F.conv2d(F.pad(out, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1))
    return out[:, 0]


def _shade(
    rng: np.random.Generator,
    out: RenderOutput,
    poses: np.ndarray,
    K: np.ndarray,
    textures: Sequence[SolidTexture],
    diameters: Sequence[float],
    background: np.ndarray,
    *,
    headlight: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Colour image ``(H, W, 3)`` and object-0 model coordinates ``(H, W, 3)`` (in diameters).

    ``headlight``: the renderer's default light (as the query's renderings are lit) instead of a
    random one.
    """
    depth = out.depth.numpy().astype(np.float64)
    inst = out.instance.numpy()
    normals = out.normals.numpy().astype(np.float64)
    H, W = depth.shape
    img = background.copy()
    coords = np.zeros((H, W, 3), np.float32)
    light = _random_direction(rng)
    light[2] = -abs(light[2]) - 0.3
    light /= np.linalg.norm(light)
    ambient, diffuse = rng.uniform(0.2, 0.7), rng.uniform(0.3, 0.8)
    spec, shine = rng.uniform(0.0, 0.6) * (rng.random() < 0.5), rng.uniform(5.0, 80.0)
    tint = np.clip(1 + rng.normal(scale=0.08, size=3), 0.7, 1.2)
    if headlight:
        default = Light()
        light, tint = default.unit_direction, np.asarray(default.color)
        ambient, diffuse, spec = default.ambient, default.diffuse, 0.0
    Kinv = np.linalg.inv(K)
    for i, (tex, diam) in enumerate(zip(textures, diameters)):
        vv, uu = np.nonzero(inst == i)
        if not len(vv):
            continue
        rays = np.stack([uu, vv, np.ones_like(uu)], axis=1) @ Kinv.T
        cam = rays * depth[vv, uu][:, None]
        R, t = poses[i, :3, :3], poses[i, :3, 3]
        model = (cam - t) @ R / diam
        n_cam = normals[vv, uu]
        albedo = tex(model, n_cam @ R)
        lam = np.clip(n_cam @ light, 0, None)
        view = -rays / np.linalg.norm(rays, axis=1, keepdims=True)
        half = light[None] + view
        half /= np.linalg.norm(half, axis=1, keepdims=True)
        hl = np.clip((n_cam * half).sum(axis=1), 0, None) ** shine
        col = albedo * (ambient + diffuse * lam)[:, None] + spec * hl[:, None]
        img[vv, uu] = np.clip(col * tint, 0, 1)
        if i == 0:
            coords[vv, uu] = model
    return img, coords


def render_pair(
    rng: np.random.Generator,
    mesh: TexturedMesh,
    texture: SolidTexture,
    images: Sequence[np.ndarray],
    *,
    input_size: int = 96,
    max_view_angle: float = 80.0,
    clutter: float = 0.5,
    span: tuple[float, float] = (32.0, 192.0),
    min_matches: int = 32,
    visibility_tolerance: float = 0.02,
    query_style: float = 0.5,
) -> ViewPair | None:
    """Render one object from two viewpoints, crop both views and match their pixels.

    Args:
        rng: the random generator.
        mesh: the object (centred on its bounding box).
        texture: its solid texture (model points in diameters).
        images: texture images for backgrounds and clutter.
        input_size: side ``S`` of the crops.
        max_view_angle: largest out-of-plane angle between the views, degrees (plus a uniform
            in-plane roll).
        clutter: probability of a second object in each view.
        span: range (log-uniform) of the object's projected diameter before the crop, pixels.
        min_matches: fewer correspondences than this give None.
        visibility_tolerance: depth agreement for a match, fraction of the diameter.
        query_style: probability that view A is rendered as
            :func:`~poseflow.features.lifting.lift_query_features` renders the query (black
            background, the default headlight, no clutter, blur or noise, the object filling
            the crop with the lifting's margin): FunFlow6D matches such renderings against
            observed crops.

    Returns:
        The :class:`ViewPair`, or None when the views share too few visible pixels.

    Example:
        >>> rng = np.random.default_rng(3)
        >>> imgs = texture_images(rng, count=2, photos=False)
        >>> pair = render_pair(rng, random_mesh(rng), random_texture(rng, imgs), imgs,
        ...                    input_size=32, span=(24.0, 32.0), min_matches=4)
        >>> pair.images.shape, pair.uv_a.shape[1]
        (torch.Size([2, 3, 32, 32]), 2)
    """
    diam = float(np.linalg.norm(mesh.extent()))
    other = random_mesh(rng, diameter=diam * rng.uniform(0.4, 1.0), max_parts=2)
    other_tex = random_texture(rng, images, patchwork=0.0)
    renderer = Renderer([mesh, other], nthreads=1)
    R_a = _random_rotation(rng)
    angle = math.radians(rng.uniform(0.0, max_view_angle))
    roll = _axis_angle(np.array([0.0, 0.0, 1.0]), rng.uniform(0, 2 * math.pi))
    R_b = roll @ _axis_angle(_random_direction(rng), angle) @ R_a
    views = []
    styled = bool(rng.random() < query_style)
    for k, R in enumerate((R_a, R_b)):
        query = styled and k == 0
        s = math.exp(rng.uniform(math.log(span[0]), math.log(span[1])))
        z = diam * rng.uniform(2.5, 8.0)
        if query:  # lift_query_features: 3 diameters away, the diameter spans the crop / 1.1
            s, z = input_size / 1.1, 3.0 * diam
        f = s * z / diam
        side = math.ceil(1.5 * s) + 8
        c = (side - 1) / 2
        K = np.array([[f, 0, c], [0, f, c], [0, 0, 1.0]])
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = [*(rng.uniform(-0.08, 0.08, size=2) * z * (not query)), z]
        T2 = np.eye(4)
        T2[:3, :3] = _random_rotation(rng)
        if rng.random() < clutter and not query:
            lateral = _random_direction(rng)[:2]
            lateral = lateral / max(np.linalg.norm(lateral), 1e-9)
            dz = rng.uniform(-0.8, 0.8) * diam
            T2[:3, 3] = [*(T[:2, 3] + lateral * rng.uniform(0.45, 0.9) * diam), z + dz]
        else:
            T2[:3, 3] = [0.0, 0.0, -10.0 * z]  # behind the camera: not rendered
        poses = np.stack([T, T2])
        out = renderer.render(poses, K, side, side, rgb=False)
        bg = np.zeros((side, side, 3), np.float32) if query else _background(rng, side, images)
        img, coords = _shade(
            rng, out, poses, K, [texture, other_tex], [diam, diam], bg, headlight=query
        )
        x = torch.from_numpy(img).permute(2, 0, 1)
        if not query:
            if rng.random() < 0.5:
                x = _blur(x, float(rng.uniform(0.3, 1.5)))
            noise = torch.from_numpy(rng.normal(size=x.shape).astype(np.float32))
            x = (x + noise * rng.uniform(0.0, 0.03)).clamp(0, 1)
        views.append((x, coords, out, K, T))
    crops, maps, masks, boxes, sources = [], [], [], [], []
    for k, (x, coords, out, K, _) in enumerate(views):
        query = styled and k == 0
        vis = out.instance == 0
        if int(vis.sum()) < 16:
            return None
        vv, uu = torch.nonzero(vis, as_tuple=True)
        cam = (
            torch.stack([uu, vv, torch.ones_like(uu)], 1).double()
            @ torch.from_numpy(np.linalg.inv(K)).T
            * out.depth[vv, uu, None].double()
        )
        margin = 1.1 if query else rng.uniform(1.0, 1.35)
        box = crop_box_around(cam[None], torch.from_numpy(K), margin=margin)
        if not query:
            seed = int(rng.integers(2**31))
            box = jitter_boxes(box, 0.08, generator=torch.Generator().manual_seed(seed))
        S = input_size
        crops.append(crop_resize(x[None], box.float(), S)[0])
        grid_v, grid_u = torch.meshgrid(
            torch.arange(vis.shape[0]), torch.arange(vis.shape[1]), indexing="ij"
        )
        planes = [torch.from_numpy(coords).permute(2, 0, 1), vis[None].float()]
        layers = torch.cat([*planes, grid_u[None], grid_v[None]]).double()
        m = crop_resize(layers[None], box, S, mode="nearest")[0]
        maps.append(m[:3].permute(1, 2, 0).float().contiguous())
        masks.append(m[3] > 0.5)
        sources.append(m[4:].permute(1, 2, 0))  # the rendered pixel each crop pixel shows
        boxes.append(box)
    # Correspondences: object pixels of crop A, projected into view B, visible there.
    ya, xa = torch.nonzero(masks[0], as_tuple=True)
    pts = maps[0][ya, xa].double()  # (P, 3) in diameters
    _, _, out_b, K_b, T_b = views[1]
    cam_b = (pts * diam) @ torch.from_numpy(T_b[:3, :3]).T + torch.from_numpy(T_b[:3, 3])
    z = cam_b[:, 2]
    uv = (cam_b @ torch.from_numpy(K_b).T)[:, :2] / z[:, None]
    side_b = out_b.depth.shape[0]
    pix = uv.round().long()
    inside = ((pix >= 0) & (pix < side_b)).all(1) & (z > 0)
    pix = pix.clamp(0, side_b - 1)
    d_b = out_b.depth[pix[:, 1], pix[:, 0]].double()
    seen = (
        inside
        & (out_b.instance[pix[:, 1], pix[:, 0]] == 0)
        & ((d_b - z).abs() <= visibility_tolerance * diam)
    )
    uv_b = pixels_to_crop(uv[None], boxes[1], input_size)[0]
    seen &= ((uv_b >= -0.5) & (uv_b <= input_size - 0.5)).all(1)
    if int(seen.sum()) < min_matches:
        return None
    # the exact crop position of each lifted point: its rendered pixel, mapped into crop A
    uv_a = pixels_to_crop(sources[0][ya, xa][None], boxes[0], input_size)[0][seen].float()
    return ViewPair(
        images=torch.stack(crops).float(),
        coords=torch.stack(maps).float(),
        mask=torch.stack(masks),
        uv_a=uv_a,
        uv_b=uv_b[seen].float(),
        points=pts[seen].float(),
        styled=(styled, False),
    )


@dataclass
class PairBatch:
    """A batch of :class:`ViewPair` with a fixed number ``P`` of correspondences each.

    Attributes:
        images_a: crops of view A ``(B, 3, S, S)``.
        images_b: crops of view B ``(B, 3, S, S)``.
        coords_a: model points of crop A's pixels ``(B, S, S, 3)`` (diameters).
        coords_b: the same for crop B ``(B, S, S, 3)``.
        mask_a: object pixels of crop A ``(B, S, S)``.
        mask_b: object pixels of crop B ``(B, S, S)``.
        uv_a: correspondences in crop A ``(B, P, 2)``.
        uv_b: the same in crop B ``(B, P, 2)``.
        points: their model points ``(B, P, 3)`` (diameters).
    """

    images_a: torch.Tensor
    images_b: torch.Tensor
    coords_a: torch.Tensor
    coords_b: torch.Tensor
    mask_a: torch.Tensor
    mask_b: torch.Tensor
    uv_a: torch.Tensor
    uv_b: torch.Tensor
    points: torch.Tensor


def _color_jitter(rng: np.random.Generator, x: torch.Tensor) -> torch.Tensor:
    """Brightness, contrast, saturation, gamma and per-channel gain of ``(3, S, S)``."""
    grey = x.mean(0, keepdim=True)
    x = grey + (x - grey) * rng.uniform(0.6, 1.4)
    x = x.mean() + (x - x.mean()) * rng.uniform(0.7, 1.3)
    gain = torch.from_numpy(rng.uniform(0.9, 1.1, size=(3, 1, 1)).astype(np.float32))
    x = (x * rng.uniform(0.7, 1.3) * gain).clamp(0, 1)
    return x ** float(rng.uniform(0.7, 1.4))


class PairGenerator:
    """Endless training pairs from procedural objects, seeded.

    Each object is rendered as ``pairs_per_object`` pairs (the mesh and texture are the slow
    part to vary); a pool of recent pairs lets a batch reuse some with new colour jitter.

    Args:
        seed: seeds everything.
        input_size: crop side ``S``.
        anchors: correspondences ``P`` per pair in a batch (drawn with replacement when fewer).
        max_view_angle: see :func:`render_pair`.
        clutter: see :func:`render_pair`.
        pool_size: pairs kept for reuse.
        pairs_per_object: pairs rendered per procedural object.
        texture_count: generated print-like texture images.
        photos: add matplotlib's sample photographs to the texture images.

    Example:
        >>> gen = PairGenerator(0, input_size=32, anchors=8, texture_count=2, photos=False)
        >>> b = gen.batch(2, fresh=2)
        >>> b.images_a.shape, b.uv_a.shape
        (torch.Size([2, 3, 32, 32]), torch.Size([2, 8, 2]))
    """

    def __init__(
        self,
        seed: int = 0,
        *,
        input_size: int = 96,
        anchors: int = 128,
        max_view_angle: float = 80.0,
        clutter: float = 0.5,
        pool_size: int = 64,
        pairs_per_object: int = 2,
        texture_count: int = 24,
        photos: bool = True,
    ) -> None:
        self.rng = np.random.default_rng(seed)
        self.input_size = int(input_size)
        self.anchors = int(anchors)
        self.max_view_angle = float(max_view_angle)
        self.clutter = float(clutter)
        self.pool_size = int(pool_size)
        self.pairs_per_object = int(pairs_per_object)
        self.images = texture_images(self.rng, count=texture_count, photos=photos)
        self.pool: list[ViewPair] = []
        self._object: tuple[TexturedMesh, SolidTexture] | None = None
        self._uses = 0

    def pair(self) -> ViewPair:
        """Render a new pair (retrying views that share too few pixels)."""
        for _ in range(100):
            if self._object is None or self._uses >= self.pairs_per_object:
                self._object = (random_mesh(self.rng), random_texture(self.rng, self.images))
                self._uses = 0
            self._uses += 1
            pair = render_pair(
                self.rng,
                *self._object,
                self.images,
                input_size=self.input_size,
                max_view_angle=self.max_view_angle,
                clutter=self.clutter,
                min_matches=min(32, self.anchors),
            )
            if pair is not None:
                return pair
            self._object = None
        raise DegenerateInputError("could not render a pair of views with enough overlap")

    def batch(self, batch_size: int, *, fresh: int | None = None) -> PairBatch:
        """A batch: ``fresh`` new pairs (default all) and the rest drawn from the pool.

        Args:
            batch_size: pairs ``B``.
            fresh: new pairs among them (at least 1 while the pool is smaller than the batch).

        Returns:
            The :class:`PairBatch`, colour-jittered per view.
        """
        fresh = batch_size if fresh is None else int(fresh)
        new = [self.pair() for _ in range(max(fresh, batch_size - len(self.pool)))]
        old = [
            self.pool[int(i)]
            for i in self.rng.choice(len(self.pool), size=batch_size - len(new), replace=False)
        ] if batch_size > len(new) else []  # fmt: skip
        self.pool = (self.pool + new)[-self.pool_size :]
        pairs = (new + old)[:batch_size]
        if self.rng.random() < 0.5:  # either view can be the anchor one
            pairs = [_swap(p) for p in pairs]
        idx = [
            torch.from_numpy(self.rng.choice(len(p.uv_a), self.anchors, len(p.uv_a) < self.anchors))
            for p in pairs
        ]
        return PairBatch(
            images_a=torch.stack([self._jitter(p, 0) for p in pairs]),
            images_b=torch.stack([self._jitter(p, 1) for p in pairs]),
            coords_a=torch.stack([p.coords[0] for p in pairs]),
            coords_b=torch.stack([p.coords[1] for p in pairs]),
            mask_a=torch.stack([p.mask[0] for p in pairs]),
            mask_b=torch.stack([p.mask[1] for p in pairs]),
            uv_a=torch.stack([p.uv_a[i] for p, i in zip(pairs, idx)]),
            uv_b=torch.stack([p.uv_b[i] for p, i in zip(pairs, idx)]),
            points=torch.stack([p.points[i] for p, i in zip(pairs, idx)]),
        )

    def _jitter(self, pair: ViewPair, view: int) -> torch.Tensor:
        """A view's crop, colour-jittered unless rendered in the query's style."""
        image = pair.images[view]
        return image if pair.styled[view] else _color_jitter(self.rng, image)


def _swap(p: ViewPair) -> ViewPair:
    return ViewPair(
        p.images.flip(0), p.coords.flip(0), p.mask.flip(0), p.uv_b, p.uv_a, p.points,
        p.styled[::-1],
    )  # fmt: skip


# --------------------------------------------------------------------------------------------
# Loss and training
# --------------------------------------------------------------------------------------------


def _cell_coords(coords: torch.Tensor, mask: torch.Tensor, h: int, w: int):
    """Model points ``(B, h·w, 3)`` and object flags ``(B, h·w)`` at the feature cell centres."""
    S = coords.shape[1]
    rows = ((torch.arange(h) + 0.5) * S / h - 0.5).round().long().clamp(0, S - 1)
    cols = ((torch.arange(w) + 0.5) * S / w - 0.5).round().long().clamp(0, S - 1)
    c = coords[:, rows][:, :, cols].reshape(len(coords), h * w, 3)
    m = mask[:, rows][:, :, cols].reshape(len(coords), h * w)
    return c, m


def _info_nce(
    feat_src: torch.Tensor,
    feat_dst: torch.Tensor,
    uv_src: torch.Tensor,
    uv_dst: torch.Tensor,
    points: torch.Tensor,
    coords_dst: torch.Tensor,
    mask_dst: torch.Tensor,
    size: int,
    temperature: float,
    exclusion: float,
    sigma: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    f_src = F.normalize(sample_features(feat_src, uv_src, (size, size)), dim=-1)  # (B, P, G)
    f_pos = F.normalize(sample_features(feat_dst, uv_dst, (size, size)), dim=-1)
    h, w = feat_dst.shape[-2:]
    cells = feat_dst.flatten(2).transpose(1, 2)  # (B, hw, G)
    pos = (f_src * f_pos).sum(-1, keepdim=True)  # (B, P, 1)
    sim = f_src @ cells.transpose(1, 2)  # (B, P, hw)
    c, m = _cell_coords(coords_dst, mask_dst, h, w)
    dist = torch.where(m[:, None], torch.cdist(points, c), torch.full_like(sim, torch.inf))
    near = dist < exclusion  # (B, P, hw)
    if sigma > 0:  # soft targets: the match and the cells around it, by surface distance
        weights = torch.cat([torch.ones_like(pos), torch.exp(-0.5 * (dist / sigma) ** 2)], -1)
        weights = weights / weights.sum(-1, keepdim=True)
        logp = torch.log_softmax(torch.cat([pos, sim], dim=-1) / temperature, dim=-1)
        loss = -(weights * logp).sum(-1).mean()
    else:
        logits = torch.cat([pos, sim.masked_fill(near, float("-inf"))], dim=-1) / temperature
        loss = -torch.log_softmax(logits, dim=-1)[..., 0].mean()
    acc = (pos[..., 0] > sim.masked_fill(near, -2.0).amax(-1)).float().mean()
    return loss, acc


def descriptor_loss(
    feat_a: torch.Tensor,
    feat_b: torch.Tensor,
    batch: PairBatch,
    *,
    temperature: float = 0.07,
    exclusion: float = 0.05,
    sigma: float = 0.06,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Symmetric InfoNCE over the ground-truth correspondences of a :class:`PairBatch`.

    For each correspondence, the source pixel's descriptor (bilinear, normalised) is scored
    against its match in the other view and every feature cell of the other view (background,
    clutter and object cells). With ``sigma > 0`` the target of the softmax is soft: the match
    and every object cell with weight ``exp(-d² / 2 sigma²)`` of its surface distance ``d`` to
    the match, so that descriptors stay similar over about ``sigma`` of the surface, the scale at
    which sparse clouds are matched (an exact-match target makes descriptors so peaked that the
    nearest of a few hundred sampled points is not the most similar). With ``sigma = 0`` the
    match is the only positive and object cells closer than ``exclusion`` are left out. Both
    directions are averaged.

    Args:
        feat_a: descriptor maps of view A ``(B, G, h, w)``.
        feat_b: descriptor maps of view B ``(B, G, h, w)``.
        batch: the batch (crops of side ``S``; the maps cover them uniformly).
        temperature: softmax temperature.
        exclusion: radius around the match without negatives (``sigma = 0``) and ignored by
            the accuracy, fraction of the diameter.
        sigma: width of the soft target, fraction of the diameter; 0: hard InfoNCE.

    Returns:
        ``(loss, accuracy)``: the mean loss and the fraction of correspondences whose match
        beats every cell farther than ``exclusion`` from it.
    """
    S = batch.images_a.shape[-1]
    la, aa = _info_nce(feat_a, feat_b, batch.uv_a, batch.uv_b, batch.points, batch.coords_b,
                       batch.mask_b, S, temperature, exclusion, sigma)  # fmt: skip
    lb, ab = _info_nce(feat_b, feat_a, batch.uv_b, batch.uv_a, batch.points, batch.coords_a,
                       batch.mask_a, S, temperature, exclusion, sigma)  # fmt: skip
    return (la + lb) / 2, (aa + ab) / 2


def train_descriptor(
    out: str | Path,
    *,
    steps: int,
    config: DescriptorTrainingConfig | None = None,
    progress: bool = True,
    save_every: int = 500,
    time_limit: float | None = None,
    log: Callable[[str], None] | None = None,
    query_pooling: str = "select",
    **changes: object,
) -> Path:
    """Train the descriptor network and write ``model.safetensors`` + ``config.json`` to ``out``.

    Args:
        out: the output folder (the files are replaced atomically, also every ``save_every``
            steps, so that an interrupted run leaves usable weights).
        steps: optimiser steps.
        config: the settings (default :class:`DescriptorTrainingConfig`); ``steps`` and
            ``changes`` override it.
        progress: show a progress bar.
        save_every: steps between intermediate saves (0: only at the end).
        time_limit: stop after this many seconds (the schedule still assumes ``steps``).
        log: called with a line of figures every 50 steps.
        query_pooling: the encoder's ``query_pooling`` written to ``config.json`` (``"mean"``
            or ``"select"``, see :mod:`poseflow.features.lifting`).
        **changes: fields of :class:`DescriptorTrainingConfig` to change.

    Returns:
        The output folder.

    Example:
        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as d:
        ...     folder = train_descriptor(d, steps=1, batch_size=1, fresh_pairs=1, pool_size=1,
        ...                               input_size=32, widths=(8, 16), dim=8, out_stride=2,
        ...                               anchors=8, progress=False)
        ...     sorted(p.name for p in folder.iterdir())
        ['config.json', 'model.safetensors']
    """
    from tqdm.auto import tqdm

    if query_pooling not in ("mean", "select"):
        raise ValueRangeError(f"query_pooling must be 'mean' or 'select', got {query_pooling!r}")
    cfg = config or DescriptorTrainingConfig()
    cfg = DescriptorTrainingConfig(**{**asdict(cfg), **changes, "steps": int(steps)})
    torch.manual_seed(cfg.seed)
    net = DescriptorNet(widths=cfg.widths, dim=cfg.dim, out_stride=cfg.out_stride)
    gen = PairGenerator(
        cfg.seed,
        input_size=cfg.input_size,
        anchors=cfg.anchors,
        max_view_angle=cfg.max_view_angle,
        clutter=cfg.clutter,
        pool_size=cfg.pool_size,
    )
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    warm = max(1, cfg.steps // 20)

    def lr_at(step: int) -> float:
        if step < warm:
            return (step + 1) / warm
        return 0.5 * (1 + math.cos(math.pi * (step - warm) / max(1, cfg.steps - warm)))

    sched = torch.optim.lr_scheduler.LambdaLR(opt, lr_at)
    start = time.monotonic()
    history: list[tuple[float, float]] = []
    done = 0

    def save(final: bool) -> None:
        recent = history[-50:]
        save_descriptor(
            net,
            out,
            input_size=cfg.input_size,
            query_pooling=query_pooling,
            training={
                **asdict(cfg),
                "steps_done": done,
                "seconds": round(time.monotonic() - start, 1),
                "final": final,
                "loss": round(float(np.mean([r[0] for r in recent])), 4) if recent else None,
                "accuracy": round(float(np.mean([r[1] for r in recent])), 4) if recent else None,
            },
        )

    net.train()
    bar = tqdm(range(cfg.steps), desc="descriptor", disable=not progress, mininterval=5.0)
    for step in bar:
        batch = gen.batch(cfg.batch_size, fresh=cfg.fresh_pairs)
        feats = net(torch.cat([batch.images_a, batch.images_b]))
        fa, fb = feats.chunk(2)
        loss, acc = descriptor_loss(
            fa, fb, batch, temperature=cfg.temperature, exclusion=cfg.exclusion, sigma=cfg.sigma
        )
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
        opt.step()
        sched.step()
        done = step + 1
        history.append((loss.item(), acc.item()))
        if done % 50 == 0 or done == cfg.steps:
            recent = history[-50:]
            line = (
                f"step {done} loss {np.mean([r[0] for r in recent]):.4f} "
                f"acc {np.mean([r[1] for r in recent]):.3f} lr {sched.get_last_lr()[0]:.2e} "
                f"{time.monotonic() - start:.0f}s"
            )
            bar.set_postfix_str(line.split(" ", 2)[2])
            if log is not None:
                log(line)
        if save_every and done % save_every == 0 and done < cfg.steps:
            save(False)
        if time_limit is not None and time.monotonic() - start > time_limit:
            break
    net.eval()
    save(True)
    return Path(out)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m poseflow.features.descriptor_training --out DIR --steps N``."""
    parser = argparse.ArgumentParser(
        prog="python -m poseflow.features.descriptor_training",
        description="Train poseflow's learned appearance descriptor on generated renders.",
    )
    parser.add_argument("--out", required=True, help="output folder (model.safetensors + config)")
    parser.add_argument("--steps", type=int, default=DescriptorTrainingConfig.steps)
    parser.add_argument("--time-limit", type=float, default=None, help="stop after SECONDS")
    parser.add_argument("--save-every", type=int, default=500)
    defaults = DescriptorTrainingConfig()
    for name in ("batch_size", "input_size", "dim", "out_stride", "anchors", "fresh_pairs",
                 "pool_size", "seed"):  # fmt: skip
        parser.add_argument(
            f"--{name.replace('_', '-')}", type=int, default=getattr(defaults, name)
        )
    for name in ("lr", "weight_decay", "temperature", "exclusion", "sigma", "max_view_angle",
                 "clutter"):  # fmt: skip
        parser.add_argument(
            f"--{name.replace('_', '-')}", type=float, default=getattr(defaults, name)
        )
    parser.add_argument(
        "--widths", type=lambda s: tuple(int(v) for v in s.split(",")), default=defaults.widths
    )
    parser.add_argument(
        "--query-pooling",
        choices=("mean", "select"),
        default="select",
        help="how the query's multi-view features are pooled at use (written to config.json)",
    )
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    torch.set_num_threads(max(1, args.threads))
    changes = {k: getattr(args, k) for k in asdict(defaults) if k != "steps" and hasattr(args, k)}
    train_descriptor(
        args.out,
        steps=args.steps,
        progress=not args.no_progress,
        save_every=args.save_every,
        time_limit=args.time_limit,
        log=lambda line: print(line, flush=True),
        query_pooling=args.query_pooling,
        **changes,
    )
    print(f"wrote {args.out}/model.safetensors and config.json", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
