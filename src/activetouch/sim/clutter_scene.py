"""MJCF builder of the dense-clutter scene (visuo-tactile clutter paper, Sec. III-A, Fig. 1).

Scene: the table (top at z = 0) and the iiwa with the two-pad gripper of the grasping scene
(``grasp_scene.robot_and_table_root``), one target object and several clutter objects, each a free body
(6 DoF: objects rest on and against each other, and pushes and grasps move them). Object ``i`` is body
``obj_<i>``; object 0 is the target.

Each object has two kinds of geoms:

* its convex parts (``scripts/decompose.py``) for collision, group ``GROUP_OBJECT_COLLISION`` (rays skip it);
* its exact watertight mesh, visual only (no contacts), group ``GROUP_OBJECT_VISUAL``, which the depth camera's
  rays hit. A **transparent** target puts this geom in ``GROUP_TRANSPARENT`` instead, which the camera skips:
  the rays pass through the target while its convex parts stay solid to touch (the paper's wineglass, where
  vision fails and touch works).

Collision bits as in the grasping scene: static = 1, object = 2, robot near the table (links 5-7, gripper) = 4,
robot far from it (links 1-4) = 8. Objects collide with the table, with each other and with every robot body.
A floor plane 0.76 m below the table catches anything pushed off it.
"""
from __future__ import annotations

import functools
import xml.etree.ElementTree as ET

import mujoco
import numpy as np
import trimesh

from .grasp_scene import GRASP_GRIPPER, GraspGripperGeometry, add_actuators, robot_and_table_root
from .scene import GROUP_OBJECT_COLLISION, GROUP_OBJECT_VISUAL, OBJECT_PHYSICS, _fmt, hull_dir

__all__ = ["GROUP_TRANSPARENT", "build_clutter_scene", "object_body_name"]

#: Geom group of a transparent target's visual mesh: the depth camera does not see it.
GROUP_TRANSPARENT = 4


@functools.lru_cache(maxsize=None)
def _inertial(mesh_path: str, mass: float) -> tuple[np.ndarray, np.ndarray]:
    """Centre of mass ``(3,)`` and inertia ``(3, 3)`` of the solid mesh at uniform density (read once)."""
    mesh = trimesh.load(mesh_path, force="mesh", process=False)
    mesh.density = mass / mesh.volume
    return np.asarray(mesh.center_mass), np.asarray(mesh.moment_inertia)


def object_body_name(i: int) -> str:
    return f"obj_{i}"


def build_clutter_scene(objects: list[str] | tuple[str, ...], transparent_target: bool = False,
                        gripper: GraspGripperGeometry = GRASP_GRIPPER, timestep: float = 0.002,
                        table_lower: tuple[float, float] = (-0.55, -0.7),
                        table_upper: tuple[float, float] = (1.05, 0.7)) -> mujoco.MjModel:
    """Compile the clutter scene (module docstring).

    Args:
        objects: packaged object names (keys of ``scene.OBJECT_PHYSICS``), the target first. A name may repeat.
        transparent_target: the camera's rays pass through the target (see module docstring).
        timestep: physics step (s).

    Returns:
        the compiled ``MjModel``: bodies ``obj_0..obj_{n-1}`` with free joints ``obj_<i>_free``, visual geoms
        ``obj_<i>_visual``, collision geoms ``obj_<i>_hull_<k>``; the robot's names as in
        ``grasp_scene.build_grasp_scene`` (site ``ee``, ``pad_0/1``, actuators ``act_1..7``, ``act_pad_0/1``).
    """
    from activetouch import objects as objects_mod

    names = list(objects)
    if not names:
        raise ValueError("objects must name at least the target")
    unknown = sorted({n for n in names if n not in OBJECT_PHYSICS})
    if unknown:
        raise ValueError(f"unknown objects {unknown}; known: {sorted(OBJECT_PHYSICS)}")
    root, world, assets = robot_and_table_root("clutter", gripper, timestep, table_lower, table_upper)
    ET.SubElement(world, "geom", name="floor", type="plane", pos="0 0 -0.76", size="3 3 0.1", contype="1",
                  conaffinity="2", group="0", rgba="0.5 0.5 0.5 1")
    asset = root.find("asset")
    done: dict[str, int] = {}
    palette = ((0.85, 0.55, 0.1), (0.2, 0.5, 0.9), (0.3, 0.7, 0.3), (0.7, 0.3, 0.6), (0.9, 0.8, 0.2),
               (0.4, 0.8, 0.8), (0.6, 0.4, 0.2), (0.8, 0.3, 0.3), (0.5, 0.5, 0.8))
    for i, name in enumerate(names):
        mesh_path = objects_mod.registry._assets_root() / name / f"{name}.obj"
        hull_files = sorted(hull_dir(name).glob("hull_*.obj"))
        if not hull_files:
            raise FileNotFoundError(f"no convex decomposition for {name!r}; run scripts/decompose.py")
        if name not in done:
            for k, f in enumerate(hull_files):
                ET.SubElement(asset, "mesh", name=f"{name}_hull_{k}", file=f"{name}_{f.name}")
                assets[f"{name}_{f.name}"] = f.read_bytes()
            ET.SubElement(asset, "mesh", name=f"{name}_mesh", file=f"{name}_visual.obj")
            assets[f"{name}_visual.obj"] = mesh_path.read_bytes()
            done[name] = len(hull_files)
        phys = OBJECT_PHYSICS[name]
        com, inertia = _inertial(str(mesh_path), phys.mass)
        body = ET.SubElement(world, "body", name=object_body_name(i), pos=_fmt([0.0, 2.0 + 0.5 * i, 0.5]))
        ET.SubElement(body, "freejoint", name=f"obj_{i}_free")
        ET.SubElement(body, "inertial", pos=_fmt(com), mass=f"{phys.mass}",
                      fullinertia=_fmt([inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1], inertia[0, 2],
                                        inertia[1, 2]]))
        rgb = palette[i % len(palette)] if i > 0 else (0.95, 0.35, 0.1)
        for k in range(done[name]):
            ET.SubElement(body, "geom", name=f"obj_{i}_hull_{k}", type="mesh", mesh=f"{name}_hull_{k}",
                          contype="2", conaffinity="15", group=str(GROUP_OBJECT_COLLISION),
                          friction=f"{phys.friction} {phys.torsional} 0.0001", condim="4",
                          rgba=_fmt([*rgb, 0.0]))
        transparent = transparent_target and i == 0
        ET.SubElement(body, "geom", name=f"obj_{i}_visual", type="mesh", mesh=f"{name}_mesh", contype="0",
                      conaffinity="0", density="0",
                      group=str(GROUP_TRANSPARENT if transparent else GROUP_OBJECT_VISUAL),
                      rgba=_fmt([*rgb, 0.25 if transparent else 1.0]))
    add_actuators(root, gripper)
    return mujoco.MjModel.from_xml_string(ET.tostring(root, encoding="unicode"), assets)
