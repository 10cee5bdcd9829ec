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
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image

from poseflow._progress import ProgressBar
from poseflow._workers import map_forked
from poseflow.data.bop import BOPWriter, TestTarget, write_test_targets
from poseflow.data.depth_noise import DepthNoise
from poseflow.data.scene_layout import Placed, look_at, place_on_plane, rot_z
from poseflow.data.synthetic_objects import (
    SyntheticObject,
    load_synthetic_objects,
    write_synthetic_models,
)
from poseflow.errors import OutputExistsError, ValueRangeError
from poseflow.render.mesh import TexturedMesh
from poseflow.render.raycast import Light, Renderer

__all__ = ["DepthNoise", "SyntheticObject", "generate_dataset", "procedural_texture"]

#: Focal length in pixels of a 640-pixel-wide image (Kinect v1 / Primesense, as in LM and LM-O).
KINECT_FOCAL_640 = 572.4

_SPLIT_CODES = {"train": 0, "test": 1}


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
    depth_noise: DepthNoise | None = DepthNoise(),  # noqa: B008 (frozen, so shared safely)
    rgb_noise: float = 2.0,
    depth_scale: float = 0.1,
    min_target_visib: float = 0.1,
    image_ext: str = ".png",
    mesh_scale: float = 1.0,
    progress: bool = True,
    overwrite: bool = False,
    workers: int = 1,
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
        progress: show a progress bar.
        overwrite: write into a folder that holds files, overwriting those of the same names.
            Files of an earlier dataset that this one does not rewrite stay and mix with it
            (scenes, images, models), which is why a non-empty folder is refused by default,
            as ``poseflow synth`` refuses it without ``--overwrite``.
        workers: render the images in this many forked processes of one thread each
            (``poseflow._workers.map_forked``): the same files.

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
    settings = _Settings.checked(
        width=width, height=height, images_per_scene=images_per_scene,
        objects_per_image=objects_per_image, distractors_per_image=distractors_per_image,
        camera_distance=camera_distance, elevation_deg=elevation_deg, clutter=clutter, seed=seed,
        focal=focal, max_roll_deg=max_roll_deg, tilt_prob=tilt_prob, depth_noise=depth_noise,
        rgb_noise=rgb_noise, depth_scale=depth_scale, min_target_visib=min_target_visib,
        image_ext=image_ext,
    )  # fmt: skip
    root = Path(out_dir)
    if root.is_dir() and any(root.iterdir()) and not overwrite:
        raise OutputExistsError(
            f"{root} is not empty: a new dataset would mix with what it holds; choose an empty "
            "or new folder, or pass overwrite=True (--overwrite for poseflow synth)"
        )
    objs = load_synthetic_objects(objects, mesh_scale)
    root.mkdir(parents=True, exist_ok=True)
    pools = _Pools.build(objs, seed, settings.distance[1])  # the renderer holds every mesh
    write_synthetic_models(root, objs)
    settings.write_camera(root / "camera.json")
    targets: list[TestTarget] = []
    total = num_train_images + num_test_images
    with ProgressBar(total, desc="synth", enabled=progress) as bar:
        for split, count in (("train", num_train_images), ("test", num_test_images)):
            targets += _render_split(root, split, count, pools, settings, bar, workers)
    write_test_targets(root / "test_targets_bop19.json", targets)
    return root


@dataclass(frozen=True)
class _Settings:
    """The checked options of :func:`generate_dataset` that scenes and images are drawn with."""

    width: int
    height: int
    K: np.ndarray  # (3, 3) intrinsics shared by all images
    seed: int
    images_per_scene: int
    objects_per_image: tuple[float, float]  # inclusive ranges
    distractors_per_image: tuple[float, float]
    distance: tuple[float, float]  # metres
    elevation_deg: tuple[float, float]
    max_roll_deg: float
    tilt_prob: float
    clutter: float
    depth_noise: DepthNoise | None
    rgb_noise: float
    depth_scale: float  # millimetres per unit of the depth PNGs
    min_target_visib: float
    image_ext: str

    @classmethod
    def checked(
        cls,
        *,
        width: int,
        height: int,
        images_per_scene: int,
        objects_per_image: int | tuple[int, int],
        distractors_per_image: int | tuple[int, int],
        camera_distance: tuple[float, float],
        elevation_deg: tuple[float, float],
        clutter: float,
        focal: float | None,
        **rest: Any,
    ) -> _Settings:
        """The settings from :func:`generate_dataset`'s arguments, checked; ``rest`` as given."""
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
            raise ValueRangeError(
                "camera_distance must be positive and elevation_deg within [0, 90]"
            )
        if not 0 < clutter <= 1:
            raise ValueRangeError(f"clutter must lie in (0, 1], got {clutter}")
        f = KINECT_FOCAL_640 * width / 640.0 if focal is None else float(focal)
        K = np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])
        return cls(
            width=width, height=height, K=K, images_per_scene=images_per_scene,
            objects_per_image=n_obj, distractors_per_image=n_dis, distance=dist,
            elevation_deg=elev, clutter=clutter, **rest,
        )  # fmt: skip

    @property
    def max_range(self) -> float:
        """The largest depth a 16-bit depth PNG holds, metres; farther depths are missing."""
        return 65535 * self.depth_scale / 1000.0

    def write_camera(self, path: Path) -> None:
        """Write the dataset's ``camera.json`` (BOP layout)."""
        K = self.K
        camera = {"cx": K[0, 2], "cy": K[1, 2], "fx": K[0, 0], "fy": K[1, 1]}
        camera.update(width=self.width, height=self.height, depth_scale=self.depth_scale)
        path.write_text(json.dumps(camera, indent=2))


