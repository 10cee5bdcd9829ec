"""Training the learned appearance descriptor on generated renders of procedural objects.

The data never contains a user's object: procedural meshes and solid textures
(:mod:`poseflow.features.procedural`) rendered in pairs (:mod:`poseflow.features.view_pairs`).
Every training pair is made as follows:

1. a procedural mesh (:func:`random_mesh`): one to four Open3D primitives (boxes, cylinders,
   cones, spheres, ellipsoids, tori, polyhedra, radially deformed blobs) joined, then scaled,
   twisted, bent or tapered; flat parts are shaded flat, round parts smooth;
2. a random solid texture (:func:`random_texture`): a function of the model-frame point and
   normal, so that both views see the same surface: plain or two-tone paint, 3D noise blotches,
   stripes, checks, dots, images mapped by triplanar projection (text-like prints, barcodes,
   tables, and photographs available offline such as matplotlib's sample images), or a
   patchwork of these in 3D Voronoi cells with dark seams;
3. two renderings (:func:`render_pair`) with poseflow's ray caster from viewpoints that differ by
   up to ``max_view_angle`` plus an arbitrary in-plane roll (the rotation augmentation), each at
   its own scale (the object spans 32 to 192 pixels before the crop is resized to
   ``input_size``, the scale augmentation), its own light (ambient, Lambertian and specular
   terms), background, optional clutter object (occluding or behind), blur and noise; each is
   cropped exactly as FunFlow6D crops a target (the square around the projection of the visible
   points' barycentre, with a random margin and jitter) and resized; in half of the pairs view
   A is instead rendered the way the query's views are (black background, headlight, no
   clutter, blur or noise, the lifting's crop), since FunFlow6D matches those renderings
   against observed crops;
4. the ground-truth correspondences: every object pixel of crop A is lifted with its depth to the
   model frame, projected into view B, and kept where B's depth at that pixel agrees (visible,
   not occluded).

The loss (:func:`descriptor_loss`) is InfoNCE over those correspondences in both directions: the
descriptor of a pixel in one view is scored against every feature cell of the other view (object
and background), with a soft target on the true match and the cells around it (Gaussian in the
surface distance, ``sigma`` diameters), so that descriptors vary smoothly over the surface at the
scale at which FunFlow6D's sparse clouds are matched. Colour jitter is applied independently to
each view.

:func:`train_descriptor` trains a :class:`~poseflow.features.learned.DescriptorNet` with AdamW
and a cosine schedule, one CPU thread friendly, seeded, and writes ``model.safetensors`` +
``config.json`` atomically (also every ``save_every`` steps). The shipped weights are made by::

    python -m poseflow.features.descriptor_training --out src/poseflow/assets/descriptor --steps N
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F

from poseflow._progress import ProgressBar
from poseflow.errors import ValueRangeError
from poseflow.features.appearance import sample_features
from poseflow.features.learned import DEPTH_CHANNELS, DescriptorNet, save_descriptor

__all__ = [
    "DescriptorTrainingConfig",
    "descriptor_loss",
    "main",
    "train_descriptor",
]

from poseflow.features.view_pairs import PairBatch, PairGenerator


@dataclass(frozen=True)
class DescriptorTrainingConfig:
    """Settings of :func:`train_descriptor` (written to ``config.json`` under ``training``).

    Attributes:
        steps: optimiser steps.
        batch_size: view pairs per step.
        input_size: side of the square crops, pixels (FunFlow6D's ``crop_size``).
        widths: channels per level of the network.
        dim: descriptor channels ``G``.
        out_stride: output stride of the descriptor map.
        lr: peak AdamW learning rate (linear warm-up over 5 % of the steps, cosine decay).
        weight_decay: AdamW weight decay.
        temperature: InfoNCE temperature.
        anchors: correspondences per pair and direction.
        exclusion: feature cells whose surface point is closer than this (fraction of the
            diameter) to the true match are not negatives (with ``sigma = 0``).
        sigma: width of the loss's soft target around the match, fraction of the diameter (see
            :func:`descriptor_loss`); 0: hard InfoNCE.
        fresh_pairs: new pairs rendered per step; the rest of the batch is drawn from a pool of
            ``pool_size`` recent pairs (with new colour jitter).
        pool_size: pairs kept for reuse.
        max_view_angle: largest out-of-plane angle between the two views, degrees (the in-plane
            roll is uniform over 360°).
        clutter: probability of a second object in a view (occluding or behind).
        depth: a depth-aware network (RGB and the depth layers in; see
            :func:`~poseflow.features.learned.depth_layers`).
        seed: seeds the data and the network.
    """

    steps: int = 2000
    batch_size: int = 8
    input_size: int = 96
    widths: tuple[int, ...] = (32, 48, 96, 128)
    dim: int = 64
    out_stride: int = 4
    lr: float = 2e-3
    weight_decay: float = 1e-4
    temperature: float = 0.07
    anchors: int = 128
    exclusion: float = 0.05
    sigma: float = 0.06
    fresh_pairs: int = 4
    pool_size: int = 64
    max_view_angle: float = 80.0
    clutter: float = 0.5
    depth: bool = False
    seed: int = 0

    def __post_init__(self) -> None:
        """Validate the values."""
        if self.steps < 1 or self.batch_size < 1 or self.anchors < 1:
            raise ValueRangeError("steps, batch_size and anchors must be positive")
        if self.input_size < 16:
            raise ValueRangeError(f"input_size must be at least 16, got {self.input_size}")
        if not 1 <= self.fresh_pairs <= self.batch_size <= self.pool_size:
            raise ValueRangeError("need 1 <= fresh_pairs <= batch_size <= pool_size")
        if not (self.lr > 0 and self.temperature > 0 and 0 <= self.exclusion < 1):
            raise ValueRangeError("lr and temperature must be positive, exclusion in [0, 1)")
        if not 0 <= self.sigma < 1:
            raise ValueRangeError(f"sigma must be in [0, 1), got {self.sigma}")
        if not 0 <= self.max_view_angle <= 180 or not 0 <= self.clutter <= 1:
            raise ValueRangeError("max_view_angle must be in [0, 180] and clutter in [0, 1]")
        object.__setattr__(self, "widths", tuple(int(w) for w in self.widths))

    def network(self) -> DescriptorNet:
        """The untrained network of these settings (seeded by the caller)."""
        channels = 3 + DEPTH_CHANNELS * self.depth
        sizes = {"widths": self.widths, "dim": self.dim, "out_stride": self.out_stride}
        return DescriptorNet(**sizes, in_channels=channels)

    def pair_generator(self) -> PairGenerator:
        """The seeded stream of training pairs of these settings."""
        names = ("input_size", "anchors", "max_view_angle", "clutter", "pool_size", "depth")
        return PairGenerator(self.seed, **{name: getattr(self, name) for name in names})


def _cell_coords(coords: torch.Tensor, mask: torch.Tensor, h: int, w: int):
    """Model points ``(B, h·w, 3)`` and object flags ``(B, h·w)`` at the feature cell centres."""
    S = coords.shape[1]
    rows = ((torch.arange(h) + 0.5) * S / h - 0.5).round().long().clamp(0, S - 1)
    cols = ((torch.arange(w) + 0.5) * S / w - 0.5).round().long().clamp(0, S - 1)
    c = coords[:, rows][:, :, cols].reshape(len(coords), h * w, 3)
    m = mask[:, rows][:, :, cols].reshape(len(coords), h * w)
    return c, m


def _info_nce(
    feat_src: torch.Tensor,
    feat_dst: torch.Tensor,
    uv_src: torch.Tensor,
    uv_dst: torch.Tensor,
    points: torch.Tensor,
    coords_dst: torch.Tensor,
    mask_dst: torch.Tensor,
    size: int,
    temperature: float,
    exclusion: float,
    sigma: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    f_src = F.normalize(sample_features(feat_src, uv_src, (size, size)), dim=-1)  # (B, P, G)
    f_pos = F.normalize(sample_features(feat_dst, uv_dst, (size, size)), dim=-1)
    h, w = feat_dst.shape[-2:]
    cells = feat_dst.flatten(2).transpose(1, 2)  # (B, hw, G)
    pos = (f_src * f_pos).sum(-1, keepdim=True)  # (B, P, 1)
    sim = f_src @ cells.transpose(1, 2)  # (B, P, hw)
    c, m = _cell_coords(coords_dst, mask_dst, h, w)
    dist = torch.where(m[:, None], torch.cdist(points, c), torch.full_like(sim, torch.inf))
    near = dist < exclusion  # (B, P, hw)
    if sigma > 0:  # soft targets: the match and the cells around it, by surface distance
        weights = torch.cat([torch.ones_like(pos), torch.exp(-0.5 * (dist / sigma) ** 2)], -1)
        weights = weights / weights.sum(-1, keepdim=True)
        logp = torch.log_softmax(torch.cat([pos, sim], dim=-1) / temperature, dim=-1)
        loss = -(weights * logp).sum(-1).mean()
    else:
        logits = torch.cat([pos, sim.masked_fill(near, float("-inf"))], dim=-1) / temperature
        loss = -torch.log_softmax(logits, dim=-1)[..., 0].mean()
    acc = (pos[..., 0] > sim.masked_fill(near, -2.0).amax(-1)).float().mean()
    return loss, acc


def descriptor_loss(
    feat_a: torch.Tensor,
    feat_b: torch.Tensor,
    batch: PairBatch,
    *,
    temperature: float = 0.07,
    exclusion: float = 0.05,
    sigma: float = 0.06,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Symmetric InfoNCE over the ground-truth correspondences of a :class:`PairBatch`.

    For each correspondence, the source pixel's descriptor (bilinear, normalised) is scored
    against its match in the other view and every feature cell of the other view (background,
    clutter and object cells). With ``sigma > 0`` the target of the softmax is soft: the match
    and every object cell with weight ``exp(-d² / 2 sigma²)`` of its surface distance ``d`` to
    the match, so that descriptors stay similar over about ``sigma`` of the surface, the scale at
    which sparse clouds are matched (an exact-match target makes descriptors so peaked that the
    nearest of a few hundred sampled points is not the most similar). With ``sigma = 0`` the
    match is the only positive and object cells closer than ``exclusion`` are left out. Both
    directions are averaged.

    Args:
        feat_a: descriptor maps of view A ``(B, G, h, w)``.
        feat_b: descriptor maps of view B ``(B, G, h, w)``.
        batch: the batch (crops of side ``S``; the maps cover them uniformly).
        temperature: softmax temperature.
        exclusion: radius around the match without negatives (``sigma = 0``) and ignored by
            the accuracy, fraction of the diameter.
        sigma: width of the soft target, fraction of the diameter; 0: hard InfoNCE.

    Returns:
        ``(loss, accuracy)``: the mean loss and the fraction of correspondences whose match
        beats every cell farther than ``exclusion`` from it.
    """
    S = batch.images_a.shape[-1]
    la, aa = _info_nce(feat_a, feat_b, batch.uv_a, batch.uv_b, batch.points, batch.coords_b,
                       batch.mask_b, S, temperature, exclusion, sigma)  # fmt: skip
    lb, ab = _info_nce(feat_b, feat_a, batch.uv_b, batch.uv_a, batch.points, batch.coords_a,
                       batch.mask_a, S, temperature, exclusion, sigma)  # fmt: skip
    return (la + lb) / 2, (aa + ab) / 2


