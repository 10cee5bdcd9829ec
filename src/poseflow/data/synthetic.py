"""Synthetic cluttered RGBD scenes written as a BOP dataset (train and test splits).

Each *scene* is one random layout seen from several viewpoints (as the scenes of BOP are): the
objects rest on a textured support plane (a random face down with a random yaw, or, with
probability ``tilt_prob``, a random orientation lowered until it touches the plane), packed
tightly enough to occlude each other, among random distractor boxes and cylinders. Each *image*
draws a camera on a viewpoint sphere around the layout (random azimuth, elevation and distance,
looking at the cluster with a small in-plane roll), a random light, a random background, and
corrupts the rendered depth with a sensor noise model (:class:`DepthNoise`).

Everything is drawn from ``numpy.random.default_rng([seed, split, scene, image])``, so a dataset is
reproducible from its seed, and a scene does not depend on how many scenes came before it.

Output (``out_dir``)::

    camera.json                    intrinsics shared by all images (BOP layout)
    models/, models_eval/          obj_XXXXXX.ply (mm) [+ .png texture], models_info.json
    train/XXXXXX/, test/XXXXXX/    rgb/, depth/, mask/, mask_visib/, scene_camera.json,
                                   scene_gt.json, scene_gt_info.json
    test_targets_bop19.json        instances of the test split with visib_fract >= 0.1
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image
from scipy import ndimage

from poseflow._units import check_diameter_units
from poseflow.data._arrays import as_numpy
from poseflow.data.bop import (
    BOPWriter,
    ModelInfo,
    TestTarget,
    read_models_info,
    write_models_info,
    write_test_targets,
)
from poseflow.errors import OutputExistsError, ShapeError, ValueRangeError
from poseflow.geometry.pointcloud import cloud_diameter
from poseflow.geometry.se3 import quaternion_to_rotation
from poseflow.render.mesh import TexturedMesh, as_textured_mesh
from poseflow.render.raycast import Light, Renderer

__all__ = ["DepthNoise", "SyntheticObject", "generate_dataset", "procedural_texture"]

#: Focal length in pixels of a 640-pixel-wide image (Kinect v1 / Primesense, as in LM and LM-O).
KINECT_FOCAL_640 = 572.4

_SPLIT_CODES = {"train": 0, "test": 1}


@dataclass(frozen=True)
class DepthNoise:
    """Depth-sensor corruption: depth- and angle-dependent Gaussian noise plus missing pixels.

    The noise follows the axial model measured for the Kinect by Nguyen, Izadi and Lovell (2012),
    ``sigma(z, a) = sigma_base + sigma_quadratic (z - reference_depth)^2
    + sigma_angle / sqrt(z) * a^2 / (pi/2 - a)^2`` metres, with ``a`` the angle between the
    surface normal and the viewing ray. Measurements are removed (depth 0) at grazing angles
    (probability rising linearly from 0 at ``grazing_start_deg`` to 1 at ``grazing_end_deg``), in
    a band of ``edge_width`` pixels along depth discontinuities larger than ``edge_jump`` metres or
    against the background (with probability ``edge_dropout``), and anywhere with probability
    ``random_dropout``.

    Example:
        >>> noise = DepthNoise()
        >>> depth = torch.full((20, 20), 0.8)
        >>> normals = torch.zeros(20, 20, 3); normals[..., 2] = -1.0
        >>> K = torch.tensor([[50.0, 0, 9.5], [0, 50.0, 9.5], [0, 0, 1]])
        >>> noisy = noise.apply(depth, normals, K, rng=0)
        >>> bool(((noisy - depth).abs() < 0.02).all()), noisy.dtype
        (True, torch.float32)
    """

    sigma_base: float = 0.0012
    sigma_quadratic: float = 0.0019
    reference_depth: float = 0.4
    sigma_angle: float = 0.0001
    grazing_start_deg: float = 70.0
    grazing_end_deg: float = 85.0
    edge_jump: float = 0.01
    edge_width: int = 1
    edge_dropout: float = 0.8
    random_dropout: float = 0.001

    def __post_init__(self) -> None:
        for name in ("sigma_base", "sigma_quadratic", "sigma_angle", "edge_jump"):
            if not getattr(self, name) >= 0:
                raise ValueRangeError(f"{name} must be non-negative, got {getattr(self, name)}")
        for name in ("edge_dropout", "random_dropout"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueRangeError(f"{name} must lie in [0, 1], got {getattr(self, name)}")
        if not 0 <= self.grazing_start_deg < self.grazing_end_deg <= 90:
            raise ValueRangeError("need 0 <= grazing_start_deg < grazing_end_deg <= 90")
        if self.edge_width < 0:
            raise ValueRangeError(f"edge_width must be >= 0, got {self.edge_width}")

    def sigma(self, depth: np.ndarray, angle: np.ndarray) -> np.ndarray:
        """Standard deviation in metres for depths and incidence angles (radians), numpy."""
        a = np.minimum(angle, np.deg2rad(89.0))
        z = np.maximum(depth, 1e-6)
        return (
            self.sigma_base
            + self.sigma_quadratic * (z - self.reference_depth) ** 2
            + self.sigma_angle / np.sqrt(z) * a**2 / (np.pi / 2 - a) ** 2
        )

    def apply(
        self,
        depth: torch.Tensor | np.ndarray,
        normals: torch.Tensor | np.ndarray,
        K: torch.Tensor | np.ndarray,
        *,
        rng: np.random.Generator | int | None = None,
    ) -> torch.Tensor:
        """Corrupt a clean depth map.

        Args:
            depth: clean z-depth ``(H, W)`` in metres, 0 where nothing was hit.
            normals: camera-frame unit normals ``(H, W, 3)`` (the renderer's ``normals``).
            K: intrinsics ``(3, 3)``.
            rng: numpy generator or seed.

        Returns:
            Noisy depth ``(H, W)`` float32 in metres, 0 where missing.
        """
        d = as_numpy(depth, np.float64)
        n = as_numpy(normals, np.float64)
        if d.ndim != 2 or n.shape != (*d.shape, 3):
            raise ShapeError(f"depth must be (H, W) and normals (H, W, 3), got {d.shape} {n.shape}")
        rng = np.random.default_rng(rng)
        h, w = d.shape
        hit = np.isfinite(d) & (d > 0)
        Kinv = np.linalg.inv(as_numpy(K, np.float64).reshape(3, 3))
        uu, vv = np.meshgrid(np.arange(w), np.arange(h))
        rays = np.stack([uu, vv, np.ones_like(uu)], axis=-1).astype(np.float64) @ Kinv.T
        rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
        cos = np.abs(np.einsum("hwc,hwc->hw", rays, n))
        angle = np.arccos(np.clip(cos, 0.0, 1.0))
        out = d + rng.standard_normal(d.shape) * self.sigma(d, angle)
        a0, a1 = np.deg2rad(self.grazing_start_deg), np.deg2rad(self.grazing_end_deg)
        p_drop = np.clip((angle - a0) / (a1 - a0), 0.0, 1.0)
        drop = rng.random(d.shape) < np.maximum(p_drop, self.random_dropout)
        if self.edge_width > 0 and self.edge_dropout > 0:
            z = np.where(hit, d, np.inf)
            edge = np.zeros_like(hit)
            for axis in (0, 1):
                with np.errstate(invalid="ignore"):
                    diff = np.abs(np.diff(z, axis=axis))
                jump = ~(diff <= self.edge_jump)  # inf - inf is nan: background stays no-edge
                both_bg = ~hit[1:, :] & ~hit[:-1, :] if axis == 0 else ~hit[:, 1:] & ~hit[:, :-1]
                jump &= ~both_bg
                if axis == 0:
                    edge[1:, :] |= jump
                    edge[:-1, :] |= jump
                else:
                    edge[:, 1:] |= jump
                    edge[:, :-1] |= jump
            if self.edge_width > 1:
                edge = ndimage.binary_dilation(edge, iterations=self.edge_width - 1)
            drop |= edge & (rng.random(d.shape) < self.edge_dropout)
        out = np.where(hit & ~drop & (out > 0), out, 0.0)
        return torch.from_numpy(out.astype(np.float32))


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


def procedural_texture(rng: np.random.Generator | int | None, size: int = 256) -> np.ndarray:
    """A random texture: smooth colour noise, a checkerboard, stripes or colour blobs.

    Args:
        rng: numpy generator or seed.
        size: side of the square texture in pixels.

    Returns:
        ``(size, size, 3)`` uint8 image.

    Example:
        >>> tex = procedural_texture(0, 32)
        >>> tex.shape, tex.dtype, bool((procedural_texture(0, 32) == tex).all())
        ((32, 32, 3), dtype('uint8'), True)
    """
    rng = np.random.default_rng(rng)
    kind = rng.integers(4)
    base = rng.random(3)
    if kind == 0:  # smooth multi-scale colour noise
        img = np.zeros((size, size, 3))
        for octave, weight in ((4, 0.5), (16, 0.3), (64, 0.2)):
            cells = max(2, min(octave, size))
            small = (rng.random((cells, cells, 3)) * 255).astype(np.uint8)
            big = Image.fromarray(small).resize((size, size), Image.BICUBIC)
            img += weight * np.asarray(big, dtype=np.float64) / 255.0
        img = 0.5 * img + 0.5 * base
    elif kind == 1:  # checkerboard of two colours
        cells = int(rng.integers(2, 16))
        yy, xx = np.mgrid[:size, :size] * cells // size
        other = rng.random(3)
        img = np.where(((yy + xx) % 2 == 0)[..., None], base, other)
    elif kind == 2:  # stripes at a random angle
        theta = rng.uniform(0, np.pi)
        period = rng.uniform(0.05, 0.3) * size
        yy, xx = np.mgrid[:size, :size]
        phase = (np.cos(theta) * xx + np.sin(theta) * yy) / period
        other = rng.random(3)
        t = (0.5 + 0.5 * np.sin(2 * np.pi * phase))[..., None]
        img = t * base + (1 - t) * other
    else:  # random colour blobs on a base colour
        img = np.broadcast_to(base, (size, size, 3)).copy()
        yy, xx = np.mgrid[:size, :size]
        for _ in range(int(rng.integers(5, 25))):
            cy, cx = rng.random(2) * size
            r = rng.uniform(0.03, 0.15) * size
            img[(yy - cy) ** 2 + (xx - cx) ** 2 < r * r] = rng.random(3)
    noise = rng.normal(0.0, 0.02, (size, size, 1))
    return (np.clip(img + noise, 0.0, 1.0) * 255 + 0.5).astype(np.uint8)


# --------------------------------------------------------------------------------------------
# Scene elements
# --------------------------------------------------------------------------------------------


def _plane_mesh(size: float, tile: float, texture: np.ndarray) -> TexturedMesh:
    """Square plane z = 0 of side ``size`` centred at the origin, the texture mirrored per tile.

    Mirroring alternate tiles makes the repeated texture continuous across tile borders.
    """
    n = max(1, math.ceil(size / tile))
    edges = np.linspace(-size / 2, size / 2, n + 1)
    verts, faces, uvs = [], [], []
    quad_uv = np.array([[[0, 0], [1, 0], [1, 1]], [[0, 0], [1, 1], [0, 1]]], dtype=np.float64)
    for i in range(n):
        for j in range(n):
            uv = quad_uv.copy()
            if i % 2:
                uv[..., 0] = 1.0 - uv[..., 0]
            if j % 2:
                uv[..., 1] = 1.0 - uv[..., 1]
            x0, x1, y0, y1 = edges[i], edges[i + 1], edges[j], edges[j + 1]
            b = len(verts)
            verts += [[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]]
            faces += [[b, b + 1, b + 2], [b, b + 2, b + 3]]
            uvs += list(uv)
    v = np.array(verts)
    normals = np.tile([0.0, 0.0, 1.0], (len(v), 1))
    return TexturedMesh(
        v, np.array(faces), vertex_normals=normals, triangle_uvs=np.array(uvs), texture=texture
    )


def _box_mesh(extent: np.ndarray, texture: np.ndarray) -> TexturedMesh:
    """Axis-aligned box centred at the origin, each face mapped to the whole texture."""
    half = np.asarray(extent, dtype=np.float64) / 2
    square = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
    verts, faces, uvs = [], [], []
    for axis in range(3):
        a, b = [i for i in range(3) if i != axis]
        for sign in (-1.0, 1.0):
            corners = np.zeros((4, 3))
            corners[:, axis] = sign
            corners[:, a], corners[:, b] = square[:, 0], square[:, 1]
            # counter-clockwise in (a, b) faces +axis, except for axis y where (x, z) faces -y
            facing = sign if axis != 1 else -sign
            order = [[0, 1, 2], [0, 2, 3]] if facing > 0 else [[0, 2, 1], [0, 3, 2]]
            base = len(verts)
            verts += list(corners * half)
            for tri in order:
                faces.append([base + i for i in tri])
                uvs.append([(square[i] + 1.0) / 2.0 for i in tri])
    return TexturedMesh(
        np.array(verts), np.array(faces), triangle_uvs=np.array(uvs), texture=texture
    )


def _cylinder_mesh(
    radius: float, height: float, texture: np.ndarray, segments: int = 32
) -> TexturedMesh:
    """Closed cylinder along z centred at the origin; the side is wrapped by the texture."""
    ang = np.linspace(0, 2 * np.pi, segments + 1)
    verts, faces, uvs = [], [], []
    h = height / 2
    for k in range(segments):
        a0, a1 = ang[k], ang[k + 1]
        p00 = [radius * np.cos(a0), radius * np.sin(a0), -h]
        p10 = [radius * np.cos(a1), radius * np.sin(a1), -h]
        p01 = [radius * np.cos(a0), radius * np.sin(a0), h]
        p11 = [radius * np.cos(a1), radius * np.sin(a1), h]
        u0, u1 = k / segments, (k + 1) / segments
        base = len(verts)
        verts += [p00, p10, p11, p01]
        faces += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
        uvs += [[[u0, 0], [u1, 0], [u1, 1]], [[u0, 0], [u1, 1], [u0, 1]]]
        for z, order in ((-h, (1, 0)), (h, (0, 1))):  # caps, outward normals
            c = len(verts)
            ring = [[radius * np.cos(a), radius * np.sin(a), z] for a in (a0, a1)]
            verts += [[0.0, 0.0, z], ring[order[0]], ring[order[1]]]
            faces.append([c, c + 1, c + 2])
            uvs.append([[0.5, 0.5], [0.5, 0.5], [0.5, 0.5]])
    return TexturedMesh(
        np.array(verts), np.array(faces), triangle_uvs=np.array(uvs), texture=texture
    )


def _distractor_pool(rng: np.random.Generator, count: int, size_range: tuple[float, float]) -> list:
    pool = []
    lo, hi = size_range
    for _ in range(count):
        tex = procedural_texture(rng, 64)
        if rng.random() < 0.6:
            pool.append(_box_mesh(rng.uniform(lo, hi, 3), tex))
        else:
            pool.append(_cylinder_mesh(rng.uniform(lo, hi) / 2, rng.uniform(lo, hi), tex))
    return pool


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


#: Rotations bringing each of the six model axes (+x, -x, +y, -y, +z, -z) to point down (-z).
_FACE_DOWN = [
    np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]], float),  # +x -> -z
    np.array([[0, 0, -1], [0, 1, 0], [1, 0, 0]], float),  # -x -> -z
    np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], float),  # +y -> -z
    np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], float),  # -y -> -z
    np.array([[1, 0, 0], [0, -1, 0], [0, 0, -1]], float),  # +z -> -z
    np.eye(3),  # -z -> -z
]


def _rest_rotation(rng: np.random.Generator, tilt_prob: float) -> np.ndarray:
    """A resting orientation: a random face down with random yaw, or any orientation."""
    if rng.random() < tilt_prob:
        return quaternion_to_rotation(rng.standard_normal(4))
    return _rot_z(rng.uniform(0, 2 * np.pi)) @ _FACE_DOWN[int(rng.integers(6))]


@dataclass
class _Placed:
    mesh_index: int  # index into the renderer's meshes
    obj_id: int  # 0 for the plane and distractors
    pose_world: np.ndarray  # (4, 4) model-to-world


def _layout(
    rng: np.random.Generator,
    meshes: Sequence[TexturedMesh],
    chosen: Sequence[int],
    obj_ids: Sequence[int],
    *,
    tilt_prob: float,
    clutter: float,
) -> tuple[list[_Placed], float]:
    """Place meshes on the plane z = 0 without overlapping footprints; returns them and a radius."""
    rests = []
    for m in chosen:
        R = _rest_rotation(rng, tilt_prob)
        v = meshes[m].vertices @ R.T
        centre = 0.5 * (v.max(0) + v.min(0))
        foot = float(np.linalg.norm(v[:, :2] - centre[:2], axis=1).max())
        rests.append((R, v.min(0)[2], centre, foot))
    area = sum(r[3] ** 2 for r in rests)
    radius = max(math.sqrt(area / max(clutter, 1e-3)), max(r[3] for r in rests))
    placed: list[_Placed] = []
    circles: list[tuple[np.ndarray, float]] = []
    order = np.argsort([-r[3] for r in rests])  # big first
    for k in order:
        R, zmin, centre, foot = rests[k]
        r_place = radius
        for attempt in range(200):
            xy = rng.uniform(-1, 1, 2) * r_place
            if np.linalg.norm(xy) > r_place:
                continue
            if all(np.linalg.norm(xy - c) >= 0.95 * (foot + f) for c, f in circles):
                break
            if attempt % 40 == 39:
                r_place *= 1.2
        circles.append((xy, foot))
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = [xy[0] - centre[0], xy[1] - centre[1], -zmin]
        placed.append(_Placed(chosen[k], obj_ids[k], T))
    spread = max(float(np.linalg.norm(c) + f) for c, f in circles)
    return placed, spread


def _look_at(eye: np.ndarray, target: np.ndarray, roll: float) -> np.ndarray:
    """World-to-camera transform (OpenCV camera: x right, y down, z forward), z up in the world."""
    f = target - eye
    f /= np.linalg.norm(f)
    up = np.array([0.0, 0.0, 1.0])
    r = np.cross(f, up)
    if np.linalg.norm(r) < 1e-6:
        r = np.array([1.0, 0.0, 0.0])
    r /= np.linalg.norm(r)
    d = np.cross(f, r)
    R_c2w = np.stack([r, d, f], axis=1)
    R_w2c = _rot_z(roll) @ R_c2w.T
    T = np.eye(4)
    T[:3, :3] = R_w2c
    T[:3, 3] = -R_w2c @ eye
    return T


def _background(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    tex = procedural_texture(rng, 128)
    return np.asarray(Image.fromarray(tex).resize((width, height), Image.BILINEAR))


def _random_light(rng: np.random.Generator) -> Light:
    d = rng.standard_normal(3)
    d[2] = -abs(d[2]) - 0.3  # towards the camera side
    tint = 1.0 + rng.uniform(-0.1, 0.1, 3)
    return Light(
        direction=tuple(float(x) for x in d / np.linalg.norm(d)),
        ambient=float(rng.uniform(0.2, 0.5)),
        diffuse=float(rng.uniform(0.5, 0.9)),
        color=tuple(float(x) for x in tint),
    )


# --------------------------------------------------------------------------------------------
# Objects
# --------------------------------------------------------------------------------------------


def _info_of(obj: Any, mesh: TexturedMesh) -> ModelInfo:
    """models_info entry of an object: its own (an ``ObjectModel``) or measured from the mesh."""
    if hasattr(obj, "model_info"):
        return obj.model_info()
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    diameter = float(cloud_diameter(torch.from_numpy(mesh.vertices)[None])[0])
    return ModelInfo(diameter=diameter, min_xyz=lo, size_xyz=hi - lo)


def _load_objects(objects: Any, mesh_scale: float = 1.0) -> list[SyntheticObject]:
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


def _write_models(root: Path, objects: Sequence[SyntheticObject]) -> None:
    from poseflow.data.objects import write_bop_model

    infos = {o.obj_id: o.info for o in objects}
    for folder in ("models", "models_eval"):
        for o in objects:
            write_bop_model(root / folder / f"obj_{o.obj_id:06d}.ply", o.mesh)
        write_models_info(root / folder / "models_info.json", infos)


# --------------------------------------------------------------------------------------------
# The generator
# --------------------------------------------------------------------------------------------


def _range(value: int | float | Sequence[float], name: str) -> tuple[float, float]:
    lo, hi = (value, value) if isinstance(value, (int, float)) else tuple(value)
    if not 0 <= lo <= hi:
        raise ValueRangeError(f"{name} must be a number or a (low, high) range, got {value!r}")
    return float(lo), float(hi)


def generate_dataset(
    out_dir: str | Path,
    objects: Any = None,
    *,
    num_train_images: int = 200,
    num_test_images: int = 50,
    objects_per_image: int | tuple[int, int] = (3, 6),
    width: int = 640,
    height: int = 480,
    seed: int = 0,
    images_per_scene: int = 10,
    distractors_per_image: int | tuple[int, int] = (1, 4),
    focal: float | None = None,
    camera_distance: tuple[float, float] = (0.45, 0.85),
    elevation_deg: tuple[float, float] = (20.0, 75.0),
    max_roll_deg: float = 15.0,
    tilt_prob: float = 0.3,
    clutter: float = 0.5,
    depth_noise: DepthNoise | None = DepthNoise(),
    rgb_noise: float = 2.0,
    depth_scale: float = 0.1,
    min_target_visib: float = 0.1,
    image_ext: str = ".png",
    mesh_scale: float = 1.0,
    progress: bool = True,
    overwrite: bool = False,
) -> Path:
    """Render a synthetic BOP dataset with ``train`` and ``test`` splits.

    Args:
        out_dir: output folder, created; it must be empty or new unless ``overwrite``.
        objects: the objects: None for the library's demo objects
            (:func:`poseflow.data.demo_objects.demo_objects`); a folder of ``.ply``/``.obj``
            meshes (scaled by ``mesh_scale``; BOP-named ``obj_XXXXXX.ply`` files keep their id
            and their ``models_info.json`` entry); a sequence of meshes (``ObjectModel``,
            ``TexturedMesh``, Open3D meshes) numbered from 1; or a mapping ``{obj_id: mesh}``.
            A :class:`SyntheticObject` keeps its own id and info.
        num_train_images: images of the ``train`` split.
        num_test_images: images of the ``test`` split.
        objects_per_image: target objects per scene, a number or an inclusive range; objects
            are drawn without replacement while there are enough, then repeated.
        width: image width in pixels.
        height: image height in pixels.
        seed: the seed everything is drawn from.
        images_per_scene: viewpoints per layout (a BOP scene).
        distractors_per_image: random boxes and cylinders per scene, a number or a range.
        focal: focal length in pixels; default that of a Kinect (572.4 at 640 pixels wide),
            scaled to ``width``. The principal point is the image centre.
        camera_distance: range of camera distances to the layout centre, metres.
        elevation_deg: range of camera elevations above the plane, degrees.
        max_roll_deg: largest in-plane camera roll, degrees.
        tilt_prob: probability that an object lies in an arbitrary orientation rather than on a
            face of its bounding box.
        clutter: packing density of the layout (footprint area over layout area); higher values
            mean more mutual occlusion.
        depth_noise: the depth sensor model, None for clean depth.
        rgb_noise: standard deviation of Gaussian colour noise, in 8-bit levels.
        depth_scale: millimetres per unit of the depth PNGs; depths beyond what 16 bits hold
            (6.5 m at the default 0.1) are written as missing.
        min_target_visib: instances of the test split at least this visible become test targets.
        image_ext: ``".png"`` or ``".jpg"``.
        mesh_scale: factor to metres of the meshes read from a folder (0.001 for meshes in mm).
        progress: show a tqdm progress bar.
        overwrite: write into a folder that holds files, overwriting those of the same names.
            Files of an earlier dataset that this one does not rewrite stay and mix with it
            (scenes, images, models), which is why a non-empty folder is refused by default,
            as ``poseflow synth`` refuses it without ``--overwrite``.

    Returns:
        ``out_dir`` as a :class:`~pathlib.Path`.

    Raises:
        ValueRangeError: bad counts, sizes or ranges.
        OutputExistsError: ``out_dir`` holds files and ``overwrite`` is False (nothing is
            written).

    Example:
        >>> import tempfile
        >>> from poseflow.data.bop import BOPImageDataset
        >>> import open3d as o3d
        >>> box = o3d.geometry.TriangleMesh.create_box(0.08, 0.06, 0.04)
        >>> root = generate_dataset(tempfile.mkdtemp(), [box], num_train_images=1,
        ...     num_test_images=1, objects_per_image=1, width=64, height=48, progress=False)
        >>> sample = BOPImageDataset(root, "test", load_masks=False)[0]
        >>> sample["rgb"].shape, sample["obj_ids"].tolist()
        (torch.Size([3, 48, 64]), [1])
    """
    for name, value in (
        ("num_train_images", num_train_images),
        ("num_test_images", num_test_images),
    ):
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ValueRangeError(f"{name} must be a non-negative integer, got {value!r}")
    if width < 8 or height < 8:
        raise ValueRangeError(f"image size must be at least 8x8, got {width}x{height}")
    if images_per_scene < 1:
        raise ValueRangeError(f"images_per_scene must be >= 1, got {images_per_scene}")
    n_obj = _range(objects_per_image, "objects_per_image")
    if n_obj[0] < 1:
        raise ValueRangeError(f"objects_per_image must be >= 1, got {objects_per_image!r}")
    n_dis = _range(distractors_per_image, "distractors_per_image")
    dist = _range(camera_distance, "camera_distance")
    elev = _range(elevation_deg, "elevation_deg")
    if dist[0] <= 0 or elev[1] > 90:
        raise ValueRangeError("camera_distance must be positive and elevation_deg within [0, 90]")
    if not 0 < clutter <= 1:
        raise ValueRangeError(f"clutter must lie in (0, 1], got {clutter}")

    root = Path(out_dir)
    if root.is_dir() and any(root.iterdir()) and not overwrite:
        raise OutputExistsError(
            f"{root} is not empty: a new dataset would mix with what it holds; choose an empty "
            "or new folder, or pass overwrite=True (--overwrite for poseflow synth)"
        )
    objs = _load_objects(objects, mesh_scale)
    root.mkdir(parents=True, exist_ok=True)
    f = KINECT_FOCAL_640 * width / 640.0 if focal is None else float(focal)
    K = np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])

    # fixed pools: the meshes are built into the renderer once
    pool_rng = np.random.default_rng([seed, 99])
    largest = max(float(np.linalg.norm(o.mesh.extent())) for o in objs)
    plane_size = 4.0 * (dist[1] + largest)
    planes = [
        _plane_mesh(plane_size, 2.0 * largest, procedural_texture(pool_rng, 256)) for _ in range(6)
    ]
    distractors = _distractor_pool(pool_rng, 12, (0.3 * largest, 0.8 * largest))
    meshes = [o.mesh for o in objs] + planes + distractors
    renderer = Renderer(meshes)
    first_plane, first_distractor = len(objs), len(objs) + len(planes)

    max_range = 65535 * depth_scale / 1000.0  # what a 16-bit depth PNG can hold, metres
    _write_models(root, objs)
    (root / "camera.json").write_text(
        json.dumps(
            {
                "cx": K[0, 2],
                "cy": K[1, 2],
                "fx": f,
                "fy": f,
                "width": width,
                "height": height,
                "depth_scale": depth_scale,
            },
            indent=2,
        )
    )
    from tqdm.auto import tqdm

    bar = tqdm(total=num_train_images + num_test_images, disable=not progress, unit="img")
    targets: list[TestTarget] = []
    for split, count in (("train", num_train_images), ("test", num_test_images)):
        writer = BOPWriter(root, split, image_ext=image_ext, depth_scale=depth_scale)
        code = _SPLIT_CODES[split]
        for scene_id in range(math.ceil(count / images_per_scene)):
            srng = np.random.default_rng([seed, code, scene_id])
            k = int(srng.integers(int(n_obj[0]), int(n_obj[1]) + 1))
            if k <= len(objs):
                chosen = list(srng.choice(len(objs), size=k, replace=False))
            else:
                chosen = list(srng.permutation(len(objs))) + list(
                    srng.integers(len(objs), size=k - len(objs))
                )
            n_d = int(srng.integers(int(n_dis[0]), int(n_dis[1]) + 1))
            d_chosen = [
                first_distractor + int(i) for i in srng.integers(len(distractors), size=n_d)
            ]
            all_chosen = [int(c) for c in chosen] + d_chosen
            ids = [objs[int(c)].obj_id for c in chosen] + [0] * n_d
            placed, spread = _layout(
                srng, meshes, all_chosen, ids, tilt_prob=tilt_prob, clutter=clutter
            )
            plane_pose = np.eye(4)
            plane_pose[:3, :3] = _rot_z(srng.uniform(0, 2 * np.pi))
            plane_pose[:2, 3] = srng.uniform(-1, 1, 2) * largest
            placed.append(_Placed(first_plane + int(srng.integers(len(planes))), 0, plane_pose))
            objects_placed = [p for p in placed if p.obj_id > 0]
            centre = np.mean([p.pose_world[:3, 3] for p in objects_placed], axis=0)
            centre[2] = 0.25 * largest  # about mid-height of the objects
            n_images = min(images_per_scene, count - scene_id * images_per_scene)
            for im_id in range(n_images):
                irng = np.random.default_rng([seed, code, scene_id, im_id])
                az = irng.uniform(0, 2 * np.pi)
                el = np.deg2rad(irng.uniform(*elev))
                r = max(irng.uniform(*dist), 1.5 * largest)
                eye = centre + r * np.array(
                    [np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)]
                )
                target = centre + np.append(irng.uniform(-0.25, 0.25, 2) * spread, 0.0)
                T_w2c = _look_at(eye, target, np.deg2rad(irng.uniform(-1, 1) * max_roll_deg))
                poses = np.stack([T_w2c @ p.pose_world for p in placed])
                out = renderer.render(
                    poses,
                    K,
                    width,
                    height,
                    object_ids=[p.mesh_index for p in placed],
                    light=_random_light(irng),
                    background=_background(irng, height, width),
                )
                depth = out.depth
                if depth_noise is not None:
                    depth = depth_noise.apply(depth, out.normals, K, rng=irng)
                depth = torch.where(depth <= max_range, depth, torch.zeros_like(depth))
                rgb = out.rgb.numpy().astype(np.float64)
                if rgb_noise > 0:
                    rgb = rgb + irng.normal(0.0, rgb_noise, rgb.shape)
                rgb8 = np.clip(np.round(rgb), 0, 255).astype(np.uint8)
                sel = [i for i, p in enumerate(placed) if p.obj_id > 0]
                masks = out.masks_full[sel]
                visib = out.masks_visible[sel]
                writer.add_image(
                    scene_id,
                    im_id,
                    K=K,
                    rgb=rgb8,
                    depth=depth,
                    obj_ids=[placed[i].obj_id for i in sel],
                    poses=poses[sel],
                    masks=masks,
                    masks_visib=visib,
                    R_w2c=T_w2c[:3, :3],
                    t_w2c=T_w2c[:3, 3],
                )
                if split == "test":
                    full = masks.flatten(1).sum(1).double()
                    fract = visib.flatten(1).sum(1).double() / full.clamp(min=1)
                    counts: dict[int, int] = {}
                    for i, fr in zip(sel, fract.tolist()):
                        if fr >= min_target_visib:
                            counts[placed[i].obj_id] = counts.get(placed[i].obj_id, 0) + 1
                    targets += [
                        TestTarget(scene_id, im_id, o, c) for o, c in sorted(counts.items())
                    ]
                bar.update(1)
            writer.flush()
    bar.close()
    write_test_targets(root / "test_targets_bop19.json", targets)
    return root
