"""``GraspEnv``: the simulated blind-grasping task of the touch-only localisation paper (Sec. VI-A, App. D).

``obs, info = env.reset(seed)``; ``obs, reward, terminated, truncated, info = env.step(action)``.

Actions:
- ``PokeAction(waypoints (K, 4))``: ee targets ``[x, y, z, yaw]`` (gripper pointing down, ``robot.py``'s ee
  frame). The arm follows the straight ee path from waypoint to waypoint at a fixed control rate
  (``spec.control_dt``; at most ``max_ee_step`` / ``max_yaw_step`` per period), one damped-least-squares IK
  solve (``robot.ArmIK``) per period gives the joint position targets of the arm's position actuators.
  Guarded motion (App. D-b): the ee contact force is estimated each period by projecting the noisy joint
  torques onto the ee (damped pseudo-inverse of ``J_ee^T``); when it passes ``guard_force`` the arm stops,
  holds where it is for ``stop_hold`` periods and the poke ends (the guard acts on the force's rise above its
  lowest value in the poke, so a poke starting in contact can move away). Waypoint heights are clipped to
  ``min_poke_height`` (pokes stay above the table).
- ``GraspAction(state (3,))``: the grasp primitive for the SE(2) box pose ``state``: lift straight up to the
  pre-grasp height, move (joint space) above the box with the pads across its narrow (object x) axis,
  open, descend (guarded: a pad landing on the box aborts the grasp), close, lift. ``terminated=True``;
  ``info["grasp_success"]`` = the box's bottom is above ``success_height`` after the lift (App. D-d).

Contact signal (App. D-a): the external joint torques of the robot's contacts are the arm's entries of
MuJoCo's ``qfrc_constraint`` (= sum over robot contacts of ``J_c^T f_c``; joint-limit rows do not enter
because IK keeps the arm off its limits and the pad limits act on pad dofs only). The sensor adds i.i.d.
Gaussian noise (``torque_noise_std``, seeded per reset); ``z = ||tau_1..5|| > contact_threshold`` per control
period, so light contacts (a box sliding away takes only ~1.6 N) give false negatives and noise gives
false positives. In simulation there is no gravity/friction/actuation residual to filter ([35] of the paper).

Particle rollouts (``rollout`` / ``grasp_success``) replay a motion (the executed control sequence of a
``TouchObservation`` or a planned ``MotionPlan``) on the full scene for every particle that the robot's
swept surface comes near, all at once with ``mujoco.rollout`` (thread pool); the others cannot be touched
and keep their state (exact for a resting box, up to MuJoCo's soft-contact creep of ~3 um/s).

Simplifications of the paper's setup, and what they cost:
- KUKA iiwa instead of the Franka; stiff joint position servos (with velocity feed-forward) instead of the
  impedance controller of App. D-b, and no gain change for the grasp: the grasp descent is guarded instead
  (``grasp_guard_force``), else the stiff arm would press a misplaced pad into the lid and drag the box up.
- The box is kept upright (SE(2) joints): hard pushes slide and turn it but never tip it over.
- Contact torques are exact plus i.i.d. Gaussian noise: no model-error residual, bias or drift as on a real
  robot, so the false-positive / false-negative rates come from the noise model and light contacts only.
- ``grasp_success`` does not simulate the transit to the pre-grasp pose (it stays above every box).
"""
from __future__ import annotations

import dataclasses
import logging
import math
import os
from typing import NamedTuple

import mujoco
import numpy as np
import torch
from mujoco import rollout as mj_rollout
from scipy.spatial import cKDTree

from ..geometry.transforms import pose_from_xyz_yaw
from .grasp_scene import ARM_GAINS, ARM_JOINTS, GRASP_GRIPPER, OBJECT_JOINTS, PAD_JOINTS, build_grasp_scene
from .grasp_tasks import GraspTaskSpec, get_grasp_spec, sample_task_instance
from .robot import BASE_POS, Q_NOMINAL, ArmIK, ee_state_from_pose, yaw_rotation

__all__ = [
    "PokeAction",
    "GraspAction",
    "MotionPlan",
    "TouchObservation",
    "RolloutResult",
    "GraspEnv",
    "make_grasp_env",
]

_STATE_SPEC = mujoco.mjtState.mjSTATE_FULLPHYSICS
#: Home ee pose at reset: above the near part of the workspace, clear of every box.
HOME_EE = (0.30, 0.0, 0.30, 0.0)
#: Largest joint motion (rad) per control period of joint-space moves (transit, plans given as joints).
MAX_JOINT_STEP = 0.02
#: Where the box waits, out of the arm's reach, in the robot-only reference rollout.
PARK_XY = (0.95, 0.5)
#: Sweep test of the rollouts: surface sampling (m), grid column (m) and the allowance (m) added to
#: ``rollout_margin``. Budget: a gripper surface point is <= 1.06 cm from a sample (box faces: a 1.5 cm grid;
#: link hulls: Poisson-disk samples 1.05 cm apart, gaps of that order), a sample <= 1.06 cm from its column
#: centre, the robot moves <= 4 mm within a period: 2.5 cm < margin 1.5 cm + allowance 1.5 cm; and a
#: particle starts two periods (~8 mm of motion) before it first comes near.
SWEEP_SPACING = 0.015
SWEEP_CELL = 0.015
SWEEP_ALLOWANCE = 0.015
#: Control periods per ``mujoco.rollout`` call, and the object speed (m/s, rad/s) below which it is at rest.
ROLLOUT_CHUNK = 8
#: Largest surface sampling distance (m) of the gripper's geoms in ``robot_points``.
GRIPPER_SPACING = 0.004
REST_SPEED = 1e-3
#: A closed pad slide below this (m) holds nothing (the box's half width is 0.036 m).
EMPTY_PAD = 0.015


def _wrap(a):
    return (np.asarray(a) + math.pi) % (2 * math.pi) - math.pi


def _check_array(x, shape_tail: tuple, name: str, min_rows: int = 1) -> np.ndarray:
    """``x`` as float64 of shape ``(N, *shape_tail)`` (or exactly ``shape_tail`` when ``min_rows`` is 0), finite."""
    if torch.is_tensor(x):
        x = x.detach().cpu().numpy()
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{name} must be a numeric array: {e}") from None
    if min_rows == 0:
        if a.shape != shape_tail:
            raise ValueError(f"{name} must have shape {shape_tail}, got {a.shape}")
    else:
        if a.ndim != len(shape_tail) + 1 or a.shape[1:] != shape_tail:
            want = "(N, " + ", ".join(map(str, shape_tail)) + ")"
            raise ValueError(f"{name} must have shape {want}, got {a.shape}")
        if a.shape[0] < min_rows:
            raise ValueError(f"{name} is empty (need at least {min_rows} row{'s' if min_rows > 1 else ''})")
    if not np.isfinite(a).all():
        raise ValueError(f"{name} contains NaN or inf")
    return a


@dataclasses.dataclass
class PokeAction:
    """A poke: ee waypoints ``(K, 4)`` = ``[x, y, z, yaw]`` (world, metres / radians), gripper pointing down."""

    waypoints: np.ndarray

    def __post_init__(self):
        self.waypoints = _check_array(self.waypoints, (4,), "waypoints")


@dataclasses.dataclass
class GraspAction:
    """A grasp of the box assumed at SE(2) ``state (3,)`` = ``(x, y, yaw)``."""

    state: np.ndarray

    def __post_init__(self):
        self.state = _check_array(self.state, (3,), "grasp state", min_rows=0)


@dataclasses.dataclass
class MotionPlan:
    """A robot motion at control rate that a rollout can replay.

    Attributes:
        ctrl: ``(S, nu)`` actuator targets per control period (arm joints, then the two pad slides).
        seg_end: ``(K,)`` index of the last control period of each waypoint.
        init_state: ``(nstate,)`` MuJoCo ``mjSTATE_FULLPHYSICS`` state at the start (its object part is
            replaced by each particle's state).
        warmstart: ``(nv,)`` constraint-solver warm start at the start (or ``None``).
        q: ``(K+1, 7)`` arm configurations at the start and at each waypoint (commanded for plans).
        ctrl0: ``(nu,)`` the targets in effect before the first period (``GraspEnv.expand_ctrl``).
        guarded: emulate the guarded stop in rollouts (for plans; an executed motion already contains it).
    """

    ctrl: np.ndarray
    seg_end: np.ndarray
    init_state: np.ndarray
    warmstart: np.ndarray | None
    q: np.ndarray
    ctrl0: np.ndarray
    guarded: bool = True

    @property
    def num_waypoints(self) -> int:
        return int(len(self.seg_end))


