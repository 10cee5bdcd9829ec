"""Features: frozen geometric and appearance descriptors, pixel→point lifting, reducers.

The frozen half of FunFlow6D (paper, "Feature extraction"): per-point descriptors of the query
model ``Q`` and of the observed target ``T``.

- geometric encoders Φ (:class:`GeometricEncoder`): :class:`FPFHEncoder` (weight-free default;
  Open3D's FPFH batched in PyTorch by :func:`compute_fpfh`, normals by
  :func:`estimate_outward_normals`), :class:`GeDiEncoder` (GeDi in plain PyTorch, public weights
  from a local file), :class:`TorchScriptEncoder` / :class:`CallableEncoder` for any other
  per-point encoder;
- appearance encoders Θ (:class:`AppearanceEncoder`): :class:`DINOv2Encoder` (transformers),
  :class:`DenseSIFTEncoder` (weight-free default), :class:`LearnedAppearanceEncoder` (poseflow's
  own descriptor network, trained on generated renders by
  :mod:`poseflow.features.descriptor_training`), :class:`SurfaceEmbeddingEncoder` (queries of
  RGB-D crops against per-object surface keys, learned from renders of the user's objects by
  :mod:`poseflow.features.surface_training`; :func:`match_surface` pairs observed points with the
  surface points they show);
- lifting: :func:`lift_target_features` (crop around the barycentre), :func:`lift_query_features`
  (multi-view renderings → :class:`QueryFeatureBank`), cached per object by :class:`FeatureCache`;
- reduction (:class:`Reducer`): :class:`UMAPReducer` (umap-learn or, on CUDA, TorchDR fit; fast
  torch transform), :class:`PCAReducer`, :class:`IdentityReducer`, saved without pickle and
  reloaded by :func:`load_reducer`.
"""

from poseflow.features.appearance import (
    DINOV2_MODELS,
    AppearanceEncoder,
    DenseSIFTEncoder,
    DINOv2Encoder,
    features_at,
    sample_features,
    upsample_features,
)
from poseflow.features.cache import FeatureCache, cached_query_features
from poseflow.features.gedi import GeDiEncoder, GeDiNet
from poseflow.features.geometric import (
    CallableEncoder,
    FPFHEncoder,
    GeometricEncoder,
    TorchScriptEncoder,
    compute_fpfh,
    encode_on_support,
    estimate_outward_normals,
)
from poseflow.features.learned import (
    SHIPPED_DESCRIPTOR_DIR,
    DescriptorNet,
    LearnedAppearanceEncoder,
    depth_layers,
    load_descriptor,
    save_descriptor,
)
from poseflow.features.lifting import (
    QueryFeatureBank,
    lift_query_features,
    lift_target_features,
    viewpoint_poses,
)
from poseflow.features.reducers import (
    IdentityReducer,
    PCAReducer,
    Reducer,
    UMAPReducer,
    load_reducer,
)
from poseflow.features.surface import (
    SurfaceEmbedding,
    SurfaceEmbeddingEncoder,
    SurfaceKeys,
    load_surface_embedding,
    match_surface,
    save_surface_embedding,
)

__all__ = [
    "DINOV2_MODELS",
    "SHIPPED_DESCRIPTOR_DIR",
    "AppearanceEncoder",
    "CallableEncoder",
    "DINOv2Encoder",
    "DenseSIFTEncoder",
    "DescriptorNet",
    "FPFHEncoder",
    "FeatureCache",
    "GeDiEncoder",
    "GeDiNet",
    "GeometricEncoder",
    "IdentityReducer",
    "LearnedAppearanceEncoder",
    "PCAReducer",
    "QueryFeatureBank",
    "Reducer",
    "SurfaceEmbedding",
    "SurfaceEmbeddingEncoder",
    "SurfaceKeys",
    "TorchScriptEncoder",
    "UMAPReducer",
    "cached_query_features",
    "compute_fpfh",
    "depth_layers",
    "encode_on_support",
    "estimate_outward_normals",
    "features_at",
    "lift_query_features",
    "lift_target_features",
    "load_descriptor",
    "load_reducer",
    "load_surface_embedding",
    "match_surface",
    "sample_features",
    "save_descriptor",
    "save_surface_embedding",
    "upsample_features",
    "viewpoint_poses",
]
