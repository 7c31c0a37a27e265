"""MJCF builder for the rummaging scene (RUMI section V-A, Fig. 7).

Scene: a table whose top is the plane z = 0, a shelf with two side walls and a back wall, the KUKA
LBR iiwa on a fixed base behind the workspace, a gripper with two rigid soft-bubble stand-in pads
on the flange, and one free object.

The object has two kinds of geometry:
- collision: the shipped convex decomposition (``assets/objects/<name>/hulls/hull_*.obj``, made by
  ``scripts/decompose.py`` with CoACD). MuJoCo collides a mesh as its convex hull, which would
  fill the mug's handle hole; the union of convex parts keeps it.
- vision: the exact watertight mesh as a visual-only geom (contype 0, conaffinity 0, its own geom
  group ``GROUP_OBJECT_VISUAL``) that the ray-cast depth camera hits.

Collision bits: static (table, walls) = 1, object = 2, robot = 4. Pairs that collide: static-object,
robot-object, robot-static. The arm links 1-4 do not collide (they stay far above the table).
"""
from __future__ import annotations

import dataclasses
import functools
import pathlib
import tempfile
import xml.etree.ElementTree as ET

import mujoco
import numpy as np
import trimesh

from .robot import ASSET_DIR, BASE_POS, FLANGE_OFFSET, GRIPPER, GripperGeometry

__all__ = [
    "ObjectPhysics",
    "OBJECT_PHYSICS",
    "SceneLayout",
    "build_scene",
    "hull_dir",
    "load_hulls",
    "GROUP_STATIC",
    "GROUP_ROBOT",
    "GROUP_OBJECT_COLLISION",
    "GROUP_OBJECT_VISUAL",
    "ARM_JOINTS",
]

GROUP_STATIC = 0
GROUP_ROBOT = 1
GROUP_OBJECT_COLLISION = 2
GROUP_OBJECT_VISUAL = 3
ARM_JOINTS = tuple(f"lbr_iiwa_joint_{i}" for i in range(1, 8))
OBJECT_ASSETS = pathlib.Path(__file__).resolve().parents[1] / "assets" / "objects"


@dataclasses.dataclass(frozen=True)
class ObjectPhysics:
    """Mass (kg) and friction coefficients of a YCB object (YCB object list masses)."""

    mass: float
    friction: float = 0.5  # sliding friction against the table and pads
    torsional: float = 0.002


#: YCB masses: 025_mug 118 g, 035_power_drill 895 g, 003_cracker_box 411 g, 006_mustard_bottle 603 g,
#: 021_bleach_cleanser 1131 g, 005_tomato_soup_can 349 g, 004_sugar_box 514 g, 010_potted_meat_can 370 g,
#: 061_foam_brick 28 g.
OBJECT_PHYSICS = {
    "mug": ObjectPhysics(mass=0.118, friction=0.5),
    "drill": ObjectPhysics(mass=0.895, friction=0.5),
    "cracker_box": ObjectPhysics(mass=0.411, friction=0.4),
    "mustard_bottle": ObjectPhysics(mass=0.603, friction=0.5),
    "bleach_cleanser": ObjectPhysics(mass=1.131, friction=0.5),
    "tomato_soup_can": ObjectPhysics(mass=0.349, friction=0.5),
    "sugar_box": ObjectPhysics(mass=0.514, friction=0.5),
    "potted_meat_can": ObjectPhysics(mass=0.370, friction=0.5),
    "foam_brick": ObjectPhysics(mass=0.028, friction=0.7),
}


@dataclasses.dataclass(frozen=True)
class SceneLayout:
    """Static geometry (metres, world frame). Table top at z = 0."""

    table_lower: tuple[float, float] = (-0.55, -0.55)
    table_upper: tuple[float, float] = (1.05, 0.55)
    wall_y: float = 0.52  # side walls at y = +-wall_y (outside the workspace |y| <= 0.4)
    back_wall_x: float = 1.0  # back of the shelf
    wall_height: float = 0.35
    wall_thickness: float = 0.02
    wall_x_start: float = -0.05


def hull_dir(name: str) -> pathlib.Path:
    return OBJECT_ASSETS / name / "hulls"


def load_hulls(name: str) -> list[trimesh.Trimesh]:
    """The shipped convex parts of object ``name`` (object frame, metres)."""
    d = hull_dir(name)
    files = sorted(d.glob("hull_*.obj"))
    if not files:
        raise FileNotFoundError(f"no convex decomposition shipped for {name!r} in {d}; run scripts/decompose.py")
    return [trimesh.load(f, force="mesh", process=False) for f in files]


@functools.lru_cache(maxsize=1)
def _robot_xml() -> str:
    """The iiwa URDF converted to MJCF by MuJoCo itself (cached)."""
    txt = (ASSET_DIR / "model.urdf").read_text()
    i = txt.index(">", txt.index("<robot")) + 1
    txt = (txt[:i] + '<mujoco><compiler meshdir="meshes" strippath="true" balanceinertia="true" '
           'discardvisual="false"/></mujoco>' + txt[i:])
    model = mujoco.MjModel.from_xml_string(txt, _robot_assets())
    with tempfile.TemporaryDirectory() as tmp:
        path = pathlib.Path(tmp) / "robot.xml"
        mujoco.mj_saveLastXML(str(path), model)
        return path.read_text()


