"""A learned dense appearance descriptor, trained once on generated renders and frozen at use.

:class:`DescriptorNet` is a small fully-convolutional U-Net: a stride-2 stem, ``len(widths) - 1``
stride-2 encoder levels, and a decoder with skip connections back up to ``1 / out_stride`` of the
input, ending in a 1 × 1 projection to ``G`` channels that are L2-normalised per cell. It is
trained by :mod:`poseflow.features.descriptor_training` on pairs of renderings of procedurally
shaped, randomly textured objects (never the user's objects), with InfoNCE over the ground-truth
pixel correspondences between the two views; the two views differ by an arbitrary in-plane roll,
so the descriptors are trained to be rotation-robust. How the query's multi-view features are
pooled (see :mod:`poseflow.features.lifting`) is written in the folder's ``config.json``: the
training command writes ``"select"`` unless told otherwise, because keeping the best-matching
views gave more inliers than averaging them on the held-out benchmark
(``benchmarks/descriptor_inliers.py``).

:class:`LearnedAppearanceEncoder` wraps the frozen network as an
:class:`~poseflow.features.appearance.AppearanceEncoder`. Weights live in a folder with
``model.safetensors`` and ``config.json`` (no pickle); :func:`save_descriptor` writes one
atomically, :func:`load_descriptor` reads it. :data:`SHIPPED_DESCRIPTOR_DIR` is the folder the
package ships (``appearance_encoder="learned"``), made by
``python -m poseflow.features.descriptor_training --out src/poseflow/assets/descriptor``.

Shape letters: B images, G descriptor channels, H × W image, h × w feature grid.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import nn
from torch.nn import functional as F

from poseflow._cache import atomic_write
from poseflow._checks import check_tensor
from poseflow.errors import CheckpointError, MissingWeightsError, ValueRangeError
from poseflow.features.appearance import network_input

__all__ = [
    "DEPTH_CHANNELS",
    "DESCRIPTOR_FORMAT",
    "SHIPPED_DESCRIPTOR_DIR",
    "DescriptorNet",
    "LearnedAppearanceEncoder",
    "depth_layers",
    "load_descriptor",
    "load_network_weights",
    "read_network_config",
    "save_descriptor",
    "write_network_folder",
]

#: The ``format`` tag of a descriptor folder's ``config.json``.
DESCRIPTOR_FORMAT = "poseflow-descriptor"
_VERSION = 1
#: The folder of the descriptor weights shipped with the package (may be absent in a checkout).
SHIPPED_DESCRIPTOR_DIR = Path(__file__).resolve().parents[1] / "assets" / "descriptor"
_WEIGHTS = "model.safetensors"
_CONFIG = "config.json"
_HOW_TO_MAKE = (
    "make them with `python -m poseflow.features.descriptor_training --out DIR --steps N` "
    "and pass appearance_encoder='learned:DIR'"
)


#: Input channels that :func:`depth_layers` adds to the RGB of a depth-aware descriptor.
DEPTH_CHANNELS = 2


def depth_layers(depth: torch.Tensor, mask: torch.Tensor, diameter: torch.Tensor) -> torch.Tensor:
    """The depth input of a depth-aware descriptor: the object's relief, scale-free.

    Channel 0 is the depth relative to the mean depth of the object's valid pixels, in quarter
    diameters, clamped to ``[-4, 4]`` (0 off the object or where depth is missing); channel 1
    marks those valid pixels. Neither depends on the object's distance or size, and both are
    invariant to in-plane rotation, like the crops they are appended to.

    Args:
        depth: depth ``(B, H, W)`` in metres, 0 where missing.
        mask: the object's pixels ``(B, H, W)`` bool (its visible mask).
        diameter: the object's diameter ``(B,)`` in metres.

    Returns:
        ``(B, 2, H, W)`` in the depth's dtype.

    Example:
        >>> d = torch.tensor([[[1.0, 1.1], [0.0, 0.9]]])
        >>> depth_layers(d, torch.ones(1, 2, 2, dtype=torch.bool), torch.tensor([0.4]))[0, 0]
        tensor([[ 0.0000,  1.0000],
                [ 0.0000, -1.0000]])
    """
    check_tensor(depth, "depth", ("B", "H", "W"))
    valid = mask.bool() & (depth > 0)
    weight = valid.to(depth.dtype)
    centre = (depth * weight).sum(dim=(1, 2)) / weight.sum(dim=(1, 2)).clamp_min(1)
    scale = 4.0 / diameter.to(depth).reshape(-1, 1, 1)
    relief = ((depth - centre[:, None, None]) * scale).clamp(-4.0, 4.0)
    relief = torch.where(valid, relief, torch.zeros((), dtype=depth.dtype, device=depth.device))
    return torch.stack([relief, weight], dim=1)


def _block(c_in: int, c_out: int, *, stride: int = 1) -> nn.Sequential:
    """Two 3 × 3 convolutions with GroupNorm and ReLU, the first one possibly strided."""
    return nn.Sequential(
        nn.Conv2d(c_in, c_out, 3, stride=stride, padding=1, bias=False),
        nn.GroupNorm(_groups(c_out), c_out),
        nn.ReLU(inplace=True),
        nn.Conv2d(c_out, c_out, 3, padding=1, bias=False),
        nn.GroupNorm(_groups(c_out), c_out),
        nn.ReLU(inplace=True),
    )


def _groups(channels: int) -> int:
    for g in (8, 4, 2):
        if channels % g == 0:
            return g
    return 1


class DescriptorNet(nn.Module):
    """Fully-convolutional dense descriptor network (a small U-Net).

    The stem (stride 2) gives level 1 at ``1/2`` resolution with ``widths[0]`` channels; each
    further level halves the resolution (level ``k`` has ``widths[k - 1]`` channels). The decoder
    upsamples from the deepest level, concatenates each skip and refines it, down to the level of
    ``out_stride``; a 1 × 1 convolution gives ``dim`` channels, L2-normalised per cell.

    Args:
        widths: channels per level, from the stem (``1/2``) down; at least two levels.
        dim: descriptor channels ``G``.
        out_stride: output stride, a power of two between 2 and ``2 ** len(widths)`` exclusive of
            the deepest level (2 or 4 in practice).
        in_channels: 3 (RGB) or ``3 + DEPTH_CHANNELS`` (RGB and :func:`depth_layers`).

    Raises:
        ValueRangeError: bad sizes.

    Example:
        >>> net = DescriptorNet(widths=(8, 16, 16), dim=12, out_stride=4)
        >>> out = net(torch.rand(2, 3, 32, 32))
        >>> out.shape, bool(torch.allclose(out.norm(dim=1), torch.ones(2, 8, 8)))
        (torch.Size([2, 12, 8, 8]), True)
    """

    def __init__(
        self,
        *,
        widths: Sequence[int] = (32, 48, 96, 128),
        dim: int = 64,
        out_stride: int = 4,
        in_channels: int = 3,
    ) -> None:
        super().__init__()
        widths = tuple(int(w) for w in widths)
        if len(widths) < 2 or min(widths) < 1:
            raise ValueRangeError(f"widths needs at least two positive entries, got {widths}")
        if dim < 1:
            raise ValueRangeError(f"dim must be positive, got {dim}")
        out_level = int(out_stride).bit_length() - 1
        if out_stride < 2 or 2**out_level != out_stride or out_level >= len(widths):
            raise ValueRangeError(
                f"out_stride must be a power of two in [2, {2 ** (len(widths) - 1)}], "
                f"got {out_stride}"
            )
        if in_channels not in (3, 3 + DEPTH_CHANNELS):
            raise ValueRangeError(
                f"in_channels must be 3 or {3 + DEPTH_CHANNELS}, got {in_channels}"
            )
        self.widths, self.dim, self.out_stride = widths, int(dim), int(out_stride)
        self.in_channels = int(in_channels)
        self.stem = _block(self.in_channels, widths[0], stride=2)
        self.down = nn.ModuleList(
            _block(widths[k - 1], widths[k], stride=2) for k in range(1, len(widths))
        )
        # up[j] merges the level above (coarser) into level len(widths) - 2 - j
        self.up = nn.ModuleList()
        c = widths[-1]
        for level in range(len(widths) - 2, out_level - 2, -1):
            self.up.append(_block(c + widths[level], widths[level]))
            c = widths[level]
        self.head = nn.Conv2d(c, self.dim, 1)

    def config(self) -> dict[str, Any]:
        """The constructor's arguments, as JSON-ready values."""
        cfg = {"widths": list(self.widths), "dim": self.dim, "out_stride": self.out_stride}
        return cfg if self.in_channels == 3 else {**cfg, "in_channels": self.in_channels}

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """Dense unit descriptors.

        Args:
            images: RGB ``(B, 3, H, W)`` in ``[0, 1]``, followed by the :func:`depth_layers`
                when ``in_channels`` is 5; ``H`` and ``W`` multiples of ``2 ** len(widths)``
                give an exact grid (others are handled by padding).

        Returns:
            Descriptors ``(B, G, ceil(H / out_stride), ceil(W / out_stride))``, unit norm per
            cell.
        """
        H, W = images.shape[-2:]
        unit = 2 ** len(self.widths)
        pad_h, pad_w = (-H) % unit, (-W) % unit
        x = torch.cat([(images[:, :3] - 0.5) / 0.25, images[:, 3:]], dim=1)
        if pad_h or pad_w:
            x = F.pad(x, (0, pad_w, 0, pad_h), mode="replicate")
        skips = [self.stem(x)]
        for block in self.down:
            skips.append(block(skips[-1]))
        y = skips[-1]
        for j, block in enumerate(self.up):
            skip = skips[len(skips) - 2 - j]
            y = F.interpolate(y, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            y = block(torch.cat([y, skip], dim=1))
        y = self.head(y)
        h, w = -(-H // self.out_stride), -(-W // self.out_stride)
        return F.normalize(y[..., :h, :w], dim=1)


class LearnedAppearanceEncoder:
    """The frozen :class:`DescriptorNet` as an appearance encoder.

    Args:
        weights: a descriptor folder (``model.safetensors`` + ``config.json``), None for the
            weights shipped with the package (:data:`SHIPPED_DESCRIPTOR_DIR`), or a ready
            :class:`DescriptorNet` (its configuration then comes from ``config``).
        input_size: side of the square crops the network is fed; None: the size it was trained
            on (from ``config.json``).
        query_pooling: ``"mean"`` or ``"select"``; None: the folder's choice (``"mean"`` when
            its ``config.json`` names none).
        config: extra configuration entries when ``weights`` is a network (``input_size``,
            ``query_pooling``).
        device: where the network runs.

    Raises:
        MissingWeightsError: the folder or one of its files is missing.
        CheckpointError: the folder's files are corrupt or do not fit together.
        ValueRangeError: a bad ``input_size`` or ``query_pooling``.

    Example:
        >>> enc = LearnedAppearanceEncoder(DescriptorNet(widths=(8, 16, 16), dim=12),
        ...                                input_size=32)
        >>> enc.dim, enc.query_pooling, enc.encode(torch.rand(2, 3, 50, 50)).shape
        (12, 'mean', torch.Size([2, 12, 8, 8]))
    """

    #: a network: FunFlow6D's ``appearance_precision`` applies (see ``AppearanceEncoder``)
    autocast = True

    def __init__(
        self,
        weights: str | Path | DescriptorNet | None = None,
        *,
        input_size: int | None = None,
        query_pooling: str | None = None,
        config: Mapping[str, Any] | None = None,
        device: str | torch.device = "cpu",
    ) -> None:
        if isinstance(weights, DescriptorNet):
            net, cfg = weights, {**weights.config(), **dict(config or {})}
            self.source = "DescriptorNet"
        else:
            folder = SHIPPED_DESCRIPTOR_DIR if weights is None else Path(weights)
            net, cfg = load_descriptor(folder)
            self.source = str(folder)
        size = int(input_size if input_size is not None else cfg.get("input_size", 96))
        if size < 8:
            raise ValueRangeError(f"input_size must be at least 8, got {size}")
        pooling = query_pooling if query_pooling is not None else cfg.get("query_pooling", "mean")
        if pooling not in ("mean", "select"):
            raise ValueRangeError(f"query_pooling must be 'mean' or 'select', got {pooling!r}")
        self.net = net.to(device).eval()
        for p in self.net.parameters():
            p.requires_grad_(False)
        self.input_size = size
        self.query_pooling = str(pooling)
        self.dim = int(net.dim)
        self.in_channels = int(net.in_channels)
        self.config = dict(cfg)
        self.weights_key = _weights_key(self.net)

    def __repr__(self) -> str:
        # the weights' key makes the repr (which keys cached query features) follow retraining
        return (
            f"LearnedAppearanceEncoder({self.source!r}, weights={self.weights_key}, "
            f"dim={self.dim}, input_size={self.input_size}, "
            f"query_pooling={self.query_pooling!r})"
        )

    @torch.no_grad()
    def encode(self, images: torch.Tensor) -> torch.Tensor:
        """Dense learned descriptors.

        Args:
            images: RGB images ``(B, 3, H, W)`` with values in ``[0, 1]``, followed by their
                :func:`depth_layers` (``(B, 5, H, W)``) when ``in_channels`` is 5.

        Returns:
            Features ``(B, G, s, s)`` with ``s = ceil(input_size / out_stride)``, unit norm per
            cell, on the images' device and in their dtype.
        """
        x = network_input(images, self.net, self.input_size, self.in_channels)
        return self.net(x).to(device=images.device, dtype=images.dtype)


def _weights_key(net: nn.Module) -> str:
    """A short hash of a network's parameters and buffers (their names, shapes and bytes)."""
    h = hashlib.sha1()
    for name, value in sorted(net.state_dict().items()):
        data = value.detach().to("cpu", torch.float32).contiguous()
        h.update(f"{name}{tuple(data.shape)}".encode())
        h.update(data.numpy().tobytes())
    return h.hexdigest()[:12]


def save_descriptor(net: DescriptorNet, out: str | Path, **config: Any) -> Path:
    """Write a descriptor folder (``model.safetensors`` + ``config.json``) atomically.

    Both files are written to temporary names in ``out`` and renamed into place, so a reader never
    sees a half-written file.

    Args:
        net: the network.
        out: the folder (created if needed).
        **config: more JSON-ready entries for ``config.json`` (``input_size``,
            ``query_pooling``, the training settings).

    Returns:
        The folder.

    Example:
        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as d:
        ...     net = DescriptorNet(widths=(8, 16), dim=4, out_stride=2)
        ...     _ = save_descriptor(net, d, input_size=32)
        ...     load_descriptor(d)[1]["dim"]
        4
    """
    meta = {"version": _VERSION, **net.config(), **config}
    return write_network_folder(net, out, DESCRIPTOR_FORMAT, meta)


def write_network_folder(net: nn.Module, out: str | Path, fmt: str, meta: dict[str, Any]) -> Path:
    """Write ``model.safetensors`` (float32) and ``config.json`` (``meta`` tagged ``fmt``)."""
    from safetensors.torch import save_file

    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu().float().contiguous() for k, v in net.state_dict().items()}
    text = json.dumps({"format": fmt, **meta}, indent=2, sort_keys=True) + "\n"
    atomic_write(folder / _WEIGHTS, lambda tmp: save_file(state, tmp, metadata={"format": fmt}))
    atomic_write(folder / _CONFIG, lambda tmp: tmp.write_text(text))
    return folder


def read_network_config(folder: Path, fmt: str, what: str) -> dict[str, Any]:
    """A folder's ``config.json``, checked to be of format ``fmt`` and a readable version.

    Raises:
        CheckpointError: not JSON, another format (``what`` names the expected one), or newer.
    """
    try:
        cfg = json.loads((folder / _CONFIG).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise CheckpointError(f"{folder / _CONFIG} is not valid JSON: {err}") from err
    if not isinstance(cfg, dict) or cfg.get("format") != fmt:
        raise CheckpointError(
            f"{folder / _CONFIG} is not a {what} configuration "
            f"(format {cfg.get('format') if isinstance(cfg, dict) else None!r}, expected {fmt!r})"
        )
    if int(cfg.get("version", 0)) > _VERSION:
        raise CheckpointError(
            f"{folder / _CONFIG} has version {cfg['version']}; this poseflow reads up to "
            f"{_VERSION}: upgrade poseflow"
        )
    return cfg


def load_network_weights(net: nn.Module, folder: Path) -> None:
    """Load ``folder/model.safetensors`` into ``net`` strictly.

    Raises:
        CheckpointError: the file cannot be read or does not fit ``net``.
    """
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    try:
        state = load_file(str(folder / _WEIGHTS))
    except (OSError, SafetensorError) as err:
        raise CheckpointError(f"{folder / _WEIGHTS} cannot be read: {err}") from err
    try:
        net.load_state_dict(state, strict=True)
    except RuntimeError as err:
        raise CheckpointError(
            f"{folder / _WEIGHTS} does not fit {folder / _CONFIG}: {str(err).splitlines()[0]}"
        ) from err


def load_descriptor(folder: str | Path) -> tuple[DescriptorNet, dict[str, Any]]:
    """Read a descriptor folder written by :func:`save_descriptor`.

    Args:
        folder: the folder with ``model.safetensors`` and ``config.json``.

    Returns:
        ``(network, config)``: the network in evaluation mode on the CPU, and the parsed
        ``config.json``.

    Raises:
        MissingWeightsError: the folder or one of its two files is missing.
        CheckpointError: a file is corrupt, of another format, or the weights do not fit the
            configuration.
    """
    folder = Path(folder)
    if not folder.is_dir():
        shipped = folder == SHIPPED_DESCRIPTOR_DIR
        what = "the package ships no learned descriptor weights" if shipped else "no folder"
        raise MissingWeightsError(f"learned descriptor: {what} at {folder}; {_HOW_TO_MAKE}")
    for name in (_CONFIG, _WEIGHTS):
        if not (folder / name).is_file():
            raise MissingWeightsError(
                f"learned descriptor folder {folder} lacks {name}; {_HOW_TO_MAKE}"
            )
    cfg = read_network_config(folder, DESCRIPTOR_FORMAT, "learned descriptor")
    try:
        net = DescriptorNet(
            widths=cfg["widths"],
            dim=int(cfg["dim"]),
            out_stride=int(cfg["out_stride"]),
            in_channels=int(cfg.get("in_channels", 3)),
        )
    except (KeyError, TypeError, ValueError) as err:
        raise CheckpointError(f"{folder / _CONFIG} has bad network sizes: {err!r}") from err
    load_network_weights(net, folder)
    return net.eval(), cfg
