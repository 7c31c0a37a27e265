"""The visuo-tactile clutter tasks (``clutter-*``, the visuo-tactile paper) on a robot: the commands
:class:`ViewCommand`, :class:`TouchCommand`, :class:`PushCommand` and :class:`PickCommand`, :class:`PosedCamera`
(a view's camera as the planners use it), :class:`ClutterRobotEnv`, such a robot as the clutter environment the
episode loop runs (``activetouch.sim.sim_clutter_robot.SimClutterRobot`` is one), and :func:`detection_prior`. The
frames' depth image (:class:`~activetouch.protocol.frames.DepthView`) is in :mod:`activetouch.protocol.frames`;
``activetouch.protocol``'s docstring is the overview."""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import torch

from activetouch.sim.camera import PinholeCamera

from .frames import (CAMERA, SURFACE, DepthView, ProtocolError, Robot, SensorFrame, _check_answer, _command_array,
                     _ee_state, _pose, check_frame)


def _unit_vector(x, name: str) -> np.ndarray:
    """``x`` as a read-only finite ``(3,)`` float64 copy of norm 1 (within 1e-3, the clutter env's tolerance)."""
    a = _command_array(x, (3,), name)
    n = float(np.linalg.norm(a))
    if abs(n - 1.0) > 1e-3:
        raise ProtocolError(f"{name} must be a unit vector, got norm {n:.4f}")
    return a


def _positive(x, name: str) -> float:
    if isinstance(x, bool) or not isinstance(x, (int, float, np.floating, np.integer)) \
            or not (math.isfinite(float(x)) and float(x) > 0):
        raise ProtocolError(f"{name} must be a finite number > 0, got {x!r}")
    return float(x)


def _label(x, name: str) -> int:
    if isinstance(x, (bool, np.bool_)) or not isinstance(x, (int, np.integer)) or int(x) < 0:
        raise ProtocolError(f"{name} must be an object label (an int >= 0), got {x!r}")
    return int(x)


@dataclasses.dataclass(frozen=True)
class ViewCommand:
    """Move the depth camera so its optical centre is at ``position (3,)`` looking at ``look_at (3,)`` (world, m),
    take one depth image and segment it (visuo-tactile paper Sec. II-D-1; the declutter phase's overhead views,
    Sec. II-B). The image's roll is the look-at convention of ``sim.camera.PinholeCamera`` (image x horizontal,
    world z up): the full camera pose is :attr:`camera_pose`, what a real arm's IK or camera mount reaches for.
    The frame that ends it carries the :class:`DepthView` of the image taken (at the pose reached).

    SIMPLIFICATION (the simulator): the camera is a free-flying sensor on the view hemisphere and the arm parks out
    of view before each image; the paper's camera rides on a second arm."""

    position: np.ndarray
    look_at: np.ndarray

    def __post_init__(self):
        from activetouch.sim.camera import look_at

        p = _command_array(self.position, (3,), "ViewCommand.position")
        t = _command_array(self.look_at, (3,), "ViewCommand.look_at")
        object.__setattr__(self, "position", p)
        object.__setattr__(self, "look_at", t)
        if np.linalg.norm(p - t) < 1e-6:
            raise ProtocolError("ViewCommand.position and look_at coincide")
        try:
            look_at(p, t)
        except ValueError:
            raise ProtocolError("ViewCommand looks straight up or down: the image's roll is undefined") from None

    @property
    def camera_pose(self) -> np.ndarray:
        """``(4, 4)`` camera -> world pose to reach, OpenCV axes (x right, y down, z forward)."""
        from activetouch.sim.camera import look_at

        T = np.eye(4)
        T[:3, :3] = look_at(self.position, self.look_at)
        T[:3, 3] = self.position
        return T


