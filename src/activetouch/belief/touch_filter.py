"""Touch-only particle filter over planar object states ``(x, y, yaw)`` (paper Sec. V, Eq. 10, App. B, App. D-c).

* :class:`TouchFilterConfig` - filter parameters (paper values where it gives them; the others documented).
* :func:`gmm_prior` - the initial belief of App. D-c: a two-component Gaussian mixture.
* :class:`TouchBelief` - weighted particles with the update of Sec. V: re-weigh with the product of Eq. 10
  likelihoods of every waypoint's contact observation at the particle's (physics-predicted) state there, move
  the particles to their final predicted state, and resample when the weights degenerate (App. B):
  contact-aware resampling after a contact, systematic importance resampling otherwise.

Weights are kept in the log domain (``log w += sum_k log P(z_k | x_k)``, normalised with ``logsumexp``), so a
long run of unlikely observations cannot underflow to a NaN belief. Fallback: if *every* particle's likelihood
is exactly zero (possible only with ``alpha_fp = 0`` or ``alpha_tp = 1``: the observation contradicts every
hypothesis), the update keeps the previous weights, logs a warning and reports ``fallback=True``; there is no
ranking to learn from it.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace

import torch

from .contact_model import (
    ContactModelConfig,
    _check_robot_points,
    _check_z,
    check_states,
    contact_likelihood,
    contact_log_likelihood,
    footprint_radius,
    pose_to_se2,
    robot_object_distance,
    se2_to_pose,
    signed_robot_object_distance,
    wrap_angle,
)
from .resample import systematic_resample

__all__ = [
    "TouchFilterConfig",
    "TouchBelief",
    "gmm_prior",
    "ContactModelConfig",
    "contact_likelihood",
    "contact_log_likelihood",
    "robot_object_distance",
    "se2_to_pose",
    "pose_to_se2",
]

log = logging.getLogger(__name__)


def _randn(shape, generator: torch.Generator | None, like: torch.Tensor) -> torch.Tensor:
    """Standard normal samples drawn on the generator's device, returned on ``like``'s device and dtype."""
    dev = generator.device if generator is not None else torch.device("cpu")
    return torch.randn(shape, generator=generator, device=dev, dtype=torch.float64).to(like)


@dataclass(frozen=True)
class TouchFilterConfig:
    """Parameters of the touch-only particle filter (Sec. V, App. B, App. D-c and D-e).

    From the paper: ``num_particles`` (N_p) = 100; ``contact`` = Eq. 10 with ``alpha_tp = 0.5``,
    ``alpha_fp = 0.1``, ``gamma = 1000``; the prior (App. D-c) ``prior_sigma_pos = 0.06`` m,
    ``prior_sigma_yaw = 0.5`` rad, ``prior_components = 2`` with equal weights.

    Not in the paper (choices):

    * ``resample`` (bool): resample at all (False for the Binary / Smooth ablation variants of Table II).
    * ``ess_threshold`` = 0.5: App. B triggers resampling "when particle weights drop below a threshold"; we
      use the usual degeneracy test, effective sample size ``1 / sum w^2`` below ``ess_threshold * N_p``.
    * ``contact_samples`` (M) = 100: candidate states of contact-aware resampling (App. B "sample M particles
      near the current robot pose"; M is not given), one per particle.
    * ``candidate_sigma_pos`` = 0.01 m, ``candidate_sigma_yaw`` = 0.1 rad: jitter of the belief particles that
      seed the candidates before they are projected onto the contact manifold (see
      :meth:`TouchBelief.contact_candidates`).
    * ``projection_iterations`` = 5 Newton steps of that projection; ``max_projection_step`` = 0.05 m per step.
    * ``max_penetration`` = 0.002 m: candidates whose robot points still lie deeper than this inside the object
      are rejected (Eq. 10 counts penetration as ``d = 0``, the most likely contact, but such states are
      physically impossible).
    * ``replace_below`` = 0.5: particles with ``w < replace_below / N_p`` are "low-weight" and may be replaced;
      ``max_replace_fraction`` = 0.5 caps the replaced share so the belief keeps its history.
    * ``roughening_pos`` = 1 mm, ``roughening_yaw`` = 0.01 rad: Gaussian jitter of the duplicates that
      resampling makes (every copy but the first). The physics prediction is deterministic (Sec. V), so without
      it copies stay identical for ever; the cost is a slight extra spread of the belief.
    * ``process_noise_pos`` = ``process_noise_yaw`` = 0: no process noise (the paper's dynamics are
      deterministic MuJoCo rollouts); set them to add Gaussian noise to every particle after each prediction.
    * ``table_height`` = 0: height of the object frame's origin (base-centred objects resting on z = 0).
    * ``active_weight`` = 1e-4: weight above which a particle counts as active (Table II).
    * ``explain_distance`` = 5 mm: a contact that no particle lies this close to is "unexplained" and also
      triggers contact-aware resampling (App. B's starvation case, where the weights stay near uniform and the ESS
      test alone would never fire); 0 disables it (the ESS test only).
    * ``contact_local_share`` = 0.5: share of the M contact candidates drawn around the robot's low part (any yaw)
      rather than from the belief (see :meth:`TouchBelief.contact_candidates`).
    * ``mode_sigma_pos`` = 1 cm, ``mode_sigma_yaw`` = 0.1 rad: kernel of the maximum-likelihood state
      (:attr:`TouchBelief.best_state`), about the grasp's tolerance across the pads and in yaw.
    * ``history_check`` = False (App. B as published): contact candidates are judged by the current contact
      alone. True (beyond the paper; the grasp tasks' default): a candidate replaces a particle only when it
      explains the *whole* observation history better (:meth:`TouchBelief.history_log_likelihood`) than that
      particle and than the belief's weighted median particle, so resampling onto the contact neither brings back
      states that earlier pokes ruled out nor fills the belief with candidates poorer than its typical particle.
      Measured (touch-ig, grasp-box-0/1/2, static prediction, 2.5 N guard): on seeds 0-3 3/12 grasps without
      the check, 9/12 against the replaced particle only, 10/12 with the median too; on seeds 0-9 15/30 with 12
      waypoints per poke, 20/30 with 36 (the planner's default since; README Table I).
    * ``history_segments`` = 15: the most recent segments kept for that check (the paper's 15 pokes).
    * ``history_motion`` = False: the check holds every state still over the kept segments, so a box the pokes
      pushed by ``delta`` makes old contacts look ``delta`` away for every state. True (beyond the paper): each
      particle is scored on its own path over the kept segments (its physics rollouts; resampled copies inherit
      their parent's path shifted by their jitter; a contact candidate drawn from a particle inherits that
      particle's path, one drawn around the robot the belief's weighted mean path), so a pushed box is judged
      where it was at each old contact. Measured (touch-ig, grasp-box-0/1/2, seeds 0-9, static prediction):
      17/30 grasps against 20/30 held still, within the intervals: off by default.
    """

    num_particles: int = 100
    contact: ContactModelConfig = field(default_factory=ContactModelConfig)
    resample: bool = True
    ess_threshold: float = 0.5
    contact_samples: int = 100
    candidate_sigma_pos: float = 0.01
    candidate_sigma_yaw: float = 0.1
    projection_iterations: int = 5
    max_projection_step: float = 0.05
    max_penetration: float = 0.002
    replace_below: float = 0.5
    max_replace_fraction: float = 0.5
    roughening_pos: float = 0.001
    roughening_yaw: float = 0.01
    process_noise_pos: float = 0.0
    process_noise_yaw: float = 0.0
    prior_sigma_pos: float = 0.06
    prior_sigma_yaw: float = 0.5
    prior_components: int = 2
    table_height: float = 0.0
    active_weight: float = 1e-4
    explain_distance: float = 0.005
    contact_local_share: float = 0.5
    mode_sigma_pos: float = 0.01
    mode_sigma_yaw: float = 0.1
    history_check: bool = False
    history_segments: int = 15
    history_motion: bool = False

    def __post_init__(self):
        if not isinstance(self.contact, ContactModelConfig):
            raise ValueError(f"contact must be a ContactModelConfig, got {type(self.contact).__name__}")
        if not isinstance(self.history_check, bool):
            raise ValueError(f"TouchFilterConfig.history_check must be true or false, got {self.history_check!r}")
        if not isinstance(self.history_motion, bool):
            raise ValueError(f"TouchFilterConfig.history_motion must be true or false, got {self.history_motion!r}")
        for name in ("num_particles", "contact_samples", "projection_iterations", "prior_components",
                     "history_segments"):
            v = getattr(self, name)
            lo = 0 if name == "projection_iterations" else 1
            if not isinstance(v, int) or isinstance(v, bool) or v < lo:
                raise ValueError(f"TouchFilterConfig.{name} must be an int >= {lo}, got {v!r}")
        for name in ("ess_threshold", "candidate_sigma_pos", "candidate_sigma_yaw", "max_projection_step",
                     "max_penetration", "replace_below", "max_replace_fraction", "roughening_pos",
                     "roughening_yaw", "process_noise_pos", "process_noise_yaw", "prior_sigma_pos",
                     "prior_sigma_yaw", "table_height", "active_weight", "explain_distance", "contact_local_share", "mode_sigma_pos", "mode_sigma_yaw"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v):
                raise ValueError(f"TouchFilterConfig.{name} must be a finite number, got {v!r}")
            if name != "table_height" and v < 0:
                raise ValueError(f"TouchFilterConfig.{name} must be >= 0, got {v}")
        if self.mode_sigma_pos <= 0 or self.mode_sigma_yaw <= 0:
            raise ValueError("mode_sigma_pos and mode_sigma_yaw must be > 0")
        if self.ess_threshold > 1 or self.max_replace_fraction > 1:
            raise ValueError("ess_threshold and max_replace_fraction must lie in [0, 1]")


def gmm_prior(means, n: int, sigma_pos: float = 0.06, sigma_yaw: float = 0.5,
              generator: torch.Generator | None = None) -> torch.Tensor:
    """``n`` states ``(n, 3)`` from the initial belief of App. D-c: an equal-weight Gaussian mixture with
    component means ``means (C, 3)`` (the paper: C = 2) and isotropic ``sigma_pos`` (m, on x and y) and
    ``sigma_yaw`` (rad) in every component. Each sample picks its component uniformly at random; yaw is wrapped
    to ``(-pi, pi]``. Dtype and device follow ``means``. (The paper's particles are 6D poses; ours are planar.)
    """
    means = check_states(means, "means")
    if not isinstance(n, int) or isinstance(n, bool) or n < 1:
        raise ValueError(f"n must be a positive int, got {n!r}")
    for name, v in (("sigma_pos", sigma_pos), ("sigma_yaw", sigma_yaw)):
        if not math.isfinite(float(v)) or float(v) < 0:
            raise ValueError(f"{name} must be finite and >= 0, got {v}")
    dev = generator.device if generator is not None else torch.device("cpu")
    comp = torch.randint(means.shape[0], (n,), generator=generator, device=dev).to(means.device)
    sig = torch.tensor([sigma_pos, sigma_pos, sigma_yaw], dtype=means.dtype, device=means.device)
    x = means.index_select(0, comp) + _randn((n, 3), generator, means) * sig
    x[:, 2] = wrap_angle(x[:, 2])
    return x


class TouchBelief:
    """Weighted planar particles ``(x, y, yaw)`` of a known object resting on the table (Sec. V).

    Args:
        obj: ``KnownObject`` (or any object with ``sdf_world_values`` / ``sdf_world`` of the same signatures;
            ``bounding_radius`` and ``sdf_padding`` enable the distance cull).
        states: ``(P, 3)`` particles.
        weights: ``(P,)`` non-negative weights with mass (normalised here); None: uniform.
        config: :class:`TouchFilterConfig`; None: the defaults with ``num_particles = P``.
    """

    def __init__(self, obj, states, weights=None, config: TouchFilterConfig | None = None):
        states = check_states(states, "states")
        P = states.shape[0]
        self.config = config if config is not None else TouchFilterConfig(num_particles=P)
        if not isinstance(self.config, TouchFilterConfig):
            raise ValueError(f"config must be a TouchFilterConfig, got {type(self.config).__name__}")
        if P != self.config.num_particles:
            raise ValueError(f"got {P} particles but config.num_particles = {self.config.num_particles}")
        self.obj = obj
        self._states = states.detach().clone()
        self._states[:, 2] = wrap_angle(self._states[:, 2])
        if weights is None:
            lw = torch.full((P,), -math.log(P), dtype=states.dtype, device=states.device)
        else:
            w = torch.as_tensor(weights).to(device=states.device, dtype=states.dtype)
            if w.shape != (P,):
                raise ValueError(f"weights must have shape ({P},), got {tuple(w.shape)}")
            if not bool(torch.isfinite(w).all()) or bool((w < 0).any()):
                raise ValueError("weights must be finite and non-negative")
            if not float(w.sum()) > 0:
                raise ValueError("weights have no mass (they sum to zero)")
            lw = torch.log(w / w.sum())
        self._log_w = lw
        self._history: list[tuple[torch.Tensor, torch.Tensor]] = []  # (z (K,), robot points (K, M, 3)) per segment
        # with config.history_motion: each particle's states over each kept segment, (P, K, 3) per segment
        self._paths: list[torch.Tensor] = []
        self._donors: torch.Tensor | None = None  # contact_candidates' source particle per candidate (-1: none)
        self._check_invariants()

    @classmethod
    def from_prior(cls, obj, states, config: TouchFilterConfig | None = None) -> "TouchBelief":
        """Belief with uniform weights ``1 / N_p`` over prior samples ``states (P, 3)`` (App. D-c)."""
        return cls(obj, states, None, config)

    # ------------------------------------------------------------------ state
    @property
    def states(self) -> torch.Tensor:
        """``(P, 3)`` particles ``(x, y, yaw)``."""
        return self._states

    @property
    def weights(self) -> torch.Tensor:
        """``(P,)`` normalised weights."""
        return torch.exp(self._log_w)

    @property
    def log_weights(self) -> torch.Tensor:
        """``(P,)`` normalised log weights (``-inf`` for particles ruled out)."""
        return self._log_w

    @property
    def poses(self) -> torch.Tensor:
        """``(P, 4, 4)`` object -> world poses of the particles (origin at ``config.table_height``)."""
        return se2_to_pose(self._states, self.config.table_height)

    @property
    def history_paths(self) -> list[torch.Tensor]:
        """Each particle's states over each kept segment, ``(P, K, 3)`` per segment, oldest first (kept with
        ``config.history_check`` and ``config.history_motion``; empty otherwise)."""
        return [p.clone() for p in self._paths]

    @property
    def num_particles(self) -> int:
        return self._states.shape[0]

    @property
    def best_state(self) -> torch.Tensor:
        """``(3,)`` the maximum-likelihood state (App. D-d): the particle at the mode of the belief's weighted
        kernel density, ``argmax_i sum_j w_j exp(-|x_i - x_j|^2 / 2 s^2)`` with ``s`` = (``mode_sigma_pos``,
        ``mode_sigma_yaw``). The largest-weight particle is arbitrary right after resampling (uniform weights:
        ``argmax`` returns the first index) and a lone heavy outlier can beat a cluster; the kernel mode is the
        particle the weighted belief around it supports most (it is the heaviest particle when the weights are
        far from uniform and particles far apart)."""
        cfg = self.config
        x, w = self._states, self.weights
        d = x[:, None, :] - x[None, :, :]
        d[..., 2] = wrap_angle(d[..., 2])
        q = (d[..., 0] ** 2 + d[..., 1] ** 2) / cfg.mode_sigma_pos ** 2 + d[..., 2] ** 2 / cfg.mode_sigma_yaw ** 2
        score = (torch.exp(-0.5 * q) * w[None, :]).sum(1)
        return x[int(torch.argmax(score))]

    def ess(self) -> float:
        """Effective sample size ``1 / sum w^2`` (1 .. P)."""
        return float(1.0 / torch.exp(2.0 * self._log_w).sum())

    def active_share(self, threshold: float | None = None) -> float:
        """Share of particles with weight above ``threshold`` (default ``config.active_weight`` = 1e-4,
        Table II's "active particles")."""
        thr = self.config.active_weight if threshold is None else float(threshold)
        return float((self.weights > thr).to(torch.float64).mean())

    def _check_invariants(self) -> None:
        if not bool(torch.isfinite(self._states).all()):
            raise RuntimeError("TouchBelief invariant violated: non-finite states")
        w = torch.exp(self._log_w)
        if bool(torch.isnan(self._log_w).any()) or abs(float(w.sum()) - 1.0) > 1e-4:
            raise RuntimeError(f"TouchBelief invariant violated: weights not a distribution (sum {float(w.sum())})")

    # ------------------------------------------------------------------ Sec. V update
    def update(self, z, robot_points, states_traj=None, generator: torch.Generator | None = None,
               resample: bool | None = None) -> dict:
        """One filter step over a trajectory segment of ``K`` waypoints (Sec. V, Eq. 10, App. B).

        Args:
            z: ``(K,)`` bool contact observation after each waypoint.
            robot_points: ``(K, M, 3)`` world points on all the robot's collision geoms at each waypoint.
            states_traj: ``(P, K, 3)`` each particle's state after each waypoint as predicted by a physics
                rollout of the segment from its current state; None: static object (states unchanged).
            generator: random source of resampling.
            resample: override ``config.resample`` for this step (e.g. False at the final step, Sec. VI-B).
        Returns:
            dict with ``ess`` and ``ess_ratio`` (after re-weighing, before resampling), ``resampled``
            (``None`` | ``"systematic"`` | ``"contact"``), ``n_replaced`` (particles replaced by contact
            candidates), ``replaced`` (their slots, ``(n_replaced,)`` long), ``fallback`` (all likelihoods
            were zero), ``distances`` ``(P, K)`` and ``log_likelihood`` ``(P,)``.

        Re-weighing: ``log w_i += sum_k log P(z_k | x_{i,k})`` (the observations of one segment are independent
        given the states), then the particles move to ``states_traj[:, -1]``. Resampling is triggered when
        ``ESS < config.ess_threshold * P`` or by a contact no particle explains; after a contact (the last ``z = 1``
        of the segment) it is contact-aware (:meth:`resample_contact`, around the robot at that waypoint), else
        systematic (:meth:`resample_systematic`); either sets uniform weights.
        """
        cfg = self.config
        zt = _check_z(z)
        if zt.ndim != 1 or zt.numel() == 0:
            raise ValueError(f"z must have shape (K,) with K > 0, got {tuple(zt.shape)}")
        rp = _check_robot_points(robot_points).to(self._states)
        K, P = zt.shape[0], self.num_particles
        if rp.shape[0] != K:
            raise ValueError(f"robot_points must have K = {K} waypoints like z, got {tuple(rp.shape)}")
        if states_traj is None:
            traj = self._states
        else:
            traj = check_states(states_traj, "states_traj", ndim=(3,)).to(self._states)
            if traj.shape[:2] != (P, K):
                raise ValueError(f"states_traj must have shape ({P}, {K}, 3), got {tuple(traj.shape)}")
        d = robot_object_distance(self.obj, traj, rp, cfg.table_height)  # (P, K)
        ll = contact_log_likelihood(zt.to(d.device), d.T, cfg.contact).sum(0)  # (P,)
        new = self._log_w + ll
        fallback = not bool(torch.isfinite(new).any())
        if fallback:
            log.warning("every particle has zero likelihood for this observation; keeping the previous weights")
        else:
            self._log_w = new - torch.logsumexp(new, 0)
        if states_traj is not None:
            self._states = traj[:, -1].clone()
            self._states[:, 2] = wrap_angle(self._states[:, 2])
        if cfg.process_noise_pos > 0 or cfg.process_noise_yaw > 0:
            self._states = self._jitter(self._states, cfg.process_noise_pos, cfg.process_noise_yaw, generator)
        if cfg.history_check:
            self._history.append((zt.to(d.device), rp))
            del self._history[:-cfg.history_segments]
            if cfg.history_motion:  # each particle's own states over this segment (held still: the same state)
                path = traj if traj.ndim == 3 else traj[:, None, :].expand(P, K, 3)
                self._paths.append(path.clone())
                del self._paths[:-cfg.history_segments]
        ess = self.ess()
        out = dict(ess=ess, ess_ratio=ess / P, resampled=None, n_replaced=0,
                   replaced=torch.zeros(0, dtype=torch.long, device=self._states.device), fallback=fallback,
                   distances=d, log_likelihood=ll)
        do = cfg.resample if resample is None else bool(resample)
        # App. B: after a contact (the segment's last z = 1: a guarded stop's trigger, possibly followed by a hold
        # whose end no longer touches a box that slid on) resample contact-aware around the robot at that contact;
        # also when no particle explains it (all farther than explain_distance): the weights then stay nearly
        # uniform (ESS high) although the belief is starved exactly where the evidence is. The candidates touch
        # the robot at the contact instant; a box that slid on during the hold (<~1 cm) is not followed.
        hits = zt.nonzero().squeeze(1)
        kc = int(hits[-1]) if hits.numel() else None
        unexplained = kc is not None and not bool((d[:, kc] <= cfg.explain_distance).any())
        if do and (ess < cfg.ess_threshold * P or (unexplained and cfg.explain_distance > 0)):
            if kc is not None:
                replaced = self.resample_contact(rp[kc], generator, last_distance=d[:, kc], any_weight=unexplained)
                out.update(resampled="contact", n_replaced=int(replaced.numel()), replaced=replaced)
            else:
                self.resample_systematic(generator)
                out.update(resampled="systematic")
        self._check_invariants()
        return out

    # ------------------------------------------------------------------ App. B resampling
    def _jitter(self, states: torch.Tensor, sigma_pos: float, sigma_yaw: float, generator) -> torch.Tensor:
        sig = torch.tensor([sigma_pos, sigma_pos, sigma_yaw], dtype=states.dtype, device=states.device)
        out = states + _randn(states.shape, generator, states) * sig
        out[:, 2] = wrap_angle(out[:, 2])
        return out

    def _draw(self, n: int, generator) -> tuple[torch.Tensor, torch.Tensor]:
        """``n`` states by systematic importance resampling, duplicates (all copies but the first) roughened;
        returns them with their parents' indices ``(n,)``."""
        cfg = self.config
        idx = systematic_resample(self.weights, n, generator)  # sorted
        s = self._states.index_select(0, idx)
        if n > 1 and (cfg.roughening_pos > 0 or cfg.roughening_yaw > 0):
            dup = torch.zeros(n, dtype=torch.bool, device=s.device)
            dup[1:] = idx[1:] == idx[:-1]
            if bool(dup.any()):
                s[dup] = self._jitter(s[dup], cfg.roughening_pos, cfg.roughening_yaw, generator)
        return s, idx

    def _inherited_paths(self, states: torch.Tensor, donors: torch.Tensor) -> list[torch.Tensor]:
        """Kept-segment paths ``(n, K, 3)`` per segment for new states ``(n, 3)``: the path of particle
        ``donors[i]`` shifted by ``states[i] - states[donors[i]]`` (yaw wrapped); ``donors[i] = -1``: the belief's
        weighted mean offset path (a state with no parent moved as the belief expects). The shift is a translation
        and a yaw offset of the whole path, an approximation for the small jitters of resampling and proposals."""
        out = []
        w = self.weights
        for path in self._paths:
            off = path - self._states[:, None, :]  # (P, K, 3) each particle's past relative to its present
            off[..., 2] = wrap_angle(off[..., 2])
            mean = (w[:, None, None] * off).sum(0)  # (K, 3)
            d = donors.clamp_min(0)
            o = torch.where((donors >= 0)[:, None, None], off.index_select(0, d), mean[None])
            p = states[:, None, :] + o
            p[..., 2] = wrap_angle(p[..., 2])
            out.append(p)
        return out

    def resample_systematic(self, generator: torch.Generator | None = None) -> None:
        """Standard importance resampling (App. B, no-contact case): systematic resampling of all ``P``
        particles by weight, duplicates roughened (``config.roughening_*``), then uniform weights."""
        new, idx = self._draw(self.num_particles, generator)
        if self._paths:
            self._paths = self._inherited_paths(new, idx)
        self._states = new
        self._log_w = torch.full_like(self._log_w, -math.log(self.num_particles))
        self._check_invariants()

    @torch.no_grad()
    def contact_candidates(self, robot_points, generator: torch.Generator | None = None,
                           n: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Candidate states near the robot's contact (App. B: "sample M particles near the current robot pose").

        Each candidate starts from a belief particle drawn by weight, jittered by ``config.candidate_sigma_*``
        (keeping the belief's information on yaw and position), then is projected onto the contact manifold
        of the robot at ``robot_points (M, 3)`` by ``config.projection_iterations`` Newton steps on the signed
        robot-object distance ``phi = min_m sdf(T^-1 p_m)``: ``t <- t + phi n / |n|^2`` in the plane, with
        ``n`` the world-frame SDF gradient at the nearest (or deepest) robot point (steps capped at
        ``config.max_projection_step``). So the object's surface passes near the robot wherever the belief
        placed it. Simplification: the projection translates only (yaw is kept); a robot point above or below
        the object (``n`` nearly vertical) cannot be reached and its candidate stays far (it then loses).

        Returns:
            ``states (n, 3)`` (default ``n = config.contact_samples``) and their signed distances ``(n,)`` (m,
            negative: penetration).
        """
        cfg = self.config
        rp = _check_robot_points(robot_points[None] if torch.is_tensor(robot_points) and robot_points.ndim == 2
                                 else robot_points)
        if rp.shape[0] != 1:
            raise ValueError(f"robot_points must have shape (M, 3), got {tuple(rp.shape)}")
        rp = rp[0].to(self._states)
        n = cfg.contact_samples if n is None else int(n)
        dev = generator.device if generator is not None else torch.device("cpu")
        j = torch.multinomial(self.weights.to(dev, torch.float64), n, replacement=True,
                              generator=generator).to(self._states.device)
        s = self._jitter(self._states.index_select(0, j), cfg.candidate_sigma_pos, cfg.candidate_sigma_yaw,
                         generator)
        donors = j.clone()
        # objects without bounds (e.g. the ablation's analytic planar box) draw every candidate from the belief
        n_local = int(round(cfg.contact_local_share * n)) if hasattr(self.obj, "bounds") else 0
        if n_local > 0:
            # App. B "near the current robot pose": a share of the candidates is drawn around the robot's low part
            # (its points below the object's top: what can touch a resting object), uniform in a disc of the
            # footprint radius, any yaw; they reach the contact manifold even when no belief particle is near it
            top = cfg.table_height + float(self.obj.bounds[1, 2])
            low = rp[rp[:, 2] <= top]
            c = (low if len(low) else rp[rp[:, 2].argmin()][None])[:, :2].mean(0)
            r = footprint_radius(self.obj)
            u = torch.rand(n_local, 3, generator=generator, dtype=torch.float64, device=dev).to(s)
            rad, ang = r * u[:, 0].sqrt(), 2 * math.pi * u[:, 1]
            loc = torch.stack([c[0] + rad * torch.cos(ang), c[1] + rad * torch.sin(ang),
                               (2 * u[:, 2] - 1) * math.pi], dim=1)
            s = torch.cat([s[: n - n_local], loc])
            donors[n - n_local:] = -1
        self._donors = donors
        ar = torch.arange(n, device=s.device)
        for _ in range(cfg.projection_iterations):
            poses = se2_to_pose(s, cfg.table_height)
            v, g = self.obj.sdf_world(poses, rp)  # (n, M), object-frame unit gradients (n, M, 3)
            m = v.argmin(1)
            phi = v[ar, m].to(s)
            nw = (poses[:, :3, :3] @ g[ar, m].to(s).unsqueeze(-1)).squeeze(-1)[:, :2]  # world gradient, plane
            step = phi.unsqueeze(-1) * nw / nw.square().sum(-1, keepdim=True).clamp_min(1e-4)
            norm = step.norm(dim=-1, keepdim=True)
            step = step * (cfg.max_projection_step / norm.clamp_min(cfg.max_projection_step))
            s = s.clone()
            s[:, :2] += step
        sd = signed_robot_object_distance(self.obj, s, rp[None], cfg.table_height)[:, 0]
        return s, sd

    @torch.no_grad()
    def history_log_likelihood(self, states: torch.Tensor, paths: list[torch.Tensor] | None = None) -> torch.Tensor:
        """``(n,)`` log-likelihood of the kept observation segments (``config.history_segments``, newest
        included) for states ``(n, 3)`` held still over all of them: ``sum_s sum_k log P(z_{s,k} | d(x, robot_{s,k}))``
        of Eq. 10. The particles' own history lives in their weights, but resampling resets those; this scores
        candidates and the particles they would replace on equal terms. Approximation (stated): a state is held
        where it is now over the past segments, so a box the pokes pushed by ``delta`` makes old contacts look
        ``delta`` away for every state alike (the comparison stays fair; its absolute value drops). ``paths``: one
        ``(n, K, 3)`` per kept segment, the states' own past over it (``config.history_motion``) instead."""
        cfg = self.config
        total = torch.zeros(states.shape[0], dtype=self._states.dtype, device=self._states.device)
        for s, (z, rp) in enumerate(self._history):
            x = states if paths is None else paths[s]
            d = robot_object_distance(self.obj, x.to(self._states), rp, cfg.table_height)  # (n, K)
            total += contact_log_likelihood(z, d.T, cfg.contact).sum(0)
        return total

    def resample_contact(self, robot_points, generator: torch.Generator | None = None,
                         last_distance: torch.Tensor | None = None, any_weight: bool = False) -> torch.Tensor:
        """Contact-aware resampling (App. B, after a contact observation); returns the replaced slots ``(R,)``.

        1. ``M = config.contact_samples`` candidates on the contact manifold of the robot at ``robot_points
           (M_r, 3)`` (:meth:`contact_candidates`), scored with the smooth model ``P(z=1 | x)`` (Eq. 10 with the
           configured alpha / gamma, whatever ``config.contact.kind``); candidates penetrating deeper than
           ``config.max_penetration`` score 0.
        2. Low-weight particles (``w < config.replace_below / P``, lowest first, at most
           ``config.max_replace_fraction * P``) are paired with the best candidates; a particle is replaced when
           its candidate matches the contact better than it does (higher ``P(z=1 | x)`` at ``last_distance``
           ``(P,)``, its distance at this waypoint; computed when None). ``any_weight``: every particle counts as
           low-weight (lowest first): for a contact that no particle explains, where the weights stay near uniform.
           With ``config.history_check`` (beyond the paper) "better" means a higher log-likelihood of the whole kept
           history (:meth:`history_log_likelihood`) than both the replaced particle and the belief's weighted
           median particle, and candidates are ranked by it.
        3. The other ``P - R`` slots are filled by systematic importance resampling of the current particles
           (duplicates roughened), as in the no-contact case.
        4. Weights are set uniform (the paper: "immediately after resampling, the share of active particles would
           trivially be one"). The candidates carry no observation history, so this moves the replaced share
           ``R / P`` of the posterior onto the contact manifold: a deliberate bias against particle starvation,
           not an exact Bayesian step.
        """
        cfg = self.config
        P = self.num_particles
        smooth = replace(cfg.contact, kind="smooth")
        rp = robot_points if torch.is_tensor(robot_points) else torch.as_tensor(robot_points)
        cand, sd = self.contact_candidates(rp, generator)
        shallow = sd >= -cfg.max_penetration
        if cfg.history_check and self._history:
            # the whole kept history decides, not the current contact alone (TouchFilterConfig.history_check).
            # (Candidates and particles are scored in two calls: one call on both, concatenated, gave other floats
            # here, which changed a grasp-box-1 episode; the two calls reproduce the measured Table I.)
            cand_paths = self._inherited_paths(cand, self._donors) if self._paths else None
            ll = self.history_log_likelihood(cand, cand_paths)
            score = torch.where(shallow, ll, torch.full_like(ll, -math.inf))
            own = self.history_log_likelihood(self._states, self._paths or None)
            # ... and must be at least as plausible as a typical particle of the belief (its weighted median):
            # beating a ruled-out low-weight particle alone would fill up to half the belief with poor candidates
            # at the uniform weights that follow
            srt = torch.argsort(own)
            cw = torch.cumsum(self.weights[srt], 0)
            typical = own[srt[int(torch.searchsorted(cw, cw[-1] * 0.5).clamp_max(len(cw) - 1))]]
            own = own.clamp_min(typical)
        else:
            if last_distance is None:
                last_distance = robot_object_distance(self.obj, self._states, rp[None], cfg.table_height)[:, 0]
            one = torch.ones(1, dtype=torch.bool)
            score = contact_likelihood(one, sd[None], smooth)[0]
            score = torch.where(shallow, score, torch.zeros_like(score))
            own = contact_likelihood(one, last_distance.to(self._states)[None], smooth)[0]
        w = self.weights
        low = torch.arange(P, device=w.device) if any_weight else (w * P < cfg.replace_below).nonzero().squeeze(1)
        low = low[torch.argsort(w[low], stable=True)]
        n = min(low.numel(), cand.shape[0], int(cfg.max_replace_fraction * P))
        order = torch.argsort(score, descending=True, stable=True)[:n]
        slots = low[:n]
        better = score[order] > own[slots]
        slots, order = slots[better], order[better]
        R = int(slots.numel())
        keep = torch.ones(P, dtype=torch.bool, device=self._states.device)
        keep[slots] = False
        new = torch.empty_like(self._states)
        if P - R > 0:
            drawn, idx = self._draw(P - R, generator)
            new[keep] = drawn
        if self._paths:  # the drawn particles inherit their parents' paths, the candidates their donors'
            paths = [torch.empty_like(p) for p in self._paths]
            if P - R > 0:
                for p, q in zip(paths, self._inherited_paths(drawn, idx)):
                    p[keep] = q
            if R:
                for p, q in zip(paths, self._inherited_paths(cand[order], self._donors[order])):
                    p[slots] = q
            self._paths = paths
        new[slots] = cand[order]
        self._states = new
        self._log_w = torch.full_like(self._log_w, -math.log(P))
        self._check_invariants()
        return slots
