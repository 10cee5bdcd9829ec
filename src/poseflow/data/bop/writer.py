"""Write a BOP split: images and scene JSON files (:class:`BOPWriter`), model PLYs, GT info."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from poseflow.data._arrays import as_numpy
from poseflow.data.bop.images import write_depth, write_image, write_mask
from poseflow.data.bop.json_io import (
    read_scene_camera,
    read_scene_gt,
    read_scene_gt_info,
    write_scene_camera,
    write_scene_gt,
    write_scene_gt_info,
)
from poseflow.data.bop.records import MM_PER_M, CameraInfo, GTInfo, GTPose
from poseflow.errors import ShapeError, ValueRangeError

__all__ = ["BOPWriter", "compute_gt_info", "write_model_ply"]


def write_model_ply(
    path: str | Path,
    vertices: torch.Tensor | np.ndarray,
    faces: torch.Tensor | np.ndarray,
    *,
    normals: torch.Tensor | np.ndarray | None = None,
    colors: torch.Tensor | np.ndarray | None = None,
    uvs: torch.Tensor | np.ndarray | None = None,
    texture_file: str | None = None,
) -> None:
    """Write a triangle mesh as a binary BOP model PLY (vertices given in metres, written in mm).

    Args:
        path: output ``.ply``.
        vertices: ``(V, 3)`` positions in metres.
        faces: ``(F, 3)`` vertex indices.
        normals: optional ``(V, 3)`` unit normals.
        colors: optional ``(V, 3)`` colours in ``[0, 1]``.
        uvs: optional ``(V, 2)`` texture coordinates, written as ``texture_u``/``texture_v`` with
            ``v`` measured from the bottom row of the texture image (the PLY/OpenGL convention).
        texture_file: name of the texture image next to the PLY (a ``comment TextureFile`` line).
    """
    v = as_numpy(vertices, np.float64)
    f = as_numpy(faces, np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise ShapeError(f"vertices must be (V, 3) and faces (F, 3), got {v.shape} and {f.shape}")
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise ValueRangeError("faces index vertices out of range")
    props: list[tuple[str, str]] = [("x", "f4"), ("y", "f4"), ("z", "f4")]
    cols: list[np.ndarray] = [v * MM_PER_M]
    if normals is not None:
        props += [("nx", "f4"), ("ny", "f4"), ("nz", "f4")]
        cols.append(as_numpy(normals, np.float64).reshape(len(v), 3))
    if colors is not None:
        props += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        c = as_numpy(colors, np.float64).reshape(len(v), 3)
        cols.append(np.clip(np.round(c * 255), 0, 255))
    if uvs is not None:
        props += [("texture_u", "f4"), ("texture_v", "f4")]
        cols.append(as_numpy(uvs, np.float64).reshape(len(v), 2))
    vdtype = np.dtype([(n, "<" + t) for n, t in props])
    vrec = np.empty(len(v), dtype=vdtype)
    flat = np.concatenate(cols, axis=1)
    for i, (n, _) in enumerate(props):
        vrec[n] = flat[:, i]
    frec = np.empty(len(f), dtype=np.dtype([("n", "u1"), ("idx", "<i4", (3,))]))
    frec["n"] = 3
    frec["idx"] = f
    ply_types = {"f4": "float", "u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0"]
    if texture_file is not None:
        header.append(f"comment TextureFile {texture_file}")
    header.append(f"element vertex {len(v)}")
    header += [f"property {ply_types[t]} {n}" for n, t in props]
    header += [f"element face {len(f)}", "property list uchar int vertex_indices", "end_header"]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as out:
        out.write(("\n".join(header) + "\n").encode("ascii"))
        out.write(vrec.tobytes())
        out.write(frec.tobytes())


def _bbox(mask: np.ndarray) -> tuple[int, int, int, int]:
    ys, xs = np.nonzero(mask)
    if ys.size == 0:
        return (-1, -1, -1, -1)
    x0, y0 = int(xs.min()), int(ys.min())
    return (x0, y0, int(xs.max()) - x0 + 1, int(ys.max()) - y0 + 1)


def compute_gt_info(
    mask: torch.Tensor | np.ndarray,
    mask_visib: torch.Tensor | np.ndarray,
    depth: torch.Tensor | np.ndarray | None = None,
) -> GTInfo:
    """Compute an instance's ``scene_gt_info`` entry from its full and visible masks.

    ``visib_fract = px_count_visib / px_count_all`` (0 when the full mask is empty); pixels are
    counted inside the image. ``px_count_valid`` counts full-mask pixels with a measured depth.

    Args:
        mask: full silhouette ``(H, W)`` bool.
        mask_visib: visible part ``(H, W)`` bool.
        depth: optional depth ``(H, W)`` (metres, 0 = missing); without it every pixel is valid.

    Example:
        >>> m = torch.zeros(4, 4, dtype=torch.bool); m[1:3, 1:3] = True
        >>> v = m.clone(); v[1, 1] = False
        >>> compute_gt_info(m, v).visib_fract
        0.75
    """
    m = as_numpy(mask).astype(bool)
    mv = as_numpy(mask_visib).astype(bool)
    if m.shape != mv.shape:
        raise ShapeError(f"mask {m.shape} and mask_visib {mv.shape} differ in shape")
    n_all, n_vis = int(m.sum()), int(mv.sum())
    if depth is None:
        n_valid = n_all
    else:
        d = as_numpy(depth, np.float64)
        n_valid = int((m & np.isfinite(d) & (d > 0)).sum())
    return GTInfo(
        bbox_obj=_bbox(m),
        bbox_visib=_bbox(mv),
        px_count_all=n_all,
        px_count_valid=n_valid,
        px_count_visib=n_vis,
        visib_fract=n_vis / n_all if n_all else 0.0,
    )


class BOPWriter:
    """Write images and annotations of one split in the BOP format.

    Images are written at once; the scene JSON files (``scene_camera``, ``scene_gt``,
    ``scene_gt_info``) are accumulated and written by :meth:`flush` (called on leaving a ``with``
    block). Existing JSON entries of a scene are kept, so a split can be written in several runs.

    Args:
        root: dataset folder.
        split: split folder name.
        image_ext: ``".png"`` or ``".jpg"`` for colour images.
        depth_scale: default millimetres per depth unit (0.1 keeps 0.1 mm resolution up to 6.5 m).

    Example:
        >>> import tempfile
        >>> root = tempfile.mkdtemp()
        >>> with BOPWriter(root, "test") as w:
        ...     w.add_image(3, 7, K=torch.eye(3), depth=torch.full((4, 5), 0.5),
        ...                 obj_ids=[2], poses=torch.eye(4)[None],
        ...                 masks=torch.ones(1, 4, 5, dtype=torch.bool),
        ...                 masks_visib=torch.ones(1, 4, 5, dtype=torch.bool))
        >>> read_scene_gt(f"{root}/test/000003/scene_gt.json")[7][0].obj_id
        2
    """

    def __init__(
        self,
        root: str | Path,
        split: str,
        *,
        image_ext: str = ".png",
        depth_scale: float = 0.1,
    ) -> None:
        if image_ext not in (".png", ".jpg"):
            raise ValueRangeError(f"image_ext must be '.png' or '.jpg', got {image_ext!r}")
        if not depth_scale > 0:
            raise ValueRangeError(f"depth_scale must be positive, got {depth_scale}")
        self.root = Path(root)
        self.split_path = self.root / split
        self.image_ext = image_ext
        self.depth_scale = depth_scale
        self._camera: dict[int, dict[int, CameraInfo]] = {}
        self._gt: dict[int, dict[int, list[GTPose]]] = {}
        self._gt_info: dict[int, dict[int, list[GTInfo]]] = {}

    def scene_path(self, scene_id: int) -> Path:
        """Folder of ``scene_id``."""
        return self.split_path / f"{scene_id:06d}"

    def add_image(
        self,
        scene_id: int,
        im_id: int,
        *,
        K: torch.Tensor | np.ndarray,
        rgb: torch.Tensor | np.ndarray | None = None,
        depth: torch.Tensor | np.ndarray | None = None,
        obj_ids: Sequence[int] | torch.Tensor = (),
        poses: torch.Tensor | np.ndarray | None = None,
        masks: torch.Tensor | np.ndarray | None = None,
        masks_visib: torch.Tensor | np.ndarray | None = None,
        depth_scale: float | None = None,
        R_w2c: torch.Tensor | np.ndarray | None = None,
        t_w2c: torch.Tensor | np.ndarray | None = None,
    ) -> None:
        """Write one image with its instances.

        Args:
            scene_id: scene id.
            im_id: image id.
            K: intrinsics ``(3, 3)``.
            rgb: colour image, float ``(3, H, W)`` in ``[0, 1]`` or uint8 ``(H, W, 3)``.
            depth: depth ``(H, W)`` in metres (0 or NaN = missing).
            obj_ids: object id of each instance, ``n`` of them.
            poses: ``(n, 4, 4)`` model-to-camera, metres.
            masks: ``(n, H, W)`` full silhouettes (``mask/``).
            masks_visib: ``(n, H, W)`` visible parts (``mask_visib/``).
            depth_scale: millimetres per depth unit for this image (default: the writer's).
            R_w2c: optional world-to-camera rotation ``(3, 3)``.
            t_w2c: optional world-to-camera translation ``(3,)``, metres.

        ``scene_gt_info`` is computed from the masks (and depth) when both mask stacks are given.
        """
        ids = [int(o) for o in (obj_ids.tolist() if isinstance(obj_ids, torch.Tensor) else obj_ids)]
        n = len(ids)
        P = np.zeros((0, 4, 4)) if poses is None else as_numpy(poses, np.float64).reshape(-1, 4, 4)
        if len(P) != n:
            raise ShapeError(f"{n} obj_ids but {len(P)} poses for scene {scene_id} image {im_id}")
        for name, m in (("masks", masks), ("masks_visib", masks_visib)):
            if m is not None and len(m) != n:
                raise ShapeError(
                    f"{n} obj_ids but {len(m)} {name} for scene {scene_id} image {im_id}"
                )
        scale = self.depth_scale if depth_scale is None else depth_scale
        sp = self.scene_path(scene_id)
        name = f"{im_id:06d}"
        if rgb is not None:
            write_image(sp / "rgb" / f"{name}{self.image_ext}", rgb)
        if depth is not None:
            write_depth(sp / "depth" / f"{name}.png", depth, scale)
        for i in range(n):
            if masks is not None:
                write_mask(sp / "mask" / f"{name}_{i:06d}.png", masks[i])
            if masks_visib is not None:
                write_mask(sp / "mask_visib" / f"{name}_{i:06d}.png", masks_visib[i])
        self._camera.setdefault(scene_id, {})[im_id] = CameraInfo(
            K=as_numpy(K, np.float64).reshape(3, 3),
            depth_scale=float(scale),
            R_w2c=None if R_w2c is None else as_numpy(R_w2c, np.float64).reshape(3, 3),
            t_w2c=None if t_w2c is None else as_numpy(t_w2c, np.float64).reshape(3),
        )
        self._gt.setdefault(scene_id, {})[im_id] = [GTPose(o, T) for o, T in zip(ids, P)]
        if masks is not None and masks_visib is not None:
            d = None if depth is None else as_numpy(depth, np.float64)
            self._gt_info.setdefault(scene_id, {})[im_id] = [
                compute_gt_info(masks[i], masks_visib[i], d) for i in range(n)
            ]

    def flush(self) -> None:
        """Write (merging with existing files) the scene JSON files accumulated so far."""
        for scene_id in sorted(set(self._camera) | set(self._gt) | set(self._gt_info)):
            sp = self.scene_path(scene_id)
            for fname, reader, writer, store in (
                ("scene_camera.json", read_scene_camera, write_scene_camera, self._camera),
                ("scene_gt.json", read_scene_gt, write_scene_gt, self._gt),
                ("scene_gt_info.json", read_scene_gt_info, write_scene_gt_info, self._gt_info),
            ):
                new = store.get(scene_id)
                if not new:
                    continue
                p = sp / fname
                merged: dict[int, Any] = dict(reader(p)) if p.is_file() else {}
                merged.update(new)
                writer(p, merged)
        self._camera.clear()
        self._gt.clear()
        self._gt_info.clear()

    def __enter__(self) -> BOPWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.flush()
