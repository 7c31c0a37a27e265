"""The simulated robot: KUKA LBR iiwa 7 + a parallel gripper with two soft-bubble stand-in pads.

Holds the gripper geometry (one source of truth for the MJCF builder, the point sets ``h(q)`` /
``h_I(q)`` of RUMI section V-A / Fig. 9 and the renderer) and a fast damped-least-squares inverse
kinematics on MuJoCo's own Jacobian (``mj_jacSite``), used inside the simulation loop.

End-effector (ee) frame: origin at the tip of the gripper (centre of the pads' lower ends), ``+z``
pointing up along the gripper towards the flange, ``+x`` the pads' width direction, ``+y`` the
direction from one pad to the other. The gripper always points down; the ee pose is fully
described by ``[x, y, z, yaw]`` with rotation ``Rz(yaw)``.
"""
from __future__ import annotations

import dataclasses
import math
import pathlib

import mujoco
import numpy as np
import torch

__all__ = [
    "ASSET_DIR",
    "BASE_POS",
    "GripperGeometry",
    "GRIPPER",
    "gripper_points",
    "ArmIK",
    "yaw_rotation",
    "ee_state_from_pose",
]

ASSET_DIR = pathlib.Path(__file__).resolve().parents[1] / "assets" / "robots" / "kuka_iiwa"
#: Robot base position in the world frame: behind the workspace [0, 0.8] x [-0.4, 0.4] (Fig. 7),
#: on the table top (z = 0). The far part of the workspace is therefore out of reach.
BASE_POS = (-0.25, 0.0, 0.0)
#: Height of the flange face above the link-7 frame origin (max z of the link-7 mesh).
FLANGE_OFFSET = 0.045
#: A comfortable "elbow up, gripper down" posture used as IK seed and null-space bias.
Q_NOMINAL = np.array([0.0, 0.6, 0.0, -1.5, 0.0, 1.05, 0.0])


