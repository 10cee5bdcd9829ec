"""Lazy, indexable readers of a BOP split for :class:`torch.utils.data.DataLoader`."""

from __future__ import annotations

import warnings
from collections.abc import Iterable, Mapping, Sequence
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import torch

from poseflow.data.bop.images import read_depth, read_image, read_mask
from poseflow.data.bop.json_io import (
    read_detections,
    read_models_info,
    read_scene_camera,
    read_scene_gt,
    read_scene_gt_info,
    read_test_targets,
)
from poseflow.data.bop.records import (
    BOPDataWarning,
    CameraInfo,
    Detection,
    GTInfo,
    GTPose,
    ModelInfo,
    TestTarget,
)
from poseflow.errors import BOPFormatError, MissingFileError, ShapeError

__all__ = [
    "BOPDataset",
    "BOPDetectionDataset",
    "BOPImageDataset",
    "BOPInstanceDataset",
    "BOPScene",
    "collate_images",
]


def _find_first(paths: Iterable[Path]) -> Path | None:
    for p in paths:
        if p.is_file():
            return p
    return None


def _validity(
    mask: torch.Tensor, depth: torch.Tensor | None, min_valid_pixels: int, what: str
) -> tuple[bool, int]:
    """Count valid depth pixels in a mask; warn and return False when too few."""
    if depth is None:
        n = int(mask.sum())
    else:
        n = int((mask & torch.isfinite(depth) & (depth > 0)).sum())
    if int(mask.sum()) == 0:
        warnings.warn(f"{what}: empty mask; instance flagged invalid", BOPDataWarning, stacklevel=3)
        return False, n
    if n < min_valid_pixels:
        warnings.warn(
            f"{what}: only {n} pixels of the mask have a valid (finite, non-zero) depth, fewer "
            f"than min_valid_pixels={min_valid_pixels}; instance flagged invalid",
            BOPDataWarning,
            stacklevel=3,
        )
        return False, n
    return True, n


