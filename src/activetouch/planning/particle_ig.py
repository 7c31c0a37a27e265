"""A mixed planner (issue 11): the touch paper's expected information gain over RUMI's pose particles.

RUMI's belief (CHSEL-weighted particles re-weighed on the labelled point features) with the touch-only paper's
planner: candidate motions end at a uniform interior point of an importance-sampled particle (Sec. IV-C, App. C:
"poking"), each is scored by Alg. 1's expected information gain (Eq. 6-9) with the shared-support entropy
(Eq. 5, App. A) over the particles' (x, y, yaw) and the proximity contact model of Eq. 10, and the best is
executed. On the rummaging tasks a candidate is one straight end-effector move (RUMI's action: at most one unit,
80 mm), sampled at ``waypoints`` points along the way.

Simplifications (named, with what they cost):

* static prediction: the particles are held still over a candidate (the touch paper's ``predict=static``, which
  its Table I was also measured with here); only the weight term of Eq. 9 changes, pushes are not foreseen;
* the robot-object distance ``d`` of Eq. 10 is the RUMI robot model's: the gripper points ``h(q)`` (not every
  link of the arm), at the particle poses through the object's cached SDF;
* the hypothetical observation of particle ``j`` at a waypoint is contact when ``d_j <= contact_tol``;
* SE(3) particles (box) enter the entropy by their (x, y, yaw): the resting face is not in the spatial term.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from activetouch.belief.contact_model import ContactModelConfig, contact_probability, pose_to_se2
from activetouch.information.entropy import SE2_PERIODIC, expected_information_gain, object_se2_scale
from activetouch.planning.dynamics import GripperModel, action_indices

__all__ = ["ParticleIGConfig", "ParticleIGPlanner"]


@dataclass(frozen=True)
class ParticleIGConfig:
    """Settings of the mixed planner: the touch paper's where it has them.

    ``num_candidates`` = N_samples = 20 (Sec. IV-C); ``rho`` = 5 (App. D e); ``contact`` = Eq. 10's alpha_tp 0.5,
    alpha_fp 0.1, gamma 1000 /m. Ours: ``waypoints`` per candidate, ``contact_tol`` (m, the hypothetical
    contact), ``overshoot`` (m past the sampled interior point, capped at one unit action), ``interior_samples``
    (object-frame interior points drawn once), ``gripper_spacing`` (m between the gripper points ``h(q)``: 2 cm,
    357 points), ``translation_scale`` (the env's, m per unit action).
    """

    num_candidates: int = 20
    waypoints: int = 8
    rho: int = 5
    contact_tol: float = 0.003
    overshoot: float = 0.02
    interior_samples: int = 512
    gripper_spacing: float = 0.02
    translation_scale: float = 0.08
    contact: ContactModelConfig = field(default_factory=ContactModelConfig)

    def __post_init__(self):
        for name in ("num_candidates", "waypoints", "rho", "interior_samples"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{name} must be a positive int, got {v!r}")
        for name in ("contact_tol", "overshoot", "translation_scale", "gripper_spacing"):
            v = float(getattr(self, name))
            pos = name in ("translation_scale", "gripper_spacing")
            if not (math.isfinite(v) and (v > 0 if pos else v >= 0)):
                raise ValueError(f"{name} must be finite and {'> 0' if pos else '>= 0'}, got {v!r}")

    def with_overrides(self, **overrides) -> "ParticleIGConfig":
        unknown = set(overrides) - set(self.__dataclass_fields__)
        if unknown:
            raise ValueError(f"unknown ParticleIGConfig fields: {sorted(unknown)}; known: "
                             f"{', '.join(sorted(self.__dataclass_fields__))}")
        return replace(self, **overrides)


class ParticleIGPlanner:
    """Expected-IG pokes for a pose-particle belief (``.poses (P, 4, 4)``, ``.weights (P,)``).

    Args:
        obj: the known object (``sdf``, ``sdf_world``, ``bounds``).
        gripper_points: ``(M, 3)`` robot points in the end-effector frame (``h(q)``).
        action_space: ``"planar"`` or ``"3d"``.
        config: :class:`ParticleIGConfig`; seed: candidate draws (a new stream per :meth:`reset`).
    """

    def __init__(self, obj, gripper_points, *, action_space: str = "planar", config: ParticleIGConfig | None = None,
                 seed: int = 0, device=None):
        self.config = config or ParticleIGConfig()
        self.obj = obj
        self.idx = action_indices(action_space)
        self.nu = len(self.idx)
        self.planar = action_space == "planar"
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        pts = torch.as_tensor(gripper_points, dtype=torch.float32)
        self.gripper = GripperModel(pts, torch.ones(pts.shape[0], dtype=torch.bool)).to(device=self.device)
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed must be a non-negative int, got {seed!r}")
        self.seed = int(seed)
        self.scale = object_se2_scale(obj)
        self.interior = self._interior_points(self.config.interior_samples)
        self.reset()

    @classmethod
    def from_env(cls, env, belief_config=None, seed: int = 0, device=None, **overrides) -> "ParticleIGPlanner":
        """For a rummaging environment (its object, gripper points at r_w, action space and scale). KMPPI settings
        (``RumiPlannerConfig`` fields a sweep gives every method, e.g. ``--samples``) are ignored: no KMPPI here."""
        from activetouch.planning.config import RumiPlannerConfig

        overrides = {k: v for k, v in overrides.items()
                     if not (k in RumiPlannerConfig.__dataclass_fields__ and k not in ParticleIGConfig.__dataclass_fields__)}
        cfg = ParticleIGConfig()
        scale = getattr(env, "action_scale", None)
        if scale is not None and "translation_scale" not in overrides:
            overrides["translation_scale"] = float(tuple(scale() if callable(scale) else scale)[0])
        cfg = cfg.with_overrides(**overrides)
        h, _ = env.gripper_points(spacing=cfg.gripper_spacing)
        return cls(env.object, h, action_space=env.spec.action_space, config=cfg, seed=seed, device=device)

    def reset(self) -> None:
        self.rng = np.random.default_rng(self.seed)
        self.last = None

    def _interior_points(self, n: int) -> torch.Tensor:
        """``(n, 3)`` object-frame points uniform inside the mesh (rejection from its bounding box)."""
        lo, hi = (np.asarray(b, dtype=np.float64) for b in self.obj.bounds.detach().cpu().numpy())
        g = np.random.default_rng(12345)
        out = []
        while sum(len(o) for o in out) < n:
            x = torch.as_tensor(g.uniform(lo, hi, size=(4 * n, 3)), dtype=torch.float32)
            v, _ = self.obj.sdf(x)
            out.append(x[v.reshape(-1) < 0])
        return torch.cat(out)[:n].to(self.device)

    def candidates(self, poses: torch.Tensor, w: torch.Tensor, ee: torch.Tensor) -> torch.Tensor:
        """``(C, 3)`` world moves of the end effector: toward a uniform interior point of an importance-sampled
        particle, ``overshoot`` beyond it, at most one unit action long (planar: no height change)."""
        c = self.config
        P = poses.shape[0]
        pw = w.detach().cpu().double().numpy()
        pick = self.rng.choice(P, size=c.num_candidates, p=pw / pw.sum())
        point = self.interior[self.rng.integers(0, self.interior.shape[0], size=c.num_candidates)]
        T = poses[torch.as_tensor(pick, device=self.device)]
        target = torch.einsum("cij,cj->ci", T[:, :3, :3], point) + T[:, :3, 3]  # (C, 3) world
        d = target - ee[:3]
        if self.planar:
            d[:, 2] = 0.0
        dist = d.norm(dim=-1, keepdim=True).clamp_min(1e-9)
        length = (dist + c.overshoot).clamp_max(c.translation_scale)
        return d / dist * length

    def next_action(self, belief, ee_state, in_contact: bool, features=None) -> tuple[np.ndarray, dict[str, float]]:
        """The candidate of highest expected information gain (Alg. 1). Returns ``(u (Nu,), timings)``."""
        t0 = time.perf_counter()
        c = self.config
        poses = torch.as_tensor(belief.poses).detach().to(self.device, torch.float32)
        w = torch.as_tensor(belief.weights).detach().to(self.device, torch.float32)
        ee = torch.as_tensor(np.asarray(ee_state, dtype=np.float32), device=self.device).reshape(-1)
        if ee.shape != (4,) or not bool(torch.isfinite(ee).all()):
            raise ValueError(f"ee_state must be a finite [x, y, z, yaw] (4,), got {tuple(ee.shape)}")
        moves = self.candidates(poses, w, ee)  # (C, 3)
        C, Tn, P = moves.shape[0], c.waypoints, poses.shape[0]
        alpha = torch.linspace(1.0 / Tn, 1.0, Tn, device=self.device)
        ee_traj = ee.expand(C, Tn, 4).clone()
        ee_traj[..., :3] = ee[:3] + alpha[None, :, None] * moves[:, None, :]
        pts = self.gripper.world(ee_traj)  # (C, T, M, 3)
        M = pts.shape[2]
        # values only; points outside the cached box come back +inf (far: Eq. 10 gives alpha_fp there)
        v = self.obj.sdf_world_values(poses, pts.reshape(-1, 3), far_positive_from=0)  # (P, C*T*M)
        d = v.reshape(P, C, Tn, M).amin(dim=-1).permute(1, 2, 0).clamp_min(0.0).double()  # (C, T, P)
        p = contact_probability(d, c.contact)
        z = d <= c.contact_tol
        x0 = pose_to_se2(poses.double())  # (P, 3)
        if P < 2:  # one particle: nothing to learn (Eq. 5 needs rho + 1 particles); take the first candidate
            res = None
        else:
            res = expected_information_gain(w.double(), x0, x0.expand(C, Tn, P, 3), p, z, rho=min(c.rho, P - 1),
                                            scale=self.scale, periodic=SE2_PERIODIC)
        best = 0 if res is None else int(torch.argmax(res.gain))
        move = moves[best]
        u = np.zeros(self.nu, dtype=np.float32)
        m = (move / c.translation_scale).cpu().numpy()
        u[0], u[1] = m[0], m[1]
        if self.nu == 4:
            u[2] = m[2]
        u = np.clip(u, -1.0, 1.0).astype(np.float32)
        self.last = {"gain": 0.0 if res is None else float(res.gain[best]),
                     "t_star": 0 if res is None else int(res.t_star[best]), "gains": None if res is None else res.gain}
        timing = dict.fromkeys(("field_s", "dynamics_s", "cost_s", "mppi_s", "plan_iters"), 0.0)
        timing["replanned"] = 1.0
        timing["ig_s"] = time.perf_counter() - t0
        return u, timing
