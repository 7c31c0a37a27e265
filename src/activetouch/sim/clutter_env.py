"""Dense-clutter environment of the visuo-tactile paper (Sec. II, III-A): look, declutter, touch.

A target object stands upright on the table inside a pile of 4-8 YCB clutter objects that were dropped onto and
around it (``reset``: a new pile per seed, real occlusion and support). The robot (the iiwa with the two-pad
gripper of the grasping scene) can take four actions, each executed in MuJoCo physics:

* :class:`ViewAction` (Sec. II-D-1): a depth image from a camera at ``position`` looking at ``look_at``, ray cast
  against the exact visual meshes (``sim.camera.PinholeCamera``). Segmentation comes from MuJoCo's geom ids
  (*simulated* segmentation, standing in for the paper's DeepLab network), optionally with label noise at mask
  boundaries. SIMPLIFICATION: the paper's camera rides on a second arm (a Panda); here it is a free-flying
  sensor restricted to ``spec.view_radius`` around the pile, and the iiwa parks out of view before each image.
* :class:`TouchAction` (II-D-2): a guarded straight touch of the closed gripper along a ray. The motion stops at
  the first contact between the gripper and any object; the contact points on the target are the tactile
  cloud (the paper's taxel positions). A contact with another object, or during the approach, is reported as
  a failed touch.
* :class:`PushAction` (II-B-1): straight push of fixed length with the closed gripper; contact with the pushed
  object is monitored and a loss of contact stops the push (the paper replans then).
* :class:`PickAction` (II-B-2): top-down grasp, lift and place outside the workspace; the grasp is verified by
  contact (both pads on the object) and aborted otherwise.

Arm motions are straight ee paths (IK per control period, gripper pointing down, as in ``grasp_env``) through a
safe height above the pile. Objects are free bodies, so touches, pushes and grasps may move anything.
"""
from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any

import mujoco
import numpy as np
import torch

from .camera import PinholeCamera
from .clutter_scene import GROUP_TRANSPARENT, build_clutter_scene, object_body_name
from .grasp_scene import ARM_JOINTS, GRASP_GRIPPER, PAD_JOINTS
from .grasp_tasks import control_substeps
from .robot import Q_NOMINAL, ArmIK, ee_state_from_pose, yaw_rotation
from .scene import GROUP_OBJECT_VISUAL, GROUP_ROBOT, GROUP_STATIC

__all__ = [
    "ClutterTaskSpec",
    "ClutterEnv",
    "ViewAction",
    "TouchAction",
    "PushAction",
    "PickAction",
    "StopAction",
    "ClutterObservation",
    "CLUTTER_POOL",
    "CLUTTER_GRIPPER",
    "PICK_CLEARANCE",
]

#: Clutter objects drawn per seed (packaged YCB meshes with convex decompositions).
CLUTTER_POOL = ("tomato_soup_can", "sugar_box", "potted_meat_can", "foam_brick", "cracker_box", "mug",
                "bleach_cleanser", "mustard_bottle", "drill")


#: A pick opens the pads to the object's width plus this (m), at most the gripper's opening: 1.5 cm per side.
PICK_CLEARANCE = 0.03

#: The grasping scene's gripper with a palm and wrist no wider (ee x) than the pads, so the pads' edges lead a
#: sideways touch or push (with the grasping gripper's 6 cm palm the palm's edge would touch tall objects first).
CLUTTER_GRIPPER = dataclasses.replace(GRASP_GRIPPER, palm_half=(0.018, 0.070, 0.015), adaptor_radius=0.018)


def _vec(x, n: int, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=float)
    if a.shape != (n,) or not np.isfinite(a).all():
        raise ValueError(f"{name} must be {n} finite numbers, got {np.asarray(x).tolist()!r}")
    return a


def _unit(x, name: str) -> np.ndarray:
    """``x`` as a finite unit 3-vector (within 1e-3), else a ValueError naming ``name``."""
    d = _vec(x, 3, name)
    if abs(np.linalg.norm(d) - 1.0) > 1e-3:
        raise ValueError(f"{name} must be a unit vector, got norm {np.linalg.norm(d):.4f}")
    return d


@dataclasses.dataclass(frozen=True)
class ViewAction:
    """Take a depth image from ``position (3,)`` looking at ``look_at (3,)`` (world, m)."""

    position: tuple
    look_at: tuple

    def __post_init__(self):
        p, t = _vec(self.position, 3, "ViewAction.position"), _vec(self.look_at, 3, "ViewAction.look_at")
        if np.linalg.norm(p - t) < 1e-6:
            raise ValueError("ViewAction.position and look_at coincide")


@dataclasses.dataclass(frozen=True)
class TouchAction:
    """Guarded touch: from ``start (3,)`` along the unit ``direction (3,)`` for at most ``max_length`` m."""

    start: tuple
    direction: tuple
    max_length: float = 0.15

    def __post_init__(self):
        _vec(self.start, 3, "TouchAction.start")
        _unit(self.direction, "TouchAction.direction")
        if not (0 < self.max_length <= 0.5):
            raise ValueError(f"TouchAction.max_length must be in (0, 0.5] m, got {self.max_length}")