class BOPScene(torch.utils.data.Dataset):
    """One scene folder, read lazily; ``scene[i]`` is the sample of its ``i``-th image.

    Args:
        path: the scene folder (``.../test/000002``).
        load_rgb: include ``rgb`` in samples.
        load_depth: include ``depth`` in samples.
        load_masks: include ``masks`` and ``masks_visib`` in samples (needs ``mask/`` and
            ``mask_visib/``).
        min_valid_pixels: an instance whose visible mask holds fewer valid depth pixels is flagged
            invalid (``valid`` False) with a :class:`BOPDataWarning`.
        check_depth_units: raise when a depth map is clearly in metres (see :func:`read_depth`).
        dtype: floating dtype of the returned tensors.

    Image samples are dicts with ``scene_id``, ``im_id`` (int), ``K`` ``(3, 3)``, ``rgb``
    ``(3, H, W)`` in ``[0, 1]``, ``depth`` ``(H, W)`` metres (0 = missing), ``obj_ids`` ``(n,)``,
    ``poses`` ``(n, 4, 4)`` model-to-camera in metres, ``visib_fract`` ``(n,)``, ``masks`` and
    ``masks_visib`` ``(n, H, W)`` bool, and ``valid`` ``(n,)`` bool.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        load_rgb: bool = True,
        load_depth: bool = True,
        load_masks: bool = True,
        min_valid_pixels: int = 16,
        check_depth_units: bool = True,
        dtype: torch.dtype = torch.float32,
    ) -> None:
        self.path = Path(path)
        if not self.path.is_dir():
            raise MissingFileError(f"missing BOP scene folder {self.path}")
        try:
            self.scene_id = int(self.path.name)
        except ValueError as exc:
            raise BOPFormatError(f"{self.path}: a scene folder is named by its id") from exc
        self.load_rgb = load_rgb
        self.load_depth = load_depth
        self.load_masks = load_masks
        self.min_valid_pixels = min_valid_pixels
        self.check_depth_units = check_depth_units
        self.dtype = dtype

    @cached_property
    def camera(self) -> dict[int, CameraInfo]:
        """``{im_id: CameraInfo}`` from ``scene_camera.json``."""
        return read_scene_camera(self.path / "scene_camera.json")

    @cached_property
    def gt(self) -> dict[int, list[GTPose]]:
        """``{im_id: [GTPose]}`` from ``scene_gt.json``; empty when the file is absent."""
        p = self.path / "scene_gt.json"
        return read_scene_gt(p) if p.is_file() else {}

    @cached_property
    def gt_info(self) -> dict[int, list[GTInfo]]:
        """``{im_id: [GTInfo]}`` from ``scene_gt_info.json``; empty when the file is absent."""
        p = self.path / "scene_gt_info.json"
        return read_scene_gt_info(p) if p.is_file() else {}

    @property
    def im_ids(self) -> list[int]:
        """Sorted image ids of the scene (the keys of ``scene_camera.json``)."""
        return sorted(self.camera)

    def __len__(self) -> int:
        return len(self.camera)

    def __getitem__(self, index: int) -> dict[str, Any]:
        ids = self.im_ids
        if not -len(ids) <= index < len(ids):
            raise IndexError(f"scene {self.scene_id} has {len(ids)} images, index {index}")
        return self.image_sample(ids[index])

    def _where(self, im_id: int, gt_idx: int | None = None) -> str:
        s = f"scene {self.scene_id} image {im_id}"
        return s if gt_idx is None else f"{s} instance {gt_idx}"

    def _cam(self, im_id: int) -> CameraInfo:
        if im_id not in self.camera:
            raise BOPFormatError(
                f"{self.path / 'scene_camera.json'}: no entry for {self._where(im_id)}"
            )
        return self.camera[im_id]

    def gt_of(self, im_id: int) -> list[GTPose]:
        """Ground-truth instances of an image (raises when the scene has GT but not this image)."""
        if not self.gt:
            return []
        if im_id not in self.gt:
            raise BOPFormatError(
                f"{self.path / 'scene_gt.json'}: no entry for {self._where(im_id)}"
            )
        return self.gt[im_id]

    def rgb_path(self, im_id: int) -> Path:
        """Path of the colour (or grey) image of ``im_id``."""
        name = f"{im_id:06d}"
        p = _find_first(
            self.path / folder / f"{name}{ext}"
            for folder in ("rgb", "gray")
            for ext in (".png", ".jpg", ".jpeg", ".tif")
        )
        if p is None:
            raise MissingFileError(
                f"missing image for {self._where(im_id)}: no {name}.png/.jpg in "
                f"{self.path / 'rgb'} or {self.path / 'gray'}"
            )
        return p

    def depth_path(self, im_id: int) -> Path:
        """Path of the depth PNG of ``im_id``."""
        p = _find_first(self.path / "depth" / f"{im_id:06d}{e}" for e in (".png", ".tif"))
        if p is None:
            want = self.path / "depth" / f"{im_id:06d}.png"
            raise MissingFileError(f"missing depth for {self._where(im_id)}: {want}")
        return p

    def mask_path(self, im_id: int, gt_idx: int, *, visible: bool = True) -> Path:
        """Path of the (visible) mask PNG of instance ``gt_idx`` of ``im_id``."""
        folder = "mask_visib" if visible else "mask"
        return self.path / folder / f"{im_id:06d}_{gt_idx:06d}.png"

    def load_rgb_image(self, im_id: int) -> torch.Tensor:
        """Colour image ``(3, H, W)`` in ``[0, 1]``."""
        return read_image(self.rgb_path(im_id)).to(self.dtype)

    def load_depth_image(self, im_id: int) -> torch.Tensor:
        """Depth ``(H, W)`` in metres (0 = missing)."""
        cam = self._cam(im_id)
        return read_depth(
            self.depth_path(im_id), cam.depth_scale, check_units=self.check_depth_units
        ).to(self.dtype)

    def load_mask(self, im_id: int, gt_idx: int, *, visible: bool = True) -> torch.Tensor:
        """Mask ``(H, W)`` bool of instance ``gt_idx``."""
        p = self.mask_path(im_id, gt_idx, visible=visible)
        if not p.is_file():
            raise MissingFileError(f"missing mask for {self._where(im_id, gt_idx)}: {p}")
        return read_mask(p)

    def _check_sizes(
        self,
        im_id: int,
        shape: tuple[int, ...],
        rgb: torch.Tensor | None,
        masks: Sequence[torch.Tensor],
        visib: Sequence[torch.Tensor],
        from_depth: bool,
    ) -> None:
        """Raise a :class:`ShapeError` naming both files where an image's files differ in size."""
        ref = (
            str(self.depth_path(im_id))
            if from_depth
            else str(self.mask_path(im_id, 0, visible=False))
        )
        H, W = shape
        named = [(m, self.mask_path(im_id, i, visible=False)) for i, m in enumerate(masks)]
        named += [(m, self.mask_path(im_id, i, visible=True)) for i, m in enumerate(visib)]
        if rgb is not None:
            named.insert(0, (rgb, self.rgb_path(im_id)))
        for x, path in named:
            if tuple(x.shape[-2:]) != (H, W):
                raise ShapeError(
                    f"{self._where(im_id)}: {path} is {x.shape[-1]}x{x.shape[-2]} but {ref} is "
                    f"{W}x{H}"
                )

    def image_sample(self, im_id: int) -> dict[str, Any]:
        """The sample of image ``im_id`` (see the class docstring for its keys)."""
        cam = self._cam(im_id)
        gts = self.gt_of(im_id)
        infos = self.gt_info.get(im_id, [])
        n = len(gts)
        out: dict[str, Any] = {
            "scene_id": self.scene_id,
            "im_id": im_id,
            "K": torch.as_tensor(cam.K, dtype=self.dtype),
            "obj_ids": torch.tensor([g.obj_id for g in gts], dtype=torch.long),
            "poses": torch.as_tensor(
                np.stack([g.pose for g in gts]) if n else np.zeros((0, 4, 4)), dtype=self.dtype
            ),
        }
        depth = self.load_depth_image(im_id) if self.load_depth else None
        if self.load_rgb:
            out["rgb"] = self.load_rgb_image(im_id)
        if depth is not None:
            out["depth"] = depth
        valid = torch.ones(n, dtype=torch.bool)
        if self.load_masks:
            masks = [self.load_mask(im_id, i, visible=False) for i in range(n)]
            visib = [self.load_mask(im_id, i, visible=True) for i in range(n)]
            shape = depth.shape if depth is not None else (masks[0].shape if n else (0, 0))
            self._check_sizes(im_id, shape, out.get("rgb"), masks, visib, depth is not None)
            out["masks"] = torch.stack(masks) if n else torch.zeros(0, *shape, dtype=torch.bool)
            out["masks_visib"] = torch.stack(visib) if n else torch.zeros_like(out["masks"])
            for i, m in enumerate(visib):
                valid[i], _ = _validity(m, depth, self.min_valid_pixels, self._where(im_id, i))
        if infos and len(infos) != n:
            raise BOPFormatError(
                f"{self.path / 'scene_gt_info.json'}: {self._where(im_id)} has {len(infos)} "
                f"entries but scene_gt.json has {n}"
            )
        out["visib_fract"] = torch.tensor(
            [i.visib_fract for i in infos] if infos else [1.0] * n, dtype=self.dtype
        )
        out["valid"] = valid
        return out


