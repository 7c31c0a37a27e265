"""Estimators: a belief bound to a task's observations, the part of a method the episode loop updates.

The loop (:func:`activetouch.experiments.runner.run_episode`) only talks to this interface::

    est = make(env, cfg, device)                      # a registered belief's factory
    est.initialise(task, obs0, info0, generator)      # from the task's prior and the first observation
    u, timings = planner.next_action(est.belief, env.ee_state(), in_contact, features=est.features)
    obs, _, terminated, truncated, info = env.step(u)
    fields = est.observe(obs, info, ee_before, generator)   # predict + update; returns the step's row fields
    est.metrics(info) / est.converged() / est.snapshot() / est.write_figures(...)

:func:`check_estimator` checks the contract every estimator must keep (finite, normalised belief of a fixed
size), the way gymnasium's ``check_env`` checks environments.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import fields
from typing import Any, Protocol

import numpy as np
import torch

from activetouch.experiments import metrics

log = logging.getLogger(__name__)


class Estimator(Protocol):
    belief: Any  # what the planner reads (e.g. ParticleBelief)
    features: Any  # the evidence the planner may read (RUMI's X_t), or None

    @property
    def poses(self) -> torch.Tensor: ...  # (P, 4, 4) object -> world hypotheses

    @property
    def weights(self) -> torch.Tensor: ...  # (P,) normalised

    def initialise(self, task, obs, info, generator: torch.Generator) -> dict[str, Any]: ...

    def observe(self, obs, info, ee_before, generator: torch.Generator) -> dict[str, Any]: ...

    def metrics(self, info) -> dict[str, float]: ...

    def converged(self) -> bool: ...

    def snapshot(self, info, planner=None) -> dict[str, Any]: ...


def check_estimator(est) -> None:
    """The estimator contract: ``poses (P, 4, 4)`` rigid and finite, ``weights (P,)`` finite, >= 0, summing to 1.
    Raises AssertionError naming the broken property."""
    poses, w = est.poses, est.weights
    assert poses.ndim == 3 and poses.shape[1:] == (4, 4), f"poses must be (P, 4, 4), got {tuple(poses.shape)}"
    assert w.shape == (poses.shape[0],), f"weights must be (P,) with P = {poses.shape[0]}, got {tuple(w.shape)}"
    assert torch.isfinite(poses).all(), "poses hold NaN or inf"
    assert torch.isfinite(w).all(), "weights hold NaN or inf"
    assert (w >= 0).all(), "negative weights"
    assert abs(float(w.sum()) - 1.0) < 1e-4, f"weights sum to {float(w.sum())}, not 1"
    R = poses[:, :3, :3]
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    assert torch.allclose(R @ R.transpose(1, 2), eye.expand_as(R), atol=1e-3), "pose rotations are not orthonormal"


def _as_tensor(x, device) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x), dtype=torch.float32, device=device)


def _is_motion(dT: torch.Tensor, tol_m: float, tol_rad: float) -> bool:
    """Whether a ``(4, 4)`` rigid motion moves more than ``tol_m`` or turns more than ``tol_rad``."""
    eye = torch.eye(4, dtype=dT.dtype, device=dT.device)
    return bool(metrics.translation_error(dT, eye) > tol_m or metrics.rotation_error(dT, eye) > tol_rad)


def pose_metrics(obj, poses: torch.Tensor, w: torch.Tensor, true_pose) -> dict[str, float]:
    """Metrics of any pose belief against the true pose ``(4, 4)``: NLL (Eq. 32), APC (Eq. 33), active share,
    the best particle's translation / rotation error and the weighted rotation error over all particles."""
    T = _as_tensor(true_pose, poses.device)
    w = w.to(poses.device)  # a belief may keep its weights on another device (TIQF's pose samples)
    best = poses[torch.argmax(w)]
    return {
        "nll": float(metrics.nll(obj, poses, w, T)),
        "apc": float(metrics.apc(obj, poses)),
        "active_share": float(metrics.active_share(w)),
        "trans_err": float(metrics.translation_error(best, T)),
        "rot_err_deg": math.degrees(float(metrics.rotation_error(best, T))),
        # weighted over all particles: small only when the belief is both concentrated and right
        "mean_rot_err_deg": math.degrees(float((w * metrics.rotation_error(poses, T.expand_as(poses))).sum())),
    }


