"""The built-in tasks, registered for the episode loop: RUMI's nine rummaging tasks (``sim.tasks``) and the
touch paper's blind-grasping tasks (``sim.grasp_tasks``, when present).

Each task supplies its environment, the kinds of observation and action it provides, its prior over the object
pose and its success criterion (:class:`activetouch.registry.TaskEntry`).
"""
from __future__ import annotations

from typing import Any

import numpy as np
import torch

from activetouch.registry import TaskEntry, register_task

#: What a RUMI rummaging environment provides (``sim.RummageEnv``).
RUMMAGE_PROVIDES = frozenset({"points", "target-points", "contact", "object-motion", "ee-delta-actions",
                              "reachability"})


def _as_tensor(x, device) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x), dtype=torch.float32, device=device)


def rummage_prior(env, n: int, generator: torch.Generator, device="cpu", *, features=None, **_) -> torch.Tensor:
    """Prior pose particles ``(P, 4, 4)`` of RUMI section V-B from the first (downsampled) features ``X_0``.

    Mug tasks: the mug centre is estimated from the initially observed surface points (a least-squares circle
    fit of their x-y positions, the mug body being a cylinder), yaw uniform. Other tasks: N(0, 0.05) in x, y
    around the task's nominal centre, yaw uniform; SE(3) tasks (box) also draw the resting face.
    """
    from activetouch.belief import priors

    spec, obj = env.spec, env.object
    nominal = _as_tensor(spec.prior_center(obj.mesh.vertices), device)
    if spec.prior_kind == "mug-centre":
        if features is None:
            raise ValueError(f"task {spec.name}: the mug prior needs the first observation's features")
        surf = features.surface.positions
        if len(surf) < 3:
            raise ValueError(f"task {spec.name}: the mug prior needs camera surface points, got {len(surf)}")
        centre = nominal.clone()
        centre[:2] = _circle_centre(surf[:, :2]).to(centre)
        return priors.mug_prior(centre, n, generator=generator, axis_offset=_body_axis(obj))
    if not spec.se2:  # SE(3) search (box): also draw the resting face, see priors.resting_face_prior
        # the table top is z = 0 (TaskSpec.start_pose rests the object's lowest point there)
        return priors.resting_face_prior(nominal, obj.mesh.vertices, sigma=spec.prior_sigma, n=n, table_z=0.0,
                                         generator=generator).to(device)
    return priors.gaussian_yaw_prior(nominal, sigma=spec.prior_sigma, n=n, generator=generator)


def _body_axis(obj) -> torch.Tensor:
    """Object-frame point on a mug body's axis: the packaged mug's body spans y symmetrically and its handle
    sticks out along +x, so the axis sits one body radius (half the y extent) in from the -x side."""
    lo, hi = (torch.as_tensor(b, dtype=torch.float32) for b in obj.bounds)
    radius = float(hi[1] - lo[1]) / 2.0
    return torch.tensor([float(lo[0]) + radius, float(lo[1] + hi[1]) / 2.0, 0.0])


def _circle_centre(xy: torch.Tensor) -> torch.Tensor:
    """Kasa least-squares circle fit: centre ``(2,)`` of points ``(N, 2)``."""
    xy = xy.double()
    A = torch.cat([2 * xy, torch.ones(len(xy), 1, dtype=xy.dtype)], dim=1)
    b = (xy**2).sum(1, keepdim=True)
    sol = torch.linalg.lstsq(A, b).solution
    return sol[:2, 0].float()


def rummage_success(rows: list[dict[str, Any]], last_info: dict[str, Any], env) -> dict[str, Any]:
    """RUMI's success (Table III): the NLL fell below the task's threshold at some step; plus the strict
    variants of ``metrics.success_fields``."""
    from activetouch.experiments import metrics

    nlls = [r["nll"] for r in rows]
    thr = env.spec.nll_threshold
    return {"success": bool(min(nlls) < thr), "nll_threshold": thr,
            **metrics.success_fields(nlls, [r["mean_rot_err_deg"] for r in rows], thr)}


def _make_rummage(name: str):
    def make_env(seed: int = 0, **overrides):
        from activetouch import sim

        return sim.make(name, seed=seed, **overrides)

    return make_env


def _register_rummage() -> None:
    from activetouch.sim.tasks import TASKS

    for name, spec in TASKS.items():
        desc = (f"RUMI: {spec.object_name}, actions={spec.action_space}, search={'SE(2)' if spec.se2 else 'SE(3)'}, "
                f"r_w={spec.r_w}, T={spec.max_steps}, success: NLL < {spec.nll_threshold:g}")
        provides = RUMMAGE_PROVIDES | ({"se2-object"} if spec.se2 else set())  # SE(2) search: mug, drill
        register_task(TaskEntry(name=name, family="rummage", description=desc, provides=provides,
                                make_env=_make_rummage(name), prior=rummage_prior, success=rummage_success,
                                belief_defaults=spec.belief_defaults, defaults_belief="rumi-particles"))


_register_rummage()


#: What a blind-grasping environment provides (``sim.grasp_env.GraspEnv``).
GRASP_PROVIDES = frozenset({"contact", "contact-signal", "proprioception", "physics-rollout", "poke-actions",
                            "grasp"})


