"""Data: object models, default demo objects, BOP datasets and the synthetic scene generator."""

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
    "MeshFormatError",
    "ObjectModel",
    "discretize_symmetries",
    "load_mesh",
    "mesh_vertex_arrays",
    "sample_surface",
    "symmetries_from_info",
    "write_bop_model",
    "write_bop_models",
]