class RumiEstimator:
    """RUMI's belief (Algorithm 1 lines 1-3 and 8-20): CHSEL-initialised pose particles weighed by the
    discrepancy of the accumulated labelled point features ``X_t`` (Algorithms 2-6)."""

    FIGURES = ("curves.png", "belief.png", "contact.png")
    #: particles replaced by contact-placed prior proposals at the step's resample (BeliefConfig.reinvigorate)
    #: ``min_cost`` / ``mean_cost``: the lowest and the weighted mean ``C^(X_t, T_i)`` (Eq. 3) of the particles after
    #: the update, i.e. how well the belief explains the evidence (no ground truth; ``true_discrepancy`` is the
    #: truth's own C^ on the same features)
    COLUMNS = ("reinvigorated", "min_cost", "mean_cost")

    def __init__(self, env, cfg, device):
        from activetouch.belief import BeliefConfig

        self.env, self.cfg, self.device = env, cfg, torch.device(device)
        self.obj = env.object
        fixed = {"num_particles", "se2", "chsel_iterations"}
        bad = sorted(set(cfg.belief) & fixed)
        if bad:
            raise ValueError(f"belief overrides {bad} are set by the episode (--particles, the task, "
                             "--chsel-iterations), not by belief=")
        known = {f.name for f in fields(BeliefConfig)}
        unknown = sorted(set(cfg.belief) - known)
        if unknown:
            raise ValueError(f"unknown belief settings {unknown} for rumi-particles; known: {', '.join(sorted(known - fixed))}")
        try:
            from activetouch.registry import belief_settings

            settings = belief_settings(cfg.task, cfg.belief, "rumi-particles")  # the task's defaults, the user's win
            self.config = BeliefConfig(num_particles=cfg.particles, se2=env.spec.se2,
                                       chsel_iterations=cfg.chsel_iterations, **settings)
        except (TypeError, ValueError) as e:
            raise ValueError(f"belief settings {cfg.belief}: {e}") from None
        self.belief = None
        self.features = None
        self.apc_stop = cfg.beta_t * self.obj.diagonal
        self.terminate = cfg.terminate_on_convergence
        self.prior_apc = None
        self.contact_story: dict[str, Any] = {}  # Fig. 6: before contact, at the first contact, after its update
        self._prev_snapshot = None
        self._last = None

    @property
    def poses(self) -> torch.Tensor:
        return self.belief.poses

    @property
    def weights(self) -> torch.Tensor:
        return self.belief.weights

    def initialise(self, task, obs, info, generator) -> dict[str, Any]:
        from activetouch.belief import ParticleBelief
        from activetouch.observations import voxel_downsample

        cfg, bcfg = self.cfg, self.config
        X = voxel_downsample(obs.features, r_free=bcfg.r_free, r_surface=bcfg.r_surface)  # X_0 (line 1)
        prior = task.prior(self.env, cfg.particles, generator, self.device, features=X, obs=obs, info=info)
        self.belief = ParticleBelief.from_prior(self.obj, prior, X, bcfg, use_chsel=cfg.use_chsel,
                                                generator=generator)  # lines 2-3
        if bcfg.reinvigorate > 0:  # beyond the paper: contact-placed prior proposals at resampling
            self.belief.proposal = lambda n, g: task.prior(self.env, n, g, self.device, features=X, obs=obs, info=info)
        self.features = X
        self.prior_apc = float(metrics.apc(self.obj, prior))
        if self.terminate and self.prior_apc < self.apc_stop:
            # APC (Eq. 33) cannot tell an uninformed belief from a converged one for this object + prior: e.g. the
            # YCB mug's handle is ~3 % of its surface, so uniform-yaw particles on the body axis already have
            # APC ~ 1 mm < 0.03 l_c = 5.1 mm. Stopping on it would end every episode at step 0, so run all T steps.
            log.warning("%s: APC of the prior (%.4f m) is already below beta_t l_c = %.4f m: APC termination is "
                        "uninformative here and is disabled for this episode", self.env.spec.name, self.prior_apc,
                        self.apc_stop)
            self.terminate = False
        return self._feature_counts()

    def _feature_counts(self) -> dict[str, Any]:
        X = self.features
        return {"n_features": len(X), "n_surface": len(X.surface), "n_free": len(X.free)}

    def observe(self, obs, info, ee_before, generator) -> dict[str, Any]:
        from activetouch.observations import merge_obs

        cfg, bcfg, belief, device = self.cfg, self.config, self.belief, self.device
        in_contact = bool(obs.in_contact)
        dT_w = None
        if obs.dT is not None:
            dT_w = _as_tensor(obs.dT, device)
        elif in_contact:  # line 10: ObjMove from the sticking-contact prior dT_r = the ee motion (line 9)
            dT_r = _as_tensor(obs.ee_pose, device) @ torch.linalg.inv(_as_tensor(ee_before, device))
            _, dT_w = belief.obj_move(self.features, obs.features, dT_r)
        moved = dT_w is not None and _is_motion(dT_w, cfg.motion_tol_m, cfg.motion_tol_rad)
        # An observed motion below the tolerance (the object settling by a fraction of a millimetre) is not
        # a "move" that earns process noise, but it is real: particles and object-fixed features follow it
        # exactly, or the drift piles up over a 40-step episode (centimetres on mug-2). An estimated one
        # that small is estimation noise and is dropped.
        follow = moved or (obs.dT is not None and _is_motion(dT_w, 1e-6, 1e-6))
        if follow:
            belief.predict(dT_w, generator=generator, noise=moved)  # lines 11-13
        X = merge_obs(self.features, obs.features, belief.poses, self.obj, dT_w if follow else None,
                      r_free=bcfg.r_free, r_surface=bcfg.r_surface)  # line 14
        self.features = X
        if len(obs.features.surface) and "touch" not in self.contact_story and cfg.figures:  # first touch
            self.contact_story.update(self._touch_snapshots(info))
        resampled = belief.update(X, generator=generator)  # lines 15-20
        self._prev_snapshot = self.snapshot(info) if cfg.figures else None
        if "touch" in self.contact_story and "after" not in self.contact_story:
            self.contact_story["after"] = self._prev_snapshot
            self.contact_story["resampled"] = resampled
        extra = {"reinvigorated": belief.last_reinvigorated if resampled else 0} if bcfg.reinvigorate > 0 else {}
        return {**self._feature_counts(), "resampled": resampled, **extra}

    def metrics(self, info) -> dict[str, float]:
        T = _as_tensor(info["true_pose"], self.device)
        with torch.no_grad():  # privileged diagnostic: is the evidence consistent with the truth? (small: yes)
            extra = {"true_discrepancy": float(self.belief.discrepancy(self.features, T.unsqueeze(0))[0])}
            l = self.belief.last_discrepancy
            if l is None or l.shape != self.belief.weights.shape:  # step 0 before any weigh/update
                l = self.belief.discrepancy(self.features)
            extra["min_cost"] = float(l.min())
            extra["mean_cost"] = float((self.belief.weights * l).sum())
        m = {**extra, **pose_metrics(self.obj, self.poses, self.weights, info["true_pose"])}
        self._last = m
        return m

    def converged(self) -> bool:
        """Algorithm 1's termination: APC (Eq. 33) below beta_t l_c (Table IV)."""
        return bool(self.terminate and self._last is not None and self._last["apc"] < self.apc_stop)

    def summary(self) -> dict[str, Any]:
        return {"prior_apc": self.prior_apc, "apc_termination": self.terminate,
                "reinvigorate": self.config.reinvigorate}

    def snapshot(self, info, planner=None) -> dict[str, Any]:
        field = getattr(planner, "last_field", None)
        return {"poses": self.belief.poses.detach().clone(), "weights": self.belief.weights.detach().clone(),
                "features": self.features, "true_pose": np.asarray(info["true_pose"]), "field": field}

    def first_snapshot(self, info, planner=None) -> None:
        self._prev_snapshot = self.snapshot(info, planner)

    def _touch_snapshots(self, info) -> dict[str, Any]:
        """The particles before the first contact and re-weighed by the contact's features (Algorithm 2 on X_t,
        without changing the belief), as in RUMI Fig. 6 (left, middle)."""
        from activetouch.belief import boltzmann_weights

        with torch.no_grad():
            w = boltzmann_weights(self.belief.discrepancy(self.features), self.belief.config.lam)
        story = {"touch": {**self.snapshot(info), "weights": w}}
        if self._prev_snapshot is not None:
            story["before"] = self._prev_snapshot
        return story

    def write_figures(self, out, rows, snapshots, task_name: str, threshold: float | None) -> list:
        """NLL/APC curves, the information field + particles at the first and last step, and (when the robot
        touched the object) the particles before the first contact, weighed by it, and after its update (Fig. 6)."""
        from activetouch.experiments import plots

        obj, story = self.obj, self.contact_story
        paths = [plots.curves_figure(out / "curves.png", rows, nll_threshold=threshold, apc_threshold=self.apc_stop,
                                     title=f"{task_name}")]
        panels = [{**snap, "title": f"{key} step: information field + particles"} for key, snap in snapshots.items()]
        paths.append(plots.belief_figure(out / "belief.png", obj, panels, zoom=0.15))
        if story and "touch" in story:
            titles = {"before": "before contact", "touch": "weighed by the first contact",
                      "after": "after the update (resampled)" if story.get("resampled") else "after the update"}
            panels = [{**story[k], "title": titles[k]} for k in ("before", "touch", "after") if k in story]
            paths.append(plots.belief_figure(out / "contact.png", obj, panels, zoom=0.08,
                                             title=f"{task_name}: particles coloured by weight around the first contact"))
        return paths