def train_descriptor(
    out: str | Path,
    *,
    steps: int,
    config: DescriptorTrainingConfig | None = None,
    progress: bool = True,
    save_every: int = 500,
    time_limit: float | None = None,
    log: Callable[[str], None] | None = None,
    query_pooling: str = "select",
    **changes: object,
) -> Path:
    """Train the descriptor network and write ``model.safetensors`` + ``config.json`` to ``out``.

    Args:
        out: the output folder (the files are replaced atomically, also every ``save_every``
            steps, so that an interrupted run leaves usable weights).
        steps: optimiser steps.
        config: the settings (default :class:`DescriptorTrainingConfig`); ``steps`` and
            ``changes`` override it.
        progress: show a progress bar.
        save_every: steps between intermediate saves (0: only at the end).
        time_limit: stop after this many seconds (the schedule still assumes ``steps``).
        log: called with a line of figures every 50 steps.
        query_pooling: the encoder's ``query_pooling`` written to ``config.json`` (``"mean"``
            or ``"select"``, see :mod:`poseflow.features.lifting`).
        **changes: fields of :class:`DescriptorTrainingConfig` to change.

    Returns:
        The output folder.

    Example:
        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as d:
        ...     folder = train_descriptor(d, steps=1, batch_size=1, fresh_pairs=1, pool_size=1,
        ...                               input_size=32, widths=(8, 16), dim=8, out_stride=2,
        ...                               anchors=8, progress=False)
        ...     sorted(p.name for p in folder.iterdir())
        ['config.json', 'model.safetensors']
    """
    if query_pooling not in ("mean", "select"):
        raise ValueRangeError(f"query_pooling must be 'mean' or 'select', got {query_pooling!r}")
    cfg = config or DescriptorTrainingConfig()
    cfg = DescriptorTrainingConfig(**{**asdict(cfg), **changes, "steps": int(steps)})
    torch.manual_seed(cfg.seed)
    net, gen = cfg.network(), cfg.pair_generator()
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, _warmup_cosine(cfg.steps))
    record = _Record(cfg, time.monotonic())

    def save(final: bool) -> None:
        save_descriptor(net, out, input_size=cfg.input_size, query_pooling=query_pooling,
                        training=record.summary(final))  # fmt: skip

    net.train()
    with ProgressBar(cfg.steps, desc="descriptor", enabled=progress) as bar:
        for _ in range(cfg.steps):
            loss, acc = _step(net, opt, gen.batch(cfg.batch_size, fresh=cfg.fresh_pairs), cfg)
            sched.step()
            record.add(loss, acc)
            bar.update()
            if record.done % 50 == 0 or record.done == cfg.steps:
                lr = sched.get_last_lr()[0]
                bar.set_postfix(**record.values(lr))
                if log is not None:
                    log(record.line(lr))
            if save_every and record.done % save_every == 0 and record.done < cfg.steps:
                save(False)
            if time_limit is not None and time.monotonic() - record.start > time_limit:
                break
    net.eval()
    save(True)
    return Path(out)


