"""A test split of a BOP folder's meshes made by another image generator than ``poseflow synth``.

``poseflow synth`` renders the recipe's training images, and a test split from it shares their
renderer, shading, sensor noise and scene layout: accuracy on it says nothing of the gap a user's
real images open. This writes a test split of the same meshes that shares none of them:

- **renderer**: OpenGL rasterisation (moderngl on a headless EGL context), Phong shading of the
  vertex colours under a point light with a specular highlight, exposure, white balance, blur and
  noise of a colour sensor (``poseflow synth`` ray-casts with Open3D);
- **layout**: the objects rest on a textured table in their stable poses
  (:func:`trimesh.poses.compute_stable_poses`, drawn by their probability, turned about the
  vertical), among resting distractor primitives, seen from cameras around the table at 25-70
  degrees of elevation and 0.45-0.75 m, four views per scene;
- **depth sensor**: a structured-light model of its own: the projector's shadows (no depth where
  the projector, ``baseline`` metres to the side, cannot see the surface), disparity noise
  correlated over 2 x 2 pixels and quantised to 1/8 pixel, dropout at grazing angles and along
  depth edges, and scattered holes.

The folder it writes (``OUT/models``, ``models_eval``, ``camera.json``, ``test/``,
``test_targets_bop19.json`` with the instances at least 10 % visible) is a BOP dataset that
``benchmarks/unseen.py`` and ``poseflow predict``/``eval`` read; its ``models/`` are the source's,
so a model trained on the source's meshes predicts on it as it is:

    python benchmarks/other_renderer.py runs/meshset2 runs/meshset2_gl
    python benchmarks/unseen.py runs/meshset2_gl --work runs/unseen/ms4 --seeds 0 1 2

(``--work`` of a recipe run on the source reuses its trained model.) Needs ``moderngl`` (the
``bench`` extra) and an EGL driver (Mesa's software one serves). ``--quick`` (CI) writes two
images of generated objects and checks the split reads back.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh
from _common import report
from scipy import ndimage

from poseflow.data.bop import BOPDataset, BOPWriter, TestTarget, write_test_targets
from poseflow.data.bop.json_io import read_models_info

#: Image size and intrinsics of the sensor (a 640 x 480 RGB-D camera).
WIDTH, HEIGHT = 640, 480
K = np.array([[605.0, 0.0, 322.5], [0.0, 604.0, 241.0], [0.0, 0.0, 1.0]])
NEAR, FAR = 0.05, 5.0
VIEWS_PER_SCENE = 4
MIN_VISIB = 0.1

_VERTEX = """
#version 330
uniform mat4 model_view;
uniform vec4 intrinsics;
uniform vec2 size;
uniform vec2 near_far;
in vec3 in_pos;
in vec3 in_normal;
in vec3 in_color;
out vec3 v_pos;
out vec3 v_normal;
out vec3 v_color;
void main() {
    vec4 p = model_view * vec4(in_pos, 1.0);
    v_pos = p.xyz;
    v_normal = mat3(model_view) * in_normal;
    v_color = in_color;
    float n = near_far.x, f = near_far.y, z = p.z;
    // OpenCV pixel centres lie on integers, OpenGL's at +0.5; window row v is image row v
    float u = intrinsics.x * p.x + (intrinsics.z + 0.5) * z;
    float v = intrinsics.y * p.y + (intrinsics.w + 0.5) * z;
    gl_Position = vec4(2.0 * u / size.x - z, 2.0 * v / size.y - z,
                       ((f + n) * z - 2.0 * f * n) / (f - n), z);
}
"""

_FRAGMENT = """
#version 330
uniform vec3 light;
uniform vec4 shading;  // ambient, diffuse, specular, shininess
uniform float instance;
in vec3 v_pos;
in vec3 v_normal;
in vec3 v_color;
layout(location = 0) out vec4 out_color;
layout(location = 1) out float out_depth;
layout(location = 2) out float out_instance;
layout(location = 3) out float out_facing;
void main() {
    vec3 view = normalize(-v_pos);
    vec3 n = normalize(v_normal);
    if (dot(n, view) < 0.0) n = -n;
    vec3 l = normalize(light - v_pos);
    float diffuse = max(dot(n, l), 0.0);
    float spec = pow(max(dot(n, normalize(l + view)), 0.0), shading.w);
    out_color = vec4(v_color * (shading.x + shading.y * diffuse) + shading.z * spec, 1.0);
    out_depth = v_pos.z;
    out_instance = instance;
    out_facing = dot(n, view);
}
"""


@dataclass
class _Mesh:
    """Vertices (metres), normals, colours in [0, 1] and faces of one mesh, and its GL arrays."""

    vertices: np.ndarray
    normals: np.ndarray
    colors: np.ndarray
    faces: np.ndarray
    vao: object = None


@dataclass
class _Placed:
    """A mesh placed in the world (z up, the table at z = 0); ``instance`` 0 for distractors."""

    mesh: _Mesh
    pose: np.ndarray
    instance: int
    shininess: float
    specular: float


class GLRenderer:
    """Colour, depth, instance and facing maps of placed meshes on a headless OpenGL context."""

    def __init__(self) -> None:
        try:
            import moderngl
        except ImportError as e:  # pragma: no cover - the bench extra
            raise SystemExit("other_renderer needs moderngl: pip install 'poseflow[bench]'") from e
        self.ctx = moderngl.create_context(standalone=True, backend="egl")
        self.prog = self.ctx.program(vertex_shader=_VERTEX, fragment_shader=_FRAGMENT)
        size = (WIDTH, HEIGHT)
        self.fbo = self.ctx.framebuffer(
            [self.ctx.renderbuffer(size, 4)]
            + [self.ctx.renderbuffer(size, 1, dtype="f4") for _ in range(3)],
            self.ctx.depth_renderbuffer(size),
        )
        self.prog["intrinsics"].value = (K[0, 0], K[1, 1], K[0, 2], K[1, 2])
        self.prog["size"].value = size
        self.prog["near_far"].value = (NEAR, FAR)
        self.depth_test = moderngl.DEPTH_TEST

    def upload(self, mesh: _Mesh) -> _Mesh:
        """``mesh`` with its vertex array on the context."""
        data = np.hstack((mesh.vertices, mesh.normals, mesh.colors)).astype("f4")
        vbo = self.ctx.buffer(data.tobytes())
        ibo = self.ctx.buffer(mesh.faces.astype("i4").tobytes())
        mesh.vao = self.ctx.vertex_array(
            self.prog, [(vbo, "3f 3f 3f", "in_pos", "in_normal", "in_color")], ibo
        )
        return mesh

    def render(
        self, placed: list[_Placed], w2c: np.ndarray, light: np.ndarray, ambient: float
    ) -> dict[str, np.ndarray]:
        """The maps of ``placed`` seen by ``w2c`` ``(4, 4)``, lit from ``light`` (world, metres).

        Returns ``rgb (H, W, 3)`` in [0, 1], ``depth (H, W)`` metres (0: nothing), ``instance``
        ``(H, W)`` int (0: none) and ``facing`` ``(H, W)``, the cosine of normal and view ray.
        """
        self.fbo.use()
        self.ctx.enable(self.depth_test)
        self.fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        self.prog["light"].value = tuple((w2c[:3, :3] @ light + w2c[:3, 3]).tolist())
        for p in placed:
            self.prog["model_view"].write((w2c @ p.pose).T.astype("f4").tobytes())
            self.prog["shading"].value = (ambient, 1.0 - ambient, p.specular, p.shininess)
            self.prog["instance"].value = float(p.instance)
            p.mesh.vao.render()

        def read(i: int, c: int) -> np.ndarray:
            raw = self.fbo.read(attachment=i, components=c, dtype="f1" if i == 0 else "f4")
            return np.frombuffer(raw, "u1" if i == 0 else "f4").reshape(HEIGHT, WIDTH, c)

        return {
            "rgb": read(0, 4)[..., :3] / 255.0,
            "depth": read(1, 1)[..., 0].copy(),
            "instance": np.rint(read(2, 1)[..., 0]).astype(int),
            "facing": read(3, 1)[..., 0].copy(),
        }


def _load_mesh(path: Path) -> _Mesh:
    m = trimesh.load(path, process=False)
    colors = np.full((len(m.vertices), 3), 0.6)
    if m.visual.kind == "vertex":
        colors = np.asarray(m.visual.vertex_colors)[:, :3] / 255.0
    return _Mesh(
        np.asarray(m.vertices) / 1000.0, np.asarray(m.vertex_normals), colors, np.asarray(m.faces)
    )


def _trimesh_of(mesh: _Mesh):  # type: ignore[no-untyped-def]
    return trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)


def _table(rng: np.random.Generator) -> _Mesh:
    """A 1.4 m square table top at z = 0 with a smooth random colour pattern."""
    n = 96
    xs = np.linspace(-0.7, 0.7, n)
    gx, gy = np.meshgrid(xs, xs)
    v = np.stack((gx.ravel(), gy.ravel(), np.zeros(n * n)), 1)
    base = rng.uniform(0.3, 0.8, 3)
    k = rng.normal(size=(6, 2)) * 25
    phase = rng.uniform(0, 2 * np.pi, 6)
    pattern = sum(np.sin(v[:, :2] @ k[i] + phase[i]) for i in range(6)) / 6
    colors = np.clip(base + 0.12 * pattern[:, None] * rng.uniform(0.5, 1.5, 3), 0, 1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    faces = np.concatenate((np.stack((a, b, d), -1), np.stack((a, d, c), -1))).reshape(-1, 3)
    normals = np.tile([0.0, 0.0, 1.0], (n * n, 1))
    return _Mesh(v, normals, colors, faces)


def _distractor(rng: np.random.Generator) -> _Mesh:
    kind = rng.integers(3)
    if kind == 0:
        m = trimesh.creation.box(rng.uniform(0.03, 0.12, 3))
    elif kind == 1:
        m = trimesh.creation.cylinder(rng.uniform(0.015, 0.05), rng.uniform(0.03, 0.14), 32)
    else:
        m = trimesh.creation.icosphere(3, rng.uniform(0.02, 0.05))
    colors = np.tile(rng.uniform(0.1, 0.95, 3), (len(m.vertices), 1))
    return _Mesh(np.asarray(m.vertices), np.asarray(m.vertex_normals), colors, np.asarray(m.faces))


def _resting(mesh: _Mesh, rng: np.random.Generator) -> np.ndarray:
    """A stable resting pose on z = 0, drawn by probability, turned about z; centred in x, y."""
    with np.errstate(invalid="ignore"):
        poses, prob = trimesh.poses.compute_stable_poses(_trimesh_of(mesh), n_samples=1)
    prob = np.nan_to_num(np.asarray(prob, float))
    prob = prob / prob.sum() if prob.sum() > 0 else np.full(len(poses), 1 / len(poses))
    T = np.asarray(poses[rng.choice(len(poses), p=prob)], float)
    a = rng.uniform(0, 2 * np.pi)
    yaw = np.eye(4)
    yaw[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    T = yaw @ T
    placed = mesh.vertices @ T[:3, :3].T + T[:3, 3]
    T[:2, 3] -= placed[:, :2].mean(0)
    T[2, 3] -= placed[:, 2].min()
    return T


def _layout(meshes: list[_Mesh], rng: np.random.Generator) -> list[np.ndarray]:
    """Non-overlapping resting poses of ``meshes`` within a disc on the table."""
    radii = [np.linalg.norm(m.vertices - m.vertices.mean(0), axis=1).max() for m in meshes]
    for _ in range(1000):
        poses, centres = [], []
        for m, r in zip(meshes, radii):
            T = _resting(m, rng)
            for _ in range(200):
                c = rng.uniform(-0.2, 0.2, 2)
                if all(np.linalg.norm(c - c2) > r + r2 for c2, r2 in centres):
                    break
            else:
                break
            T[:2, 3] += c
            poses.append(T)
            centres.append((c, r))
        if len(poses) == len(meshes):
            return poses
    raise RuntimeError("could not place the objects without overlap")


def _camera(rng: np.random.Generator, azimuth: float) -> np.ndarray:
    """World-to-camera ``(4, 4)`` (OpenCV axes) looking at the table's centre region."""
    el = np.deg2rad(rng.uniform(25, 70))
    dist = rng.uniform(0.45, 0.75)
    target = np.array([*rng.uniform(-0.05, 0.05, 2), 0.03])
    eye = target + dist * np.array(
        [np.cos(el) * np.cos(azimuth), np.cos(el) * np.sin(azimuth), np.sin(el)]
    )
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    R = np.stack((right, down, forward))
    roll = np.deg2rad(rng.uniform(-8, 8))
    Rz = np.array([[np.cos(roll), -np.sin(roll), 0], [np.sin(roll), np.cos(roll), 0], [0, 0, 1]])
    w2c = np.eye(4)
    w2c[:3, :3] = Rz @ R
    w2c[:3, 3] = -(Rz @ R) @ eye
    return w2c


