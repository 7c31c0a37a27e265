"""``RummageEnv``: the gymnasium-style simulated rummaging environment (RUMI section V-A/B).

``obs, info = env.reset(seed)``; ``obs, reward, terminated, truncated, info = env.step(u)``.

Acting: the end effector is position + yaw controlled. ``u`` is ``[dx, dy, dyaw]`` (planar, fixed tip
height) or ``[dx, dy, dz, dyaw]`` (3D); each entry is clipped to [-1, 1] and a value of 1 means
``translation_scale`` (80 mm) or ``rotation_scale`` (0.5 rad). The commanded ee target
``clip(ee + scale * u, ee_lower, ee_upper)`` is reached through many mini steps (<= 4 mm, <= 0.04
rad each): every mini step solves IK (damped least squares on ``mj_jacSite``) for joint-position
targets of the arm's position actuators and simulates a few physics steps, so pushing is
quasi-static. Targets the arm cannot reach end where the arm stops: IK returns the best
joint-limited approximation and the gripper moves continuously, it never teleports.

Sensing after each step (``Observation.features``, the new ``X'_t`` only):
- tactile (``tactile.TactileSensor``): the points of ``h_I(q)`` within 3 mm of the true object surface,
  each reported at its closest point on that surface (the contact), and the gripper's other interior points as
  free space;
- the depth camera (``camera.cast_rays``) at reset (and every step if ``camera_every_step``);
- at reset of tasks with ``floor_free_points``: free points just below the table top.
``Observation.dT`` is the object's world-frame motion over the step, ``T_new = dT @ T_old``
(``None`` when ``observe_dT`` is False). ``info["true_pose"]`` is for metrics only.
"""
from __future__ import annotations

import dataclasses
import logging
import math

import mujoco
import numpy as np
import torch

from .camera import cast_rays
from .robot import ArmIK, Q_NOMINAL, ee_state_from_pose, gripper_points, yaw_rotation
from .scene import ARM_JOINTS, build_scene
from .tactile import TactileSensor
from .tasks import TaskSpec, get_spec

__all__ = ["Observation", "RummageEnv", "make"]
log = logging.getLogger(__name__)

SURFACE, FREE = 0, 1  # chsel.SemanticsClass values (activetouch.observations.Semantics)


@dataclasses.dataclass
class Observation:
    """One step's observation.

    Attributes:
        features: ``Features`` of the new points ``X'_t`` (world frame).
        ee_pose: ``(4, 4)`` float32 end-effector pose after the step.
        in_contact: whether the gripper touched the object during the step or touches it now.
        dT: ``(4, 4)`` float32 world-frame object motion over the step (``T_new = dT @ T_old``) or
            ``None`` (``observe_dT=False``: the belief must estimate it).
    """

    features: object
    ee_pose: torch.Tensor
    in_contact: bool
    dT: torch.Tensor | None


def _voxel_unique(x: np.ndarray, res: float) -> np.ndarray:
    """One observed point (the first) per occupied cell of side ``res``: ``(K, 3)``.

    Keeps real ray samples rather than cell centres: a cell centre may lie inside the object.
    """
    if len(x) == 0:
        return x.reshape(0, 3)
    _, idx = np.unique(np.floor(x / res).astype(np.int64), axis=0, return_index=True)
    return x[np.sort(idx)]


def _features(surface: list[np.ndarray], free: list[np.ndarray]):
    from activetouch.observations import Features

    s = np.concatenate([a.reshape(-1, 3) for a in surface]) if surface else np.zeros((0, 3))
    f = np.concatenate([a.reshape(-1, 3) for a in free]) if free else np.zeros((0, 3))
    pos = torch.as_tensor(np.concatenate([s, f]), dtype=torch.float32)
    sem = torch.cat([torch.full((len(s),), SURFACE, dtype=torch.long), torch.full((len(f),), FREE, dtype=torch.long)])
    return Features(pos, sem)


