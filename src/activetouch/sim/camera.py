"""Fixed pinhole depth camera by ray casting (no OpenGL), RUMI section V-A.

Each pixel's ray is intersected with the scene by ``mujoco.mj_multiRay`` against the exact visual
geometry (static scene, robot visual meshes and the object's exact visual mesh; the object's convex
collision parts are in a group the rays skip). The observation is

- ``s = free`` points sampled along each ray from the camera up to 95 % of its depth (rays that hit
  nothing: up to 95 % of ``max_depth``), with spacing ``free_spacing``;
- ``s = surface`` points where rays hit the segmented target object.

Free points are kept only inside the task workspace box (3D workspace, also for planar tasks) so the
observation stays a manageable size, and thinned to one per 1 cm cell by the environment.
"""
from __future__ import annotations

import dataclasses
import math

import mujoco
import numpy as np

from .scene import GROUP_OBJECT_VISUAL, GROUP_ROBOT, GROUP_STATIC

__all__ = ["PinholeCamera", "CameraReading", "cast_rays", "look_at"]


def look_at(pos, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world rotation ``(3, 3)`` with columns (right, down, forward) (OpenCV convention)."""
    pos, target, up = (np.asarray(v, float) for v in (pos, target, up))
    f = target - pos
    n = np.linalg.norm(f)
    if n < 1e-9:
        raise ValueError("camera position and look-at target coincide")
    f /= n
    r = np.cross(f, up)
    if np.linalg.norm(r) < 1e-9:
        raise ValueError("camera forward direction is parallel to the up vector")
    r /= np.linalg.norm(r)
    d = np.cross(f, r)
    return np.stack([r, d, f], axis=1)


@dataclasses.dataclass(frozen=True)
class PinholeCamera:
    """A fixed pinhole depth camera.

    Intrinsics: ``width x height`` pixels, focal lengths ``fx, fy`` and principal point ``cx, cy`` in
    pixels (``None``: from ``fov_y_deg`` and the image centre). Extrinsics: ``pos`` looking at
    ``target``.
    """

    pos: tuple[float, float, float]
    target: tuple[float, float, float]
    width: int = 80
    height: int = 60
    fov_y_deg: float = 55.0
    fx: float | None = None
    fy: float | None = None
    cx: float | None = None
    cy: float | None = None
    max_depth: float = 2.5
    free_fraction: float = 0.95
    free_spacing: float = 0.01
    crop_lower: tuple[float, float, float] | None = None  # None: the task workspace
    crop_upper: tuple[float, float, float] | None = None

    def __post_init__(self):
        if self.width < 1 or self.height < 1:
            raise ValueError(f"camera image size must be positive, got {self.width}x{self.height}")
        if not (0.0 < self.free_fraction <= 1.0):
            raise ValueError(f"free_fraction must be in (0, 1], got {self.free_fraction}")
        if not (self.free_spacing > 0 and self.max_depth > 0):
            raise ValueError("free_spacing and max_depth must be > 0")
        look_at(self.pos, self.target)  # validates

    def intrinsics(self) -> np.ndarray:
        """``K (3, 3)``."""
        f_default = 0.5 * self.height / math.tan(math.radians(self.fov_y_deg) / 2)
        fx = self.fx if self.fx is not None else f_default
        fy = self.fy if self.fy is not None else f_default
        cx = self.cx if self.cx is not None else (self.width - 1) / 2
        cy = self.cy if self.cy is not None else (self.height - 1) / 2
        return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])

    def rotation(self) -> np.ndarray:
        """Camera-to-world rotation ``(3, 3)``."""
        return look_at(self.pos, self.target)

    def ray_directions(self) -> np.ndarray:
        """Unit ray directions in the world frame, ``(height*width, 3)`` row-major over pixels."""
        K = self.intrinsics()
        u, v = np.meshgrid(np.arange(self.width), np.arange(self.height))
        pix = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=0)
        d_cam = np.linalg.solve(K, pix)
        d = (self.rotation() @ d_cam).T
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def frustum_contains(self, x: np.ndarray) -> np.ndarray:
        """Whether world points ``x (N, 3)`` project inside the image and in front of the camera."""
        R = self.rotation()
        pc = (np.asarray(x, float) - np.asarray(self.pos)) @ R
        z = pc[:, 2]
        uvw = pc @ self.intrinsics().T
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = uvw[:, 0] / z, uvw[:, 1] / z
        return (z > 0) & (u >= -0.5) & (u <= self.width - 0.5) & (v >= -0.5) & (v <= self.height - 0.5)


@dataclasses.dataclass
class CameraReading:
    """Raw result of one ray cast: depth per pixel (``inf`` for no hit), hit geom ids, points."""

    depth: np.ndarray  # (H*W,)
    geom: np.ndarray  # (H*W,) int, -1 for no hit
    free: np.ndarray  # (F, 3)
    surface: np.ndarray  # (S, 3) hits on the target object


def cast_rays(model: mujoco.MjModel, data: mujoco.MjData, cam: PinholeCamera, target_geom: int,
              crop_lower=None, crop_upper=None) -> CameraReading:
    """Render one depth image by ray casting and turn it into free / surface points.

    Args:
        target_geom: id of the object's visual geom (segmentation of the target object).
        crop_lower, crop_upper: ``(3,)`` box that free points are kept in (the camera's own crop
            box takes precedence; no box at all: keep every free point).
    """
    dirs = cam.ray_directions()
    n = len(dirs)
    geomid = np.full(n, -1, dtype=np.int32)
    dist = np.full(n, -1.0)
    group = np.zeros(6, dtype=np.uint8)
    for g in (GROUP_STATIC, GROUP_ROBOT, GROUP_OBJECT_VISUAL):
        group[g] = 1
    pnt = np.asarray(cam.pos, dtype=np.float64)
    mujoco.mj_multiRay(model, data, pnt, dirs.reshape(-1).copy(), group, 1, -1, geomid, dist, None, n,
                       cam.max_depth)
    hit = (dist >= 0) & (geomid >= 0)
    depth = np.where(hit, dist, np.inf)
    # surface points on the segmented target object
    on_obj = hit & (geomid == target_geom)
    surface = pnt + dirs[on_obj] * dist[on_obj, None]
    # free points along every ray up to free_fraction of its depth
    reach = np.where(hit, dist, cam.max_depth) * cam.free_fraction
    steps = np.arange(cam.free_spacing, reach.max() + 1e-9, cam.free_spacing)
    t = steps[None, :].repeat(n, 0)
    valid = t <= reach[:, None]
    pts = pnt + dirs[:, None, :] * t[..., None]
    pts = pts[valid]
    lo = cam.crop_lower if cam.crop_lower is not None else crop_lower
    up = cam.crop_upper if cam.crop_upper is not None else crop_upper
    if lo is not None and up is not None:
        pts = pts[((pts >= np.asarray(lo)) & (pts <= np.asarray(up))).all(axis=1)]
    return CameraReading(depth=depth, geom=geomid, free=pts, surface=surface)
