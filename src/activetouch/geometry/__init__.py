"""Rigid transforms (SE(3)/SE(2) pose batches) and voxel grids."""
from . import proximity, transforms, voxel
from .proximity import near_any
from .transforms import (
    axis_angle_to_matrix,
    check_poses,
    invert,
    make_pose,
    perturb_transform,
    pose_from_xyz_yaw,
    transform_points,
    yaw_matrix,
    yaw_of,
)
from .voxel import VoxelGrid

__all__ = [
    "proximity",
    "transforms",
    "voxel",
    "VoxelGrid",
    "axis_angle_to_matrix",
    "check_poses",
    "near_any",
    "invert",
    "make_pose",
    "perturb_transform",
    "pose_from_xyz_yaw",
    "transform_points",
    "yaw_matrix",
    "yaw_of",
]
