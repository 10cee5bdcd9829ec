"""Object-specific surface embeddings: dense queries of RGB-D crops against keys of each surface.

A :class:`SurfaceEmbedding` is learned per set of objects (a user's meshes) from renders of them,
as SurfEmb and ZebraPose learn theirs: a query network (a :class:`DescriptorNet` on the colour crop
and its :func:`depth_layers`) gives a unit descriptor per pixel, and one small MLP per object
(:class:`SurfaceKeys`, on Fourier features of the canonical coordinates in half diameters) gives
a unit key per surface point; a pixel and the point it shows are trained to agree
(:mod:`poseflow.features.surface_training`). Unlike the generic learned descriptor, whose query
features are read from renderings of the model, the keys give every surface point its descriptor
directly, and the query network learns the object's own shading, texture and relief.

:class:`SurfaceEmbeddingEncoder` is the trained embedding as FunFlow6D's appearance encoder
(``appearance_encoder="surface:FOLDER"``): ``encode`` gives the query maps of target crops and
``point_keys`` the keys of an object's surface points; :func:`match_surface` finds each observed
point's best key, the surface point it shows. Matching two RGB-D observations of a known object
needs only the query maps of both (:func:`~poseflow.features.sample_features`).

A folder holds ``model.safetensors`` and ``config.json`` (no pickle), written by
:func:`save_surface_embedding` and read by :func:`load_surface_embedding`.

Shape letters: B images or instances, G descriptor channels, P or M points, N queries, H × W image.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import nn
from torch.nn import functional as F

from poseflow._checks import check_tensor
from poseflow.errors import CheckpointError, MissingWeightsError, ValueRangeError
from poseflow.features.appearance import network_input
from poseflow.features.learned import (
    _CONFIG,
    _VERSION,
    _WEIGHTS,
    DEPTH_CHANNELS,
    DescriptorNet,
    _weights_key,
    load_network_weights,
    read_network_config,
    write_network_folder,
)

__all__ = [
    "SURFACE_FORMAT",
    "SurfaceEmbedding",
    "SurfaceEmbeddingEncoder",
    "SurfaceKeys",
    "load_surface_embedding",
    "match_surface",
    "save_surface_embedding",
]

#: The ``format`` tag of a surface embedding folder's ``config.json``.
SURFACE_FORMAT = "poseflow-surface-embedding"
_HOW_TO_MAKE = (
    "make one with `poseflow train-surface TRAIN_DATASET --out DIR` "
    "and pass appearance_encoder='surface:DIR'"
)
#: Relative tolerance between an object's diameter and the one its keys were trained for.
DIAMETER_TOLERANCE = 0.01


class SurfaceKeys(nn.Module):
    """One MLP per object from canonical coordinates to unit keys.

    Args:
        obj_ids: the objects.
        dim: key channels ``G``.
        frequencies: octaves of the sine and cosine features of each coordinate.
        width: hidden width of each MLP (two hidden layers).

    Example:
        >>> keys = SurfaceKeys([1, 2], dim=8, frequencies=2, width=16)
        >>> k = keys(2, torch.rand(5, 3))
        >>> k.shape, bool(torch.allclose(k.norm(dim=-1), torch.ones(5)))
        (torch.Size([5, 8]), True)
    """

    def __init__(
        self, obj_ids: Sequence[int], *, dim: int, frequencies: int = 6, width: int = 128
    ) -> None:
        super().__init__()
        if not obj_ids:
            raise ValueRangeError("SurfaceKeys needs at least one object")
        if dim < 1 or frequencies < 0 or width < 1:
            raise ValueRangeError(
                f"dim and width must be positive and frequencies >= 0, got {dim}, {width}, "
                f"{frequencies}"
            )
        self.obj_ids = tuple(sorted(int(o) for o in obj_ids))
        self.dim, self.frequencies, self.width = int(dim), int(frequencies), int(width)
        scales = (2.0 ** torch.arange(self.frequencies, dtype=torch.float32)) * (math.pi / 2)
        self.register_buffer("scales", scales, persistent=False)
        d_in = 3 + 6 * self.frequencies
        self.mlps = nn.ModuleDict(
            {
                str(o): nn.Sequential(
                    nn.Linear(d_in, width),
                    nn.ReLU(inplace=True),
                    nn.Linear(width, width),
                    nn.ReLU(inplace=True),
                    nn.Linear(width, dim),
                )
                for o in self.obj_ids
            }
        )

    def forward(self, obj_id: int, points: torch.Tensor) -> torch.Tensor:
        """Unit keys of canonical points.

        Args:
            obj_id: the object.
            points: canonical coordinates ``(..., 3)`` in half diameters (the surface within the
                unit ball about the model origin, when that is the centre).

        Returns:
            Keys ``(..., G)``, unit norm.

        Raises:
            ValueRangeError: an object these keys were not trained for.
        """
        if int(obj_id) not in self.obj_ids:
            raise ValueRangeError(
                f"no surface keys for object {obj_id}; trained for {self.obj_ids}"
            )
        x = points.to(self.scales.dtype)
        angles = (x[..., None] * self.scales).flatten(-2)
        h = torch.cat([x, angles.sin(), angles.cos()], dim=-1)
        return F.normalize(self.mlps[str(int(obj_id))](h), dim=-1).to(points.dtype)


class SurfaceEmbedding(nn.Module):
    """A query network and per-object keys, with each object's diameter (metres).

    Args:
        diameters: ``{obj_id: diameter in metres}`` of the objects it describes.
        dim: descriptor channels ``G`` of queries and keys.
        widths: the query :class:`DescriptorNet`'s channels per level.
        out_stride: its output stride.
        frequencies: see :class:`SurfaceKeys`.
        key_width: see :class:`SurfaceKeys` (``width``).

    Example:
        >>> emb = SurfaceEmbedding({3: 0.1}, dim=8, widths=(8, 16, 16), key_width=16)
        >>> emb.query(torch.rand(1, 5, 32, 32)).shape, emb.keys_of(3, torch.zeros(4, 3)).shape
        (torch.Size([1, 8, 8, 8]), torch.Size([4, 8]))
    """

    def __init__(
        self,
        diameters: Mapping[int, float],
        *,
        dim: int = 32,
        widths: Sequence[int] = (32, 48, 96, 128),
        out_stride: int = 4,
        frequencies: int = 6,
        key_width: int = 128,
    ) -> None:
        super().__init__()
        if not diameters or min(float(d) for d in diameters.values()) <= 0:
            raise ValueRangeError(f"diameters must be positive, got {dict(diameters)}")
        self.diameters = {int(o): float(d) for o, d in diameters.items()}
        self.query = DescriptorNet(
            widths=widths, dim=dim, out_stride=out_stride, in_channels=3 + DEPTH_CHANNELS
        )
        self.keys = SurfaceKeys(
            sorted(self.diameters), dim=dim, frequencies=frequencies, width=key_width
        )

    @property
    def dim(self) -> int:
        """Descriptor channels ``G``."""
        return self.query.dim

    def config(self) -> dict[str, Any]:
        """The constructor's arguments, as JSON-ready values."""
        return {
            "diameters": {str(o): d for o, d in sorted(self.diameters.items())},
            "dim": self.dim,
            "widths": list(self.query.widths),
            "out_stride": self.query.out_stride,
            "frequencies": self.keys.frequencies,
            "key_width": self.keys.width,
        }

    def keys_of(self, obj_id: int, points: torch.Tensor) -> torch.Tensor:
        """Keys ``(P, G)`` of model points ``(P, 3)`` in metres, in the model frame."""
        check_tensor(points, "points", ("P", 3))
        half = self.diameters[int(obj_id)] / 2 if int(obj_id) in self.diameters else 1.0
        return self.keys(obj_id, points / half)


