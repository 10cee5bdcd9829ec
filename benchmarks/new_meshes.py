"""More sets of new objects for ``benchmarks/unseen.py``: meshes nobody tuned poseflow for.

Writes ``OUT/models/obj_00000{1..5}.ply`` (millimetres, vertex colours) and ``models_info.json``
(diameter, bounding box, declared continuous symmetries), then a test split of them rendered by
``poseflow synth`` with its own seed, so that ``OUT`` is a BOP folder the recipe can run on.

``--set 2`` (the default):

1. a torus (80 mm across) with a printed band pattern;
2. a grey arrow (cylinder and cone), declared continuously symmetric about its axis;
3. a printed cylinder (56 mm across, 95 mm tall);
4. a grey L-block of two bars;
5. a printed box (85 x 52 x 30 mm).

``--set 3``, the kinds of object a user brings, each new here:

1. a plain white bowl (130 mm across), declared continuously symmetric about its axis;
2. a grey machined bracket: a base plate, an upright plate and an off-centre boss;
3. a textured pebble: a sphere displaced by smooth noise, painted with a patchwork;
4. a printed hexagonal prism (a pencil box): its six faces alike but for the print;
5. a printed can (66 mm across, 120 mm tall) with a grey lid: a label of text lines, a
   barcode and a picture, the only thing that decides its turn about the axis.

Run::

    python benchmarks/new_meshes.py runs/meshset2
    python benchmarks/unseen.py runs/meshset2 --seeds 0 1 2

The test images come from the same renderer as the recipe's training images (devbench's come
from another one), so such a set checks new geometry and texture, not a renderer gap;
``benchmarks/other_renderer.py`` renders a test split of the same meshes that shares neither the
renderer, the sensor model nor the layout with ``poseflow synth``.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path

import numpy as np

from poseflow.cli import main as poseflow
from poseflow.data.synthetic import procedural_texture
from poseflow.render.backend import import_open3d

UV = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


def _paint(mesh, uv: UV, seed: int):  # type: ignore[no-untyped-def]
    """Vertex colours from a procedural texture at the vertices' ``uv``, both wrapped to [0, 1)."""
    texture = procedural_texture(seed, 256).astype(np.float64)
    texture = texture / 255.0 if texture.max() > 1 else texture

    def wrapped(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u, w = uv(v)
        return u, w % 1.0

    return _paint_image(mesh, texture, wrapped)


def _grey(mesh, level: float):  # type: ignore[no-untyped-def]
    o3d = import_open3d("the new meshes")
    colours = np.full((len(mesh.vertices), 3), level)
    mesh.vertex_colors = o3d.utility.Vector3dVector(colours)
    return mesh


def _fine(mesh, triangles: int = 20_000):  # type: ignore[no-untyped-def]
    """Midpoint-subdivided until it has ``triangles`` faces, so colours vary across faces."""
    while len(mesh.triangles) < triangles:
        mesh = mesh.subdivide_midpoint(1)
    return mesh


def _around_z(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.arctan2(v[:, 1], v[:, 0]) / (2 * np.pi), v[:, 2] / 120.0


def _planar(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return (v[:, 0] + 0.7 * v[:, 2]) / 90.0, (v[:, 1] + 0.5 * v[:, 2]) / 70.0


def build_meshes() -> dict[int, tuple[object, dict]]:
    """The second set: ``{obj_id: (Open3D mesh in mm, extra models_info fields)}``."""
    o3d = import_open3d("the new meshes")
    T = o3d.geometry.TriangleMesh
    torus = T.create_torus(
        torus_radius=40, tube_radius=13, radial_resolution=60, tubular_resolution=30
    )
    arrow = T.create_arrow(
        cylinder_radius=9, cone_radius=16, cylinder_height=70, cone_height=32, resolution=40
    )
    arrow.translate(-arrow.get_center() * np.array([0.0, 0.0, 1.0]))  # the axis stays z
    cylinder = T.create_cylinder(radius=28, height=95, resolution=60, split=12)
    block = T.create_box(70, 22, 22) + T.create_box(22, 22, 55).translate([0, 0, 22])
    block.translate(-block.get_center())
    box = T.create_box(85, 52, 30)
    box.translate(-box.get_center())
    band = lambda v: (np.arctan2(v[:, 1], v[:, 0]) / (2 * np.pi), v[:, 2] / 40.0 + 0.5)  # noqa: E731
    about_z = {"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]}
    return {
        1: (_paint(_fine(torus), band, 11), {}),
        2: (_grey(_fine(arrow), 0.55), about_z),
        3: (_paint(_fine(cylinder), _around_z, 23), {}),
        4: (_grey(_fine(block), 0.5), {}),
        5: (_paint(_fine(box), _planar, 37), {}),
    }


def _label(seed: int, width: int = 1024, height: int = 384) -> np.ndarray:
    """A printed label ``(height, width, 3)`` in [0, 1]: text lines, a barcode and a picture."""
    from PIL import Image, ImageDraw, ImageFont

    rng = np.random.default_rng(seed)
    img = Image.new("RGB", (width, height), tuple(int(c) for c in rng.integers(150, 256, 3)))
    draw = ImageDraw.Draw(img)
    ink = tuple(int(c) for c in rng.integers(0, 90, 3))
    words = ["FRESH", "NET WT", "ORGANIC", "SINCE 1987", "BEST BEFORE", "TOMATO", "SOUP", "450 g"]
    for row in range(5):
        text = " ".join(rng.choice(words, 3))
        size = 56 if row == 0 else 30
        draw.text((30, 20 + row * 70), text, fill=ink, font=ImageFont.load_default(size=size))
    for k in range(40):  # a barcode
        x = 560 + k * 6
        if rng.random() < 0.6:
            draw.rectangle((x, 230, x + int(rng.integers(2, 5)), 350), fill=(0, 0, 0))
    picture = procedural_texture(seed + 1, 256)[:, :, :3]  # a picture beside the text
    img.paste(Image.fromarray(picture).resize((220, 300)), (790, 40))
    return np.asarray(img, np.float64) / 255.0


def _paint_image(mesh, image: np.ndarray, uv: UV, where=None):  # type: ignore[no-untyped-def]
    """Vertex colours from ``image`` ``(h, w, 3)`` in [0, 1] where ``where`` holds (all: None).

    ``uv`` maps vertices to ``(u, r)``: ``u`` across the image (wrapped to [0, 1)), ``r`` down
    its rows from the top (clipped to [0, 1]).
    """
    o3d = import_open3d("the new meshes")
    v = np.asarray(mesh.vertices)
    u, r = uv(v)
    h, wd = image.shape[:2]
    iu = np.clip((u % 1.0) * (wd - 1), 0, wd - 1).astype(int)
    iv = np.clip(np.clip(r, 0, 1) * (h - 1), 0, h - 1).astype(int)
    colours = np.asarray(mesh.vertex_colors) if mesh.has_vertex_colors() else np.zeros_like(v)
    keep = np.ones(len(v), bool) if where is None else where(v)
    colours[keep] = image[iv[keep], iu[keep]]
    mesh.vertex_colors = o3d.utility.Vector3dVector(colours)
    return mesh


def _from_trimesh(mesh):  # type: ignore[no-untyped-def]
    o3d = import_open3d("the new meshes")
    return o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.asarray(mesh.vertices, np.float64)),
        o3d.utility.Vector3iVector(np.asarray(mesh.faces, np.int32)),
    )


def build_meshes_3() -> dict[int, tuple[object, dict]]:
    """The third set: ``{obj_id: (Open3D mesh in mm, extra models_info fields)}``."""
    import trimesh

    o3d = import_open3d("the new meshes")
    T = o3d.geometry.TriangleMesh
    # a bowl: the profile (radius, height) of its wall revolved about z, foot to rim and back
    outer = [(0, 0), (30, 0), (34, 6), (52, 22), (62, 44), (65, 58)]
    inner = [(60, 58), (57, 44), (47, 24), (28, 12), (0, 12)]
    bowl = _from_trimesh(trimesh.creation.revolve(np.array(outer + inner, float), sections=96))
    bowl.translate(-bowl.get_center() * np.array([0.0, 0.0, 1.0]))
    base = T.create_box(80, 50, 12)
    upright = T.create_box(12, 50, 45).translate([68, 0, 12])
    boss = T.create_cylinder(radius=9, height=20, resolution=40).translate([25, 14, 22])
    bracket = base + upright + boss
    bracket.translate(-bracket.get_center())
    rng = np.random.default_rng(5)
    pebble = T.create_sphere(radius=40, resolution=60)
    v = np.asarray(pebble.vertices)
    k, phase = rng.normal(size=(5, 3)) / 25, rng.uniform(0, 2 * np.pi, 5)
    bump = sum(np.sin(v @ k[i] + phase[i]) for i in range(5)) / 5
    scale = np.array([1.25, 0.95, 0.75]) * (1 + 0.35 * bump)[:, None]
    pebble.vertices = o3d.utility.Vector3dVector(v * scale)
    prism = T.create_cylinder(radius=24, height=150, resolution=6, split=30)
    can = T.create_cylinder(radius=33, height=120, resolution=120, split=60)
    about_z = {"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]}
    on_side = lambda v: np.abs(v[:, 2]) < 57.0  # noqa: E731  the can's label, not its lid
    lid = lambda v: np.ones(len(v), bool)  # noqa: E731

    def around(height: float) -> UV:
        """A label around z, ``height`` mm tall, its top row at ``z = height / 2``."""
        return lambda v: (
            np.arctan2(v[:, 1], v[:, 0]) / (2 * np.pi),
            1 - np.clip(v[:, 2] / height + 0.5, 0, 1),
        )

    return {
        1: (_grey(_fine(bowl), 0.92), about_z),
        2: (_grey(_fine(bracket), 0.45), {}),
        3: (_paint(_fine(pebble), lambda v: (v[:, 0] / 70, v[:, 1] / 55 + v[:, 2] / 90), 51), {}),
        4: (_paint_image(_fine(prism, 60_000), _label(61, 1024, 256), around(150), lid), {}),
        5: (_paint_image(_grey(_fine(can, 80_000), 0.6), _label(71), around(114), on_side), {}),
    }


SETS = {2: build_meshes, 3: build_meshes_3}


def write_models(folder: Path, which: int = 2) -> dict[str, dict]:
    """Write set ``which``'s meshes and ``models_info.json`` to ``folder``; returns the info."""
    o3d = import_open3d("the new meshes")
    folder.mkdir(parents=True, exist_ok=True)
    info: dict[str, dict] = {}
    for obj_id, (mesh, extra) in SETS[which]().items():
        mesh.compute_vertex_normals()
        o3d.io.write_triangle_mesh(str(folder / f"obj_{obj_id:06d}.ply"), mesh)
        v = np.asarray(mesh.vertices)
        hull = np.asarray(mesh.compute_convex_hull()[0].vertices)
        diameter = float(np.linalg.norm(hull[:, None] - hull[None], axis=-1).max())
        lo, hi = v.min(0), v.max(0)
        info[str(obj_id)] = {
            "diameter": diameter,
            **{f"min_{a}": float(lo[i]) for i, a in enumerate("xyz")},
            **{f"size_{a}": float(hi[i] - lo[i]) for i, a in enumerate("xyz")},
            **extra,
        }
    (folder / "models_info.json").write_text(json.dumps(info, indent=1))
    return info


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", help="the BOP folder to write (models/ and test/)")
    parser.add_argument("--test", type=int, default=24, help="test images")
    parser.add_argument("--seed", type=int, default=42, help="seed of the test images")
    parser.add_argument("--set", type=int, choices=sorted(SETS), default=2, help="which meshes")
    args = parser.parse_args()
    out = Path(args.out)
    meshes = out.parent / f"{out.name}_meshes"
    info = write_models(meshes, args.set)
    print({k: round(v["diameter"], 1) for k, v in info.items()}, "mm diameters")
    code = poseflow([
        "synth", str(out), "--objects", str(meshes), "--mesh-scale", "0.001", "--train", "0",
        "--test", str(args.test), "--seed", str(args.seed), "--no-progress",
    ])  # fmt: skip
    if code:
        raise SystemExit(code)


if __name__ == "__main__":
    main()
