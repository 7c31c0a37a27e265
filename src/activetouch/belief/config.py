"""Configuration of the RUMI pose particle belief (RUMI Table IV defaults)."""
from __future__ import annotations

import math
from dataclasses import dataclass, fields

__all__ = ["BeliefConfig", "MIN_PARTICLES", "chsel_min_batch"]


def chsel_min_batch(chsel_iterations: int) -> int:
    """Smallest number of particles CHSEL (chsel 0.2.1, Algorithm 1 line 2) registers without failing.

    Measured on the mug (tests/test_belief.py scenario) and read from chsel / pyribs 0.2.1 / 0.x:

    * between registration rounds chsel re-initialises around the ``int(0.2 B)`` best transforms and samples
      with their standard deviation (``chsel.initialization.reinitialize_transform_around_elites``); fewer
      than 2 elites give a NaN std and NaN poses (B = 2..9 with the default 5 rounds: "points_obj contains
      NaN or inf"), so more than one round needs ``B >= 10``;
    * its quality-diversity step runs pyribs' ``GradientArborescenceEmitter`` with ``batch_size = B - 1``,
      whose CMA-ES keeps ``batch_size // 2`` parents: B = 1 raises ``IndexError``; B = 2 keeps no parent
      (NaN strategy parameters, pyribs warns ``mueff = 0 / 0``; its poses happened to stay finite in our
      runs), so a single round needs ``B >= 3``.
    """
    return 10 if int(chsel_iterations) > 1 else 3


#: Smallest particle count (P) the default belief set-up (CHSEL initialisation with the default 5 rounds)
#: accepts; :meth:`ParticleBelief.from_prior` raises below it when CHSEL is used. Without CHSEL
#: (``use_chsel=False``, the CLI's ``--no-chsel``) any P >= 1 works.
MIN_PARTICLES = chsel_min_batch(5)