def _warmup_cosine(steps: int) -> Callable[[int], float]:
    """The learning-rate factor: linear warm-up over 5 % of ``steps``, then cosine decay."""
    warm = max(1, steps // 20)

    def factor(step: int) -> float:
        if step < warm:
            return (step + 1) / warm
        return 0.5 * (1 + math.cos(math.pi * (step - warm) / max(1, steps - warm)))

    return factor


def _step(
    net: DescriptorNet, opt: torch.optim.Optimizer, batch: PairBatch, cfg: DescriptorTrainingConfig
) -> tuple[float, float]:
    """One optimiser step on a batch; returns its ``(loss, accuracy)``."""
    feats = net(torch.cat([batch.images_a, batch.images_b]))
    fa, fb = feats.chunk(2)
    loss, acc = descriptor_loss(
        fa, fb, batch, temperature=cfg.temperature, exclusion=cfg.exclusion, sigma=cfg.sigma
    )
    opt.zero_grad(set_to_none=True)
    loss.backward()
    torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
    opt.step()
    return loss.item(), acc.item()


@dataclass
class _Record:
    """The losses and accuracies of the steps done, for the log and ``config.json``."""

    cfg: DescriptorTrainingConfig
    start: float
    history: list[tuple[float, float]] = field(default_factory=list)

    @property
    def done(self) -> int:
        return len(self.history)

    def add(self, loss: float, acc: float) -> None:
        self.history.append((loss, acc))

    def _recent(self, k: int) -> float | None:
        recent = self.history[-50:]
        return float(np.mean([r[k] for r in recent])) if recent else None

    def values(self, lr: float) -> dict[str, str]:
        """The recent loss and accuracy and ``lr``, formatted: ``{"loss": "0.4123", ...}``."""
        return {
            "loss": f"{self._recent(0):.4f}",
            "acc": f"{self._recent(1):.3f}",
            "lr": f"{lr:.2e}",
        }

    def line(self, lr: float) -> str:
        values = " ".join(f"{k} {v}" for k, v in self.values(lr).items())
        return f"step {self.done} {values} {time.monotonic() - self.start:.0f}s"

    def summary(self, final: bool) -> dict:
        loss, acc = self._recent(0), self._recent(1)
        return {
            **asdict(self.cfg),
            "steps_done": self.done,
            "seconds": round(time.monotonic() - self.start, 1),
            "final": final,
            "loss": None if loss is None else round(loss, 4),
            "accuracy": None if acc is None else round(acc, 4),
        }


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m poseflow.features.descriptor_training --out DIR --steps N``."""
    parser = argparse.ArgumentParser(
        prog="python -m poseflow.features.descriptor_training",
        description="Train poseflow's learned appearance descriptor on generated renders.",
    )
    parser.add_argument("--out", required=True, help="output folder (model.safetensors + config)")
    parser.add_argument("--steps", type=int, default=DescriptorTrainingConfig.steps)
    parser.add_argument("--time-limit", type=float, default=None, help="stop after SECONDS")
    parser.add_argument("--save-every", type=int, default=500)
    defaults = DescriptorTrainingConfig()
    for name in ("batch_size", "input_size", "dim", "out_stride", "anchors", "fresh_pairs",
                 "pool_size", "seed"):  # fmt: skip
        parser.add_argument(
            f"--{name.replace('_', '-')}", type=int, default=getattr(defaults, name)
        )
    for name in ("lr", "weight_decay", "temperature", "exclusion", "sigma", "max_view_angle",
                 "clutter"):  # fmt: skip
        parser.add_argument(
            f"--{name.replace('_', '-')}", type=float, default=getattr(defaults, name)
        )
    parser.add_argument(
        "--widths", type=lambda s: tuple(int(v) for v in s.split(",")), default=defaults.widths
    )
    parser.add_argument(
        "--query-pooling",
        choices=("mean", "select"),
        default="select",
        help="how the query's multi-view features are pooled at use (written to config.json)",
    )
    parser.add_argument(
        "--depth",
        action="store_true",
        help="a depth-aware descriptor: RGB and the object's depth relief in",
    )
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    torch.set_num_threads(max(1, args.threads))
    changes = {k: getattr(args, k) for k in asdict(defaults) if k != "steps" and hasattr(args, k)}
    train_descriptor(
        args.out,
        steps=args.steps,
        progress=not args.no_progress,
        save_every=args.save_every,
        time_limit=args.time_limit,
        log=lambda line: print(line, flush=True),
        query_pooling=args.query_pooling,
        **changes,
    )
    print(f"wrote {args.out}/model.safetensors and config.json", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
