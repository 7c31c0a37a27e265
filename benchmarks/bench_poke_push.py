"""How far the touch task's pokes push the box, and how well the particle rollouts follow it.

Usage: ``.venv/bin/python benchmarks/bench_poke_push.py [--tasks grasp-box-0 grasp-box-1] [--seeds 4] [--pokes 4]
[--set max_ee_step=0.002 ...]`` (or ``activetouch bench poke-push -- ...``).

Per seed, ``--pokes`` pokes in a row are drawn as the touch planner draws its candidates (``TouchIGPlanner.
sample_candidates``, a via-point spline into a point inside the box, backing off after a contact) with every
candidate aimed at the *true* box, and executed in ``GraspEnv``. Prints, over all pokes:

- how far each poke moved the box (median, 90th percentile, max, share above 2 mm), split into before the
  guard fired and during the hold after it (App. D-b's guarded stop);
- the largest ee force estimate of each poke (the guard's signal) at its median;
- the replay error: the true state before the poke rolled out under the executed controls (``env.rollout(x, obs)``,
  what the belief update does) against the true state after it (exact physics replays give ~0);
- the chaos of a poke: the largest distance between that replay and the replays of 8 states 1 mm / 0.5 deg away
  (what one poke does to a tight cluster of particles around the truth).

``--set FIELD=VALUE`` overrides ``GraspTaskSpec`` fields (e.g. ``max_ee_step``, ``guard_force``) to compare
controllers. Measured on this 2-core CPU (grasp-box-0/1, seeds 0-3, 4 pokes each, K = 36 waypoints, 11 s):
at the defaults the box moved median 4.1 mm, p90 11 mm, max 80 mm, 84 % of pokes above 2 mm (median 0.6 mm before
the guard fired, 3.0 mm during the hold after it); peak ee force estimate median 6.9 N, p90 55 N; replay error
median 0.00 mm but max 55 mm (a kick left the box sliding at 0.6 m/s when the next poke began: replays start
at rest); 1 mm-neighbour spread median 3.3 mm, p90 11 mm. At ``--set max_ee_step=0.001``
(0.05 m/s instead of 0.2 m/s): median push 1.1 mm (31 % above 2 mm), neighbour spread median 1.9 mm but p90 20 mm,
and one push of 257 mm that the replay missed by 268 mm.
"""
from __future__ import annotations

import argparse
import math
import time
from types import SimpleNamespace

import numpy as np
import torch

from activetouch.belief.touch_filter import TouchFilterConfig
from activetouch.cli import _key_values
from activetouch.planning.touch_ig import TouchIGPlanner, TouchPlannerConfig
from activetouch.sim.grasp_env import GraspEnv, PokeAction
from activetouch.sim.grasp_tasks import get_grasp_spec


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tasks", nargs="+", default=["grasp-box-0", "grasp-box-1"])
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--pokes", type=int, default=4, help="pokes in a row per seed")
    ap.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE", help="GraspTaskSpec overrides")
    a = ap.parse_args()
    if a.seeds < 1 or a.pokes < 1:
        raise SystemExit("--seeds and --pokes must be >= 1")
    try:  # the CLI's KEY=VALUE parsing (--planner / --belief), and the spec's own checks, before any work
        overrides = _key_values(a.set, "--set")
        specs = [get_grasp_spec(task, **overrides) for task in a.tasks]
    except (ValueError, TypeError) as e:
        raise SystemExit(f"bench_poke_push: {e}") from None
    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    moved, before, during, force, replay, spread = [], [], [], [], [], []
    t0 = time.perf_counter()
    for spec in specs:
        for seed in range(a.seeds):
            env = GraspEnv(spec, seed=seed)
            env.reset(seed=seed)
            planner = TouchIGPlanner(env, TouchFilterConfig(), TouchPlannerConfig(), seed=seed)
            for k in range(a.pokes):
                x = env.true_state().copy()
                # a stand-in belief with every particle at the truth: the candidate pokes the true box
                at_truth = SimpleNamespace(states=torch.tensor(np.tile(x, (100, 1))), weights=torch.full((100,), 0.01))
                poke = planner.sample_candidates(at_truth, env.ee_state(), retreat=k > 0)[0]
                obs, _, _, _, info = env.step(PokeAction(poke))
                planner._last_target = poke[-1, :3].copy()  # the back-off of the next poke, as in next_action
                after = env.true_state()
                traj = info["object_states"]  # (K'+1, 3): before, after each observation
                moved.append(1e3 * math.hypot(*(after[:2] - x[:2])))
                force.append(obs.contact_force)
                if obs.stopped_early and len(traj) >= 3:  # trigger observation, then the end of the hold
                    before.append(1e3 * math.hypot(*(traj[-2, :2] - x[:2])))
                    during.append(1e3 * math.hypot(*(traj[-1, :2] - traj[-2, :2])))
                near = np.vstack([x, x + np.c_[rng.normal(0, 1e-3, (8, 2)), rng.normal(0, math.radians(0.5), 8)]])
                r = env.rollout(torch.tensor(near), obs).numpy()[:, -1]
                replay.append(1e3 * math.hypot(*(r[0, :2] - after[:2])))
                spread.append(1e3 * float(np.hypot(r[1:, 0] - r[0, 0], r[1:, 1] - r[0, 1]).max()))
    m = np.asarray(moved)

    def q(v, p):
        return float(np.percentile(v, p)) if len(v) else float("nan")

    print(f"{len(m)} pokes ({', '.join(a.tasks)}; seeds 0-{a.seeds - 1}; overrides {overrides or 'none'}), "
          f"{time.perf_counter() - t0:.0f} s")
    print(f"  box moved (mm)            median {q(m, 50):6.1f}  p90 {q(m, 90):6.1f}  max {m.max():6.1f}  "
          f"share > 2 mm {(m > 2).mean():.2f}")
    print(f"  guarded stops {len(before):3d}: before the trigger median {q(before, 50):.1f} mm, during the hold "
          f"median {q(during, 50):.1f} mm (p90 {q(during, 90):.1f})")
    print(f"  peak ee force estimate (N) median {q(force, 50):.1f}  p90 {q(force, 90):.1f}")
    print(f"  replay of the true state   median error {q(replay, 50):.2f} mm  max {max(replay):.2f} mm")
    print(f"  1 mm-neighbour spread      median {q(spread, 50):.1f} mm  p90 {q(spread, 90):.1f} mm")


if __name__ == "__main__":
    main()
