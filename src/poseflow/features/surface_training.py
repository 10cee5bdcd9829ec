"""Training a :class:`~poseflow.features.surface.SurfaceEmbedding` on renders of the user's objects.

The data is a BOP split with ground-truth poses, visible masks and depth: in the recipe, the
``poseflow synth`` images FunFlow6D trains on (never the test images). :func:`surface_crops`
cuts every visible instance out as FunFlow6D cuts a target (the square around its masked depth's
projection, :func:`~poseflow.geometry.crop_box_around`), resized, with its
:func:`~poseflow.features.learned.depth_layers`, and keeps ``points_per_crop`` of its pixels with
their canonical coordinates (the back-projected depth under the inverse ground-truth pose, in
half diameters).

The loss (:func:`surface_loss`): each sampled pixel's query is scored against the keys of its own
point and of ``negatives`` random points of the object's surface (InfoNCE at ``temperature``),
with a soft target that is Gaussian in the distance between surface points (``sigma`` half
diameters), taken as the smallest over the object's symmetries, so that symmetric points are
not pushed apart. The query network starts from the shipped learned descriptor's weights (the
depth channels from zero) when the package has them.

``precision="bf16"`` (or ``"auto"``: bfloat16 where the CPU multiplies it natively) runs the
query network's products in bfloat16, as FunFlow6D can at use (``appearance_precision``): 1.55
times the steps per second of float32 on one thread, the same loss and inliers, but FunFlow6D
trained on it scored 0.008 and 0.023 AR lower on devbench in two pairs of runs, so the default is
float32 (``benchmarks/surface_precision.py``, ``benchmarks/LOG.md``).

Run ``poseflow train-surface TRAIN_DATASET --out DIR`` (about 20 minutes
on one CPU thread at the default 10,000 steps: a minute for the crops of 1,600 images, 0.12 s a
step); FunFlow6D uses the result with ``appearance_encoder="surface:DIR"``.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import torch

from poseflow._precision import PRECISIONS, autocast_dtype, precision_autocast
from poseflow._progress import progress as progress_loop
from poseflow.errors import DegenerateInputError, ValueRangeError
from poseflow.features.appearance import sample_features
from poseflow.features.descriptor_training import _warmup_cosine
from poseflow.features.learned import SHIPPED_DESCRIPTOR_DIR, depth_layers, load_descriptor
from poseflow.features.surface import SurfaceEmbedding, SurfaceKeys, save_surface_embedding
from poseflow.geometry.crops import crop_box_around, crop_resize, pixels_to_crop
from poseflow.geometry.projection import backproject_depth

__all__ = ["SurfaceCrops", "surface_crops", "surface_loss", "train_surface_embedding"]


@dataclass
class SurfaceCrops:
    """Training crops of visible instances.

    Attributes:
        crops: colour and depth layers ``(M, 5, S, S)`` float16.
        uv: crop pixel of each sampled point ``(M, P, 2)``.
        coords: its canonical coordinates in half diameters ``(M, P, 3)``.
        obj_ids: the object of each crop ``(M,)``.
        surfaces: ``{obj_id: (points (K, 3) in half diameters, symmetries (S, 4, 4) in half
            diameters)}``.
        diameters: ``{obj_id: diameter in metres}``.
    """

    crops: torch.Tensor
    uv: torch.Tensor
    coords: torch.Tensor
    obj_ids: torch.Tensor
    surfaces: dict[int, tuple[torch.Tensor, torch.Tensor]]
    diameters: dict[int, float]


def surface_crops(
    root: str | Path,
    split: str = "train",
    *,
    max_images: int | None = None,
    size: int = 96,
    points_per_crop: int = 128,
    min_pixels: int = 150,
    seed: int = 0,
    progress: bool = True,
) -> SurfaceCrops:
    """The crops of every instance of a BOP split with at least ``min_pixels`` valid pixels.

    Raises:
        DegenerateInputError: no instance has enough pixels.
    """
    from poseflow.data.bop import BOPDataset
    from poseflow.data.object_folder import load_object_models

    ds = BOPDataset(root, split)
    objects = load_object_models(root)
    g = torch.Generator().manual_seed(seed)
    crops, uvs, coords, ids = [], [], [], []
    images = [(s, i) for s in ds.scene_ids for i in ds.scene(s).im_ids][:max_images]
    for s, im in progress_loop(images, total=len(images), desc="crops", enabled=progress):
        scene = ds.scene(s)
        rgb = scene.load_rgb_image(im)
        rgb = rgb.float() if rgb.is_floating_point() else rgb.float() / 255.0
        depth = torch.nan_to_num(scene.load_depth_image(im).float())
        K = torch.as_tensor(scene.camera[im].K, dtype=torch.float32)
        for k, gt in enumerate(scene.gt_of(im)):
            mask = scene.load_mask(im, k, visible=True).bool() & (depth > 0)
            if int(mask.sum()) < min_pixels or gt.obj_id not in objects:
                continue
            half = objects[gt.obj_id].diameter / 2
            cloud = backproject_depth(depth[None], K, mask[None])
            points, pixels = cloud.points[0][cloud.mask[0]], cloud.pixels[0][cloud.mask[0]]
            box = crop_box_around(points[None], K)
            layers = depth_layers(depth[None], mask[None], torch.tensor([2 * half]))
            crop = crop_resize(torch.cat([rgb[None], layers], dim=1), box, size)[0]
            pick = torch.randint(len(points), (points_per_crop,), generator=g)
            pose = torch.as_tensor(gt.pose, dtype=torch.float32)
            canonical = (points[pick] - pose[:3, 3]) @ pose[:3, :3] / half
            crops.append(crop.half())
            uvs.append(pixels_to_crop(pixels[pick][None].float(), box, size)[0])
            coords.append(canonical)
            ids.append(gt.obj_id)
    if not crops:
        raise DegenerateInputError(f"no instance of {root}/{split} has {min_pixels} valid pixels")
    surfaces = {}
    for o, model in objects.items():
        half = model.diameter / 2
        syms = torch.as_tensor(model.symmetries, dtype=torch.float32).clone()
        syms[:, :3, 3] /= half
        surfaces[o] = (torch.as_tensor(model.points, dtype=torch.float32) / half, syms)
    return SurfaceCrops(
        torch.stack(crops),
        torch.stack(uvs),
        torch.stack(coords),
        torch.tensor(ids),
        surfaces,
        {o: float(m.diameter) for o, m in objects.items()},
    )


def surface_loss(
    queries: torch.Tensor,
    coords: torch.Tensor,
    obj_ids: Sequence[int],
    keys: SurfaceKeys,
    surfaces: dict[int, tuple[torch.Tensor, torch.Tensor]],
    *,
    negatives: int = 256,
    temperature: float = 0.07,
    sigma: float = 0.1,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """InfoNCE of queries against keys with a symmetry-aware soft target (a scalar).

    Args:
        queries: unit queries ``(B, Q, G)`` of sampled pixels.
        coords: their canonical coordinates ``(B, Q, 3)``, half diameters.
        obj_ids: the object of each crop ``(B,)``.
        keys: the per-object keys.
        surfaces: ``{obj_id: (surface points (K, 3), symmetries (S, 4, 4))}``, half diameters.
        negatives: random surface points scored besides the ``Q`` true ones.
        temperature: of the softmax over the candidates.
        sigma: width of the soft target, half diameters.
        generator: draws the negatives.
    """
    total = queries.new_zeros(())
    for b, o in enumerate(obj_ids):
        points, syms = surfaces[int(o)]
        pick = torch.randint(len(points), (negatives,), generator=generator)
        candidates = torch.cat([coords[b], points[pick]])
        logits = queries[b] @ keys(int(o), candidates).T / temperature
        moved = torch.einsum("sij,kj->ski", syms[:, :3, :3], candidates) + syms[:, None, :3, 3]
        d2 = ((coords[b][None, :, None] - moved[:, None]) ** 2).sum(-1).min(0).values
        target = torch.softmax(-d2 / (2 * sigma**2), dim=-1)
        total = total - (target * logits.log_softmax(-1)).sum(-1).mean()
    return total / len(obj_ids)


def train_surface_embedding(
    root: str | Path,
    out: str | Path,
    *,
    steps: int = 10000,
    split: str = "train",
    max_images: int | None = 1600,
    batch_size: int = 16,
    queries: int = 48,
    points_per_crop: int = 128,
    negatives: int = 256,
    dim: int = 32,
    lr: float = 2e-3,
    temperature: float = 0.07,
    sigma: float = 0.1,
    init: str | Path | None = "shipped",
    precision: str = "fp32",
    seed: int = 0,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
) -> Path:
    """Train a surface embedding of a BOP split's objects and write it to ``out``.

    Args:
        root: the BOP dataset (``models/`` and the split).
        out: the output folder.
        steps: optimiser steps (AdamW, warm-up then cosine).
        split: the split with poses, masks and depth.
        max_images: crops from at most this many images (None: all).
        batch_size: crops per step.
        queries: pixels per crop per step, drawn (with replacement) among its
            ``points_per_crop``.
        points_per_crop: pixels kept per crop with their canonical coordinates.
        negatives: see :func:`surface_loss`.
        temperature: see :func:`surface_loss`.
        sigma: see :func:`surface_loss`.
        dim: descriptor channels.
        lr: peak learning rate.
        init: a descriptor folder whose weights start the query network, ``"shipped"`` for the
            package's (when present), or None for a random start.
        precision: what the query network's products compute in (``"bf16"``, ``"auto"``:
            bfloat16 where the CPU has it; the keys and the loss stay float32), see
            :func:`poseflow.flows.autocast_dtype`.
        seed: seeds the crops' points, the initialisation and the batches.
        progress: show progress bars.
        log: called with a line of figures every 100 steps.

    Returns:
        The output folder.

    Example:
        >>> import tempfile
        >>> from poseflow.data import generate_dataset
        >>> with tempfile.TemporaryDirectory() as d:
        ...     root = generate_dataset(d + "/ds", num_train_images=1, num_test_images=0,
        ...                             width=160, height=120, progress=False)
        ...     out = train_surface_embedding(root, d + "/emb", steps=1, batch_size=2, init=None,
        ...                                   progress=False)
        ...     sorted(p.name for p in out.iterdir())
        ['config.json', 'model.safetensors']
    """
    if steps < 1 or batch_size < 1 or queries < 1 or negatives < 1:
        raise ValueRangeError("steps, batch_size, queries and negatives must be positive")
    if queries > points_per_crop:
        raise ValueRangeError(
            f"queries must be at most points_per_crop, got {queries} of {points_per_crop}"
        )
    dtype = autocast_dtype(precision, "cpu")
    data = surface_crops(
        root, split, max_images=max_images, points_per_crop=points_per_crop, seed=seed,
        progress=progress,
    )  # fmt: skip
    torch.manual_seed(seed)
    model = SurfaceEmbedding(data.diameters, dim=dim)
    if init is not None:
        _start_from_descriptor(model, SHIPPED_DESCRIPTOR_DIR if init == "shipped" else init)
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, _warmup_cosine(steps))
    g = torch.Generator().manual_seed(seed)
    size, start, recent = data.crops.shape[-1], time.monotonic(), []
    model.train()
    for step in progress_loop(
        range(steps), total=steps, desc="surface embedding", enabled=progress
    ):
        idx = torch.randint(len(data.crops), (batch_size,), generator=g)
        x = _colour_jitter(data.crops[idx].float(), g)
        pick = torch.randint(data.uv.shape[1], (batch_size, queries), generator=g)
        uv = torch.gather(data.uv[idx], 1, pick[..., None].expand(-1, -1, 2))
        coords = torch.gather(data.coords[idx], 1, pick[..., None].expand(-1, -1, 3))
        with precision_autocast(precision, "cpu"):
            dense = model.query(x)
        q = sample_features(dense.float(), uv, (size, size))
        loss = surface_loss(
            torch.nn.functional.normalize(q, dim=-1), coords, data.obj_ids[idx].tolist(),
            model.keys, data.surfaces, negatives=negatives, temperature=temperature,
            sigma=sigma, generator=g,
        )  # fmt: skip
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        sched.step()
        recent = [*recent[-99:], loss.item()]
        if log is not None and ((step + 1) % 100 == 0 or step + 1 == steps):
            mean = sum(recent) / len(recent)
            log(f"step {step + 1} loss {mean:.4f} {time.monotonic() - start:.0f}s")
    model.eval()
    training = {
        "steps": steps, "images": max_images, "crops": len(data.crops), "batch_size": batch_size,
        "queries": queries, "points_per_crop": points_per_crop, "negatives": negatives, "lr": lr,
        "temperature": temperature, "sigma": sigma, "seed": seed,
        "init": None if init is None else str(init),
        "precision": next(name for name, d in PRECISIONS.items() if d is dtype),
        "loss": round(sum(recent) / len(recent), 4),
        "seconds": round(time.monotonic() - start, 1),
    }  # fmt: skip
    return save_surface_embedding(model, out, input_size=size, training=training)


def _colour_jitter(x: torch.Tensor, g: torch.Generator) -> torch.Tensor:
    """Random brightness per crop and offset per channel on the colour channels."""
    n = x.shape[0]
    gain = 0.8 + 0.4 * torch.rand(n, 1, 1, 1, generator=g)
    offset = 0.1 * (torch.rand(n, 3, 1, 1, generator=g) - 0.5)
    x[:, :3] = (x[:, :3] * gain + offset).clamp(0, 1)
    return x


def _start_from_descriptor(model: SurfaceEmbedding, folder: str | Path) -> None:
    """Copy a descriptor's weights into the query network (depth channels from zero, new head)."""
    if not (Path(folder) / "model.safetensors").is_file():
        return
    source, _ = load_descriptor(folder)
    own = model.query.state_dict()
    for name, value in source.state_dict().items():
        if name.startswith("head") or name not in own:
            continue
        if own[name].shape == value.shape:
            own[name] = value
        elif own[name].dim() == 4 and own[name].shape[1] > value.shape[1]:  # the stem's input
            own[name] = torch.zeros_like(own[name])
            own[name][:, : value.shape[1]] = value
    model.query.load_state_dict(own)