class SurfaceEmbeddingEncoder:
    """A frozen :class:`SurfaceEmbedding` as FunFlow6D's appearance encoder.

    Args:
        weights: a folder from :func:`save_surface_embedding`, or a :class:`SurfaceEmbedding`.
        input_size: side of the square crops (default: the training crops', or 96).
        device: where the networks run.

    Raises:
        MissingWeightsError: the folder or one of its files is missing.
        CheckpointError: the folder's files are corrupt or do not fit together.

    Example:
        >>> enc = SurfaceEmbeddingEncoder(
        ...     SurfaceEmbedding({1: 0.2}, dim=8, widths=(8, 16, 16), key_width=16), input_size=32
        ... )
        >>> enc.encode(torch.rand(2, 5, 40, 40)).shape
        torch.Size([2, 8, 8, 8])
    """

    #: a network: FunFlow6D's ``appearance_precision`` applies
    autocast = True
    #: the queries see the colour and the depth relief (``depth_layers``)
    in_channels = 3 + DEPTH_CHANNELS
    #: every query point has one key: there are no views to pool
    query_pooling = "mean"

    def __init__(
        self,
        weights: str | Path | SurfaceEmbedding,
        *,
        input_size: int | None = None,
        device: str | torch.device = "cpu",
    ) -> None:
        if isinstance(weights, SurfaceEmbedding):
            model, cfg, self.source = weights, {}, "SurfaceEmbedding"
        else:
            model, cfg = load_surface_embedding(weights)
            self.source = str(weights)
        size = int(input_size if input_size is not None else cfg.get("input_size", 96))
        if size < 8:
            raise ValueRangeError(f"input_size must be at least 8, got {size}")
        self.model = model.to(device).eval()
        for p in self.model.parameters():
            p.requires_grad_(False)
        self.input_size = size
        self.dim = model.dim
        self.weights_key = _weights_key(self.model)

    def __repr__(self) -> str:
        # the weights' key makes the repr (which keys cached features) follow retraining
        return (
            f"SurfaceEmbeddingEncoder({self.source!r}, weights={self.weights_key}, "
            f"dim={self.dim}, input_size={self.input_size})"
        )

    @torch.no_grad()
    def encode(self, images: torch.Tensor) -> torch.Tensor:
        """Query maps ``(B, G, s, s)`` of RGB-D crops ``(B, 5, H, W)`` (colour and depth layers)."""
        x = network_input(images, self.model.query, self.input_size, self.in_channels)
        return self.model.query(x).to(device=images.device, dtype=images.dtype)

    @torch.no_grad()
    def point_keys(self, obj_id: int, points: torch.Tensor, diameter: float) -> torch.Tensor:
        """The keys of an object's surface points, the descriptors their pixels are matched to.

        Args:
            obj_id: the object.
            points: surface points ``(P, 3)``, metres, model frame.
            diameter: the object's diameter in metres (checked against the trained one).

        Returns:
            Unit keys ``(P, G)``, float32 on the CPU.

        Raises:
            ValueRangeError: an object the embedding was not trained for, or of another size.
        """
        trained = self.model.diameters.get(int(obj_id))
        if trained is None:
            raise ValueRangeError(
                f"the surface embedding {self.source} has no keys for object {obj_id} (it was "
                f"trained for objects {sorted(self.model.diameters)}); {_HOW_TO_MAKE}"
            )
        if abs(trained - float(diameter)) > DIAMETER_TOLERANCE * trained:
            raise ValueRangeError(
                f"object {obj_id} has diameter {diameter:.4f} m but the surface embedding "
                f"{self.source} was trained for {trained:.4f} m: another mesh or mesh scale"
            )
        param = next(self.model.parameters())
        keys = self.model.keys_of(obj_id, points.to(device=param.device, dtype=param.dtype))
        return keys.cpu().float()


