"""3D scenes of one image: the observed cloud and the object meshes in their poses, for viewers.

A :class:`SceneView` holds everything needed to look at the estimates of one RGB-D image in 3D,
in the camera frame (x right, y down, z forward, metres): the colour image, the depth lifted to a
coloured point cloud (:func:`backproject_rgbd`), the intrinsics, and every object mesh placed by
its pose (:func:`place_mesh`): the estimates with their scores and validity, and the ground truth
when there is one. :func:`build_scene` assembles it from images, poses and meshes.

Two writers turn a scene into files that free viewers open offline:

- :func:`write_recording`: a Rerun recording (``.rrd``, ``pip install rerun-sdk``; open it with
  ``rerun FILE.rrd``) holding the image, the camera (pinhole with ``K``), the cloud, the posed
  meshes (each with its object id, score and validity) and a table of the estimates;
- :func:`export_scene`: one glTF binary scene (``.glb``) with every mesh and the cloud, or a PLY
  of the posed meshes with the cloud beside it, for any mesh viewer (written through trimesh).

Both dependencies are optional (``pip install 'poseflow[viz]'``) and imported only when a file is
written.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from poseflow.data.objects import mesh_vertex_arrays
from poseflow.errors import MissingDependencyError, PoseflowError, ShapeError, ValueRangeError
from poseflow.eval.overlay import GT_COLOR, as_uint8_image
from poseflow.geometry.pointcloud import backproject_depth
from poseflow.render.mesh import DEFAULT_COLOR, as_textured_mesh, sample_texture

__all__ = [
    "GLTF_FROM_CAMERA",
    "ObservedCloud",
    "PosedMesh",
    "SceneView",
    "backproject_rgbd",
    "build_scene",
    "export_scene",
    "place_mesh",
    "write_recording",
]

#: The axis change from the camera frame (OpenCV: y down, z forward) to glTF's (y up, z towards
#: the viewer), the transform of every node of an exported ``.glb``, so that a mesh viewer shows
#: the scene upright, as the camera saw it.
GLTF_FROM_CAMERA = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True, eq=False)
class PosedMesh:
    """An object mesh placed in the camera frame by a model-to-camera pose.

    Attributes:
        name: a name unique within its scene (``est_0_obj_000001``, ``gt_0_obj_000001``), used
            for the Rerun entity and the glTF node.
        obj_id: the object's id.
        pose: the model-to-camera transform, ``(4, 4)`` float64, metres.
        vertices: the vertices under the pose, camera frame, ``(V, 3)`` float64, metres.
        triangles: vertex indices of each triangle, ``(F, 3)`` int64.
        colors: RGB of each vertex, ``(V, 3)`` uint8.
        score: the estimate's confidence, or None for a ground-truth pose.
        valid: whether the estimate is valid (always True for the ground truth).
    """

    name: str
    obj_id: int
    pose: np.ndarray
    vertices: np.ndarray
    triangles: np.ndarray
    colors: np.ndarray
    score: float | None = None
    valid: bool = True

    @property
    def label(self) -> str:
        """One line for a viewer: object id, score and validity (or ``ground truth``)."""
        if self.score is None:
            return f"obj {self.obj_id} (ground truth)"
        return f"obj {self.obj_id}: score {self.score:.3f}, {'valid' if self.valid else 'INVALID'}"


@dataclass(frozen=True, eq=False)
class ObservedCloud:
    """The depth image lifted to camera-frame points, coloured by the image.

    Attributes:
        points: ``(N, 3)`` float32, metres, camera frame.
        colors: ``(N, 3)`` uint8 RGB of each point's pixel.
        pixels: ``(N, 2)`` int64 ``(u, v)`` pixel of each point.
    """

    points: np.ndarray
    colors: np.ndarray
    pixels: np.ndarray

    def __len__(self) -> int:
        return int(self.points.shape[0])


@dataclass(frozen=True, eq=False)
class SceneView:
    """One RGB-D image with its estimates (and ground truth) placed in 3D, camera frame.

    Attributes:
        rgb: the colour image, ``(H, W, 3)`` uint8.
        K: intrinsics, ``(3, 3)`` float64.
        cloud: the observed depth as a coloured cloud.
        estimates: the estimated objects, in the order of the poses given.
        ground_truth: the ground-truth objects (empty when unknown).
        method: the name of the method that estimated (may be empty).
        name: what the scene is (``scene 1 image 0``; may be empty).
    """

    rgb: np.ndarray
    K: np.ndarray
    cloud: ObservedCloud
    estimates: tuple[PosedMesh, ...]
    ground_truth: tuple[PosedMesh, ...] = ()
    method: str = ""
    name: str = ""

    @property
    def size(self) -> tuple[int, int]:
        """``(W, H)`` of the image, pixels."""
        return int(self.rgb.shape[1]), int(self.rgb.shape[0])


def _float64(x: Any) -> np.ndarray:
    """A tensor, array or nested sequence as a float64 numpy array."""
    return np.asarray(torch.as_tensor(x).detach().cpu(), dtype=np.float64)


def _as_pose(pose: Any) -> np.ndarray:
    T = _float64(pose)
    if T.shape != (4, 4):
        raise ShapeError(f"a pose must have shape (4, 4), got {T.shape}")
    return T


def _vertex_colors(arrays: Mapping[str, Any], mesh: Any) -> np.ndarray:
    """RGB uint8 per vertex: the texture at the vertex's UV, else the vertex colours, else grey."""
    n = len(arrays["vertices"])
    if mesh.texture is not None and arrays["uvs"] is not None:
        rgb = sample_texture(mesh.texture, arrays["uvs"])
    elif arrays["colors"] is not None:
        rgb = np.asarray(arrays["colors"], dtype=np.float32)
    else:
        rgb = np.broadcast_to(np.asarray(DEFAULT_COLOR, dtype=np.float32), (n, 3))
    return (np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def place_mesh(
    mesh: Any,
    pose: torch.Tensor | np.ndarray,
    *,
    obj_id: int = 0,
    name: str = "",
    score: float | None = None,
    valid: bool = True,
    color: tuple[int, int, int] | None = None,
) -> PosedMesh:
    """Put a mesh into the camera frame: ``x_cam = R x_model + t`` for every vertex.

    A textured mesh is coloured by its texture sampled at each vertex (vertices split along
    texture seams), a mesh with vertex colours by those, any other in grey.

    Args:
        mesh: the object mesh in metres (a :class:`~poseflow.render.TexturedMesh`, an
            ``ObjectModel`` or an Open3D ``TriangleMesh``).
        pose: model-to-camera transform ``(4, 4)``, metres.
        obj_id: the object's id.
        name: the name of the placed mesh (default ``obj_XXXXXX``).
        score: the estimate's confidence, None for a ground-truth pose.
        valid: the estimate's validity.
        color: one RGB for every vertex instead of the mesh's colours.

    Returns:
        The :class:`PosedMesh`.

    Raises:
        ShapeError: ``pose`` is not ``(4, 4)`` or ``mesh`` is not a mesh.
        ValueRangeError: ``pose`` is not finite.

    Example:
        >>> from poseflow.render import TexturedMesh
        >>> tri = TexturedMesh(np.eye(3), np.array([[0, 1, 2]]))
        >>> T = np.eye(4); T[2, 3] = 0.5
        >>> placed = place_mesh(tri, T, obj_id=3, score=0.9)
        >>> placed.vertices[:, 2].tolist(), placed.colors[0].tolist(), placed.label
        ([0.5, 0.5, 1.5], [179, 179, 179], 'obj 3: score 0.900, valid')
    """
    T = _as_pose(pose)
    if not np.isfinite(T).all():
        raise ValueRangeError(f"the pose of obj {obj_id} is not finite")
    tm = as_textured_mesh(mesh)
    arrays = mesh_vertex_arrays(tm)
    v = np.asarray(arrays["vertices"], dtype=np.float64)
    if color is None:
        colors = _vertex_colors(arrays, tm)
    else:
        colors = np.broadcast_to(np.asarray(color, dtype=np.uint8), v.shape).copy()
    return PosedMesh(
        name=name or f"obj_{obj_id:06d}",
        obj_id=int(obj_id),
        pose=T,
        vertices=v @ T[:3, :3].T + T[:3, 3],
        triangles=np.asarray(arrays["triangles"], dtype=np.int64),
        colors=colors,
        score=None if score is None else float(score),
        valid=bool(valid),
    )


def backproject_rgbd(
    rgb: torch.Tensor | np.ndarray,
    depth: torch.Tensor | np.ndarray,
    K: torch.Tensor | np.ndarray,
    *,
    stride: int = 1,
    max_points: int | None = None,
    seed: int = 0,
) -> ObservedCloud:
    """Lift the valid depth pixels to camera-frame points coloured by the image.

    Args:
        rgb: the colour image, ``(H, W, 3)`` uint8 or ``(3, H, W)`` float in ``[0, 1]``.
        depth: depth ``(H, W)`` in metres (0 or not finite: missing).
        K: intrinsics ``(3, 3)``.
        stride: keep one pixel in ``stride`` along each axis.
        max_points: keep at most this many points, drawn at random with ``seed``.
        seed: seed of the ``max_points`` draw.

    Returns:
        The :class:`ObservedCloud`.

    Raises:
        ShapeError: the image and the depth differ in size.
        ValueRangeError: ``stride < 1``.

    Example:
        >>> K = np.array([[100.0, 0, 1], [0, 100.0, 1], [0, 0, 1]])
        >>> depth = np.zeros((2, 3), np.float32); depth[1, 2] = 2.0
        >>> rgb = np.full((2, 3, 3), 7, np.uint8)
        >>> cloud = backproject_rgbd(rgb, depth, K)
        >>> cloud.points.tolist(), cloud.colors.tolist()
        ([[0.019999999552965164, 0.0, 2.0]], [[7, 7, 7]])
    """
    if isinstance(stride, bool) or stride < 1:
        raise ValueRangeError(f"stride must be a positive integer, got {stride!r}")
    image = as_uint8_image(rgb)
    d = torch.as_tensor(np.asarray(depth) if not isinstance(depth, torch.Tensor) else depth)
    d = d.detach().cpu().to(torch.float32)
    if d.dim() != 2 or tuple(d.shape) != tuple(image.shape[:2]):
        raise ShapeError(
            f"depth must be (H, W) = {tuple(image.shape[:2])} like the image, got {tuple(d.shape)}"
        )
    Kt = torch.as_tensor(np.asarray(torch.as_tensor(K).cpu(), dtype=np.float64))
    mask = torch.zeros(d.shape, dtype=torch.bool)
    mask[::stride, ::stride] = True
    cloud = backproject_depth(
        d[None],
        Kt,
        mask[None],
        max_points=max_points,
        generator=torch.Generator().manual_seed(seed),
    )
    keep = cloud.mask[0]
    pixels = cloud.pixels[0][keep]
    return ObservedCloud(
        points=cloud.points[0][keep].to(torch.float32).numpy(),
        colors=image[pixels[:, 1], pixels[:, 0]].numpy(),
        pixels=pixels.numpy(),
    )


def _rows(x: Any, n: int, what: str, dtype: Any) -> np.ndarray:
    a = np.asarray(x.detach().cpu() if isinstance(x, torch.Tensor) else x, dtype=dtype)
    a = a.reshape(-1)
    if a.shape[0] != n:
        raise ShapeError(f"{what} must hold one entry per pose ({n}), got {a.shape[0]}")
    return a


def build_scene(
    rgb: torch.Tensor | np.ndarray,
    depth: torch.Tensor | np.ndarray,
    K: torch.Tensor | np.ndarray,
    meshes: Mapping[int, Any],
    poses: torch.Tensor | np.ndarray,
    obj_ids: Sequence[int] | torch.Tensor,
    *,
    scores: Sequence[float] | torch.Tensor | None = None,
    valid: Sequence[bool] | torch.Tensor | None = None,
    gt_poses: torch.Tensor | np.ndarray | None = None,
    gt_obj_ids: Sequence[int] | torch.Tensor | None = None,
    method: str = "",
    name: str = "",
    stride: int = 2,
    max_points: int | None = None,
    gt_color: tuple[int, int, int] | None = GT_COLOR,
) -> SceneView:
    """Assemble the :class:`SceneView` of one image: cloud, estimates and ground truth.

    Args:
        rgb: the colour image, ``(H, W, 3)`` uint8 or ``(3, H, W)`` float in ``[0, 1]``.
        depth: depth ``(H, W)`` in metres.
        K: intrinsics ``(3, 3)``.
        meshes: ``{obj_id: mesh}`` in metres (meshes, ``ObjectModel`` or Open3D meshes).
        poses: estimated model-to-camera poses ``(n, 4, 4)``, metres.
        obj_ids: the object of each pose ``(n,)``.
        scores: the confidence of each pose ``(n,)`` (default: NaN, unknown).
        valid: the validity of each pose ``(n,)`` (default: all valid).
        gt_poses: ground-truth poses ``(m, 4, 4)``, or None.
        gt_obj_ids: the object of each ground-truth pose ``(m,)``.
        method: the name of the method that estimated.
        name: what the scene is, e.g. ``scene 1 image 0``.
        stride: the cloud keeps one depth pixel in ``stride`` along each axis.
        max_points: the cloud keeps at most this many points.
        gt_color: one colour for the ground-truth meshes (None: the meshes' own colours).

    Returns:
        The :class:`SceneView`.

    Raises:
        ShapeError: sizes that disagree.
        ValueRangeError: an object id without a mesh, or a pose that is not finite.

    Example:
        >>> from poseflow.render import TexturedMesh
        >>> tri = TexturedMesh(np.eye(3) * 0.1, np.array([[0, 1, 2]]))
        >>> K = np.array([[50.0, 0, 4], [0, 50.0, 3], [0, 0, 1]])
        >>> T = np.eye(4); T[2, 3] = 0.5
        >>> view = build_scene(np.zeros((6, 8, 3), np.uint8), np.full((6, 8), 0.6, np.float32),
        ...                    K, {7: tri}, T[None], [7], scores=[0.8], gt_poses=T[None],
        ...                    gt_obj_ids=[7], stride=1)
        >>> len(view.cloud), [m.name for m in view.estimates + view.ground_truth]
        (48, ['est_0_obj_000007', 'gt_0_obj_000007'])
    """
    estimates = _place_estimates(meshes, poses, obj_ids, scores, valid)
    truth: tuple[PosedMesh, ...] = ()
    if gt_poses is not None:
        truth = _place_ground_truth(meshes, gt_poses, gt_obj_ids, gt_color)
    cloud = backproject_rgbd(rgb, depth, K, stride=stride, max_points=max_points)
    K64 = _float64(K).reshape(3, 3)
    return SceneView(
        rgb=as_uint8_image(rgb).numpy(),
        K=K64,
        cloud=cloud,
        estimates=estimates,
        ground_truth=truth,
        method=method,
        name=name,
    )


def _place_estimates(
    meshes: Mapping[int, Any],
    poses: torch.Tensor | np.ndarray,
    obj_ids: Sequence[int] | torch.Tensor,
    scores: Sequence[float] | torch.Tensor | None,
    valid: Sequence[bool] | torch.Tensor | None,
) -> tuple[PosedMesh, ...]:
    """The estimates placed, ``est_<i>_obj_<id>``, with their scores (default NaN) and validity."""
    P = _float64(poses).reshape(-1, 4, 4)
    n = P.shape[0]
    ids = _rows(obj_ids, n, "obj_ids", np.int64)
    sc = np.full(n, np.nan) if scores is None else _rows(scores, n, "scores", np.float64)
    ok = np.ones(n, dtype=bool) if valid is None else _rows(valid, n, "valid", bool)
    missing = sorted({int(o) for o in ids} - {int(o) for o in meshes})
    if missing:
        raise ValueRangeError(f"no mesh given for objects {missing}")
    return tuple(
        place_mesh(
            meshes[int(o)],
            P[i],
            obj_id=int(o),
            name=f"est_{i}_obj_{int(o):06d}",
            score=float(sc[i]),
            valid=bool(ok[i]),
        )
        for i, o in enumerate(ids)
    )


def _place_ground_truth(
    meshes: Mapping[int, Any],
    gt_poses: torch.Tensor | np.ndarray,
    gt_obj_ids: Sequence[int] | torch.Tensor | None,
    color: tuple[int, int, int] | None,
) -> tuple[PosedMesh, ...]:
    """The ground truth placed, ``gt_<j>_obj_<id>``; an object without a mesh is left out."""
    G = _float64(gt_poses).reshape(-1, 4, 4)
    if gt_obj_ids is None:
        raise ShapeError("gt_poses needs gt_obj_ids")
    gids = _rows(gt_obj_ids, G.shape[0], "gt_obj_ids", np.int64)
    return tuple(
        place_mesh(
            meshes[int(o)], G[j], obj_id=int(o), name=f"gt_{j}_obj_{int(o):06d}", color=color
        )
        for j, o in enumerate(gids)
        if int(o) in meshes
    )


# ------------------------------------------------------------------------------ files


def _describe(view: SceneView) -> str:
    """A Markdown table of the estimates of ``view``."""
    title = " · ".join(s for s in (view.method, view.name) if s) or "estimates"
    lines = [
        f"## {title}",
        "",
        f"{len(view.estimates)} estimates, {len(view.ground_truth)} ground-truth poses, "
        f"{len(view.cloud)} observed points. Camera frame: x right, y down, z forward, metres.",
        "",
        "| entity | obj_id | score | valid | t (mm) |",
        "|---|---|---|---|---|",
    ]
    for m in view.estimates:
        t = " ".join(f"{1000 * x:.1f}" for x in m.pose[:3, 3])
        lines.append(f"| {m.name} | {m.obj_id} | {m.score:.3f} | {m.valid} | {t} |")
    return "\n".join(lines) + "\n"


def write_recording(
    view: SceneView,
    path: str | os.PathLike[str],
    *,
    application_id: str = "poseflow",
    point_radius: float = 0.001,
) -> Path:
    """Write ``view`` as a Rerun recording (``.rrd``) that the free viewer opens offline.

    Entities, all static, in the camera frame (declared right-down-forward):

    - ``world/camera``: the pinhole with ``K`` and the image size; ``world/camera/image``: RGB;
    - ``world/observed``: the depth as points coloured by the image;
    - ``world/estimates/<name>``: each estimate's posed mesh with its vertex colours and
      ``obj_id``, ``score``, ``valid``, ``method``; ``.../label``: one point at its centre
      labelled with the object id, score and validity;
    - ``world/ground_truth/<name>``: each ground-truth mesh with its ``obj_id``;
    - ``description``: a Markdown table of the estimates.

    Nothing is spawned or served: ``rerun FILE.rrd`` opens the file.

    Args:
        view: the scene (:func:`build_scene`).
        path: the ``.rrd`` file to write.
        application_id: Rerun's application id.
        point_radius: radius of the observed points, metres.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        MissingDependencyError: rerun-sdk is not installed.
        PoseflowError: Rerun wrote no file (e.g. logging turned off by ``RERUN=off``).
    """
    try:
        import rerun as rr
    except ImportError as exc:
        raise MissingDependencyError("rerun-sdk", "viz", "Rerun recordings") from exc
    path = Path(path)
    rec = rr.RecordingStream(application_id, default_enabled=True)
    rec.save(path)
    if view.name:
        rec.send_recording_name(view.name)
    W, H = view.size
    rec.log("world", rr.ViewCoordinates.RDF, static=True)
    rec.log("world/camera", rr.Pinhole(image_from_camera=view.K, resolution=[W, H]), static=True)
    rec.log("world/camera/image", rr.Image(view.rgb), static=True)
    rec.log(
        "world/observed",
        rr.Points3D(view.cloud.points, colors=view.cloud.colors, radii=point_radius),
        static=True,
    )
    for group, meshes in (("estimates", view.estimates), ("ground_truth", view.ground_truth)):
        for m in meshes:
            _log_mesh(rec, rr, f"world/{group}/{m.name}", m, view.method)
    rec.log(
        "description", rr.TextDocument(_describe(view), media_type="text/markdown"), static=True
    )
    rec.flush()
    rec.disconnect()
    if not path.is_file():
        raise PoseflowError(f"Rerun wrote no recording at {path} (is RERUN=off set?)")
    return path


def _log_mesh(rec: Any, rr: Any, entity: str, m: PosedMesh, method: str) -> None:
    """Log a posed mesh with its values at ``entity`` and its label at ``<entity>/label``."""
    values: dict[str, Any] = {"obj_id": m.obj_id}
    if m.score is not None:
        values.update(score=m.score, valid=m.valid, method=method)
    rec.log(
        entity,
        rr.Mesh3D(
            vertex_positions=m.vertices.astype(np.float32),
            triangle_indices=m.triangles.astype(np.uint32),
            vertex_colors=m.colors,
        ),
        rr.AnyValues(**values),
        static=True,
    )
    rec.log(
        f"{entity}/label",
        rr.Points3D(m.vertices.mean(0, keepdims=True), labels=[m.label], radii=0.002),
        static=True,
    )


def _trimesh() -> Any:
    try:
        import trimesh
    except ImportError as exc:
        raise MissingDependencyError("trimesh", "viz", "GLB and PLY scenes") from exc
    return trimesh


def _rgba(colors: np.ndarray) -> np.ndarray:
    return np.concatenate([colors, np.full((len(colors), 1), 255, np.uint8)], axis=1)


def export_scene(
    view: SceneView,
    path: str | os.PathLike[str],
    *,
    ground_truth: bool = True,
    cloud: bool = True,
) -> list[Path]:
    """Write the posed meshes and the observed cloud of ``view`` for any mesh viewer.

    - ``.glb``: one glTF binary scene; a node per mesh (named as in :class:`PosedMesh`) and
      ``observed`` for the cloud, with vertex colours. Vertices are stored in the camera frame
      and every node carries :data:`GLTF_FROM_CAMERA`, so viewers show the scene upright.
    - ``.ply``: the posed meshes merged into one coloured mesh at ``path`` (camera frame), and
      the cloud beside it as ``<stem>_cloud.ply``.

    Args:
        view: the scene (:func:`build_scene`).
        path: a ``.glb`` or ``.ply`` file.
        ground_truth: include the ground-truth meshes.
        cloud: include the observed cloud.

    Returns:
        The files written.

    Raises:
        ValueRangeError: another suffix, or nothing to write in a PLY.
        MissingDependencyError: trimesh is not installed.

    Example:
        >>> import tempfile
        >>> from poseflow.render import TexturedMesh
        >>> tri = TexturedMesh(np.eye(3) * 0.1, np.array([[0, 1, 2]]))
        >>> K = np.array([[50.0, 0, 4], [0, 50.0, 3], [0, 0, 1]])
        >>> T = np.eye(4); T[2, 3] = 0.5
        >>> view = build_scene(np.zeros((6, 8, 3), np.uint8), np.full((6, 8), 0.6, np.float32),
        ...                    K, {7: tri}, T[None], [7], stride=1)
        >>> [p.suffix for p in export_scene(view, Path(tempfile.mkdtemp()) / "scene.glb")]
        ['.glb']
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".glb", ".ply"):
        raise ValueRangeError(f"a scene is written as .glb or .ply, got {path.name!r}")
    trimesh = _trimesh()
    meshes = list(view.estimates) + (list(view.ground_truth) if ground_truth else [])
    geoms = {
        m.name: trimesh.Trimesh(
            vertices=m.vertices, faces=m.triangles, vertex_colors=_rgba(m.colors), process=False
        )
        for m in meshes
    }
    points = None
    if cloud and len(view.cloud):
        points = trimesh.PointCloud(view.cloud.points, colors=_rgba(view.cloud.colors))
    path.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".glb":
        scene = trimesh.Scene()
        for name, g in geoms.items():
            scene.add_geometry(g, node_name=name, geom_name=name, transform=GLTF_FROM_CAMERA)
        if points is not None:
            scene.add_geometry(
                points, node_name="observed", geom_name="observed", transform=GLTF_FROM_CAMERA
            )
        path.write_bytes(scene.export(file_type="glb"))
        return [path]
    written = []
    if geoms:
        merged = trimesh.util.concatenate(list(geoms.values()))
        path.write_bytes(merged.export(file_type="ply"))
        written.append(path)
    if points is not None:
        cloud_path = path.with_name(f"{path.stem}_cloud.ply")
        cloud_path.write_bytes(points.export(file_type="ply"))
        written.append(cloud_path)
    if not written:
        raise ValueRangeError(f"nothing to write in {path}: no mesh and no observed point")
    return written
