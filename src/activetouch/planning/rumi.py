"""RUMI's planner: KMPPI (pytorch_mppi) over the stochastic dynamics f^ with the Eq. 31 terminal cost.

Per planning call (Algorithm 1 lines 5-6, section IV-E..IV-I):

1. cache ``p(S|X)``, ``I~(x|X)`` and the weighted normals on the workspace grid (information.field) and the
   reachability correlation of Algorithm 8 (planning.costs);
2. run KMPPI: 500 kernel-interpolated action trajectories (8 support points, RBF scale 2), each rolled out
   5 times through f^ (Algorithm 7, 4 mini steps per action), scored by Eq. 31 as a terminal cost over the
   whole trajectory and averaged over the 5 rollouts; temperature 0.01, noise covariance 1.5 I;
3. return the first action. The first call warm-starts the nominal trajectory (initialised with noise) with
   ``warmstart_iters`` iterations that execute nothing; afterwards the executed action is shifted out
   (``u_2..H, 0`` becomes the nominal trajectory).

:meth:`RumiPlanner.next_action` adds the replanning policy of V-F: execute the planned actions in order and
replan after ``replan_every`` (3) of them or as soon as the robot reports contact.
"""
from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np
import torch
from pytorch_mppi import KMPPI
from pytorch_mppi.mppi import RBFKernel

from activetouch.geometry.voxel import VoxelGrid
from activetouch.information.field import InformationField, compute_field
from activetouch.planning.config import RumiPlannerConfig
from activetouch.planning.costs import InformationCost, ReachabilityCost, RumiCost, resample_to_grid
from activetouch.planning.dynamics import STATE_DIM, GripperModel, StochasticDynamics, action_indices

__all__ = ["RumiPlanner"]

log = logging.getLogger(__name__)


class _SeededKMPPI(KMPPI):
    """KMPPI whose noise comes from a given ``torch.Generator`` (pytorch_mppi uses the global RNG)."""

    def __init__(self, *args, generator: torch.Generator, **kwargs):
        self._generator = generator
        super().__init__(*args, **kwargs)

    def _sample_noise(self, shape):
        z = torch.randn(*shape, self.nu, device=self.d, dtype=self.dtype, generator=self._generator)
        if self._diagonal_sigma:
            return z * self._noise_sigma_sqrt_diag + self.noise_mu
        return z @ self._noise_sigma_chol.T + self.noise_mu

    def init_nominal_with_noise(self):
        """Nominal control points initialised with (bounded) noise, as in IV-E."""
        self.theta = self._bound_action(self._sample_noise((self.num_support_pts,)))
        self.U, _ = self.deparameterize_to_trajectory_single(self.theta)