def touch_filter_config(settings: dict[str, Any], particles: int, given: dict[str, Any]):
    """``TouchFilterConfig`` of belief ``settings`` (its fields; the contact model's as ``contact_<name>``, e.g.
    ``contact_kind=binary``) with ``particles`` particles; ValueError naming the problem (``given``: the user's
    ``--belief`` settings, for the message)."""
    from activetouch.belief.contact_model import ContactModelConfig
    from activetouch.belief.touch_filter import TouchFilterConfig

    overrides = dict(settings)
    contact = {k[len("contact_"):]: overrides.pop(k) for k in list(overrides) if k.startswith("contact_")}
    if "num_particles" in overrides:
        raise ValueError("the particle count is set by --particles, not by belief=")
    try:
        return TouchFilterConfig(num_particles=particles, contact=ContactModelConfig(**contact), **overrides)
    except TypeError as e:
        raise ValueError(f"belief settings {given}: {e} (TouchFilterConfig fields; contact model fields "
                         "as contact_<name>, e.g. contact_kind=binary)") from None


class _RunsAllSteps:
    """The parts of the estimator interface a belief without its own stop rule or snapshots shares: it never
    converges (the planner or ``T`` ends the episode), adds nothing to the summary and keeps no snapshots."""

    def converged(self) -> bool:
        return False

    def summary(self) -> dict[str, Any]:
        return {}

    def snapshot(self, info, planner=None) -> dict[str, Any]:
        return {}

    def first_snapshot(self, info, planner=None) -> None:
        return None


