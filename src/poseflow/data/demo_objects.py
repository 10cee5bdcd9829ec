"""The default demo objects, generated in code (no download), deterministic.

Three objects exercise the two cues of FunFlow6D:

1. ``labelled_box`` (obj 1): a 9 x 12 x 4 cm box whose six faces carry different printed
   artwork. The geometry has the symmetries of a box; only the print tells the faces apart.
2. ``labelled_can`` (obj 2): a can, 6.6 cm across and 11.5 cm tall, with a wrap-around label
   and printed lids. The cylinder is rotationally symmetric; the label breaks the symmetry.
3. ``bracket`` (obj 3): a plain grey, textureless L-bracket (10 x 5 x 6 cm) with two round holes,
   a gusset and a boss: geometry alone determines its pose.

Symmetries: all three objects are asymmetric once their appearance is taken into account, so by
default none gets a ``models_info.json`` symmetry entry (BOP annotates symmetries that keep the
object's look, and the print of the box and of the can breaks theirs). With
``geometric_symmetries=True`` the box gets its three 180° rotations and the can its continuous
rotation about its axis, for experiments that ignore texture.

Textures are drawn procedurally with Pillow (coloured bands, text, shapes and seeded speckle, so
that local descriptors find structure everywhere). The bracket is built on a 2 mm voxel grid and
meshed along the boundary of the occupied cells, so it has no internal faces.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from poseflow.data.objects import ObjectModel, write_bop_models
from poseflow.errors import ValueRangeError
from poseflow.render.mesh import TexturedMesh

__all__ = [
    "DEMO_OBJECT_NAMES",
    "demo_mesh",
    "demo_objects",
    "write_demo_models",
]

#: Names of the demo objects, in BOP object-id order (ids 1, 2, 3).
DEMO_OBJECT_NAMES = ("labelled_box", "labelled_can", "bracket")

_BOX_SIZE = (0.09, 0.12, 0.04)
_CAN_RADIUS, _CAN_HEIGHT, _CAN_SEGMENTS = 0.033, 0.115, 96
_VOXEL = 0.002


def demo_mesh(name: str) -> TexturedMesh:
    """The mesh of one demo object (metres, centred on its bounding box).

    Args:
        name: one of :data:`DEMO_OBJECT_NAMES`.

    Returns:
        The mesh (built once per process, then cached).

    Example:
        >>> m = demo_mesh("labelled_can")
        >>> m.has_texture, np.round(m.extent(), 3).tolist()
        (True, [0.066, 0.066, 0.115])
    """
    if name not in DEMO_OBJECT_NAMES:
        raise ValueRangeError(f"unknown demo object {name!r}; choose from {DEMO_OBJECT_NAMES}")
    return _build(name)


@functools.cache
def _build(name: str) -> TexturedMesh:
    if name == "labelled_box":
        return _labelled_box()
    if name == "labelled_can":
        return _labelled_can()
    return _bracket()


def demo_objects(
    *,
    num_points: int = 2048,
    seed: int = 0,
    names: Sequence[str] = DEMO_OBJECT_NAMES,
    geometric_symmetries: bool = False,
) -> list[ObjectModel]:
    """The demo objects as :class:`~poseflow.data.objects.ObjectModel` instances.

    Args:
        num_points: size of each query cloud.
        seed: seed of the surface sampling.
        names: which objects, in order (default all three, in BOP id order).
        geometric_symmetries: give the box and the can the symmetries of their shape
            (see the module docstring); by default the objects have none.

    Returns:
        One model per name.

    Example:
        >>> [m.name for m in demo_objects(num_points=64)]
        ['labelled_box', 'labelled_can', 'bracket']
    """
    out = []
    for name in names:
        disc: list[np.ndarray] = []
        cont: list[tuple[np.ndarray, np.ndarray]] = []
        if geometric_symmetries and name == "labelled_box":
            for axis in np.eye(3):
                S = np.eye(4)
                S[:3, :3] = 2 * np.outer(axis, axis) - np.eye(3)  # 180° about the axis
                disc.append(S)
        if geometric_symmetries and name == "labelled_can":
            cont.append((np.array([0.0, 0.0, 1.0]), np.zeros(3)))
        out.append(
            ObjectModel.from_mesh(
                demo_mesh(name),
                num_points=num_points,
                seed=seed,
                symmetries_discrete=disc,
                symmetries_continuous=cont,
                name=name,
            )
        )
    return out


def write_demo_models(
    folder: str | Path, *, num_points: int = 256, geometric_symmetries: bool = False
) -> dict[int, Path]:
    """Write the demo objects as a BOP ``models/`` folder (PLY in mm, PNG textures, info).

    Args:
        folder: destination, e.g. ``dataset_root / "models"``.
        num_points: query-cloud size used while building the models (not written).
        geometric_symmetries: see :func:`demo_objects`.

    Returns:
        ``{obj_id: ply_path}`` with ids 1, 2, 3 in :data:`DEMO_OBJECT_NAMES` order.
    """
    models = demo_objects(num_points=num_points, geometric_symmetries=geometric_symmetries)
    return write_bop_models(folder, models)


# ---------------------------------------------------------------------------------------------
# Textures


def _font(size: int) -> Any:
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except (TypeError, OSError):  # Pillow without FreeType: the fixed bitmap font
        return ImageFont.load_default()


def _speckle(draw: Any, rng: np.random.Generator, box: tuple[int, int, int, int], n: int) -> None:
    x0, y0, x1, y1 = box
    for _ in range(n):
        x, y = rng.uniform(x0, x1), rng.uniform(y0, y1)
        r = rng.uniform(2, 9)
        col = tuple(int(c) for c in rng.integers(0, 256, 3))
        if rng.random() < 0.5:
            draw.ellipse((x - r, y - r, x + r, y + r), fill=col)
        else:
            draw.rectangle((x - r, y - r * 0.6, x + r, y + r * 0.6), fill=col)


def _panel(
    draw: Any,
    rng: np.random.Generator,
    box: tuple[int, int, int, int],
    base: tuple[int, int, int],
    accent: tuple[int, int, int],
    text: str,
    motif: int,
) -> None:
    """Draw one asymmetric panel of artwork into ``box``."""
    x0, y0, x1, y1 = box
    w, h = x1 - x0, y1 - y0
    draw.rectangle(box, fill=base)
    # diagonal bands in the upper-left corner only
    for k in range(6):
        off = k * w // 10
        draw.polygon(
            [(x0 + off, y0), (x0 + off + w // 20, y0), (x0, y0 + off + w // 20), (x0, y0 + off)],
            fill=accent,
        )
    # a stripe near the bottom with tick marks of growing height (reads left to right)
    sy = y0 + int(0.78 * h)
    draw.rectangle((x0, sy, x1, sy + h // 12), fill=accent)
    for k in range(12):
        tx = x0 + int((k + 0.5) * w / 12)
        draw.rectangle((tx, sy - 2 - 3 * k, tx + 3, sy), fill=(20, 20, 20))
    # motif: an off-centre shape that differs per panel
    cx, cy, r = x0 + int(0.68 * w), y0 + int(0.42 * h), int(0.16 * min(w, h))
    if motif == 0:
        draw.polygon(
            [(cx - r, cy + r), (cx + r, cy + r), (cx - r // 2, cy - r)], fill=(250, 250, 250)
        )
    elif motif == 1:
        draw.ellipse((cx - r, cy - r, cx + r, cy + r), fill=(250, 250, 250))
        draw.ellipse((cx - r // 3, cy - r, cx + r, cy), fill=accent)
    elif motif == 2:
        draw.rectangle((cx - r, cy - r // 2, cx + r, cy + r // 2), fill=(250, 250, 250))
        draw.polygon([(cx + r, cy - r), (cx + 2 * r, cy), (cx + r, cy + r)], fill=(250, 250, 250))
    else:
        for k in range(4):
            draw.ellipse(
                (cx - r + k * r // 2, cy - r + k * r // 3, cx + k * r // 2, cy + k * r // 3),
                outline=(250, 250, 250),
                width=5,
            )
    _speckle(draw, rng, (x0, y0 + int(0.55 * h), x0 + int(0.55 * w), y0 + int(0.75 * h)), 40)
    font = _font(max(12, h // 7))
    draw.text((x0 + w // 12, y0 + int(0.30 * h)), text, fill=(15, 15, 15), font=font)
    small = _font(max(10, h // 16))
    draw.text(
        (x0 + w // 12, y0 + int(0.88 * h)), f"{text.lower()} / {motif}", fill=base, font=small
    )


_PALETTE = [
    ((214, 48, 49), (253, 203, 110)),
    ((9, 132, 227), (255, 234, 167)),
    ((0, 184, 148), (45, 52, 54)),
    ((108, 92, 231), (250, 177, 160)),
    ((225, 112, 85), (116, 185, 255)),
    ((253, 203, 110), (214, 48, 49)),
]


def _box_texture() -> np.ndarray:
    from PIL import Image, ImageDraw

    cw, ch = 340, 384
    img = Image.new("RGB", (3 * cw, 2 * ch), (255, 255, 255))
    draw = ImageDraw.Draw(img)
    rng = np.random.default_rng(1)
    words = ["POSEFLOW", "BACK", "LEFT", "RIGHT", "TOP", "BASE"]
    for face in range(6):
        i, j = face % 3, face // 3
        base, accent = _PALETTE[face]
        box = (i * cw + 4, j * ch + 4, (i + 1) * cw - 4, (j + 1) * ch - 4)
        _panel(draw, rng, box, base, accent, words[face], face % 4)
    return np.asarray(img, dtype=np.uint8).copy()


def _can_texture() -> np.ndarray:
    from PIL import Image, ImageDraw

    W, H = 1024, 1024
    label_h = 768  # rows 0..767: the wrap-around label; rows 768..1023: the two lids
    img = Image.new("RGB", (W, H), (200, 200, 205))
    draw = ImageDraw.Draw(img)
    rng = np.random.default_rng(2)
    draw.rectangle((0, 0, W, label_h), fill=(180, 20, 40))
    for k, col in enumerate([(250, 240, 220), (30, 30, 30), (250, 200, 40)]):
        y = 60 + 90 * k
        draw.rectangle((0, y, W, y + 24 + 8 * k), fill=col)
    # a wave whose amplitude grows around the can (no rotational repeat)
    pts = [(x, 420 + (20 + x / 12) * math.sin(x / 45)) for x in range(0, W, 4)]
    draw.line(pts, fill=(255, 255, 255), width=10)
    draw.text((60, 300), "POSEFLOW", fill=(255, 255, 255), font=_font(110))
    draw.text((620, 520), "COLA", fill=(250, 200, 40), font=_font(90))
    draw.ellipse((700, 300, 840, 440), fill=(250, 200, 40))
    draw.polygon([(300, 700), (420, 560), (470, 700)], fill=(255, 255, 255))
    _speckle(draw, rng, (0, 560, W, 740), 160)
    for k in range(30):  # a barcode on one side only
        x = 80 + k * 9 + (k % 3) * 2
        draw.rectangle((x, 570, x + 2 + (k * 7) % 5, 690), fill=(0, 0, 0))
    # lids: top lid in the first 256x256 cell, bottom lid in the second
    for cell, (ring, mark) in enumerate(
        [((160, 160, 170), (60, 60, 70)), ((140, 140, 150), (200, 30, 30))]
    ):
        x0, y0 = 256 * cell, label_h
        draw.rectangle((x0, y0, x0 + 255, y0 + 255), fill=ring)
        draw.ellipse((x0 + 20, y0 + 20, x0 + 235, y0 + 235), outline=mark, width=8)
        if cell == 0:  # a pull tab off-centre
            draw.rounded_rectangle((x0 + 110, y0 + 40, x0 + 150, y0 + 120), radius=12, fill=mark)
            draw.ellipse((x0 + 118, y0 + 130, x0 + 142, y0 + 154), fill=mark)
        else:
            draw.text((x0 + 60, y0 + 100), "LOT 42", fill=mark, font=_font(36))
        _speckle(draw, rng, (x0 + 60, y0 + 160, x0 + 200, y0 + 220), 25)
    return np.asarray(img, dtype=np.uint8).copy()


# ---------------------------------------------------------------------------------------------
# Geometry


def _textured_mesh(
    verts: list[Any], tris: list[Any], normals: list[Any], uvs: list[Any], texture: np.ndarray
) -> TexturedMesh:
    """The mesh of what a builder collects: vertices, triangles, normals and UVs ``(T, 3, 2)``."""
    return TexturedMesh(
        np.asarray(verts),
        np.asarray(tris),
        vertex_normals=np.asarray(normals),
        triangle_uvs=np.asarray(uvs),
        texture=texture,
    )


def _labelled_box() -> TexturedMesh:
    a, b, c = (s / 2 for s in _BOX_SIZE)
    ex, ey, ez = np.eye(3)
    # (outward normal, right, up, half-width, half-height, centre distance): right x up = normal
    faces = [
        (ez, ex, ey, a, b, c),
        (-ez, -ex, ey, a, b, c),
        (ex, -ez, ey, c, b, a),
        (-ex, ez, ey, c, b, a),
        (ey, ex, -ez, a, c, b),
        (-ey, ex, ez, a, c, b),
    ]
    verts, tris, uvs, normals = [], [], [], []
    cu, cv, inset = 1 / 3, 1 / 2, 0.01
    for k, (n, r, up, hw, hh, d) in enumerate(faces):
        i, j = k % 3, k // 3
        u0, u1 = i * cu + inset * cu, (i + 1) * cu - inset * cu
        v1, v0 = 1 - j * cv - inset * cv, 1 - (j + 1) * cv + inset * cv  # row j from the top
        centre = n * d
        corners = [
            centre - r * hw - up * hh,
            centre + r * hw - up * hh,
            centre + r * hw + up * hh,
            centre - r * hw + up * hh,
        ]
        corner_uv = [(u0, v0), (u1, v0), (u1, v1), (u0, v1)]
        base = len(verts)
        verts += corners
        normals += [n] * 4
        for t in ((0, 1, 2), (0, 2, 3)):
            tris.append([base + t[0], base + t[1], base + t[2]])
            uvs.append([corner_uv[t[0]], corner_uv[t[1]], corner_uv[t[2]]])
    return _textured_mesh(verts, tris, normals, uvs, _box_texture())


def _labelled_can() -> TexturedMesh:
    r, h, n = _CAN_RADIUS, _CAN_HEIGHT, _CAN_SEGMENTS
    theta = np.linspace(0.0, 2 * np.pi, n + 1)
    cos, sin = np.cos(theta), np.sin(theta)
    verts, normals, tris, uvs = [], [], [], []
    v_lo, v_hi = 0.25 + 0.002, 1.0 - 0.002  # the label occupies the upper 3/4 of the texture
    # side: columns k = 0..n (the seam is duplicated so u runs 0..1)
    for z in (-h / 2, h / 2):
        for k in range(n + 1):
            verts.append((r * cos[k], r * sin[k], z))
            normals.append((cos[k], sin[k], 0.0))
    for k in range(n):
        b0, b1, t0, t1 = k, k + 1, n + 1 + k, n + 2 + k
        u0, u1 = k / n, (k + 1) / n
        tris += [[b0, b1, t1], [b0, t1, t0]]
        uvs += [[(u0, v_lo), (u1, v_lo), (u1, v_hi)], [(u0, v_lo), (u1, v_hi), (u0, v_hi)]]
    # lids: top in texture cell [0, 0.25] x [0, 0.25], bottom in [0.25, 0.5] x [0, 0.25]
    for z, sign, cu in ((h / 2, 1.0, 0.125), (-h / 2, -1.0, 0.375)):
        centre = len(verts)
        verts.append((0.0, 0.0, z))
        normals.append((0.0, 0.0, sign))
        ring = len(verts)
        for k in range(n):
            verts.append((r * cos[k], r * sin[k], z))
            normals.append((0.0, 0.0, sign))
        cuv = (cu, 0.125)
        rad = 0.115
        for k in range(n):
            a, b = ring + k, ring + (k + 1) % n
            ua = (cu + sign * rad * cos[k], 0.125 + rad * sin[k])
            ub = (cu + sign * rad * cos[k + 1], 0.125 + rad * sin[k + 1])
            if sign > 0:
                tris.append([centre, a, b])
                uvs.append([cuv, ua, ub])
            else:
                tris.append([centre, b, a])
                uvs.append([cuv, ub, ua])
    return _textured_mesh(verts, tris, normals, uvs, _can_texture())


def _bracket_occupancy() -> np.ndarray:
    """Occupancy of the bracket on a 2 mm grid, indexed ``[x, y, z]``."""
    nx, ny, nz = 50, 25, 30  # 100 x 50 x 60 mm
    c = (np.indices((nx, ny, nz)) + 0.5) * 2.0  # cell centres in mm
    x, y, z = c
    occ = (z < 8) | (x < 8)  # base plate and upright plate: the L
    occ &= ~((x - 70) ** 2 + (y - 32) ** 2 < 8.0**2)  # round hole through the base
    occ &= ~((z - 42) ** 2 + (y - 16) ** 2 < 6.0**2)  # smaller hole through the upright
    occ |= (y >= 38) & (y < 44) & (x >= 8) & (z >= 8) & ((x - 8) + (z - 8) <= 30)  # gusset
    occ |= (x >= 80) & (x < 94) & (y >= 4) & (y < 14) & (z >= 8) & (z < 18)  # boss
    return occ


def _bracket() -> TexturedMesh:
    occ = _bracket_occupancy()
    padded = np.pad(occ, 1)
    corners_uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float64)
    verts, tris, normals = [], [], []
    count = 0
    for axis in range(3):
        u_ax, v_ax = [a for a in range(3) if a != axis]
        for sign in (1, -1):
            # a face where an occupied cell's neighbour along +-axis is empty
            face = padded & ~np.roll(padded, -sign, axis=axis)
            cells = np.argwhere(face).astype(np.float64) - 1.0  # (K, 3) unpadded cell indices
            K = len(cells)
            quad = np.repeat(cells[:, None, :], 4, axis=1)  # (K, 4, 3) lower cell corners
            quad[:, :, axis] += 1.0 if sign > 0 else 0.0
            quad[:, :, u_ax] += corners_uv[:, 0]
            quad[:, :, v_ax] += corners_uv[:, 1]
            n = np.zeros(3)
            n[axis] = sign
            e_u, e_v = np.eye(3)[u_ax], np.eye(3)[v_ax]
            order = [[0, 1, 2], [0, 2, 3]]
            if np.dot(np.cross(e_u, e_v), n) < 0:
                order = [[0, 2, 1], [0, 3, 2]]
            base = count + 4 * np.arange(K)[:, None, None]
            tris.append((base + np.asarray(order)[None]).reshape(-1, 3))
            verts.append(quad.reshape(-1, 3) * _VOXEL)
            normals.append(np.broadcast_to(n, (4 * K, 3)))
            count += 4 * K
    v = np.concatenate(verts)
    v -= (v.max(axis=0) + v.min(axis=0)) / 2
    grey = np.full_like(v, 0.58)
    grey[:, 2] = 0.6
    return TexturedMesh(
        v, np.concatenate(tris), vertex_colors=grey, vertex_normals=np.concatenate(normals)
    )
