"""Appearance encoders Θ: dense image features, and their transfer to pixels.

Every encoder follows :class:`AppearanceEncoder`: ``encode(images)`` maps RGB images
``(B, 3, H, W)`` with values in ``[0, 1]`` to a dense feature map ``(B, G, h, w)`` that covers the
image uniformly (feature cell ``j`` of ``w`` spans image columns ``[j W / w, (j + 1) W / w)``).
:func:`sample_features` reads the map at sub-pixel positions (bilinear), :func:`upsample_features`
resizes it to the image.

- :class:`DINOv2Encoder`: DINOv2 through ``transformers`` (ViT-S/B/L/G, patch 14), any layer,
  with or without the final layer norm. Weights come from a local directory or the local
  Hugging Face cache; nothing is downloaded unless asked.
- :class:`DenseSIFTEncoder`: kornia's dense SIFT, weight-free, the offline default. SIFT is not
  rotation-invariant, so its query features are kept per view and per in-plane roll
  (``query_pooling = "select"``, see :mod:`poseflow.features.lifting`) instead of averaged.

Shape letters: B images, G channels, h × w feature grid, P sampled positions.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal, Protocol, runtime_checkable

import torch
from torch import nn
from torch.nn import functional as F

from poseflow._checks import check_tensor
from poseflow.errors import MissingDependencyError, MissingWeightsError, ValueRangeError

__all__ = [
    "DINOV2_MODELS",
    "AppearanceEncoder",
    "DINOv2Encoder",
    "DenseSIFTEncoder",
    "features_at",
    "sample_features",
    "upsample_features",
]

#: Short names of the public DINOv2 backbones and their Hugging Face repositories.
DINOV2_MODELS = {
    "vits14": "facebook/dinov2-small",
    "vitb14": "facebook/dinov2-base",
    "vitl14": "facebook/dinov2-large",
    "vitg14": "facebook/dinov2-giant",
}

_IMAGENET_MEAN = (0.485, 0.456, 0.406)
_IMAGENET_STD = (0.229, 0.224, 0.225)


@runtime_checkable
class AppearanceEncoder(Protocol):
    """What the pipeline needs from an appearance encoder.

    Attributes:
        dim: the feature size ``G``.
        input_size: side of the square images the encoder is fed (crops are resized to it).
        query_pooling: how the query model's multi-view features should be aggregated: ``"mean"``
            (average the views, the paper's choice for DINOv2) or ``"select"`` (keep every view
            and pick, per target instance, the views that match it; for descriptors that change
            with the in-plane rotation).

    An encoder that is a neural network may also set ``autocast = True``: FunFlow6D then runs
    it under its ``appearance_precision`` (bfloat16 where the device computes it natively).
    """

    dim: int
    input_size: int
    query_pooling: str

    def encode(self, images: torch.Tensor) -> torch.Tensor:
        """Dense features: ``(B, 3, H, W)`` in ``[0, 1]`` → ``(B, G, h, w)``."""
        ...


def sample_features(
    features: torch.Tensor, uv: torch.Tensor, image_size: tuple[int, int]
) -> torch.Tensor:
    """Bilinearly sample a dense feature map at pixel positions of the image it describes.

    Pixel ``(u, v)`` = (column, row) with integer values at pixel centres (OpenCV convention);
    the map is assumed to cover the ``H × W`` image uniformly. Positions outside the image read
    the border.

    Args:
        features: feature maps ``(B, G, h, w)``.
        uv: pixel positions ``(B, P, 2)`` in the image's coordinates.
        image_size: ``(H, W)`` of the image the map was computed from.

    Returns:
        Features ``(B, P, G)`` in the map's dtype.

    Example:
        >>> f = torch.arange(4.0).reshape(1, 1, 2, 2)  # a 2×2 map over a 4×4 image
        >>> sample_features(f, torch.tensor([[[0.5, 0.5], [2.5, 0.5], [1.5, 1.5]]]), (4, 4))
        tensor([[[0.0000],
                 [1.0000],
                 [1.5000]]])
    """
    sizes = check_tensor(features, "features", ("B", "G", None, None))
    check_tensor(uv, "uv", ("B", "P", 2), sizes=sizes)
    H, W = image_size
    scale = torch.tensor([2.0 / W, 2.0 / H], dtype=features.dtype, device=features.device)
    grid = (uv.to(features.dtype) + 0.5) * scale - 1.0
    out = F.grid_sample(
        features, grid[:, :, None, :], mode="bilinear", padding_mode="border", align_corners=False
    )
    return out[..., 0].transpose(1, 2)


def upsample_features(features: torch.Tensor, image_size: tuple[int, int]) -> torch.Tensor:
    """Resize dense features ``(B, G, h, w)`` to pixels ``(B, G, H, W)`` (bilinear).

    Example:
        >>> upsample_features(torch.rand(1, 8, 16, 16), (224, 224)).shape
        torch.Size([1, 8, 224, 224])
    """
    check_tensor(features, "features", ("B", "G", None, None))
    return F.interpolate(features, size=image_size, mode="bilinear", align_corners=False)


def network_input(
    images: torch.Tensor, network: nn.Module, size: int, channels: int = 3
) -> torch.Tensor:
    """Images ``(B, C, H, W)`` checked and made ready for a network encoder.

    Returns them on the network's device and in its dtype, resized to ``size × size``
    (bilinear, antialiased) unless already that size.

    Raises:
        ShapeError: not ``(B, channels, H, W)``.
        ValueRangeError: a value that is not finite.
    """
    check_tensor(images, "images", ("B", channels, None, None), finite=True)
    param = next(network.parameters())
    x = images.to(device=param.device, dtype=param.dtype)
    if x.shape[-2:] != (size, size):
        x = F.interpolate(
            x, size=(size, size), mode="bilinear", align_corners=False, antialias=True
        )
    return x


def _check_images(images: torch.Tensor) -> None:
    check_tensor(images, "images", ("B", 3, None, None), finite=True)


class DINOv2Encoder:
    """DINOv2 patch features through ``transformers.Dinov2Model``.

    Images are resized to ``input_size`` (a multiple of the patch size 14), normalised with the
    ImageNet statistics and run through the ViT; the patch tokens of ``layer`` (optionally passed
    through the model's final layer norm, and optionally L2-normalised) form a
    ``(B, G, input_size / 14, input_size / 14)`` map.

    Args:
        model: a short name (``"vits14"``, ``"vitb14"``, ``"vitl14"``, ``"vitg14"``), a
            Hugging Face repository id, a local directory with ``config.json`` and the weights, or
            a ready ``Dinov2Model`` (e.g. built from a ``Dinov2Config`` for tests).
        input_size: side of the square input in pixels.
        layer: which transformer block's output to read (1-based; negative counts from the end,
            ``-1`` is the last block).
        layernorm: apply the model's final layer norm to that layer's tokens.
        l2_normalize: L2-normalise every feature vector.
        local_files_only: never reach the network (the default); ``HF_HUB_OFFLINE=1`` is also
            honoured.
        device: where the model runs (defaults to CPU).

    Raises:
        MissingDependencyError: ``transformers`` is not installed.
        MissingWeightsError: the weights are not available locally; the message says how to get
            them.

    Example:
        >>> from transformers import Dinov2Config, Dinov2Model
        >>> cfg = Dinov2Config(hidden_size=32, num_hidden_layers=2, num_attention_heads=2,
        ...                    intermediate_size=64, image_size=28)
        >>> enc = DINOv2Encoder(Dinov2Model(cfg), input_size=28)
        >>> enc.encode(torch.rand(2, 3, 40, 40)).shape
        torch.Size([2, 32, 2, 2])
    """

    #: a network: FunFlow6D's ``appearance_precision`` applies (see :class:`AppearanceEncoder`)
    autocast = True

    query_pooling = "mean"

    def __init__(
        self,
        model: str | Path | nn.Module = "vits14",
        *,
        input_size: int = 224,
        layer: int = -1,
        layernorm: bool = True,
        l2_normalize: bool = False,
        local_files_only: bool = True,
        device: str | torch.device = "cpu",
    ) -> None:
        if isinstance(model, nn.Module):
            net = model
            cfg = model.config
            self.name = f"{type(model).__name__}({cfg.hidden_size}x{cfg.num_hidden_layers})"
        else:
            net = _load_dinov2(model, local_files_only=local_files_only)
            self.name = str(model)
        self.model = net.to(device).eval()
        config = self.model.config
        self.patch_size = int(config.patch_size)
        if input_size <= 0 or input_size % self.patch_size:
            raise ValueRangeError(
                f"input_size must be a positive multiple of {self.patch_size}, got {input_size}"
            )
        n_layers = int(config.num_hidden_layers)
        resolved = layer if layer > 0 else n_layers + 1 + layer
        if not 1 <= resolved <= n_layers:
            raise ValueRangeError(f"layer must be in [1, {n_layers}] or negative, got {layer}")
        self.input_size = int(input_size)
        self.layer = resolved
        self.layernorm = layernorm
        self.l2_normalize = l2_normalize
        self.dim = int(config.hidden_size)

    def __repr__(self) -> str:
        return (
            f"DINOv2Encoder({self.name!r}, dim={self.dim}, input_size={self.input_size}, "
            f"layer={self.layer}, "
            f"layernorm={self.layernorm}, l2_normalize={self.l2_normalize})"
        )

    @torch.no_grad()
    def encode(self, images: torch.Tensor) -> torch.Tensor:
        """Dense DINOv2 features.

        Args:
            images: RGB images ``(B, 3, H, W)`` with values in ``[0, 1]``.

        Returns:
            Features ``(B, G, s, s)`` with ``s = input_size / 14``, on the images' device and
            in their dtype.
        """
        x = network_input(images, self.model, self.input_size)
        mean = torch.tensor(_IMAGENET_MEAN, dtype=x.dtype, device=x.device)[:, None, None]
        std = torch.tensor(_IMAGENET_STD, dtype=x.dtype, device=x.device)[:, None, None]
        out = self.model(pixel_values=(x - mean) / std, output_hidden_states=True)
        tokens = out.hidden_states[self.layer]
        if self.layernorm:
            tokens = self.model.layernorm(tokens)
        s = self.input_size // self.patch_size
        patches = tokens[:, -s * s :]  # drop the class token
        feat = patches.transpose(1, 2).reshape(len(x), self.dim, s, s)
        if self.l2_normalize:
            feat = F.normalize(feat, dim=1)
        return feat.to(device=images.device, dtype=images.dtype)


def _load_dinov2(model: str | Path, *, local_files_only: bool) -> nn.Module:
    try:
        from transformers import Dinov2Model
    except ImportError as err:
        raise MissingDependencyError("transformers", "dinov2", "DINOv2Encoder") from err
    source = str(model)
    is_dir = Path(source).is_dir()
    repo = source if is_dir else DINOV2_MODELS.get(source, source)
    offline = local_files_only or os.environ.get("HF_HUB_OFFLINE", "0") not in ("", "0")
    try:
        return Dinov2Model.from_pretrained(repo, local_files_only=offline or is_dir)
    except (OSError, ValueError) as err:
        how = (
            f"the directory {repo} lacks config.json or the weights"
            if is_dir
            else f"'{repo}' is not in the local Hugging Face cache"
        )
        raise MissingWeightsError(
            f"DINOv2 weights unavailable: {how}. Download them on a machine with network "
            f"(`hf download {DINOV2_MODELS.get(source, repo)} --local-dir DIR`, or "
            "`huggingface-cli download ...`) and pass DIR, or allow downloading with "
            "local_files_only=False and HF_HUB_OFFLINE unset"
        ) from err


class DenseSIFTEncoder:
    """Dense SIFT descriptors (kornia), one per pixel: the weight-free appearance default.

    Images are resized to ``input_size``, converted to grey (or kept per colour channel), padded by
    reflection so that the descriptor grid has the image's size (descriptor ``(i, j)`` is centred
    on pixel ``(i − 0.5, j − 0.5)``, half a pixel off, negligible against its 16-pixel support) and
    described with kornia's ``DenseSIFTDescriptor`` (RootSIFT, 128-d per channel). Per-channel
    descriptors are concatenated and L2-normalised.

    SIFT's histogram grid is aligned with the image axes, so a descriptor changes when the object
    rolls in the image plane; ``query_pooling = "select"`` tells the lifting to keep per-view,
    per-roll query features (see :mod:`poseflow.features.lifting` and the measurements there).

    Args:
        input_size: side of the square input in pixels.
        color: ``"gray"`` (one 128-d descriptor) or ``"rgb"`` (one per channel, 384-d).
        spatial_bin_size: pixels per spatial bin (4 bins per side: the support is 4× this).

    Example:
        >>> enc = DenseSIFTEncoder(input_size=32)
        >>> enc.encode(torch.rand(2, 3, 50, 50)).shape
        torch.Size([2, 128, 32, 32])
    """

    query_pooling = "select"

    def __init__(
        self,
        *,
        input_size: int = 128,
        color: Literal["gray", "rgb"] = "gray",
        spatial_bin_size: int = 4,
    ) -> None:
        from kornia.feature import DenseSIFTDescriptor

        if color not in ("gray", "rgb"):
            raise ValueRangeError(f"color must be 'gray' or 'rgb', got {color!r}")
        if spatial_bin_size < 1:
            raise ValueRangeError(f"spatial_bin_size must be positive, got {spatial_bin_size}")
        span = 3 * spatial_bin_size - 1  # output = input + pads - span (kornia's geometry)
        if input_size <= span:
            raise ValueRangeError(f"input_size must exceed {span}, got {input_size}")
        self.input_size = int(input_size)
        self.color = color
        self.spatial_bin_size = int(spatial_bin_size)
        self._pad = ((span + 1) // 2, span // 2)
        self._sift = DenseSIFTDescriptor(spatial_bin_size=spatial_bin_size, padding=0)
        # Channels-last pooling weights make the descriptor map channels-last, so that the
        # normalisations over its 128 channels read contiguous memory (the same values, about
        # 20 % less time on the CPU).
        pooling = self._sift.PoolingConv.weight
        pooling.data = pooling.data.contiguous(memory_format=torch.channels_last)
        self.dim = 128 * (3 if color == "rgb" else 1)

    def __repr__(self) -> str:
        return (
            f"DenseSIFTEncoder(input_size={self.input_size}, color={self.color!r}, "
            f"spatial_bin_size={self.spatial_bin_size})"
        )

    @torch.no_grad()
    def encode(self, images: torch.Tensor) -> torch.Tensor:
        """Dense SIFT features.

        Args:
            images: RGB images ``(B, 3, H, W)`` with values in ``[0, 1]``.

        Returns:
            Features ``(B, G, input_size, input_size)`` with unit norm per pixel, on the images'
            device and in their dtype.
        """
        pooled = self._pooled(images)  # (B, C, 128, S, S)
        B, C, D, S, _ = pooled.shape
        desc = self._normalise(pooled.permute(0, 3, 4, 1, 2).reshape(B, S, S, C, D))
        return desc.permute(0, 3, 1, 2)

    @torch.no_grad()
    def encode_at(self, images: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
        """``sample_features(self.encode(images), uv, size)``, normalising only what it reads.

        The gradient histograms and their pooling are computed densely (convolutions); the
        RootSIFT normalisations, most of the cost of :meth:`encode`, only at the pixels around
        ``uv`` that the bilinear sampling reads.

        Args:
            images: RGB images ``(B, 3, H, W)`` with values in ``[0, 1]``.
            uv: pixel positions ``(B, P, 2)`` in the ``input_size`` image.

        Returns:
            Features ``(B, P, G)`` in the images' dtype.
        """
        check_tensor(uv, "uv", (len(images), "P", 2))
        pooled = self._pooled(images)
        B, C, D, S, _ = pooled.shape
        # The 3 × 3 pixels around each position cover the bilinear reads whatever the rounding.
        base = uv.to(pooled.dtype).clamp(0, S - 1).floor().long()
        step = torch.tensor([-1, 0, 1], device=uv.device)
        cols = (base[..., 0, None] + step).clamp(0, S - 1)  # (B, P, 3)
        rows = (base[..., 1, None] + step).clamp(0, S - 1)
        read = (rows[..., :, None] * S + cols[..., None, :]).reshape(B, -1)  # (B, 9P)
        per_pixel = pooled.permute(0, 3, 4, 1, 2).reshape(B, S * S, C * D)  # a view for grey
        picked = per_pixel.gather(1, read[..., None].expand(B, read.shape[1], C * D))
        desc = self._normalise(picked.reshape(B, -1, C, D))  # (B, 9P, G)
        sparse = desc.new_zeros(B, S * S, desc.shape[-1])
        sparse.scatter_(1, read[..., None].expand_as(desc), desc)
        sparse = sparse.transpose(1, 2).reshape(B, -1, S, S)
        return sample_features(sparse, uv, (S, S))

    def _pooled(self, images: torch.Tensor) -> torch.Tensor:
        """Spatially pooled gradient histograms before normalisation ``(B, C, 128, S, S)``."""
        _check_images(images)
        x = images
        if x.shape[-2:] != (self.input_size, self.input_size):
            x = F.interpolate(
                x, size=(self.input_size,) * 2, mode="bilinear", align_corners=False, antialias=True
            )
        if self.color == "gray":
            weights = torch.tensor([0.299, 0.587, 0.114], dtype=x.dtype, device=x.device)
            channels = (x * weights[:, None, None]).sum(dim=1, keepdim=True)
        else:
            channels = x.reshape(-1, 1, *x.shape[-2:])
        lo, hi = self._pad
        channels = F.pad(channels, (lo, hi, lo, hi), mode="reflect")
        sift = self._sift.to(x.device)
        histograms = sift.get_gradient_histograms(channels)  # (B·C, 8, H', W')
        n, bins = histograms.shape[:2]
        binning = sift.bin_pooling_kernel
        spread = F.conv2d(
            histograms.reshape(n * bins, 1, *histograms.shape[-2:]),
            binning.weight.to(x.dtype),
            None,
            padding=binning.padding,
        )
        spread = spread.reshape(n, bins, *spread.shape[-2:])
        pooling = sift.PoolingConv
        pooled = F.conv2d(  # (B·C, 128, S, S)
            spread,
            pooling.weight.to(x.dtype),
            None,
            pooling.stride,
            pooling.padding,
            pooling.dilation,
        )
        return pooled.reshape(len(x), -1, *pooled.shape[1:])

    def _normalise(self, desc: torch.Tensor) -> torch.Tensor:
        """RootSIFT of each channel's 128 bins, the channels concatenated and L2-normalised.

        Args:
            desc: pooled histograms ``(..., C, 128)``.

        Returns:
            Unit descriptors ``(..., C · 128)``.
        """
        eps = self._sift.eps
        desc = F.normalize(desc, dim=-1).clamp(0, float(self._sift.clipval))
        desc = F.normalize(desc, dim=-1)
        desc = torch.sqrt(F.normalize(desc, p=1, dim=-1, eps=1e-12) + eps)
        return F.normalize(desc.flatten(-2), dim=-1)


def features_at(encoder: AppearanceEncoder, images: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """An encoder's features at pixel positions of its input images ``(B, P, G)``.

    The same as :func:`sample_features` of ``encoder.encode(images)``; an encoder with an
    ``encode_at(images, uv)`` method (:class:`DenseSIFTEncoder`) computes only what is read.

    Args:
        encoder: the appearance encoder.
        images: ``(B, 3, S, S)`` at the encoder's ``input_size`` ``S``, values in ``[0, 1]``.
        uv: pixel positions ``(B, P, 2)``.
    """
    encode_at = getattr(encoder, "encode_at", None)
    if encode_at is not None:
        return encode_at(images, uv)
    return sample_features(encoder.encode(images), uv, tuple(images.shape[-2:]))
