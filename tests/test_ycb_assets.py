"""The six packaged YCB clutter objects: meshes, shipped convex decompositions and a MuJoCo drop test."""
import json
import xml.etree.ElementTree as ET

import mujoco
import numpy as np
import pytest
import trimesh

from activetouch import objects
from activetouch.sim.scene import OBJECT_PHYSICS, hull_dir, load_hulls

#: extents x, y, z (mm) from the shared objects README (assets/objects/README.md has the same table).
EXTENTS_MM = {
    "mustard_bottle": (97.2, 66.6, 191.3),
    "bleach_cleanser": (102.4, 67.7, 250.6),
    "tomato_soup_can": (67.9, 67.7, 101.9),
    "sugar_box": (49.5, 94.2, 176.0),
    "potted_meat_can": (102.1, 60.1, 83.5),
    "foam_brick": (52.6, 77.9, 51.2),
}
NAMES = list(EXTENTS_MM)


@pytest.fixture(scope="module", params=NAMES)
def loaded(request):
    name = request.param
    return name, objects.load(name), load_hulls(name)


def test_registered():
    assert set(NAMES) <= set(objects.available())
    assert set(NAMES) <= set(OBJECT_PHYSICS)
    assert OBJECT_PHYSICS["foam_brick"].mass == pytest.approx(0.028)


def test_mesh(loaded):
    name, obj, _ = loaded
    m = obj.mesh
    assert obj.name == name and obj.mesh_path.name == f"{name}.obj"
    assert "shared" not in obj.mesh_path.parts  # packaged copy, not the shared data folder
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0
    np.testing.assert_allclose(m.extents, np.array(EXTENTS_MM[name]) / 1000, atol=1e-3)
    # base-centred frame
    assert abs(m.bounds[0, 2]) < 1e-6
    np.testing.assert_allclose(m.bounds.mean(axis=0)[:2], 0.0, atol=1e-4)


def test_hulls(loaded):
    name, obj, hulls = loaded
    m = obj.mesh
    info = json.loads((hull_dir(name) / "hulls.json").read_text())
    assert info["object"] == name and info["method"] == "coacd"
    assert info["num_hulls"] == len(hulls) and 1 <= len(hulls) <= 24
    for h in hulls:
        # closed, outward-wound and convex up to the 6-decimal rounding of the OBJ coordinates
        assert h.is_watertight and h.is_winding_consistent and h.volume > 0
        ch = h.convex_hull
        assert h.volume == pytest.approx(ch.volume, rel=1e-3)
        dist = np.asarray(h.vertices) @ ch.face_normals.T - np.einsum("ij,ij->i", ch.face_normals,
                                                                      ch.triangles[:, 0])
        assert dist.max() < 1e-5  # every vertex inside or on every face plane of its hull
    lo = np.min([h.bounds[0] for h in hulls], axis=0)
    hi = np.max([h.bounds[1] for h in hulls], axis=0)
    np.testing.assert_allclose(np.stack([lo, hi]), m.bounds, atol=5e-3)
    ratio = sum(h.volume for h in hulls) / m.volume
    assert 0.9 <= ratio <= 1.6, ratio


def _drop_model(name: str, obj, drop: float) -> mujoco.MjModel:
    """A plane and the object as a free body made of its shipped hull meshes, base ``drop`` m above it."""
    phys = OBJECT_PHYSICS[name]
    files = sorted(hull_dir(name).glob("hull_*.obj"))
    mp = obj.mesh.copy()
    mp.density = phys.mass / mp.volume
    com, inertia = mp.center_mass, mp.moment_inertia
    root = ET.Element("mujoco", model=f"drop_{name}")
    ET.SubElement(root, "option", timestep="0.002", integrator="implicitfast", cone="elliptic", impratio="2")
    asset = ET.SubElement(root, "asset")
    world = ET.SubElement(root, "worldbody")
    ET.SubElement(world, "geom", name="floor", type="plane", size="1 1 0.1", friction="0.5 0.005 0.0001")
    body = ET.SubElement(world, "body", name="object", pos=f"0 0 {drop}")
    ET.SubElement(body, "freejoint", name="object_free")
    ET.SubElement(body, "inertial", pos=" ".join(f"{x:.6g}" for x in com), mass=f"{phys.mass}",
                  fullinertia=" ".join(f"{x:.6g}" for x in (inertia[0, 0], inertia[1, 1], inertia[2, 2],
                                                             inertia[0, 1], inertia[0, 2], inertia[1, 2])))
    for i, f in enumerate(files):
        ET.SubElement(asset, "mesh", name=f"hull_{i}", file=f.name)
        ET.SubElement(body, "geom", name=f"hull_{i}", type="mesh", mesh=f"hull_{i}", condim="4",
                      friction=f"{phys.friction} {phys.torsional} 0.0001")
    assets = {f.name: f.read_bytes() for f in files}
    return mujoco.MjModel.from_xml_string(ET.tostring(root, encoding="unicode"), assets)


def test_drop_on_plane(loaded):
    name, obj, hulls = loaded
    model = _drop_model(name, obj, drop=0.02)
    assert model.ngeom == 1 + len(hulls)
    data = mujoco.MjData(model)
    mujoco.mj_step(model, data, nstep=int(round(1.0 / model.opt.timestep)))
    pos, quat = data.qpos[:3].copy(), data.qpos[3:7].copy()
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, quat)
    rot = rot.reshape(3, 3)
    verts = np.concatenate([np.asarray(h.vertices) for h in hulls])
    lowest = float((verts @ rot.T + pos)[:, 2].min())
    speed = float(np.linalg.norm(data.qvel[:3]))
    assert abs(lowest) < 5e-3, (name, lowest)
    assert speed < 0.01, (name, speed)
    assert rot[2, 2] > 0.99, (name, rot[2, 2])  # still standing as placed
