"""Training FunFlow6D: per-instance flow inputs from BOP images, augmented, then flow matching.

The frozen encoders are the slow part of a training step and do not change during training, so
:func:`build_training_set` runs them once per instance (``copies`` times, each with fresh
augmentations) and stores the flow inputs; :func:`train` then runs
:class:`~poseflow.flows.CFMTrainer` over them (under ``torchrun`` too).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from poseflow._cache import atomic_write
from poseflow._progress import progress as progress_loop
from poseflow._workers import map_forked
from poseflow.data.bop import BOPImageDataset
from poseflow.data.frame import ImageInstances
from poseflow.errors import DegenerateInputError, ValueRangeError
from poseflow.eval.distributed import image_seed
from poseflow.flows import (
    CFMObjective,
    CFMTrainer,
    DistillationObjective,
    TrainConfig,
    get_sampler,
    pad_maps,
)
from poseflow.models.funflow6d import FunFlow6D
from poseflow.models.inputs import OPTIONAL_TRAINING_FIELDS, TRAINING_FIELDS, equivalent_maps

__all__ = ["FlowTrainingSet", "augment", "build_training_set", "train"]


class FlowTrainingSet(torch.utils.data.Dataset):
    """Precomputed flow inputs of training instances, one dict of tensors per item.

    Args:
        tensors: ``{name: (I, ...)}`` for every name of
            :data:`~poseflow.models.inputs.TRAINING_FIELDS` (fields of
            :class:`~poseflow.models.inputs.FlowInputs`), and optionally ``equivalents``
            ``(I, K, 3, 4)`` for symmetric objects; a saved set is stored under these names.
    """

    def __init__(self, tensors: dict[str, torch.Tensor]) -> None:
        missing = [k for k in TRAINING_FIELDS if k not in tensors]
        if missing:
            raise ValueRangeError(f"training tensors lack {missing}")
        sizes = {len(v) for v in tensors.values()}
        if len(sizes) != 1:
            raise ValueRangeError(f"training tensors have different lengths: {sorted(sizes)}")
        names = TRAINING_FIELDS + tuple(k for k in OPTIONAL_TRAINING_FIELDS if k in tensors)
        self.tensors = {k: tensors[k] for k in names}

    def __len__(self) -> int:
        return len(self.tensors["x_1"])

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        return {k: v[i] for k, v in self.tensors.items()}

    def save(self, path: str | Path) -> Path:
        """Write the tensors to one safetensors file."""
        from safetensors.torch import save_file

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tensors = {k: v.contiguous() for k, v in self.tensors.items()}
        return atomic_write(path, lambda tmp: save_file(tensors, tmp))

    @classmethod
    def load(cls, path: str | Path) -> FlowTrainingSet:
        """Read a file written by :meth:`save`."""
        from safetensors.torch import load_file

        return cls(load_file(str(path)))


def augment(
    depth: torch.Tensor,
    masks: torch.Tensor,
    *,
    generator: torch.Generator,
    depth_noise: float = 0.002,
    max_erosion: int = 2,
    mask_noise: float = 0.02,
    occlusion: float = 0.0,
    kept: tuple[float, float] = (0.3, 0.8),
) -> tuple[torch.Tensor, torch.Tensor]:
    """Perturb a training observation the way real sensors, segmenters and clutter do.

    (The fourth augmentation, jitter of the appearance crop, is applied by
    :meth:`FunFlow6D.observe <poseflow.models.FunFlow6D.observe>`'s ``crop_jitter``.)

    Depth gets Gaussian noise (``depth_noise`` metres at 1 m, growing with ``z²``); each mask is
    eroded by a random radius up to ``max_erosion`` pixels and loses a random ``mask_noise``
    fraction of its pixels; with probability ``occlusion`` it is then cut by a straight edge
    in a random direction, as by an object in front, keeping a fraction of its pixels drawn
    uniformly from ``kept``: an instance seen only in part, which generated scenes rarely show
    (most of their instances are over 90 % visible) and real ones often do.

    Args:
        depth: depth ``(H, W)`` metres.
        masks: instance masks ``(B, H, W)`` bool.
        generator: the random generator.
        depth_noise: noise standard deviation at 1 m, metres.
        max_erosion: largest erosion radius, pixels.
        mask_noise: fraction of mask pixels dropped at random.
        occlusion: probability that a mask is cut, in ``[0, 1]``.
        kept: the range of the fraction of its pixels a cut mask keeps, within ``(0, 1]``.

    Returns:
        The perturbed ``(depth, masks)``.

    Example:
        >>> d, m = augment(torch.ones(8, 8), torch.ones(1, 8, 8, dtype=torch.bool),
        ...                generator=torch.Generator().manual_seed(0))
        >>> d.shape, bool(m.sum() < 64)
        (torch.Size([8, 8]), True)
    """
    if not 0.0 <= occlusion <= 1.0 or not 0.0 < kept[0] <= kept[1] <= 1.0:
        raise ValueRangeError(
            f"occlusion must lie in [0, 1] and kept be a range within (0, 1], got {occlusion}, "
            f"{kept}"
        )
    noise = torch.randn(depth.shape, generator=generator).to(depth) * depth_noise * depth.square()
    depth = torch.where(depth > 0, depth + noise, depth)
    out = []
    for m in masks:
        r = int(torch.randint(0, max_erosion + 1, (1,), generator=generator))
        if r:
            k = 2 * r + 1
            m = -F.max_pool2d(-m[None, None].float(), k, stride=1, padding=r)[0, 0] > 0.5
        drop = (torch.rand(m.shape, generator=generator) < mask_noise).to(m.device)
        m = m & ~drop
        if occlusion and float(torch.rand((), generator=generator)) < occlusion:
            m = _cut(m, generator, kept)
        out.append(m)
    return depth, torch.stack(out) if out else masks


def _cut(mask: torch.Tensor, generator: torch.Generator, kept: tuple[float, float]) -> torch.Tensor:
    """``mask`` ``(H, W)`` bool less the pixels beyond a straight edge in a random direction.

    The edge keeps a fraction of the pixels drawn uniformly from ``kept``; an empty mask stays
    empty.
    """
    pixels = mask.nonzero().to(torch.float64)  # (P, 2)
    if len(pixels) == 0:
        return mask
    angle = float(torch.rand((), generator=generator)) * 2 * torch.pi
    fraction = kept[0] + float(torch.rand((), generator=generator)) * (kept[1] - kept[0])
    along = pixels @ torch.tensor([math.cos(angle), math.sin(angle)], dtype=torch.float64)
    count = max(1, round(fraction * len(pixels)))
    keep = along.argsort()[:count]
    out = torch.zeros_like(mask)
    rows, cols = pixels[keep].long().unbind(1)
    out[rows, cols] = True
    return out


@torch.no_grad()
def build_training_set(
    model: FunFlow6D,
    root: str | Path,
    *,
    split: str = "train",
    copies: int = 1,
    crop_jitter: float = 0.1,
    occlusion: float = 0.0,
    min_visib_fract: float = 0.1,
    max_images: int | None = None,
    seed: int = 0,
    symmetries: Mapping[int, torch.Tensor] | None = None,
    workers: int = 1,
    progress: bool = True,
) -> FlowTrainingSet:
    """Run the frozen encoders over the instances of a BOP split.

    With ``symmetries``, the instances of a symmetric object keep the maps to their equivalent
    targets (:func:`~poseflow.models.inputs.equivalent_maps`, identity-padded to the largest
    count), and training pairs each noise draw with the nearest one: a flipped ground truth of
    a symmetric object costs no loss. A set whose objects are all asymmetric stores no maps.

    Every image draws its augmentations and samplings from its own generator, seeded by
    ``seed`` and the image's ids (:func:`~poseflow.eval.distributed.image_seed`), so the set is
    the same whichever ``workers`` build it.

    Args:
        model: the model; the objects of the split must be prepared.
        root: the BOP dataset folder.
        split: the split to read (``train`` for generated data, ``train_pbr`` for BOP's).
        copies: augmented copies of every instance (the first is not augmented).
        crop_jitter: jitter of the appearance crop of the augmented copies (see
            :func:`~poseflow.features.lifting.jitter_boxes`).
        occlusion: the probability that an instance of an augmented copy is seen only in part
            (see :func:`augment`).
        min_visib_fract: skip instances less visible than this.
        max_images: use at most this many images.
        seed: seed of the augmentations and samplings.
        symmetries: ``{obj_id: (S, 4, 4)}`` symmetry transforms in metres, identity included
            (:attr:`~poseflow.data.objects.ObjectModel.symmetries`); None: no equivalents.
        workers: CPU processes of one thread each that take whole images
            (``poseflow._workers.map_forked``); 1: here, on the current threads.
        progress: show a progress bar.

    Returns:
        The :class:`FlowTrainingSet`.

    Raises:
        DegenerateInputError: no usable instance in the split.
    """
    images = BOPImageDataset(root, split)
    count = len(images) if max_images is None else min(max_images, len(images))
    object_maps = None  # (S, 3, 4) per prepared object: its instances share them
    if symmetries is not None:
        identity = torch.eye(4)[None]
        object_maps = {
            oid: equivalent_maps(symmetries.get(oid, identity), obj.diameter / 2).numpy()
            for oid, obj in model.objects.items()
        }

    def image_inputs(i: int) -> tuple[dict[str, list[np.ndarray]], list[np.ndarray]]:
        """The flow inputs ``{field: [(B, ...)] per copy}`` and symmetry maps of image ``i``.

        As numpy arrays: what a worker process returns is pickled back to the parent.
        """
        s = images[i]
        g = torch.Generator().manual_seed(image_seed(seed, s["scene_id"], s["im_id"]))
        parts: dict[str, list[np.ndarray]] = {k: [] for k in TRAINING_FIELDS}
        maps: list[np.ndarray] = []  # (S, 3, 4) per kept instance
        keep = (s["visib_fract"] >= min_visib_fract) & s["valid"]
        keep &= torch.tensor([int(o) in model.objects for o in s["obj_ids"]], dtype=torch.bool)
        if not bool(keep.any()):
            return parts, maps
        for copy in range(copies):
            depth, masks = s["depth"], s["masks_visib"][keep]
            if copy:
                depth, masks = augment(depth, masks, generator=g, occlusion=occlusion)
            image = ImageInstances(s["rgb"], depth, s["K"], masks, s["obj_ids"][keep])
            obs = model.observe(image, generator=g, crop_jitter=crop_jitter if copy else 0.0)
            inputs = model.flow_inputs(obs, s["poses"][keep])
            for k in TRAINING_FIELDS:
                parts[k].append(getattr(inputs, k)[obs.valid].numpy())
            if object_maps is not None:
                maps += [object_maps[int(oid)] for oid in obs.obj_ids[obs.valid].tolist()]
        return parts, maps

    parts: dict[str, list[torch.Tensor]] = {k: [] for k in TRAINING_FIELDS}
    maps: list[torch.Tensor] = []
    outcomes = map_forked(image_inputs, count, workers)
    for image_parts, image_maps in progress_loop(
        outcomes, total=count, desc=f"features of {split}", enabled=progress
    ):
        for k in TRAINING_FIELDS:
            parts[k] += map(torch.from_numpy, image_parts[k])
        maps += map(torch.from_numpy, image_maps)
    if not parts["x_1"] or sum(len(p) for p in parts["x_1"]) == 0:
        raise DegenerateInputError(f"{root}/{split} holds no usable instance of a prepared object")
    tensors = {k: torch.cat(v) for k, v in parts.items()}
    if maps and max(len(m) for m in maps) > 1:
        tensors["equivalents"] = pad_maps(maps, dtype=tensors["x_1"].dtype)
    return FlowTrainingSet(tensors)


def train(
    model: FunFlow6D,
    data: FlowTrainingSet,
    *,
    config: TrainConfig | None = None,
    out_dir: str | Path | None = None,
    resume: bool = False,
    validate: Any = None,
    device: str | torch.device | None = None,
    teacher: FunFlow6D | None = None,
) -> dict[str, float]:
    """Train the model's network by conditional flow matching, or distil a teacher into it.

    With a ``teacher`` (a trained model of the same configuration, usually the one ``model``
    starts from), the network learns to take in one Euler step what the teacher's sampler
    (``teacher.config.solver`` and ``steps``) takes in several
    (:class:`~poseflow.flows.DistillationObjective`); the model is then set to sample so.

    Args:
        model: the model (its network is trained in place; the EMA weights are copied into it
            at the end).
        data: the precomputed training set.
        config: trainer settings.
        out_dir: checkpoints and ``metrics.jsonl`` (None: nothing written).
        resume: continue from the latest checkpoint in ``out_dir``.
        validate: optional validation hook (see :class:`~poseflow.flows.CFMTrainer`).
        device: training device.
        teacher: the model to distil, or None (flow matching).

    Returns:
        The last logged metrics.
    """
    pin_frozen = model.config.anchor == "pinned"
    if teacher is None:
        objective: Any = CFMObjective(
            time_sampler=model.config.time_sampler, pin_frozen=pin_frozen, noise_kwarg="x_0"
        )
    else:
        if teacher is model:
            raise ValueRangeError(
                "the teacher must be another model: copy it (e.g. FunFlow6D.load of its folder)"
            )
        teacher = teacher.eval().requires_grad_(False)
        sampler = get_sampler(teacher.config.solver, steps=teacher.config.steps)
        objective = DistillationObjective(
            teacher, sampler, pin_frozen=pin_frozen, noise_kwarg="x_0"
        )
    trainer = CFMTrainer(
        model,
        data,
        config=config,
        objective=objective,
        validate=validate,
        out_dir=out_dir,
        device=device,
    )
    if teacher is not None:
        teacher.to(trainer.device)
    if resume:
        trainer.resume()
    metrics = trainer.fit()
    model.load_state_dict(trainer.ema_model.state_dict())
    if teacher is not None:
        model.config = model.config.with_inference(steps=1, solver="euler")
    return metrics
