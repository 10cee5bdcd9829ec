"""A CPU renderer on Open3D's ``RaycastingScene``: depth, instance masks and shaded RGB.

Pixel-centre convention: the integer pixel ``(u, v)`` (column ``u``, row ``v``) is the centre of
that pixel, and its ray is ``K^-1 [u, v, 1]^T`` from the camera centre. This is the OpenCV / BOP
back-projection convention, so rendering a depth map and lifting it with
:func:`poseflow.geometry.pointcloud.backproject_depth` returns points on the surface exactly.
(Open3D's ``create_rays_pinhole`` shoots rays through ``(u + 0.5, v + 0.5)`` instead; it is not
used here.)

Each mesh gets its own ``RaycastingScene`` in its model frame, built once when the
:class:`Renderer` is made. To render an object at a pose, the camera rays are moved into the
object's frame (a rigid motion keeps the ray parameter, so the hit distance stays the camera
z-depth) and only the rays inside the projection of the object's bounding box are cast. This
gives every object's full (unoccluded) depth and mask for free, and the visible instance map is
the per-pixel nearest of them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from poseflow._threads import get_num_threads
from poseflow.errors import ShapeError, ValueRangeError
from poseflow.render.mesh import TexturedMesh, as_textured_mesh

__all__ = ["Light", "RenderOutput", "Renderer", "box_window", "render"]


def box_window(
    corners: np.ndarray, T: np.ndarray, K: np.ndarray, width: int, height: int
) -> tuple[int, int, int, int] | None:
    """The pixels that can see a posed box: a half-open window ``(u0, u1, v0, v1)``, or None.

    The projection of the box's corners, widened by a pixel (two at the far ends); the whole
    image when a corner lies at or behind the camera plane, None when the box is wholly behind
    the camera or projects outside the ``width x height`` image.

    Args:
        corners: the box's corners ``(8, 3)`` in its model frame (any ``(N, 3)`` points).
        T: the pose ``(4, 4)``, model to camera.
        K: the intrinsics ``(3, 3)``.
        width: the image width.
        height: the image height.

    Example:
        >>> box = np.array([[x, y, 1.0] for x in (-0.1, 0.1) for y in (-0.1, 0.1)])
        >>> box_window(box, np.eye(4), np.diag([100.0, 100.0, 1.0]), 64, 48)
        (0, 12, 0, 12)
    """
    c = corners @ T[:3, :3].T + T[:3, 3]
    z = c[:, 2]
    if (z <= 0).all():
        return None
    if (z <= 1e-6).any():
        return 0, width, 0, height
    p = c @ K.T
    u, v = p[:, 0] / z, p[:, 1] / z
    u0, u1 = max(math.floor(u.min()) - 1, 0), min(math.ceil(u.max()) + 2, width)
    v0, v1 = max(math.floor(v.min()) - 1, 0), min(math.ceil(v.max()) + 2, height)
    return None if u0 >= u1 or v0 >= v1 else (u0, u1, v0, v1)


@dataclass(frozen=True)
class Light:
    """A directional light with an ambient term (Lambertian shading).

    The shaded colour of a surface point with albedo ``a`` and camera-facing unit normal ``n`` is
    ``a * color * (ambient + diffuse * max(0, n . direction))``, clipped to ``[0, 1]``.

    Args:
        direction: unit vector from the surface toward the light, in the camera frame
            (x right, y down, z forward). The default ``(0, 0, -1)`` is a headlight.
        ambient: ambient intensity.
        diffuse: diffuse intensity.
        color: RGB multiplier of the light.

    Example:
        >>> Light(direction=(0.0, -1.0, -1.0)).unit_direction.round(3).tolist()
        [0.0, -0.707, -0.707]
    """

    direction: tuple[float, float, float] = (0.0, 0.0, -1.0)
    ambient: float = 0.35
    diffuse: float = 0.65
    color: tuple[float, float, float] = (1.0, 1.0, 1.0)

    @property
    def unit_direction(self) -> np.ndarray:
        """The normalised direction, ``(3,)`` float64."""
        d = np.asarray(self.direction, dtype=np.float64)
        n = float(np.linalg.norm(d))
        if not n > 0:
            raise ValueRangeError("light direction must be non-zero")
        return d / n


@dataclass
class RenderOutput:
    """What :meth:`Renderer.render` returns (CPU tensors).

    Attributes:
        depth: z-depth in metres, ``(H, W)`` float32, 0 where no surface was hit.
        instance: index (into the rendered poses) of the visible object per pixel, ``(H, W)``
            int64, -1 for background.
        masks_full: each object's silhouette as if it were alone, ``(n, H, W)`` bool.
        rgb: shaded colour image, ``(H, W, 3)`` uint8.
        normals: unit surface normals in the camera frame, turned toward the camera,
            ``(H, W, 3)`` float32, 0 for background.
    """

    depth: torch.Tensor
    instance: torch.Tensor
    masks_full: torch.Tensor
    rgb: torch.Tensor
    normals: torch.Tensor

    @property
    def masks_visible(self) -> torch.Tensor:
        """Visible part of each object's silhouette, ``(n, H, W)`` bool."""
        n = self.masks_full.shape[0]
        return self.instance.unsqueeze(0) == torch.arange(n).view(n, 1, 1)

    @property
    def visib_fract(self) -> torch.Tensor:
        """Visible over full silhouette area per object (0 when not in view), ``(n,)`` float64."""
        full = self.masks_full.flatten(1).sum(1).double()
        vis = self.masks_visible.flatten(1).sum(1).double()
        return torch.where(full > 0, vis / full.clamp(min=1), torch.zeros_like(full))


