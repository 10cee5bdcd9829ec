"""The detector's network: a small RGB-D U-Net with three dense heads (Panoptic-DeepLab style).

Shape letters: B batch, C input channels, K objects, H/W image rows/columns, h/w head rows/columns
(half the input's).

The input (:func:`detector_inputs`) is the image resampled to a fixed focal length (so an object
appears at the same size whatever the camera), with its depth as relative depth, a validity flag
and the depth's slopes. The heads, at half the input's resolution:

- ``semantic`` ``(B, K + 1, h, w)``: logits of background and of each object,
- ``centres`` ``(B, K, h, w)``: logits of a heatmap that peaks at each instance's centre (the mean
  of its visible pixels), one channel per object,
- ``offsets`` ``(B, 2, h, w)``: from each pixel to its instance's centre, in head pixels ``(x, y)``.

:func:`~poseflow.detect.grouping.group_instances` turns them into instance masks.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["INPUT_CHANNELS", "InstanceSegmenter", "detector_inputs", "resample_to_focal"]

#: Channels of :func:`detector_inputs`: RGB, relative depth, validity, two depth slopes.
INPUT_CHANNELS = 7

#: Metres of relative depth mapped to one unit of the input (clipped at two units).
_DEPTH_UNIT = 0.25


def detector_inputs(rgb: torch.Tensor, depth: torch.Tensor, focal: torch.Tensor) -> torch.Tensor:
    """The network's input channels from colour and depth at the same resolution.

    Args:
        rgb: colour in ``[0, 1]`` ``(B, 3, H, W)``.
        depth: metres, 0 where missing ``(B, H, W)``.
        focal: the focal length in pixels of this resolution ``(B,)``.

    Returns:
        ``(B, 7, H, W)``: RGB centred, depth minus the image's median valid depth (in units of
        0.25 m, clipped to ±2), the validity flag, and the depth's slopes along x and y (the
        tangent of the surface's tilt, through tanh), 0 where depth is missing.

    Example:
        >>> f = torch.tensor([5.0, 5.0])
        >>> x = detector_inputs(torch.rand(2, 3, 8, 8), torch.ones(2, 8, 8), f)
        >>> x.shape, bool(x[:, 3].abs().max() == 0), bool(x[:, 4].min() == 1)
        (torch.Size([2, 7, 8, 8]), True, True)
    """
    valid = depth > 0
    z = torch.where(valid, depth, torch.full_like(depth, float("nan")))
    median = z.flatten(1).nanmedian(dim=1).values.nan_to_num(0.0)
    relative = ((depth - median[:, None, None]) / _DEPTH_UNIT).clamp(-2, 2)
    relative = torch.where(valid, relative, torch.zeros_like(relative))
    scale = focal[:, None, None] / z.clamp_min(1e-3)
    slope_x = torch.zeros_like(depth)
    slope_y = torch.zeros_like(depth)
    slope_x[:, :, 1:-1] = (z[:, :, 2:] - z[:, :, :-2]) / 2 * scale[:, :, 1:-1]
    slope_y[:, 1:-1] = (z[:, 2:] - z[:, :-2]) / 2 * scale[:, 1:-1]
    slopes = torch.stack([slope_x, slope_y], dim=1).nan_to_num(0.0).clamp(-10, 10).tanh()
    return torch.cat(
        [(rgb - 0.5) / 0.25, relative[:, None], valid[:, None].to(rgb.dtype), slopes.to(rgb.dtype)],
        dim=1,
    )


def resample_to_focal(
    rgb: torch.Tensor,
    depth: torch.Tensor,
    focal: float,
    input_focal: float,
    idmap: torch.Tensor | None = None,
) -> tuple[torch.Tensor, ...]:
    """An image resampled so that its focal length becomes ``input_focal``.

    Colour is resampled with antialiasing, depth and the instance map by nearest neighbour (no
    depth mixed across an edge).

    Args:
        rgb: colour ``(3, H, W)`` float.
        depth: metres ``(H, W)``.
        focal: the image's focal length in pixels (``fy``).
        input_focal: the focal length to resample to.
        idmap: an instance map ``(H, W)`` uint8 to resample alike, or None.

    Returns:
        ``(rgb, depth)`` (and the instance map) at ``round(H * s), round(W * s)``,
        ``s = input_focal / focal``.
    """
    s = input_focal / focal
    size = (max(1, round(rgb.shape[-2] * s)), max(1, round(rgb.shape[-1] * s)))
    rgb_s = F.interpolate(rgb[None], size=size, mode="bilinear", antialias=True)[0].clamp(0, 1)
    depth_s = F.interpolate(depth[None, None], size=size, mode="nearest-exact")[0, 0]
    if idmap is None:
        return rgb_s, depth_s
    map_s = F.interpolate(idmap[None, None].float(), size=size, mode="nearest-exact")[0, 0]
    return rgb_s, depth_s, map_s.to(torch.uint8)


def _block(c_in: int, c_out: int, stride: int = 1, dilation: int = 1) -> nn.Sequential:
    """Conv 3x3, batch norm, ReLU."""
    return nn.Sequential(
        nn.Conv2d(c_in, c_out, 3, stride, padding=dilation, dilation=dilation, bias=False),
        nn.BatchNorm2d(c_out),
        nn.ReLU(inplace=True),
    )


class InstanceSegmenter(nn.Module):
    """U-Net encoder (strides 2-32) and decoder back to stride 2, with three 1x1 heads.

    Args:
        num_objects: K, the objects it tells apart (plus background).
        widths: channels at strides 2, 4, 8, 16 and 32 of the input.

    Shape:
        - input: ``(B, 7, H, W)`` with H and W multiples of 32 (:func:`detector_inputs`).
        - output: ``semantic (B, K + 1, H/2, W/2)``, ``centres (B, K, H/2, W/2)``,
          ``offsets (B, 2, H/2, W/2)``.

    Example:
        >>> net = InstanceSegmenter(3, widths=(8, 8, 8, 8, 8))
        >>> sem, cen, off = net(torch.zeros(1, 7, 64, 96))
        >>> sem.shape, cen.shape, off.shape
        (torch.Size([1, 4, 32, 48]), torch.Size([1, 3, 32, 48]), torch.Size([1, 2, 32, 48]))
    """

    def __init__(self, num_objects: int, *, widths: tuple[int, ...] = (24, 32, 48, 64, 96)) -> None:
        super().__init__()
        w2, w4, w8, w16, w32 = widths
        self.num_objects = num_objects
        self.down2 = nn.Sequential(_block(INPUT_CHANNELS, w2, 2), _block(w2, w2))
        self.down4 = nn.Sequential(_block(w2, w4, 2), _block(w4, w4))
        self.down8 = nn.Sequential(_block(w4, w8, 2), _block(w8, w8))
        self.down16 = nn.Sequential(_block(w8, w16, 2), _block(w16, w16))
        self.down32 = nn.Sequential(_block(w16, w32, 2), _block(w32, w32, dilation=2))
        self.up16 = _block(w32 + w16, w16)
        self.up8 = _block(w16 + w8, w8)
        self.up4 = _block(w8 + w4, w4)
        fine = max(w2 // 2, 8)
        self.up2 = nn.Sequential(
            nn.Conv2d(w4, fine, 1, bias=False), nn.BatchNorm2d(fine), nn.ReLU()
        )
        self.fuse2 = _block(fine + w2, fine)
        self.semantic = nn.Conv2d(fine, num_objects + 1, 1)
        self.centres = nn.Conv2d(fine, num_objects, 1)
        self.offsets = nn.Conv2d(fine, 2, 1)
        nn.init.constant_(self.centres.bias, -4.0)  # heatmaps start near 0 (focal loss prior)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Semantic logits, centre logits and offsets at half the input's resolution."""
        s2 = self.down2(x)
        s4 = self.down4(s2)
        s8 = self.down8(s4)
        s16 = self.down16(s8)
        s32 = self.down32(s16)
        d16 = self.up16(torch.cat([_upsample(s32, s16), s16], dim=1))
        d8 = self.up8(torch.cat([_upsample(d16, s8), s8], dim=1))
        d4 = self.up4(torch.cat([_upsample(d8, s4), s4], dim=1))
        d2 = self.fuse2(torch.cat([self.up2(_upsample(d4, s2)), s2], dim=1))
        return self.semantic(d2), self.centres(d2), self.offsets(d2)


def _upsample(x: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    return F.interpolate(x, size=like.shape[-2:], mode="bilinear", align_corners=False)
