"""Slide baseline of RUMI section V-H (a heuristic after ref. [13]).

Two modes. In contact, the robot slides tangentially to the estimated surface normal, parallel to the shelf
(the x-y plane), clockwise or counter-clockwise around the contact; the direction is drawn once per run from the
seed. Out of contact, it moves toward the object centre estimated by the pose particles (their weighted mean).
The belief is still updated by Algorithm 1 (the runner does that); Slide only reads it.

Choices of ours (the paper gives no numbers): step lengths (``slide_step``, ``approach_step``), the small inward
component that keeps the contact while sliding (``inward``), how the contact point is found
(``contact_radius``) and the fallbacks when the normal is not informative (see :class:`SlideConfig`).
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, replace

import numpy as np
import torch

from activetouch.observations import Features
from activetouch.planning.dynamics import GripperModel, action_indices

__all__ = ["SlideConfig", "SlidePlanner"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SlideConfig:
    """Parameters of the Slide heuristic (RUMI section V-H; none are given in the paper).

    ``slide_step``: translation per step while in contact (m); ``approach_step``: translation per step toward the
    estimated centre out of contact (m; the last step toward it is shorter when the centre is closer);
    ``inward``: ratio of the inward (``-n``) to the tangential component while sliding (0.2: 11 deg into the
    surface), which keeps the pads on a convex surface that curves away; ``contact_radius``: an observed surface
    point within this distance of the pads ``h_I(q)`` is taken as the current contact (m);
    ``min_horizontal_normal``: when the horizontal part of the estimated normal is shorter than this fraction of
    the normal (a top face, or no particle near), the horizontal direction from the estimated centre to the
    contact is used as the normal instead. ``translation_scale`` (m per unit action) is the env's action scale.
    """

    slide_step: float = 0.02
    approach_step: float = 0.04
    inward: float = 0.2
    contact_radius: float = 0.02
    min_horizontal_normal: float = 0.3
    translation_scale: float = 0.08

    def __post_init__(self):
        for name in ("slide_step", "approach_step", "contact_radius", "translation_scale"):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be finite and > 0, got {v}")
        if not (math.isfinite(self.inward) and self.inward >= 0):
            raise ValueError(f"inward must be finite and >= 0, got {self.inward}")
        if not 0 <= self.min_horizontal_normal < 1:
            raise ValueError(f"min_horizontal_normal must be in [0, 1), got {self.min_horizontal_normal}")
        for name in ("slide_step", "approach_step"):  # longer steps would be clipped per axis (bent)
            if getattr(self, name) > self.translation_scale + 1e-12:
                raise ValueError(f"{name} ({getattr(self, name)}) exceeds one unit action "
                                 f"(translation_scale = {self.translation_scale} m)")

    def with_overrides(self, **overrides) -> "SlideConfig":
        unknown = set(overrides) - set(self.__dataclass_fields__)
        if unknown:
            raise ValueError(f"unknown SlideConfig fields: {sorted(unknown)}")
        return replace(self, **overrides)


class SlidePlanner:
    """The Slide heuristic (section V-H) as a registry planner.

    Args:
        obj: the known object (``sdf_world``, ``bounds``).
        gripper_points: ``(M, 3)`` robot points in the ee frame; ``info_mask (M,)`` selects the pads ``h_I``.
        action_space: ``"planar"`` (``u = [dx, dy, dyaw]``) or ``"3d"`` (``[dx, dy, dz, dyaw]``).
        config: :class:`SlideConfig`.
        seed: draws the sliding direction (``direction``: +1 counter-clockwise, -1 clockwise, seen from above,
            around the object) once per run, at :meth:`reset`.
        device: torch device of the belief queries.
    """

    def __init__(self, obj, gripper_points, info_mask, *, action_space: str = "planar",
                 config: SlideConfig | None = None, seed: int = 0, device=None):
        self.config = config or SlideConfig()
        if not isinstance(self.config, SlideConfig):
            raise ValueError(f"config must be a SlideConfig, got {type(self.config).__name__}")
        self.obj = obj
        self.action_space = action_space
        self.idx = action_indices(action_space)  # validates the action space
        self.nu = len(self.idx)
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        self.gripper = GripperModel(torch.as_tensor(gripper_points, dtype=torch.float32),
                                    torch.as_tensor(info_mask, dtype=torch.bool)).to(device=self.device)
        lo, hi = (torch.as_tensor(np.asarray(b), dtype=torch.float32) for b in obj.bounds)
        self.centre_obj = ((lo + hi) / 2).to(self.device)  # object-frame bounding-box centre
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed must be a non-negative int, got {seed!r}")
        self.seed = int(seed)
        self.reset()

    @classmethod
    def from_env(cls, env, belief_config=None, seed: int = 0, config: SlideConfig | None = None, device=None,
                 **overrides) -> "SlidePlanner":
        """Slide for a :class:`activetouch.sim.RummageEnv` (its object, pads, action space and action scale);
        ``overrides`` are :class:`SlideConfig` fields. KMPPI settings (:class:`RumiPlannerConfig` fields, e.g. a
        sweep's ``num_samples`` given to every method) are ignored: Slide does not plan."""
        from activetouch.planning.config import RumiPlannerConfig

        spec = env.spec
        ignored = sorted(k for k in overrides if k in RumiPlannerConfig.__dataclass_fields__
                         and k not in SlideConfig.__dataclass_fields__)
        if ignored:
            log.info("slide: ignoring KMPPI settings %s (Slide does not plan)", ignored)
            overrides = {k: v for k, v in overrides.items() if k not in ignored}
        cfg = config or SlideConfig()
        scale = getattr(env, "action_scale", None)
        if scale is not None and "translation_scale" not in overrides:
            scale = tuple(scale() if callable(scale) else scale)
            overrides["translation_scale"] = float(scale[0])
        cfg = cfg.with_overrides(**overrides)
        h, mask = env.gripper_points(spacing=float(spec.r_w))
        return cls(env.object, h, mask, action_space=spec.action_space, config=cfg, seed=seed, device=device)

    def reset(self) -> None:
        """New run: draw the sliding direction from the seed (+1 counter-clockwise, -1 clockwise)."""
        rng = np.random.default_rng(self.seed)
        self.direction = 1 if rng.random() < 0.5 else -1
        self.last_mode = None
        self.last_contact = None
        self.last_normal = None

    # ------------------------------------------------------------------ belief queries
    @staticmethod
    def _particles(poses, weights, device):
        poses = torch.as_tensor(poses).detach().to(device=device, dtype=torch.float32)
        if poses.ndim != 3 or poses.shape[1:] != (4, 4):
            raise ValueError(f"poses must have shape (P, 4, 4), got {tuple(poses.shape)}")
        w = torch.as_tensor(weights).detach().to(device=device, dtype=torch.float32)
        if w.shape != (poses.shape[0],):
            raise ValueError(f"weights must have shape ({poses.shape[0]},), got {tuple(w.shape)}")
        if not bool(torch.isfinite(w).all()) or bool((w < 0).any()) or not float(w.sum()) > 0:
            raise ValueError("weights must be finite, non-negative and not all zero")
        return poses, w / w.sum()

    def centre(self, poses, weights) -> torch.Tensor:
        """Estimated object centre ``(3,)``: ``sum_i w_i T_i c`` with ``c`` the object-frame bounding-box centre."""
        poses, w = self._particles(poses, weights, self.device)
        c = torch.einsum("pij,j->pi", poses[:, :3, :3], self.centre_obj) + poses[:, :3, 3]
        return (w[:, None] * c).sum(0)

    def normal(self, poses, weights, x) -> torch.Tensor:
        """Estimated outward surface normal at the world point ``x (3,)`` -> ``(3,)`` (not normalised):
        ``sum_i w_i R_i grad sdf(T_i^-1 x)``, the weighted SDF gradient of the particles (as in Alg. 7 line 11,
        evaluated exactly at ``x`` with ``obj.sdf_world``)."""
        poses, w = self._particles(poses, weights, self.device)
        x = torch.as_tensor(x, device=self.device, dtype=torch.float32).reshape(1, 3)
        with torch.no_grad():
            _, g = self.obj.sdf_world(poses, x)  # (P, 1, 3) object frame
        g = g[:, 0].to(torch.float32)
        return torch.einsum("p,pij,pj->i", w, poses[:, :3, :3], g)

    def contact_point(self, poses, weights, ee_state, features: Features | None = None) -> torch.Tensor:
        """World point ``(3,)`` of the current contact.

        Our choice: the observed surface point nearest to the pads ``h_I(q)`` when one lies within
        ``contact_radius`` of them (the patch just felt); otherwise (no features, e.g. a runner that does not pass
        them) the pad point deepest inside the estimated object (smallest weighted SDF over the particles).
        """
        ee = self._ee(ee_state)
        pads = self.gripper.world_info(ee)  # (M_I, 3)
        if features is not None:
            if not isinstance(features, Features):
                raise ValueError(f"features must be activetouch.observations.Features, got {type(features).__name__}")
            surf = features.surface.positions.to(device=self.device, dtype=torch.float32)
            if surf.shape[0]:
                d = torch.cdist(surf, pads).min(dim=1).values
                j = int(torch.argmin(d))
                if float(d[j]) <= self.config.contact_radius:
                    return surf[j]
        poses, w = self._particles(poses, weights, self.device)
        with torch.no_grad():
            v, _ = self.obj.sdf_world(poses, pads)  # (P, M_I)
        return pads[int(torch.argmin(w @ v.to(torch.float32)))]

    # ------------------------------------------------------------------ policy
    def _ee(self, ee_state) -> torch.Tensor:
        ee = torch.as_tensor(np.asarray(ee_state, dtype=np.float32), device=self.device).reshape(-1)
        if ee.shape != (4,):
            raise ValueError(f"ee_state must be [x, y, z, yaw] (4,), got shape {tuple(ee.shape)}")
        if not bool(torch.isfinite(ee).all()):
            raise ValueError("ee_state contains NaN or inf")
        return ee

    def slide_direction(self, normal_xy: torch.Tensor) -> torch.Tensor:
        """Unit x-y translation ``(2,)`` for a unit horizontal outward normal ``(2,)``: the tangent
        ``direction * (z x n)`` (counter-clockwise around the object for +1) plus ``inward * (-n)``, normalised."""
        t = self.direction * torch.stack([-normal_xy[1], normal_xy[0]])
        v = t - self.config.inward * normal_xy
        return v / v.norm()

    def _to_action(self, move: torch.Tensor) -> np.ndarray:
        """World translation ``(3,)`` (m) -> action ``(Nu,)`` in [-1, 1] (yaw unchanged)."""
        u = np.zeros(self.nu, dtype=np.float32)
        m = (move / self.config.translation_scale).detach().cpu().numpy()
        u[0], u[1] = m[0], m[1]
        if self.nu == 4:  # 3d: [dx, dy, dz, dyaw]
            u[2] = m[2]
        return np.clip(u, -1.0, 1.0).astype(np.float32)

    def next_action(self, belief, ee_state, in_contact: bool, poses=None, weights=None,
                    features: Features | None = None) -> tuple[np.ndarray, dict[str, float]]:
        """One step of the heuristic for the belief (``.poses (P, 4, 4)``, ``.weights (P,)``, or ``poses`` and
        ``weights``) at ``ee_state [x, y, z, yaw]``. ``features`` (the accumulated ``X``) locate the contact.

        Returns ``(u (Nu,) float32 in [-1, 1], timings)``; timings hold RUMI's keys (all 0: no field, dynamics or
        cost) with ``replanned`` = 1 (it decides every step) and ``slide_s`` (seconds of this call).
        """
        t0 = time.perf_counter()
        if belief is not None:
            poses, weights = belief.poses, belief.weights
        if poses is None or weights is None:
            raise ValueError("Slide needs a belief (or poses and weights) to estimate the object centre")
        ee = self._ee(ee_state)
        centre = self.centre(poses, weights)
        c = self.config
        if in_contact:
            # Normal estimate (our choice): weighted particle SDF gradient at the contact point (contact_point),
            # flattened to the shelf plane; the horizontal direction centre -> contact when it is not informative.
            x = self.contact_point(poses, weights, ee, features)
            n = self.normal(poses, weights, x)
            n_xy = n[:2]
            if not float(n_xy.norm()) > c.min_horizontal_normal * float(n.norm()) or not float(n_xy.norm()) > 1e-9:
                n_xy = (x - centre)[:2]
                if not float(n_xy.norm()) > 1e-9:
                    n_xy = (ee - centre)[:2]
            if float(n_xy.norm()) > 1e-9:
                n_xy = n_xy / n_xy.norm()
                move = torch.zeros(3, device=self.device)
                move[:2] = c.slide_step * self.slide_direction(n_xy)  # dz = 0 while sliding
            else:  # contact exactly at the estimated centre, no direction: stay
                move = torch.zeros(3, device=self.device)
            self.last_mode, self.last_contact, self.last_normal = "slide", x, n_xy
        else:
            d = centre - ee[:3]
            if self.nu == 3:  # planar: the height is fixed
                d[2] = 0.0
            dist = float(d.norm())
            move = d * (min(c.approach_step, dist) / dist) if dist > 1e-9 else torch.zeros(3, device=self.device)
            self.last_mode, self.last_contact, self.last_normal = "approach", None, None
        u = self._to_action(move)
        timing = dict.fromkeys(("field_s", "dynamics_s", "cost_s", "mppi_s", "plan_iters"), 0.0)
        timing["replanned"] = 1.0
        timing["slide_s"] = time.perf_counter() - t0
        return u, timing