def grasp_prior(env, n: int, generator: torch.Generator, device="cpu", *, info=None, config=None, **_) -> torch.Tensor:
    """App. D-c: ``n`` poses ``(n, 4, 4)`` from the two-component Gaussian mixture around the task's two mode
    means (``info["prior_means"]``), sigma_pos = 0.06 m, sigma_yaw = 0.5 rad (the belief config's values)."""
    from activetouch.belief.contact_model import se2_to_pose
    from activetouch.belief.touch_filter import TouchFilterConfig, gmm_prior

    if info is None or "prior_means" not in info:
        raise ValueError("the grasp tasks' prior needs info['prior_means'] from env.reset()")
    cfg = config or TouchFilterConfig()
    states = gmm_prior(torch.as_tensor(np.asarray(info["prior_means"]), dtype=torch.float64), n,
                       sigma_pos=cfg.prior_sigma_pos, sigma_yaw=cfg.prior_sigma_yaw, generator=generator)
    return se2_to_pose(states, z=cfg.table_height).to(device=device, dtype=torch.float32)


def grasp_success(rows: list[dict[str, Any]], last_info: dict[str, Any], env) -> dict[str, Any]:
    """Touch paper Table I: success = the executed grasp lifted the box; ``iterations`` = localisation actions
    (pokes) before the grasp."""
    pokes = sum(1 for r in rows[1:] if r.get("n_waypoints", 0))
    grasped = "grasp_success" in last_info
    return {"success": bool(last_info.get("grasp_success", False)), "grasped": grasped, "iterations": pokes,
            "grasp_p_at_grasp": rows[-1].get("grasp_p") if grasped else None}


def _make_grasp(name: str):
    def make_env(seed: int = 0, **overrides):
        from activetouch.sim.grasp_env import make_grasp_env

        return make_grasp_env(name, seed=seed, **overrides)

    return make_env


def _register_grasp() -> None:
    from activetouch.sim.grasp_tasks import GRASP_TASKS

    for name, spec in GRASP_TASKS.items():
        desc = (f"touch-only: {spec.object_name} on a table, no camera, SE(2) belief, prior modes "
                f"{spec.mode_separation:g} m apart, <= {spec.max_actions} pokes then a grasp; success: lifted")
        register_task(TaskEntry(name=name, family="grasp", description=desc, provides=GRASP_PROVIDES,
                                make_env=_make_grasp(name), prior=grasp_prior, success=grasp_success,
                                belief_defaults=spec.belief_defaults, defaults_belief="touch-particles"))


_register_grasp()


#: What a dense-clutter environment provides (``sim.clutter_env.ClutterEnv``).
CLUTTER_PROVIDES = frozenset({"target-points", "segmentation", "tactile-points", "view-actions", "touch-actions",
                              "push-actions", "pick-actions"})


def clutter_prior(env, n: int, generator: torch.Generator, device="cpu", *, info=None, **_) -> torch.Tensor:
    """The clutter tasks' prior: ``n`` poses ``(n, 4, 4)``, the true target pose perturbed by N(0, sigma_t) in x, y
    and N(0, sigma_yaw) about z (``spec.prior_sigma_t``, ``prior_sigma_yaw_deg``). It stands in for the paper's
    starting point, the approximate target centroid of its segmentation network (Sec. II-D-1) and an upright
    bottle of unknown heading accuracy."""
    import math

    from activetouch.geometry import make_pose

    if info is None or "true_pose" not in info:
        raise ValueError("the clutter tasks' prior needs info['true_pose'] from env.reset()")
    s = env.spec
    T = torch.as_tensor(np.asarray(info["true_pose"]), dtype=torch.float64)
    dxy = torch.randn(n, 2, generator=generator, dtype=torch.float64) * s.prior_sigma_t
    dyaw = torch.randn(n, generator=generator, dtype=torch.float64) * math.radians(s.prior_sigma_yaw_deg)
    c, si = torch.cos(dyaw), torch.sin(dyaw)
    Rz = torch.zeros(n, 3, 3, dtype=torch.float64)
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -si, si, c, 1.0
    t = T[:3, 3].expand(n, 3).clone()
    t[:, :2] += dxy
    return make_pose(Rz @ T[:3, :3], t).to(device=device, dtype=torch.float32)


def clutter_success(rows: list[dict[str, Any]], last_info: dict[str, Any], env) -> dict[str, Any]:
    """Visuo-tactile paper's metrics (Eq. 26-28) of the final estimate, the action counts and the decluttering's
    grasp / push success rates (Sec. III-B). ``success``: final ADI below 10 mm (the paper's "< 1 cm" of Fig. 6)."""
    last = rows[-1]
    acts = [r.get("action") for r in rows[1:]]
    picks = [bool(r.get("action_success")) for r in rows[1:] if r.get("action") == "pick"]
    pushes = [bool(r.get("action_success")) for r in rows[1:] if r.get("action") == "push"]
    return {"success": bool(last["adi_mm"] < 10.0), "final_adi_mm": last["adi_mm"],
            "final_trans_err_mm": last["trans_err_mm"], "final_rot_err_deg_tiqf": last["rot_err_deg"],
            "initial_adi_mm": rows[0]["adi_mm"],
            "views": acts.count("view"), "touches": acts.count("touch"), "pushes": len(pushes), "picks": len(picks),
            "pick_success_rate": (sum(picks) / len(picks)) if picks else None,
            "push_success_rate": (sum(pushes) / len(pushes)) if pushes else None,
            "stop_reason": last_info.get("stop_reason")}


def _make_clutter(name: str):
    def make_env(seed: int = 0, **overrides):
        from activetouch.sim.clutter_tasks import make_clutter_env

        return make_clutter_env(name, seed=seed, **overrides)

    return make_env


def _register_clutter() -> None:
    from activetouch.sim.clutter_tasks import CLUTTER_TASKS

    for name, spec in CLUTTER_TASKS.items():
        register_task(TaskEntry(name=name, family="clutter", description=f"visuo-tactile clutter: {spec.description}; "
                                f"<= {spec.max_actions} actions; success: final ADI < 10 mm", provides=CLUTTER_PROVIDES,
                                make_env=_make_clutter(name), prior=clutter_prior, success=clutter_success))


_register_clutter()
