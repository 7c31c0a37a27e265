"""The dense-clutter environment (visuo-tactile paper, Sec. III-A): piles, segmented depth views, guarded touches,
pushes and grasps in MuJoCo. Properties with margins (physics), no episode outcomes."""
import math

import mujoco
import numpy as np
import pytest
import torch

from activetouch import objects
from activetouch.sim.clutter_env import (ClutterEnv, ClutterTaskSpec, PickAction, PushAction, StopAction,
                                         TouchAction, ViewAction)
from activetouch.sim.clutter_scene import GROUP_TRANSPARENT, build_clutter_scene
from activetouch.sim.clutter_tasks import CLUTTER_TASKS, get_clutter_spec, make_clutter_env
from activetouch.sim.robot import yaw_rotation


def _surface_distance(name: str, T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Unsigned distance (m) of world points ``(N, 3)`` to object ``name``'s mesh at pose ``T``."""
    import trimesh

    mesh = objects.load(name).mesh
    local = (pts - T[:3, 3]) @ T[:3, :3]
    _, d, _ = trimesh.proximity.closest_point(mesh, local)
    return np.asarray(d)


@pytest.fixture(scope="module")
def env():
    e = make_clutter_env("clutter-mustard", depth_noise_std=0.0, seg_boundary_noise=0.0)
    e.reset(0)
    return e


def test_scene_compiles_with_a_transparent_target():
    m = build_clutter_scene(["mustard_bottle", "tomato_soup_can", "sugar_box"], transparent_target=True)
    vis = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "obj_0_visual")
    assert m.geom_group[vis] == GROUP_TRANSPARENT and m.geom_contype[vis] == 0
    other = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "obj_1_visual")
    assert m.geom_group[other] != GROUP_TRANSPARENT
    hull = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "obj_0_hull_0")
    assert m.geom_contype[hull] != 0  # solid to touch
    with pytest.raises(ValueError, match="unknown objects"):
        build_clutter_scene(["mustard_bottle", "teapot"])


def test_spec_checks():
    with pytest.raises(ValueError, match="num_clutter"):
        ClutterTaskSpec("x", num_clutter=(5, 3))
    with pytest.raises(ValueError, match="exceeds"):
        ClutterTaskSpec("x", num_clutter=(2, 20))
    with pytest.raises(ValueError, match="unknown ClutterTaskSpec fields"):
        get_clutter_spec("clutter-mustard", nonsense=1)
    assert {"clutter-mustard", "clutter-transparent"} <= set(CLUTTER_TASKS)


def test_pile_is_deterministic_upright_and_at_rest(env):
    P0 = env.object_poses()
    n = len(env.names) - 1
    lo, hi = env.spec.num_clutter
    assert lo <= n <= hi and env.names[0] == "mustard_bottle"
    assert len(set(env.names[1:])) == n and "mustard_bottle" not in env.names[1:]
    tilt = math.degrees(math.acos(P0[0, 2, 2]))
    assert tilt < 15.0
    assert np.linalg.norm(P0[0, :2, 3] - np.asarray(env.spec.pile_centre)) < 0.05
    speeds = [np.linalg.norm(env.data.qvel[a:a + 3]) for a in env._obj_vadr]
    assert max(speeds) < 0.02
    other = make_clutter_env("clutter-mustard", depth_noise_std=0.0, seg_boundary_noise=0.0)
    other.reset(0)
    assert other.names == env.names
    np.testing.assert_allclose(other.object_poses(), P0, atol=1e-9)


def test_view_segments_the_target_surface(env):
    T = env.true_pose()
    c = T[:3, 3] + np.array([0, 0, 0.1])
    obs, _, term, trunc, info = env.step(ViewAction(tuple(c + [-0.3, 0.1, 0.4]), tuple(c)))
    assert obs.kind == "view" and not term
    H, W = env.spec.camera_height, env.spec.camera_width
    assert obs.seg.shape == (H, W) and obs.cloud.shape == (H, W, 3)
    assert len(obs.points) > 30
    d = _surface_distance("mustard_bottle", T, obs.points)
    assert np.percentile(d, 95) < 0.002  # noise-free depth: the points lie on the target's mesh
    # every object's pixels lie on that object's surface
    for lab in set(np.unique(obs.seg)) - {-1, 0}:
        pts = obs.cloud[obs.seg == lab]
        dd = _surface_distance(env.names[lab], env.object_poses()[lab], pts)
        assert np.median(dd) < 0.002


