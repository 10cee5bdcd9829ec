"""Geometry: SE(3) algebra and point-cloud primitives, batch-first, on any device and dtype."""

from poseflow.geometry.crops import crop_box_around, crop_resize, crop_to_pixels, pixels_to_crop
from poseflow.geometry.neighbors import NeighborIndex, NeighborTracker, nearest_neighbors
from poseflow.geometry.normals import estimate_normals
from poseflow.geometry.pointcloud import cloud_diameter, remove_statistical_outliers
from poseflow.geometry.projection import BackprojectedCloud, backproject_depth, project_points
from poseflow.geometry.sampling import farthest_point_sample, voxel_downsample
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
    "BackprojectedCloud",
    "NeighborIndex",
    "NeighborTracker",
    "backproject_depth",
    "cloud_diameter",
    "compose",
    "crop_box_around",
    "crop_resize",
    "crop_to_pixels",
    "estimate_normals",
    "farthest_point_sample",
    "from_Rt",
    "inverse_transform",
    "nearest_neighbors",
    "pixels_to_crop",
    "project_points",
    "random_rotation",
    "random_transform",
    "remove_statistical_outliers",
    "rotation_angle_error",
    "to_Rt",
    "transform_points",
    "translation_error",
    "voxel_downsample",
]
