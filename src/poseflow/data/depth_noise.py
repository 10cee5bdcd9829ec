"""A depth-sensor model: depth- and angle-dependent Gaussian noise plus missing pixels."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage

from poseflow.data._arrays import as_numpy
from poseflow.errors import ShapeError, ValueRangeError

__all__ = ["DepthNoise"]


@dataclass(frozen=True)
class DepthNoise:
    """Depth-sensor corruption: depth- and angle-dependent Gaussian noise plus missing pixels.

    The noise follows the axial model measured for the Kinect by Nguyen, Izadi and Lovell (2012),
    ``sigma(z, a) = sigma_base + sigma_quadratic (z - reference_depth)^2
    + sigma_angle / sqrt(z) * a^2 / (pi/2 - a)^2`` metres, with ``a`` the angle between the
    surface normal and the viewing ray. Measurements are removed (depth 0) at grazing angles
    (probability rising linearly from 0 at ``grazing_start_deg`` to 1 at ``grazing_end_deg``), in
    a band of ``edge_width`` pixels along depth discontinuities larger than ``edge_jump`` metres or
    against the background (with probability ``edge_dropout``), and anywhere with probability
    ``random_dropout``.

    Example:
        >>> noise = DepthNoise()
        >>> depth = torch.full((20, 20), 0.8)
        >>> normals = torch.zeros(20, 20, 3); normals[..., 2] = -1.0
        >>> K = torch.tensor([[50.0, 0, 9.5], [0, 50.0, 9.5], [0, 0, 1]])
        >>> noisy = noise.apply(depth, normals, K, rng=0)
        >>> bool(((noisy - depth).abs() < 0.02).all()), noisy.dtype
        (True, torch.float32)
    """

    sigma_base: float = 0.0012
    sigma_quadratic: float = 0.0019
    reference_depth: float = 0.4
    sigma_angle: float = 0.0001
    grazing_start_deg: float = 70.0
    grazing_end_deg: float = 85.0
    edge_jump: float = 0.01
    edge_width: int = 1
    edge_dropout: float = 0.8
    random_dropout: float = 0.001

    def __post_init__(self) -> None:
        for name in ("sigma_base", "sigma_quadratic", "sigma_angle", "edge_jump"):
            if not getattr(self, name) >= 0:
                raise ValueRangeError(f"{name} must be non-negative, got {getattr(self, name)}")
        for name in ("edge_dropout", "random_dropout"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueRangeError(f"{name} must lie in [0, 1], got {getattr(self, name)}")
        if not 0 <= self.grazing_start_deg < self.grazing_end_deg <= 90:
            raise ValueRangeError("need 0 <= grazing_start_deg < grazing_end_deg <= 90")
        if self.edge_width < 0:
            raise ValueRangeError(f"edge_width must be >= 0, got {self.edge_width}")

    def sigma(self, depth: np.ndarray, angle: np.ndarray) -> np.ndarray:
        """Standard deviation in metres for depths and incidence angles (radians), numpy."""
        a = np.minimum(angle, np.deg2rad(89.0))
        z = np.maximum(depth, 1e-6)
        return (
            self.sigma_base
            + self.sigma_quadratic * (z - self.reference_depth) ** 2
            + self.sigma_angle / np.sqrt(z) * a**2 / (np.pi / 2 - a) ** 2
        )

    def apply(
        self,
        depth: torch.Tensor | np.ndarray,
        normals: torch.Tensor | np.ndarray,
        K: torch.Tensor | np.ndarray,
        *,
        rng: np.random.Generator | int | None = None,
    ) -> torch.Tensor:
        """Corrupt a clean depth map.

        Args:
            depth: clean z-depth ``(H, W)`` in metres, 0 where nothing was hit.
            normals: camera-frame unit normals ``(H, W, 3)`` (the renderer's ``normals``).
            K: intrinsics ``(3, 3)``.
            rng: numpy generator or seed.

        Returns:
            Noisy depth ``(H, W)`` float32 in metres, 0 where missing.
        """
        d = as_numpy(depth, np.float64)
        n = as_numpy(normals, np.float64)
        if d.ndim != 2 or n.shape != (*d.shape, 3):
            raise ShapeError(f"depth must be (H, W) and normals (H, W, 3), got {d.shape} {n.shape}")
        rng = np.random.default_rng(rng)
        h, w = d.shape
        hit = np.isfinite(d) & (d > 0)
        Kinv = np.linalg.inv(as_numpy(K, np.float64).reshape(3, 3))
        uu, vv = np.meshgrid(np.arange(w), np.arange(h))
        rays = np.stack([uu, vv, np.ones_like(uu)], axis=-1).astype(np.float64) @ Kinv.T
        rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
        cos = np.abs(np.einsum("hwc,hwc->hw", rays, n))
        angle = np.arccos(np.clip(cos, 0.0, 1.0))
        out = d + rng.standard_normal(d.shape) * self.sigma(d, angle)
        a0, a1 = np.deg2rad(self.grazing_start_deg), np.deg2rad(self.grazing_end_deg)
        p_drop = np.clip((angle - a0) / (a1 - a0), 0.0, 1.0)
        drop = rng.random(d.shape) < np.maximum(p_drop, self.random_dropout)
        if self.edge_width > 0 and self.edge_dropout > 0:
            z = np.where(hit, d, np.inf)
            edge = np.zeros_like(hit)
            for axis in (0, 1):
                with np.errstate(invalid="ignore"):
                    diff = np.abs(np.diff(z, axis=axis))
                jump = ~(diff <= self.edge_jump)  # inf - inf is nan: background stays no-edge
                both_bg = ~hit[1:, :] & ~hit[:-1, :] if axis == 0 else ~hit[:, 1:] & ~hit[:, :-1]
                jump &= ~both_bg
                if axis == 0:
                    edge[1:, :] |= jump
                    edge[:-1, :] |= jump
                else:
                    edge[:, 1:] |= jump
                    edge[:, :-1] |= jump
            if self.edge_width > 1:
                edge = ndimage.binary_dilation(edge, iterations=self.edge_width - 1)
            drop |= edge & (rng.random(d.shape) < self.edge_dropout)
        out = np.where(hit & ~drop & (out > 0), out, 0.0)
        return torch.from_numpy(out.astype(np.float32))