def test_transparent_target_is_segmented_but_has_no_depth():
    e = make_clutter_env("clutter-transparent", depth_noise_std=0.0, seg_boundary_noise=0.0)
    e.reset(0)
    T = e.true_pose()
    c = T[:3, 3] + np.array([0, 0, 0.1])
    obs, *_ = e.step(ViewAction(tuple(c + [-0.3, 0.0, 0.4]), tuple(c)))
    assert (obs.seg == 0).sum() > 30  # the segmentation sees the glass
    if len(obs.points):  # the depth behind the glass: nowhere near the target's surface
        d = _surface_distance("mustard_bottle", T, obs.points)
        assert np.median(d) > 0.01


def _touch_face(env, sign: float):
    """A TouchAction at the target's +-x bounding-box face (object frame), 10 cm above the table."""
    T = env.true_pose()
    lo, hi = (b.numpy() for b in env.object.bounds)
    face = hi[0] if sign > 0 else lo[0]
    p_local = np.array([face + sign * 0.05, (lo[1] + hi[1]) / 2, 0.10])
    start = T[:3, :3] @ p_local + T[:3, 3]
    d = -sign * T[:3, 0]
    return TouchAction(tuple(start), tuple(d / np.linalg.norm(d)), 0.15)


def test_guarded_touch_records_target_surface_points():
    e = make_clutter_env("clutter-mustard", depth_noise_std=0.0, seg_boundary_noise=0.0, num_clutter=(0, 0))
    e.reset(1)
    T0 = e.true_pose()
    for sign in (1.0, -1.0):
        obs, *_ = e.step(_touch_face(e, sign))
        assert obs.kind == "touch" and obs.success and obs.contact_label == 0
        assert len(obs.points) >= 1
        assert _surface_distance("mustard_bottle", e.true_pose(), obs.points).max() < 0.003
    # a guarded touch barely moves the target
    assert np.linalg.norm(e.true_pose()[:3, 3] - T0[:3, 3]) < 0.005
    # a ray that misses everything: no contact
    far = TouchAction((T0[0, 3], T0[1, 3] + 0.3, 0.1), (0.0, 1.0, 0.0), 0.1)
    obs, *_ = e.step(far)
    assert not obs.success and len(obs.points) == 0 and obs.contact_label == -1


def _lone_can(seed: int = 0):
    """Target alone at the pile centre plus a soup can put 16 cm to its side (a known, free placement)."""
    e = ClutterEnv(ClutterTaskSpec("t", target="mustard_bottle", clutter_pool=("tomato_soup_can",),
                                   num_clutter=(1, 1), depth_noise_std=0.0, seg_boundary_noise=0.0))
    e.reset(seed)
    xy = np.asarray(e.spec.pile_centre) + np.array([0.0, -0.16])
    e._place(1, xy, yaw_rotation(0.0), 0.0005)
    mujoco.mj_forward(e.model, e.data)
    e._simulate(0.5)
    return e, xy


def test_pick_lifts_a_free_can_out_of_the_workspace_and_detects_a_missed_grasp():
    e, xy = _lone_can()
    top = e.object_top(1)
    obs, *_ = e.step(PickAction(1, (xy[0], xy[1], top / 2), 0.0, 0.068))
    assert obs.kind == "pick" and obs.success, e.last_pick_failure
    assert np.linalg.norm(e.object_poses()[1][:2, 3] - np.asarray(e.spec.dropoff)) < 0.1
    # a grasp at an empty place closes on nothing: the contact check reports failure
    obs, *_ = e.step(PickAction(1, (xy[0] + 0.05, xy[1] - 0.1, 0.04), 0.0, 0.068))
    assert not obs.success


def test_push_moves_the_can_along_the_push():
    e, xy = _lone_can()
    P0 = e.object_poses()[1]
    start = (xy[0], xy[1] + 0.034 + 0.03, 0.04)  # 3 cm off the can's +y side, pushing along -y
    obs, *_ = e.step(PushAction(1, start, (0.0, -1.0, 0.0), 0.10))
    dy = e.object_poses()[1][1, 3] - P0[1, 3]
    assert obs.kind == "push" and obs.success
    assert dy < -0.03  # moved away along the push
    assert np.linalg.norm(e.true_pose()[:2, 3] - np.asarray(e.spec.pile_centre)) < 0.05  # the target stayed


