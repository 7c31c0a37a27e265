"""The nine simulated RUMI tasks (section V-B, Tables I and III, Figs. 10 and 11) and their registry.

World frame: table top at z = 0, workspace W = [0, 0.8] x [-0.4, 0.4] (x [0, 0.2] for 3D actions),
robot base at ``robot.BASE_POS`` = (-0.25, 0, 0), behind the workspace (Fig. 7). At the working
height the arm reaches roughly 0.16 m < x < 0.55 m on the centre line, so the far part of the
workspace is out of reach (see ``docs/tasks.md`` and the reachability map).

Start poses (fixed; pictures in ``docs/img/``):
- mug-0/1/2: planar actions, SE(2). The mug stands near the far edge of reach with its handle
  (object +x) pointing away from the robot and away from the camera, which sees the mug's front
  from near the robot base: the handle is hidden and out of reach.
- drill-0/1/2: 3D actions, SE(2). The camera looks at the left (+y) near part of the shelf; the
  drill lies outside its view.
- box-0/1/2: 3D actions, SE(3). The cracker box lies on its back / stands upright / lies on its
  side, outside the camera's view; free points on the floor are added to the first observation.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from .camera import PinholeCamera

__all__ = ["TaskSpec", "TASKS", "registered", "get_spec", "MUG_CAMERA", "OCCLUDED_CAMERA"]

#: Camera of the mug tasks: low, beside the robot base, looking along +x at the mug's front.
MUG_CAMERA = PinholeCamera(pos=(0.0, -0.1, 0.14), target=(0.45, 0.05, 0.03), width=80, height=60, fov_y_deg=45.0)
#: Camera of the drill and box tasks: it looks at the left near corner of the shelf, where the
#: object is not ("placing the camera at an angle such that it cannot directly observe the object").
OCCLUDED_CAMERA = PinholeCamera(pos=(0.05, 0.42, 0.45), target=(0.22, 0.28, 0.0), width=80, height=60,
                                fov_y_deg=45.0)


@dataclasses.dataclass(frozen=True)
class TaskSpec:
    """Everything that defines one task. All lengths in metres, angles in radians.

    Attributes:
        action_space: ``"planar"`` (u = [dx, dy, dyaw]) or ``"3d"`` (u = [dx, dy, dz, dyaw]).
        se2: pose search space SE(2) (True) or SE(3).
        workspace_lower/upper: ``(3,)`` workspace box W (planar: z range collapses to ``ee_height``).
        r_w: workspace grid resolution (Table I).
        nll_threshold: success threshold (Table III).
        ee_height: tip height of the gripper for planar actions.
        start_xy, start_yaw: object start position and yaw (world).
        start_rest_rpy: roll, pitch applied before the yaw to choose the resting face (box); the
            object is placed so its lowest point touches the table.
        ee_start: ``[x, y, z, yaw]`` of the gripper at reset.
        ee_lower/ee_upper: ``(4,)`` bounds the commanded ``[x, y, z, yaw]`` is clipped to.
        prior_kind: ``"mug-centre"`` (centre estimated from the first camera surface points, uniform
            yaw) or ``"gaussian"`` (``prior_center`` + N(0, prior_sigma^2) in x, y, uniform yaw).
        prior_center: nominal object position for the gaussian prior (the start position).
        floor_free_points: add free points just below the table top to the first observation.
        floor_free_depth: their depth below z = 0.
        belief_defaults: ``((field, value), ...)`` BeliefConfig settings this task runs with unless the user
            overrides them (``--belief``): the drill and box tasks turn on the contact-placed prior proposals
            (``reinvigorate``, beyond the paper, see :mod:`activetouch.belief.reinvigorate`).
    """

    name: str
    object_name: str
    action_space: str
    se2: bool
    r_w: float
    nll_threshold: float
    start_xy: tuple[float, float]
    start_yaw: float
    camera: PinholeCamera
    prior_kind: str
    ee_start: tuple[float, float, float, float]
    start_rest_rpy: tuple[float, float] = (0.0, 0.0)
    workspace_lower: tuple[float, float, float] = (0.0, -0.4, 0.0)
    workspace_upper: tuple[float, float, float] = (0.8, 0.4, 0.2)
    max_steps: int = 40
    ee_height: float = 0.02
    ee_lower: tuple[float, float, float, float] = (0.0, -0.4, 0.01, -2.5)
    ee_upper: tuple[float, float, float, float] = (0.8, 0.4, 0.2, 2.5)
    prior_sigma: float = 0.05
    floor_free_points: bool = False
    floor_free_depth: float = 0.01
    observe_dT: bool = True
    camera_every_step: bool = False  # the paper uses vision for X_0 only
    translation_scale: float = 0.08  # a control value of 1 is 80 mm ...
    rotation_scale: float = 0.5  # ... or 0.5 rad
    mini_step: float = 0.004  # metres per mini step (quasi-static pushing)
    mini_step_yaw: float = 0.04  # radians per mini step
    contact_band: float = 0.003  # tactile surface band |sdf| < 3 mm
    belief_defaults: tuple = ()

    def __post_init__(self):
        if self.action_space not in ("planar", "3d"):
            raise ValueError(f"action_space must be 'planar' or '3d', got {self.action_space!r}")
        if self.prior_kind not in ("mug-centre", "gaussian"):
            raise ValueError(f"prior_kind must be 'mug-centre' or 'gaussian', got {self.prior_kind!r}")
        if self.max_steps < 1 or self.r_w <= 0 or self.mini_step <= 0 or self.mini_step_yaw <= 0:
            raise ValueError("max_steps, r_w, mini_step and mini_step_yaw must be positive")
        lo, up = np.asarray(self.ee_lower), np.asarray(self.ee_upper)
        if lo.shape != (4,) or up.shape != (4,) or not (up >= lo).all():
            raise ValueError("ee_lower/ee_upper must be (4,) with upper >= lower")

    @property
    def action_dim(self) -> int:
        return 3 if self.action_space == "planar" else 4

    @property
    def workspace(self) -> tuple[np.ndarray, np.ndarray]:
        """``(lower (3,), upper (3,))``; planar tasks: z range ``ee_height +- r_w / 2``."""
        lo, up = np.array(self.workspace_lower, float), np.array(self.workspace_upper, float)
        if self.action_space == "planar":
            lo[2], up[2] = self.ee_height - self.r_w / 2, self.ee_height + self.r_w / 2
        return lo, up

    def start_rotation(self) -> np.ndarray:
        """``Rz(yaw) Ry(pitch) Rx(roll)`` ``(3, 3)`` of the start pose."""
        r, p = self.start_rest_rpy
        cr, sr, cp, sp = math.cos(r), math.sin(r), math.cos(p), math.sin(p)
        cy, sy = math.cos(self.start_yaw), math.sin(self.start_yaw)
        Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
        Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
        Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
        return Rz @ Ry @ Rx

    def start_pose(self, mesh_vertices: np.ndarray) -> torch.Tensor:
        """Object -> world start pose ``(4, 4)`` float64, resting on the table (lowest point at z = 0)."""
        R = self.start_rotation()
        z = -float((np.asarray(mesh_vertices) @ R.T)[:, 2].min())
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = (self.start_xy[0], self.start_xy[1], z)
        return torch.as_tensor(T)

    def prior_center(self, mesh_vertices: np.ndarray) -> torch.Tensor:
        """Nominal object position ``(3,)`` for the gaussian prior (the start position)."""
        return self.start_pose(mesh_vertices)[:3, 3].clone()


def _mug(name: str, xy, yaw) -> TaskSpec:
    return TaskSpec(name=name, object_name="mug", action_space="planar", se2=True, r_w=0.01, nll_threshold=20.0,
                    start_xy=xy, start_yaw=yaw, camera=MUG_CAMERA, prior_kind="mug-centre",
                    ee_start=(0.25, 0.22, 0.02, 0.0))


#: Belief settings of the occluded-camera tasks (drill, box): X_0 holds no surface point, so CHSEL (Alg. 1 line 2)
#: cannot diversify the prior; contact-placed prior proposals at each resample stand in for it (beyond the paper,
#: ``belief/reinvigorate.py``). Measured with rumi, same seeds and code: box 8/30 against 1/15 (seeds 0-4) without,
#: drill 23/30 against 18/30 (README "Where we differ"). ``--belief reinvigorate=0`` runs Algorithm 4 as published.
OCCLUDED_BELIEF = (("reinvigorate", 100),)


def _drill(name: str, xy, yaw) -> TaskSpec:
    return TaskSpec(name=name, object_name="drill", action_space="3d", se2=True, r_w=0.02, nll_threshold=100.0,
                    start_xy=xy, start_yaw=yaw, camera=OCCLUDED_CAMERA, prior_kind="gaussian",
                    ee_start=(0.25, 0.15, 0.15, 0.0), belief_defaults=OCCLUDED_BELIEF)


def _box(name: str, xy, yaw, rpy) -> TaskSpec:
    return TaskSpec(name=name, object_name="cracker_box", action_space="3d", se2=False, r_w=0.02,
                    nll_threshold=150.0, start_xy=xy, start_yaw=yaw, start_rest_rpy=rpy, camera=OCCLUDED_CAMERA,
                    prior_kind="gaussian", floor_free_points=True, ee_start=(0.25, 0.15, 0.15, 0.0),
                    belief_defaults=OCCLUDED_BELIEF)


TASKS: dict[str, TaskSpec] = {
    # mug: near the far edge of reach, handle pointing away from the robot and the camera
    "mug-0": _mug("mug-0", (0.50, 0.0), 0.0),
    "mug-1": _mug("mug-1", (0.45, 0.20), 0.5),
    "mug-2": _mug("mug-2", (0.42, -0.22), -0.6),
    # drill: lying on its side, outside the camera view
    "drill-0": _drill("drill-0", (0.40, -0.15), 0.3),
    "drill-1": _drill("drill-1", (0.47, -0.25), 2.0),
    "drill-2": _drill("drill-2", (0.52, 0.05), -1.2),
    # box: on its back, upright, on its side; outside the camera view
    "box-0": _box("box-0", (0.40, -0.18), 0.5, (0.0, math.pi / 2)),
    "box-1": _box("box-1", (0.36, -0.2), 0.2, (0.0, 0.0)),
    "box-2": _box("box-2", (0.46, -0.25), -0.4, (math.pi / 2, 0.0)),
}


def registered() -> list[str]:
    """Names of the registered tasks."""
    return list(TASKS)


def get_spec(task_id: str, **overrides) -> TaskSpec:
    """The ``TaskSpec`` of ``task_id`` with dataclass fields replaced by ``overrides``."""
    if task_id not in TASKS:
        raise ValueError(f"unknown task {task_id!r}; registered: {', '.join(TASKS)}")
    return with_overrides(TASKS[task_id], overrides)


def with_overrides(spec, overrides: dict):
    """``spec`` (a task spec dataclass) with fields replaced by ``overrides``; ValueError naming unknown fields."""
    if not overrides:
        return spec
    bad = set(overrides) - {f.name for f in dataclasses.fields(spec)}
    if bad:
        raise ValueError(f"unknown {type(spec).__name__} fields in overrides: {sorted(bad)}")
    return dataclasses.replace(spec, **overrides)