def match_surface(
    queries: torch.Tensor, keys: torch.Tensor, key_mask: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Each query's best-matching key by cosine similarity.

    Args:
        queries: descriptors of observed points ``(B, N, G)`` (e.g. query maps sampled at the
            pixels of a target cloud; normalised here).
        keys: unit keys of surface points ``(B, M, G)``
            (:meth:`SurfaceEmbeddingEncoder.point_keys`).
        key_mask: valid keys ``(B, M)`` (padding of objects with fewer points), or None.

    Returns:
        ``(index (B, N), similarity (B, N))``: the best key of every query and its cosine.

    Example:
        >>> keys = F.normalize(torch.randn(1, 6, 4), dim=-1)
        >>> index, sim = match_surface(2 * keys[:, [3, 0]], keys)
        >>> index.tolist(), [round(v, 4) for v in sim[0].tolist()]
        ([[3, 0]], [1.0, 1.0])
    """
    check_tensor(queries, "queries", ("B", "N", "G"))
    check_tensor(keys, "keys", ("B", "M", "G"))
    sim = F.normalize(queries.to(keys.dtype), dim=-1) @ keys.transpose(1, 2)
    if key_mask is not None:
        sim = sim.masked_fill(~key_mask[:, None, :], -2.0)  # below any cosine
    similarity, index = sim.max(dim=-1)
    return index, similarity


def save_surface_embedding(model: SurfaceEmbedding, out: str | Path, **config: Any) -> Path:
    """Write a surface embedding folder (``model.safetensors`` + ``config.json``) atomically.

    Args:
        model: the embedding.
        out: the folder (created if needed).
        **config: more JSON-ready entries (``input_size``, the training settings).

    Returns:
        The folder.

    Example:
        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as d:
        ...     emb = SurfaceEmbedding({1: 0.2}, dim=4, widths=(8, 16), out_stride=2, key_width=8)
        ...     _ = save_surface_embedding(emb, d, input_size=32)
        ...     load_surface_embedding(d)[0].diameters
        {1: 0.2}
    """
    meta = {"version": _VERSION, **model.config(), **config}
    return write_network_folder(model, out, SURFACE_FORMAT, meta)


def load_surface_embedding(folder: str | Path) -> tuple[SurfaceEmbedding, dict[str, Any]]:
    """Read a folder written by :func:`save_surface_embedding`.

    Returns:
        ``(embedding, config)``: the embedding in evaluation mode on the CPU and the parsed
        ``config.json``.

    Raises:
        MissingWeightsError: the folder or one of its two files is missing.
        CheckpointError: a file is corrupt, of another format, or the weights do not fit.
    """
    folder = Path(folder)
    for path in (folder, folder / _CONFIG, folder / _WEIGHTS):
        if not path.exists():
            raise MissingWeightsError(f"surface embedding: no {path}; {_HOW_TO_MAKE}")
    cfg = read_network_config(folder, SURFACE_FORMAT, "surface embedding")
    try:
        model = SurfaceEmbedding(
            {int(o): float(d) for o, d in cfg["diameters"].items()},
            dim=int(cfg["dim"]),
            widths=cfg["widths"],
            out_stride=int(cfg["out_stride"]),
            frequencies=int(cfg["frequencies"]),
            key_width=int(cfg["key_width"]),
        )
    except (KeyError, TypeError, ValueError, AttributeError) as err:
        raise CheckpointError(f"{folder / _CONFIG} has bad sizes: {err!r}") from err
    load_network_weights(model, folder)
    return model.eval(), cfg