@dataclass(frozen=True)
class _Pools:
    """The meshes scenes are built from, in one renderer: objects, support planes, distractors."""

    meshes: list[TexturedMesh]
    renderer: Renderer
    obj_ids: list[int]  # of the object meshes, which come first
    planes: range  # mesh indices
    distractors: range
    largest: float  # the largest object extent, metres

    @classmethod
    def build(cls, objs: Sequence[SyntheticObject], seed: int, max_distance: float) -> _Pools:
        """Draw the planes and distractors (sized after the largest object) from ``seed``."""
        rng = np.random.default_rng([seed, 99])
        largest = max(float(np.linalg.norm(o.mesh.extent())) for o in objs)
        plane_size = 4.0 * (max_distance + largest)
        planes = [
            _plane_mesh(plane_size, 2.0 * largest, procedural_texture(rng, 256)) for _ in range(6)
        ]
        distractors = _distractor_pool(rng, 12, (0.3 * largest, 0.8 * largest))
        meshes = [o.mesh for o in objs] + planes + distractors
        n, n_p = len(objs), len(planes)
        return cls(
            meshes, Renderer(meshes), [o.obj_id for o in objs], range(n, n + n_p),
            range(n + n_p, len(meshes)), largest,
        )  # fmt: skip


@dataclass(frozen=True)
class _Image:
    """One rendered image and its object instances (``B`` of them)."""

    rgb: np.ndarray  # (H, W, 3) uint8
    depth: torch.Tensor  # (H, W) metres, 0 where missing
    obj_ids: list[int]
    poses: np.ndarray  # (B, 4, 4) model-to-camera
    masks: torch.Tensor  # (B, H, W) bool, full silhouettes
    masks_visib: torch.Tensor  # (B, H, W) bool, visible parts


def _render_split(
    root: Path,
    split: str,
    count: int,
    pools: _Pools,
    s: _Settings,
    bar: ProgressBar,
    workers: int,
) -> list[TestTarget]:
    """Render and write the ``count`` images of ``split``; the test targets among them.

    Every scene and image draws from its own generator (seeded by the ids), so the images can
    be rendered in ``workers`` processes and written here in order, the same files as in one.
    """
    writer = BOPWriter(root, split, image_ext=s.image_ext, depth_scale=s.depth_scale)
    code = _SPLIT_CODES[split]
    images = [
        (scene_id, im_id)
        for scene_id in range(math.ceil(count / s.images_per_scene))
        for im_id in range(min(s.images_per_scene, count - scene_id * s.images_per_scene))
    ]
    scenes = {
        scene_id: _draw_scene(np.random.default_rng([s.seed, code, scene_id]), pools, s)
        for scene_id in sorted({scene_id for scene_id, _ in images})
    }

    def render(n: int) -> tuple[np.ndarray, _Image]:
        scene_id, im_id = images[n]
        placed, centre, spread = scenes[scene_id]
        rng = np.random.default_rng([s.seed, code, scene_id, im_id])
        T_w2c = _draw_camera(rng, centre, spread, pools.largest, s)
        return T_w2c, _render_image(rng, pools.renderer, placed, T_w2c, s)

    targets: list[TestTarget] = []
    for n, (T_w2c, image) in enumerate(map_forked(render, len(images), workers)):
        scene_id, im_id = images[n]
        writer.add_image(
            scene_id, im_id, K=s.K, rgb=image.rgb, depth=image.depth, obj_ids=image.obj_ids,
            poses=image.poses, masks=image.masks, masks_visib=image.masks_visib,
            R_w2c=T_w2c[:3, :3], t_w2c=T_w2c[:3, 3],
        )  # fmt: skip
        if split == "test":
            targets += _test_targets(scene_id, im_id, image, s.min_target_visib)
        bar.update()
        if n + 1 == len(images) or images[n + 1][0] != scene_id:
            writer.flush()
    return targets


