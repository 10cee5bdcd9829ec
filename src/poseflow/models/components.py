"""Frozen parts of FunFlow6D built from the configuration's names."""

from __future__ import annotations

from typing import Any

from poseflow.errors import ValueRangeError
from poseflow.features import (
    DenseSIFTEncoder,
    DINOv2Encoder,
    FPFHEncoder,
    GeDiEncoder,
    IdentityReducer,
    PCAReducer,
    UMAPReducer,
)

__all__ = ["build_appearance_encoder", "build_geometric_encoder", "build_reducer"]


def build_geometric_encoder(name: str, *, radii: tuple[float, ...]) -> Any:
    """``"fpfh"``, ``"gedi:PATH"`` or ``"none"`` (returns None).

    Example:
        >>> build_geometric_encoder("fpfh", radii=(0.3, 0.4)).dim
        66
    """
    kind, _, arg = name.partition(":")
    if kind == "none":
        return None
    if kind == "fpfh":
        return FPFHEncoder(radius_fractions=radii)
    if kind == "gedi":
        if not arg:
            raise ValueRangeError("gedi needs its weights: geometric_encoder='gedi:/path/to/file'")
        return GeDiEncoder.from_checkpoint(arg)
    raise ValueRangeError(f"unknown geometric encoder {name!r}; use 'fpfh', 'gedi:PATH' or 'none'")


def build_appearance_encoder(name: str, *, crop_size: int) -> Any:
    """``"dsift"``, ``"dinov2:NAME_OR_PATH"`` or ``"none"`` (returns None).

    Example:
        >>> build_appearance_encoder("dsift", crop_size=64).dim
        128
    """
    kind, _, arg = name.partition(":")
    if kind == "none":
        return None
    if kind == "dsift":
        return DenseSIFTEncoder(input_size=crop_size)
    if kind == "dinov2":
        return DINOv2Encoder(arg or "vits14", input_size=crop_size)
    raise ValueRangeError(
        f"unknown appearance encoder {name!r}; use 'dsift', 'dinov2:NAME_OR_PATH' or 'none'"
    )


def build_reducer(name: str, *, n_components: int, seed: int = 0) -> Any:
    """``"umap"``, ``"pca"`` or ``"identity"`` (unfitted).

    Example:
        >>> type(build_reducer("pca", n_components=8)).__name__
        'PCAReducer'
    """
    if name == "umap":
        return UMAPReducer(n_components=n_components, random_state=seed)
    if name == "pca":
        return PCAReducer(n_components)
    if name == "identity":
        return IdentityReducer()
    raise ValueRangeError(f"unknown reducer {name!r}; use 'umap', 'pca' or 'identity'")
