"""MJCF builder for the blind-grasping scene (touch-only localisation paper, Sec. VI-A, Fig. 1, App. D).

Scene: a table whose top is the plane z = 0, the KUKA LBR iiwa on a fixed base (``robot.BASE_POS``),
a two-pad parallel gripper whose pads are actuated (one slide joint + position actuator each) on the
flange, and the cracker box standing upright (joints slide x, slide y, slide z, hinge z as
``scene.build_scene(upright=True)``), so pokes can push it over the table but never tip it over.
No camera and no shelf walls (the paper's task is touch only, in an uncluttered scene).

The paper uses a Franka Emika arm; we keep the repository's iiwa (same assets as the RUMI scene) so
both tasks share one robot model. The paper's "end-effector width is slightly larger than the object
width": the pads open to ``opening`` (default 0.09 m) around the box's 0.072 m narrow side.

Collision bits: static (table) = 1, object = 2, robot near the table (links 5-7, gripper) = 4, robot
far from the table (links 1-4) = 8. Pairs that collide: table-object, robot-object (every robot
link and the gripper: the paper's d of Eq. 10 is the distance to the *whole* robot), gripper/links 5-7
with the table. Links 1-4 skip the table (link 1 stands on it). The fixed base (link 0) is visual only:
the box cannot reach it inside the workspace.
"""
from __future__ import annotations

import dataclasses
import pathlib
import xml.etree.ElementTree as ET

import mujoco
import numpy as np
import trimesh

from .robot import BASE_POS, FLANGE_OFFSET
from .scene import OBJECT_PHYSICS, _fmt, _robot_assets, _robot_xml, hull_dir

__all__ = [
    "GraspGripperGeometry",
    "GRASP_GRIPPER",
    "build_grasp_scene",
    "robot_and_table_root",
    "add_actuators",
    "ARM_JOINTS",
    "PAD_JOINTS",
    "OBJECT_JOINTS",
]

ARM_JOINTS = tuple(f"lbr_iiwa_joint_{i}" for i in range(1, 8))
PAD_JOINTS = ("pad_0_slide", "pad_1_slide")
OBJECT_JOINTS = ("object_x", "object_y", "object_z", "object_yaw")
#: Arm actuator gains (kp, kv), the RUMI scene's: stiff joint position control.
ARM_GAINS = ((3000, 150), (3000, 150), (2000, 100), (2000, 100), (800, 30), (800, 30), (400, 15))


@dataclasses.dataclass(frozen=True)
class GraspGripperGeometry:
    """Parallel gripper in the ee frame (metres; same ee frame as ``robot.py``: origin at the pads' tips,
    ``+z`` up along the gripper, ``+y`` from pad 1 to pad 0, pads closing along ``y``).

    Each pad is a box; its slide joint value ``s`` is the ``y`` of its inner face (``+s`` for pad 0,
    ``-s`` for pad 1), so the opening (gap between the inner faces) is ``2 s``.
    """

    pad_half: tuple[float, float, float] = (0.020, 0.006, 0.035)  # width (x), thickness (y), height (z)
    max_opening: float = 0.11  # slide range of the pads: s in [0, max_opening / 2]
    palm_half: tuple[float, float, float] = (0.030, 0.070, 0.015)
    adaptor_radius: float = 0.035
    adaptor_half_height: float = 0.015
    pad_kp: float = 600.0  # pad position actuator stiffness (N/m)
    pad_kv: float = 20.0
    pad_force: float = 20.0  # pad force limit (N): the grip force, ~5x the box's weight over 2 mu

    def __post_init__(self):
        if self.max_opening <= 0 or min(self.pad_half) <= 0 or min(self.palm_half) <= 0:
            raise ValueError("gripper dimensions must be positive")
        if self.palm_half[1] < self.max_opening / 2 + 2 * self.pad_half[1] - 1e-9:
            raise ValueError("palm_half[1] must cover the fully opened pads")

    @property
    def palm_centre(self) -> tuple[float, float, float]:
        return (0.0, 0.0, 2 * self.pad_half[2] + self.palm_half[2])

    @property
    def adaptor_centre(self) -> tuple[float, float, float]:
        return (0.0, 0.0, 2 * self.pad_half[2] + 2 * self.palm_half[2] + self.adaptor_half_height)

    @property
    def length(self) -> float:
        """Tip-to-flange distance (m)."""
        return 2 * (self.pad_half[2] + self.palm_half[2] + self.adaptor_half_height)

    @property
    def footprint_radius(self) -> float:
        """Radius (m) of the smallest z-axis cylinder around the ee frame holding the fully opened gripper."""
        y_out = self.max_opening / 2 + 2 * self.pad_half[1]
        return float(max(np.hypot(self.pad_half[0], y_out), np.hypot(*self.palm_half[:2]), self.adaptor_radius))


GRASP_GRIPPER = GraspGripperGeometry()