class TouchEstimator(_RunsAllSteps):
    """The touch paper's belief (Sec. V): SE(2) particles re-weighed by the binary joint-torque contact signal with
    the proximity model of Eq. 10, predicted by MuJoCo rollouts of the executed poke, contact-aware resampling
    (App. B); prior: the task's two-component Gaussian mixture (App. D-c). The planner ends the episode with a grasp
    (App. D-d, e)."""

    FIGURES = ("particles.png", "entropy.png")
    #: steps.csv columns beyond RUMI's
    COLUMNS = ("xy_err", "yaw_err_deg", "yaw_err_mod180_deg", "weight_entropy", "log_support_volume", "entropy", "grasp_p", "expected_ig",
               "t_star", "weight_term", "spatial_term", "contacted_particles", "n_waypoints", "n_contacts", "stopped_early", "resample_kind",
               "n_replaced", "ess_ratio", "grasp_s", "sample_s", "ig_s", "rollout_s", "distance_s", "belief_rollout_s", "filter_s")

    def __init__(self, env, cfg, device):
        from activetouch.registry import belief_settings

        self.env, self.cfg, self.device = env, cfg, torch.device(device)
        self.obj = env.object
        # the task's defaults, the user's win
        self.config = touch_filter_config(belief_settings(cfg.task, cfg.belief, "touch-particles"), cfg.particles, cfg.belief)
        self.belief = None
        self.features = None
        self.se2_scale = None
        self.history: list[dict[str, Any]] = []  # per step: states, weights, robot path, contacts (figures)
        self.last_obs = None  # the last poke's TouchObservation

    @property
    def poses(self) -> torch.Tensor:
        return self.belief.poses

    @property
    def weights(self) -> torch.Tensor:
        return self.belief.weights

    def initialise(self, task, obs, info, generator) -> dict[str, Any]:
        from activetouch.belief.contact_model import pose_to_se2
        from activetouch.belief.touch_filter import TouchBelief

        prior = task.prior(self.env, self.cfg.particles, generator, self.device, obs=obs, info=info,
                           config=self.config)
        states = pose_to_se2(prior).double()
        self.belief = TouchBelief.from_prior(self.obj, states, self.config)
        from activetouch.information import entropy

        self.se2_scale = entropy.object_se2_scale(self.obj)
        self._record(obs, None)
        return {"n_waypoints": 0, "n_contacts": 0}

    def observe(self, obs, info, ee_before, generator) -> dict[str, Any]:
        from activetouch.sim.grasp_env import TouchObservation

        if not isinstance(obs, TouchObservation) or obs.num_waypoints == 0:  # the grasp ends the episode
            self._record(None, info)
            return {"resampled": False, "n_waypoints": 0, "n_contacts": 0}
        t0 = time.perf_counter()
        traj = self.env.rollout(self.belief.states, obs)  # (P, K', 3) MuJoCo rollouts of the executed poke
        t1 = time.perf_counter()
        from activetouch.planning.touch_ig import near_robot_points

        # the whole robot at each waypoint (only points that can come near a particle: the others are far)
        pts = near_robot_points(self.obj, self.env.robot_points(obs.q[1:]), traj)  # (K', M', 3)
        diag = self.belief.update(torch.as_tensor(obs.z), pts, traj.to(self.belief.states), generator=generator)
        t2 = time.perf_counter()
        self.last_obs = obs
        self._record(obs, info)
        return {"resampled": diag.get("resampled") is not None, "resample_kind": diag.get("resampled") or "",
                "n_replaced": int(diag.get("n_replaced", 0)), "ess_ratio": float(diag.get("ess_ratio", float("nan"))),
                "n_waypoints": obs.num_waypoints, "n_contacts": int(np.asarray(obs.z).sum()),
                "stopped_early": bool(obs.stopped_early), "belief_rollout_s": t1 - t0, "filter_s": t2 - t1}

    def _record(self, obs, info) -> None:
        ee = None if obs is None or obs.num_waypoints == 0 else np.asarray(obs.ee)
        z = None if obs is None or obs.num_waypoints == 0 else np.asarray(obs.z, dtype=bool)
        self.history.append({"states": self.belief.states.detach().cpu().numpy().copy(),
                             "weights": self.belief.weights.detach().cpu().numpy().copy(), "ee": ee, "z": z})

    def metrics(self, info) -> dict[str, float]:
        from activetouch.information import entropy

        s, w = self.belief.states.detach().double().cpu(), self.belief.weights.detach().double().cpu()
        m = pose_metrics(self.obj, self.poses, self.weights, info["true_pose"])
        true = np.asarray(info["true_state"], dtype=np.float64)
        best = self.belief.best_state.detach().double().cpu().numpy()  # the ML state the grasp is planned for
        dyaw = (best[2] - true[2] + math.pi) % (2 * math.pi) - math.pi
        h_w = float(entropy.weight_entropy(w))
        h_v = float(entropy.log_support_volume(s, rho=min(5, len(w) - 1), scale=self.se2_scale,
                                               periodic=entropy.SE2_PERIODIC)) if len(w) > 1 else float("nan")
        sym = abs(math.degrees(dyaw))
        # the best particle's errors are those of the ML state here (pose_metrics takes the heaviest particle)
        m["trans_err"], m["rot_err_deg"] = float(np.hypot(*(best[:2] - true[:2]))), sym
        return {**m, "xy_err": float(np.hypot(*(best[:2] - true[:2]))), "yaw_err_deg": sym,
                # the cracker box looks the same after a half turn: the grasp (pads across it) does not care
                "yaw_err_mod180_deg": min(sym, 180.0 - sym),
                "weight_entropy": h_w, "log_support_volume": h_v, "entropy": h_w + h_v}

    def write_figures(self, out, rows, snapshots, task_name: str, threshold: float | None) -> list:
        from activetouch.experiments import touch_plots

        true = np.asarray(self.env.true_state(), dtype=np.float64)
        return [touch_plots.particles_figure(out / "particles.png", self.obj, self.history, true,
                                             title=f"{task_name}: particles (position + heading) and the robot's pokes"),
                touch_plots.entropy_figure(out / "entropy.png", rows, title=f"{task_name}: entropy and expected IG")]


class TiqfBelief:
    """What the clutter planners read: the TIQF posterior (``state``, ``pose (4, 4)``), the accumulated visual and
    tactile clouds of the target (``visual (V, 3)``, ``tactile (K, 3)``, world), the model cloud
    ``model_points (M, 3)`` (object frame) and the object."""

    def __init__(self, obj, state, model_points: torch.Tensor, config):
        self.obj, self.state, self.model_points, self.config = obj, state, model_points, config
        self.visual = torch.zeros(0, 3, dtype=torch.float64)
        self.tactile = torch.zeros(0, 3, dtype=torch.float64)
        self.history: list[torch.Tensor] = [state.pose.clone()]  # the pose after every acquisition
        self.visual_pose: torch.Tensor | None = None  # the estimate just before the first touch
        # tactile points from which the touches' registration is complete (the estimator's restarts and surface fit
        # act from there on); the touch phase's stop rule judges no estimate made from fewer (0: any)
        self.min_stop_points = 0

    @property
    def pose(self) -> torch.Tensor:
        return self.state.pose

    @property
    def poses(self) -> torch.Tensor:
        """The estimate as a one-hypothesis particle set ``(1, 4, 4)`` (for planners written for particles)."""
        return self.pose.to(torch.float32)[None]

    @property
    def weights(self) -> torch.Tensor:
        return torch.ones(1, device=self.poses.device)  # beside the poses (CUDA when the belief is there)


