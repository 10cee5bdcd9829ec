"""Geometry: SE(3) algebra and point-cloud primitives, batch-first, on any device and dtype."""

from poseflow.geometry.se3 import (
    compose,
    from_Rt,
    inverse_transform,
    random_rotation,
    random_transform,
    rotation_angle_error,
    to_Rt,
    transform_points,
    translation_error,
)

__all__ = [
    "compose",
    "from_Rt",
    "inverse_transform",
    "random_rotation",
    "random_transform",
    "rotation_angle_error",
    "to_Rt",
    "transform_points",
    "translation_error",
]
