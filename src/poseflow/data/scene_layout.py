"""Where things go in a synthetic scene: objects at rest on a plane, and the camera looking at them.

Coordinates: the world has z up and the support plane at z = 0; cameras are OpenCV cameras (x right,
y down, z forward).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from poseflow.geometry.se3 import quaternion_to_rotation
from poseflow.render.mesh import TexturedMesh

__all__ = ["Placed", "look_at", "place_on_plane", "rot_z"]


def rot_z(a: float) -> np.ndarray:
    """The rotation ``(3, 3)`` by ``a`` radians about z."""
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
    return rot_z(rng.uniform(0, 2 * np.pi)) @ _FACE_DOWN[int(rng.integers(6))]


@dataclass
class Placed:
    """A mesh placed in a scene: which mesh, its object id and its model-to-world pose."""

    mesh_index: int  # index into the renderer's meshes
    obj_id: int  # 0 for the plane and distractors
    pose_world: np.ndarray  # (4, 4) model-to-world


def place_on_plane(
    rng: np.random.Generator,
    meshes: Sequence[TexturedMesh],
    chosen: Sequence[int],
    obj_ids: Sequence[int],
    *,
    tilt_prob: float,
    clutter: float,
) -> tuple[list[Placed], float]:
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
    placed: list[Placed] = []
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
        placed.append(Placed(chosen[k], obj_ids[k], T))
    spread = max(float(np.linalg.norm(c) + f) for c, f in circles)
    return placed, spread


def look_at(eye: np.ndarray, target: np.ndarray, roll: float) -> np.ndarray:
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
    R_w2c = rot_z(roll) @ R_c2w.T
    T = np.eye(4)
    T[:3, :3] = R_w2c
    T[:3, 3] = -R_w2c @ eye
    return T