class Renderer:
    """Ray-casting renderer for a fixed set of meshes placed at any poses.

    Args:
        meshes: the meshes (:class:`~poseflow.render.mesh.TexturedMesh`, an object with a
            ``mesh`` attribute such as ``poseflow.data.objects.ObjectModel``, or a legacy
            Open3D ``TriangleMesh``), in metres.
        nthreads: threads for Open3D's ray casting; None (default): poseflow's setting at each
            cast (:func:`poseflow.get_num_threads`); 0: every core.

    Example:
        >>> import open3d as o3d
        >>> box = o3d.geometry.TriangleMesh.create_box(0.1, 0.1, 0.1)
        >>> box = box.translate((-0.05, -0.05, -0.05))
        >>> K = torch.tensor([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]])
        >>> pose = torch.eye(4); pose[2, 3] = 0.5
        >>> out = Renderer([box]).render(pose[None], K, 64, 48)
        >>> round(out.depth[24, 32].item(), 4), out.instance[24, 32].item(), out.rgb.shape
        (0.45, 0, torch.Size([48, 64, 3]))
    """

    def __init__(self, meshes: Sequence[Any], *, nthreads: int | None = None) -> None:
        from poseflow.render.backend import import_open3d

        o3d = import_open3d("rendering")

        self.meshes: list[TexturedMesh] = [as_textured_mesh(m) for m in meshes]
        if not self.meshes:
            raise ShapeError("Renderer needs at least one mesh")
        self.nthreads = None if nthreads is None else int(nthreads)
        self._scenes = []
        for m in self.meshes:
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(
                o3d.core.Tensor(m.vertices.astype(np.float32)),
                o3d.core.Tensor(m.triangles.astype(np.uint32)),
            )
            self._scenes.append(scene)
        self._corners = [m.bounding_box_corners() for m in self.meshes]

    def __len__(self) -> int:
        return len(self.meshes)

    def render(
        self,
        poses: torch.Tensor | np.ndarray,
        K: torch.Tensor | np.ndarray,
        width: int,
        height: int,
        *,
        object_ids: Sequence[int] | torch.Tensor | np.ndarray | None = None,
        light: Light | None = None,
        background: Any = None,
        rgb: bool = True,
    ) -> RenderOutput:
        """Render meshes at the given model-to-camera poses.

        Args:
            poses: model-to-camera transforms (``x_cam = R x_model + t``, metres), ``(n, 4, 4)``.
            K: camera intrinsics, ``(3, 3)`` with last row ``[0, 0, 1]``.
            width: image width ``W`` in pixels.
            height: image height ``H`` in pixels.
            object_ids: which mesh each pose places, ``(n,)`` indices into ``meshes`` (a mesh
                may appear several times). Default: ``range(len(meshes))`` with ``n`` equal to
                the number of meshes.
            light: the light; default :class:`Light()` (a headlight).
            background: RGB behind the objects: None (black), an RGB triple in 0..255, or an
                ``(H, W, 3)`` uint8 image (array or tensor).
            rgb: shade the colour image (False leaves ``rgb`` at the background, faster).

        Returns:
            A :class:`RenderOutput`.

        Raises:
            ShapeError: bad shapes or object ids.
            ValueRangeError: non-finite poses or intrinsics, non-positive image size.
        """
        T = _as_numpy(poses, "poses")
        if T.ndim != 3 or T.shape[1:] != (4, 4):
            raise ShapeError(f"poses must have shape (n, 4, 4), got {T.shape}")
        n = T.shape[0]
        ids = np.arange(len(self.meshes)) if object_ids is None else _as_numpy(object_ids, "ids")
        ids = ids.astype(np.int64).reshape(-1)
        if ids.shape[0] != n:
            raise ShapeError(f"got {n} poses but {ids.shape[0]} object ids")
        if n and (ids.min() < 0 or ids.max() >= len(self.meshes)):
            raise ShapeError(f"object ids must lie in [0, {len(self.meshes)}), got {ids.tolist()}")
        Km = _as_numpy(K, "K")
        if Km.shape != (3, 3):
            raise ShapeError(f"K must have shape (3, 3), got {Km.shape}")
        if not np.allclose(Km[2], [0.0, 0.0, 1.0]):
            raise ValueRangeError(f"K's last row must be [0, 0, 1], got {Km[2].tolist()}")
        if not (np.isfinite(T).all() and np.isfinite(Km).all()):
            raise ValueRangeError("poses and K must be finite")
        width, height = int(width), int(height)
        if width <= 0 or height <= 0:
            raise ValueRangeError(f"image size must be positive, got {width}x{height}")
        light = Light() if light is None else light
        bg = _background(background, height, width)

        Kinv = np.linalg.inv(Km)
        zbuf = np.full((height, width), np.inf, dtype=np.float32)
        inst = np.full((height, width), -1, dtype=np.int64)
        prim = np.zeros((height, width), dtype=np.int64)
        bary = np.zeros((height, width, 2), dtype=np.float32)
        full = np.zeros((n, height, width), dtype=bool)
        windows: dict[int, tuple[int, int, int, int]] = {}
        for i in range(n):
            window = box_window(self._corners[ids[i]], T[i], Km, width, height)
            if window is None:
                continue
            u0, u1, v0, v1 = window
            hit = self._cast(ids[i], T[i], Kinv, u0, u1, v0, v1)
            t_hit = hit["t_hit"].numpy()
            ok = np.isfinite(t_hit) & (t_hit > 0)
            if not ok.any():
                continue
            windows[i] = window
            full[i, v0:v1, u0:u1] = ok
            zwin = zbuf[v0:v1, u0:u1]
            nearer = ok & (t_hit < zwin)
            zwin[nearer] = t_hit[nearer]
            inst[v0:v1, u0:u1][nearer] = i
            prim[v0:v1, u0:u1][nearer] = hit["primitive_ids"].numpy()[nearer].astype(np.int64)
            bary[v0:v1, u0:u1][nearer] = hit["primitive_uvs"].numpy()[nearer]

        depth = np.where(inst >= 0, zbuf, np.float32(0.0)).astype(np.float32)
        image = bg.copy()
        normals = np.zeros((height, width, 3), dtype=np.float32)
        for i, (u0, u1, v0, v1) in windows.items():
            # shade inside the object's window only: the rest of the image cannot show it
            sel = inst[v0:v1, u0:u1] == i
            if not sel.any():
                continue
            mesh = self.meshes[ids[i]]
            fid, b = prim[v0:v1, u0:u1][sel], bary[v0:v1, u0:u1][sel]
            R = T[i, :3, :3]
            nrm = mesh.surface_normals(fid, b) @ R.T
            vv, uu = np.nonzero(sel)
            pix = np.stack([uu + u0, vv + v0, np.ones_like(uu)], axis=1).astype(np.float64)
            flip = np.einsum("pc,pc->p", nrm, pix @ Kinv.T) > 0
            nrm[flip] = -nrm[flip]
            normals[v0:v1, u0:u1][sel] = nrm
            if rgb:
                albedo = mesh.surface_colors(fid, b)
                lambert = np.clip(nrm @ light.unit_direction, 0.0, None)
                shade = (light.ambient + light.diffuse * lambert).astype(np.float32)
                col = albedo * shade[:, None] * np.asarray(light.color, dtype=np.float32)
                image[v0:v1, u0:u1][sel] = (np.clip(col, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
        return RenderOutput(
            depth=torch.from_numpy(depth),
            instance=torch.from_numpy(inst),
            masks_full=torch.from_numpy(full),
            rgb=torch.from_numpy(image),
            normals=torch.from_numpy(normals),
        )

    def _cast(
        self, mesh_id: int, T: np.ndarray, Kinv: np.ndarray, u0: int, u1: int, v0: int, v1: int
    ) -> dict[str, Any]:
        from poseflow.render.backend import import_open3d

        o3d = import_open3d("rendering")

        uu, vv = np.meshgrid(np.arange(u0, u1), np.arange(v0, v1))
        pix = np.stack([uu, vv, np.ones_like(uu)], axis=-1).astype(np.float64)
        d_cam = pix @ Kinv.T  # z component is 1, so the ray parameter is the z-depth
        R, t = T[:3, :3], T[:3, 3]
        origin = -(R.T @ t)
        d_model = d_cam @ R  # R^T d for every ray
        rays = np.empty((*d_model.shape[:2], 6), dtype=np.float32)
        rays[..., :3] = origin
        rays[..., 3:] = d_model
        nthreads = get_num_threads() if self.nthreads is None else self.nthreads
        return self._scenes[mesh_id].cast_rays(o3d.core.Tensor(rays), nthreads=nthreads)


def render(
    meshes: Sequence[Any],
    poses: torch.Tensor | np.ndarray,
    K: torch.Tensor | np.ndarray,
    width: int,
    height: int,
    *,
    light: Light | None = None,
    background: Any = None,
) -> RenderOutput:
    """Render meshes at poses in one call (builds a :class:`Renderer`; reuse one for many calls).

    Args:
        meshes: ``n`` meshes in metres (see :class:`Renderer`).
        poses: model-to-camera transforms, ``(n, 4, 4)``.
        K: intrinsics, ``(3, 3)``.
        width: image width ``W``.
        height: image height ``H``.
        light: the light; default a headlight.
        background: None (black), an RGB triple in 0..255, or an ``(H, W, 3)`` uint8 image.

    Returns:
        A :class:`RenderOutput`.

    Example:
        >>> import open3d as o3d
        >>> s = o3d.geometry.TriangleMesh.create_sphere(0.05, resolution=40)
        >>> K = torch.tensor([[200.0, 0, 32], [0, 200.0, 32], [0, 0, 1]])
        >>> pose = torch.eye(4); pose[2, 3] = 1.0
        >>> out = render([s], pose[None], K, 64, 64)
        >>> int(out.masks_full[0].sum())  # about pi * (200 * 0.05 / sqrt(1 - 0.05**2))**2 = 315
        317
    """
    return Renderer(meshes).render(poses, K, width, height, light=light, background=background)


def _as_numpy(x: Any, name: str) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().double().numpy() if x.is_floating_point() else x.cpu().numpy()
    try:
        return np.asarray(x, dtype=np.float64) if name != "ids" else np.asarray(x)
    except (TypeError, ValueError) as e:
        raise ShapeError(f"{name} must be array-like: {e}") from e


def _background(background: Any, height: int, width: int) -> np.ndarray:
    if background is None:
        return np.zeros((height, width, 3), dtype=np.uint8)
    bg = (
        background.cpu().numpy() if isinstance(background, torch.Tensor) else np.asarray(background)
    )
    if bg.shape == (3,):
        if (bg < 0).any() or (bg > 255).any():
            raise ValueRangeError(f"background colour must lie in 0..255, got {bg.tolist()}")
        return np.broadcast_to(bg.astype(np.uint8), (height, width, 3)).copy()
    if bg.shape != (height, width, 3) or bg.dtype != np.uint8:
        raise ShapeError(
            f"background must be an RGB triple or a ({height}, {width}, 3) uint8 image, "
            f"got {bg.shape} {bg.dtype}"
        )
    return bg.copy()