def _quat_left(q: torch.Tensor) -> torch.Tensor:
    """``L(q) (4, 4)`` with ``q (x) p = L(q) p`` (Hamilton product, ``(w, x, y, z)``)."""
    w, x, y, z = q.unbind()
    return torch.stack([torch.stack([w, -x, -y, -z]), torch.stack([x, w, -z, y]),
                        torch.stack([y, z, w, -x]), torch.stack([z, -y, x, w])])


def move_state(state, dT: torch.Tensor):
    """The TIQF posterior of an object that moved by the world-frame rigid motion ``dT (4, 4)`` (``T' = dT T``):
    the mean ``x' = q(dT) (x) x`` with its covariance ``L Sigma L^T`` (``L`` orthogonal), ``t' = R t + t_dT``."""
    from activetouch.belief.tiqf import TIQFState, _matrix_to_quat

    dT = dT.to(state.x)
    q = _matrix_to_quat(dT[:3, :3])
    q = q / torch.linalg.vector_norm(q)
    L = _quat_left(q)
    return TIQFState(x=L @ state.x, Sigma=L @ state.Sigma @ L.T, t=dT[:3, :3] @ state.t + dT[:3, 3],
                     iterations=state.iterations, converged=state.converged)


class TiqfEstimator:
    """The visuo-tactile paper's estimator (Sec. II-C): a Gaussian over the target's rotation quaternion plus the
    Eq. 6 translation, registered by TIQF (``belief.tiqf.register``) to the accumulated segmented depth points of
    the target after every view and to the tactile cloud after every touch; the posterior carries over between
    acquisitions, so touches refine the visual estimate (Sec. II-D). Prior: the task's coarse pose.

    Belief settings (``--belief KEY=VALUE``): ``TIQFConfig`` fields, plus ``model_points`` (model cloud size,
    default 2000), ``voxel`` (the visual cloud's voxel size, default 0.005 m) and ``touch_cloud``
    (``tactile``: register the tactile points alone, as the paper; ``visuo-tactile``: tactile and visual together;
    ``verify``: together when the touches lie within ``verify_tol`` (default 4 mm, median) of the surface at the
    estimate the views gave, else tactile alone: the touches verify the visual estimate or replace it).

    Beyond the paper, a registration of the tactile points alone that leaves them more than ``restart_tol``
    (default 1 mm, mean distance to the target's mesh) from the surface is restarted
    (``belief.tiqf.register_restarts``): from the prior turned about the vertical in ``touch_restarts`` steps
    (default 6; 0: the paper's single registration from the carried-over posterior) and shifted by
    ``restart_shift`` (default 3 cm) in x and y, then in rounds around the best; the smallest residual wins. Only
    from ``restart_min_points`` (default 7) points on: each touch point fixes about one degree of freedom (its
    distance along the surface normal), so the residual of 6 or fewer says nothing about the pose. Why: a few
    touches keep TIQF's nearest-neighbour registration in the basin it starts from, and a wrong visual estimate (the
    transparent target's) is a wrong basin. ``model_points`` is 20,000 (a 2,000-point model leaves 1-2.5 mm between
    exact touches and their nearest model point, too coarse to tell a wrong basin from the right one).

    Also beyond the paper, from the same ``restart_min_points`` on, the tactile registration's pose is polished on
    the exact mesh (``belief.surface_fit.refine_on_surface``: the touches' signed distances in a least-squares fit
    regularised towards TIQF's pose; ``surface_fit=false``: off): TIQF's point-to-model-point pairs leave sparse
    touches 0.3-1.8 mm off the surface. The polished pose becomes the posterior's mean (its covariance stays).
    The belief then asks the touch phase's stop rule to wait for those points (``TiqfBelief.min_stop_points``):
    before them a registration stuck in a wrong visual basin does not move, and passes the rule unchecked.
    ``visual_fit=true`` (off by default: not the paper's pipeline) polishes every view's registration the same way
    on the segmented cloud, with a robust loss (``belief.surface_fit.VISUAL_FIT``: 2 mm, Cauchy): TIQF's least
    squares is pulled by the mislabelled boundary pixels the simulated segmentation adds, the robust fit is not.
    """

    FIGURES = ("tiqf.png", "declutter.png", "views.png")
    COLUMNS = ("adi_mm", "trans_err_mm", "action", "action_success", "contact_label", "n_visual", "n_tactile",
               "tiqf_iterations", "tiqf_converged", "touch_cloud", "touch_restarts", "residual_mm", "surface_fit_mm",
               "visual_fit_mm", "pose_change_mm", "pose_change_deg", "sigma_trace")
    EXTRA = {"model_points": 20000, "voxel": 0.005, "touch_cloud": "tactile", "verify_tol": 0.004,
             "touch_restarts": 6, "restart_shift": 0.03, "restart_tol": 0.001, "restart_min_points": 7,
             "surface_fit": True, "visual_fit": False}

    def __init__(self, env, cfg, device):
        from activetouch.belief.tiqf import TIQFConfig

        self.env, self.cfg, self.device = env, cfg, torch.device(device)
        self.obj = env.object
        over = dict(cfg.belief)
        self.extra = {k: over.pop(k, v) for k, v in self.EXTRA.items()}
        if self.extra["touch_cloud"] not in ("tactile", "visuo-tactile", "verify"):
            raise ValueError(f"belief touch_cloud must be 'tactile', 'visuo-tactile' or 'verify', "
                             f"got {self.extra['touch_cloud']!r}")
        if not (isinstance(self.extra["model_points"], int) and self.extra["model_points"] >= 10):
            raise ValueError(f"belief model_points must be an int >= 10, got {self.extra['model_points']!r}")
        if not (float(self.extra["voxel"]) > 0):
            raise ValueError(f"belief voxel must be > 0 m, got {self.extra['voxel']!r}")
        r = self.extra["touch_restarts"]
        if isinstance(r, bool) or not isinstance(r, int) or r < 0:
            raise ValueError(f"belief touch_restarts must be an int >= 0 (0: no restarts), got {r!r}")
        for k in ("surface_fit", "visual_fit"):
            if not isinstance(self.extra[k], bool):
                raise ValueError(f"belief {k} must be true or false, got {self.extra[k]!r}")
        m = self.extra["restart_min_points"]
        if isinstance(m, bool) or not isinstance(m, int) or m < 3:
            raise ValueError(f"belief restart_min_points must be an int >= 3, got {m!r}")
        for k in ("restart_shift", "restart_tol"):
            v = self.extra[k]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v > 0):
                raise ValueError(f"belief {k} must be a number > 0 (m), got {v!r}")
        known = {f.name for f in fields(TIQFConfig)}
        unknown = sorted(set(over) - known)
        if unknown:
            raise ValueError(f"unknown belief settings {unknown} for tiqf; known: "
                             f"{', '.join(sorted(known | set(self.EXTRA)))}")
        try:
            self.config = TIQFConfig(**over)
        except (TypeError, ValueError) as e:
            raise ValueError(f"belief settings {cfg.belief}: {e}") from None
        self.belief: TiqfBelief | None = None
        self.features = None  # the last observation (the declutter graph reads its segmentation)
        self._last_info: dict[str, Any] = {}

    @property
    def poses(self) -> torch.Tensor:
        return self.belief.pose.to(torch.float32)[None]

    @property
    def weights(self) -> torch.Tensor:
        return torch.ones(1, device=self.poses.device)  # beside the poses (CUDA when the belief is there)

    def initialise(self, task, obs, info, generator) -> dict[str, Any]:
        from activetouch.belief.tiqf import initial_state

        feats = getattr(obs, "features", None)  # a RUMI task: labelled point features, not a clutter view
        prior = task.prior(self.env, 1, generator, self.device, obs=obs, info=info, features=feats)
        state = initial_state(prior[0].double(), self.config)
        pts = self.obj.sample_surface(self.extra["model_points"], seed=0).double()
        self.belief = TiqfBelief(self.obj, state, pts, self.config)
        checked = self.extra["touch_restarts"] > 0 or self.extra["surface_fit"]
        if self.extra["touch_cloud"] != "visuo-tactile" and checked:
            self.belief.min_stop_points = int(self.extra["restart_min_points"])
        self.features = obs
        if feats is not None:  # X_0's surface points (camera) are the first visual cloud
            self.features = feats
            self._rummage_points(feats)
        return {"action": "reset", "n_visual": len(self.belief.visual), "n_tactile": 0}

    def _rummage_points(self, feats) -> dict[str, Any]:
        """Add a RUMI observation's surface points (camera and pads: the object's own, segmented points) to the
        visual cloud and register it (from the carried-over posterior)."""
        from activetouch.belief.tiqf import register
        from activetouch.observations import voxel_representatives

        b = self.belief
        surf = feats.surface.positions.detach().to("cpu", torch.float64)
        if len(surf):
            allpts = torch.cat([b.visual, surf])
            b.visual = allpts[voxel_representatives(allpts, float(self.extra["voxel"]))]
        if len(b.visual) >= 3:
            _, b.state, tinfo = register(b.model_points, b.visual, b.state, self.config)
            return {"tiqf_iterations": tinfo["iterations"], "tiqf_converged": bool(tinfo["converged"])}
        return {}

    def observe(self, obs, info, ee_before, generator) -> dict[str, Any]:
        from activetouch.belief.surface_fit import VISUAL_FIT, refine_on_surface, surface_residual
        from activetouch.belief.tiqf import register, register_restarts, state_at_pose, yaw_shift_starts
        from activetouch.experiments.metrics import rotation_error, translation_error
        from activetouch.observations import voxel_representatives

        b = self.belief
        prev = b.pose.clone()
        if not hasattr(obs, "kind") and hasattr(obs, "features"):  # a RUMI task's observation
            return self._observe_rummage(obs, prev)
        self.features = obs
        row: dict[str, Any] = {"action": obs.kind, "action_success": bool(obs.success),
                               "contact_label": int(getattr(obs, "contact_label", -1))}
        pts = torch.as_tensor(np.asarray(obs.points, dtype=np.float64).reshape(-1, 3))
        cloud, mode = None, None
        if obs.kind in ("push", "pick"):
            # decluttering moves things: the views taken before it no longer show the scene as it is
            b.visual = torch.zeros(0, 3, dtype=torch.float64)
        elif obs.kind == "view" and len(pts):
            allpts = torch.cat([b.visual, pts])
            b.visual = allpts[voxel_representatives(allpts, float(self.extra["voxel"]))]
            cloud = b.visual
        elif obs.kind == "touch" and len(pts):
            if b.visual_pose is None:  # the estimate the views gave, before any touch moved it
                b.visual_pose = b.pose.clone()
            b.tactile = torch.cat([b.tactile, pts])
            if len(b.tactile) >= 3:
                mode = self.extra["touch_cloud"]
                if mode == "verify":  # "correct and verify": keep the visual points if the touches agree with them
                    mode = "visuo-tactile" if self._touch_residual(b) < float(self.extra["verify_tol"]) else "tactile"
                    row["touch_cloud"] = mode
                cloud = b.tactile if mode == "tactile" else torch.cat([b.tactile, b.visual])
        if cloud is not None and len(cloud) >= 3:
            # enough touches registered alone for a residual to mean something: restarts and the surface fit
            touches_alone = (obs.kind == "touch" and mode == "tactile"
                             and len(cloud) >= self.extra["restart_min_points"])
            if touches_alone and self.extra["touch_restarts"] > 0:
                starts = yaw_shift_starts(b.history[0], int(self.extra["touch_restarts"]),
                                          float(self.extra["restart_shift"]))
                _, b.state, tinfo = register_restarts(b.model_points, cloud, b.state, starts, self.config,
                                                      restart_tol=float(self.extra["restart_tol"]),
                                                      residual=lambda T: surface_residual(self.obj.sdf, cloud, T))
                row.update(touch_restarts=tinfo["restarts"], residual_mm=1000 * tinfo["residual"])
            else:
                _, b.state, tinfo = register(b.model_points, cloud, b.state, self.config)
            row.update(tiqf_iterations=tinfo["iterations"], tiqf_converged=bool(tinfo["converged"]))
            if touches_alone and self.extra["surface_fit"]:
                fit = refine_on_surface(self.obj.sdf, cloud, b.state.pose)
                b.state = state_at_pose(b.state, fit.pose)
                row.update(surface_fit_mm=1000 * fit.residual)
            elif obs.kind == "view" and self.extra["visual_fit"]:
                fit = refine_on_surface(self.obj.sdf, cloud, b.state.pose, VISUAL_FIT)
                b.state = state_at_pose(b.state, fit.pose)
                row.update(visual_fit_mm=1000 * fit.residual)
        b.history.append(b.pose.clone())
        row.update(n_visual=len(b.visual), n_tactile=len(b.tactile),
                   pose_change_mm=1000 * float(translation_error(b.pose, prev)),
                   pose_change_deg=math.degrees(float(rotation_error(b.pose, prev))))
        return row

    def _observe_rummage(self, obs, prev: torch.Tensor) -> dict[str, Any]:
        """A RUMI step: the observed object motion ``dT`` moves the posterior and the object-fixed cloud (as RUMI's
        Alg. 1 line 11-13 moves particles and features), then the new surface points are registered."""
        from activetouch.experiments.metrics import rotation_error, translation_error

        b = self.belief
        row: dict[str, Any] = {"action": "rummage", "action_success": bool(obs.in_contact)}
        dT = obs.dT
        if dT is not None:
            dT = torch.as_tensor(dT, dtype=torch.float64)
            if _is_motion(dT, self.cfg.motion_tol_m, self.cfg.motion_tol_rad):
                b.state = move_state(b.state, dT)
                b.visual = b.visual @ dT[:3, :3].T + dT[:3, 3]
        # (with observe_dT=False the motion is not known: the cloud stays where it was seen)
        row.update(self._rummage_points(obs.features))
        self.features = obs.features
        b.history.append(b.pose.clone())
        row.update(n_visual=len(b.visual), n_tactile=0,
                   pose_change_mm=1000 * float(translation_error(b.pose, prev)),
                   pose_change_deg=math.degrees(float(rotation_error(b.pose, prev))))
        return row

    @staticmethod
    def _touch_residual(b: "TiqfBelief") -> float:
        """Median distance (m) of the tactile points to the model at the visual estimate (the pose before the first
        touch): whether touch and vision agree."""
        T = (b.visual_pose if b.visual_pose is not None else b.pose).double()
        local = (b.tactile - T[:3, 3]) @ T[:3, :3]
        return float(torch.cdist(local, b.model_points).min(dim=1).values.median())

    def metrics(self, info) -> dict[str, float]:
        """ADI (Eq. 28), translation (Eq. 26) and rotation (Eq. 27) errors of the estimate."""
        from activetouch.experiments import metrics as M

        T = _as_tensor(info["true_pose"], "cpu").double()
        est = self.belief.pose.double()
        adi = M.adi(self.obj, est, T)
        te = float(M.translation_error(est, T))
        re = math.degrees(float(M.rotation_error(est, T)))
        self._last_info = info
        out = {"adi_mm": 1000 * adi, "trans_err": te, "trans_err_mm": 1000 * te, "rot_err_deg": re,
               "mean_rot_err_deg": re, "active_share": 1.0, "sigma_trace": float(torch.trace(self.belief.state.Sigma))}
        if hasattr(getattr(self.env, "spec", None), "nll_threshold"):  # a RUMI task: its NLL (Eq. 36) and APC too
            m = pose_metrics(self.obj, self.poses, self.weights, info["true_pose"])
            out.update(nll=m["nll"], apc=m["apc"])
        return out

    def converged(self) -> bool:
        return False  # the planner ends the episode (NBV / NBT stop rules, Sec. II-D)

    def summary(self) -> dict[str, Any]:
        return {"n_visual": len(self.belief.visual), "n_tactile": len(self.belief.tactile)}

    def snapshot(self, info, planner=None) -> dict[str, Any]:
        """What the figures draw from the planner: its declutter decisions, views, NBV candidates, grid."""
        if planner is None:
            return {}
        return {k: getattr(planner, k, None) for k in ("decisions", "view_positions", "candidates",
                                                       "entropy_history", "grid")}

    def first_snapshot(self, info, planner=None) -> None:
        return None

    def write_figures(self, out, rows, snapshots, task_name: str, threshold: float | None) -> list:
        """``tiqf.png`` (the scene, the estimate against the truth, ADI after each action), ``declutter.png`` (the
        declutter graphs over the segmentations, Fig. 3a) and ``views.png`` (the views and the occupancy grid's
        entropy, Fig. 4) when the method decluttered / looked actively."""
        from activetouch.experiments import clutter_plots

        paths = [clutter_plots.tiqf_figure(out / "tiqf.png", self.env, self.belief, rows, title=task_name)]
        last = snapshots.get("last") or {}
        if last.get("decisions") and hasattr(clutter_plots, "declutter_sequence_figure"):
            paths.append(clutter_plots.declutter_sequence_figure(out / "declutter.png", last["decisions"],
                                                                 names=self.env.names,
                                                                 title=f"{task_name}: declutter graphs (Eq. 1-2)"))
        if last.get("grid") is not None and len(last.get("view_positions") or []) > 1 and \
                hasattr(clutter_plots, "views_figure"):
            cand = last.get("candidates") or (None, None)
            ctr = self.belief.pose.detach().cpu().numpy()[:3, 3]
            paths.append(clutter_plots.views_figure(out / "views.png", last["grid"], ctr,
                                                    np.asarray(last["view_positions"]), cand[0], cand[1],
                                                    last["entropy_history"],
                                                    title=f"{task_name}: next best views (Eq. 19-24)"))
        return paths


