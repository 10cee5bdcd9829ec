"""Data: object models, default demo objects, BOP datasets and the synthetic scene generator.

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
from poseflow.data.synthetic import DepthNoise, SyntheticObject, generate_dataset

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
    "GTInfo",
    "GTPose",
    "ModelInfo",
    "ObjectModel",
    "SyntheticObject",
    "TestTarget",
    "collate_images",
    "demo_mesh",
    "demo_objects",
    "discretize_symmetries",
    "generate_dataset",
    "load_mesh",
    "mesh_vertex_arrays",
    "read_detections",
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