@dataclasses.dataclass(frozen=True)
class TouchCommand:
    """A guarded touch (visuo-tactile paper Sec. II-D-2): bring the closed gripper to ``start (3,)`` (world, m;
    through a safe height above the pile, the pads' narrow edges leading along ``direction``), then move straight
    along the unit ``direction (3,)`` at touch speed for at most ``max_length`` m and stop at the first contact of
    the gripper with anything; retreat. The frame that ends it reports ``contact_label`` (the object touched first,
    ``-1``: none) and, when that is the target, ``in_contact`` and the tactile contact points on it (``points``:
    SURFACE, TOUCH; the paper's taxel positions). A contact on the way to ``start`` ends the touch too."""

    start: np.ndarray
    direction: np.ndarray
    max_length: float = 0.15

    def __post_init__(self):
        object.__setattr__(self, "start", _command_array(self.start, (3,), "TouchCommand.start"))
        object.__setattr__(self, "direction", _unit_vector(self.direction, "TouchCommand.direction"))
        object.__setattr__(self, "max_length", _positive(self.max_length, "TouchCommand.max_length"))


@dataclasses.dataclass(frozen=True)
class PushCommand:
    """Push object ``label`` (a label of the views' segmentation, not the target's) with the closed gripper
    (visuo-tactile paper Sec. II-B-1): from ``start (3,)`` straight along the unit ``direction (3,)`` by ``length``
    m, monitoring the contact with the object; a loss of contact stops the push. The frame that ends it reports
    ``push_success`` (the object moved away from the target) and ``contact_label`` (``label`` if the gripper
    touched it, else ``-1``)."""

    label: int
    start: np.ndarray
    direction: np.ndarray
    length: float = 0.10

    def __post_init__(self):
        object.__setattr__(self, "label", _label(self.label, "PushCommand.label"))
        object.__setattr__(self, "start", _command_array(self.start, (3,), "PushCommand.start"))
        object.__setattr__(self, "direction", _unit_vector(self.direction, "PushCommand.direction"))
        object.__setattr__(self, "length", _positive(self.length, "PushCommand.length"))


@dataclasses.dataclass(frozen=True)
class PickCommand:
    """Pick object ``label`` (a label of the views' segmentation, not the target's) and place it outside the
    workspace (visuo-tactile paper Sec. II-B-2): open to ``width`` m plus clearance, descend top-down (guarded:
    touching another object aborts) until the pads' tips are at ``position (3,)`` (world, m), close along the
    horizontal direction at ``closing_angle`` (rad, world x-y), verify the grasp by contact (both pads on the
    object), lift, set the object down outside the workspace. The frame that ends it reports ``grasp_success``
    (grasped and set down outside) and ``contact_label`` (``label`` if grasped, else ``-1``)."""

    label: int
    position: np.ndarray
    closing_angle: float
    width: float

    def __post_init__(self):
        object.__setattr__(self, "label", _label(self.label, "PickCommand.label"))
        object.__setattr__(self, "position", _command_array(self.position, (3,), "PickCommand.position"))
        a = self.closing_angle
        if isinstance(a, bool) or not isinstance(a, (int, float, np.floating, np.integer)) or not math.isfinite(a):
            raise ProtocolError(f"PickCommand.closing_angle must be a finite angle (rad), got {a!r}")
        object.__setattr__(self, "closing_angle", float(a))
        object.__setattr__(self, "width", _positive(self.width, "PickCommand.width"))


@dataclasses.dataclass(frozen=True)
class PosedCamera(PinholeCamera):
    """The camera of a :class:`DepthView` as the clutter planners use it (``sim.camera.PinholeCamera``'s interface:
    ``pos``, ``intrinsics()``, ``rotation()``, ``ray_directions() (H*W, 3)``, ``max_depth``), at the pose the robot
    reported rather than a look-at: ``orientation`` is the camera -> world rotation (9 floats, row-major, OpenCV
    axes), so a camera that rolled or looks straight down keeps its pixels' rays; ``target`` is 1 m along the
    optical axis (for viewers); ``fx, fy, cx, cy`` are the view's intrinsics."""

    orientation: tuple = ()

    def __post_init__(self):
        if self.width < 1 or self.height < 1:
            raise ValueError(f"camera image size must be positive, got {self.width}x{self.height}")
        if len(self.orientation) != 9:
            raise ValueError(f"PosedCamera.orientation must be 9 floats (a row-major 3x3 rotation), got "
                             f"{len(self.orientation)}")

    def rotation(self) -> np.ndarray:
        """Camera-to-world rotation ``(3, 3)`` (the reported one)."""
        return np.array(self.orientation, dtype=np.float64).reshape(3, 3)

    @classmethod
    def of(cls, view: DepthView) -> "PosedCamera":
        """The camera of ``view`` (valid: :func:`check_frame`)."""
        T = np.asarray(view.camera_pose, dtype=np.float64)
        K = np.asarray(view.intrinsics, dtype=np.float64)
        H, W = view.shape
        return cls(pos=tuple(float(v) for v in T[:3, 3]), target=tuple(float(v) for v in T[:3, 3] + T[:3, 2]),
                   width=int(W), height=int(H), fov_y_deg=math.degrees(2 * math.atan(0.5 * H / K[1, 1])),
                   fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]),
                   max_depth=float(view.max_depth), orientation=tuple(float(v) for v in T[:3, :3].reshape(-1)))


