"""Rendering: a CPU ray-casting renderer (depth, instance masks, textured RGB) on Open3D."""

from poseflow.render.backend import import_open3d
from poseflow.render.mesh import DEFAULT_COLOR, TexturedMesh, as_textured_mesh, sample_texture
from poseflow.render.raycast import Light, Renderer, RenderOutput, render

__all__ = [
    "DEFAULT_COLOR",
    "Light",
    "RenderOutput",
    "Renderer",
    "TexturedMesh",
    "as_textured_mesh",
    "import_open3d",
    "render",
    "sample_texture",
]