def _add_gripper(link7: ET.Element, g: GraspGripperGeometry) -> None:
    """Gripper body in link 7 (its frame = the ee frame), two pad bodies with slide joints."""
    body = ET.SubElement(link7, "body", name="gripper", pos=_fmt([0, 0, FLANGE_OFFSET + g.length]),
                         quat="0 1 0 0", gravcomp="1")
    ET.SubElement(body, "inertial", pos=_fmt(g.palm_centre), mass="0.6", diaginertia="0.002 0.002 0.002")
    common = dict(contype="4", conaffinity="3", friction="0.8 0.005 0.0001", solref="0.005 1", group="1")
    ET.SubElement(body, "geom", name="palm", type="box", size=_fmt(g.palm_half), pos=_fmt(g.palm_centre),
                  rgba="0.3 0.3 0.3 1", **common)
    ET.SubElement(body, "geom", name="adaptor", type="cylinder",
                  size=_fmt([g.adaptor_radius, g.adaptor_half_height]), pos=_fmt(g.adaptor_centre),
                  rgba="0.3 0.3 0.3 1", **common)
    ET.SubElement(body, "site", name="ee", pos="0 0 0", size="0.005")
    for i, sgn in enumerate((1.0, -1.0)):
        pad = ET.SubElement(body, "body", name=f"pad_{i}", pos="0 0 0", gravcomp="1")
        ET.SubElement(pad, "inertial", pos=_fmt([0, sgn * g.pad_half[1], g.pad_half[2]]), mass="0.05",
                      diaginertia="2e-5 2e-5 2e-5")
        ET.SubElement(pad, "joint", name=PAD_JOINTS[i], type="slide", axis=_fmt([0, sgn, 0]),
                      range=_fmt([0.0, g.max_opening / 2]), damping="2", armature="0.01")
        ET.SubElement(pad, "geom", name=f"pad_{i}", type="box", size=_fmt(g.pad_half),
                      pos=_fmt([0, sgn * g.pad_half[1], g.pad_half[2]]), rgba="0.85 0.3 0.3 1", **common)


def robot_and_table_root(model_name: str, gripper: GraspGripperGeometry = GRASP_GRIPPER, timestep: float = 0.002,
                         table_lower: tuple[float, float] = (-0.55, -0.6),
                         table_upper: tuple[float, float] = (1.05, 0.6)) -> tuple[ET.Element, ET.Element, dict]:
    """MJCF root of the iiwa on its fixed base with the two-pad gripper and the table (top at z = 0), shared by
    the grasping scene and the clutter scene (``clutter_scene``). Returns ``(root, worldbody, assets)``; the
    caller adds its objects, then :func:`add_actuators`, and compiles with ``assets``."""
    root = ET.fromstring(_robot_xml())
    root.set("model", model_name)
    comp = root.find("compiler")
    comp.set("inertiafromgeom", "false")
    comp.attrib.pop("meshdir", None)
    root.insert(1, ET.Element("option", timestep=f"{timestep}", integrator="implicitfast", cone="elliptic",
                              impratio="2"))
    ET.SubElement(root, "size", memory="20M")

    # ---------------------------------------------------------------- robot
    world = root.find("worldbody")
    base = ET.Element("body", name="iiwa_base", pos=_fmt(BASE_POS))
    for g in list(world.findall("geom")):
        world.remove(g)
        if g.get("contype") == "0":  # the fixed base: visual only
            g.set("group", "1")
            base.append(g)
    ET.SubElement(base, "inertial", pos="0 0 0.05", mass="5", diaginertia="0.05 0.05 0.05")
    link1 = world.find("body")
    world.remove(link1)
    base.append(link1)
    world.append(base)
    for body in base.iter("body"):
        body.set("gravcomp", "1")
        name = body.get("name", "")
        if not name.startswith("lbr_iiwa_link"):
            continue
        idx = int(name.rsplit("_", 1)[-1])
        for g in body.findall("geom"):
            if g.get("contype") != "0":
                body.remove(g)  # drop the duplicate copy; keep one geom per link
        for g in body.findall("geom"):
            g.set("group", "1")
            g.set("name", f"link_{idx}")
            g.set("contype", "4" if idx >= 5 else "8")
            g.set("conaffinity", "3" if idx >= 5 else "2")
    link7 = next(b for b in base.iter("body") if b.get("name") == "lbr_iiwa_link_7")
    _add_gripper(link7, gripper)

    # ---------------------------------------------------------------- table
    world.insert(0, ET.Element("light", pos="0.3 0 2.0", dir="0 0 -1", directional="true"))
    tl, tu = np.asarray(table_lower, float), np.asarray(table_upper, float)
    ET.SubElement(world, "geom", name="table", type="box", pos=_fmt([*(tl + tu) / 2, -0.025]),
                  size=_fmt([*(tu - tl) / 2, 0.025]), rgba="0.75 0.65 0.5 1", contype="1", conaffinity="6",
                  group="0", friction="0.5 0.005 0.0001")

    return root, world, dict(_robot_assets())


