"""Data: object models, demo objects, BOP datasets, single frames, the synthetic scene generator.

Units are metres inside the library; BOP files (millimetres) are converted when read and written.
"""

from poseflow.data.bop import (
    BOPDataset,
    BOPDataWarning,
    BOPDetectionDataset,
    BOPImageDataset,
    BOPInstanceDataset,
    BOPScene,
    BOPWriter,
    CameraInfo,
    ContinuousSymmetry,
    Detection,
    GTInfo,
    GTPose,
    ModelInfo,
    TestTarget,
    collate_images,
    read_detections,
    read_models_info,
    read_test_targets,
)
from poseflow.data.demo_objects import (
    DEMO_OBJECT_NAMES,
    demo_mesh,
    demo_objects,
    write_demo_models,
)
from poseflow.data.depth_noise import DepthNoise
from poseflow.data.frame import (
    Frame,
    ImageInstances,
    read_color,
    read_frame,
    read_intrinsics,
    read_masks,
    read_metric_depth,
)
from poseflow.data.object_folder import (
    check_dataset,
    dataset_fingerprint,
    load_object_models,
    models_fingerprint,
    object_cache_dir,
)
from poseflow.data.objects import (
    ObjectModel,
    discretize_symmetries,
    load_mesh,
    mesh_vertex_arrays,
    sample_surface,
    symmetries_from_info,
    write_bop_model,
    write_bop_models,
)
from poseflow.data.rle import rle_decode, rle_encode
from poseflow.data.synthetic import generate_dataset
from poseflow.data.synthetic_objects import SyntheticObject

__all__ = [
    "DEMO_OBJECT_NAMES",
    "BOPDataWarning",
    "BOPDataset",
    "BOPDetectionDataset",
    "BOPImageDataset",
    "BOPInstanceDataset",
    "BOPScene",
    "BOPWriter",
    "CameraInfo",
    "ContinuousSymmetry",
    "DepthNoise",
    "Detection",
    "Frame",
    "GTInfo",
    "GTPose",
    "ImageInstances",
    "ModelInfo",
    "ObjectModel",
    "SyntheticObject",
    "TestTarget",
    "check_dataset",
    "collate_images",
    "dataset_fingerprint",
    "demo_mesh",
    "demo_objects",
    "discretize_symmetries",
    "generate_dataset",
    "load_mesh",
    "load_object_models",
    "mesh_vertex_arrays",
    "models_fingerprint",
    "object_cache_dir",
    "read_color",
    "read_detections",
    "read_frame",
    "read_intrinsics",
    "read_masks",
    "read_metric_depth",
    "read_models_info",
    "read_test_targets",
    "rle_decode",
    "rle_encode",
    "sample_surface",
    "symmetries_from_info",
    "write_bop_model",
    "write_bop_models",
    "write_demo_models",
]