def _sensor_depth(
    depth: np.ndarray, facing: np.ndarray, projector: np.ndarray, baseline: float, rng
) -> np.ndarray:
    """The structured-light depth of a rendered depth map (metres, 0 missing)."""
    f = K[0, 0]
    valid = depth > 0
    # projector shadows: the surface point seen from the projector, `baseline` along +x
    v, u = np.nonzero(valid)
    z = depth[v, u]
    x = (u - K[0, 2]) * z / f - baseline
    up = np.rint(f * x / z + K[0, 2]).astype(int)
    inside = (up >= 0) & (up < WIDTH)
    seen = np.zeros_like(z, dtype=bool)
    zp = projector[v[inside], up[inside]]
    seen[inside] = (zp > 0) & (z[inside] <= zp + 0.004 + 0.01 * z[inside])
    valid[v[~seen], u[~seen]] = False
    # disparity noise correlated over 2 x 2 pixels, quantised to 1/8 pixel
    disparity = np.where(valid, f * baseline / np.maximum(depth, 1e-6), 0.0)
    noise = rng.normal(0.0, 0.06, (HEIGHT // 2 + 1, WIDTH // 2 + 1)).repeat(2, 0).repeat(2, 1)
    disparity = np.round((disparity + noise[:HEIGHT, :WIDTH]) * 8) / 8
    # grazing angles and depth edges lose their measurement; scattered holes
    grazing = np.clip((0.25 - facing) / 0.2, 0, 1)
    valid &= rng.random(depth.shape) >= grazing
    gy, gx = np.gradient(depth)
    edge = (np.abs(gx) + np.abs(gy)) > 0.02
    edge = ndimage.binary_dilation(edge, iterations=1) & (rng.random(depth.shape) < 0.7)
    valid &= ~edge & (rng.random(depth.shape) >= 0.003)
    return np.where(valid & (disparity > 0), f * baseline / np.maximum(disparity, 1e-6), 0.0)


def _sensor_rgb(rgb: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Exposure, white balance, optical blur and noise of a colour sensor; uint8 ``(H, W, 3)``."""
    out = rgb * rng.uniform(0.85, 1.2) * rng.uniform(0.9, 1.1, 3)
    out = ndimage.gaussian_filter(out, sigma=(0.6, 0.6, 0))
    out = out + rng.normal(0.0, 0.012, out.shape)
    return (np.clip(out, 0, 1) * 255 + 0.5).astype(np.uint8)


def write_split(
    source: Path, out: Path, *, scenes: int, seed: int, baseline: float = 0.075
) -> dict:
    """Render ``scenes`` x 4 test images of ``source``'s meshes into the BOP folder ``out``."""
    began = time.perf_counter()
    rng = np.random.default_rng(seed)
    out.mkdir(parents=True, exist_ok=True)
    for name in ("models", "models_eval"):
        shutil.copytree(source / "models", out / name, dirs_exist_ok=True)
    info = read_models_info(source / "models" / "models_info.json")
    obj_ids = sorted(info)
    gl = GLRenderer()
    objects = {o: gl.upload(_load_mesh(source / "models" / f"obj_{o:06d}.ply")) for o in obj_ids}
    camera = {"cx": K[0, 2], "cy": K[1, 2], "fx": K[0, 0], "fy": K[1, 1]}
    camera |= {"depth_scale": 0.1, "height": HEIGHT, "width": WIDTH}
    (out / "camera.json").write_text(json.dumps(camera, indent=1))
    targets: list[TestTarget] = []
    with BOPWriter(out, "test") as writer:
        for scene_id in range(1, scenes + 1):
            table = gl.upload(_table(rng))
            distractors = [gl.upload(_distractor(rng)) for _ in range(rng.integers(2, 5))]
            movable = [objects[o] for o in obj_ids] + distractors
            poses = _layout(movable, rng)
            placed = [_Placed(table, np.eye(4), 0, 8.0, 0.05)] + [
                _Placed(m, T, k + 1 if k < len(obj_ids) else 0,
                        float(rng.uniform(5, 60)), float(rng.uniform(0.0, 0.35)))
                for k, (m, T) in enumerate(zip(movable, poses))
            ]  # fmt: skip
            start = rng.uniform(0, 2 * np.pi)
            for view in range(VIEWS_PER_SCENE):
                im_id = (scene_id - 1) * VIEWS_PER_SCENE + view
                w2c = _camera(rng, start + view * 2 * np.pi / VIEWS_PER_SCENE)
                light = np.array([*rng.uniform(-0.6, 0.6, 2), rng.uniform(0.6, 1.4)])
                ambient = float(rng.uniform(0.25, 0.5))
                full = gl.render(placed, w2c, light, ambient)
                shifted = w2c.copy()
                shifted[0, 3] -= baseline  # the projector's view, `baseline` along camera +x
                projector = gl.render(placed, shifted, light, ambient)["depth"]
                depth = _sensor_depth(full["depth"], full["facing"], projector, baseline, rng)
                ids, Ts, masks, visib = [], [], [], []
                for k, o in enumerate(obj_ids):
                    alone = gl.render([placed[k + 1]], w2c, light, ambient)["instance"] == k + 1
                    if not alone.any():
                        continue
                    ids.append(o)
                    Ts.append(w2c @ placed[k + 1].pose)
                    masks.append(alone)
                    visib.append(full["instance"] == k + 1)
                    if visib[-1].sum() >= MIN_VISIB * alone.sum():
                        targets.append(TestTarget(scene_id, im_id, o, 1))
                writer.add_image(
                    scene_id, im_id, K=K, rgb=_sensor_rgb(full["rgb"], rng), depth=depth,
                    obj_ids=ids, poses=np.stack(Ts), masks=np.stack(masks),
                    masks_visib=np.stack(visib), R_w2c=w2c[:3, :3], t_w2c=w2c[:3, 3],
                )  # fmt: skip
    write_test_targets(out / "test_targets_bop19.json", targets)
    seconds = round(time.perf_counter() - began, 1)
    return {
        "images": scenes * VIEWS_PER_SCENE, "targets": len(targets), "objects": obj_ids,
        "seconds": seconds,
    }  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source", nargs="?", help="BOP folder whose models/ are rendered")
    parser.add_argument("out", nargs="?", help="the BOP folder to write")
    parser.add_argument("--scenes", type=int, default=6, help="scenes of four views each")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--quick", action="store_true", help="one scene of generated objects (CI)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        if args.quick:
            from poseflow.data.synthetic import generate_dataset

            args.source = generate_dataset(
                Path(tmp) / "src", num_train_images=0, num_test_images=1, seed=3, progress=False
            )
            args.out, args.scenes = Path(tmp) / "gl", 1
        if args.source is None or args.out is None:
            parser.error("give SOURCE and OUT, or --quick")
        record = write_split(Path(args.source), Path(args.out), scenes=args.scenes, seed=args.seed)
        split = BOPDataset(Path(args.out), "test")
        scene = split.scene(1)
        depth = scene.load_depth_image(0)
        record["valid_depth"] = round(float((depth > 0).float().mean()), 3)
        if args.quick:
            assert record["targets"] > 0, record
            assert 0.5 < record["valid_depth"] < 1.0, record
            assert torch.isfinite(depth).all()
    report(record, __file__)


if __name__ == "__main__":
    main()