@dataclasses.dataclass(frozen=True)
class PushAction:
    """Straight push of object ``label`` from ``start (3,)`` along the horizontal unit ``direction`` by ``length``."""

    label: int
    start: tuple
    direction: tuple
    length: float = 0.10

    def __post_init__(self):
        _vec(self.start, 3, "PushAction.start")
        _unit(self.direction, "PushAction.direction")
        if not (0 < self.length <= 0.4):
            raise ValueError(f"PushAction.length must be in (0, 0.4] m, got {self.length}")


@dataclasses.dataclass(frozen=True)
class PickAction:
    """Top-down grasp of object ``label``: the pads' tips go to ``position (3,)``, closing along the horizontal
    direction at angle ``closing_angle`` (rad, world x-y), opened to ``width`` + clearance first."""

    label: int
    position: tuple
    closing_angle: float
    width: float

    def __post_init__(self):
        _vec(self.position, 3, "PickAction.position")
        if not math.isfinite(self.closing_angle):
            raise ValueError("PickAction.closing_angle must be finite")
        if not (0 < self.width < 1):
            raise ValueError(f"PickAction.width must be in (0, 1) m, got {self.width}")


@dataclasses.dataclass(frozen=True)
class StopAction:
    """The method declares its estimate final: the episode ends (``terminated``)."""

    reason: str = ""


@dataclasses.dataclass
class ClutterObservation:
    """What one action returned.

    Attributes:
        kind: ``"view" | "touch" | "push" | "pick" | "reset"``.
        points: ``(N, 3)`` world points on the target: its segmented depth points (view) or the tactile contact
            points (touch); empty otherwise.
        seg: ``(H, W)`` int object label per pixel, ``-1`` = table, robot or nothing (view only).
        cloud: ``(H, W, 3)`` world hit points, NaN where a ray hit nothing (view only).
        camera: the ``PinholeCamera`` of a view.
        in_contact: a touch ended on the target.
        success: the push / pick reached its goal; a touch that touched the target.
        contact_label: the object a touch or push first touched (``-1``: none).
    """

    kind: str
    points: np.ndarray
    seg: np.ndarray | None = None
    cloud: np.ndarray | None = None
    camera: PinholeCamera | None = None
    in_contact: bool = False
    success: bool = False
    contact_label: int = -1


@dataclasses.dataclass(frozen=True)
class ClutterTaskSpec:
    """One clutter task (defaults: Sec. III's setting in our simulation).

    Attributes:
        target: the target object (object 0). ``transparent_target``: the camera cannot see it (Sec. III-A's
            wineglass / transparent box).
        clutter_pool, num_clutter: clutter objects drawn per seed without replacement (the target excluded),
            ``num_clutter = (min, max)`` inclusive.
        pile_centre, pile_radius: the target stands at the centre (+-2 cm); clutter lands within the radius.
        view_radius, min_view_elevation_deg: the camera stays on the hemisphere of this radius around the target
            (Eq. 20-21), above this elevation: the reachable workspace of the paper's camera arm.
        camera_*: the depth camera (ray cast).
        seg_boundary_noise: probability that a pixel on a mask boundary takes its neighbour's label (the
            segmentation network's boundary errors).
        depth_noise_std: Gaussian noise (m) along each ray of the depth image (the Azure Kinect's random depth error
            is about 1-3 mm at 0.5-1 m).
        prior_sigma_t, prior_sigma_yaw_deg: the task's prior over the target pose (the coarse "approximate
            centroid" detection the paper starts from): the true pose perturbed by these.
        camera_calibration_error: ``(m, deg)``: a fixed rigid error per scene between where the robot believes the
            camera's points are and where they are (the camera arm's base or hand-eye calibration; touches are
            measured in the touching arm's frame and have none): every view's points are turned by ``deg`` about a
            random axis through the pile centre and shifted by ``m`` in a random direction, both drawn per seed.
            ``(0, 0)`` (default): a perfectly calibrated camera.
        max_actions: episode budget T.
        control_dt, timestep, max_ee_step, touch_step: arm control period, physics step, ee speed per period
            (0.2 m/s transit, 0.05 m/s during guarded touches).
    """

    name: str
    target: str = "mustard_bottle"
    transparent_target: bool = False
    clutter_pool: tuple[str, ...] = CLUTTER_POOL
    num_clutter: tuple[int, int] = (4, 8)
    pile_centre: tuple[float, float] = (0.32, 0.0)
    pile_radius: float = 0.11
    view_radius: float = 0.55
    min_view_elevation_deg: float = 25.0
    camera_width: int = 96
    camera_height: int = 72
    camera_fov_y_deg: float = 50.0
    camera_max_depth: float = 1.5
    seg_boundary_noise: float = 0.2
    depth_noise_std: float = 0.002
    prior_sigma_t: float = 0.02
    prior_sigma_yaw_deg: float = 20.0
    camera_calibration_error: tuple[float, float] = (0.0, 0.0)
    max_actions: int = 40  # covers the planner's own caps: 8 declutter actions + their 8 views, 9 views, 12 touches
    control_dt: float = 0.02
    timestep: float = 0.002
    max_ee_step: float = 0.004
    touch_step: float = 0.001
    settle_time: float = 0.4
    dropoff: tuple[float, float] = (0.10, 0.50)
    park_ee: tuple[float, float, float, float] = (0.0, -0.45, 0.40, 0.0)
    description: str = ""

    def __post_init__(self):
        lo, hi = self.num_clutter
        if not (0 <= lo <= hi):
            raise ValueError(f"num_clutter must be (min, max) with 0 <= min <= max, got {self.num_clutter}")
        pool = [o for o in self.clutter_pool if o != self.target]
        if hi > len(pool):
            raise ValueError(f"num_clutter max {hi} exceeds the {len(pool)} clutter objects of the pool")
        if not (self.depth_noise_std >= 0.0):
            raise ValueError(f"depth_noise_std must be >= 0, got {self.depth_noise_std}")
        err = tuple(self.camera_calibration_error)
        if len(err) != 2 or not all(isinstance(v, (int, float)) and math.isfinite(v) and v >= 0 for v in err):
            raise ValueError(f"camera_calibration_error must be (metres >= 0, degrees >= 0), got "
                             f"{self.camera_calibration_error!r}")
        if not (0.0 <= self.seg_boundary_noise <= 1.0):
            raise ValueError(f"seg_boundary_noise must be in [0, 1], got {self.seg_boundary_noise}")
        if self.max_actions < 1:
            raise ValueError("max_actions must be >= 1")
        control_substeps(self.control_dt, self.timestep)

    @property
    def substeps(self) -> int:
        return control_substeps(self.control_dt, self.timestep)

    @property
    def max_steps(self) -> int:
        return self.max_actions


