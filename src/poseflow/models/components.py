"""Frozen parts of FunFlow6D built from the configuration's names, and the names they accept.

Each ``build_*`` factory reads one configuration string; the matching tuple
(:data:`GEOMETRIC_ENCODERS`, :data:`APPEARANCE_ENCODERS`, :data:`REDUCERS`) lists the kinds it
knows (``"kind"`` or ``"kind:ARGUMENT"``), so that :class:`~poseflow.models.FunFlow6DConfig` can
reject an unknown name when it is built (:func:`check_name`).
"""

from __future__ import annotations

from torch import nn

from poseflow.errors import ValueRangeError
from poseflow.features import (
    AppearanceEncoder,
    DenseSIFTEncoder,
    DINOv2Encoder,
    FPFHEncoder,
    GeDiEncoder,
    GeometricEncoder,
    IdentityReducer,
    LearnedAppearanceEncoder,
    PCAReducer,
    Reducer,
    SurfaceEmbeddingEncoder,
    UMAPReducer,
)

__all__ = [
    "APPEARANCE_ENCODERS",
    "GEOMETRIC_ENCODERS",
    "REDUCERS",
    "build_appearance_encoder",
    "build_geometric_encoder",
    "build_reducer",
    "check_name",
    "encoder_networks",
]

#: Kinds of :func:`build_geometric_encoder` (``"gedi"`` is written ``"gedi:PATH"``).
GEOMETRIC_ENCODERS: tuple[str, ...] = ("fpfh", "gedi", "none")
#: Kinds of :func:`build_appearance_encoder` (``"dinov2"`` takes ``":NAME_OR_PATH"``,
#: ``"learned"`` an optional ``":FOLDER"``, ``"surface"`` a ``":FOLDER"``).
APPEARANCE_ENCODERS: tuple[str, ...] = ("dsift", "dinov2", "learned", "surface", "none")
#: Names of :func:`build_reducer`.
REDUCERS: tuple[str, ...] = ("umap", "pca", "identity")


def check_name(
    field: str, name: str, allowed: tuple[str, ...], *, takes_argument: bool = False
) -> tuple[str, str]:
    """Check that a configured name is one of a registry's.

    Args:
        field: the configuration field, for the message.
        name: the configured name.
        allowed: the allowed names.
        takes_argument: ``name`` may be ``"kind:ARGUMENT"`` (an encoder's weights).

    Returns:
        ``(kind, argument)``; the argument is empty without one.

    Raises:
        ValueRangeError: an unknown name; the message lists the allowed ones.

    Example:
        >>> check_name("appearance_encoder", "dinov2:vits14", APPEARANCE_ENCODERS,
        ...            takes_argument=True)
        ('dinov2', 'vits14')
    """
    if not isinstance(name, str):
        raise ValueRangeError(f"{field} must be a name (a string), got {name!r}")
    kind, _, argument = name.partition(":") if takes_argument else (name, "", "")
    if kind not in allowed:
        raise ValueRangeError(f"{field} must be one of {', '.join(allowed)}; got {name!r}")
    return kind, argument


def build_geometric_encoder(name: str, *, radii: tuple[float, ...]) -> GeometricEncoder | None:
    """``"fpfh"``, ``"gedi:PATH"`` or ``"none"`` (returns None).

    Raises:
        ValueRangeError: an unknown name, or ``"gedi"`` without a path.

    Example:
        >>> build_geometric_encoder("fpfh", radii=(0.3, 0.4)).dim
        66
    """
    kind, path = check_name("geometric_encoder", name, GEOMETRIC_ENCODERS, takes_argument=True)
    if kind == "fpfh":
        return FPFHEncoder(radius_fractions=radii)
    if kind == "gedi":
        if not path:
            raise ValueRangeError("gedi needs its weights: geometric_encoder='gedi:/path/to/file'")
        return GeDiEncoder.from_checkpoint(path)
    return None


def build_appearance_encoder(name: str, *, crop_size: int) -> AppearanceEncoder | None:
    """An appearance encoder by name (``"none"``: None).

    ``"dsift"``, ``"dinov2:NAME_OR_PATH"``, ``"learned[:FOLDER]"`` or ``"surface:FOLDER"``:
    ``"learned"`` is the descriptor shipped with the package, ``"learned:FOLDER"`` one made by
    ``python -m poseflow.features.descriptor_training --out FOLDER``; ``"surface:FOLDER"`` a
    surface embedding of the user's objects made by ``poseflow train-surface TRAIN_DATASET
    --out FOLDER``.

    Raises:
        ValueRangeError: an unknown name, or ``"surface"`` without a folder.
        MissingWeightsError: ``"learned"`` or ``"surface"`` weights that are not there.

    Example:
        >>> build_appearance_encoder("dsift", crop_size=64).dim
        128
    """
    kind, weights = check_name("appearance_encoder", name, APPEARANCE_ENCODERS, takes_argument=True)
    if kind == "dsift":
        return DenseSIFTEncoder(input_size=crop_size)
    if kind == "dinov2":
        return DINOv2Encoder(weights or "vits14", input_size=crop_size)
    if kind == "learned":
        return LearnedAppearanceEncoder(weights or None, input_size=crop_size)
    if kind == "surface":
        if not weights:
            raise ValueRangeError(
                "appearance_encoder 'surface' needs its folder: 'surface:FOLDER', made by "
                "`poseflow train-surface TRAIN_DATASET --out FOLDER`"
            )
        return SurfaceEmbeddingEncoder(weights, input_size=crop_size)
    return None


def build_reducer(name: str, *, n_components: int, seed: int = 0) -> Reducer:
    """``"umap"``, ``"pca"`` or ``"identity"`` (unfitted).

    Raises:
        ValueRangeError: an unknown name.

    Example:
        >>> type(build_reducer("pca", n_components=8)).__name__
        'PCAReducer'
    """
    check_name("reducer", name, REDUCERS)
    if name == "umap":
        return UMAPReducer(n_components=n_components, random_state=seed)
    if name == "pca":
        return PCAReducer(n_components)
    return IdentityReducer()


def encoder_networks(**encoders: object) -> dict[str, nn.Module]:
    """The networks inside frozen encoders, named ``{encoder}_{attribute}``.

    An encoder is a plain object that holds its network (DINOv2's ``model``, the learned
    descriptor's ``net``, ...); a model moves these with itself (``.to()``, ``load(device=)``).

    Example:
        >>> from poseflow.features.learned import DescriptorNet, LearnedAppearanceEncoder
        >>> net = DescriptorNet(widths=(8, 16), dim=4, out_stride=2)
        >>> enc = LearnedAppearanceEncoder(net, input_size=32)
        >>> list(encoder_networks(appearance=enc, geometric=None))
        ['appearance_net']
    """
    return {
        f"{name}_{attr}": value
        for name, encoder in encoders.items()
        if encoder is not None
        for attr, value in vars(encoder).items()
        if isinstance(value, nn.Module)
    }
