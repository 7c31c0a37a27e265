"""Tests of activetouch.sim: determinism, pushing + tactile sensing, camera, clipping, collision geometry."""
from __future__ import annotations


import mujoco
import numpy as np
import pytest
import torch

from activetouch.geometry.transforms import invert, transform_points
from activetouch.sim import make, registered
from activetouch.sim.robot import gripper_points
from activetouch.sim.scene import build_scene


@pytest.fixture(scope="module")
def env():
    return make("mug-0", seed=0)


def _sdf_world(env, x: torch.Tensor, T) -> torch.Tensor:
    xo = transform_points(invert(torch.as_tensor(T, dtype=torch.float32)), x.float())
    v, _ = env.object.sdf(xo)
    return v


def _drive_to(env, xy, max_steps=10):
    """Planar moves toward ``xy`` (no yaw); returns the last step's outputs."""
    out = None
    for _ in range(max_steps):
        ee = env.ee_state()
        d = (np.asarray(xy) - ee[:2]) / env.action_scale[0]
        if np.abs(d).max() < 0.05:
            break
        out = env.step(np.array([*np.clip(d, -1, 1), 0.0]))
    return out


def test_registry_has_nine_tasks():
    assert sorted(registered()) == sorted(f"{o}-{i}" for o in ("mug", "drill", "box") for i in range(3))
    with pytest.raises(ValueError, match="unknown task"):
        make("teapot-0")


def test_same_seed_same_trajectory(env):
    actions = [np.array([0.0, -1.0, 0.0]), np.array([0.0, -1.0, 0.3]), np.array([1.0, -0.4, -0.3]),
               np.array([1.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])]
    runs = []
    for _ in range(2):
        obs, info = env.reset(seed=3)
        traj = [info["true_pose"].clone()]
        feats = [obs.features.positions.clone()]
        for u in actions:
            obs, _, _, _, info = env.step(u)
            traj.append(info["true_pose"].clone())
            feats.append(obs.features.positions.clone())
        runs.append((traj, feats, env.ee_state().copy()))
    for a, b in zip(runs[0][0], runs[1][0]):
        assert torch.equal(a, b)
    for a, b in zip(runs[0][1], runs[1][1]):
        assert torch.equal(a, b)
    np.testing.assert_array_equal(runs[0][2], runs[1][2])


def test_push_moves_object_and_tactile_points_on_surface(env):
    env.reset()
    T0 = env.true_pose()
    _drive_to(env, (0.33, -0.005))
    touched = 0
    for _ in range(3):
        obs, _, _, _, info = env.step(np.array([1.0, 0.0, 0.0]))
        surf = obs.features.surface.positions
        if len(surf):
            touched += 1
            v = _sdf_world(env, surf, info["true_pose"])
            assert v.abs().max().item() < 0.003 + 1e-5, "tactile surface point farther than 3 mm from the true surface"
            assert obs.in_contact
        # free gripper points are never inside the object
        free = obs.features.free.positions
        assert _sdf_world(env, free, info["true_pose"]).min().item() > 0.003 - 1e-5
        assert obs.dT is not None
    moved = float(np.linalg.norm(env.true_pose()[:2, 3] - T0[:2, 3]))
    assert touched >= 2
    assert moved > 0.03, f"push moved the mug only {moved:.3f} m"


def test_tactile_points_are_the_contact_on_the_surface_not_the_pad_grid(env):
    # the rigid pads hold a 3-D grid of points; those within 3 mm of the object lie 0-3 mm outside it, a bias
    # that let a face placed through the band fit a contact patch better than the true pose. The sensor
    # reports each such pad point at its closest surface point (a conforming membrane's view of the contact).
    from activetouch.sim.tactile import TactileSensor

    env.reset()
    _drive_to(env, (0.33, -0.005))
    for _ in range(3):
        env.step(np.array([1.0, 0.0, 0.0]))
        if len(env.tactile.sense(env.ee_pose(), env.true_pose(), surface_only=True).surface) > 50:
            break
    ee, T = env.ee_pose(), env.true_pose()
    on = env.tactile.sense(ee, T, surface_only=True).surface
    grid = TactileSensor(env.object, band=env.tactile.band, project=False).sense(ee, T, surface_only=True).surface
    assert len(on) == len(grid) > 50
    v_on = _sdf_world(env, torch.as_tensor(on), T)
    v_grid = _sdf_world(env, torch.as_tensor(grid), T)
    # on the surface (a few points near a crease of the handle land up to ~0.5 mm off: one projection step)
    assert v_on.abs().median().item() < 1e-5 and v_on.abs().max().item() < 1e-3
    assert v_grid.mean().item() > 5e-4 and v_grid.abs().max().item() < 0.003 + 1e-5  # the outward bias removed
    # each contact point is its grid point moved along the SDF gradient, by its distance (within the 3 mm band)
    moved = np.linalg.norm(on - grid, axis=1)
    assert np.median(np.abs(moved - v_grid.abs().double().numpy())) < 1e-5 and moved.max() < 0.003 + 1e-5