@functools.lru_cache(maxsize=1)
def _robot_assets() -> dict[str, bytes]:
    return {f.name: f.read_bytes() for f in (ASSET_DIR / "meshes").glob("*.stl")}


def _fmt(v) -> str:
    return " ".join(f"{float(x):.6g}" for x in np.ravel(v))


def _add_gripper(link7: ET.Element, g: GripperGeometry) -> None:
    """Gripper body in link 7, its frame = the ee frame (tip, z up along the gripper)."""
    body = ET.SubElement(link7, "body", name="gripper", pos=_fmt([0, 0, FLANGE_OFFSET + g.length]),
                         quat="0 1 0 0", gravcomp="1")
    ET.SubElement(body, "inertial", pos=_fmt(g.palm_centre), mass="0.8", diaginertia="0.002 0.002 0.002")
    common = dict(contype="4", conaffinity="3", group=str(GROUP_ROBOT), friction="0.8 0.005 0.0001",
                  solref="0.005 1")
    for i, c in enumerate(g.pad_centres):
        ET.SubElement(body, "geom", name=f"pad_{i}", type="box", size=_fmt(g.pad_half), pos=_fmt(c),
                      rgba="0.85 0.3 0.3 1", **common)
    ET.SubElement(body, "geom", name="palm", type="box", size=_fmt(g.palm_half), pos=_fmt(g.palm_centre),
                  rgba="0.3 0.3 0.3 1", **common)
    ET.SubElement(body, "geom", name="adaptor", type="cylinder",
                  size=_fmt([g.adaptor_radius, g.adaptor_half_height]), pos=_fmt(g.adaptor_centre),
                  rgba="0.3 0.3 0.3 1", **common)
    ET.SubElement(body, "site", name="ee", pos="0 0 0", size="0.005")


