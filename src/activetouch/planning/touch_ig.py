"""The touch paper's information-gathering controller (Sec. IV, Alg. 1, App. C, Sec. VI-A) and its baselines.

Each call of :meth:`TouchIGPlanner.next_action`:

1. **Grasp check** (App. D-d, e): the grasp primitive planned for the maximum-likelihood state is simulated on
   every particle (``env.grasp_success``); its weighted share is the success probability. At >= 0.8, or after
   the 15th localisation action, the planner returns the grasp (``GraspAction``), which ends the episode.
2. **Candidates** (Sec. IV-C, VI-A, App. C): ``N_samples = 20`` via-point splines from the current ee pose
   (zero velocity at both ends, :mod:`activetouch.planning.splines`). The last via-point pokes into the belief:
   a particle is importance-sampled from the weights and a point drawn uniformly inside the object at that
   particle's pose; the via-point before it lies ``approach_distance`` away from it horizontally in a random
   direction, so the poke comes from the side at the target's height (or from above when the path passes over
   a box). The arm follows the spline by IK (``env.plan_poke``); the guarded motion stops it at contact.
3. **Prediction**: every particle is rolled out in MuJoCo under each candidate's planned motion
   (``env.rollout``; particles the robot never comes near keep their state exactly), the distance between
   the whole robot and each predicted particle gives ``P(z = 1 | x)`` of Eq. 10 at every waypoint, and the
   hypothetical observation of particle ``j`` as the truth is contact iff the robot reaches it (``d <= tol``).
4. **Selection**: ``method="ig"``: Alg. 1's expected information gain (Eq. 6-9, shared-support entropy with
   ``rho = 5``), the trajectory truncated at its ``t*``; ``"uninformed"``: a random candidate (Sec. VI-A-b i);
   ``"max-contact"``: the candidate touching the most particles (ii). Both baselines execute the whole
   candidate (their metric has no ``t*``).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import numpy as np
import torch

__all__ = ["TouchPlannerConfig", "TouchIGPlanner", "near_robot_points"]


def near_robot_points(obj, robot_points: torch.Tensor, states: torch.Tensor, z: float = 0.0) -> torch.Tensor:
    """The robot points ``(K, M', 3)`` of ``robot_points (K, M, 3)`` that can lie within the object's cached SDF
    box at some particle state ``states (P, 3)`` or ``(P, K, 3)``: a point index is kept when, at some waypoint,
    the point lies inside the x-y box of all particle origins grown by the object's footprint radius plus the
    cache padding, below the object's top plus the padding. The others are farther than the padding from every
    particle, where Eq. 10 equals alpha_fp to 4e-7 (``robot_object_distance``'s ``far_inf``), so dropping them
    changes no distance below the padding. Written here because the whole arm (~10k points) sweeps the table while
    only its lowest links and the gripper come near a box: the cull cuts the SDF lookups ~5-10x."""
    from activetouch.belief.contact_model import footprint_radius

    r = footprint_radius(obj) + float(getattr(obj, "sdf_padding", 0.015))
    xy = states[..., :2].reshape(-1, 2).to(robot_points)
    lo, hi = xy.amin(0) - r, xy.amax(0) + r
    top = float(obj.bounds[1, 2]) + z + float(getattr(obj, "sdf_padding", 0.015))
    p = robot_points
    inside = ((p[..., 0] >= lo[0]) & (p[..., 0] <= hi[0]) & (p[..., 1] >= lo[1]) & (p[..., 1] <= hi[1])
              & (p[..., 2] <= top))  # (K, M)
    keep = inside.any(0)
    if not bool(keep.any()):
        keep[0] = True  # one far point: distances come back +inf (no contact possible), shapes stay valid
    return p[:, keep]


@dataclass(frozen=True)
class TouchPlannerConfig:
    """Paper values: ``num_samples`` (N_samples) = 20, ``rho`` = 5, ``grasp_threshold`` = 0.8,
    ``max_actions`` = 15 (App. D-e).

    Not in the paper (choices): ``waypoints`` K = 36 per candidate (the spline sampled at s = k/K). The waypoints
    are the time steps of Alg. 1 and of the filter: the environment reports one contact observation per waypoint
    and Eq. 10 re-weighs every particle there, so K sets how densely the free space a poke sweeps is observed (the
    paper's z_t at every time step of the trajectory). At K = 12 (about one observation per 2-3 cm of a poke) a particle
    that a poke passes through is seen by a few no-contact observations, each only 0.5 / 0.9 against it, and the
    kept history barely separated the true state from the belief's median particle (by < 1 nat over 15 pokes,
    grasp-box-1 seed 2); at K = 36 touch-ig grasped 20/30 instead of 15/30 and random pokes 15/30 instead of 18/30
    (Table I in README; planning ~4.5x slower, 7.7 s per poke at static prediction). ``--planner waypoints=12``
    is the earlier setting.
    ``approach_distance`` = 0.15 m; ``min_poke_height`` = 0.03 m (targets lower than this are raised so the
    pads stay clear of the table: a table contact would be a false object contact); ``contact_tolerance`` =
    2 mm (the robot "reaches" a particle for its hypothetical observation); ``grasp_min_weight`` = 1e-4:
    particles lighter than this are not simulated for the grasp probability (they fail; the estimate is low by
    at most P x 1e-4 = 0.01); ``predict`` = ``"rollout"`` (MuJoCo, the paper) or ``"static"`` (particles do not
    move in the prediction: only the weight term of Eq. 9 can change; cheaper). The approach direction is drawn
    within +-90 deg of the direction from the target to the gripper, so the transit stays on the robot's side of
    the target instead of cutting through the box; after a contact (guarded stop) every candidate first backs off
    ``retreat_distance`` = 4 cm against the last poke's direction and ``retreat_height`` = 2 cm up: a poke
    that starts pressing on the box would otherwise stop again at once.
    """

    num_samples: int = 20
    rho: int = 5
    grasp_threshold: float = 0.8
    max_actions: int = 15
    waypoints: int = 36
    approach_distance: float = 0.15
    min_poke_height: float = 0.03
    contact_tolerance: float = 0.002
    grasp_min_weight: float = 1e-4
    predict: str = "rollout"
    criterion: str = "ig"
    max_tries: int = 20  # draws per candidate until its poke target is in reach
    retreat_distance: float = 0.04
    retreat_height: float = 0.02
    truncate: bool = True  # Alg. 1: execute the chosen poke up to its t*; False: the whole poke (an ablation)

    def __post_init__(self):
        for name in ("num_samples", "rho", "max_actions", "waypoints", "max_tries"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"TouchPlannerConfig.{name} must be a positive int, got {v!r}")
        if not 0 < self.grasp_threshold <= 1:
            raise ValueError(f"grasp_threshold must lie in (0, 1], got {self.grasp_threshold}")
        for name in ("approach_distance", "min_poke_height", "contact_tolerance", "grasp_min_weight"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"TouchPlannerConfig.{name} must be a finite number >= 0, got {v!r}")
        if not isinstance(self.truncate, bool):
            raise ValueError(f"TouchPlannerConfig.truncate must be true or false, got {self.truncate!r}")
        if self.predict not in ("rollout", "static"):
            raise ValueError(f"predict must be 'rollout' or 'static', got {self.predict!r}")
        if self.criterion not in ("ig", "uninformed", "max-contact"):
            raise ValueError(f"criterion must be 'ig', 'uninformed' or 'max-contact', got {self.criterion!r}")


class TouchIGPlanner:
    """Sampling-based information-gathering controller over spline pokes (module docstring)."""

    def __init__(self, env, belief_config, config: TouchPlannerConfig, seed: int = 0):
        from activetouch.belief.contact_model import ContactModelConfig

        self.env = env
        self.obj = env.object
        self.config = config
        self.contact = getattr(belief_config, "contact", ContactModelConfig())
        self.seed = int(seed)
        from activetouch.information import entropy

        self.se2_scale = entropy.object_se2_scale(self.obj)  # yaw as arc length for the shared support
        self._interior = self._interior_points(4096)
        self.reset()

    @classmethod
    def from_env(cls, env, belief_config, seed: int = 0, config: TouchPlannerConfig | None = None, **overrides):
        cfg = config or TouchPlannerConfig()
        if overrides:
            try:
                cfg = replace(cfg, **overrides)
            except TypeError as e:
                raise TypeError(f"unknown touch planner setting: {e}") from None
        return cls(env, belief_config, cfg, seed)

    def reset(self) -> None:
        self.rng = np.random.default_rng(self.seed + 7919)
        self.actions = 0
        self.last = None  # what the last call evaluated (figures, tests)
        self._last_target = None  # (3,) the last chosen poke's final waypoint

    # ------------------------------------------------------------------ sampling
    def _interior_points(self, n: int) -> np.ndarray:
        """``(n, 3)`` object-frame points uniform inside the object (rejection in its bounds on the SDF)."""
        g = torch.Generator().manual_seed(12345)
        lo, hi = self.obj.bounds[0].double(), self.obj.bounds[1].double()
        out = []
        while sum(len(o) for o in out) < n:
            x = lo + (hi - lo) * torch.rand(4 * n, 3, generator=g, dtype=torch.float64)
            v, _ = self.obj.cached_sdf(x.float())
            out.append(x[v.reshape(-1) < 0].numpy())
        return np.concatenate(out)[:n]

    def sample_candidates(self, belief, ee_state: np.ndarray, retreat: bool = False) -> list[np.ndarray]:
        """``num_samples`` candidate waypoint arrays ``(K, 4)`` (module docstring, step 2); ``retreat``: start
        each with the back-off via-point (after a contact)."""
        from activetouch.planning.splines import spline_waypoints

        cfg, env, rng = self.config, self.env, self.rng
        states = belief.states.detach().cpu().double().numpy()
        w = belief.weights.detach().cpu().double().numpy()
        w = w / w.sum()
        u0 = np.asarray(ee_state, dtype=np.float64).copy()
        back = None
        if retreat and self._last_target is not None:
            # where the last poke wanted to go, seen from where the guarded stop left the gripper: into the contact
            into = self._last_target - u0[:3]
            into[2] = 0.0
            n = np.linalg.norm(into)
            back = u0.copy()
            if n > 1e-6:
                back[:3] -= cfg.retreat_distance * into / n
            back[2] += cfg.retreat_height
        cands = []
        for _ in range(cfg.num_samples):
            for _try in range(cfg.max_tries):
                j = rng.choice(len(w), p=w)  # importance-sample a particle ...
                x, y, yaw = states[j]
                p_obj = self._interior[rng.integers(len(self._interior))]  # ... and a point inside it
                c, s = math.cos(yaw), math.sin(yaw)
                target = np.array([x + c * p_obj[0] - s * p_obj[1], y + s * p_obj[0] + c * p_obj[1],
                                   max(p_obj[2], cfg.min_poke_height)])
                to_ee = math.atan2(u0[1] - target[1], u0[0] - target[0])
                phi = to_ee + rng.uniform(-math.pi / 2, math.pi / 2)
                approach = target + cfg.approach_distance * np.array([math.cos(phi), math.sin(phi), 0.0])
                if env.reachable(np.stack([target, approach])).all() or _try == cfg.max_tries - 1:
                    break
            # gripper yaw: pads facing the approach direction, unwrapped next to the current yaw
            g_yaw = u0[3] + ((phi + math.pi / 2 - u0[3] + math.pi / 2) % math.pi - math.pi / 2)
            via = np.array([[*approach, g_yaw], [*target, g_yaw]])
            if back is not None:
                via = np.vstack([back, via])
            cands.append(spline_waypoints(u0, via, cfg.waypoints))
        return cands

    # ------------------------------------------------------------------ evaluation
    def _evaluate(self, belief, plans) -> dict:
        """Predicted states ``(C, K, P, 3)``, contact probabilities and hypothetical observations ``(C, K, P)``."""
        from activetouch.belief.contact_model import contact_likelihood, robot_object_distance

        x0 = belief.states.detach().double().cpu()
        xs, ps, zs, t_roll, t_dist = [], [], [], 0.0, 0.0
        for plan in plans:
            t0 = time.perf_counter()
            if self.config.predict == "rollout":
                traj = self.env.rollout(x0, plan).double()  # (P, K, 3)
            else:
                traj = x0[:, None, :].expand(-1, plan.num_waypoints, -1).clone()
            t1 = time.perf_counter()
            pts = near_robot_points(self.obj, self.env.robot_points(plan.q[1:]), traj)  # (K, M', 3)
            d = robot_object_distance(self.obj, traj.float(), pts.float()).double()  # (P, K)
            p1 = contact_likelihood(torch.ones(d.shape[1], dtype=torch.bool), d.T, self.contact)  # (K, P)
            t_roll += t1 - t0
            t_dist += time.perf_counter() - t1
            xs.append(traj.transpose(0, 1))
            ps.append(p1)
            zs.append(d.T <= self.config.contact_tolerance)
        return {"x": xs, "p": ps, "z": zs, "rollout_s": t_roll, "distance_s": t_dist}

    def grasp_probability(self, belief) -> tuple[float, np.ndarray]:
        """App. D-d: the weighted share of particles that the grasp planned for the ML state lifts."""
        w = belief.weights.detach().cpu().double()
        best = belief.best_state.detach().cpu().double().numpy()
        keep = w > self.config.grasp_min_weight
        ok = torch.zeros(len(w), dtype=torch.bool)
        if keep.any():
            ok[keep] = self.env.grasp_success(belief.states.detach().cpu().double()[keep], best).cpu()
        return float(w[ok].sum()), best

    def next_action(self, belief, ee_state, in_contact: bool, features=None):
        from activetouch.information import entropy
        from activetouch.sim.grasp_env import GraspAction, PokeAction

        cfg = self.config
        t0 = time.perf_counter()
        p_grasp, best = self.grasp_probability(belief)
        t_grasp = time.perf_counter() - t0
        timings = {"grasp_s": t_grasp, "grasp_p": p_grasp, "replanned": 1.0}
        if p_grasp >= cfg.grasp_threshold or self.actions >= cfg.max_actions:
            self.last = {"kind": "grasp", "grasp_p": p_grasp, "state": best}
            return GraspAction(best), timings
        t1 = time.perf_counter()
        cands = self.sample_candidates(belief, ee_state, retreat=bool(in_contact))
        plans = [self.env.plan_poke(c) for c in cands]
        t2 = time.perf_counter()
        ev = self._evaluate(belief, plans) if cfg.criterion != "uninformed" else None
        t3 = time.perf_counter()
        gain = float("nan")
        if cfg.criterion == "uninformed":
            k, t_star = 0, len(cands[0])
        elif cfg.criterion == "max-contact":
            counts = [int(z.any(0).sum()) for z in ev["z"]]  # particles contacted along each candidate
            k, t_star = int(np.argmax(counts)), len(cands[0])
            gain = float(counts[k])
        else:
            w0 = belief.weights.detach().double().cpu()
            x0 = belief.states.detach().double().cpu()
            res = entropy.expected_information_gain(
                w0, x0, torch.stack(ev["x"]), torch.stack(ev["p"]), torch.stack(ev["z"]), rho=cfg.rho,
                scale=self.se2_scale, periodic=entropy.SE2_PERIODIC)
            k = int(torch.argmax(res.gain))
            t_star, gain = int(res.t_star[k]), float(res.gain[k])
            if not cfg.truncate:
                t_star = len(cands[k])
            timings.update(weight_term=float(res.weight_term[k, t_star - 1]),
                           spatial_term=float(res.spatial_term[k, t_star - 1]))
        t4 = time.perf_counter()
        self.actions += 1
        waypoints = cands[k][:t_star]
        self._last_target = waypoints[-1, :3].copy()
        self.last = {"kind": "poke", "candidates": cands, "chosen": k, "t_star": t_star, "gain": gain,
                     "grasp_p": p_grasp}
        timings.update(t_star=float(t_star), sample_s=t2 - t1, ig_s=t4 - t3,
                       rollout_s=ev["rollout_s"] if ev else 0.0, distance_s=ev["distance_s"] if ev else 0.0)
        if cfg.criterion == "ig":
            timings["expected_ig"] = gain
        elif cfg.criterion == "max-contact":
            timings["contacted_particles"] = gain
        return PokeAction(waypoints), timings