def test_contacts_made_during_the_mini_steps_are_sensed(env):
    # brushing the mug sideways pushes it away within one action: without reading the pads after each mini step
    # the last contact step reported no surface point at all (touch read once, after settling)
    env.reset()
    _drive_to(env, (0.45, 0.22))
    contact_steps, points = 0, 0
    for _ in range(5):
        obs, _, _, _, info = env.step(np.array([0.0, -1.0, 0.0]))
        surf = obs.features.surface.positions
        if obs.in_contact:
            contact_steps += 1
            assert len(surf) > 0, "a step in contact reported no surface point"
        if len(surf):  # carried with the object to its pose at the end of the step
            points += len(surf)
            assert _sdf_world(env, surf, info["true_pose"]).abs().max().item() < 0.003 + 1e-4
    assert contact_steps >= 2 and points > 100


def test_dT_is_the_observed_object_motion(env):
    env.reset()
    _drive_to(env, (0.33, 0.0))
    moved = False
    for _ in range(2):
        T_before = torch.as_tensor(env.true_pose(), dtype=torch.float32)
        obs, _, _, _, info = env.step(np.array([1.0, 0.0, 0.0]))
        torch.testing.assert_close(obs.dT @ T_before, info["true_pose"], atol=1e-4, rtol=0)
        moved = moved or not torch.allclose(obs.dT, torch.eye(4), atol=1e-3)
    assert moved


def test_camera_free_points_never_inside_object_and_handle_hidden(env):
    obs, info = env.reset()
    T = info["true_pose"]
    free = obs.features.free.positions
    assert len(free) > 1000
    # only points near the object can be inside it: query those exactly
    xo = transform_points(invert(T), free)
    lo, up = env.object.bounds
    near = ((xo >= lo - 0.01) & (xo <= up + 0.01)).all(dim=1)
    assert near.sum() > 10
    v, _ = env.object.sdf(xo[near])
    assert v.min().item() > 0.0, "a camera free point lies inside the object"
    surf = obs.features.surface.positions
    assert info["camera_surface_points"] > 50
    vs, _ = env.object.sdf(transform_points(invert(T), surf))
    assert vs.abs().max().item() < 1e-3
    # the handle (object x > 31 mm, beyond the body's outer wall) is not seen by the camera
    so = transform_points(invert(T), surf)
    assert int((so[:, 0] > 0.031).sum()) == 0


def test_occluded_camera_does_not_see_drill():
    e = make("drill-0")
    obs, info = e.reset()
    assert info["camera_surface_points"] == 0
    assert len(obs.features.free) > 1000


def test_bad_and_out_of_range_actions(env):
    env.reset()
    with pytest.raises(ValueError, match="NaN"):
        env.step(np.array([np.nan, 0.0, 0.0]))
    with pytest.raises(ValueError, match="shape"):
        env.step(np.array([0.1, 0.2, 0.3, 0.4]))
    ee0 = env.ee_state()
    _, _, _, _, info = env.step(np.array([0.0, -5.0, 0.0]))  # clipped to -1: 80 mm
    assert info["target_ee"][1] == pytest.approx(ee0[1] - 0.08, abs=1e-9)
    assert abs(env.ee_state()[1] - (ee0[1] - 0.08)) < 0.005