class RumiPlanner:
    """RUMI's KMPPI planner (section IV-E..IV-I, V-F).

    Args:
        obj: the known object (:class:`activetouch.objects.KnownObject`).
        workspace: workspace grid ``W`` (resolution ``r_w``).
        gripper_points: ``(M, 3)`` robot interior points ``h`` in the end-effector frame
            ``pose_from_xyz_yaw(ee[:3], ee[3])``; info_mask ``(M,)`` selects ``h_I``.
        reachability: ``(VoxelGrid, values (nx, ny, nz))`` reachability map ``r(x)`` (Eq. 30) or None (then
            ``config.beta_R`` must be 0).
        config: :class:`RumiPlannerConfig` (paper defaults).
        action_space: ``"planar"`` (``u = [dx, dy, dyaw]``) or ``"3d"`` (``[dx, dy, dz, dyaw]``).
        lam, free_scale, violation_tolerance: ``lambda`` of Eq. 23, ``C`` of Eq. 4-5 and ``-alpha`` of Eq. 4-5
            (the belief's values, see ``activetouch.belief.discrepancy`` for the sign of alpha).
        sensor: sensor model with ``probs(sdf)`` (default ``SemanticSensorModel()``).
        ee_bounds: ``(lower (4,), upper (4,))`` clip bounds of ``[x, y, z, yaw]`` in ``f_f`` (default: the
            workspace box, yaw unbounded).
        seed: seed of the planner's generator (noise and contact samples).
        device: torch device of the planning tensors.
    """

    def __init__(self, obj, workspace: VoxelGrid, gripper_points, info_mask, *, reachability=None,
                 config: RumiPlannerConfig | None = None, action_space: str = "planar", lam: float = 2.0,
                 free_scale: float = 10.0, violation_tolerance: float = 0.004, sensor=None, ee_bounds=None,
                 seed: int = 0, device=None):
        self.config = config or RumiPlannerConfig()
        if not isinstance(workspace, VoxelGrid):
            raise ValueError(f"workspace must be a VoxelGrid, got {type(workspace).__name__}")
        self.obj = obj
        self.workspace = workspace
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        self.dtype = torch.float32
        self.gripper = GripperModel(torch.as_tensor(gripper_points, dtype=self.dtype),
                                    torch.as_tensor(info_mask, dtype=torch.bool)).to(device=self.device)
        self.action_space = action_space
        self.nu = len(action_indices(action_space))
        self.lam, self.free_scale, self.alpha = float(lam), float(free_scale), -float(violation_tolerance)
        self.sensor = sensor
        if self.sensor is None:
            from activetouch.observations import SemanticSensorModel

            self.sensor = SemanticSensorModel()
        self.reach_values = None
        if reachability is not None:
            rgrid, rvals = reachability
            self.reach_values = resample_to_grid(rgrid, rvals, workspace, device=self.device, dtype=self.dtype)
        elif self.config.beta_R > 0:
            raise ValueError("config.beta_R > 0 needs a reachability map (or use RumiPlannerConfig.info_only())")
        self.seed = int(seed)
        self.generator = torch.Generator(device=self.device)
        if ee_bounds is None:
            self._ws_lower = workspace.lower.to(device=self.device, dtype=self.dtype)
            self._ws_upper = workspace.upper.to(device=self.device, dtype=self.dtype)
        else:
            self._ws_lower = torch.as_tensor(np.asarray(ee_bounds[0]), device=self.device, dtype=self.dtype)
            self._ws_upper = torch.as_tensor(np.asarray(ee_bounds[1]), device=self.device, dtype=self.dtype)
            if self._ws_lower.shape != (4,) or self._ws_upper.shape != (4,):
                raise ValueError("ee_bounds must be (lower (4,), upper (4,)) for [x, y, z, yaw]")
        self.field: InformationField | None = None
        self._field_key = None
        self._dynamics: StochasticDynamics | None = None
        self._cost: RumiCost | None = None
        self.mppi = self._make_mppi()
        self.reset()

    # ------------------------------------------------------------------ construction helpers
    @classmethod
    def from_env(cls, env, belief_config=None, seed: int = 0, config: RumiPlannerConfig | None = None,
                 device=None, point_spacing: float | None = None, **overrides) -> "RumiPlanner":
        """Planner for a :class:`activetouch.sim.RummageEnv` (its workspace, gripper points, reachability).

        ``overrides`` are :class:`RumiPlannerConfig` fields (e.g. ``beta_R=0`` for InfoOnly).
        ``point_spacing``: spacing of the robot points ``h`` (default the workspace resolution ``r_w``; the
        dynamics' cost grows with their number, e.g. ~5 s per plan on one CPU thread for the drill tasks).
        """
        spec = env.spec
        cfg = (config or RumiPlannerConfig()).with_overrides(**overrides)
        lo, up = spec.workspace if hasattr(spec, "workspace") else (spec.workspace_lower, spec.workspace_upper)
        workspace = VoxelGrid(lo, up, spec.r_w)
        try:  # robot points at the field's resolution (finer points add look-ups, not information)
            h, mask = env.gripper_points(spacing=float(point_spacing or spec.r_w))
        except TypeError:
            h, mask = env.gripper_points()
        reach = env.reachability() if cfg.beta_R > 0 else None
        kw: dict[str, Any] = {}
        if belief_config is not None:
            kw["lam"] = float(getattr(belief_config, "lam", 2.0))
            kw["free_scale"] = float(getattr(belief_config, "free_scale", 10.0))
            kw["violation_tolerance"] = float(getattr(belief_config, "violation_tolerance", 0.004))
        scale = getattr(env, "action_scale", None)
        if scale is not None:
            scale = tuple(scale() if callable(scale) else scale)
            if "translation_scale" not in overrides and "rotation_scale" not in overrides:
                cfg = cfg.with_overrides(translation_scale=float(scale[0]), rotation_scale=float(scale[1]))
        if hasattr(spec, "ee_lower") and hasattr(spec, "ee_upper"):
            kw["ee_bounds"] = (np.asarray(spec.ee_lower, dtype=np.float32), np.asarray(spec.ee_upper, dtype=np.float32))
        return cls(env.object, workspace, torch.as_tensor(np.asarray(h), dtype=torch.float32),
                   torch.as_tensor(np.asarray(mask), dtype=torch.bool), reachability=reach, config=cfg,
                   action_space=spec.action_space, seed=seed, device=device, **kw)

    def _make_mppi(self) -> _SeededKMPPI:
        c = self.config
        noise = c.noise_sigma * torch.eye(self.nu, device=self.device, dtype=self.dtype)
        u_min = torch.full((self.nu,), c.u_min, device=self.device, dtype=self.dtype)
        u_max = torch.full((self.nu,), c.u_max, device=self.device, dtype=self.dtype)
        return _SeededKMPPI(
            self._dynamics_fn, self._running_cost_fn, STATE_DIM, noise, num_samples=c.num_samples, horizon=c.horizon,
            device=self.device, terminal_state_cost=self._terminal_cost_fn, lambda_=c.lambda_, u_min=u_min,
            u_max=u_max, rollout_samples=c.rollout_samples, num_support_pts=c.num_support_pts,
            kernel=RBFKernel(sigma=c.kernel_sigma), generator=self.generator,
        )

    # KMPPI callbacks: they read the current field through self
    def _dynamics_fn(self, state, u):
        return self._dynamics(state, u)

    def _running_cost_fn(self, state, u):
        return torch.zeros(state.shape[0], device=state.device, dtype=state.dtype)

    def _terminal_cost_fn(self, states, actions):
        return self._cost(states, actions)

    # ------------------------------------------------------------------ public API
    def reset(self) -> None:
        """Start a new episode: reseed, noise-initialised nominal trajectory, warm start pending."""
        self.generator.manual_seed(self.seed)
        self.mppi.init_nominal_with_noise()
        self._warm = False
        self._queue: list[np.ndarray] = []
        self._since_plan = 0
        self.last_timing: dict[str, float] = {}

    @property
    def last_field(self):
        """``(grid, I~ values (nx, ny, nz))`` of the latest cached field (for plots), or None."""
        if self.field is None:
            return None
        return self.field.grid, self.field.info.detach().cpu()

    def update_field(self, poses: torch.Tensor, weights: torch.Tensor) -> bool:
        """Cache the fields for the belief ``poses (P, 4, 4)``, ``weights (P,)`` (Alg. 1 line 5).

        Returns False (and keeps the cache) when the particles are unchanged since the last call.
        """
        if self.obj is None:
            raise ValueError("this planner has no object model: give it a field with set_field")
        poses = torch.as_tensor(poses).detach().to(device=self.device, dtype=self.dtype)
        weights = torch.as_tensor(weights).detach().to(device=self.device, dtype=self.dtype)
        if self._field_key is not None and self._field_key[0].shape == poses.shape and torch.equal(
                self._field_key[0], poses) and torch.equal(self._field_key[1], weights):
            return False
        c = self.config
        field = compute_field(self.obj, poses, weights, self.workspace, lam=self.lam, free_scale=self.free_scale,
                              alpha=self.alpha, sensor=self.sensor, negligible=c.negligible)
        self.set_field(field)
        self._field_key = (poses.clone(), weights.clone())
        return True

    def set_field(self, field: InformationField) -> None:
        """Plan on a given cached field (e.g. a hand-made one in tests); rebuilds the dynamics and costs."""
        if not isinstance(field, InformationField):
            raise ValueError(f"field must be an InformationField, got {type(field).__name__}")
        if field.grid.shape != self.workspace.shape:
            raise ValueError(f"field grid {field.grid.shape} differs from the workspace grid {self.workspace.shape}")
        c = self.config
        self.field = field
        self._field_key = None
        self._dynamics = StochasticDynamics(
            field, self.gripper, self.action_space, self._ws_lower, self._ws_upper,
            translation_scale=c.translation_scale, rotation_scale=c.rotation_scale, theta_p=c.theta_p,
            mini_steps=c.mini_steps, generator=self.generator, negligible=c.negligible)
        info_cost = InformationCost(field, self.gripper, c.info_downsample, c.chunk_points) if c.beta_I > 0 else None
        reach_cost = ReachabilityCost(field, self.reach_values) if c.beta_R > 0 else None
        self._cost = RumiCost(info_cost, reach_cost, c.beta_I, c.beta_R)

    def _state(self, ee_state) -> torch.Tensor:
        ee = torch.as_tensor(np.asarray(ee_state, dtype=np.float32), device=self.device).reshape(-1)
        if ee.shape != (4,):
            raise ValueError(f"ee_state must be [x, y, z, yaw] (4,), got shape {tuple(ee.shape)}")
        if not bool(torch.isfinite(ee).all()):
            raise ValueError("ee_state contains NaN or inf")
        return torch.cat([ee, torch.zeros(3, device=self.device)])

    def plan(self, poses, weights, ee_state, features=None) -> tuple[np.ndarray, dict[str, float]]:
        """Plan from the end-effector state ``ee_state`` ``[x, y, z, yaw]`` for the belief ``(poses, weights)``.

        ``poses``/``weights`` None plans on the field given to :meth:`set_field`.
        Runs the warm start on the first call of an episode, then ``iterations_per_plan`` KMPPI iterations.
        Returns ``(u (Nu,) numpy in [u_min, u_max], timings)`` with timings (seconds) ``field_s``,
        ``dynamics_s``, ``cost_s``, ``mppi_s`` (whole KMPPI time), ``plan_iters`` and the process CPU times
        ``field_cpu_s``, ``dynamics_cpu_s``, ``cost_cpu_s``, ``mppi_cpu_s`` (robust to other jobs on the machine).
        ``features`` is unused: RUMI's fields depend on the observations only through the particles (Eq. 23, 27).
        The returned action is treated as executed (the nominal trajectory is shifted by one step);
        the remaining planned actions are available as :attr:`planned_actions`.
        """
        t0, c0 = time.perf_counter(), time.process_time()
        if (poses is None) != (weights is None):
            raise ValueError("give both poses and weights (or neither, to plan on the field set with set_field)")
        if poses is not None:
            self.update_field(poses, weights)
        elif self.field is None:
            raise ValueError("plan needs poses and weights (or a field given with set_field)")
        t1, c1 = time.perf_counter(), time.process_time()
        state = self._state(ee_state)
        self._dynamics.elapsed = self._dynamics.elapsed_cpu = 0.0
        self._cost.elapsed = self._cost.elapsed_cpu = 0.0
        iters = self.config.iterations_per_plan + (0 if self._warm else self.config.warmstart_iters)
        for _ in range(iters):
            self.mppi.command(state, shift_nominal_trajectory=False)
        self._warm = True
        U = self.mppi.U.detach().clamp(self.config.u_min, self.config.u_max).cpu().numpy().astype(np.float32)
        self.planned_actions = U
        self.mppi.shift_nominal_trajectory()  # u_1 is executed: u_2..H, 0 is the next nominal trajectory
        t2, c2 = time.perf_counter(), time.process_time()
        self.last_timing = {"field_s": t1 - t0, "dynamics_s": self._dynamics.elapsed, "cost_s": self._cost.elapsed,
                            "mppi_s": t2 - t1, "plan_iters": float(iters),
                            "field_cpu_s": c1 - c0, "dynamics_cpu_s": self._dynamics.elapsed_cpu,
                            "cost_cpu_s": self._cost.elapsed_cpu, "mppi_cpu_s": c2 - c1}
        u = U[0].copy()
        if not np.isfinite(u).all():
            raise RuntimeError("KMPPI produced a non-finite action")
        return u, dict(self.last_timing)

    def next_action(self, belief, ee_state, in_contact: bool, poses=None, weights=None, features=None
                    ) -> tuple[np.ndarray, dict[str, float]]:
        """Replanning policy of V-F: replan after ``replan_every`` executed actions or on contact.

        ``belief`` is anything with ``.poses (P, 4, 4)`` and ``.weights (P,)`` (a ``ParticleBelief``) or None
        when ``poses`` and ``weights`` are given (or a field was set with :meth:`set_field`). Between replans
        the remaining planned actions are executed in order (and shifted out of the KMPPI nominal trajectory).
        ``features``: the accumulated observations ``X`` (:class:`activetouch.observations.Features`), passed on
        to :meth:`plan`; unused by RUMI (its fields depend on ``X`` only through the particles), taken so that
        every registered planner has the same signature.
        Returns ``(u (Nu,), timings)``; timings are zero for steps that did not replan (``replanned`` = 0).
        """
        if belief is not None:
            poses, weights = belief.poses, belief.weights
        if (poses is None or weights is None) and self.field is None:
            raise ValueError("next_action needs a belief, or poses and weights, or a field given with set_field")
        c = self.config
        must = (not self._queue or self._since_plan >= c.replan_every or (in_contact and c.replan_on_contact))
        if must:
            u, timing = self.plan(poses, weights, ee_state, features=features)
            self._queue = [a for a in self.planned_actions[1:]]
            self._since_plan = 1
            timing["replanned"] = 1.0
            return u, timing
        u = self._queue.pop(0).copy()
        self.mppi.shift_nominal_trajectory()
        self._since_plan += 1
        zero = ("field_s", "dynamics_s", "cost_s", "mppi_s", "plan_iters", "field_cpu_s", "dynamics_cpu_s",
                "cost_cpu_s", "mppi_cpu_s", "replanned")
        return u, dict.fromkeys(zero, 0.0)
