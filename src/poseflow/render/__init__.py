"""Rendering: a CPU ray-casting renderer (depth, instance masks, textured RGB) on Open3D."""

from poseflow.render.mesh import DEFAULT_COLOR, TexturedMesh, as_textured_mesh, sample_texture
from poseflow.render.raycast import Light, Renderer, RenderOutput, render

__all__ = [
    "DEFAULT_COLOR",
    "Light",
    "RenderOutput",
    "Renderer",
    "TexturedMesh",
    "as_textured_mesh",
    "render",
    "sample_texture",
]