def _draw_scene(
    rng: np.random.Generator, pools: _Pools, s: _Settings
) -> tuple[list[Placed], np.ndarray, float]:
    """One layout on a support plane: the placed meshes, the centre ``(3,)`` and the spread.

    Objects are drawn without replacement while there are enough, then repeated.
    """
    n = len(pools.obj_ids)
    k = int(rng.integers(int(s.objects_per_image[0]), int(s.objects_per_image[1]) + 1))
    if k <= n:
        chosen = list(rng.choice(n, size=k, replace=False))
    else:
        chosen = list(rng.permutation(n)) + list(rng.integers(n, size=k - n))
    n_d = int(rng.integers(int(s.distractors_per_image[0]), int(s.distractors_per_image[1]) + 1))
    d_chosen = [pools.distractors[int(i)] for i in rng.integers(len(pools.distractors), size=n_d)]
    ids = [pools.obj_ids[int(c)] for c in chosen] + [0] * n_d
    placed, spread = place_on_plane(
        rng, pools.meshes, [int(c) for c in chosen] + d_chosen, ids, tilt_prob=s.tilt_prob,
        clutter=s.clutter,
    )  # fmt: skip
    plane_pose = np.eye(4)
    plane_pose[:3, :3] = rot_z(rng.uniform(0, 2 * np.pi))
    plane_pose[:2, 3] = rng.uniform(-1, 1, 2) * pools.largest
    placed.append(Placed(pools.planes[int(rng.integers(len(pools.planes)))], 0, plane_pose))
    centre = np.mean([p.pose_world[:3, 3] for p in placed if p.obj_id > 0], axis=0)
    centre[2] = 0.25 * pools.largest  # about mid-height of the objects
    return placed, centre, spread


def _draw_camera(
    rng: np.random.Generator, centre: np.ndarray, spread: float, largest: float, s: _Settings
) -> np.ndarray:
    """A world-to-camera transform ``(4, 4)`` on the viewpoint sphere around ``centre``."""
    az = rng.uniform(0, 2 * np.pi)
    el = np.deg2rad(rng.uniform(*s.elevation_deg))
    r = max(rng.uniform(*s.distance), 1.5 * largest)
    eye = centre + r * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    target = centre + np.append(rng.uniform(-0.25, 0.25, 2) * spread, 0.0)
    return look_at(eye, target, np.deg2rad(rng.uniform(-1, 1) * s.max_roll_deg))


def _render_image(
    rng: np.random.Generator,
    renderer: Renderer,
    placed: Sequence[Placed],
    T_w2c: np.ndarray,
    s: _Settings,
) -> _Image:
    """Render the placed meshes from ``T_w2c`` under a random light, with sensor noise."""
    poses = np.stack([T_w2c @ p.pose_world for p in placed])
    out = renderer.render(
        poses, s.K, s.width, s.height, object_ids=[p.mesh_index for p in placed],
        light=_random_light(rng), background=_background(rng, s.height, s.width),
    )  # fmt: skip
    depth = out.depth
    if s.depth_noise is not None:
        depth = s.depth_noise.apply(depth, out.normals, s.K, rng=rng)
    depth = torch.where(depth <= s.max_range, depth, torch.zeros_like(depth))
    rgb = out.rgb.numpy().astype(np.float64)
    if s.rgb_noise > 0:
        rgb = rgb + rng.normal(0.0, s.rgb_noise, rgb.shape)
    sel = [i for i, p in enumerate(placed) if p.obj_id > 0]
    return _Image(
        rgb=np.clip(np.round(rgb), 0, 255).astype(np.uint8),
        depth=depth,
        obj_ids=[placed[i].obj_id for i in sel],
        poses=poses[sel],
        masks=out.masks_full[sel],
        masks_visib=out.masks_visible[sel],
    )


def _test_targets(scene_id: int, im_id: int, image: _Image, min_visib: float) -> list[TestTarget]:
    """The image's test targets: per object, its instances at least ``min_visib`` visible."""
    full = image.masks.flatten(1).sum(1).double()
    fract = image.masks_visib.flatten(1).sum(1).double() / full.clamp(min=1)
    counts: dict[int, int] = {}
    for obj_id, fr in zip(image.obj_ids, fract.tolist()):
        if fr >= min_visib:
            counts[obj_id] = counts.get(obj_id, 0) + 1
    return [TestTarget(scene_id, im_id, o, c) for o, c in sorted(counts.items())]
