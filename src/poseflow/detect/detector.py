"""The detector of the user's objects: instance masks, object ids and scores from one RGB-D image.

Shape letters: I instances, H/W image rows/columns.

:class:`Detector` wraps :class:`~poseflow.detect.network.InstanceSegmenter`: it resamples the
image to the focal length it was trained at, runs the network, groups the heads into instances
(:func:`~poseflow.detect.grouping.group_instances`) and returns their masks at the image's
resolution. :func:`detect_dataset` runs it over a BOP split and returns BOP detections
(:class:`~poseflow.data.bop.Detection`, COCO-RLE masks), which
:func:`~poseflow.data.bop.write_detections` writes.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from poseflow._progress import progress as progress_loop
from poseflow.data.bop import Detection
from poseflow.data.rle import rle_encode
from poseflow.detect.grouping import Instances, group_instances
from poseflow.detect.network import InstanceSegmenter, detector_inputs, resample_to_focal
from poseflow.errors import CheckpointError, MissingWeightsError, ShapeError, ValueRangeError
from poseflow.features.learned import (
    load_network_weights,
    read_network_config,
    write_network_folder,
)

__all__ = [
    "DETECTOR_FORMAT",
    "DetectedObjects",
    "Detector",
    "DetectorConfig",
    "detect_dataset",
    "mask_box",
]

#: The ``format`` tag of a detector folder's ``config.json``.
DETECTOR_FORMAT = "poseflow-detector"
_HOW_TO_MAKE = "train one with `poseflow train-detector TRAIN_DATASET --out DIR`"


@dataclass
class DetectorConfig:
    """What a detector detects and how.

    Attributes:
        obj_ids: the object ids it tells apart (BOP ids of the training set's models).
        widths: the network's channels at strides 2-32 of its input.
        input_focal: the focal length in pixels every image is resampled to.
        centre_threshold: lowest centre-heatmap peak that makes an instance.
        min_pixels: fewest pixels of an instance's mask at the image's resolution.
    """

    obj_ids: list[int]
    widths: tuple[int, ...] = (24, 32, 48, 64, 96)
    input_focal: float = 290.0
    centre_threshold: float = 0.1
    min_pixels: int = 30

    def __post_init__(self) -> None:
        self.obj_ids = [int(o) for o in self.obj_ids]
        self.widths = tuple(int(c) for c in self.widths)
        if not self.obj_ids or len(set(self.obj_ids)) != len(self.obj_ids):
            raise ValueRangeError(f"obj_ids must be distinct and not empty, got {self.obj_ids}")
        if len(self.widths) != 5 or min(self.widths) < 1:
            raise ValueRangeError(f"widths must be five positive channels, got {self.widths}")
        if self.input_focal <= 0:
            raise ValueRangeError(f"input_focal must be positive, got {self.input_focal}")
        if not 0 < self.centre_threshold < 1:
            raise ValueRangeError(
                f"centre_threshold must be in (0, 1), got {self.centre_threshold}"
            )


@dataclass
class DetectedObjects:
    """The objects found in one image, best score first.

    Attributes:
        obj_ids: object id of each ``(I,)``.
        masks: visible masks ``(I, H, W)`` bool.
        scores: confidences in ``[0, 1]`` ``(I,)``.
        seconds: the detector's wall-clock time on this image.
    """

    obj_ids: torch.Tensor
    masks: torch.Tensor
    scores: torch.Tensor
    seconds: float = field(default=0.0)

    def __len__(self) -> int:
        return len(self.obj_ids)

    def to_detections(self, scene_id: int, im_id: int) -> list[Detection]:
        """BOP detection records with COCO-RLE masks and ``(x, y, w, h)`` boxes."""
        return [
            Detection(
                scene_id,
                im_id,
                int(o),
                float(s),
                mask_box(m),
                rle_encode(m),
                self.seconds,
            )
            for o, m, s in zip(self.obj_ids.tolist(), self.masks, self.scores.tolist())
        ]


def mask_box(mask: torch.Tensor) -> tuple[float, float, float, float]:
    """The ``(x, y, w, h)`` box of a mask's pixels (zeros for an empty mask).

    Example:
        >>> m = torch.zeros(5, 6, dtype=torch.bool); m[1:3, 2:5] = True
        >>> mask_box(m)
        (2.0, 1.0, 3.0, 2.0)
    """
    ys, xs = mask.nonzero(as_tuple=True)
    if len(xs) == 0:
        return (0.0, 0.0, 0.0, 0.0)
    x0, y0 = int(xs.min()), int(ys.min())
    return (float(x0), float(y0), float(int(xs.max()) - x0 + 1), float(int(ys.max()) - y0 + 1))


class Detector(nn.Module):
    """Finds the instances of known objects in an RGB-D image.

    Args:
        config: :class:`DetectorConfig`.

    Example:
        >>> det = Detector(DetectorConfig(obj_ids=[3, 7], widths=(4, 4, 4, 4, 4))).eval()
        >>> found = det.detect(torch.rand(3, 48, 64), torch.ones(48, 64), torch.tensor(
        ...     [[290.0, 0, 32], [0, 290.0, 24], [0, 0, 1]]))
        >>> found.masks.shape[1:], found.masks.dtype
        (torch.Size([48, 64]), torch.bool)
    """

    def __init__(self, config: DetectorConfig) -> None:
        super().__init__()
        self.config = config
        #: How it was trained (:func:`~poseflow.detect.train_detector`'s record), kept on save.
        self.training_record: dict[str, Any] = {}
        self.net = InstanceSegmenter(len(config.obj_ids), widths=config.widths)

    @torch.no_grad()
    def detect(self, rgb: torch.Tensor, depth: torch.Tensor, K: torch.Tensor) -> DetectedObjects:
        """The instances of the detector's objects in one image.

        Args:
            rgb: colour in ``[0, 1]`` (or uint8) ``(3, H, W)``.
            depth: metres, 0 or NaN where missing ``(H, W)``.
            K: intrinsics ``(3, 3)``.

        Returns:
            :class:`DetectedObjects` on the CPU, best score first.

        Raises:
            ShapeError: the shapes disagree.
        """
        start = time.perf_counter()
        if rgb.ndim != 3 or rgb.shape[0] != 3 or depth.shape != rgb.shape[1:]:
            raise ShapeError(
                f"detector: rgb must be (3, H, W) and depth (H, W) of the same size, got "
                f"{tuple(rgb.shape)} and {tuple(depth.shape)}"
            )
        if tuple(K.shape) != (3, 3):
            raise ShapeError(f"detector: K must be (3, 3), got {tuple(K.shape)}")
        param = next(self.net.parameters())
        rgb = rgb.float() / 255 if not rgb.is_floating_point() else rgb.float()
        depth = torch.nan_to_num(depth.float().cpu())
        rgb_s, depth_s = resample_to_focal(
            rgb.cpu(), depth, float(K[1, 1]), self.config.input_focal
        )
        h, w = depth_s.shape
        pad_h, pad_w = -h % 32, -w % 32
        x = detector_inputs(rgb_s[None], depth_s[None], torch.tensor([self.config.input_focal]))
        x = F.pad(x, (0, pad_w, 0, pad_h)).to(param)
        semantic, centres, offsets = (t[0].float().cpu() for t in self.net(x))
        found: Instances = group_instances(
            semantic,
            centres,
            offsets,
            input_size=(h, w),
            image_size=tuple(depth.shape),
            centre_threshold=self.config.centre_threshold,
            min_pixels=self.config.min_pixels,
        )
        ids = torch.tensor(self.config.obj_ids)[found.labels]
        return DetectedObjects(ids, found.masks, found.scores, time.perf_counter() - start)

    def save(self, folder: str | Path, *, training: dict[str, Any] | None = None) -> Path:
        """Write ``config.json`` (the configuration and the training record) and the weights."""
        if training is not None:
            self.training_record = dict(training)
        meta = {"version": 1, "config": _config_json(self.config), "training": self.training_record}
        return write_network_folder(self.net, folder, DETECTOR_FORMAT, meta)

    @classmethod
    def load(cls, folder: str | Path, *, device: str | torch.device = "cpu") -> Detector:
        """Read a folder written by :meth:`save`, in evaluation mode on ``device``.

        Raises:
            MissingWeightsError: the folder or one of its files is missing.
            CheckpointError: a file is corrupt, of another format, or does not fit.
        """
        folder = Path(folder)
        for path in (folder, folder / "config.json", folder / "model.safetensors"):
            if not path.exists():
                raise MissingWeightsError(f"detector: no {path}; {_HOW_TO_MAKE}")
        cfg = read_network_config(folder, DETECTOR_FORMAT, "detector")
        try:
            config = DetectorConfig(**cfg["config"])
        except (KeyError, TypeError, ValueError) as err:
            raise CheckpointError(
                f"{folder / 'config.json'}: bad detector configuration: {err}"
            ) from err
        detector = cls(config)
        detector.training_record = dict(cfg.get("training") or {})
        load_network_weights(detector.net, folder)
        if not all(torch.isfinite(p).all() for p in detector.net.state_dict().values()):
            raise CheckpointError(f"{folder / 'model.safetensors'} holds non-finite weights")
        return detector.eval().to(device)


def _config_json(config: DetectorConfig) -> dict[str, Any]:
    return {**asdict(config), "widths": list(config.widths)}


def detect_dataset(
    detector: Detector,
    root: str | Path,
    split: str = "test",
    *,
    images: Sequence[tuple[int, int]] | None = None,
    max_images: int | None = None,
    progress: bool = True,
) -> list[Detection]:
    """Detect the objects in every image of a BOP split.

    Args:
        detector: the detector.
        root: the BOP dataset folder.
        split: its split.
        images: the ``(scene_id, im_id)`` images to detect (default: all of the split).
        max_images: the first this many of them (default: all).
        progress: show progress.

    Returns:
        BOP detections, by image and best score first; each carries its image's detector time.
    """
    from poseflow.data.bop import BOPDataset

    ds = BOPDataset(root, split)
    if images is None:
        images = [(s, i) for s in ds.scene_ids for i in ds.scene(s).im_ids]
    images = list(images)[:max_images]
    out: list[Detection] = []
    for s, im in progress_loop(images, total=len(images), desc="detect", enabled=progress):
        scene = ds.scene(s)
        K = torch.as_tensor(scene.camera[im].K, dtype=torch.float32)
        found = detector.detect(scene.load_rgb_image(im), scene.load_depth_image(im), K)
        out += found.to_detections(s, im)
    return out