def test_unreachable_command_is_clipped_and_gripper_moves_continuously(env):
    env.reset()
    prev = env.ee_state()
    xs = []
    for _ in range(8):  # far beyond the arm's reach (x > 0.6 m at y = 0.22 is out of reach)
        _, _, _, _, info = env.step(np.array([1.0, 0.0, 0.0]))
        ee = env.ee_state()
        assert np.linalg.norm(ee[:2] - prev[:2]) <= 0.08 + 0.01  # never teleports
        assert ee[0] <= 0.8 + 1e-6 and abs(ee[2] - env.spec.ee_height) < 0.01
        xs.append(ee[0])
        prev = ee
    assert not info["reached"]  # the last target was clipped by the arm's reach
    assert xs[-1] < info["target_ee"][0] - 0.02
    assert abs(xs[-1] - xs[-2]) < 0.01  # stays at the edge of reach


def test_object_never_passes_through_gripper(env):
    env.reset()
    _drive_to(env, (0.33, 0.0))
    pads, _ = gripper_points(0.004, pads_only=True)
    for _ in range(6):  # keep pushing, also past the edge of reach
        env.step(np.array([1.0, 0.0, 0.0]))
        E = torch.as_tensor(env.ee_pose(), dtype=torch.float32)
        v = _sdf_world(env, transform_points(E, pads), env.true_pose())
        assert v.min().item() > -0.004, f"pad penetrates the object by {-v.min().item():.4f} m"
        # the mug stays in front of the pads (it was pushed, not passed through)
        assert env.true_pose()[0, 3] > env.ee_state()[0]


def _probe_contacts(model, data, probe_geom, object_geoms, path):
    hits = []
    for p in path:
        data.mocap_pos[0] = p
        mujoco.mj_forward(model, data)
        hit = False
        for i in range(data.ncon):
            c = data.contact[i]
            if (c.geom1 == probe_geom and c.geom2 in object_geoms) or (c.geom2 == probe_geom and c.geom1 in object_geoms):
                hit = hit or c.dist < 0
        hits.append(hit)
    return np.array(hits)


def test_mug_handle_is_physically_there(env):
    model = build_scene("mug", env.object.mesh_path, probe_radius=0.003)
    data = mujoco.MjData(model)
    oj = model.joint("object_free")
    data.qpos[oj.qposadr[0]:oj.qposadr[0] + 7] = [0.4, 0.0, 0.0, 1, 0, 0, 0]
    probe = model.geom("probe").id
    obj_geoms = {g for g in range(model.ngeom) if model.geom_bodyid[g] == model.body("object").id and model.geom_contype[g] == 2}
    ys = np.linspace(-0.06, 0.06, 61)
    # through the hole between handle and body (object frame x = 38 mm, z = 42 mm): free
    hole = _probe_contacts(model, data, probe, obj_geoms, [(0.4 + 0.038, y, 0.042) for y in ys])
    assert not hole.any(), "the probe through the handle hole collided: the hole is filled"
    # into the handle itself (x = 53.5 mm): stops on contact
    handle = _probe_contacts(model, data, probe, obj_geoms, [(0.4 + 0.0535, y, 0.042) for y in ys])
    assert handle.any(), "the probe passed through the handle: the handle is missing"
    first = int(np.argmax(handle))
    assert abs(ys[first]) < 0.03  # it hits near the handle (|y| < 30 mm), not somewhere else


def test_gripper_points_interface(env):
    h, mask = env.gripper_points()
    assert h.shape[1] == 3 and mask.dtype == torch.bool and mask.shape == (len(h),)
    assert 0 < int(mask.sum()) < len(h)
    # h_I is the pads: below the palm, at the front (tip) of the gripper
    assert h[mask][:, 2].max() <= 0.11 + 1e-6 and h[mask][:, 2].min() >= -1e-6
    assert env.action_scale == (0.08, 0.5)


def test_reachability_eq30_orders_points_by_reach():
    from activetouch.sim.reachability import ReachabilityConfig, compute_reachability

    pts = torch.tensor([[0.35, 0.0, 0.02], [0.8, 0.4, 0.02], [0.0, 0.0, 0.02]], dtype=torch.float64)
    r = compute_reachability(pts, ReachabilityConfig(yaws=(0.0,), num_retries=4))
    assert r.shape == (3,) and ((r >= 0) & (r <= 1)).all()
    assert r[0] > 0.97  # comfortably inside the reach: IK converges, error ~ 0
    assert r[1] < 0.6 and r[2] < 0.8  # far corner and too close to the base: large IK error
    with pytest.raises(ValueError):
        compute_reachability(torch.tensor([[float("nan"), 0.0, 0.0]]))
