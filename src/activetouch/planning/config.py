"""RUMI planner parameters: Table IV and section V-F of the paper as defaults."""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

__all__ = ["RumiPlannerConfig"]


@dataclass(frozen=True)
class RumiPlannerConfig:
    """Parameters of RUMI's KMPPI planner (section IV-E..IV-I, V-F, Table IV).

    KMPPI (V-F): ``horizon`` H = 15, ``num_support_pts`` H_v = 8, RBF kernel scale ``kernel_sigma`` = 2,
    ``num_samples`` = 500 action trajectories each rolled out ``rollout_samples`` = 5 times, every action
    applied as ``mini_steps`` = 4 sequential quarter actions, temperature ``lambda_`` = 0.01, noise
    covariance ``noise_sigma * I`` = 1.5 I, controls in ``[u_min, u_max]`` = [-1, 1]; replan after
    ``replan_every`` = 3 executed actions or on contact.

    Costs (Table IV): ``theta_p`` = 45 deg pushing threshold (Alg. 7), ``beta_I`` = 1, ``beta_R`` = 200
    (Eq. 31); ``info_downsample`` is the ``r_d`` of Eq. 29 (the paper's free-space r_d,f = 10 mm).

    Not numbers in the paper (choices of ours): ``warmstart_iters`` ("several" warm-start MPPI iterations before
    the first action), ``iterations_per_plan`` (MPPI iterations per replanning; the paper runs one command per
    step), ``negligible`` (probability treated as zero to skip far-away work, see information.field).
    The ablations of section V-H are ``RumiPlannerConfig.info_only()`` (beta_R = 0) and ``reach_only()``
    (beta_I = 0).
    """

    horizon: int = 15
    num_support_pts: int = 8
    kernel_sigma: float = 2.0
    num_samples: int = 500
    rollout_samples: int = 5
    mini_steps: int = 4
    lambda_: float = 0.01
    noise_sigma: float = 1.5
    u_min: float = -1.0
    u_max: float = 1.0
    warmstart_iters: int = 5
    iterations_per_plan: int = 1
    replan_every: int = 3
    replan_on_contact: bool = True
    theta_p: float = math.radians(45.0)
    beta_I: float = 1.0
    beta_R: float = 200.0
    info_downsample: float = 0.010
    translation_scale: float = 0.080
    rotation_scale: float = 0.5
    negligible: float = 1e-4
    chunk_points: int = 2_000_000

    def __post_init__(self):
        ints = ("horizon", "num_support_pts", "num_samples", "rollout_samples", "mini_steps", "replan_every",
                "iterations_per_plan")
        for name in ints:
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.warmstart_iters < 0:
            raise ValueError(f"warmstart_iters must be >= 0, got {self.warmstart_iters}")
        if self.num_support_pts > self.horizon:
            raise ValueError(f"num_support_pts ({self.num_support_pts}) must be <= horizon ({self.horizon})")
        for name in ("kernel_sigma", "lambda_", "noise_sigma", "info_downsample", "translation_scale",
                     "rotation_scale"):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be finite and > 0, got {v}")
        if not self.u_min < self.u_max:
            raise ValueError(f"u_min must be < u_max, got {self.u_min}, {self.u_max}")
        if not 0 < self.theta_p <= math.pi:
            raise ValueError(f"theta_p must be in (0, pi], got {self.theta_p}")
        if self.beta_I < 0 or self.beta_R < 0 or (self.beta_I == 0 and self.beta_R == 0):
            raise ValueError(f"beta_I, beta_R must be >= 0 and not both 0, got {self.beta_I}, {self.beta_R}")
        if not 0 < self.negligible < 1:
            raise ValueError(f"negligible must be in (0, 1), got {self.negligible}")

    @classmethod
    def info_only(cls, **overrides) -> "RumiPlannerConfig":
        """InfoOnly ablation (V-H): C_R removed (beta_R = 0)."""
        return cls(**{"beta_R": 0.0, **overrides})

    @classmethod
    def reach_only(cls, **overrides) -> "RumiPlannerConfig":
        """ReachOnly ablation (V-H): C_I removed (beta_I = 0)."""
        return cls(**{"beta_I": 0.0, **overrides})

    def with_overrides(self, **overrides) -> "RumiPlannerConfig":
        unknown = set(overrides) - set(self.__dataclass_fields__)
        if unknown:
            raise ValueError(f"unknown RumiPlannerConfig fields: {sorted(unknown)}")
        return replace(self, **overrides)
