"""Observations: geometric features, voxel downsampling, MergeObs (Alg. 6), semantic sensor model."""
from .downsample import voxel_downsample, voxel_representatives
from .features import Features, Semantics
from .merge import merge_obs
from .sensor_model import SemanticSensorModel

__all__ = ["Features", "Semantics", "SemanticSensorModel", "merge_obs", "voxel_downsample", "voxel_representatives"]