@functools.lru_cache(maxsize=None)
def _vertices(name: str) -> np.ndarray:
    """Object-frame mesh vertices ``(V, 3)`` of a packaged object (read once per process)."""
    from activetouch import objects

    v = np.asarray(objects.load(name).mesh.vertices, dtype=np.float64)
    v.setflags(write=False)
    return v


@functools.lru_cache(maxsize=64)
def _scene(names: tuple[str, ...], transparent: bool, gripper, timestep: float) -> mujoco.MjModel:
    """Compiled clutter scenes, shared by every environment of the process (each has its own ``MjData``)."""
    return build_clutter_scene(names, transparent, gripper, timestep=timestep)


def _pose_of(xpos: np.ndarray, xmat: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.asarray(xmat).reshape(3, 3)
    T[:3, 3] = xpos
    return T


class ClutterEnv:
    """The dense-clutter task (module docstring). ``reset(seed)`` builds a pile; ``step(action)`` returns
    ``(obs, reward, terminated, truncated, info)`` with ``info["true_pose"]`` the target's pose ``(4, 4)``."""

    def __init__(self, spec: ClutterTaskSpec, seed: int = 0):
        from activetouch import objects

        self.spec = spec
        self.seed = int(seed)
        self.object = objects.load(spec.target)
        self.gripper = CLUTTER_GRIPPER
        self.model: mujoco.MjModel | None = None
        self.data: mujoco.MjData | None = None
        self.names: tuple[str, ...] = ()
        self._reset_done = False
        self._terminated = False
        self._n_actions = 0
        self._parked = False
        self._motion_dir = np.array([0.0, 0.0, -1.0])  # the direction of the last straight ee motion
        self._calibration = None  # the scene's camera calibration error (drawn by reset)

    @property
    def max_steps(self) -> int:
        return self.spec.max_actions

    # ------------------------------------------------------------------ model
    def _bind(self, names: tuple[str, ...]) -> None:
        m = _scene(names, self.spec.transparent_target, self.gripper, self.spec.timestep)
        self.model, self.names = m, names
        self.data = mujoco.MjData(m)
        jid = lambda n: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n)  # noqa: E731
        self._qadr = m.jnt_qposadr[[jid(j) for j in ARM_JOINTS]].copy()
        self._vadr = m.jnt_dofadr[[jid(j) for j in ARM_JOINTS]].copy()
        self._pad_qadr = m.jnt_qposadr[[jid(j) for j in PAD_JOINTS]].copy()
        self._site = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, "ee")
        self.ik = ArmIK(m, self._site, self._qadr, self._vadr)
        self._obj_body = np.array([mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, object_body_name(i))
                                   for i in range(len(names))])
        self._obj_qadr = np.array([m.jnt_qposadr[jid(f"obj_{i}_free")] for i in range(len(names))])
        self._obj_vadr = np.array([m.jnt_dofadr[jid(f"obj_{i}_free")] for i in range(len(names))])
        body_label = np.full(m.nbody, -1)
        body_label[self._obj_body] = np.arange(len(names))
        #: object label of every geom (-1: not an object)
        self.geom_label = body_label[m.geom_bodyid]
        base = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "iiwa_base")
        robot_bodies = {b for b in range(m.nbody) if self._in_subtree(b, base)}
        self._robot_geom = np.array([m.geom_bodyid[g] in robot_bodies and m.geom_contype[g] != 0
                                     for g in range(m.ngeom)])
        gid = lambda n: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, n)  # noqa: E731
        self._pad_geoms = (gid("pad_0"), gid("pad_1"))
        self._target_ctrl = np.zeros(m.nu)
        self._ray_group = np.zeros(6, dtype=np.uint8)
        for g in (GROUP_STATIC, GROUP_ROBOT, GROUP_OBJECT_VISUAL):
            self._ray_group[g] = 1
        assert GROUP_TRANSPARENT not in (GROUP_STATIC, GROUP_ROBOT, GROUP_OBJECT_VISUAL)

    def _in_subtree(self, b: int, root: int) -> bool:
        m = self.model
        while b > 0:
            if b == root:
                return True
            b = int(m.body_parentid[b])
        return b == root

    # ------------------------------------------------------------------ state
    def object_poses(self) -> np.ndarray:
        """``(n, 4, 4)`` object -> world poses of every object (ground truth)."""
        d = self.data
        return np.stack([_pose_of(d.xpos[b], d.xmat[b]) for b in self._obj_body])

    def true_pose(self) -> np.ndarray:
        return self.object_poses()[0]

    def current_q(self) -> np.ndarray:
        return self.data.qpos[self._qadr].copy()

    def ee_state(self) -> np.ndarray:
        """ee ``[x, y, z, yaw] (4,)``."""
        d = self.data
        return ee_state_from_pose(d.site_xpos[self._site].copy(), d.site_xmat[self._site].reshape(3, 3))

    def object_top(self, label: int) -> float:
        """Highest point (m, world z) of object ``label``'s mesh."""
        T = self.object_poses()[label]
        return float((_vertices(self.names[label]) @ T[2, :3] + T[2, 3]).max())

    def _info(self, **extra) -> dict[str, Any]:
        T = self.true_pose()
        info = {"true_pose": torch.as_tensor(T, dtype=torch.float32), "object_poses": self.object_poses(),
                "object_names": self.names, "num_actions": self._n_actions,
                "pile_centre": np.asarray(self.spec.pile_centre, float)}
        info.update(extra)
        return info

    # ------------------------------------------------------------------ reset: drop a pile
    def _draw_names(self, rng: np.random.Generator) -> tuple[str, ...]:
        s = self.spec
        pool = [o for o in s.clutter_pool if o != s.target]
        k = int(rng.integers(s.num_clutter[0], s.num_clutter[1] + 1))
        pick = rng.choice(len(pool), size=k, replace=False)
        return (s.target, *[pool[i] for i in sorted(pick)])

    def _place(self, i: int, xy: np.ndarray, R: np.ndarray, z_bottom: float) -> None:
        """Put object ``i`` with rotation ``R`` so its lowest point is at ``z_bottom`` above ``xy``."""
        low = float((_vertices(self.names[i]) @ R[2]).min())
        q = np.zeros(4)
        mujoco.mju_mat2Quat(q, R.reshape(-1))
        a = self._obj_qadr[i]
        self.data.qpos[a:a + 3] = (xy[0], xy[1], z_bottom - low)
        self.data.qpos[a + 3:a + 7] = q
        self.data.qvel[self._obj_vadr[i]:self._obj_vadr[i] + 6] = 0.0

    def _simulate(self, seconds: float) -> None:
        for _ in range(int(round(seconds / self.spec.timestep))):
            self.data.ctrl[:] = self._target_ctrl
            mujoco.mj_step(self.model, self.data)

    def _scene_top(self, upto: int) -> float:
        return max([0.0] + [self.object_top(j) for j in range(upto)])

    def reset(self, seed: int | None = None) -> tuple[ClutterObservation, dict[str, Any]]:
        """Drop a new pile for ``seed``: the target upright at the pile centre, then each clutter object from
        above the pile at a random place and orientation (half of them on their side), each falling onto what
        is already there; re-drawn (deterministically) when the target ends up tipped over. The arm parks."""
        seed = self.seed if seed is None else int(seed)
        s = self.spec
        for attempt in range(20):
            rng = np.random.default_rng([seed, 11, attempt])
            self._bind(self._draw_names(rng))
            m, d = self.model, self.data
            mujoco.mj_resetData(m, d)
            q = self.ik.solve(Q_NOMINAL.copy(), np.asarray(s.park_ee[:3]), yaw_rotation(s.park_ee[3]), iterations=200)
            d.qpos[self._qadr] = q
            self._target_ctrl = np.concatenate([q, [0.0, 0.0]])
            for i in range(len(self.names)):  # everything far away first
                self._place(i, np.array([-0.4, -0.6 + 0.25 * i]), np.eye(3), 2.0 + 0.4 * i)
            mujoco.mj_forward(m, d)
            c = np.asarray(s.pile_centre, float)
            yaw = rng.uniform(-math.pi, math.pi)
            self._place(0, c + rng.uniform(-0.02, 0.02, 2), yaw_rotation(yaw), 0.0005)
            mujoco.mj_forward(m, d)
            self._simulate(0.1)
            for i in range(1, len(self.names)):
                r = rng.uniform(0.05, s.pile_radius)
                phi = rng.uniform(-math.pi, math.pi)
                R = yaw_rotation(rng.uniform(-math.pi, math.pi))
                if rng.random() < 0.5:  # on its side
                    ax = rng.integers(2)
                    t = math.pi / 2
                    Rs = (np.array([[1, 0, 0], [0, math.cos(t), -math.sin(t)], [0, math.sin(t), math.cos(t)]])
                          if ax == 0 else np.array([[math.cos(t), 0, math.sin(t)], [0, 1, 0],
                                                    [-math.sin(t), 0, math.cos(t)]]))
                    R = R @ Rs
                self._place(i, c + r * np.array([math.cos(phi), math.sin(phi)]), R, self._scene_top(i) + 0.02)
                mujoco.mj_forward(m, d)
                self._simulate(0.35)
            self._simulate(1.0)
            T = self.true_pose()
            tilt = math.degrees(math.acos(float(np.clip(T[2, 2], -1.0, 1.0))))
            off = float(np.linalg.norm(T[:2, 3] - c))
            if tilt < 15.0 and off < 0.05:
                break
        self._noise = np.random.default_rng([seed, 12])
        self._calibration = self._draw_calibration(np.random.default_rng([seed, 13]))
        self._n_actions = 0
        self._parked = True
        self._reset_done = True
        self._terminated = False
        self.reset_attempts = attempt + 1
        return ClutterObservation("reset", np.zeros((0, 3))), self._info()

    # ------------------------------------------------------------------ camera
    def _draw_calibration(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray] | None:
        """The scene's camera calibration error (``ClutterTaskSpec.camera_calibration_error``): ``(R (3, 3),
        t (3,))`` applied as ``p -> R (p - c) + c + t`` about the pile centre ``c`` on the table; None when 0."""
        metres, deg = self.spec.camera_calibration_error
        if metres == 0 and deg == 0:
            return None
        from activetouch.geometry import axis_angle_to_matrix

        axis, shift = rng.normal(size=3), rng.normal(size=3)
        w = torch.as_tensor(axis / np.linalg.norm(axis) * math.radians(deg), dtype=torch.float64)
        return axis_angle_to_matrix(w).numpy(), metres * shift / np.linalg.norm(shift)

    def view_camera(self, position, look_at) -> PinholeCamera:
        s = self.spec
        return PinholeCamera(pos=tuple(map(float, position)), target=tuple(map(float, look_at)),
                             width=s.camera_width, height=s.camera_height, fov_y_deg=s.camera_fov_y_deg,
                             max_depth=s.camera_max_depth)

    def _cast(self, cam: PinholeCamera, group: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = len(dirs)
        geomid = np.full(n, -1, dtype=np.int32)
        dist = np.full(n, -1.0)
        mujoco.mj_multiRay(self.model, self.data, np.asarray(cam.pos, dtype=np.float64), dirs.reshape(-1).copy(),
                           group, 1, -1, geomid, dist, None, n, cam.max_depth)
        hit = (dist >= 0) & (geomid >= 0)
        return np.where(hit, dist, np.inf), np.where(hit, geomid, -1)

    def render(self, cam: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
        """Ray-cast ``cam``: ``seg (H, W)`` object labels (-1: not an object) and ``cloud (H, W, 3)`` world hits
        (NaN: no hit).

        A transparent target is *segmented* (a segmentation network sees the glass in the colour image) but has no
        depth: its pixels' depth is that of whatever lies behind it, as a depth camera reports through glass.
        """
        dirs = cam.ray_directions()
        depth, geom = self._cast(cam, self._ray_group, dirs)
        seg = np.where(geom >= 0, self.geom_label[np.maximum(geom, 0)], -1)
        if self.spec.transparent_target:
            group = self._ray_group.copy()
            group[GROUP_TRANSPARENT] = 1
            _, geom_rgb = self._cast(cam, group, dirs)
            seg = np.where(geom_rgb >= 0, self.geom_label[np.maximum(geom_rgb, 0)], -1)
        hit = np.isfinite(depth)
        if self.spec.depth_noise_std > 0:
            depth = depth + self._noise.normal(0.0, self.spec.depth_noise_std, depth.shape)
        cloud = np.where(hit[:, None], np.asarray(cam.pos) + dirs * np.where(hit, depth, 0.0)[:, None], np.nan)
        if self._calibration is not None:  # where the robot believes the points are
            R, t = self._calibration
            c = np.array([*self.spec.pile_centre, 0.0])
            cloud = (cloud - c) @ R.T + c + t
        H, W = cam.height, cam.width
        seg = seg.reshape(H, W)
        if self.spec.seg_boundary_noise > 0:
            seg = self._boundary_noise(seg)
        return seg, cloud.reshape(H, W, 3)

    def _boundary_noise(self, seg: np.ndarray) -> np.ndarray:
        """Pixels whose 4-neighbour has another label take that label with probability ``seg_boundary_noise``."""
        out = seg.copy()
        p = self.spec.seg_boundary_noise
        for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
            nb = np.roll(seg, (dy, dx), axis=(0, 1))
            flip = (nb != seg) & (self._noise.random(seg.shape) < p / 4)
            out[flip] = nb[flip]
        return out

    # ------------------------------------------------------------------ arm control
    def _contacts(self) -> list[tuple[int, int, np.ndarray]]:
        """Robot-object contacts now: ``(object label, robot geom, position (3,))``."""
        d = self.data
        out = []
        for i in range(d.ncon):
            c = d.contact[i]
            g1, g2 = int(c.geom1), int(c.geom2)
            if self._robot_geom[g1] and self.geom_label[g2] >= 0:
                out.append((int(self.geom_label[g2]), g1, c.pos.copy()))
            elif self._robot_geom[g2] and self.geom_label[g1] >= 0:
                out.append((int(self.geom_label[g1]), g2, c.pos.copy()))
        return out

    def _first_contact_guard(self, first: list, allowed=()):
        """A motion guard: true on any robot-object contact with an object not in ``allowed``; the contacts of the
        first such moment are appended to ``first`` (once)."""
        def guard() -> bool:
            cs = [c for c in self._contacts() if c[0] not in allowed]
            if cs and not first:
                first.extend(cs)
            return bool(cs)

        return guard

    def _period(self, q: np.ndarray, pad: float, guard=None) -> bool:
        """One control period toward arm joints ``q (7,)`` and pad slide ``pad`` (linear ramp of the targets);
        ``guard()`` is checked after every physics step and stops the period (returns True) when true."""
        s = self.spec
        goal = np.concatenate([q, [pad, pad]])
        prev = self._target_ctrl
        for j in range(1, s.substeps + 1):
            self.data.ctrl[:] = prev + (j / s.substeps) * (goal - prev)
            mujoco.mj_step(self.model, self.data)
            if guard is not None and guard():
                self._target_ctrl = np.concatenate([self.current_q(), [pad, pad]])
                return True
        self._target_ctrl = goal
        return False

    def _hold(self, periods: int, pad: float | None = None) -> None:
        q = self._target_ctrl[:7].copy()
        p = self._target_ctrl[7] if pad is None else pad
        for _ in range(periods):
            self._period(q, p)

    def _line(self, goal, pad: float, step: float, guard=None) -> bool:
        """Straight ee path from here to ``goal [x, y, z, yaw]``; True when ``guard`` stopped it."""
        self._parked = False
        ee = self.ee_state()
        goal = np.asarray(goal, float)
        dpos = goal[:3] - ee[:3]
        if np.linalg.norm(dpos) > 1e-9:
            self._motion_dir = dpos / np.linalg.norm(dpos)
        dyaw = float((goal[3] - ee[3] + math.pi) % (2 * math.pi) - math.pi)
        n = max(1, int(math.ceil(max(np.linalg.norm(dpos) / step, abs(dyaw) / 0.05))))
        q = self.current_q()
        for j in range(1, n + 1):
            a = j / n
            q = self.ik.solve(q, ee[:3] + a * dpos, yaw_rotation(ee[3] + a * dyaw), iterations=6)
            if self._period(q, pad, guard):
                return True
        return False

    def _safe_height(self) -> float:
        return min(0.42, self._scene_top(len(self.names)) + 0.08)

    def _transit(self, goal, pad: float, guard=None) -> bool:
        """Up to the safe height, across, and down to ``goal [x, y, z, yaw]``; True when ``guard`` stopped it."""
        s = self.spec
        z = max(self._safe_height(), float(goal[2]))
        ee = self.ee_state()
        for wp in ([ee[0], ee[1], max(z, ee[2]), ee[3]], [goal[0], goal[1], max(z, ee[2]), goal[3]], goal):
            if self._line(wp, pad, s.max_ee_step, guard):
                return True
        for _ in range(5):  # settle on the goal (the position servos lag a moving target by ~1 cm)
            if self._period(self._target_ctrl[:7].copy(), pad, guard):
                return True
        return False

    def _park(self) -> None:
        if not self._parked:
            self._transit(np.asarray(self.spec.park_ee), float(self._target_ctrl[7]))
            self._hold(10)
            self._simulate(self.spec.settle_time)
            self._parked = True

    def _reachable_yaw(self, pos: np.ndarray, yaw: float) -> float:
        """The gripper is symmetric under a half turn: of ``yaw`` and ``yaw + pi``, the one the arm reaches at ``pos``
        (IK from the current joints; the smaller rotation error, then the smaller turn from the current yaw). Without
        this the wrist's last joint (limits +-3.05 rad) left yaws 1-2 rad short, so a touch led with the palm's 14 cm
        side instead of its 3.6 cm side and the palm landed on the target."""
        cur = float(self.ee_state()[3])
        best = None
        for c in (yaw, yaw + math.pi):
            c = (c + math.pi) % (2 * math.pi) - math.pi
            R = yaw_rotation(c)
            q = self.ik.solve(self.current_q(), np.asarray(pos, float), R, iterations=60)
            err = self.ik.error(q, np.asarray(pos, float), R)[1]
            key = (round(err, 2), abs((c - cur + math.pi) % (2 * math.pi) - math.pi))
            if best is None or key < best[0]:
                best = (key, c)
        return best[1]

    @staticmethod
    def _leading_yaw(direction: np.ndarray, current: float) -> float:
        """ee yaw for a horizontal motion along ``direction``: the ee x-axis along it, so the pads' narrow edges
        (and the palm's narrow side, 1 cm beyond them) lead; along the ee y-axis the palm would stick out 6 cm
        ahead of the closed pads."""
        h = direction[:2]
        if np.linalg.norm(h) < 1e-6:
            return current
        return math.atan2(h[1], h[0])

    # ------------------------------------------------------------------ actions
    def step(self, action):
        if not self._reset_done:
            raise RuntimeError("call reset() before step()")
        if self._terminated:
            raise RuntimeError("the episode has ended (StopAction); call reset()")
        if isinstance(action, StopAction):
            self._terminated = True
            return (ClutterObservation("stop", np.zeros((0, 3))), 0.0, True, False,
                    self._info(action="stop", action_success=True, stop_reason=action.reason))
        if self._n_actions >= self.spec.max_actions:
            raise RuntimeError(f"max_actions = {self.spec.max_actions} actions made; call reset()")
        self._n_actions += 1
        truncated = self._n_actions >= self.spec.max_actions
        if isinstance(action, ViewAction):
            obs = self._view(action)
        elif isinstance(action, TouchAction):
            obs = self._touch(action)
        elif isinstance(action, PushAction):
            obs = self._push(action)
        elif isinstance(action, PickAction):
            obs = self._pick(action)
        else:
            raise ValueError(f"action must be a ViewAction, TouchAction, PushAction or PickAction, "
                             f"got {type(action).__name__}")
        return obs, 0.0, False, truncated, self._info(action=obs.kind, action_success=obs.success)

    def _view(self, a: ViewAction) -> ClutterObservation:
        self._park()
        cam = self.view_camera(a.position, a.look_at)
        seg, cloud = self.render(cam)
        pts = cloud[seg == 0]
        return ClutterObservation("view", pts[np.isfinite(pts).all(1)], seg=seg, cloud=cloud, camera=cam,
                                  success=len(pts) > 0)

    def _touch(self, a: TouchAction) -> ClutterObservation:
        d = np.asarray(a.direction, float)
        start = np.asarray(a.start, float)
        start[2] = max(start[2], 0.012)
        self._motion_dir = d
        yaw = self._reachable_yaw(start, self._leading_yaw(d, float(self.ee_state()[3])))
        first: list = []
        guard = self._first_contact_guard(first)
        aborted = self._transit(np.array([*start, yaw]), 0.0, guard=guard)
        touched = False
        if not aborted:
            end = start + a.max_length * d
            end[2] = max(end[2], 0.012)
            touched = self._line(np.array([*end, yaw]), 0.0, self.spec.touch_step, guard=guard)
            self._hold(2)
        label = first[0][0] if first else -1
        pts = np.array([p for (lab, _, p) in first if lab == 0]).reshape(-1, 3)
        # a contact with the target on the way to the start point is a touch too (the tactile points are real)
        touched = touched or (aborted and label == 0)
        # retreat the way the gripper came, slowly while it may still touch
        back_dir = self._motion_dir
        for dist, step in ((0.01, self.spec.touch_step), (0.03, self.spec.max_ee_step)):
            back = self.ee_state()
            back[:3] = back[:3] - dist * back_dir
            back[2] = max(back[2], 0.012)
            self._line(back, 0.0, step)
        ok = touched and label == 0 and len(pts) > 0
        return ClutterObservation("touch", pts if ok else np.zeros((0, 3)), in_contact=ok, success=ok,
                                  contact_label=label)

    def _push(self, a: PushAction) -> ClutterObservation:
        s = self.spec
        if not 0 < a.label < len(self.names):
            raise ValueError(f"PushAction.label must name a clutter object 1..{len(self.names) - 1}, got {a.label}")
        d = np.asarray(a.direction, float)
        start = np.asarray(a.start, float)
        start[2] = min(max(start[2], 0.015), max(0.015, self.object_top(a.label) - 0.01))
        yaw = self._reachable_yaw(start, self._leading_yaw(d, float(self.ee_state()[3])))
        before = self.object_poses()
        aborted = self._transit(np.array([*start, yaw]), 0.0, guard=lambda: bool(self._contacts()))
        touched = False
        lost = 0
        if not aborted:
            end = start + a.length * d
            n = max(1, int(math.ceil(a.length / s.max_ee_step)))
            q = self.current_q()
            for j in range(1, n + 1):
                p = start + (j / n) * (end - start)
                q = self.ik.solve(q, p, yaw_rotation(yaw), iterations=6)
                self._period(q, 0.0)
                on = any(lab == a.label for lab, _, _ in self._contacts())
                touched |= on
                lost = 0 if on else lost + (1 if touched else 0)
                if lost >= 8:  # contact lost for 8 periods after it was made: stop and replan (Sec. III-B)
                    break
        self._line(self.ee_state() + np.array([0, 0, 0.05, 0]), 0.0, s.max_ee_step)
        self._simulate(s.settle_time)
        after = self.object_poses()
        moved = float(np.linalg.norm(after[a.label, :2, 3] - before[a.label, :2, 3]))
        gap0 = float(np.linalg.norm(before[a.label, :2, 3] - before[0, :2, 3]))
        gap1 = float(np.linalg.norm(after[a.label, :2, 3] - after[0, :2, 3]))
        ok = (not aborted) and touched and moved > 0.02 and gap1 > gap0
        return ClutterObservation("push", np.zeros((0, 3)), success=ok, contact_label=a.label if touched else -1)

    def _pick(self, a: PickAction) -> ClutterObservation:
        s = self.spec
        if not 0 < a.label < len(self.names):
            raise ValueError(f"PickAction.label must name a clutter object 1..{len(self.names) - 1}, got {a.label}")
        yaw = a.closing_angle - math.pi / 2  # the pads close along the ee y-axis
        yaw = (yaw + math.pi / 2) % math.pi - math.pi / 2  # symmetric gripper
        open_ = min(self.gripper.max_opening, a.width + PICK_CLEARANCE) / 2
        p = np.asarray(a.position, float)
        z_top = self.object_top(a.label)
        z_grasp = max(0.012, min(p[2], z_top - 0.02))
        yaw = self._reachable_yaw(np.array([p[0], p[1], z_grasp]), yaw)
        pre = np.array([p[0], p[1], z_top + 0.05, yaw])
        # open while in transit, guarded descent onto the grasp height
        self._hold(10, open_)
        first: list = []
        aborted = self._transit(pre, open_, guard=self._first_contact_guard(first))
        where = "approach"
        if not aborted:
            where = "descent"
            aborted = self._line(np.array([p[0], p[1], z_grasp, yaw]), open_, s.max_ee_step,
                                 guard=self._first_contact_guard(first, allowed=(a.label,)))
        grasped = False
        self.last_pick_failure = ""
        if aborted:
            names = sorted({(int(lab), self.model.geom(int(g)).name) for lab, g, _ in first})
            self.last_pick_failure = f"aborted in the {where}: contacts {names}"
        if not aborted:
            self._hold(int(round(0.6 / s.control_dt)), 0.0)  # close
            on = {g for lab, g, _ in self._contacts() if lab == a.label}
            grasped = all(g in on for g in self._pad_geoms)  # contact-based grasp check
            if not grasped:
                self.last_pick_failure = f"pads in contact after closing: {sorted(on)} (pads {self._pad_geoms})"
        if grasped:
            z_lift = self._safe_height() + 0.05
            self._line(np.array([p[0], p[1], z_lift, yaw]), 0.0, s.max_ee_step)
            self._line(np.array([*s.dropoff, z_lift, yaw]), 0.0, s.max_ee_step)
            self._line(np.array([*s.dropoff, 0.12 + (z_top - z_grasp), yaw]), 0.0, s.max_ee_step)
            self._hold(15, open_)
        else:
            self._hold(10, open_)
        self._line(self.ee_state() + np.array([0, 0, 0.08, 0]), open_, s.max_ee_step)
        self._hold(5, 0.0)
        self._simulate(s.settle_time)
        xy = self.object_poses()[a.label, :2, 3]
        removed = float(np.linalg.norm(xy - np.asarray(s.pile_centre))) > s.pile_radius + 0.12
        return ClutterObservation("pick", np.zeros((0, 3)), success=bool(grasped and removed),
                                  contact_label=a.label if grasped else -1)

    def close(self):
        pass

    # ------------------------------------------------------------------ helpers for planners
    def isolated(self, clearance: float = 0.02) -> bool:
        """Ground truth (tests, metrics): no other object within ``clearance`` of the target's convex parts."""
        m, d = self.model, self.data
        mujoco.mj_forward(m, d)
        for i in range(d.ncon):
            c = d.contact[i]
            l1, l2 = self.geom_label[int(c.geom1)], self.geom_label[int(c.geom2)]
            if (l1 == 0 and l2 > 0) or (l2 == 0 and l1 > 0):
                return False
        return True
