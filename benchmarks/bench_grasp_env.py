"""Timings and contact-signal rates of the blind-grasping environment (``activetouch.sim.grasp_env``).

Usage: ``.venv/bin/python benchmarks/bench_grasp_env.py [--task grasp-box-1] [--seed 0] [--particles 100]
[--repeats 3] [--pokes 20]``

Measures (median wall time over ``--repeats``, plus CPU time, which is what a loaded machine still shows):
- ``rollout``: 100 particles from the task's two-mode prior (App. D-c), one planned poke of 15 waypoints into
  the box of a particle of the true mode; target <= 0.5 s on a 2-core CPU with ~20 particles touched;
- the replay of the executed poke (``rollout(states, obs)``), ``grasp_success`` of 100 particles, one
  ``step`` (poke), ``robot_points`` of 15 configurations;
- the contact signal's false-positive / false-negative rates per control period and per waypoint over
  ``--pokes`` random pokes into prior particles (truth: any robot geom in contact).
"""
from __future__ import annotations

import argparse
import math

import numpy as np

from activetouch.sim.grasp_env import PokeAction, make_grasp_env


def poke_waypoints(target: np.ndarray, approach_yaw: float, n: int = 15, standoff: float = 0.12,
                   overshoot: float = 0.03, height: float = 0.25) -> np.ndarray:
    """``(n, 4)`` ee waypoints: above a stand-off point, down to the target's height, then horizontally through
    ``target (3,)`` (ee tip) along ``approach_yaw``, ``overshoot`` beyond it (the guarded stop ends it)."""
    u = np.array([math.cos(approach_yaw), math.sin(approach_yaw), 0.0])
    p0 = target - standoff * u
    above = np.array([p0[0], p0[1], height])
    n_down = 4
    down = np.linspace(above, p0, n_down)
    across = np.linspace(p0, target + overshoot * u, n - n_down + 1)[1:]
    xyz = np.concatenate([down, across])
    return np.concatenate([xyz, np.full((len(xyz), 1), approach_yaw + math.pi / 2)], axis=1)


def prior_particles(means: np.ndarray, n: int, spec, rng) -> np.ndarray:
    """``(n, 3)`` from the equal-weight two-component GMM of App. D-c."""
    k = rng.integers(2, size=n)
    return means[k] + rng.normal(size=(n, 3)) * np.array([spec.sigma_pos, spec.sigma_pos, spec.sigma_yaw])


def point_in_box(state: np.ndarray, bounds: np.ndarray, rng, z_range=(0.04, 0.18)) -> np.ndarray:
    """A uniform point inside the box at SE(2) ``state`` (heights clipped to ``z_range``), world frame."""
    lo, hi = bounds
    p = rng.uniform(lo[:2] * 0.8, hi[:2] * 0.8)
    c, s = math.cos(state[2]), math.sin(state[2])
    return np.array([state[0] + c * p[0] - s * p[1], state[1] + s * p[0] + c * p[1], rng.uniform(*z_range)])


from activetouch.experiments.timing import timed  # noqa: E402  (median wall / CPU seconds)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", default="grasp-box-1")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--particles", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--pokes", type=int, default=40)
    args = ap.parse_args()

    env = make_grasp_env(args.task, seed=args.seed)
    rng = np.random.default_rng(args.seed)
    bounds = env.object.bounds.numpy()
    w, c, (obs, info) = timed(lambda: env.reset(), 1)
    print(f"reset: {w * 1e3:.0f} ms")
    means, truth = info["prior_means"], info["true_state"]
    P = prior_particles(means, args.particles, env.spec, rng)
    P[0] = truth
    # a poke into the box of a particle of the true mode (the planner's candidates poke into the belief)
    target = point_in_box(truth, bounds, rng)
    wp = poke_waypoints(target, approach_yaw=math.atan2(target[1], target[0] + 0.25))

    plan = env.plan_poke(wp)

    def plan_rollout():
        plan.__dict__.pop("_reference_states", None)  # time the robot-only reference run too
        return env.rollout_detailed(P, plan)

    w, c, res = timed(plan_rollout, args.repeats)
    st = env.rollout_stats
    print(f"rollout (planned poke, {plan.num_waypoints} waypoints, {len(plan.ctrl)} periods): {w:.3f} s wall, "
          f"{c:.3f} s cpu; particles simulated {int(res.simulated.sum())}/{len(P)}, guarded stops "
          f"{int((res.stop_waypoint >= 0).sum())}, moved > 1 mm "
          f"{int(((res.states[:, -1] - res.states.new_tensor(P)).norm(dim=1) > 1e-3).sum())}; "
          f"{st['particle_periods']} particle-periods in {st['calls']} mujoco.rollout calls")

    w, c, (obs, *_rest) = timed(lambda: (env.reset(), env.step(PokeAction(wp)))[1], 1)
    print(f"step (poke): {w * 1e3:.0f} ms; executed {obs.num_waypoints} waypoints, stopped early {obs.stopped_early}, "
          f"z {obs.z.astype(int).tolist()}")
    w, c, res = timed(lambda: env.rollout_detailed(P, obs), args.repeats)
    print(f"rollout (executed poke replay): {w:.3f} s wall, {c:.3f} s cpu; simulated {int(res.simulated.sum())}")

    w, c, ok = timed(lambda: env.grasp_success(P, truth), args.repeats)
    print(f"grasp_success ({len(P)} particles): {w:.3f} s wall, {c:.3f} s cpu; success share "
          f"{float(ok.float().mean()):.2f}, {env.rollout_stats['particle_periods']} particle-periods")

    q15 = np.repeat(obs.q[:1], 15, axis=0)
    for spacing in (0.01, 0.02):
        env.robot_points(q15[:1], spacing)  # build the surface sample once
        w, c, pts = timed(lambda: env.robot_points(q15, spacing), args.repeats)
        print(f"robot_points (15 configs, spacing {spacing}): {w * 1e3:.1f} ms, M = {pts.shape[1]}")

    # contact-signal rates over random pokes into prior particles
    fp = fn = n_free = n_con = 0
    wfp = wfn = w_free = w_con = 0
    for i in range(args.pokes):
        obs, info = env.reset(seed=args.seed + 1000 + i)
        x = info["true_state"] if i % 2 == 0 else prior_particles(info["prior_means"], 1, env.spec, rng)[0]
        tgt = point_in_box(x, bounds, rng)
        yaw = rng.uniform(-math.pi, math.pi)
        obs, *_ = env.step(PokeAction(poke_waypoints(tgt, yaw)))
        tc, zs = obs.true_contact_samples, obs.z_samples
        fp += int((zs & ~tc).sum())
        n_free += int((~tc).sum())
        fn += int((~zs & tc).sum())
        n_con += int(tc.sum())
        tcw = tc[obs.z_period]  # the true contact at the period each z was read
        wfp += int((obs.z & ~tcw).sum())
        w_free += int((~tcw).sum())
        wfn += int((~obs.z & tcw).sum())
        w_con += int(tcw.sum())
    print(f"contact signal over {args.pokes} pokes: per period FP {fp / max(n_free, 1):.3f} ({n_free} free), "
          f"FN {fn / max(n_con, 1):.3f} ({n_con} in contact); per waypoint FP {wfp / max(w_free, 1):.3f} ({w_free}), "
          f"FN {wfn / max(w_con, 1):.3f} ({w_con})")
    env.close()


if __name__ == "__main__":
    main()