def add_actuators(root: ET.Element, gripper: GraspGripperGeometry = GRASP_GRIPPER) -> None:
    """Position actuators ``act_1..7`` (arm joints, ``ARM_GAINS``) and ``act_pad_0/1`` (pad slides)."""
    act = ET.SubElement(root, "actuator")
    for i, (kp, kv) in enumerate(ARM_GAINS, start=1):
        ET.SubElement(act, "position", name=f"act_{i}", joint=f"lbr_iiwa_joint_{i}", kp=str(kp), kv=str(kv),
                      forcerange="-300 300")
    for i, j in enumerate(PAD_JOINTS):
        ET.SubElement(act, "position", name=f"act_pad_{i}", joint=j, kp=f"{gripper.pad_kp}",
                      kv=f"{gripper.pad_kv}", forcerange=_fmt([-gripper.pad_force, gripper.pad_force]),
                      ctrlrange=_fmt([0.0, gripper.max_opening / 2]))


def build_grasp_scene(object_name: str = "cracker_box", mesh_path: pathlib.Path | str | None = None,
                      gripper: GraspGripperGeometry = GRASP_GRIPPER, timestep: float = 0.002,
                      table_lower: tuple[float, float] = (-0.55, -0.6),
                      table_upper: tuple[float, float] = (1.05, 0.6)) -> mujoco.MjModel:
    """Compile the grasping scene (module docstring).

    Args:
        object_name: a key of ``scene.OBJECT_PHYSICS`` (selects the convex hulls and the mass).
        mesh_path: the exact watertight mesh (object frame) for the inertia; default the packaged one.
        timestep: physics step (s).
    Returns:
        the compiled ``MjModel``. Names: body ``object`` with joints ``OBJECT_JOINTS`` (consecutive in
        ``qpos``), site ``ee``, bodies ``gripper``, ``pad_0``, ``pad_1``, joints ``PAD_JOINTS``, actuators
        ``act_1..7`` (arm joint positions) and ``act_pad_0``, ``act_pad_1`` (pad slide positions), sensor
        ``object_robot_force`` (net contact force between the object and the robot, world frame).
    """
    if object_name not in OBJECT_PHYSICS:
        raise ValueError(f"unknown object {object_name!r}; known: {sorted(OBJECT_PHYSICS)}")
    phys = OBJECT_PHYSICS[object_name]
    if mesh_path is None:
        from activetouch import objects

        mesh_path = objects.load(object_name).mesh_path
    mesh_path = pathlib.Path(mesh_path)
    mesh = trimesh.load(mesh_path, force="mesh", process=False)
    hull_files = sorted(hull_dir(object_name).glob("hull_*.obj"))
    if not hull_files:
        raise FileNotFoundError(f"no convex decomposition for {object_name!r}; run scripts/decompose.py")

    root, world, assets = robot_and_table_root(f"grasp_{object_name}", gripper, timestep, table_lower, table_upper)

    # ---------------------------------------------------------------- object (upright: x, y, z, yaw joints)
    asset = root.find("asset")
    for i, f in enumerate(hull_files):
        ET.SubElement(asset, "mesh", name=f"object_hull_{i}", file=f"{object_name}_{f.name}")
    mp = mesh.copy()
    mp.density = phys.mass / mesh.volume
    com, inertia = mp.center_mass, mp.moment_inertia
    obj = ET.SubElement(world, "body", name="object", pos="0 0 0")
    for name, kind, axis in zip(OBJECT_JOINTS, ("slide", "slide", "slide", "hinge"),
                                ("1 0 0", "0 1 0", "0 0 1", "0 0 1")):
        ET.SubElement(obj, "joint", name=name, type=kind, axis=axis, damping="0", armature="0")
    ET.SubElement(obj, "inertial", pos=_fmt(com), mass=f"{phys.mass}",
                  fullinertia=_fmt([inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1], inertia[0, 2],
                                    inertia[1, 2]]))
    for i in range(len(hull_files)):
        ET.SubElement(obj, "geom", name=f"object_hull_{i}", type="mesh", mesh=f"object_hull_{i}", contype="2",
                      conaffinity="13", group="2", friction=f"{phys.friction} {phys.torsional} 0.0001",
                      condim="4", rgba="0.2 0.5 0.9 1")

    # ---------------------------------------------------------------- actuators and sensor
    add_actuators(root, gripper)
    sens = ET.SubElement(root, "sensor")
    ET.SubElement(sens, "contact", name="object_robot_force", body1="object", subtree2="iiwa_base", num="1",
                  data="force", reduce="netforce")

    for f in hull_files:
        assets[f"{object_name}_{f.name}"] = f.read_bytes()
    return mujoco.MjModel.from_xml_string(ET.tostring(root, encoding="unicode"), assets)