def _swap_label(label: int, target: int) -> int:
    """The planners' numbering (target = 0) <-> the robot's (target = ``target``): 0 and ``target`` trade places,
    every other label (and -1, no object) stays. Its own inverse."""
    label = int(label)
    return 0 if label == target else target if label == 0 else label


class ClutterRobotEnv:
    """The dense-clutter environment interface (``activetouch.sim.clutter_env.ClutterEnv``'s: the visuo-tactile
    paper's ``clutter-*`` tasks) on top of any :class:`Robot` that executes :class:`ViewCommand`,
    :class:`TouchCommand`, :class:`PushCommand` and :class:`PickCommand`.

    The loop's ``step`` goes to the robot: a ``ViewAction`` becomes a :class:`ViewCommand` (Sec. II-D-1), a
    ``TouchAction`` a :class:`TouchCommand` (II-D-2), a ``PushAction`` / ``PickAction`` a :class:`PushCommand` /
    :class:`PickCommand` (the declutter actions, II-B); a ``StopAction`` ends the episode without moving the robot.
    The frames become the ``ClutterObservation`` the TIQF estimator and the clutter planner read: a view's target
    points (``frame.points``' SURFACE / CAMERA rows), segmentation ``seg (H, W)``, organised cloud ``cloud (H, W,
    3)`` and camera (a :class:`PosedCamera` at the reported pose); a touch's contact points on the target; a push's
    or pick's outcome; the label of the object touched. Labels: the planners call the target 0; a robot whose
    segmenter gives the target another label ``t`` has 0 and ``t`` swapped both ways (into ``seg`` and
    ``contact_label``, back into the commands' labels); every other label passes unchanged.

    No model queries: the clutter planners predict on their own occupancy grid (Eq. 19-24) and on the target's mesh
    (Eq. 25), so unlike :class:`GraspRobotEnv` no model environment is needed, only task knowledge: ``spec`` (the view
    hemisphere, the camera model the next best views are predicted with, the budget, the prior's spread), the
    target's mesh ``obj`` and the ``gripper`` (its opening and pad size, for grasp and push planning).

    Args:
        robot: a :class:`Robot` of the clutter tasks (``activetouch.sim.sim_clutter_robot.SimClutterRobot``; a real
            arm's driver with a depth camera and a segmenter).
        spec: the task (``sim.clutter_env.ClutterTaskSpec``): ``view_radius``, ``min_view_elevation_deg``,
            ``camera_*`` (set them to the real camera's), ``max_actions``, ``prior_sigma_*``, ``target``.
        obj: the target (``activetouch.objects.KnownObject``); None: ``objects.load(spec.target)``.
        gripper: the gripper's geometry (``sim.grasp_scene.GripperSpec``); None: the simulated ``CLUTTER_GRIPPER``.
        prior_pose: the coarse target pose ``(4, 4)`` the episode starts from (the paper's approximate centroid from
            its segmentation network, an upright target of unknown heading; Sec. II-D-1), or a callable
            ``seed -> (4, 4)`` called after the robot's reset; reported as ``info["prior_pose"]`` for
            :func:`detection_prior`. None: no ``prior_pose`` (the task's prior must come from elsewhere).
        names: object names by label for figures (default: ``(spec.target,)``: a robot does not know the clutter).
        seed: default seed of ``reset`` (only a callable ``prior_pose`` reads it: the robot draws nothing).

    ``info["true_pose"]`` (float32 torch ``(4, 4)``) comes from the frames' ``object_pose`` (evaluation only: the
    loop's metrics read it, no estimator or planner does); ``info`` has no ``object_poses``, ``object_names`` or
    ``pile_centre`` (the simulator's ground truth beyond the target's pose).
    """

    def __init__(self, robot, spec, obj=None, gripper=None, prior_pose=None, names=None, seed: int = 0):
        if not isinstance(robot, Robot):
            raise ProtocolError(f"{type(robot).__name__} lacks reset(), observe() or act()")
        from activetouch import objects
        from activetouch.sim.clutter_env import CLUTTER_GRIPPER

        self.robot, self.spec = robot, spec
        self.object = objects.load(spec.target) if obj is None else obj
        self.gripper = CLUTTER_GRIPPER if gripper is None else gripper
        self.names = (spec.target,) if names is None else tuple(names)
        self.seed = int(seed)
        self._prior_pose = prior_pose
        self._frame: SensorFrame | None = None
        self._n_joints: int | None = None
        self._n_actions = 0
        self._terminated = False
        self._target = 0  # the robot's label of the target (the last view's)

    @property
    def max_steps(self) -> int:
        """Episode budget T: ``spec.max_actions``."""
        return self.spec.max_actions

    # -- the robot's state (its last frame)
    def _require_frame(self) -> SensorFrame:
        if self._frame is None:
            raise RuntimeError("call reset() before step()")
        return self._frame

    def ee_state(self) -> np.ndarray:
        """Measured end effector ``[x, y, z, yaw] (4,)`` of the last frame."""
        return _ee_state(self._require_frame())

    def current_q(self) -> np.ndarray:
        """Measured arm joints ``(n,)`` of the last frame."""
        return np.array(self._require_frame().joint_positions, dtype=np.float64)

    def true_pose(self) -> np.ndarray | None:
        """Ground-truth target pose ``(4, 4)`` of the last frame (evaluation only), None when unknown."""
        f = self._require_frame()
        return None if f.object_pose is None else np.asarray(f.object_pose, dtype=np.float64)

    def object_poses(self) -> np.ndarray:
        """``(1, 4, 4)``: the target's ground-truth pose (figures only; the clutter's poses are not reported)."""
        T = self.true_pose()
        if T is None:
            raise RuntimeError("the robot reports no object_pose: no ground truth to draw")
        return T[None].copy()

    def close(self) -> None:
        if hasattr(self.robot, "close"):
            self.robot.close()

    # -- the loop's calls
    def _accept(self, frame: SensorFrame, command=None) -> SensorFrame:
        check_frame(frame, self._n_joints)
        if command is not None:
            _check_answer(command, frame)
        self._n_joints = len(frame.joint_positions)
        return frame

    def _observation(self, command, frame: SensorFrame):
        """The ``ClutterObservation`` of ``frame``, the answer to ``command``."""
        from activetouch.sim.clutter_env import ClutterObservation

        none = np.zeros((0, 3))
        if isinstance(command, ViewCommand):
            v = frame.view
            t = int(v.target_label)
            self._target = t
            lab = np.asarray(v.labels)
            seg = lab.copy() if t == 0 else np.where(lab == t, 0, np.where(lab == 0, t, lab)).astype(lab.dtype)
            pts = np.asarray(frame.points, dtype=np.float64)
            pts = pts[(np.asarray(frame.semantics) == SURFACE) & (np.asarray(frame.source) == CAMERA)]
            return ClutterObservation("view", pts, seg=seg, cloud=np.array(v.points), camera=PosedCamera.of(v),
                                      success=bool((lab == t).any()))
        label = _swap_label(frame.contact_label, self._target)
        if isinstance(command, TouchCommand):
            contacts = np.asarray(frame.contacts, dtype=np.float64)
            ok = bool(frame.in_contact) and len(contacts) > 0
            return ClutterObservation("touch", contacts if ok else none, in_contact=ok, success=ok,
                                      contact_label=label)
        if isinstance(command, PushCommand):
            return ClutterObservation("push", none, success=bool(frame.push_success), contact_label=label)
        return ClutterObservation("pick", none, success=bool(frame.grasp_success), contact_label=label)

    def _info(self, **extra) -> dict[str, Any]:
        f = self._require_frame()
        info: dict[str, Any] = {"num_actions": self._n_actions, "stamp": float(f.stamp)}
        if f.object_pose is not None:
            info["true_pose"] = torch.as_tensor(np.asarray(f.object_pose, dtype=np.float64), dtype=torch.float32)
        info.update(extra)
        return info

    def reset(self, seed: int | None = None):
        """Reset the robot; returns ``ClutterObservation("reset")`` and ``info`` with ``num_actions``, ``stamp``,
        ``prior_pose (4, 4)`` float32 torch (when given) and, when the robot reports ``object_pose``, ``true_pose``."""
        from activetouch.sim.clutter_env import ClutterObservation

        seed = self.seed if seed is None else int(seed)
        self._n_joints = None
        self._frame = self._accept(self.robot.reset())
        self._n_actions = 0
        self._terminated = False
        self._target = 0
        extra: dict[str, Any] = {}
        if self._prior_pose is not None:
            P = self._prior_pose(seed) if callable(self._prior_pose) else self._prior_pose
            extra["prior_pose"] = torch.as_tensor(_pose(P, "prior_pose"), dtype=torch.float32)
        return ClutterObservation("reset", np.zeros((0, 3))), self._info(**extra)

    def step(self, action):
        """Execute a ``ViewAction`` / ``TouchAction`` / ``PushAction`` / ``PickAction`` on the robot (a
        ``StopAction`` ends the episode); returns ``(obs, reward, terminated, truncated, info)`` as
        ``ClutterEnv.step`` does (``info``: ``action``, ``action_success``, ``num_actions``, ``stamp``,
        ``true_pose``; a stop's ``stop_reason``)."""
        from activetouch.sim.clutter_env import (ClutterObservation, PickAction, PushAction, StopAction, TouchAction,
                                                 ViewAction)

        self._require_frame()
        if self._terminated:
            raise RuntimeError("the episode has ended (StopAction); call reset()")
        if isinstance(action, StopAction):
            self._terminated = True
            return (ClutterObservation("stop", np.zeros((0, 3))), 0.0, True, False,
                    self._info(action="stop", action_success=True, stop_reason=action.reason))
        if self._n_actions >= self.spec.max_actions:
            raise RuntimeError(f"max_actions = {self.spec.max_actions} actions made; call reset()")
        if isinstance(action, ViewAction):
            cmd = ViewCommand(action.position, action.look_at)
        elif isinstance(action, TouchAction):
            cmd = TouchCommand(action.start, action.direction, action.max_length)
        elif isinstance(action, PushAction):
            cmd = PushCommand(_swap_label(action.label, self._target), action.start, action.direction, action.length)
        elif isinstance(action, PickAction):
            cmd = PickCommand(_swap_label(action.label, self._target), action.position, action.closing_angle,
                              action.width)
        else:
            raise ValueError(f"action must be a ViewAction, TouchAction, PushAction, PickAction or StopAction, "
                             f"got {type(action).__name__}")
        self._n_actions += 1
        self._frame = self._accept(self.robot.act(cmd), cmd)
        obs = self._observation(cmd, self._frame)
        truncated = self._n_actions >= self.spec.max_actions
        return obs, 0.0, False, truncated, self._info(action=obs.kind, action_success=obs.success)


def detection_prior(env, n: int, generator: torch.Generator, device="cpu", *, info=None, **_) -> torch.Tensor:
    """The clutter tasks' prior around the robot's detection of the target: ``n`` poses ``(n, 4, 4)``, the coarse
    pose ``info["prior_pose"]`` (:class:`ClutterRobotEnv`'s ``prior_pose``) perturbed exactly as
    ``activetouch.tasks.clutter_prior`` perturbs the simulator's truth (N(0, ``spec.prior_sigma_t``) in x, y and
    N(0, ``spec.prior_sigma_yaw_deg``) about z). Register a clutter task on a robot with ``prior=detection_prior``:
    the registered tasks' ``clutter_prior`` reads ``info["true_pose"]``, the simulator's stand-in for the paper's
    approximate centroid (Sec. II-D-1)."""
    from activetouch.tasks import clutter_prior

    if info is None or "prior_pose" not in info:
        raise ValueError("detection_prior needs info['prior_pose'] from ClutterRobotEnv.reset() (its prior_pose)")
    return clutter_prior(env, n, generator, device, info={"true_pose": info["prior_pose"]})