@dataclasses.dataclass(frozen=True)
class GripperGeometry:
    """Box-shaped gripper parts in the ee frame (half extents and centres, metres).

    Pads are rigid stand-ins for the soft-bubble sensors of Kuppuswamy et al. (2020) used in the
    RUMI paper (Fig. 9): about 110 mm tall, 80 mm wide, 35 mm thick, facing each other.
    """

    pad_half: tuple[float, float, float] = (0.040, 0.0175, 0.055)
    # Pads at y = +-0.0195: a 4 mm gap between their inner faces, like the nearly touching bubbles of Fig. 9.
    # (A wider gap traps the mug handle between the pads and the robot then drags the mug off the shelf.)
    pad_centre_y: float = 0.0195
    palm_half: tuple[float, float, float] = (0.030, 0.075, 0.020)
    adaptor_radius: float = 0.035
    adaptor_half_height: float = 0.015

    @property
    def pad_centres(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        z = self.pad_half[2]
        return ((0.0, self.pad_centre_y, z), (0.0, -self.pad_centre_y, z))

    @property
    def palm_centre(self) -> tuple[float, float, float]:
        return (0.0, 0.0, 2 * self.pad_half[2] + self.palm_half[2])

    @property
    def adaptor_centre(self) -> tuple[float, float, float]:
        return (0.0, 0.0, 2 * self.pad_half[2] + 2 * self.palm_half[2] + self.adaptor_half_height)

    @property
    def length(self) -> float:
        """Tip-to-flange distance."""
        return 2 * (self.pad_half[2] + self.palm_half[2] + self.adaptor_half_height)


GRIPPER = GripperGeometry()


def _box_grid(centre, half, spacing: float) -> np.ndarray:
    """Grid points filling a box, boundary included: ``(K, 3)``."""
    axes = []
    for c, h in zip(centre, half):
        n = max(2, int(math.ceil(2 * h / spacing)) + 1)
        axes.append(np.linspace(c - h, c + h, n))
    g = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    return g.reshape(-1, 3)


def gripper_points(spacing: float = 0.01, geometry: GripperGeometry = GRIPPER,
                   pads_only: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Interior points of the gripper ``h(q)`` in the ee frame and the mask of ``h_I(q)``.

    RUMI section V-A / Fig. 9: ``h(q)`` are the robot's interior points (whole gripper: pads, palm,
    flange adaptor); ``h_I(q)`` is the information-gathering subset, the two soft-bubble pads at
    the front of the gripper. Points form a regular grid with the boxes' boundary included, so a
    pad face touching an object has points on the object surface.

    Args:
        spacing: grid spacing (metres, > 0).
        pads_only: return only the pad points (all of ``h_I``).
    Returns:
        ``h_ee (M, 3)`` float32 in the ee frame and ``info_mask (M,)`` bool (True for ``h_I``).
    """
    if not (math.isfinite(spacing) and spacing > 0):
        raise ValueError(f"spacing must be finite and > 0, got {spacing}")
    pads = [_box_grid(c, geometry.pad_half, spacing) for c in geometry.pad_centres]
    parts = list(pads)
    mask = [np.ones(len(p), bool) for p in pads]
    if not pads_only:
        palm = _box_grid(geometry.palm_centre, geometry.palm_half, spacing)
        r, hh = geometry.adaptor_radius, geometry.adaptor_half_height
        ad = _box_grid(geometry.adaptor_centre, (r, r, hh), spacing)
        ad = ad[np.hypot(ad[:, 0], ad[:, 1]) <= r + 1e-9]
        parts += [palm, ad]
        mask += [np.zeros(len(palm), bool), np.zeros(len(ad), bool)]
    pts = np.concatenate(parts)
    m = np.concatenate(mask)
    return torch.as_tensor(pts, dtype=torch.float32), torch.as_tensor(m)


def yaw_rotation(yaw: float) -> np.ndarray:
    """``Rz(yaw)`` as a ``(3, 3)`` array."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def ee_state_from_pose(pos: np.ndarray, mat: np.ndarray) -> np.ndarray:
    """``[x, y, z, yaw] (4,)`` from an ee position ``(3,)`` and rotation ``(3, 3)``."""
    return np.array([pos[0], pos[1], pos[2], math.atan2(mat[1, 0], mat[0, 0])])


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


class ArmIK:
    """Damped-least-squares IK for the ee site on MuJoCo's Jacobian (``mj_jacSite``).

    Own implementation rather than pytorch_kinematics: this runs hundreds of times per environment
    step on single goals, where a C Jacobian on a private ``MjData`` costs microseconds while a
    torch call costs ~1 ms. (The reachability map, which solves many goals at once, uses
    pytorch_kinematics' batched IK.)

    Args:
        model: compiled scene model; ``arm_qpos_adr`` / ``arm_dof_adr`` index the 7 arm joints.
        site_id: id of the ee site.
    """

    def __init__(self, model: mujoco.MjModel, site_id: int, arm_qpos_adr: np.ndarray,
                 arm_dof_adr: np.ndarray, damping: float = 0.02, nullspace_gain: float = 0.05):
        self.model = model
        self.data = mujoco.MjData(model)
        self.site_id = site_id
        self.qadr = np.asarray(arm_qpos_adr)
        self.vadr = np.asarray(arm_dof_adr)
        jnt = [int(np.nonzero(model.jnt_qposadr == a)[0][0]) for a in self.qadr]
        self.lower = model.jnt_range[jnt, 0].copy()
        self.upper = model.jnt_range[jnt, 1].copy()
        # keep a small margin from the joint limits
        margin = 0.02
        self.lower += margin
        self.upper -= margin
        self.damping = damping
        self.nullspace_gain = nullspace_gain
        self._jacp = np.zeros((3, model.nv))
        self._jacr = np.zeros((3, model.nv))
        self._quat = np.zeros(4)
        self._vel = np.zeros(3)

    def fk(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """ee position ``(3,)`` and rotation ``(3, 3)`` for arm joints ``q (7,)``."""
        self.data.qpos[self.qadr] = q
        mujoco.mj_kinematics(self.model, self.data)
        return self.data.site_xpos[self.site_id].copy(), self.data.site_xmat[self.site_id].reshape(3, 3).copy()

    def error(self, q: np.ndarray, pos: np.ndarray, rot: np.ndarray) -> tuple[float, float]:
        """Position error (m) and rotation error (rad) of ``q`` w.r.t. the goal ``(pos, rot)``."""
        p, r = self.fk(q)
        return float(np.linalg.norm(pos - p)), float(np.linalg.norm(self._rot_err(rot, r)))

    def _rot_err(self, rot_goal: np.ndarray, rot: np.ndarray) -> np.ndarray:
        """World-frame rotation vector taking ``rot`` to ``rot_goal``."""
        mujoco.mju_mat2Quat(self._quat, (rot_goal @ rot.T).reshape(-1))
        mujoco.mju_quat2Vel(self._vel, self._quat, 1.0)
        return self._vel.copy()

    def solve(self, q0: np.ndarray, pos: np.ndarray, rot: np.ndarray, iterations: int = 8,
              max_step: float = 0.15, rot_weight: float = 2.0, tol: float = 2e-4) -> np.ndarray:
        """Joint positions ``(7,)`` that bring the ee site toward ``(pos, rot)``, starting at ``q0``.

        Damped least squares with joint-limit clamping and a null-space pull toward the nominal
        posture. Unreachable goals give the best joint-limited approximation (the goal is "clipped
        to what the arm can reach").
        """
        q = np.array(q0, dtype=float)
        lam2 = self.damping ** 2
        for _ in range(iterations):
            self.data.qpos[self.qadr] = q
            mujoco.mj_kinematics(self.model, self.data)
            mujoco.mj_comPos(self.model, self.data)
            p = self.data.site_xpos[self.site_id]
            r = self.data.site_xmat[self.site_id].reshape(3, 3)
            e_p = pos - p
            e_r = self._rot_err(rot, r)
            if np.linalg.norm(e_p) < tol and np.linalg.norm(e_r) < 10 * tol:
                break
            mujoco.mj_jacSite(self.model, self.data, self._jacp, self._jacr, self.site_id)
            J = np.vstack([self._jacp[:, self.vadr], rot_weight * self._jacr[:, self.vadr]])
            e = np.concatenate([e_p, rot_weight * e_r])
            JJt = J @ J.T + lam2 * np.eye(6)
            dq = J.T @ np.linalg.solve(JJt, e)
            # null-space pull toward the nominal posture keeps the elbow up and away from limits
            Jpinv = J.T @ np.linalg.inv(JJt)
            dq += (np.eye(7) - Jpinv @ J) @ (self.nullspace_gain * (Q_NOMINAL - q))
            n = np.abs(dq).max()
            if n > max_step:
                dq *= max_step / n
            q = np.clip(q + dq, self.lower, self.upper)
        return q