@dataclasses.dataclass
class TouchObservation:
    """What one poke (or the reset) observed; ``K'`` executed waypoints (0 at reset).

    Attributes:
        z: ``(K',)`` bool binary contact per executed waypoint (the signal of its last control period; for
            the stopped waypoint, of the period that triggered the stop, followed by one more observation at the
            end of the ``stop_hold`` periods, when a pushed box may have slid off): the period index is ``z_period``.
        q: ``(K'+1, 7)`` measured arm joints at the start and after each executed waypoint.
        ee: ``(K'+1, 4)`` measured ee ``[x, y, z, yaw]`` at the same instants.
        stopped_early: the guarded motion stopped the poke.
        contact_force: largest estimated ee contact force (N) during the poke.
        tau_norm: ``(K',)`` norm of the first ``contact_joints`` noisy external torques at those periods.
        ctrl, seg_end, init_state, warmstart, ctrl0: the executed control sequence (``MotionPlan`` fields).
        z_samples, tau_samples, force_samples: ``(S,)`` signal, torque norm, ee force per control period.
        true_contact_samples: ``(S,)`` bool, whether any robot geom was in contact (for measuring rates).
    """

    z: np.ndarray
    q: np.ndarray
    ee: np.ndarray
    stopped_early: bool
    contact_force: float
    tau_norm: np.ndarray
    ctrl: np.ndarray
    seg_end: np.ndarray
    init_state: np.ndarray
    warmstart: np.ndarray | None
    ctrl0: np.ndarray
    z_period: np.ndarray
    z_samples: np.ndarray
    tau_samples: np.ndarray
    force_samples: np.ndarray
    true_contact_samples: np.ndarray

    @property
    def num_waypoints(self) -> int:
        return int(len(self.z))

    def motion(self) -> MotionPlan:
        """The executed motion as a ``MotionPlan`` (not guarded: the stop is in the controls)."""
        return MotionPlan(self.ctrl, self.seg_end, self.init_state, self.warmstart, self.q, self.ctrl0,
                          guarded=False)


class _Sweep(NamedTuple):
    """The robot's swept surface (``GraspEnv._sweep_cells``): column cells ``(N, 3)`` (x, y centre, lowest z),
    their configuration index ``(N,)`` (sorted), the number of configurations and a k-d tree over the xy."""

    cells: np.ndarray
    cfg: np.ndarray
    ncfg: int
    tree: object


class RolloutResult(NamedTuple):
    """``states (P, K, 3)`` object SE(2) state after each waypoint; ``simulated (P,)`` bool (the particle
    came within the margin of the robot's sweep); ``stop_waypoint (P,)`` long, the waypoint at which the
    emulated guarded stop froze the particle (-1: none)."""

    states: torch.Tensor
    simulated: torch.Tensor
    stop_waypoint: torch.Tensor


