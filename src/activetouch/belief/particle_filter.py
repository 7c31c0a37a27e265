"""The RUMI pose particle belief ``p(T | X)`` (RUMI section IV-A and IV-D, Algorithms 1-5).

Weights are not recursive: every update re-weighs the particles on the full merged feature set X_t
(Algorithm 1 lines 15-20, Algorithm 2), as the paper does.

Robustness (documented behaviour, tested in tests/test_belief.py):

* empty features: every discrepancy is 0, so weights are uniform (Eq. 3 is an empty sum) and no resample;
* NaN/inf feature positions or poses, non-rigid poses (``geometry.check_poses``), ``lam`` NaN or < 0, a prior
  whose size is not ``config.num_particles``, or too few particles for CHSEL: ``ValueError``;
* non-finite discrepancies (e.g. +inf for some particles): those particles get weight 0; if no particle
  has a finite discrepancy the weights fall back to uniform with a logged warning (there is no
  information to prefer any particle);
* the belief never holds NaN: ``_check_invariants`` runs after every change and raises ``RuntimeError``.
"""
from __future__ import annotations

import logging
import math
from dataclasses import replace

import torch

from ..geometry import check_poses
from .config import BeliefConfig, chsel_min_batch
from .discrepancy import discrepancy as _discrepancy
from .discrepancy import discrepancy_and_objective as _discrepancy_and_objective
from .objmove import obj_move as _obj_move
from .objmove import project_se2_motion
from .optimise import optimise_poses
from .resample import perturb_poses, systematic_resample

__all__ = ["ParticleBelief", "boltzmann_weights"]

log = logging.getLogger(__name__)


def boltzmann_weights(l: torch.Tensor, lam: float) -> torch.Tensor:
    """Normalised weights ``(P,)`` from discrepancies ``l (P,)`` (Algorithm 2, Eq. 10).

    ``w_i = exp(-lam (l_i - min l)) / sum``: the minimum is subtracted for numerical stability (section
    IV-D). Particles with a non-finite (NaN or +inf) discrepancy get weight 0; if none is finite the
    weights are uniform and a warning is logged. ``lam`` must be finite and >= 0 (Eq. 10 has lam > 0;
    0 gives uniform weights over the finite particles); anything else raises ``ValueError``.
    """
    try:
        lam_f = float(lam)
    except (TypeError, ValueError, RuntimeError):
        raise ValueError(f"lam must be a finite number >= 0, got {lam!r}") from None
    if not math.isfinite(lam_f) or lam_f < 0:
        raise ValueError(f"lam must be a finite number >= 0 (Eq. 10 peakiness), got {lam!r}")
    if l.ndim != 1 or l.numel() == 0:
        raise ValueError(f"discrepancies must have shape (P,) with P > 0, got {tuple(l.shape)}")
    l = l.detach()
    finite = torch.isfinite(l)
    if not bool(finite.any()):
        log.warning("no particle has a finite discrepancy; falling back to uniform weights")
        return torch.full_like(l, 1.0 / l.numel())
    lf = torch.where(finite, l, torch.zeros_like(l))
    lmin = lf[finite].min()
    w = torch.where(finite, torch.exp(-lam_f * (lf - lmin)), torch.zeros_like(l))
    return w / w.sum()  # the minimum particle has weight 1 before normalising, so the sum is >= 1


