"""A second set of new objects for ``benchmarks/unseen.py``: five meshes nobody tuned poseflow for.

Writes ``OUT/models/obj_00000{1..5}.ply`` (millimetres, vertex colours) and ``models_info.json``
(diameter, bounding box, the arrow's continuous symmetry), then a test split of them rendered by
``poseflow synth`` with its own seed, so that ``OUT`` is a BOP folder the recipe can run on:

1. a torus (80 mm across) with a printed band pattern;
2. a grey arrow (cylinder and cone), declared continuously symmetric about its axis;
3. a printed cylinder (56 mm across, 95 mm tall);
4. a grey L-block of two bars;
5. a printed box (85 x 52 x 30 mm).

Run::

    python benchmarks/new_meshes.py runs/meshset2
    python benchmarks/unseen.py runs/meshset2 --seeds 0 1 2

The test images come from the same renderer as the recipe's training images (devbench's come
from another one), so this set checks new geometry and texture, not a renderer gap.
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
    """Vertex colours from a procedural texture at the vertices' ``uv`` (wrapped to [0, 1))."""
    o3d = import_open3d("the new meshes")
    texture = procedural_texture(seed, 256).astype(np.float64)
    texture = texture / 255.0 if texture.max() > 1 else texture
    u, v = uv(np.asarray(mesh.vertices))
    iu = np.clip((u % 1.0) * 255, 0, 255).astype(int)
    iv = np.clip((v % 1.0) * 255, 0, 255).astype(int)
    mesh.vertex_colors = o3d.utility.Vector3dVector(texture[iv, iu, :3])
    return mesh


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
    """``{obj_id: (Open3D mesh in mm, extra models_info fields)}``."""
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


def write_models(folder: Path) -> dict[str, dict]:
    """Write the meshes and ``models_info.json`` to ``folder``; returns the info."""
    o3d = import_open3d("the new meshes")
    folder.mkdir(parents=True, exist_ok=True)
    info: dict[str, dict] = {}
    for obj_id, (mesh, extra) in build_meshes().items():
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
    args = parser.parse_args()
    out = Path(args.out)
    meshes = out.parent / f"{out.name}_meshes"
    info = write_models(meshes)
    print({k: round(v["diameter"], 1) for k, v in info.items()}, "mm diameters")
    code = poseflow([
        "synth", str(out), "--objects", str(meshes), "--mesh-scale", "0.001", "--train", "0",
        "--test", str(args.test), "--seed", str(args.seed), "--no-progress",
    ])  # fmt: skip
    if code:
        raise SystemExit(code)


if __name__ == "__main__":
    main()