class RummageContactEstimator(_RunsAllSteps):
    """The touch paper's binary-contact filter (Sec. V, Eq. 10, App. B) on RUMI's rummaging tasks (issue 11).

    SE(2) particles ``(x, y, yaw)`` on the object's support plane, drawn from the task's prior (RUMI V-B, from the
    first camera points; no CHSEL), re-weighed once per step by the step's binary contact flag with the proximity
    model of Eq. 10, ``d`` = the distance between the gripper points ``h(q)`` at the end-effector pose after the step
    and the object at each particle (``TouchBelief.update`` with one waypoint), contact-aware resampling around the
    gripper after a contact (App. B). Prediction: every particle follows the observed object motion ``dT``
    (``object-motion``; the rummaging tasks have no particle rollouts, unlike the grasp tasks' ``physics-rollout``);
    with ``--estimate-dT`` no motion is given and the particles stay where they are (no ObjMove here).

    Simplifications, named: one contact sample per step (the touch paper reads the signal at every waypoint); the
    gripper alone stands for "the whole robot" (the rummaging tasks' robot is a floating gripper); the camera's
    free and surface points after the first view are not used (that is RUMI's belief, not this one). Runs all
    ``T`` steps (no APC termination): the task's success (NLL below the threshold at some step) is read as for RUMI.
    """

    FIGURES = ("curves.png",)
    COLUMNS = ("n_contacts", "resample_kind", "n_replaced", "ess_ratio", "weight_entropy", "filter_s")

    def __init__(self, env, cfg, device):
        if not getattr(getattr(env, "spec", None), "se2", False):
            raise ValueError(f"belief contact-particles needs an SE(2) task (x, y, yaw); {cfg.task} searches SE(3)")
        self.env, self.cfg, self.device = env, cfg, torch.device(device)
        self.obj = env.object
        if "table_height" in cfg.belief:
            raise ValueError("belief table_height is set by the task's prior, not by belief=")
        self.config = touch_filter_config(dict(cfg.belief), cfg.particles, cfg.belief)
        h, _ = env.gripper_points(spacing=env.spec.r_w)
        self.gripper = torch.as_tensor(h, dtype=torch.float64)  # (M, 3) h(q) in the ee frame
        self.belief = None
        self.features = None
        self.apc_stop = cfg.beta_t * self.obj.diagonal

    @property
    def poses(self) -> torch.Tensor:
        """``(P, 4, 4)`` the SE(2) states, upright at the prior's height."""
        from activetouch.belief.contact_model import se2_to_pose

        return se2_to_pose(self.belief.states, self.config.table_height).to(torch.float32)

    @property
    def weights(self) -> torch.Tensor:
        return self.belief.weights.to(torch.float32)

    def initialise(self, task, obs, info, generator) -> dict[str, Any]:
        from dataclasses import replace

        from activetouch.belief.contact_model import pose_to_se2
        from activetouch.belief.touch_filter import TouchBelief
        from activetouch.observations import voxel_downsample

        X = voxel_downsample(obs.features, r_free=self.env.spec.r_w, r_surface=self.env.spec.r_w)
        prior = task.prior(self.env, self.cfg.particles, generator, self.device, features=X, obs=obs, info=info)
        prior = prior.double()
        if not bool(torch.all(prior[:, 2, 2] > 1 - 1e-6)):  # the filter's poses are upright: R = Rz(yaw)
            raise ValueError(f"belief contact-particles needs an upright prior (rotations about z) on {self.cfg.task}")
        states = pose_to_se2(prior)
        self.config = replace(self.config, table_height=float(prior[:, 2, 3].mean()))
        self.belief = TouchBelief.from_prior(self.obj, states, self.config)
        self.features = X
        return {"n_contacts": 0}

    def observe(self, obs, info, ee_before, generator) -> dict[str, Any]:
        from activetouch.belief.contact_model import pose_to_se2

        t0 = time.perf_counter()
        b = self.belief
        traj = None
        if obs.dT is not None:
            dT = torch.as_tensor(np.asarray(obs.dT), dtype=torch.float64)
            if _is_motion(dT, self.cfg.motion_tol_m, self.cfg.motion_tol_rad):
                traj = pose_to_se2(dT @ self.poses.double())[:, None]  # (P, 1, 3) the particles moved by dT
        ee = torch.as_tensor(np.asarray(obs.ee_pose), dtype=torch.float64)
        pts = (self.gripper @ ee[:3, :3].T + ee[:3, 3])[None]  # (1, M, 3) the gripper after the step
        z = torch.tensor([bool(obs.in_contact)])
        diag = b.update(z, pts, traj, generator=generator)
        self.features = obs.features
        return {"resampled": diag.get("resampled") is not None, "resample_kind": diag.get("resampled") or "",
                "n_replaced": int(diag.get("n_replaced", 0)), "ess_ratio": float(diag.get("ess_ratio", float("nan"))),
                "n_contacts": int(z.sum()), "filter_s": time.perf_counter() - t0}

    def metrics(self, info) -> dict[str, float]:
        from activetouch.information import entropy

        m = pose_metrics(self.obj, self.poses, self.weights, info["true_pose"])
        return {**m, "weight_entropy": float(entropy.weight_entropy(self.belief.weights.detach().double().cpu()))}

    def write_figures(self, out, rows, snapshots, task_name: str, threshold: float | None) -> list:
        from activetouch.experiments import plots

        return [plots.curves_figure(out / "curves.png", rows, nll_threshold=threshold, apc_threshold=self.apc_stop,
                                    title=f"{task_name}: binary-contact filter")]