class GraspEnv:
    """Blind grasping of the cracker box by touch (module docstring).

    Args:
        spec: the task (``grasp_tasks.GraspTaskSpec``).
        seed: default seed of ``reset`` (task instance and sensor noise).
        nthread: threads of the rollout pool (default ``min(2, cpu count)``).
    """

    def __init__(self, spec: GraspTaskSpec, seed: int = 0, nthread: int | None = None):
        from activetouch import objects

        self.spec = spec
        self.seed = int(seed)
        self.object = objects.load(spec.object_name)
        self.gripper = GRASP_GRIPPER
        if not spec.gripper_opening <= self.gripper.max_opening:
            raise ValueError(f"gripper_opening {spec.gripper_opening} exceeds the pads' range "
                             f"{self.gripper.max_opening}")
        self.model = build_grasp_scene(spec.object_name, self.object.mesh_path, timestep=spec.timestep)
        m = self.model
        self.data = mujoco.MjData(m)
        self._site = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, "ee")
        jid = lambda n: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n)  # noqa: E731
        self._qadr = m.jnt_qposadr[[jid(j) for j in ARM_JOINTS]].copy()
        self._vadr = m.jnt_dofadr[[jid(j) for j in ARM_JOINTS]].copy()
        self._pad_qadr = m.jnt_qposadr[[jid(j) for j in PAD_JOINTS]].copy()
        self._pad_vadr = m.jnt_dofadr[[jid(j) for j in PAD_JOINTS]].copy()
        self._obj_qadr = int(m.jnt_qposadr[jid(OBJECT_JOINTS[0])])
        self._obj_vadr = int(m.jnt_dofadr[jid(OBJECT_JOINTS[0])])
        self._obj_body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "object")
        base = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "iiwa_base")
        robot_bodies = {b for b in range(m.nbody) if self._in_subtree(b, base)}
        #: ids of every robot collision geom (links 1-7, palm, adaptor, pads)
        self.robot_geoms = np.array([g for g in range(m.ngeom)
                                     if m.geom_bodyid[g] in robot_bodies and m.geom_contype[g] != 0])
        self._robot_geom_set = set(self.robot_geoms.tolist())
        self.ik = ArmIK(m, self._site, self._qadr, self._vadr)
        self._kin = mujoco.MjData(m)  # scratch data for kinematics (robot_points, plans)
        self._jacp = np.zeros((3, m.nv))
        self._nstate = mujoco.mj_stateSize(m, _STATE_SPEC)
        self._state_obj_q, self._state_obj_v = self._state_offsets()
        lo, hi = self.object.bounds.numpy().astype(np.float64)
        self._rect_lo, self._rect_hi, self._obj_top = lo[:2], hi[:2], float(hi[2])
        self._geom_radius = np.array([float(m.geom_rbound[g]) for g in self.robot_geoms])
        # sweep cells farther than this (xy) from a box centre cannot be within reach of the box
        self._query_radius = float(np.hypot(*np.maximum(np.abs(lo[:2]), np.abs(hi[:2])))) + \
            spec.rollout_margin + SWEEP_ALLOWANCE
        self._nthread = int(nthread) if nthread is not None else max(1, min(2, os.cpu_count() or 1))
        self._pool = mj_rollout.Rollout(nthread=self._nthread)
        self._rdata = [mujoco.MjData(m) for _ in range(max(1, self._nthread))]
        self._surface_cache: dict[float, tuple[np.ndarray, np.ndarray]] = {}
        # velocity feed-forward of the arm's position servos (see expand_ctrl): kv / kp per joint
        self._lead = np.array([kv / kp for kp, kv in ARM_GAINS])
        self._target = np.zeros(m.nu)
        #: counters of the last rollout: simulated particle-periods and ``mujoco.rollout`` calls
        self.rollout_stats = {"particle_periods": 0, "calls": 0}
        self.z_rest = self._settle_height()
        self._q_home: np.ndarray | None = None
        self._reset_done = False
        self._terminated = False

    @property
    def max_steps(self) -> int:
        """Episode length T for the episode loop: ``max_actions`` pokes and the grasp."""
        return int(self.spec.max_actions) + 1

    def close(self):
        """Shut the rollout thread pool down."""
        if self._pool is not None:
            self._pool.close()
            self._pool = None

    def __del__(self):  # pragma: no cover - best effort
        try:
            self.close()
        except Exception:
            pass

    # ------------------------------------------------------------------ helpers
    def _in_subtree(self, b: int, root: int) -> bool:
        while b > 0:
            if b == root:
                return True
            b = int(self.model.body_parentid[b])
        return b == root

    def _state_offsets(self) -> tuple[int, int]:
        """Offsets of the object's qpos and qvel inside a ``mjSTATE_FULLPHYSICS`` vector (found by probing)."""
        d = mujoco.MjData(self.model)
        d.qpos[:] = 0
        d.qvel[:] = 0
        d.qpos[self._obj_qadr] = 123.25
        d.qvel[self._obj_vadr] = -77.5
        s = np.zeros(self._nstate)
        mujoco.mj_getState(self.model, d, s, _STATE_SPEC)
        return int(np.nonzero(s == 123.25)[0][0]), int(np.nonzero(s == -77.5)[0][0])

    def _settle_height(self) -> float:
        """Resting height of the object's slide-z joint on the table (the particles' z)."""
        d = mujoco.MjData(self.model)
        d.qpos[self._qadr] = Q_NOMINAL
        d.ctrl[:7] = Q_NOMINAL
        d.qpos[self._obj_qadr:self._obj_qadr + 4] = (0.4, 0.0, 0.0, 0.0)
        for _ in range(300):
            mujoco.mj_step(self.model, d)
        return float(d.qpos[self._obj_qadr + 2])

    def _get_state(self, d: mujoco.MjData | None = None) -> np.ndarray:
        s = np.zeros(self._nstate)
        mujoco.mj_getState(self.model, self.data if d is None else d, s, _STATE_SPEC)
        return s

    def _robot_state(self) -> np.ndarray:
        """The current full physics state with the box parked out of reach: what observations and plans carry
        (the robot's state; the true box pose must not leak into them)."""
        st = self._get_state()
        o, v = self._state_obj_q, self._state_obj_v
        st[o:o + 4] = (*PARK_XY, self.z_rest, 0.0)
        st[v:v + 4] = 0.0
        return st

    def _robot_warmstart(self) -> np.ndarray:
        w = self.data.qacc_warmstart.copy()
        w[self._obj_vadr:self._obj_vadr + 4] = 0.0
        return w

    def _pad_ctrl(self, opening: float) -> float:
        return float(np.clip(opening / 2, 0.0, self.gripper.max_opening / 2))

    # ------------------------------------------------------------------ state access
    def current_q(self) -> np.ndarray:
        """Measured arm joints ``(7,)``."""
        return self.data.qpos[self._qadr].copy()

    def ee_state(self) -> np.ndarray:
        """Measured ee ``[x, y, z, yaw] (4,)``."""
        return ee_state_from_pose(self.data.site_xpos[self._site], self.data.site_xmat[self._site].reshape(3, 3))

    def true_state(self) -> np.ndarray:
        """Ground-truth SE(2) box state ``(3,)`` (metrics only)."""
        q = self.data.qpos[self._obj_qadr:self._obj_qadr + 4]
        return np.array([q[0], q[1], q[3]])

    def true_pose(self) -> np.ndarray:
        """Ground-truth object -> world pose ``(4, 4)`` float64 (metrics only)."""
        T = np.eye(4)
        T[:3, :3] = self.data.xmat[self._obj_body].reshape(3, 3)
        T[:3, 3] = self.data.xpos[self._obj_body]
        return T

    def reachable(self, points) -> np.ndarray:
        """Whether ee tip positions ``(N, 3)`` are in the arm's measured reach (``spec.reach_radius`` annulus
        around the base, tip heights ``spec.reach_height``), gripper pointing down, any yaw: ``(N,)`` bool."""
        p = _check_array(points, (3,), "points")
        r = np.hypot(p[:, 0] - BASE_POS[0], p[:, 1] - BASE_POS[1])
        (r0, r1), (h0, h1) = self.spec.reach_radius, self.spec.reach_height
        return (r >= r0) & (r <= r1) & (p[:, 2] >= h0) & (p[:, 2] <= h1)

    def ik_to_point(self, p, yaw: float, q0=None, restarts: int = 10) -> np.ndarray:
        """Arm joints ``(7,)`` putting the ee tip at ``p (3,)`` with yaw ``yaw`` (gripper down), from ``q0``
        (default the nominal posture). Unreachable goals give the best joint-limited approximation; check
        with ``ik_error``."""
        p = _check_array(p, (3,), "p", min_rows=0)
        if not math.isfinite(float(yaw)):
            raise ValueError(f"yaw must be finite, got {yaw}")
        q = Q_NOMINAL.copy() if q0 is None else _check_array(q0, (7,), "q0", min_rows=0).copy()
        R = yaw_rotation(float(yaw))
        for _ in range(restarts):
            q = self.ik.solve(q, p, R, iterations=20)
        return q

    def ik_error(self, q, p, yaw: float) -> tuple[float, float]:
        """Position (m) and rotation (rad) error of ``q (7,)`` w.r.t. the ee goal ``(p (3,), yaw)``."""
        return self.ik.error(_check_array(q, (7,), "q", min_rows=0), _check_array(p, (3,), "p", min_rows=0),
                             yaw_rotation(float(yaw)))

    def fk(self, q) -> np.ndarray:
        """ee ``[x, y, z, yaw] (4,)`` of arm joints ``q (7,)``."""
        p, R = self.ik.fk(_check_array(q, (7,), "q", min_rows=0))
        return ee_state_from_pose(p, R)

    # ------------------------------------------------------------------ reset
    def reset(self, seed: int | None = None) -> tuple[TouchObservation, dict]:
        """Draw the task instance of ``seed`` (``grasp_tasks.sample_task_instance``), put the box there at rest
        and the arm at ``HOME_EE``. Returns an empty ``TouchObservation`` (``K' = 0``) and ``info`` with
        ``true_pose (4, 4)`` float32 torch, ``true_state (3,)``, ``prior_means (2, 3)``, ``true_mode``."""
        seed = self.seed if seed is None else int(seed)
        s, m, d = self.spec, self.model, self.data
        means, mode, x = sample_task_instance(s, seed)
        self._noise = np.random.default_rng([seed, 1])
        mujoco.mj_resetData(m, d)
        d.qpos[self._obj_qadr:self._obj_qadr + 4] = (x[0], x[1], self.z_rest, x[2])
        if self._q_home is None:
            self._q_home = self.ik_to_point(HOME_EE[:3], HOME_EE[3])
        q = self._q_home.copy()
        d.qpos[self._qadr] = q
        d.qpos[self._pad_qadr] = self._pad_ctrl(s.poke_opening)
        self._target = np.concatenate([q, [self._pad_ctrl(s.poke_opening)] * 2])
        d.ctrl[:] = self._target
        mujoco.mj_forward(m, d)
        for _ in range(100):
            mujoco.mj_step(m, d)
        self._prior_means = means
        self._true_mode = mode
        self._n_actions = 0
        self._reset_done = True
        self._terminated = False
        return self._empty_obs(), self._info()

    def _empty_obs(self) -> TouchObservation:
        """A ``TouchObservation`` of no motion (``K' = 0``) at the current state."""
        return TouchObservation(
            z=np.zeros(0, bool), q=self.current_q()[None], ee=self.ee_state()[None], stopped_early=False,
            contact_force=0.0, tau_norm=np.zeros(0), ctrl=np.zeros((0, self.model.nu)),
            seg_end=np.zeros(0, np.int64), init_state=self._robot_state(), warmstart=self._robot_warmstart(),
            ctrl0=self._target.copy(), z_period=np.zeros(0, np.int64), z_samples=np.zeros(0, bool),
            tau_samples=np.zeros(0), force_samples=np.zeros(0), true_contact_samples=np.zeros(0, bool))

    def _info(self, **extra) -> dict:
        st = self.true_state()
        T = pose_from_xyz_yaw(torch.tensor([st[0], st[1], 0.0], dtype=torch.float64), torch.tensor(st[2]))
        info = {"true_pose": T.to(torch.float32), "true_state": st, "prior_means": self._prior_means.copy(),
                "true_mode": self._true_mode, "num_actions": self._n_actions}
        info.update(extra)
        return info

    # ------------------------------------------------------------------ planning (no physics)
    def _ee_path_ctrl(self, q0: np.ndarray, ee0: np.ndarray, waypoints: np.ndarray, pad: float,
                      clip_height: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """IK chain along the straight ee path through ``waypoints (K, 4)`` from ``ee0`` / ``q0``.

        Returns ``ctrl (S, nu)``, ``seg_end (K,)`` and the commanded joints at the waypoints ``(K, 7)``.
        """
        s = self.spec
        ctrl, seg_end, q_wp = [], [], []
        q = np.array(q0, float)
        prev = np.array(ee0, float)
        for wp in waypoints:
            tgt = np.array(wp, float)
            if clip_height:
                tgt[2] = max(tgt[2], s.min_poke_height)
            dpos = tgt[:3] - prev[:3]
            dyaw = float(_wrap(tgt[3] - prev[3]))
            n = max(1, int(math.ceil(max(np.linalg.norm(dpos) / s.max_ee_step, abs(dyaw) / s.max_yaw_step))))
            for j in range(1, n + 1):
                a = j / n
                q = self.ik.solve(q, prev[:3] + a * dpos, yaw_rotation(prev[3] + a * dyaw),
                                  iterations=s.ik_iterations)
                ctrl.append(np.concatenate([q, [pad, pad]]))
            seg_end.append(len(ctrl) - 1)
            q_wp.append(q.copy())
            prev = np.concatenate([tgt[:3], [prev[3] + dyaw]])
        return np.asarray(ctrl), np.asarray(seg_end, np.int64), np.asarray(q_wp)

    def _rest_state(self, q: np.ndarray, pad: float) -> np.ndarray:
        """Full physics state with the arm at rest at ``q (7,)`` and the pads at ``pad``."""
        d = self._kin
        mujoco.mj_resetData(self.model, d)
        d.qpos[self._qadr] = q
        d.qpos[self._pad_qadr] = pad
        d.qpos[self._obj_qadr:self._obj_qadr + 4] = (0.4, 0.0, self.z_rest, 0.0)
        return self._get_state(d)

    def plan_poke(self, waypoints, q0=None) -> MotionPlan:
        """The control sequence ``step(PokeAction(waypoints))`` would execute (same IK chain), as a guarded
        ``MotionPlan``. ``q0 (7,)``: start joints (default: the current ones, and the current physics state as
        the start state; otherwise the arm at rest at ``q0``)."""
        w = PokeAction(waypoints).waypoints
        self._check_len(w)
        pad = self._pad_ctrl(self.spec.poke_opening)
        if q0 is None:
            self._require_reset()
            q0, ee0 = self.current_q(), self.ee_state()
            init, warm, c0 = self._robot_state(), self._robot_warmstart(), self._target.copy()
        else:
            q0 = _check_array(q0, (7,), "q0", min_rows=0)
            ee0 = self.fk(q0)
            init, warm, c0 = self._rest_state(q0, pad), None, np.concatenate([q0, [pad, pad]])
        ctrl, seg_end, q_wp = self._ee_path_ctrl(q0, ee0, w, pad)
        return MotionPlan(ctrl, seg_end, init, warm, np.concatenate([q0[None], q_wp]), c0, guarded=True)

    # ------------------------------------------------------------------ model hooks (protocol.GraspRobotEnv)
    def robot_physics_state(self, q, dq, pads, pad_velocities, time: float = 0.0, warmstart=None
                            ) -> tuple[np.ndarray, np.ndarray | None]:
        """The full physics state ``(nstate,)`` and solver warm start ``(nv,)`` (or None) of a robot measured at arm
        joints ``q (7,)`` / velocities ``dq (7,)`` and pad slides ``pads (2,)`` / ``pad_velocities (2,)`` at
        ``time`` (s), the box parked out of reach: what ``_robot_state()`` and ``_robot_warmstart()`` give for this
        environment's own arm, built from another robot's measurements, so this environment can serve as the model
        of a robot driven through ``activetouch.protocol`` (plans and rollouts start where that robot is).
        ``warmstart``: ``(9,)`` the constraint solver's warm start of the arm's and pads' dofs (a simulated robot's;
        None: the solver starts cold). Reads and changes nothing of this environment's own state."""
        q = _check_array(q, (7,), "q", min_rows=0)
        dq = _check_array(dq, (7,), "dq", min_rows=0)
        pads = _check_array(pads, (2,), "pads", min_rows=0)
        pad_v = _check_array(pad_velocities, (2,), "pad_velocities", min_rows=0)
        if not math.isfinite(float(time)):
            raise ValueError(f"time must be finite, got {time}")
        d = mujoco.MjData(self.model)  # a fresh one: the state of nothing else leaks in
        d.time = float(time)
        d.qpos[self._qadr], d.qvel[self._vadr] = q, dq
        d.qpos[self._pad_qadr], d.qvel[self._pad_vadr] = pads, pad_v
        d.qpos[self._obj_qadr:self._obj_qadr + 4] = (*PARK_XY, self.z_rest, 0.0)
        d.qvel[self._obj_vadr:self._obj_vadr + 4] = 0.0
        warm = None
        if warmstart is not None:
            w = _check_array(warmstart, (9,), "warmstart", min_rows=0)
            warm = np.zeros(self.model.nv)
            warm[self._vadr], warm[self._pad_vadr] = w[:7], w[7:]
        return self._get_state(d), warm

    def plan_poke_at(self, waypoints, q0, ee0, init_state, warmstart, ctrl0) -> MotionPlan:
        """``plan_poke(waypoints)`` from a given start instead of this environment's current state: arm joints
        ``q0 (7,)``, measured ee ``ee0 (4,)``, physics state ``init_state`` and warm start ``warmstart``
        (``robot_physics_state``) and the actuator targets in effect ``ctrl0 (9,)``: the same IK chain, so a model
        plans exactly the motion a robot at that state executes for ``GuardedMoveCommand(waypoints)``."""
        w = PokeAction(waypoints).waypoints
        self._check_len(w)
        q0 = _check_array(q0, (7,), "q0", min_rows=0)
        ee0 = _check_array(ee0, (4,), "ee0", min_rows=0)
        init = _check_array(init_state, (self._nstate,), "init_state", min_rows=0)
        c0 = _check_array(ctrl0, (self.model.nu,), "ctrl0", min_rows=0)
        ctrl, seg_end, q_wp = self._ee_path_ctrl(q0, ee0, w, self._pad_ctrl(self.spec.poke_opening))
        return MotionPlan(ctrl, seg_end, init.copy(), None if warmstart is None else np.array(warmstart, float),
                          np.concatenate([q0[None], q_wp]), c0.copy(), guarded=True)

    def plan_from_joints(self, q_plan, opening: float | None = None) -> MotionPlan:
        """A guarded ``MotionPlan`` through arm configurations ``q_plan (K+1, 7)`` (start at rest at
        ``q_plan[0]``), interpolated linearly in joint space at the control rate (at most ``max_ee_step`` of
        ee motion, ``max_yaw_step`` of yaw and ``MAX_JOINT_STEP`` rad of any joint per period)."""
        q_plan = _check_array(q_plan, (7,), "q_plan", min_rows=2)
        self._check_len(q_plan[1:])
        s = self.spec
        pad = self._pad_ctrl(s.poke_opening if opening is None else opening)
        ee = np.stack([self.fk(q) for q in q_plan])
        ctrl, seg_end = [], []
        for k in range(1, len(q_plan)):
            dq = q_plan[k] - q_plan[k - 1]
            n = max(1, int(math.ceil(max(np.linalg.norm(ee[k, :3] - ee[k - 1, :3]) / s.max_ee_step,
                                         abs(float(_wrap(ee[k, 3] - ee[k - 1, 3]))) / s.max_yaw_step,
                                         np.abs(dq).max() / MAX_JOINT_STEP))))
            for j in range(1, n + 1):
                ctrl.append(np.concatenate([q_plan[k - 1] + j / n * dq, [pad, pad]]))
            seg_end.append(len(ctrl) - 1)
        return MotionPlan(np.asarray(ctrl), np.asarray(seg_end, np.int64), self._rest_state(q_plan[0], pad), None,
                          q_plan.copy(), np.concatenate([q_plan[0], [pad, pad]]), guarded=True)

    def _check_len(self, w: np.ndarray):
        if len(w) > self.spec.max_waypoints:
            raise ValueError(f"a motion has at most {self.spec.max_waypoints} waypoints, got {len(w)}")

    def grasp_yaw(self, box_yaw: float) -> float:
        """ee yaw of the grasp of a box at ``box_yaw``: pads (ee y) across the box's narrow object-x axis,
        folded into [-pi/2, pi/2) (the gripper is symmetric under a half turn)."""
        y = box_yaw + math.pi / 2
        return float((y + math.pi / 2) % math.pi - math.pi / 2)

    def grasp_plan(self, grasp_state) -> MotionPlan:
        """The grasp primitive below the pre-grasp pose for the SE(2) box pose ``grasp_state (3,)``: starting
        at rest above the box with the pads open (``init_state``), descend, close, lift and hold.
        ``seg_end`` marks the end of each phase (descent, close, lift, hold); ``q[0]`` is the pre-grasp arm
        configuration (solved from the nominal posture)."""
        g = _check_array(grasp_state, (3,), "grasp state", min_rows=0)
        s = self.spec
        yaw = self.grasp_yaw(g[2])
        z_pre = self._obj_top + s.pregrasp_clearance
        z_grasp = self._obj_top - s.grasp_depth
        q_pre = self.ik_to_point(np.array([g[0], g[1], z_pre]), yaw)
        open_, closed = self._pad_ctrl(s.gripper_opening), 0.0
        ee_pre = np.array([g[0], g[1], z_pre, yaw])
        ctrl_d, end_d, q_d = self._ee_path_ctrl(q_pre, ee_pre, np.array([[g[0], g[1], z_grasp, yaw]]), open_,
                                                clip_height=False)
        n_close = max(1, int(round(s.grasp_close_time / s.control_dt)))
        q_low = q_d[-1]
        close = np.tile(np.concatenate([q_low, [closed, closed]]), (n_close, 1))
        ctrl_l, _, q_l = self._ee_path_ctrl(q_low, np.array([g[0], g[1], z_grasp, yaw]),
                                            np.array([[g[0], g[1], z_grasp + s.lift_height, yaw]]), closed,
                                            clip_height=False)
        n_hold = max(1, int(round(s.lift_hold_time / s.control_dt)))
        hold = np.tile(np.concatenate([q_l[-1], [closed, closed]]), (n_hold, 1))
        ctrl = np.concatenate([ctrl_d, close, ctrl_l, hold])
        ends = np.cumsum([len(ctrl_d), n_close, len(ctrl_l), n_hold]) - 1
        return MotionPlan(ctrl, ends.astype(np.int64), self._rest_state(q_pre, open_), None,
                          np.stack([q_pre, q_low, q_low, q_l[-1], q_l[-1]]), np.concatenate([q_pre, [open_, open_]]),
                          guarded=False)

    # ------------------------------------------------------------------ physics
    def _measure(self) -> tuple[float, float, bool, np.ndarray]:
        """Noisy torque norm (first ``contact_joints``), estimated ee force, true contact, noisy torques (7,)."""
        s, m, d = self.spec, self.model, self.data
        tau = d.qfrc_constraint[self._vadr].copy()
        if s.torque_noise_std > 0:
            tau = tau + self._noise.normal(0.0, s.torque_noise_std, 7)
        mujoco.mj_jacSite(m, d, self._jacp, None, self._site)
        J = self._jacp[:, self._vadr]
        # damped pseudo-inverse of J^T: F = (J J^T + lambda^2 I)^-1 J tau (App. D-b's projection onto the ee)
        F = np.linalg.solve(J @ J.T + 1e-4 * np.eye(3), J @ tau)
        touching = False
        for i in range(d.ncon):
            c = d.contact[i]
            if int(c.geom1) in self._robot_geom_set or int(c.geom2) in self._robot_geom_set:
                touching = True
                break
        return float(np.linalg.norm(tau[:s.contact_joints])), float(np.linalg.norm(F)), touching, tau

    def expand_ctrl(self, ctrl: np.ndarray, ctrl0: np.ndarray) -> np.ndarray:
        """Physics-rate actuator inputs ``(S * substeps, nu)`` of control targets ``ctrl (S, nu)`` (``ctrl0`` in
        effect before): a first-order hold (linear ramp over each period) plus, for the arm, the velocity
        feed-forward ``(kv / kp) * dq*/dt``, so the position servo ``kp (u - q) - kv dq`` becomes
        ``kp (q* - q) + kv (dq* - dq)`` and tracks the moving target without the ``kv v / kp`` lag (~1 cm at
        0.2 m/s otherwise). The environment and the rollouts use this one expansion."""
        sub = self.spec.substeps
        prev = np.concatenate([np.asarray(ctrl0, float)[None], ctrl[:-1]])
        a = np.arange(1, sub + 1) / sub
        phys = prev[:, None, :] + a[None, :, None] * (ctrl - prev)[:, None, :]
        phys[..., :7] += (self._lead * (ctrl[:, :7] - prev[:, :7]) / self.spec.control_dt)[:, None, :]
        return phys.reshape(-1, ctrl.shape[1])

    def _run(self, ctrl: np.ndarray) -> float:
        """One control period toward the target ``ctrl (nu,)``; returns the largest object-robot contact force
        (N, the ``object_robot_force`` sensor) over its physics steps."""
        phys = self.expand_ctrl(np.asarray(ctrl, float)[None], self._target)
        f = 0.0
        for u in phys:
            self.data.ctrl[:] = u
            mujoco.mj_step(self.model, self.data)
            f = max(f, float(np.linalg.norm(self.data.sensordata[:3])))
        self._target = np.array(ctrl, float)
        return f

    def _object_moving(self) -> bool:
        """Whether the box moves faster than ``spec.settle_speed`` (m/s in the plane, 10 x that in rad/s)."""
        v = self.data.qvel[self._obj_vadr:self._obj_vadr + 4]
        lim = self.spec.settle_speed
        return bool(math.hypot(v[0], v[1]) > lim or abs(v[3]) > 10 * lim)

    def _require_reset(self):
        if not self._reset_done:
            raise RuntimeError("call reset() before step()")

    def step(self, action):
        """Execute a ``PokeAction`` or ``GraspAction`` (module docstring).

        Returns ``(obs, reward, terminated, truncated, info)``. Pokes: ``obs`` a ``TouchObservation``, reward 0; ``info`` adds
        ``object_states (K'+1, 3)`` (ground truth, metrics/tests only); never truncated (after ``max_actions`` pokes
        only a grasp is allowed). Grasp: ``obs`` empty (``K' = 0``),
        ``terminated=True``, reward 1 on success, ``info["grasp_success"]`` and ``info["object_height"]``.
        Not thread-safe: use one environment per thread.
        """
        self._require_reset()
        if self._terminated:
            raise RuntimeError("the episode has terminated (grasp done); call reset()")
        if isinstance(action, PokeAction):
            if self._n_actions >= self.spec.max_actions:
                raise RuntimeError(f"max_actions = {self.spec.max_actions} pokes made; only a GraspAction is allowed")
            return self._poke(action.waypoints)
        if isinstance(action, GraspAction):
            return self._grasp(action.state)
        raise ValueError(f"action must be a PokeAction or GraspAction, got {type(action).__name__}")

    def _poke(self, waypoints: np.ndarray):
        s = self.spec
        self._check_len(waypoints)
        plan = self.plan_poke(waypoints)
        ctrl0 = self._target.copy()
        q_log, ee_log, obj_log = [self.current_q()], [self.ee_state()], [self.true_state()]
        ctrl_done, zs, taus, forces, touch = [], [], [], [], []
        z_wp, tau_wp, seg_end, z_per = [], [], [], []
        seg = 0
        stopped = False
        # the guard acts on the force's rise above its lowest value in this poke, so a poke that starts pressing on
        # something (after a guarded stop) can move away, and stops if it presses harder
        base = self._measure()[1]

        def period(c: np.ndarray) -> tuple[float, float]:  # run one control period and log its signals
            self._run(c)
            tn, f, t, _ = self._measure()
            ctrl_done.append(c)
            zs.append(tn > s.contact_threshold)
            taus.append(tn)
            forces.append(f)
            touch.append(t)
            return tn, f

        def record(tau_norm: float) -> None:  # one observation: the last period's z, the arm and the box now
            z_wp.append(zs[-1])
            tau_wp.append(tau_norm)
            z_per.append(len(zs) - 1)
            seg_end.append(len(ctrl_done) - 1)
            q_log.append(self.current_q())
            ee_log.append(self.ee_state())
            obj_log.append(self.true_state())

        for i, c in enumerate(plan.ctrl):
            tn, f = period(c)
            base = min(base, f)
            if f - base > s.guard_force:
                stopped = True
                # two observations: the guard's trigger (its z, the arm and the box at that period) and the end of
                # the hold (a pushed box may slide on, off the stopped gripper): each z is paired with the robot and
                # object states of its own instant, as the filter's Eq. 10 and the rollouts need
                record(tn)
                hold = np.concatenate([self.current_q(), c[7:]])
                for _ in range(s.stop_hold):
                    tn, _ = period(hold)
                if s.stop_hold > 0:
                    record(tn)
                break
            if i == plan.seg_end[seg]:
                record(tn)
                seg += 1
        n_settle = int(round(s.settle_time / s.control_dt))
        if n_settle > 0 and ctrl_done and self._object_moving():
            # the box still slides or spins (a hard first contact): hold the last command until it is at rest, so
            # the next poke (and every particle's rollout of it) starts from a resting box (spec.settle_time)
            for _ in range(n_settle):
                tn, _ = period(ctrl_done[-1])
                if not self._object_moving():
                    break
            record(tn)
        self._n_actions += 1
        obs = TouchObservation(
            z=np.asarray(z_wp, bool), q=np.asarray(q_log), ee=np.asarray(ee_log), stopped_early=stopped,
            contact_force=float(max(forces)), tau_norm=np.asarray(tau_wp), ctrl=np.asarray(ctrl_done),
            seg_end=np.asarray(seg_end, np.int64), init_state=plan.init_state, warmstart=plan.warmstart,
            ctrl0=ctrl0, z_period=np.asarray(z_per, np.int64), z_samples=np.asarray(zs, bool),
            tau_samples=np.asarray(taus), force_samples=np.asarray(forces),
            true_contact_samples=np.asarray(touch, bool))
        # not truncated after the last poke: the episode still ends with the grasp (App. D-e); step() refuses
        # more pokes than max_actions
        return obs, 0.0, False, False, self._info(object_states=np.asarray(obj_log),
                                                       target_waypoints=plan.q.shape[0] - 1)

    def _grasp(self, g: np.ndarray):
        s = self.spec
        plan = self.grasp_plan(g)
        q_pre = plan.q[0]
        pad_now = float(self._target[7])
        open_ = self._pad_ctrl(s.gripper_opening)
        # 1) straight up to the pre-grasp height, 2) joint-space transit to the pre-grasp configuration while
        # opening, 3) settle; then the primitive exactly as grasp_plan / grasp_success simulate it.
        ee = self.ee_state()
        z_pre = self._obj_top + s.pregrasp_clearance
        if ee[2] < z_pre:
            ctrl_up, _, q_up = self._ee_path_ctrl(self.current_q(), ee, np.array([[ee[0], ee[1], z_pre, ee[3]]]),
                                                  pad_now, clip_height=False)
            for c in ctrl_up:
                self._run(c)
            q_from = q_up[-1]
        else:
            q_from = self.current_q()
        dq = q_pre - q_from
        n = max(1, int(math.ceil(np.abs(dq).max() / MAX_JOINT_STEP)))
        for j in range(1, n + 1):
            a = j / n
            self._run(np.concatenate([q_from + a * dq, [pad_now + a * (open_ - pad_now)] * 2]))
        for _ in range(15):
            self._run(np.concatenate([q_pre, [open_, open_]]))
        aborted = False
        for i, c in enumerate(plan.ctrl):
            f = self._run(c)
            if i <= plan.seg_end[0] and f > s.grasp_guard_force:  # guarded descent: a pad landed on the box
                aborted = True
                hold = np.concatenate([self.current_q(), c[7:]])
                for _ in range(s.stop_hold):
                    self._run(hold)
                break
        z = float(self.data.qpos[self._obj_qadr + 2])
        success = bool(not aborted and z > s.success_height)
        self._terminated = True
        self._n_actions += 1
        return self._empty_obs(), float(success), True, False, self._info(grasp_success=success, object_height=z,
                                                                          grasp_aborted=aborted)

    # ------------------------------------------------------------------ robot surface points
    def _geom_surface(self, spacing: float) -> tuple[np.ndarray, np.ndarray]:
        """Surface points of every robot collision geom in its own frame ``(M, 3)`` and their geom ``(M,)``.

        Boxes: a grid on each face (edges and corners included). Cylinders and meshes: trimesh's even (Poisson
        disk, seeded) surface sampling of the primitive / of the mesh's convex hull (MuJoCo collides a mesh as
        its hull); the grid is written here because the pads' flat faces and edges matter most for d.
        """
        if spacing in self._surface_cache:
            return self._surface_cache[spacing]
        import trimesh

        m = self.model
        pts, gid = [], []
        grip = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "gripper")
        for gi, g in enumerate(self.robot_geoms):
            t = m.geom_type[g]
            size = m.geom_size[g]
            # the gripper touches the box far more often than the links, and Eq. 10's gamma = 1000 / m makes d's
            # error matter at the millimetre: its geoms get at most GRIPPER_SPACING (a 1 cm grid reads a box
            # corner against a pad face up to ~7 mm away, where the contact likelihood is already ~alpha_fp)
            sp = min(spacing, GRIPPER_SPACING) if grip >= 0 and self._in_subtree(int(m.geom_bodyid[g]), grip) else spacing
            if t == mujoco.mjtGeom.mjGEOM_BOX:
                p = _box_surface(size, sp)
            else:
                if t == mujoco.mjtGeom.mjGEOM_MESH:
                    mid = m.geom_dataid[g]
                    v = m.mesh_vert[m.mesh_vertadr[mid]:m.mesh_vertadr[mid] + m.mesh_vertnum[mid]]
                    tm = trimesh.Trimesh(vertices=np.asarray(v, float)).convex_hull
                elif t == mujoco.mjtGeom.mjGEOM_CYLINDER:
                    tm = trimesh.creation.cylinder(radius=size[0], height=2 * size[1], sections=32)
                else:  # pragma: no cover - the scene has boxes, cylinders and meshes only
                    raise ValueError(f"unsupported robot geom type {t}")
                n = max(8, int(math.ceil(tm.area / sp ** 2)))
                tlog = logging.getLogger("trimesh")
                level = tlog.level
                tlog.setLevel(logging.ERROR)  # it logs "only got N/M samples" for the rejected ones
                try:
                    p, _ = trimesh.sample.sample_surface_even(tm, n, radius=0.7 * sp, seed=0)
                finally:
                    tlog.setLevel(level)
            pts.append(np.asarray(p, float))
            gid.append(np.full(len(p), gi))
        out = (np.concatenate(pts), np.concatenate(gid))
        self._surface_cache[spacing] = out
        return out

    def _geom_poses(self, q: np.ndarray, pad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World rotations ``(K, G, 3, 3)`` and positions ``(K, G, 3)`` of the robot geoms at ``q (K, 7)``."""
        d = self._kin
        g = self.robot_geoms
        R = np.empty((len(q), len(g), 3, 3))
        t = np.empty((len(q), len(g), 3))
        for k in range(len(q)):
            d.qpos[self._qadr] = q[k]
            d.qpos[self._pad_qadr] = pad[k]
            mujoco.mj_kinematics(self.model, d)
            R[k] = d.geom_xmat[g].reshape(-1, 3, 3)
            t[k] = d.geom_xpos[g]
        return R, t

    def _points_np(self, q: np.ndarray, pad: np.ndarray, spacing: float) -> np.ndarray:
        local, gid = self._geom_surface(spacing)
        R, t = self._geom_poses(q, pad)
        return np.einsum("kmij,mj->kmi", R[:, gid], local) + t[:, gid]

    def robot_points(self, q, spacing: float = 0.01, opening=None) -> torch.Tensor:
        """World points on the surfaces of every robot collision geom (links 1-7 and the gripper: the "whole
        robot" of Eq. 10's distance d) at each arm configuration: ``q (K, 7)`` -> ``(K, M, 3)`` float32.

        Args:
            q: arm joints per configuration.
            spacing: surface sampling distance (m); ``M`` grows like ``1 / spacing^2`` (~7300 at 0.01, ~1800
                at 0.02; the arm links are most of it: with gamma = 1000 / m in Eq. 10 keep it <= 0.01).
            opening: pad gap (m), a scalar or ``(K,)``; default ``spec.poke_opening``.
        """
        q = _check_array(q, (7,), "q")
        if not (math.isfinite(spacing) and spacing > 0):
            raise ValueError(f"spacing must be finite and > 0, got {spacing}")
        op = self.spec.poke_opening if opening is None else opening
        op = np.broadcast_to(np.asarray(op, float), (len(q),))
        if not np.isfinite(op).all():
            raise ValueError("opening contains NaN or inf")
        pad = np.clip(op / 2, 0.0, self.gripper.max_opening / 2)
        return torch.as_tensor(self._points_np(q, pad, float(spacing)), dtype=torch.float32)

    # ------------------------------------------------------------------ particle rollouts
    def _reference(self, motion: MotionPlan) -> np.ndarray:
        """States ``(S+1, nstate)`` at the start and at the end of every control period of ``motion`` with the box
        parked out of reach: the robot's own trajectory, which is every particle's until its box is touched
        (cached on the motion)."""
        ref = getattr(motion, "_reference_states", None)
        if ref is not None:
            return ref
        init = motion.init_state.copy()
        o, v = self._state_obj_q, self._state_obj_v
        init[o:o + 4] = (*PARK_XY, self.z_rest, 0.0)
        init[v:v + 4] = 0.0
        control = self.expand_ctrl(motion.ctrl, motion.ctrl0)[None]
        warm = None if motion.warmstart is None else motion.warmstart[None]
        state, _ = self._pool_rollout(init[None], control, warm)
        sub = self.spec.substeps
        ref = np.concatenate([motion.init_state[None], state[0, sub - 1::sub]])
        motion._reference_states = ref
        return ref

    def _pool_rollout(self, init: np.ndarray, control: np.ndarray, warm=None):
        if self._pool is None:
            raise RuntimeError("the environment was closed")
        return self._pool.rollout(self.model, self._rdata, np.ascontiguousarray(init), np.ascontiguousarray(control),
                                  initial_warmstart=warm)

    def _sweep_cells(self, ref: np.ndarray) -> "_Sweep":
        """The robot's surface at each configuration of ``ref`` (points every ``SWEEP_SPACING``) below the box
        top + reach, reduced to the columns of a ``SWEEP_CELL`` grid in xy: for every (configuration, column) the
        column centre and the lowest point's height (an upright box spans heights 0..top, so a column's lowest
        point is its nearest one), with a k-d tree over the columns' xy."""
        qoff = self._state_obj_q - self._obj_qadr
        q = ref[:, qoff + self._qadr]
        pad = ref[:, qoff + self._pad_qadr[0]]
        local, gid = self._geom_surface(SWEEP_SPACING)
        R, t = self._geom_poses(q, pad)
        top = self._obj_top + self.spec.rollout_margin + SWEEP_ALLOWANCE
        low = t[..., 2] - self._geom_radius[None] <= top  # cull (configuration, geom) pairs above the reach
        keys, zs = [], []
        for g in np.nonzero(low.any(axis=0))[0]:
            ks = np.nonzero(low[:, g])[0]
            p = np.einsum("kij,mj->kmi", R[ks, g], local[gid == g]) + t[ks, g][:, None]
            keep = p[..., 2] <= top
            c = np.floor(p[..., :2] / SWEEP_CELL).astype(np.int64) + 2 ** 19
            key = (np.broadcast_to(ks[:, None], keep.shape) << 40) | (c[..., 0] << 20) | c[..., 1]
            keys.append(key[keep])
            zs.append(p[..., 2][keep])
        if not keys or sum(len(k) for k in keys) == 0:
            return _Sweep(np.zeros((0, 3)), np.zeros(0, np.int64), len(ref), None)
        key, z = np.concatenate(keys), np.concatenate(zs)
        order = np.argsort(key, kind="stable")
        key, z = key[order], z[order]
        first = np.concatenate([[0], np.nonzero(np.diff(key))[0] + 1])
        u, zmin = key[first], np.minimum.reduceat(z, first)
        cx = ((u >> 20) & (2 ** 20 - 1)) - 2 ** 19
        cy = (u & (2 ** 20 - 1)) - 2 ** 19
        cells = np.stack([(cx + 0.5) * SWEEP_CELL, (cy + 0.5) * SWEEP_CELL, zmin], axis=1)
        return _Sweep(cells, u >> 40, len(ref), cKDTree(cells[:, :2]))

    def _cell_dist(self, x: np.ndarray, sweep: "_Sweep", first_cfg: int = 0) -> np.ndarray:
        """Distance ``(P, ncfg - first_cfg)`` from each particle's box (the upright bounding box of the object at
        SE(2) state ``x (P, 3)``: a rectangle in xy, heights 0..top) to the nearest sweep cell of each
        configuration from ``first_cfg`` on; inf where none is within ``box radius + rollout_margin +
        SWEEP_ALLOWANCE`` of the box centre in xy (the sweep's k-d tree, scipy's, picks the candidate pairs)."""
        out = np.full((len(x), sweep.ncfg - first_cfg), np.inf, dtype=np.float32)
        if sweep.tree is None or len(x) == 0:
            return out
        lists = sweep.tree.query_ball_point(x[:, :2], self._query_radius)
        counts = np.fromiter((len(li) for li in lists), dtype=np.int64, count=len(x))
        if counts.sum() == 0:
            return out
        pi = np.repeat(np.arange(len(x)), counts)
        ci = np.concatenate([np.asarray(li, dtype=np.int64) for li in lists if len(li)])
        if first_cfg:
            keep = sweep.cfg[ci] >= first_cfg
            pi, ci = pi[keep], ci[keep]
        c = sweep.cells
        cs, sn = np.cos(x[pi, 2]), np.sin(x[pi, 2])
        dx, dy = c[ci, 0] - x[pi, 0], c[ci, 1] - x[pi, 1]
        lx, ly = cs * dx + sn * dy, -sn * dx + cs * dy  # cells in each particle's object frame
        (x0, y0), (x1, y1) = self._rect_lo, self._rect_hi
        ex = np.maximum(np.maximum(x0 - lx, lx - x1), 0.0)
        ey = np.maximum(np.maximum(y0 - ly, ly - y1), 0.0)
        ez = np.maximum(c[ci, 2] - self._obj_top, 0.0)
        np.minimum.at(out, (pi, sweep.cfg[ci] - first_cfg), np.sqrt(ex * ex + ey * ey + ez * ez))
        return out

    def _engine(self, x: np.ndarray, motion: MotionPlan, grasp: tuple[int, int] | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Batched physics of ``motion`` with the box starting at rest at each SE(2) state ``x (P, 3)``.

        Returns the object qpos ``(P, S, 4)`` at the end of every control period, ``simulated (P,)`` and the
        period of an emulated guarded stop ``(P,)`` (-1: none). Exactness-preserving shortcuts (a resting box
        only moves when something touches it, and before that the robot's motion does not depend on it):
        - a particle is simulated only from two periods before the robot's swept surface (``_sweep_cells``)
          first comes within ``rollout_margin`` (+ ``SWEEP_ALLOWANCE`` for the sampling, the 1.5 cm columns and
          the <= 4 mm a period moves) of its box, starting from the robot's reference state at that period
          (the warm start aside, the same state the full run would have: nothing touched the robot before);
        - it stops being simulated once its box is at rest and the rest of the sweep stays clear of it, or (a
          guarded motion) once its contact force passes ``guard_force``: the real arm stops there, the open-loop
          rollout cannot branch, so the box is frozen at that period (simplification: the hold's settling is
          ignored and the true contact force stands in for the noisy torque projection).
        - a grasp (``grasp``: the last periods of the descent and of the closing phase) ends for a particle once
          its box is above ``success_height`` (lifted: success; the grip is 5x the weight, it does not slip
          afterwards), when the guarded descent hits the box (contact force above ``grasp_guard_force``, the
          environment aborts that grasp) or when the closed pads hold nothing (both slides below ``EMPTY_PAD``):
          failure.
        Simulation runs in chunks of ``ROLLOUT_CHUNK`` periods through ``mujoco.rollout``'s thread pool. A chunk
        restarts the solver without the warm start (the results differ by < 1e-6 m unless the contact
        dynamics are chaotic, e.g. a box pivoting about a pad's corner during a long push).
        """
        s = self.spec
        sub, S, n = s.substeps, len(motion.ctrl), len(x)
        o, v = self._state_obj_q, self._state_obj_v
        out = np.empty((n, S, 4))
        out[:] = np.concatenate([x[:, :2], np.full((n, 1), self.z_rest), x[:, 2:3]], axis=1)[:, None]
        simulated = np.zeros(n, bool)
        stop = np.full(n, -1, np.int64)
        if S == 0:
            return out, simulated, stop
        self.rollout_stats = {"particle_periods": 0, "calls": 0}
        ref = self._reference(motion)
        sweep = self._sweep_cells(ref)
        reach = s.rollout_margin + SWEEP_ALLOWANCE
        near = self._cell_dist(x, sweep) <= reach  # (P, S+1) per configuration
        touched = near.any(axis=1)
        # period j moves the robot from configuration j to j+1: start one period before the first near one
        start = np.where(touched, np.maximum(near.argmax(axis=1) - 2, 0), S)
        phys = self.expand_ctrl(motion.ctrl, motion.ctrl0)
        cur = np.zeros((n, self._nstate))
        active = np.zeros(n, bool)
        next_check = np.zeros(n, np.int64)  # a resting box is re-tested for "clear of the rest" from here on
        t = int(start.min()) if touched.any() else S
        while t < S:
            new = np.nonzero(touched & ~simulated & (start < t + ROLLOUT_CHUNK))[0]
            if len(new):
                cur[new] = ref[t]
                cur[new, o:o + 4] = out[new, 0]
                cur[new, v:v + 4] = 0.0
                simulated[new] = True
                active[new] = True
            idx = np.nonzero(active)[0]
            if len(idx) == 0:
                pending = touched & ~simulated
                if not pending.any():
                    break
                t = int(start[pending].min())
                continue
            t1 = min(t + ROLLOUT_CHUNK, S)
            warm = motion.warmstart[None] if (t == 0 and motion.warmstart is not None) else None
            state, sens = self._pool_rollout(cur[idx], phys[None, t * sub:t1 * sub], warm)
            self.rollout_stats["particle_periods"] += len(idx) * (t1 - t)
            self.rollout_stats["calls"] += 1
            obj = state[:, sub - 1::sub, o:o + 4]  # (m, t1 - t, 4)
            out[idx, t:t1] = obj
            cur[idx] = state[:, -1]
            done = np.zeros(len(idx), bool)
            if motion.guarded or grasp is not None:
                f = np.linalg.norm(sens.reshape(len(idx), t1 - t, sub, 3), axis=-1).max(axis=-1)
            if motion.guarded:
                hit = f > s.guard_force
                for r in np.nonzero(hit.any(axis=1))[0]:
                    j = t + int(hit[r].argmax())
                    out[idx[r], j:] = out[idx[r], j]
                    stop[idx[r]] = j
                    done[r] = True
            if grasp is not None:
                descent_end, close_end = grasp
                if t <= descent_end:
                    hit = (f > s.grasp_guard_force) & (np.arange(t, t1) <= descent_end)[None]
                    for r in np.nonzero(~done & hit.any(axis=1))[0]:
                        j = t + int(hit[r].argmax())
                        out[idx[r], j:] = out[idx[r], j]
                        out[idx[r], j:, 2] = min(out[idx[r], j, 2], self.z_rest)  # aborted: a failure
                        done[r] = True
                lifted = state[:, sub - 1::sub, o + 2] > s.success_height
                for r in np.nonzero(~done & lifted.any(axis=1))[0]:
                    j = t + int(lifted[r].argmax())
                    out[idx[r], j:] = out[idx[r], j]
                    done[r] = True
                if t <= close_end < t1:
                    qoff = self._state_obj_q - self._obj_qadr
                    pads = state[:, (close_end - t + 1) * sub - 1, qoff + self._pad_qadr]
                    empty = ~done & (pads < EMPTY_PAD).all(axis=1)
                    out[idx[empty], close_end:] = out[idx[empty], close_end][:, None]
                    done |= empty
            if t1 < S:
                vel = np.abs(state[:, -1, v:v + 4]).max(axis=1)
                rest = np.nonzero(~done & (vel < REST_SPEED) & (next_check[idx] <= t1))[0]
                if len(rest):
                    xr = cur[idx[rest]][:, [o, o + 1, o + 3]]
                    near_f = self._cell_dist(xr, sweep, first_cfg=t1) <= reach
                    clear = ~near_f.any(axis=1)
                    ri = rest[clear]
                    out[idx[ri], t1:] = out[idx[ri], t1 - 1][:, None]
                    done[ri] = True
                    # not clear: at this pose it stays near until its last near configuration; test again after
                    last = near_f.shape[1] - 1 - np.argmax(near_f[:, ::-1], axis=1)
                    next_check[idx[rest[~clear]]] = t1 + last[~clear]
            active[idx[done]] = False
            t = t1
        return out, simulated, stop

    def _as_states(self, states) -> tuple[np.ndarray, torch.dtype, torch.device]:
        dtype, device = torch.float64, torch.device("cpu")
        if torch.is_tensor(states):
            device = states.device
            if torch.is_floating_point(states):
                dtype = states.dtype
        return _check_array(states, (3,), "states"), dtype, device

    def rollout_detailed(self, states, motion) -> RolloutResult:
        """``rollout`` plus which particles were simulated and the waypoint at which an emulated guarded stop
        froze each (-1: none)."""
        x, dtype, device = self._as_states(states)
        motion = self._as_motion(motion)
        obj, simulated, stop = self._engine(x, motion)
        res = obj[:, motion.seg_end][..., [0, 1, 3]] if motion.num_waypoints else np.zeros((len(x), 0, 3))
        res[~simulated] = x[~simulated, None, :]  # untouched particles keep their state exactly
        stop_wp = np.where(stop >= 0, np.searchsorted(motion.seg_end, np.maximum(stop, 0)), -1)
        t = lambda a, dt: torch.as_tensor(a, device=device, dtype=dt)  # noqa: E731
        return RolloutResult(t(res, dtype), t(simulated, torch.bool), t(stop_wp, torch.long))

    def rollout(self, states, motion) -> torch.Tensor:
        """Object SE(2) states after each waypoint when the box starts at rest at each particle ``states (P, 3)``
        and the robot executes ``motion``: a ``TouchObservation`` (the executed poke, replayed exactly as
        executed), a ``MotionPlan`` (``plan_poke``, ``plan_from_joints``) or a planned joint path
        ``q_plan (K+1, 7)``. Returns ``(P, K, 3)`` with the input's float dtype and device (float64 for numpy
        input). Particles the robot never comes near keep their state exactly; planned (guarded) motions freeze a
        particle once its contact force passes ``guard_force`` (see ``_engine``).
        """
        return self.rollout_detailed(states, motion).states

    def _as_motion(self, motion) -> MotionPlan:
        if isinstance(motion, TouchObservation):
            return motion.motion()
        if isinstance(motion, MotionPlan):
            return motion
        if isinstance(motion, (np.ndarray, torch.Tensor, list, tuple)):
            return self.plan_from_joints(motion)
        raise ValueError("motion must be a TouchObservation, MotionPlan or q_plan (K+1, 7), "
                         f"got {type(motion).__name__}")

    def grasp_success(self, states, grasp_state) -> torch.Tensor:
        """Whether the grasp primitive planned for ``grasp_state (3,)`` lifts the box when it is at each particle
        ``states (P, 3)``: ``(P,)`` bool on the input's device (App. D-d; the caller weights them).

        Simulates ``grasp_plan``'s primitive (from rest above the box, pads open; the transit to the pre-grasp
        pose, above every box, is not simulated) for the particles whose box the gripper's swept surface comes
        within ``rollout_margin + SWEEP_ALLOWANCE`` (3 cm) of; the others fail without simulation. Bound: the
        primitive's swept surface below the box top stays inside the cylinder of radius
        ``GRASP_GRIPPER.footprint_radius`` (0.076 m) around the grasp point, so every particle whose centre is
        farther than 0.076 + 0.090 (the box's bounding radius in xy) + 0.03 = 0.196 m from it fails unsimulated
        (the sweep test is tighter: it uses the box's rectangle and yaw). A guarded descent that hits the box
        (``grasp_guard_force``) is a failure, as in ``step``.
        """
        x, _, device = self._as_states(states)
        plan = self.grasp_plan(grasp_state)
        obj, simulated, _ = self._engine(x, plan, grasp=(int(plan.seg_end[0]), int(plan.seg_end[1])))
        ok = simulated & (obj[:, -1, 2] > self.spec.success_height)
        return torch.as_tensor(ok, device=device)


def _box_surface(half: np.ndarray, spacing: float) -> np.ndarray:
    """Grid points on the six faces of a box of half extents ``half (3,)`` centred at the origin: ``(M, 3)``."""
    axes = [np.linspace(-h, h, max(2, int(math.ceil(2 * h / spacing)) + 1)) for h in half]
    out = []
    for a in range(3):
        b, c = [i for i in range(3) if i != a]
        g = np.stack(np.meshgrid(axes[b], axes[c], indexing="ij"), -1).reshape(-1, 2)
        for sgn in (-1.0, 1.0):
            p = np.zeros((len(g), 3))
            p[:, a] = sgn * half[a]
            p[:, b] = g[:, 0]
            p[:, c] = g[:, 1]
            out.append(p)
    return np.unique(np.round(np.concatenate(out), 12), axis=0)


def make_grasp_env(name: str, seed: int = 0, **overrides) -> GraspEnv:
    """``GraspEnv`` of a registered grasp task; ``overrides`` replace ``GraspTaskSpec`` fields."""
    return GraspEnv(get_grasp_spec(name, **overrides), seed=seed)