class ParticleBelief:
    """Weighted pose particles ``T_{1..P}`` (object -> world) of a known object.

    Args:
        obj: ``KnownObject``.
        poses: ``(P, 4, 4)`` pose particles.
        weights: ``(P,)`` non-negative weights (normalised here); None: uniform.
        config: ``BeliefConfig`` (Table IV defaults).
    """

    def __init__(self, obj, poses: torch.Tensor, weights: torch.Tensor | None = None,
                 config: BeliefConfig | None = None):
        self.obj = obj
        self.config = config if config is not None else BeliefConfig()
        poses = check_poses(poses, "poses")
        if poses.ndim != 3 or poses.shape[0] == 0:
            raise ValueError(f"poses must have shape (P, 4, 4) with P > 0, got {tuple(poses.shape)}")
        self._poses = poses.detach().clone()
        if weights is None:
            w = torch.full((poses.shape[0],), 1.0 / poses.shape[0], dtype=poses.dtype, device=poses.device)
        else:
            w = torch.as_tensor(weights).to(device=poses.device, dtype=poses.dtype)
            if w.shape != (poses.shape[0],):
                raise ValueError(f"weights must have shape ({poses.shape[0]},), got {tuple(w.shape)}")
            if not bool(torch.isfinite(w).all()) or bool((w < 0).any()) or not float(w.sum()) > 0:
                raise ValueError("weights must be finite, non-negative and not all zero")
            w = w / w.sum()
        self._weights = w.detach().clone()
        #: ``(P,)`` discrepancies of the last weigh/update (None before the first).
        self.last_discrepancy: torch.Tensor | None = None
        #: ``(n, generator) -> (n, 4, 4)`` prior sampler used by ``config.reinvigorate`` (None: off).
        self.proposal = None
        #: particles replaced by placed prior proposals at the last resample (0 when off or none won).
        self.last_reinvigorated = 0
        self._model_points: torch.Tensor | None = None  # (2000, 3) object surface samples for the placement
        self._model_normals: torch.Tensor | None = None  # (2000, 3) their outward normals (None: no mesh)
        self._check_invariants()

    # ------------------------------------------------------------------ state
    @property
    def poses(self) -> torch.Tensor:
        """``(P, 4, 4)`` pose particles (object -> world)."""
        return self._poses

    @property
    def weights(self) -> torch.Tensor:
        """``(P,)`` normalised weights."""
        return self._weights

    @property
    def num_particles(self) -> int:
        return self._poses.shape[0]

    @property
    def device(self) -> torch.device:
        return self._poses.device

    def best_pose(self) -> torch.Tensor:
        """``(4, 4)`` particle with the largest weight."""
        return self._poses[int(torch.argmax(self._weights))]

    def active_share(self, threshold: float | None = None) -> float:
        """Share of particles with weight above ``threshold`` (default ``config.active_weight`` = 1e-4)."""
        thr = self.config.active_weight if threshold is None else float(threshold)
        return float((self._weights > thr).float().mean())

    def _check_invariants(self) -> None:
        if not bool(torch.isfinite(self._poses).all()):
            raise RuntimeError("ParticleBelief invariant violated: non-finite poses")
        w = self._weights
        if not bool(torch.isfinite(w).all()) or bool((w < 0).any()) or abs(float(w.sum()) - 1.0) > 1e-4:
            raise RuntimeError(f"ParticleBelief invariant violated: weights not a finite distribution (sum {float(w.sum())})")

    # ------------------------------------------------------------------ Eq. 3
    def discrepancy(self, features, poses: torch.Tensor | None = None) -> torch.Tensor:
        """``C^(X, T_i)`` ``(P,)`` for the belief's particles (or the given ``poses (K, 4, 4)``), Eq. 3."""
        cfg = self.config
        return _discrepancy(self.obj, features, self._poses if poses is None else poses,
                            free_scale=cfg.free_scale, violation_tolerance=cfg.violation_tolerance,
                            exact=cfg.exact_sdf)

    def _cost_fn(self, features):
        """``T -> (C^(X, T), J(X, T))`` for Algorithms 4 and 5: descend J (Eq. 7-9), keep the lowest C^
        (``config.opt_objective="linear_hinge"``: ``T -> C^(X, T)``, descend C^ itself)."""
        cfg = self.config
        if cfg.opt_objective == "linear_hinge":
            return lambda T: self.discrepancy(features, T)
        return lambda T: _discrepancy_and_objective(self.obj, features, T, free_scale=cfg.free_scale,
                                                    violation_tolerance=cfg.violation_tolerance,
                                                    exact=cfg.exact_sdf)

    # ------------------------------------------------------------------ Algorithm 2
    def weigh(self, features) -> torch.Tensor:
        """WeighParticles (Algorithm 2): ``w_i ∝ exp(-lam C^(X, T_i))``; sets and returns the weights ``(P,)``."""
        with torch.no_grad():
            l = self.discrepancy(features)
        self.last_discrepancy = l
        self._weights = boltzmann_weights(l, self.config.lam)
        self._check_invariants()
        return self._weights

    # ------------------------------------------------------------------ Algorithm 1 lines 15-20
    def resample_statistic(self, l: torch.Tensor) -> float:
        """Max discrepancy (Alg. 1 line 16) or its ``config.resample_percentile``-th percentile."""
        finite = l[torch.isfinite(l)]
        if finite.numel() < l.numel():
            return float("inf")
        if self.config.resample_percentile is None:
            return float(l.max())
        return float(torch.quantile(l.double(), float(self.config.resample_percentile) / 100.0))

    def update(self, features, generator: torch.Generator | None = None) -> bool:
        """Correction step on the merged features X_t (Algorithm 1 lines 15-20).

        Computes ``l = C^(X_t, T)``; if ``max(l) > l_r`` (or the configured percentile), resamples
        (Algorithm 4) and sets uniform weights (line 18), else re-weighs (line 20). Returns True when it
        resampled. The importance weights of Algorithm 4 line 1 are those of ``l`` (Algorithm 2 on X_t): the
        weights carried from the previous step do not know the newest features, and since RUMI's weights
        are not recursive (they are recomputed from all of X_t) these are the current posterior weights.
        """
        cfg = self.config
        with torch.no_grad():
            l = self.discrepancy(features)
        self.last_discrepancy = l
        self.last_reinvigorated = 0
        if self.resample_statistic(l) > cfg.resample_threshold:
            w = boltzmann_weights(l, cfg.lam)
            self._resample(features, w, generator)
            resampled = True
        else:
            if cfg.reinvigorate_every_step and cfg.reinvigorate > 0 and self.proposal is not None and len(features) > 0:
                # the resample-move step also between resamples: once every particle fits the evidence (max C^ <
                # l_r) no resample brings proposals, and a cluster on a wrong pose that fits converges (APC) while
                # a placement at another pose fits as well (beyond the paper, BeliefConfig.reinvigorate_every_step)
                self._poses = self._reinvigorate(features, self._poses.detach(), l, generator).detach()
                l = self.last_discrepancy
            self._weights = boltzmann_weights(l, cfg.lam)
            resampled = False
        self._check_invariants()
        return resampled

    # ------------------------------------------------------------------ Algorithm 4
    def resample(self, features, generator: torch.Generator | None = None) -> None:
        """Resample (Algorithm 4) with the current weights, then set uniform weights (Alg. 1 line 18)."""
        self._resample(features, self._weights, generator)
        self._check_invariants()

    def _resample(self, features, weights: torch.Tensor, generator) -> None:
        cfg = self.config
        idx = systematic_resample(weights, self.num_particles, generator)  # line 1
        poses = perturb_poses(self._poses[idx], cfg.sigma_t, cfg.sigma_R, cfg.se2, generator)  # lines 2-3
        costs = None
        if cfg.n_opt > 0 and len(features) > 0:  # lines 4-6
            poses, costs = optimise_poses(self._cost_fn(features), poses, cfg.n_opt, cfg.opt_lr_t, cfg.opt_lr_R,
                                          cfg.se2)
            self.last_discrepancy = costs
        self.last_reinvigorated = 0
        if cfg.reinvigorate > 0 and self.proposal is not None and len(features) > 0:
            poses = self._reinvigorate(features, poses.detach(), costs, generator)
        self._poses = poses.detach()
        self._weights = torch.full_like(self._weights, 1.0 / self.num_particles)

    def _reinvigorate(self, features, poses: torch.Tensor, costs: torch.Tensor | None, generator) -> torch.Tensor:
        """A resample-move step with contact-placed prior proposals (beyond the paper, ``config.reinvigorate``;
        see :mod:`activetouch.belief.reinvigorate`). ``poses (P, 4, 4)``, ``costs (P,)`` their C^ (None: computed
        here). Returns the new ``(P, 4, 4)``.

        ``reinvigorate`` prior draws are placed on the observed surface points; the ``reinvigorate_share P`` of
        lowest C^ get Algorithm 4's N_o optimisation steps; each is then paired with a distinct particle drawn
        uniformly and replaces it with the Metropolis probability ``min(1, exp(-lam (C_p - C_i)))`` of the
        posterior of Eq. 10 (Algorithm 2): an independence-proposal move (Gilks and Berzuini's resample-move),
        whose proposal density is taken as uniform over the placements. Proposals that fit the evidence as well
        as the particles enter as often as they leave, so the particle set keeps the poses the evidence cannot
        tell apart, and APC stays high until it can.
        """
        from .discrepancy import SURFACE
        from .reinvigorate import model_surface, place_on_surface

        cfg = self.config
        surface = features.positions[features.semantics == SURFACE]
        if surface.shape[0] == 0:
            return poses
        if self._model_points is None:
            pts, normals = model_surface(self.obj, 2000, seed=0)
            self._model_points = pts.to(poses)
            self._model_normals = None if normals is None else normals.to(poses)
        cand = check_poses(self.proposal(cfg.reinvigorate, generator), "proposal poses").to(poses)
        cand = place_on_surface(self._model_points, cand, surface, generator,
                                model_normals=self._model_normals if cfg.reinvigorate_normals else None)
        with torch.no_grad():
            if costs is None:
                costs = self.discrepancy(features, poses)
            lc = self.discrepancy(features, cand)
        m = max(1, min(cand.shape[0], int(cfg.reinvigorate_share * self.num_particles)))
        best = torch.argsort(lc)[:m]
        cand, lc = cand[best], lc[best]
        if cfg.n_opt > 0:
            cand, lc = optimise_poses(self._cost_fn(features), cand, cfg.n_opt, cfg.opt_lr_t, cfg.opt_lr_R, cfg.se2)
        gdev = generator.device if generator is not None else torch.device("cpu")
        target = torch.randperm(self.num_particles, generator=generator, device=gdev)[:m].to(poses.device)
        u = torch.rand(m, generator=generator, device=gdev, dtype=poses.dtype).to(poses.device)
        log_ratio = -float(cfg.lam) * (lc - costs[target])
        accept = torch.isfinite(lc) & (torch.log(u) < log_ratio)
        k = int(accept.sum())
        if k:
            poses = poses.clone()
            costs = costs.clone()
            poses[target[accept]] = cand[accept]
            costs[target[accept]] = lc[accept]
        self.last_reinvigorated = k
        self.last_discrepancy = costs
        return poses

    # ------------------------------------------------------------------ Algorithm 1 lines 11-13
    def predict(self, dT: torch.Tensor, generator: torch.Generator | None = None, noise: bool = True) -> None:
        """Prediction step: ``T_i <- dT_sigma . dT . T_i`` (Algorithm 1 lines 11-13).

        Args:
            dT: ``(4, 4)`` world-frame object motion (``T_new = dT @ T``; from the simulator or the ``dT_w`` of
                :meth:`obj_move`). With ``config.se2`` it is projected onto a planar motion (yaw about world
                z, x-y translation) so particles stay upright at their height.
            generator: torch generator for PerturbTransform (Algorithm 3).
            noise: False applies ``dT`` exactly (``dT_sigma = I``): for motions too small to count as the
                object "moving" in Alg. 1 line 11 (physics settling) that must still carry the particles along.
        The perturbation ``dT_sigma`` is applied about each particle's own origin (see
        :func:`activetouch.belief.resample.apply_perturbation`).
        """
        dT = check_poses(dT, "dT")
        if dT.shape != (4, 4):
            raise ValueError(f"dT must have shape (4, 4), got {tuple(dT.shape)}")
        dT = dT.to(self._poses)
        if self.config.se2:
            dT = project_se2_motion(dT)
        moved = dT @ self._poses
        if noise:
            moved = perturb_poses(moved, self.config.sigma_t, self.config.sigma_R, self.config.se2, generator)
        self._poses = moved
        self._check_invariants()

    # ------------------------------------------------------------------ Algorithm 5
    def obj_move(self, prev, new, dT_r: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """ObjMove (Algorithm 5): estimate the object's motion from the new features.

        Args:
            prev: ``Features`` X_{t-1} (picks the lowest-discrepancy particle T_i, line 2-3).
            new: ``Features`` X'_t: N_o Adam steps on ``dT_w T_i`` descend the Eq. 7-9 gradient
                (:func:`~activetouch.belief.discrepancy.optimisation_objective`) and keep the lowest ``C^(X', .)``.
            dT_r: ``(4, 4)`` world-frame end-effector motion in contact (sticking-contact prior; None = I).
        Returns:
            ``(dT, dT_w)``: ``dT (4, 4)`` the object-frame (body) motion ``T_i^-1 dT_w T_i`` and ``dT_w (4, 4)``
            the world-frame motion (``T_new = dT_w @ T``, world points ``x' = dT_w x``). See
            :mod:`activetouch.belief.objmove` for the frame algebra.
        """
        cfg = self.config
        with torch.no_grad():
            l_prev = self.discrepancy(prev)
        dT_r = None if dT_r is None else torch.as_tensor(dT_r).to(self._poses)
        return _obj_move(self._cost_fn(new), l_prev, self._poses, dT_r, cfg.n_opt, cfg.opt_lr_t, cfg.opt_lr_R,
                         cfg.se2)

    # ------------------------------------------------------------------ Algorithm 1 lines 1-3
    @classmethod
    def from_prior(cls, obj, prior_poses: torch.Tensor, features, config: BeliefConfig | None = None,
                   use_chsel: bool = True, generator: torch.Generator | None = None,
                   **config_overrides) -> "ParticleBelief":
        """Initial belief from prior particles ``T_{0,1..P}`` and the first features X_0 (Alg. 1 lines 2-3).

        Args:
            obj: ``KnownObject``.
            prior_poses: ``(P, 4, 4)`` prior particles (see :mod:`activetouch.belief.priors`), rigid, with
                ``P == config.num_particles`` (``ValueError`` otherwise).
            features: ``Features`` X_0.
            config: ``BeliefConfig``; ``config_overrides`` replace its fields (e.g. ``chsel_iterations=2``).
            use_chsel: register the prior with CHSEL (line 2, slow: ~10 s on a CPU). False keeps the prior
                particles (faster, less accurate); either way the particles are then weighed (line 3).
                Without any SURFACE feature CHSEL is skipped with a warning. CHSEL needs at least
                :func:`~activetouch.belief.config.chsel_min_batch` particles (``MIN_PARTICLES`` = 10 with the
                default 5 rounds): ``ValueError`` below that, before any registration work.
            generator: torch generator (CHSEL's random numbers are seeded from it).
        """
        config = config if config is not None else BeliefConfig()
        if config_overrides:
            unknown = set(config_overrides) - set(BeliefConfig.field_names())
            if unknown:
                raise ValueError(f"unknown BeliefConfig fields: {sorted(unknown)}")
            config = replace(config, **config_overrides)
        prior = check_poses(prior_poses, "prior_poses")
        if prior.ndim != 3 or prior.shape[0] == 0:
            raise ValueError(f"prior_poses must have shape (P, 4, 4) with P > 0, got {tuple(prior.shape)}")
        if prior.shape[0] != config.num_particles:
            raise ValueError(f"prior_poses holds {prior.shape[0]} poses but config.num_particles is "
                             f"{config.num_particles}: draw {config.num_particles} prior poses or set "
                             f"num_particles={prior.shape[0]}")
        if use_chsel:
            B = prior.shape[0] if config.chsel_batch is None else min(config.chsel_batch, prior.shape[0])
            need = chsel_min_batch(config.chsel_iterations)
            if B < need:
                raise ValueError(f"CHSEL initialisation with {config.chsel_iterations} round(s) needs at least "
                                 f"{need} particles, got {B} (see activetouch.belief.MIN_PARTICLES); use more "
                                 f"particles or use_chsel=False (--no-chsel)")
        poses = prior
        if use_chsel:
            from .discrepancy import SURFACE

            if int((features.semantics == SURFACE).sum()) == 0:
                log.warning("no surface features: skipping CHSEL, keeping the prior particles")
            else:
                from .chsel_init import chsel_register

                poses = chsel_register(obj, prior, features, config, generator)
        belief = cls(obj, poses, None, config)
        belief.weigh(features)
        return belief

    def __repr__(self) -> str:
        return (f"ParticleBelief({getattr(self.obj, 'name', self.obj)!r}, P={self.num_particles}, "
                f"active={self.active_share():.2f})")