class TaskGeometry:
    """What the planners read of a rummaging task, all derived from ``self.spec`` (a ``TaskSpec``): action
    scale and size, the free-space end-effector dynamics, the gripper points and the reachability map. Shared by
    the simulated :class:`RummageEnv` and :class:`activetouch.protocol.RobotEnv` (any robot)."""

    @property
    def action_scale(self) -> tuple[float, float]:
        """``(translation per unit action (m), rotation per unit action (rad))`` = (0.08, 0.5)."""
        return (self.spec.translation_scale, self.spec.rotation_scale)

    @property
    def action_dim(self) -> int:
        return self.spec.action_dim

    def gripper_points(self, spacing: float = 0.01) -> tuple[torch.Tensor, torch.Tensor]:
        """``h(q)`` in the ee frame ``(M, 3)`` and the ``h_I(q)`` mask ``(M,)``; see ``robot.gripper_points``."""
        return gripper_points(spacing)

    def target_ee(self, ee: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Free-space ee dynamics ``clip(ee + scale * u)``: ``[x, y, z, yaw] (4,)`` (u already clipped)."""
        s = self.spec
        if s.action_space == "planar":
            delta = np.array([u[0] * s.translation_scale, u[1] * s.translation_scale, 0.0, u[2] * s.rotation_scale])
        else:
            delta = np.concatenate([u[:3] * s.translation_scale, [u[3] * s.rotation_scale]])
        tgt = np.clip(ee + delta, s.ee_lower, s.ee_upper)
        if s.action_space == "planar":
            tgt[2] = s.ee_height
        return tgt

    def reachability(self):
        """Reachability map of Eq. 30 over the task workspace: ``(VoxelGrid, values (nx, ny, nz))`` (cached)."""
        from .reachability import reachability_map

        lo, up = self.spec.workspace
        return reachability_map(lo, up, planar=self.spec.action_space == "planar")


class RummageEnv(TaskGeometry):
    """Simulated rummaging task: KUKA iiwa + soft-bubble gripper + one movable known object.

    Args:
        spec: the task.
        seed: default seed of ``reset``. The simulation itself is deterministic; the seed only
            drives ``start_noise`` (default 0: the fixed start poses of the paper's tasks).
        start_noise: std of an optional Gaussian perturbation of the start x, y (m) and yaw (rad/10).
    """

    physics_substeps = 8  # physics steps (2 ms) per mini step
    settle_steps = 40  # physics steps after the last mini step
    # Read the pads after every mini step in contact, not only once after settling: a contact made and lost
    # within one action (the object pushed away, the gripper sliding past a corner) otherwise leaves no surface
    # point. Points sensed at mini step k are object-fixed: they are carried to the object's pose at the end of
    # the step (x -> T_end T_k^-1 x), as Algorithm 6 carries object features.
    touch_every_mini_step = True

    def __init__(self, spec: TaskSpec, seed: int = 0, start_noise: float = 0.0):
        from activetouch import objects

        self.spec = spec
        self.seed = int(seed)
        self.start_noise = float(start_noise)
        self.object = objects.load(spec.object_name)
        self._upright = bool(spec.se2)  # SE(2) search <=> the object is kept upright (RUMI V-B)
        self.model = build_scene(spec.object_name, self.object.mesh_path, upright=self._upright)
        self.data = mujoco.MjData(self.model)
        m = self.model
        self._site = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, "ee")
        jids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, j) for j in ARM_JOINTS]
        self._qadr = m.jnt_qposadr[jids]
        self._vadr = m.jnt_dofadr[jids]
        oj = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "object_x" if self._upright else "object_free")
        self._obj_qadr = int(m.jnt_qposadr[oj])
        self._obj_vadr = int(m.jnt_dofadr[oj])
        self._obj_body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "object")
        self._obj_visual = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "object_visual")
        self._gripper_body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "gripper")
        self._robot_geoms = {g for g in range(m.ngeom) if m.geom_contype[g] == 4}
        self._object_geoms = {g for g in range(m.ngeom) if m.geom_bodyid[g] == self._obj_body and m.geom_contype[g] == 2}
        self.ik = ArmIK(m, self._site, self._qadr, self._vadr)
        self.tactile = TactileSensor(self.object, band=spec.contact_band)
        self._verts = np.asarray(self.object.mesh.vertices)
        self._step = 0
        self._reset_done = False

    # ------------------------------------------------------------------ properties
    # action_scale, action_dim, gripper_points, target_ee, reachability: TaskGeometry (from self.spec)
    def ee_state(self) -> np.ndarray:
        """Current ``[x, y, z, yaw] (4,)`` of the end effector."""
        return ee_state_from_pose(self.data.site_xpos[self._site], self.data.site_xmat[self._site].reshape(3, 3))

    def ee_pose(self) -> np.ndarray:
        """Current ee pose ``(4, 4)`` (float64)."""
        T = np.eye(4)
        T[:3, :3] = self.data.site_xmat[self._site].reshape(3, 3)
        T[:3, 3] = self.data.site_xpos[self._site]
        return T

    def true_pose(self) -> np.ndarray:
        """Ground-truth object -> world pose ``(4, 4)`` float64 (metrics only)."""
        T = np.eye(4)
        T[:3, :3] = self.data.xmat[self._obj_body].reshape(3, 3)
        T[:3, 3] = self.data.xpos[self._obj_body]
        return T

    # ------------------------------------------------------------------ reset
    def reset(self, seed: int | None = None):
        """Put the object at its start pose and the gripper at ``ee_start``; observe ``X'_0``."""
        s = self.spec
        rng = np.random.default_rng(self.seed if seed is None else int(seed))
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        T0 = s.start_pose(self._verts).numpy().copy()
        if self.start_noise > 0:
            dx, dy, dyaw = rng.normal(0.0, self.start_noise, 3)
            T0[:3, :3] = yaw_rotation(dyaw / 10.0) @ T0[:3, :3]
            T0[:2, 3] += (dx, dy)
        T0[2, 3] += 0.0005  # start just above the table
        d.qpos[self._obj_qadr:self._obj_qadr + 3] = T0[:3, 3]
        if self._upright:  # x, y, z, yaw joints (an upright start rotation is a pure yaw)
            d.qpos[self._obj_qadr + 3] = math.atan2(T0[1, 0], T0[0, 0])
        else:
            quat = np.zeros(4)
            mujoco.mju_mat2Quat(quat, T0[:3, :3].reshape(-1))
            d.qpos[self._obj_qadr + 3:self._obj_qadr + 7] = quat
        # arm: IK from the nominal posture to the start ee pose
        ee0 = np.array(s.ee_start, float)
        if s.action_space == "planar":
            ee0[2] = s.ee_height
        q = Q_NOMINAL.copy()
        for _ in range(20):
            q = self.ik.solve(q, ee0[:3], yaw_rotation(ee0[3]), iterations=20)
        d.qpos[self._qadr] = q
        d.ctrl[:] = q
        mujoco.mj_forward(m, d)
        for _ in range(150):  # let the object settle on the table
            mujoco.mj_step(m, d)
        self._q_cmd = q.copy()
        self._step = 0
        self._reset_done = True
        surface, free = [], []
        cam = cast_rays(m, d, s.camera, self._obj_visual, s.workspace_lower, s.workspace_upper)
        surface.append(cam.surface)
        free.append(_voxel_unique(cam.free, s.camera.free_spacing))
        n_floor = 0
        if s.floor_free_points:
            free.append(self._floor_points())
            n_floor = len(free[-1])
        tac = self.tactile.sense(self.ee_pose(), self.true_pose())
        surface.append(tac.surface)
        free.append(tac.free)
        obs = Observation(features=_features(surface, free), ee_pose=torch.as_tensor(self.ee_pose(), dtype=torch.float32),
                          in_contact=len(tac.surface) > 0,
                          dT=torch.eye(4) if s.observe_dT else None)
        return obs, self._info(camera_surface_points=len(cam.surface), camera_free_points=len(free[0]),
                               floor_free_points=n_floor)

    def _floor_points(self) -> np.ndarray:
        """Free points on a grid of spacing ``r_w`` just below the table top over the workspace (box tasks)."""
        lo, up = self.spec.workspace
        r = self.spec.r_w
        xs = np.arange(lo[0] + r / 2, up[0], r)
        ys = np.arange(lo[1] + r / 2, up[1], r)
        g = np.stack(np.meshgrid(xs, ys, indexing="ij"), -1).reshape(-1, 2)
        return np.concatenate([g, np.full((len(g), 1), -self.spec.floor_free_depth)], axis=1)

    def _info(self, **extra) -> dict:
        info = {"true_pose": torch.as_tensor(self.true_pose(), dtype=torch.float32), "step": self._step,
                "ee_state": self.ee_state()}
        info.update(extra)
        return info

    # ------------------------------------------------------------------ step
    def _check_action(self, action) -> np.ndarray:
        u = np.asarray(action, dtype=np.float64).reshape(-1)
        if u.shape != (self.action_dim,):
            raise ValueError(f"action must have shape ({self.action_dim},) for a {self.spec.action_space} task, got {np.shape(action)}")
        if not np.isfinite(u).all():
            raise ValueError(f"action contains NaN or inf: {u.tolist()}")
        return np.clip(u, -1.0, 1.0)

    def _touching(self) -> bool:
        d = self.data
        for i in range(d.ncon):
            c = d.contact[i]
            g1, g2 = int(c.geom1), int(c.geom2)
            if (g1 in self._robot_geoms and g2 in self._object_geoms) or (g2 in self._robot_geoms and g1 in self._object_geoms):
                return True
        return False

    def step(self, action):
        """Execute one action; see the module docstring. Returns ``(obs, reward, terminated, truncated, info)``."""
        if not self._reset_done:
            raise RuntimeError("call reset() before step()")
        u = self._check_action(action)
        s, m, d = self.spec, self.model, self.data
        ee0 = self.ee_state()
        if s.action_space == "planar":
            ee0[2] = s.ee_height
        tgt = self.target_ee(ee0, u)
        T_before = self.true_pose()
        dpos = tgt[:3] - ee0[:3]
        dyaw = tgt[3] - ee0[3]
        n = max(1, int(math.ceil(max(np.linalg.norm(dpos) / s.mini_step, abs(dyaw) / s.mini_step_yaw))))
        q = d.qpos[self._qadr].copy()
        contact = False
        touched_obj = []  # object-frame surface points sensed during the mini steps
        for k in range(1, n + 1):
            a = k / n
            p = ee0[:3] + a * dpos
            R = yaw_rotation(ee0[3] + a * dyaw)
            q = self.ik.solve(q, p, R, iterations=6)
            d.ctrl[:] = q
            for _ in range(self.physics_substeps):
                mujoco.mj_step(m, d)
            touching = self._touching()
            contact = contact or touching
            if touching and self.touch_every_mini_step and k < n:
                T_k = self.true_pose()
                pts = self.tactile.sense(self.ee_pose(), T_k, surface_only=True).surface
                if len(pts):
                    inv = np.linalg.inv(T_k)
                    touched_obj.append(pts @ inv[:3, :3].T + inv[:3, 3])
        for _ in range(self.settle_steps):
            mujoco.mj_step(m, d)
        contact = contact or self._touching()
        self._q_cmd = q
        self._step += 1
        T_after = self.true_pose()
        surface, free = [], []
        tac = self.tactile.sense(self.ee_pose(), T_after)
        surface.extend(pts @ T_after[:3, :3].T + T_after[:3, 3] for pts in touched_obj)
        surface.append(tac.surface)
        free.append(tac.free)
        if s.camera_every_step:
            cam = cast_rays(m, d, s.camera, self._obj_visual, s.workspace_lower, s.workspace_upper)
            surface.append(cam.surface)
            free.append(_voxel_unique(cam.free, s.camera.free_spacing))
        dT = None
        if s.observe_dT:
            dT = torch.as_tensor(T_after @ np.linalg.inv(T_before), dtype=torch.float32)
        obs = Observation(features=_features(surface, free), ee_pose=torch.as_tensor(self.ee_pose(), dtype=torch.float32),
                          in_contact=bool(contact or len(tac.surface) > 0), dT=dT)
        truncated = self._step >= s.max_steps
        ee1 = self.ee_state()
        info = self._info(target_ee=tgt, reached=bool(np.linalg.norm(ee1[:3] - tgt[:3]) < 0.005),
                          mini_steps=n)
        return obs, 0.0, False, truncated, info

    # ------------------------------------------------------------------ extras
    def render(self, path, features=None, **kwargs):
        """Save a headless top-down + side picture of the current state to ``path`` (PNG)."""
        from .render import render_env

        return render_env(self, path, features=features, **kwargs)


def make(task_id: str, seed: int = 0, **overrides) -> RummageEnv:
    """Build the environment of a registered task; ``overrides`` replace ``TaskSpec`` fields
    (``start_noise`` goes to the environment)."""
    start_noise = overrides.pop("start_noise", 0.0)
    return RummageEnv(get_spec(task_id, **overrides), seed=seed, start_noise=start_noise)
