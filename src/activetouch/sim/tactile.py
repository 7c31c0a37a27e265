"""Simulated tactile sensing of the two soft-bubble stand-in pads (RUMI section V-A).

After each step the sensors report

- ``s = surface``: the pad points ``{x in h_I(q) : |sdf(T* x)| < 3 mm}`` (exact object SDF, ``obj.sdf``),
  each reported where the contact is: projected onto the object's surface, ``x - sdf(x) grad sdf(x)``. A soft
  bubble's membrane conforms to the object and its depth camera sees that contact patch; the rigid pads that stand
  in for it hold a 3-D grid of points, and reporting the grid points themselves put every contact 0-3 mm outside
  the object (mean +1.8 mm on box-0's first contact), a bias that let poses 90 deg off fit a one-face patch better
  than the true pose (``project=False`` keeps the grid points),
- ``s = free``: the gripper's interior points ``h(q)`` that are not in contact (``sdf(T* x) > 3 mm``).

Points are world-frame. Points that cannot be near the object (outside its bounding box grown by
the contact band) are classified without an SDF query, which keeps a step fast.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import torch

from .robot import GRIPPER, GripperGeometry, gripper_points

__all__ = ["TactileSensor", "TactileReading"]


@dataclasses.dataclass
class TactileReading:
    surface: np.ndarray  # (S, 3) world
    free: np.ndarray  # (F, 3) world


class TactileSensor:
    """Contact and free-space sensing of the gripper for one known object.

    Args:
        obj: the ``KnownObject`` (needs ``.sdf`` and ``.bounds``).
        band: contact band half-width (metres), 3 mm in the paper.
        contact_spacing: spacing of the pad points ``h_I`` used for contact (finer than the planner's). 2 mm
            = the surface downsampling r_d,s of Table IV, so a contact gives a dense patch of surface points like
            the soft-bubble sensors' depth cameras do (4 mm gave ~4x fewer points: too few for the resampling
            trigger l_r = 5 to fire after a push).
        free_spacing: spacing of ``h`` used for free-space points.
        shell: only pad points within this distance of the pad boundary are tested for contact: the
            pads are rigid, so deeper points are farther than ``band`` from any object surface.
        project: report each touching pad point at its closest point on the object surface (the contact, as a
            conforming membrane sees it); False reports the pad point itself (0-3 mm off the surface, biased outward).
    """

    def __init__(self, obj, band: float = 0.003, contact_spacing: float = 0.002, free_spacing: float = 0.01,
                 shell: float = 0.006, geometry: GripperGeometry = GRIPPER, project: bool = True):
        if not band > 0:
            raise ValueError(f"band must be > 0, got {band}")
        self.obj = obj
        self.band = band
        self.project = bool(project)
        pads, _ = gripper_points(contact_spacing, geometry, pads_only=True)
        pads = pads.double().numpy()
        depth = np.full(len(pads), np.inf)
        for c in geometry.pad_centres:
            rel = np.abs(pads - np.asarray(c)) - np.asarray(geometry.pad_half)
            inside = (rel <= 1e-9).all(axis=1)
            depth = np.where(inside, np.minimum(depth, -rel.max(axis=1)), depth)
        self.pad_pts = pads[depth <= shell]  # (Mc, 3) ee frame
        h, mask = gripper_points(free_spacing, geometry)
        self.h_pts = h.double().numpy()  # (M, 3) ee frame
        b = np.asarray(obj.bounds, dtype=np.float64) if not torch.is_tensor(obj.bounds) else obj.bounds.double().cpu().numpy()
        self.lo = b[0] - band
        self.hi = b[1] + band

    def _sdf_obj(self, x_obj: np.ndarray, grad: bool = False):
        """Exact SDF of object-frame points ``(N, 3)`` -> ``(N,)``; boxes-outside points get +inf. With ``grad``
        also the unit SDF gradient ``(N, 3)`` (zeros where the value is +inf)."""
        out = np.full(len(x_obj), np.inf)
        g = np.zeros((len(x_obj), 3))
        near = ((x_obj >= self.lo) & (x_obj <= self.hi)).all(axis=1)
        if near.any():
            v, gv = self.obj.sdf(torch.as_tensor(x_obj[near], dtype=torch.float32))
            out[near] = v.detach().cpu().double().numpy()
            g[near] = gv.detach().cpu().double().numpy()
        return (out, g) if grad else out

    def sense(self, ee_pose: np.ndarray, obj_pose: np.ndarray, surface_only: bool = False) -> TactileReading:
        """Tactile reading for ee pose ``(4, 4)`` and true object pose ``(4, 4)`` (object -> world);
        ``surface_only`` skips the free points (empty ``free``)."""
        inv = np.linalg.inv(obj_pose)
        A = inv @ ee_pose  # ee frame -> object frame
        pad_obj = self.pad_pts @ A[:3, :3].T + A[:3, 3]
        v, g = self._sdf_obj(pad_obj, grad=True)
        touch = np.abs(v) < self.band
        if self.project:  # the contact on the object's surface (closest point of the exact SDF), then to world
            # (one step: near a crease the mesh SDF's gradient is a face normal, not the direction to the closest
            # point, and a few points land up to ~0.5 mm off the surface; the rest within ~1e-5 mm, 1e-8 m)
            on = pad_obj[touch] - v[touch, None] * g[touch]
            surface = on @ obj_pose[:3, :3].T + obj_pose[:3, 3]
        else:
            surface = self.pad_pts[touch] @ ee_pose[:3, :3].T + ee_pose[:3, 3]
        if surface_only:
            return TactileReading(surface=surface, free=np.zeros((0, 3)))
        h_obj = self.h_pts @ A[:3, :3].T + A[:3, 3]
        vf = self._sdf_obj(h_obj)
        free = self.h_pts[vf > self.band] @ ee_pose[:3, :3].T + ee_pose[:3, 3]
        return TactileReading(surface=surface, free=free)
