"""Data: object models, default demo objects, BOP datasets and the synthetic scene generator."""

from poseflow.data.demo_objects import (
    DEMO_OBJECT_NAMES,
    demo_mesh,
    demo_objects,
    write_demo_models,
)
from poseflow.data.objects import (
    MeshFormatError,
    ObjectModel,
    discretize_symmetries,
    load_mesh,
    mesh_vertex_arrays,
    sample_surface,
    symmetries_from_info,
    write_bop_model,
    write_bop_models,
)

__all__ = [
    "DEMO_OBJECT_NAMES",
    "MeshFormatError",
    "ObjectModel",
    "demo_mesh",
    "demo_objects",
    "discretize_symmetries",
    "load_mesh",
    "mesh_vertex_arrays",
    "sample_surface",
    "symmetries_from_info",
    "write_bop_model",
    "write_bop_models",
    "write_demo_models",
]