def collate_images(batch: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Collate image samples with different instance counts, padding to the largest.

    Per-instance entries (``obj_ids``, ``poses``, ``visib_fract``, ``masks``, ``masks_visib``,
    ``valid``) are padded along a new instance dimension ``n_max`` (``obj_ids`` with -1, poses with
    the identity, ``valid`` with False) and ``instance_mask`` ``(B, n_max)`` says which entries are
    real; everything else is stacked by :func:`torch.utils.data.default_collate`.

    Example:
        >>> a = {"im_id": 0, "obj_ids": torch.tensor([1, 2]), "poses": torch.eye(4).repeat(2, 1, 1),
        ...      "valid": torch.tensor([True, True])}
        >>> b = {"im_id": 1, "obj_ids": torch.tensor([5]), "poses": torch.eye(4)[None],
        ...      "valid": torch.tensor([True])}
        >>> out = collate_images([a, b])
        >>> out["obj_ids"].tolist(), out["instance_mask"].tolist()
        ([[1, 2], [5, -1]], [[True, True], [True, False]])
    """
    per_instance = {"obj_ids", "poses", "visib_fract", "masks", "masks_visib", "valid"}
    counts = [len(s["obj_ids"]) for s in batch]
    n_max = max(counts, default=0)
    out = torch.utils.data.default_collate(
        [{k: v for k, v in s.items() if k not in per_instance} for s in batch]
    )
    for key in per_instance & set(batch[0]):
        items = [s[key] for s in batch]
        first = items[0]
        pad_shape = (len(batch), n_max, *first.shape[1:])
        if key == "obj_ids":
            padded = torch.full(pad_shape, -1, dtype=first.dtype)
        elif key == "poses":
            padded = torch.eye(4, dtype=first.dtype).expand(pad_shape).clone()
        else:
            padded = torch.zeros(pad_shape, dtype=first.dtype)
        for b, x in enumerate(items):
            padded[b, : len(x)] = x
        out[key] = padded
    out["instance_mask"] = torch.arange(n_max)[None] < torch.tensor(counts)[:, None]
    return out


class BOPDataset:
    """A BOP dataset folder: scenes of one split, object models and targets, all read lazily.

    Args:
        root: the dataset folder (holding ``models/`` and the split folders).
        split: split folder name, e.g. ``"test"``, ``"train_pbr"``, ``"test_primesense"``.
        **scene_kwargs: passed to every :class:`BOPScene` (``load_rgb``, ``min_valid_pixels``, ...).

    Raises:
        MissingFileError: ``root`` or the split folder does not exist.

    Example:
        >>> import tempfile
        >>> from poseflow.data.bop import BOPWriter
        >>> root = tempfile.mkdtemp()
        >>> with BOPWriter(root, "test") as w:
        ...     w.add_image(1, 0, K=torch.eye(3), depth=torch.full((4, 5), 0.5))
        >>> ds = BOPDataset(root, "test", load_rgb=False, load_masks=False)
        >>> ds.scene_ids, ds.scene(1)[0]["depth"].shape
        ([1], torch.Size([4, 5]))
    """

    def __init__(self, root: str | Path, split: str = "test", **scene_kwargs: Any) -> None:
        self.root = Path(root)
        self.split = split
        self.split_path = self.root / split
        if not self.split_path.is_dir():
            raise MissingFileError(f"missing BOP split folder {self.split_path}")
        self.scene_kwargs = scene_kwargs
        self._scenes: dict[int, BOPScene] = {}

    @cached_property
    def scene_ids(self) -> list[int]:
        """Sorted ids of the scene folders of the split."""
        return sorted(
            int(p.name) for p in self.split_path.iterdir() if p.is_dir() and p.name.isdigit()
        )

    def scene(self, scene_id: int) -> BOPScene:
        """The :class:`BOPScene` of ``scene_id`` (cached)."""
        if scene_id not in self._scenes:
            self._scenes[scene_id] = BOPScene(
                self.split_path / f"{scene_id:06d}", **self.scene_kwargs
            )
        return self._scenes[scene_id]

    def models_info(self, *, eval_models: bool = False) -> dict[int, ModelInfo]:
        """``models_info.json`` of ``models/`` (or ``models_eval/``), in metres."""
        folder = "models_eval" if eval_models else "models"
        return read_models_info(self.root / folder / "models_info.json")

    def model_path(self, obj_id: int, *, eval_models: bool = False) -> Path:
        """Path of the PLY of ``obj_id`` (``models_eval/`` is what BOP evaluation uses)."""
        folder = "models_eval" if eval_models else "models"
        p = self.root / folder / f"obj_{obj_id:06d}.ply"
        if not p.is_file():
            raise MissingFileError(f"missing model of obj {obj_id}: {p}")
        return p

    def test_targets(self, name: str = "test_targets_bop19.json") -> list[TestTarget]:
        """Targets of the BOP challenge (``test_targets_bop19.json`` in ``root``)."""
        return read_test_targets(self.root / name)


def _image_index(
    dataset: BOPDataset, scene_ids: Sequence[int] | None, targets: Sequence[TestTarget] | None
) -> list[tuple[int, int]]:
    if targets is not None:
        keys = sorted({(t.scene_id, t.im_id) for t in targets})
        return [k for k in keys if scene_ids is None or k[0] in scene_ids]
    ids = dataset.scene_ids if scene_ids is None else list(scene_ids)
    return [(s, i) for s in ids for i in dataset.scene(s).im_ids]


def _targets(root: Path, targets: bool | str | Path | Sequence[TestTarget] | None) -> Any:
    if targets is None or targets is False:
        return None
    if targets is True:
        return read_test_targets(root / "test_targets_bop19.json")
    if isinstance(targets, (str, Path)):
        p = Path(targets)
        return read_test_targets(p if p.is_absolute() or p.exists() else root / p)
    return list(targets)


class BOPImageDataset(torch.utils.data.Dataset):
    """Every image of a BOP split (optionally only those named by the test targets).

    Batch with ``DataLoader(ds, collate_fn=collate_images)``.

    Args:
        root: dataset folder.
        split: split folder name.
        scene_ids: restrict to these scenes.
        targets: ``True`` for ``test_targets_bop19.json``, a path, or a list of
            :class:`TestTarget`: keep only the images they name.
        **scene_kwargs: see :class:`BOPScene`.
    """

    def __init__(
        self,
        root: str | Path,
        split: str = "test",
        *,
        scene_ids: Sequence[int] | None = None,
        targets: bool | str | Path | Sequence[TestTarget] | None = None,
        **scene_kwargs: Any,
    ) -> None:
        self.dataset = BOPDataset(root, split, **scene_kwargs)
        self.index = _image_index(self.dataset, scene_ids, _targets(self.dataset.root, targets))

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, i: int) -> dict[str, Any]:
        scene_id, im_id = self.index[i]
        return self.dataset.scene(scene_id).image_sample(im_id)


def _instance_sample(
    scene: BOPScene,
    im_id: int,
    mask: torch.Tensor,
    what: str,
) -> dict[str, Any]:
    cam = scene._cam(im_id)
    out: dict[str, Any] = {
        "scene_id": scene.scene_id,
        "im_id": im_id,
        "K": torch.as_tensor(cam.K, dtype=scene.dtype),
    }
    depth = scene.load_depth_image(im_id) if scene.load_depth else None
    if scene.load_rgb:
        out["rgb"] = scene.load_rgb_image(im_id)
    if depth is not None:
        out["depth"] = depth
        if depth.shape != mask.shape:
            warnings.warn(
                f"{what}: mask {tuple(mask.shape)} and depth {tuple(depth.shape)} differ in size; "
                "instance flagged invalid",
                BOPDataWarning,
                stacklevel=3,
            )
            out["mask"] = torch.zeros(depth.shape, dtype=torch.bool)
            out["valid"], out["num_valid_pixels"] = False, 0
            return out
    out["mask"] = mask
    out["valid"], out["num_valid_pixels"] = _validity(mask, depth, scene.min_valid_pixels, what)
    return out


class BOPInstanceDataset(torch.utils.data.Dataset):
    """Every ground-truth object instance of a BOP split, one per item.

    Items are dicts with ``scene_id``, ``im_id``, ``gt_idx``, ``obj_id`` (int), ``K`` ``(3, 3)``,
    ``rgb`` ``(3, H, W)``, ``depth`` ``(H, W)`` metres, ``mask`` ``(H, W)`` bool (the visible
    mask), ``mask_full`` ``(H, W)``, ``pose`` ``(4, 4)`` model-to-camera in metres,
    ``visib_fract``, ``valid`` (bool) and ``num_valid_pixels``. An item whose mask is empty or holds
    fewer than ``min_valid_pixels`` valid depth pixels has ``valid`` False (with a warning).

    Args:
        root: dataset folder.
        split: split folder name.
        scene_ids: restrict to these scenes.
        obj_ids: restrict to these objects.
        targets: keep only instances of the (image, object) pairs of the test targets (see
            :class:`BOPImageDataset`).
        min_visib_fract: skip instances less visible than this (needs ``scene_gt_info.json``);
            decided from the JSON, without reading images.
        **scene_kwargs: see :class:`BOPScene`.
    """

    def __init__(
        self,
        root: str | Path,
        split: str = "test",
        *,
        scene_ids: Sequence[int] | None = None,
        obj_ids: Sequence[int] | None = None,
        targets: bool | str | Path | Sequence[TestTarget] | None = None,
        min_visib_fract: float = 0.0,
        **scene_kwargs: Any,
    ) -> None:
        self.dataset = BOPDataset(root, split, **scene_kwargs)
        tg = _targets(self.dataset.root, targets)
        wanted = None if tg is None else {(t.scene_id, t.im_id, t.obj_id) for t in tg}
        self.index: list[tuple[int, int, int]] = []
        for scene_id, im_id in _image_index(self.dataset, scene_ids, tg):
            scene = self.dataset.scene(scene_id)
            infos = scene.gt_info.get(im_id, [])
            for gt_idx, g in enumerate(scene.gt_of(im_id)):
                if obj_ids is not None and g.obj_id not in obj_ids:
                    continue
                if wanted is not None and (scene_id, im_id, g.obj_id) not in wanted:
                    continue
                if min_visib_fract > 0 and infos and infos[gt_idx].visib_fract < min_visib_fract:
                    continue
                self.index.append((scene_id, im_id, gt_idx))

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, i: int) -> dict[str, Any]:
        scene_id, im_id, gt_idx = self.index[i]
        scene = self.dataset.scene(scene_id)
        gt = scene.gt_of(im_id)[gt_idx]
        mask = scene.load_mask(im_id, gt_idx, visible=True)
        out = _instance_sample(scene, im_id, mask, scene._where(im_id, gt_idx))
        out["mask_full"] = scene.load_mask(im_id, gt_idx, visible=False)
        infos = scene.gt_info.get(im_id, [])
        out["gt_idx"] = gt_idx
        out["obj_id"] = gt.obj_id
        out["pose"] = torch.as_tensor(gt.pose, dtype=scene.dtype)
        out["visib_fract"] = float(infos[gt_idx].visib_fract) if infos else 1.0
        return out


class BOPDetectionDataset(torch.utils.data.Dataset):
    """Instances given by detection/segmentation results (e.g. public ZebraPose/CNOS masks).

    Items are dicts with ``scene_id``, ``im_id``, ``det_idx``, ``obj_id``, ``score``, ``bbox``
    ``(4,)`` ``(x, y, w, h)``, ``K``, ``rgb``, ``depth``, ``mask`` (the decoded segmentation,
    ``(H, W)`` bool), ``valid`` and ``num_valid_pixels``. A detection whose mask is empty, has the
    wrong size or covers too few valid depth pixels is flagged invalid (with a warning).

    Args:
        root: dataset folder.
        split: split folder name.
        detections: a results file path or a list of :class:`Detection`.
        score_threshold: drop detections scoring below this.
        targets: keep only detections of (image, object) pairs in the test targets, at most
            ``inst_count`` per pair (the best scoring), as the BOP challenge does.
        **scene_kwargs: see :class:`BOPScene`.

    Raises:
        BOPFormatError: a detection names a scene or image the split does not have.
    """

    def __init__(
        self,
        root: str | Path,
        split: str,
        detections: str | Path | Sequence[Detection],
        *,
        score_threshold: float = 0.0,
        targets: bool | str | Path | Sequence[TestTarget] | None = None,
        **scene_kwargs: Any,
    ) -> None:
        self.dataset = BOPDataset(root, split, **scene_kwargs)
        dets = read_detections(detections) if isinstance(detections, (str, Path)) else detections
        dets = [d for d in dets if d.score >= score_threshold]
        tg = _targets(self.dataset.root, targets)
        if tg is not None:
            budget = {(t.scene_id, t.im_id, t.obj_id): t.inst_count for t in tg}
            kept = []
            for d in sorted(dets, key=lambda d: -d.score):
                key = (d.scene_id, d.im_id, d.obj_id)
                if budget.get(key, 0) > 0:
                    budget[key] -= 1
                    kept.append(d)
            dets = kept
        scenes = set(self.dataset.scene_ids)
        for d in dets:
            if d.scene_id not in scenes:
                raise BOPFormatError(
                    f"detection of obj {d.obj_id} names scene {d.scene_id} image {d.im_id}, but "
                    f"{self.dataset.split_path} has no scene {d.scene_id}"
                )
            if d.im_id not in self.dataset.scene(d.scene_id).camera:
                raise BOPFormatError(
                    f"detection of obj {d.obj_id} names scene {d.scene_id} image {d.im_id}, which "
                    "is not in its scene_camera.json"
                )
        self.detections = sorted(dets, key=lambda d: (d.scene_id, d.im_id, -d.score))

    def __len__(self) -> int:
        return len(self.detections)

    def __getitem__(self, i: int) -> dict[str, Any]:
        d = self.detections[i]
        scene = self.dataset.scene(d.scene_id)
        what = f"scene {d.scene_id} image {d.im_id} detection {i} (obj {d.obj_id})"
        try:
            mask = d.mask()
        except BOPFormatError as exc:
            warnings.warn(f"{exc}; instance flagged invalid", BOPDataWarning, stacklevel=2)
            mask = torch.zeros(0, 0, dtype=torch.bool)
        out = _instance_sample(scene, d.im_id, mask, what)
        out["det_idx"] = i
        out["obj_id"] = d.obj_id
        out["score"] = float(d.score)
        out["bbox"] = torch.tensor(d.bbox, dtype=scene.dtype)
        return out