def build_scene(object_name: str, mesh_path: pathlib.Path | str, layout: SceneLayout = SceneLayout(),
                gripper: GripperGeometry = GRIPPER, timestep: float = 0.002,
                probe_radius: float | None = None, upright: bool = False) -> mujoco.MjModel:
    """Compile the scene for one object.

    Args:
        object_name: name of the object (selects hulls and physics).
        mesh_path: exact watertight mesh (object frame), used for the visual geom and the inertia.
        probe_radius: add a mocap body ``probe`` with a sphere of this radius that collides with the
            object like the robot does (for tests of the collision geometry).
        upright: keep the object upright (tasks with SE(2) pose search: mug, drill, as the paper assumes):
            joints slide x, slide y, slide z and hinge z (``object_x``, ``object_y``, ``object_z``,
            ``object_yaw``, consecutive in ``qpos``) instead of a free joint, so pushes cannot tip it over.
    Returns:
        the compiled ``MjModel``. Names: body ``object`` (free joint ``object_free`` or the upright joints), geom
        ``object_visual``, site ``ee``, actuators ``act_1..7``.
    """
    if object_name not in OBJECT_PHYSICS:
        raise ValueError(f"unknown object {object_name!r}; known: {sorted(OBJECT_PHYSICS)}")
    phys = OBJECT_PHYSICS[object_name]
    mesh_path = pathlib.Path(mesh_path)
    mesh = trimesh.load(mesh_path, force="mesh", process=False)
    hull_files = sorted(hull_dir(object_name).glob("hull_*.obj"))
    if not hull_files:
        raise FileNotFoundError(f"no convex decomposition for {object_name!r}; run scripts/decompose.py")

    root = ET.fromstring(_robot_xml())
    root.set("model", f"rummage_{object_name}")
    comp = root.find("compiler")
    comp.set("inertiafromgeom", "false")
    comp.attrib.pop("meshdir", None)
    opt = ET.Element("option", timestep=f"{timestep}", integrator="implicitfast", cone="elliptic",
                     impratio="2")
    root.insert(1, opt)
    ET.SubElement(root, "size", memory="40M")

    # ---------------------------------------------------------------- robot edits
    world = root.find("worldbody")
    base = ET.Element("body", name="iiwa_base", pos=_fmt(BASE_POS))
    for g in list(world.findall("geom")):
        world.remove(g)
        if g.get("contype") == "0":  # keep the visual copy only
            g.set("group", str(GROUP_ROBOT))
            base.append(g)
    ET.SubElement(base, "inertial", pos="0 0 0.05", mass="5", diaginertia="0.05 0.05 0.05")
    link1 = world.find("body")
    world.remove(link1)
    base.append(link1)
    world.append(base)
    for body in base.iter("body"):
        body.set("gravcomp", "1")
        geoms = body.findall("geom")
        for g in geoms:
            if g.get("contype") != "0":
                body.remove(g)  # drop the duplicate collision copy; keep one geom per link
        idx = int(body.get("name", "x_0").rsplit("_", 1)[-1]) if body.get("name", "").startswith("lbr_iiwa_link") else 0
        for g in body.findall("geom"):
            g.set("group", str(GROUP_ROBOT))
            if idx >= 5:  # forearm, wrist and flange may touch the object or walls
                g.set("contype", "4")
                g.set("conaffinity", "3")
    link7 = next(b for b in base.iter("body") if b.get("name") == "lbr_iiwa_link_7")
    _add_gripper(link7, gripper)

    # ---------------------------------------------------------------- static scene
    L = layout
    world.insert(0, ET.Element("light", pos="0.3 0 2.0", dir="0 0 -1", directional="true"))
    static = dict(contype="1", conaffinity="6", group=str(GROUP_STATIC), friction="0.5 0.005 0.0001")
    tx = (L.table_lower[0] + L.table_upper[0]) / 2
    ty = (L.table_lower[1] + L.table_upper[1]) / 2
    ET.SubElement(world, "geom", name="table", type="box", pos=_fmt([tx, ty, -0.025]),
                  size=_fmt([(L.table_upper[0] - L.table_lower[0]) / 2, (L.table_upper[1] - L.table_lower[1]) / 2,
                             0.025]), rgba="0.75 0.65 0.5 1", **static)
    wl = (L.back_wall_x - L.wall_x_start) / 2
    for s, name in ((1, "wall_left"), (-1, "wall_right")):
        ET.SubElement(world, "geom", name=name, type="box",
                      pos=_fmt([L.wall_x_start + wl, s * (L.wall_y + L.wall_thickness / 2), L.wall_height / 2]),
                      size=_fmt([wl, L.wall_thickness / 2, L.wall_height / 2]), rgba="0.6 0.55 0.45 1", **static)
    ET.SubElement(world, "geom", name="wall_back", type="box",
                  pos=_fmt([L.back_wall_x + L.wall_thickness / 2, 0, L.wall_height / 2]),
                  size=_fmt([L.wall_thickness / 2, L.wall_y + L.wall_thickness, L.wall_height / 2]),
                  rgba="0.6 0.55 0.45 1", **static)

    # ---------------------------------------------------------------- object
    asset = root.find("asset")
    ET.SubElement(asset, "mesh", name="object_visual", file=f"{object_name}_visual.obj")
    for i, f in enumerate(hull_files):
        ET.SubElement(asset, "mesh", name=f"object_hull_{i}", file=f"{object_name}_{f.name}")
    # inertia of the exact solid, uniform density, scaled to the real mass
    mp = mesh.copy()
    mp.density = phys.mass / mesh.volume
    com = mp.center_mass
    inertia = mp.moment_inertia  # about the centre of mass, object axes
    obj = ET.SubElement(world, "body", name="object", pos="0 0 0" if upright else "0.4 0 0")
    if upright:
        for name, kind, axis in (("object_x", "slide", "1 0 0"), ("object_y", "slide", "0 1 0"),
                                 ("object_z", "slide", "0 0 1"), ("object_yaw", "hinge", "0 0 1")):
            ET.SubElement(obj, "joint", name=name, type=kind, axis=axis, damping="0", armature="0")
    else:
        ET.SubElement(obj, "freejoint", name="object_free")
    ET.SubElement(obj, "inertial", pos=_fmt(com), mass=f"{phys.mass}",
                  fullinertia=_fmt([inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1], inertia[0, 2],
                                    inertia[1, 2]]))
    for i in range(len(hull_files)):
        ET.SubElement(obj, "geom", name=f"object_hull_{i}", type="mesh", mesh=f"object_hull_{i}",
                      contype="2", conaffinity="5", group=str(GROUP_OBJECT_COLLISION),
                      friction=f"{phys.friction} {phys.torsional} 0.0001", condim="4", rgba="0.2 0.5 0.9 0.5")
    ET.SubElement(obj, "geom", name="object_visual", type="mesh", mesh="object_visual", contype="0",
                  conaffinity="0", group=str(GROUP_OBJECT_VISUAL), rgba="0.2 0.4 0.9 1")

    if probe_radius is not None:
        probe = ET.SubElement(world, "body", name="probe", mocap="true", pos="0 0 1")
        ET.SubElement(probe, "geom", name="probe", type="sphere", size=f"{float(probe_radius)}", contype="4",
                      conaffinity="3", group=str(GROUP_ROBOT), rgba="0 1 0 1")

    # ---------------------------------------------------------------- actuators
    act = ET.SubElement(root, "actuator")
    gains = [(3000, 150), (3000, 150), (2000, 100), (2000, 100), (800, 30), (800, 30), (400, 15)]
    for i, (kp, kv) in enumerate(gains, start=1):
        ET.SubElement(act, "position", name=f"act_{i}", joint=f"lbr_iiwa_joint_{i}", kp=str(kp), kv=str(kv),
                      forcerange="-300 300")

    assets = dict(_robot_assets())
    assets[f"{object_name}_visual.obj"] = mesh_path.read_bytes()
    for f in hull_files:
        assets[f"{object_name}_{f.name}"] = f.read_bytes()
    xml = ET.tostring(root, encoding="unicode")
    return mujoco.MjModel.from_xml_string(xml, assets)