@dataclass(frozen=True)
class BeliefConfig:
    """Parameters of the pose particle filter (RUMI section IV-A, IV-D, Algorithms 1-6, Table IV).

    Table IV values: ``num_particles`` (P) = 100, ``lam`` (lambda, peakiness) = 2, ``resample_threshold``
    (l_r) = 5, ``free_scale`` (C) = 10, ``sigma_t`` = 10 mm, ``sigma_R`` = 0, ``n_opt`` (N_o) = 10,
    ``r_free`` (r_d,f) = 10 mm, ``r_surface`` (r_d,s) = 2 mm, ``beta_t`` = 0.03.

    Not in Table IV (choices documented here):

    * ``violation_tolerance`` (m): the paper's alpha of Eq. 4-5 is ``-violation_tolerance``. chsel 0.2.1
      (``costs.FreeSpaceLookupCost``: "alpha < 0 to tolerate some amount of penetration ...
      surface_threshold = -alpha") implements ``max(0, -surface_threshold - sdf)`` and its ``CHSEL`` wrapper
      defaults ``surface_threshold`` to the registration ``resolution``. We use 4 mm, the CHSEL resolution
      that works for the thin-walled mug (LIBRARY-NOTES), so the filter's cost and CHSEL's agree.
    * ``opt_lr_t`` / ``opt_lr_R``: Adam step sizes (m, rad) of the N_o pose optimisation steps of Algorithm 4
      and 5. chsel's own SGD uses Adam with lr 0.01 for both; we found a smaller translation step converges to
      the mm level within N_o = 10 steps (see tests/test_belief.py).
    * ``resample_percentile``: None uses the max discrepancy (Alg. 1 line 16); a value in (0, 100] uses that
      percentile instead ("for better robustness against outlier pose samples", section IV-D).
    * ``exact_sdf``: evaluate the exact mesh SDF instead of the voxel cache (slow; for checks).
    * ``opt_objective``: what the N_o Adam steps of Algorithms 4 and 5 descend (each particle keeps its iterate
      with the lowest discrepancy C^ either way). ``"squared_hinge"`` (default, the paper): the objective
      ``sum k r^2 / 2`` whose gradient is Eq. 7-9, residual times SDF gradient. ``"linear_hinge"``: the autograd
      gradient of C^ itself (Eq. 3-6), every violation pulling equally hard - the behaviour before Eq. 7-9 was
      followed. Measured on the side-camera mug of tests/test_belief.py (100 particles 6 mm / 0.1 rad off,
      one Resample, 3 seeds): median C^ after the 10 steps 1.3-1.7 with ``"squared_hinge"`` against 1.0-1.3
      with ``"linear_hinge"`` (median translation error 1.5-1.9 vs 1.1-1.3 mm); Adam's normalised steps shrink
      with the residuals of the squared hinge, not with those of the linear one.
    * ``num_particles`` may be any P >= 1, but CHSEL initialisation needs at least
      :func:`chsel_min_batch` particles (:data:`MIN_PARTICLES` = 10 with the default 5 rounds):
      ``ParticleBelief.from_prior(use_chsel=True)`` raises below it.
    * ``chsel_*``: CHSEL (Alg. 1 line 2) registration settings. ``chsel_batch=None`` registers all P prior
      particles (the paper); ``chsel_qd_iterations`` is chsel's n_o (its default 100). ``chsel_max_points``:
      CHSEL registers against at most this many points of each semantics class (a seeded random subset, free
      points first restricted to those that can touch a prior particle); a camera view holds ~60k free points
      and CHSEL's cost grows linearly with them (LIBRARY-NOTES checked 250 surface + 200 free points).
    * ``reinvigorate`` / ``reinvigorate_share`` (beyond the paper, 0 = off = Algorithm 4 as published): at each
      resample with surface evidence, this many fresh prior draws are placed on the observed surface points
      (:mod:`activetouch.belief.reinvigorate`), the best ``reinvigorate_share`` P of them are optimised like the
      resampled particles and each replaces a random particle with the Metropolis probability
      ``min(1, exp(-lam (C_p - C_i)))`` (a resample-move step). Needs the belief's ``proposal``
      (the task's prior sampler, set by the episode). The drill and box tasks turn it on (``TaskSpec.belief_defaults``).
      ``reinvigorate_normals`` (default True): each placement also turns the draw about the world z axis so the
      model's normal matches the observed patch's normal there (``reinvigorate.place_on_surface``); False places
      with the drawn yaw (the first version of the proposals). ``reinvigorate_every_step`` (default False): the
      same move also at updates that do not resample (Alg. 1 line 20), so a proposal that fits the evidence as
      well as the particles can enter after every particle already fits.
    """

    num_particles: int = 100
    lam: float = 2.0
    resample_threshold: float = 5.0
    free_scale: float = 10.0
    sigma_t: float = 0.010
    sigma_R: float = 0.0
    n_opt: int = 10
    r_free: float = 0.010
    r_surface: float = 0.002
    beta_t: float = 0.03
    se2: bool = True
    resample_percentile: float | None = None
    violation_tolerance: float = 0.004
    opt_lr_t: float = 0.003
    opt_lr_R: float = 0.03
    exact_sdf: bool = False
    opt_objective: str = "squared_hinge"
    active_weight: float = 1e-4
    chsel_iterations: int = 5
    chsel_batch: int | None = None
    chsel_qd_iterations: int = 100
    chsel_resolution: float = 0.004
    chsel_max_points: int = 500
    reinvigorate: int = 0
    reinvigorate_share: float = 0.2
    reinvigorate_normals: bool = True
    reinvigorate_every_step: bool = False

    def __post_init__(self):
        def _pos(name, allow_zero=False):
            v = getattr(self, name)
            ok = math.isfinite(float(v)) and (v >= 0 if allow_zero else v > 0)
            if not ok:
                raise ValueError(f"BeliefConfig.{name} must be finite and {'>= 0' if allow_zero else '> 0'}, got {v!r}")

        for name in ("num_particles", "n_opt", "chsel_iterations", "chsel_qd_iterations", "chsel_max_points",
                     "reinvigorate"):
            v = getattr(self, name)
            lowest = 0 if name in ("n_opt", "reinvigorate") else 1
            if not isinstance(v, int) or isinstance(v, bool) or v < lowest:
                raise ValueError(f"BeliefConfig.{name} must be an int >= {lowest}, got {v!r}")
        for name in ("lam", "resample_threshold", "free_scale", "r_free", "r_surface", "beta_t", "opt_lr_t",
                     "opt_lr_R", "chsel_resolution"):
            _pos(name)
        for name in ("sigma_t", "sigma_R", "violation_tolerance", "active_weight"):
            _pos(name, allow_zero=True)
        for name in ("reinvigorate_normals", "reinvigorate_every_step"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"BeliefConfig.{name} must be true or false, got {getattr(self, name)!r}")
        if not (math.isfinite(float(self.reinvigorate_share)) and 0.0 < float(self.reinvigorate_share) <= 1.0):
            raise ValueError(f"BeliefConfig.reinvigorate_share must be in (0, 1], got {self.reinvigorate_share!r}")
        if self.resample_percentile is not None and not (0.0 < float(self.resample_percentile) <= 100.0):
            raise ValueError(f"BeliefConfig.resample_percentile must be in (0, 100] or None, "
                             f"got {self.resample_percentile!r}")
        if self.opt_objective not in ("squared_hinge", "linear_hinge"):
            raise ValueError(f"BeliefConfig.opt_objective must be 'squared_hinge' (Eq. 7-9) or 'linear_hinge', "
                             f"got {self.opt_objective!r}")
        if self.chsel_batch is not None:
            need = chsel_min_batch(self.chsel_iterations)
            if not isinstance(self.chsel_batch, int) or isinstance(self.chsel_batch, bool) or self.chsel_batch < need:
                raise ValueError(f"BeliefConfig.chsel_batch must be None or an int >= {need} (CHSEL with "
                                 f"{self.chsel_iterations} round(s) fails below that), got {self.chsel_batch!r}")

    @classmethod
    def field_names(cls) -> list[str]:
        return [f.name for f in fields(cls)]