def test_stop_terminates_and_actions_are_validated(env):
    with pytest.raises(ValueError, match="unit vector"):
        TouchAction((0, 0, 0.1), (1.0, 1.0, 0.0))
    with pytest.raises(ValueError, match="label"):
        env.step(PushAction(0, (0.3, 0.0, 0.05), (1.0, 0.0, 0.0)))
    with pytest.raises(ValueError, match="ViewAction.position"):
        ViewAction((0.0, float("nan"), 0.0), (0.0, 0.0, 0.0))
    obs, _, term, _, info = env.step(StopAction("done"))
    assert term and obs.kind == "stop" and info["stop_reason"] == "done"
    with pytest.raises(RuntimeError, match="ended"):
        env.step(ViewAction((0.0, 0.0, 0.5), (0.3, 0.0, 0.0)))
    assert torch.is_tensor(info["true_pose"]) and info["true_pose"].shape == (4, 4)


def test_every_gripper_yaw_is_reached_up_to_a_half_turn():
    """The gripper is symmetric under a half turn; the wrist's last joint is not: from the parked arm half the yaws
    are out of its range. ``_reachable_yaw`` picks the half turn the arm reaches, so the pads line up as asked."""
    e = make_clutter_env("clutter-mustard", depth_noise_std=0.0, seg_boundary_noise=0.0, num_clutter=(0, 0))
    e.reset(seed=0)
    pos = np.array([0.3, -0.25, 0.25])
    short = 0
    for wanted in np.linspace(-math.pi, math.pi, 9)[:-1] + 0.1:
        e._line(np.array([*pos, e.ee_state()[3]]), 0.0, e.spec.max_ee_step)
        plain = e.ik.solve(e.current_q(), pos, yaw_rotation(wanted), iterations=60)
        short += e.ik.error(plain, pos, yaw_rotation(wanted))[1] > 0.1  # the literal yaw is out of reach
        c = e._reachable_yaw(pos, float(wanted))
        assert abs(((c - wanted) % math.pi + math.pi / 2) % math.pi - math.pi / 2) < 1e-9  # wanted, mod pi
        e._line(np.array([*pos, c]), 0.0, e.spec.max_ee_step)
        e._hold(10)
        got = float(e.ee_state()[3])
        assert abs(((got - wanted) + math.pi / 2) % math.pi - math.pi / 2) < 0.05, (wanted, c, got)
    assert short >= 1  # the case the choice exists for occurs on this path


def test_camera_calibration_error_moves_every_view_rigidly():
    """A miscalibrated camera (the clutter-miscal-* tasks): the same scene's view, with the same depth noise, comes
    back turned about the pile centre and shifted by the set amounts; touches are not affected (the arm's frame)."""
    views = {}
    for err in ((0.0, 0.0), (0.01, 2.0)):
        e = make_clutter_env("clutter-mustard", seg_boundary_noise=0.0, camera_calibration_error=err)
        e.reset(3)
        c = e.true_pose()[:3, 3] + np.array([0, 0, 0.1])
        obs, *_ = e.step(ViewAction(tuple(c + [-0.3, 0.1, 0.4]), tuple(c)))
        views[err] = obs.cloud.reshape(-1, 3)
    a, b = views[(0.0, 0.0)], views[(0.01, 2.0)]
    hit = np.isfinite(a).all(1)
    assert hit.sum() > 1000 and np.array_equal(hit, np.isfinite(b).all(1))
    a, b = a[hit], b[hit]
    # rigid: pairwise distances kept; moved: by about 1 cm plus up to 2 deg x 0.3 m about the pile centre
    i = np.random.default_rng(0).integers(0, len(a), (500, 2))
    assert np.allclose(np.linalg.norm(a[i[:, 0]] - a[i[:, 1]], axis=1),
                       np.linalg.norm(b[i[:, 0]] - b[i[:, 1]], axis=1), atol=1e-9)
    moved = np.linalg.norm(b - a, axis=1)
    assert 0.002 < np.median(moved) < 0.025
    # the fitted rigid motion (Kabsch) turns by 2 deg
    ca, cb = a.mean(0), b.mean(0)
    U, _, Vt = np.linalg.svd((a - ca).T @ (b - cb))
    R = Vt.T @ U.T
    assert math.degrees(math.acos(np.clip((np.trace(R) - 1) / 2, -1, 1))) == pytest.approx(2.0, abs=1e-6)
    with pytest.raises(ValueError, match="camera_calibration_error"):
        ClutterTaskSpec("x", camera_calibration_error=(-0.01, 0.0))
    assert CLUTTER_TASKS["clutter-miscal-mustard"].camera_calibration_error == (0.008, 1.0)
