"""Configuration of the RUMI pose particle belief (RUMI Table IV defaults)."""
from __future__ import annotations

import math
from dataclasses import dataclass, fields

__all__ = ["BeliefConfig"]


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
    * ``chsel_*``: CHSEL (Alg. 1 line 2) registration settings. ``chsel_batch=None`` registers all P prior
      particles (the paper); ``chsel_qd_iterations`` is chsel's n_o (its default 100). ``chsel_max_points``:
      CHSEL registers against at most this many points of each semantics class (a seeded random subset, free
      points first restricted to those that can touch a prior particle); a camera view holds ~60k free points
      and CHSEL's cost grows linearly with them (LIBRARY-NOTES checked 250 surface + 200 free points).
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
    active_weight: float = 1e-4
    chsel_iterations: int = 5
    chsel_batch: int | None = None
    chsel_qd_iterations: int = 100
    chsel_resolution: float = 0.004
    chsel_max_points: int = 500

    def __post_init__(self):
        def _pos(name, allow_zero=False):
            v = getattr(self, name)
            ok = math.isfinite(float(v)) and (v >= 0 if allow_zero else v > 0)
            if not ok:
                raise ValueError(f"BeliefConfig.{name} must be finite and {'>= 0' if allow_zero else '> 0'}, got {v!r}")

        for name in ("num_particles", "n_opt", "chsel_iterations", "chsel_qd_iterations", "chsel_max_points"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < (0 if name == "n_opt" else 1):
                raise ValueError(f"BeliefConfig.{name} must be a positive int, got {v!r}")
        for name in ("lam", "resample_threshold", "free_scale", "r_free", "r_surface", "beta_t", "opt_lr_t",
                     "opt_lr_R", "chsel_resolution"):
            _pos(name)
        for name in ("sigma_t", "sigma_R", "violation_tolerance", "active_weight"):
            _pos(name, allow_zero=True)
        if self.resample_percentile is not None and not (0.0 < float(self.resample_percentile) <= 100.0):
            raise ValueError(f"BeliefConfig.resample_percentile must be in (0, 100] or None, "
                             f"got {self.resample_percentile!r}")
        if self.chsel_batch is not None and (not isinstance(self.chsel_batch, int) or self.chsel_batch < 1):
            raise ValueError(f"BeliefConfig.chsel_batch must be a positive int or None, got {self.chsel_batch!r}")

    @classmethod
    def field_names(cls) -> list[str]:
        return [f.name for f in fields(cls)]
