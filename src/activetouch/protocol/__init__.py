"""The robot / sensor protocol: what a robot (simulated or real) gives the episode loop, and what it takes.

A robot implements :class:`Robot`: ``reset()``, ``observe()`` and ``act(command)``, each returning a
:class:`SensorFrame`. :class:`activetouch.sim.sim_robot.SimRobot` implements it on the MuJoCo rummaging tasks;
a real arm implements the same three methods on its drivers (docs/ROBOT.md walks through it).
:class:`RobotEnv` turns any :class:`Robot` back into the environment the one episode loop runs
(``reset() -> (obs, info)``, ``step(u) -> (obs, r, terminated, truncated, info)`` and the task geometry the
planners read), so every method registered for the rummaging tasks (RUMI, its ablations, GPVR, Slide,
tiqf-slide) runs on it unchanged; :func:`check_robot` is the contract a robot must pass (as gymnasium's
``check_env`` is for environments).

The touch-only grasp tasks (``grasp-box-*``, the touch paper) run through the same three calls with two more
commands, :class:`GuardedMoveCommand` (a guarded poke through end-effector via-points) and :class:`GraspCommand`
(the grasp primitive), and frames that carry the arm's full state (:class:`ArmState`), the control-rate log of the
motion (:class:`MotionLog`: the binary contact signal, the guard) and the grasp's outcome. :class:`GraspRobotEnv`
turns such a robot back into the grasp environment the loop runs; its estimator and planner still predict with a
*model* (a ``GraspEnv`` used only for particle rollouts, IK, grasp simulation, robot surface points and reach),
whose own object is never read. :class:`activetouch.sim.sim_grasp_robot.SimGraspRobot` implements it.

The visuo-tactile clutter tasks (``clutter-*``, the visuo-tactile paper) run through the same three calls with four
more commands: :class:`ViewCommand` (move the depth camera to a view pose, Sec. II-D-1), :class:`PushCommand` and
:class:`PickCommand` (the declutter actions, Sec. II-B) and :class:`TouchCommand` (a guarded touch, Sec. II-D-2);
a view's frame carries the segmented depth image (:class:`DepthView`: the organised point cloud, per-pixel object
labels from the robot's segmenter and which label is the target), a touch's frame the contact points and the label
of the object touched, a push's or pick's frame its outcome. :class:`ClutterRobotEnv` turns such a robot back into
the clutter environment the loop runs; the clutter planners make no model queries (they predict on their own
occupancy grid and on the target's mesh), so it needs no model environment, only the task knowledge (the task spec's
camera model and view hemisphere, the target's mesh, the gripper's size). :func:`detection_prior` is the tasks'
prior around the robot's coarse detection of the target instead of the simulator's truth.
:class:`activetouch.sim.sim_clutter_robot.SimClutterRobot` implements it.

The episode log (``episode.h5``) records the observations the loop saw, so
a real robot's episodes replay offline with ``activetouch replay`` like simulated ones.

Conventions (docs/INTERFACES.md): metres, radians, world frame = the robot base frame with z up; poses are
``(4, 4)`` homogeneous object/end-effector -> world transforms.

The package holds one part per module: :mod:`activetouch.protocol.frames` (:class:`SensorFrame` and its parts
:class:`ArmState`, :class:`MotionLog` and :class:`DepthView`, the ``semantics`` / ``source`` constants,
:class:`ProtocolError`, :class:`EeDeltaCommand`, :class:`Robot`, :func:`check_frame`, :func:`check_robot`),
:mod:`activetouch.protocol.rummage` (:class:`RobotEnv`), :mod:`activetouch.protocol.grasp` (the grasp commands,
:class:`GraspRobotEnv`) and :mod:`activetouch.protocol.clutter` (the clutter commands, :class:`PosedCamera`,
:class:`ClutterRobotEnv`, :func:`detection_prior`); every name of ``__all__`` is importable from
``activetouch.protocol``.
"""
from .frames import (CAMERA, FREE, OCCUPIED, PRIOR, SURFACE, TOUCH, ArmState, DepthView, EeDeltaCommand, MotionLog,
                     ProtocolError, Robot, SensorFrame, check_frame, check_robot)
from .rummage import RobotEnv
from .grasp import GraspCommand, GraspRobotEnv, GuardedMoveCommand
from .clutter import (ClutterRobotEnv, PickCommand, PosedCamera, PushCommand, TouchCommand, ViewCommand,
                      detection_prior)

__all__ = ["SensorFrame", "EeDeltaCommand", "GuardedMoveCommand", "GraspCommand", "ViewCommand", "TouchCommand",
           "PushCommand", "PickCommand", "ArmState", "MotionLog", "DepthView", "PosedCamera", "Robot", "RobotEnv",
           "GraspRobotEnv", "ClutterRobotEnv", "detection_prior", "check_frame", "check_robot", "ProtocolError",
           "CAMERA", "TOUCH", "PRIOR", "SURFACE", "FREE", "OCCUPIED"]
