"""The closed loop of RUMI Algorithm 1 for any registered method on any registered task.

One episode: reset the task, build the prior and initialise the particle belief with CHSEL (Alg. 1 lines 1-3),
then repeat for ``T`` steps: plan (line 5-6), act (7), observe (8-9), estimate or observe the object motion
(10), predict (11-13), merge observations (14) and update / resample the belief (15-20). Metrics of every
step go to ``steps.csv`` as soon as the step ends and ``summary.json`` is written at the end.
"""
from __future__ import annotations

import logging
import math
import os
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from activetouch.experiments import metrics
from activetouch.experiments.records import StepWriter, is_finished, read_steps, write_json_atomic

log = logging.getLogger(__name__)


@dataclass
class EpisodeConfig:
    """What to run. Defaults are the RUMI paper's (T from the task, P = 100, beta_t = 0.03)."""

    task: str = "mug-0"
    method: str = "rumi"
    seed: int = 0
    steps: int | None = None  # None: the task's T (40)
    particles: int = 100
    device: str = "cpu"
    use_chsel: bool = True
    chsel_iterations: int = 5
    observe_dT: bool = True  # the paper observes dT in sim; False estimates it with ObjMove (Algorithm 5)
    terminate_on_convergence: bool = True
    beta_t: float = 0.03  # APC convergence ratio (Table IV)
    # Object motions below these are treated as no motion (Alg. 1 line 11 "if dT not 0"): the physics settles the
    # object by fractions of a millimetre between steps, and every predict step adds sigma_t = 10 mm of noise.
    motion_tol_m: float = 5e-4
    motion_tol_rad: float = 0.01
    planner: dict[str, Any] = field(default_factory=dict)  # overrides of the planner config
    figures: bool = True
    progress: bool = True

    def __post_init__(self):
        if self.steps is not None and (not isinstance(self.steps, int) or self.steps < 1):
            raise ValueError(f"steps must be a positive int or None, got {self.steps!r}")
        if not isinstance(self.particles, int) or self.particles < 1:
            raise ValueError(f"particles must be a positive int, got {self.particles!r}")
        if not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"seed must be a non-negative int, got {self.seed!r}")
        if not (0 < self.beta_t < 1):
            raise ValueError(f"beta_t must be in (0, 1), got {self.beta_t!r}")
        if self.chsel_iterations < 1:
            raise ValueError(f"chsel_iterations must be >= 1, got {self.chsel_iterations!r}")


def check_device(device: str) -> torch.device:
    """``torch.device`` of ``device``; ValueError when the name is not a device or the device is not available."""
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as e:
        raise ValueError(f"--device {device!r} is not a torch device ({e}); use cpu or cuda") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"--device {device!r}: CUDA is not available here (torch {torch.__version__}); use cpu")
    if dev.type == "cuda" and dev.index is not None and dev.index >= torch.cuda.device_count():
        raise ValueError(f"--device {device!r}: only {torch.cuda.device_count()} CUDA device(s) here")
    if dev.type not in ("cpu", "cuda"):
        raise ValueError(f"--device {device!r}: activetouch runs on cpu or cuda")
    return dev


def check_output_dir(out_dir: str | Path) -> Path:
    """``out_dir`` as a Path after checking it is (or can be made) a writable folder; ValueError otherwise."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"output folder {str(out)!r} exists and is not a folder")
    probe = out
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir() or not os.access(probe, os.W_OK | os.X_OK):
        raise ValueError(f"output folder {str(out)!r} cannot be written ({str(probe)!r} is not writable)")
    return out


def check_config(cfg: EpisodeConfig, out_dir: str | Path | None = None):
    """Every check that can fail before the long work of an episode starts (ValueError naming the problem):
    the task and method exist, the device is available, the particle count is one the belief handles, the
    output folder is writable and the planner accepts ``cfg.planner`` (built once on the task's env).
    Returns ``(env, method)``."""
    from activetouch import sim
    from activetouch.belief import BeliefConfig, chsel_min_batch
    from activetouch.registry import get_method

    if cfg.task not in sim.registered():
        raise ValueError(f"unknown task {cfg.task!r}; available: {', '.join(sim.registered())}")
    method = get_method(cfg.method)
    check_device(cfg.device)
    if out_dir is not None:
        check_output_dir(out_dir)
    if cfg.use_chsel and cfg.particles < chsel_min_batch(cfg.chsel_iterations):
        raise ValueError(f"particles = {cfg.particles}: CHSEL (Alg. 1 line 2) with {cfg.chsel_iterations} rounds needs "
                         f"at least {chsel_min_batch(cfg.chsel_iterations)} particles; use more or --no-chsel")
    env = sim.make(cfg.task, seed=cfg.seed, observe_dT=cfg.observe_dT)
    bcfg = BeliefConfig(num_particles=cfg.particles, se2=env.spec.se2, chsel_iterations=cfg.chsel_iterations)
    try:
        method.make_planner(env, bcfg, cfg.seed, **cfg.planner)
    except TypeError as e:  # an override the factory does not take
        raise ValueError(f"method {cfg.method!r} does not accept the planner settings {cfg.planner}: {e}") from None
    return env, method


def platform_info() -> dict[str, Any]:
    """What makes two machines' numbers differ: CPU, library versions, threads (for ``summary.json``)."""
    import platform

    import mujoco

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {"cpu": cpu, "machine": platform.machine(), "system": platform.platform(), "python": platform.python_version(),
            "torch": torch.__version__, "mujoco": mujoco.__version__, "numpy": np.__version__,
            "torch_threads": torch.get_num_threads(), "cpu_count": os.cpu_count(),
            "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None}


FIGURES = ("curves.png", "belief.png", "contact.png")


def _as_tensor(x, device) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x), dtype=torch.float32, device=device)


def build_prior(env, features, n: int, generator: torch.Generator, device="cpu") -> torch.Tensor:
    """Prior pose particles ``(P, 4, 4)`` of the paper (section V-B).

    Mug tasks: the mug centre is estimated from the initially observed surface points (a least-squares circle
    fit of their x-y positions, the mug body being a cylinder), yaw uniform. Other tasks: N(0, 0.05) in x, y
    around the task's nominal centre, yaw uniform.
    """
    from activetouch.belief import priors

    spec, obj = env.spec, env.object
    nominal = _as_tensor(spec.prior_center(obj.mesh.vertices), device)
    if spec.prior_kind == "mug-centre":
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


def _is_motion(dT: torch.Tensor, tol_m: float, tol_rad: float) -> bool:
    """Whether a ``(4, 4)`` rigid motion moves more than ``tol_m`` or turns more than ``tol_rad``."""
    eye = torch.eye(4, dtype=dT.dtype, device=dT.device)
    return bool(metrics.translation_error(dT, eye) > tol_m or metrics.rotation_error(dT, eye) > tol_rad)


def _step_metrics(obj, belief, true_pose, device, X=None) -> dict[str, float]:
    T = _as_tensor(true_pose, device)
    poses, w = belief.poses, belief.weights
    best = poses[torch.argmax(w)]
    extra = {}
    if X is not None:  # privileged diagnostic: is the evidence consistent with the truth? (small: yes)
        with torch.no_grad():
            extra["true_discrepancy"] = float(belief.discrepancy(X, T.unsqueeze(0))[0])
    return {**extra,
        "nll": float(metrics.nll(obj, poses, w, T)),
        "apc": float(metrics.apc(obj, poses)),
        "active_share": float(metrics.active_share(w)),
        "trans_err": float(metrics.translation_error(best, T)),
        "rot_err_deg": math.degrees(float(metrics.rotation_error(best, T))),
        # weighted over all particles: small only when the belief is both concentrated and right
        "mean_rot_err_deg": math.degrees(float((w * metrics.rotation_error(poses, T.expand_as(poses))).sum())),
    }


def run_episode(cfg: EpisodeConfig, out_dir: str | Path) -> dict[str, Any]:
    """Run one episode of Algorithm 1 and write ``steps.csv``, ``summary.json`` and figures to ``out_dir``."""
    from activetouch.belief import BeliefConfig, ParticleBelief
    from activetouch.observations import merge_obs, voxel_downsample

    env, method = check_config(cfg, out_dir)  # every check before the long work (CHSEL, planning)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "summary.json").unlink(missing_ok=True)  # a re-run is unfinished until its new summary is written
    for name in FIGURES:  # figures of an earlier run in this folder are not this run's
        (out / name).unlink(missing_ok=True)
    torch.manual_seed(cfg.seed)
    gen = torch.Generator(device="cpu").manual_seed(cfg.seed)
    device = torch.device(cfg.device)

    spec, obj = env.spec, env.object
    T_max = cfg.steps if cfg.steps is not None else spec.max_steps
    bcfg = BeliefConfig(num_particles=cfg.particles, se2=spec.se2, chsel_iterations=cfg.chsel_iterations)
    planner = method.make_planner(env, bcfg, cfg.seed, **cfg.planner)

    obs, info = env.reset(seed=cfg.seed)
    X = voxel_downsample(obs.features, r_free=bcfg.r_free, r_surface=bcfg.r_surface)  # X_0 (line 1)
    prior = build_prior(env, X, cfg.particles, gen, device)
    belief = ParticleBelief.from_prior(obj, prior, X, bcfg, use_chsel=cfg.use_chsel, generator=gen)  # lines 2-3
    planner.reset()
    apc_stop = cfg.beta_t * obj.diagonal
    terminate = cfg.terminate_on_convergence
    apc_prior = float(metrics.apc(obj, prior))
    if terminate and apc_prior < apc_stop:
        # APC (Eq. 33) cannot tell an uninformed belief from a converged one for this object + prior: e.g. the
        # YCB mug's handle is ~3 % of its surface, so uniform-yaw particles on the body axis already have
        # APC ~ 1 mm < 0.03 l_c = 5.1 mm. Stopping on it would end every episode at step 0, so run all T steps.
        log.warning("%s: APC of the prior (%.4f m) is already below beta_t l_c = %.4f m: APC termination is "
                    "uninformative here and is disabled for this episode", spec.name, apc_prior, apc_stop)
        terminate = False

    snapshots: dict[str, Any] = {}
    contact_story: dict[str, Any] = {}  # Fig. 6: before contact, at the first contact, after its update
    prev_snapshot = None
    rows: list[dict[str, Any]] = []
    converged = False
    in_contact = False
    t_episode = time.perf_counter()
    pbar = None
    if cfg.progress:
        from activetouch.experiments.progress import progress

        pbar = progress(T_max, f"{cfg.method} on {cfg.task} (seed {cfg.seed})", unit="step")
    with StepWriter(out / "steps.csv") as writer:
        m = _step_metrics(obj, belief, info["true_pose"], device, X)
        row = {"step": 0, **m, "n_features": len(X), "n_surface": len(X.surface), "n_free": len(X.free),
               "in_contact": False, "resampled": False}
        writer.write(row)
        rows.append(row)
        snapshots["first"] = prev_snapshot = _snapshot(belief, X, info, planner)
        for t in range(1, T_max + 1):
            if terminate and m["apc"] < apc_stop:
                converged = True
                break
            t0 = time.perf_counter()
            u, timings = planner.next_action(belief, env.ee_state(), in_contact, features=X)  # lines 5-6
            t1 = time.perf_counter()
            if t == 1:
                snapshots["first"] = _snapshot(belief, X, info, planner)
            ee_before = _as_tensor(env.ee_pose(), device)
            obs, _, terminated, truncated, info = env.step(u)  # lines 7-9
            in_contact = bool(obs.in_contact)
            t2 = time.perf_counter()
            dT_w = None
            if obs.dT is not None:
                dT_w = _as_tensor(obs.dT, device)
            elif in_contact:  # line 10: ObjMove from the sticking-contact prior dT_r = the ee motion (line 9)
                dT_r = _as_tensor(obs.ee_pose, device) @ torch.linalg.inv(ee_before)
                _, dT_w = belief.obj_move(X, obs.features, dT_r)
            moved = dT_w is not None and _is_motion(dT_w, cfg.motion_tol_m, cfg.motion_tol_rad)
            # An observed motion below the tolerance (the object settling by a fraction of a millimetre) is not
            # a "move" that earns process noise, but it is real: particles and object-fixed features follow it
            # exactly, or the drift piles up over a 40-step episode (centimetres on mug-2). An estimated one
            # that small is estimation noise and is dropped.
            follow = moved or (obs.dT is not None and _is_motion(dT_w, 1e-6, 1e-6))
            if follow:
                belief.predict(dT_w, generator=gen, noise=moved)  # lines 11-13
            X = merge_obs(X, obs.features, belief.poses, obj, dT_w if follow else None,
                          r_free=bcfg.r_free, r_surface=bcfg.r_surface)  # line 14
            if len(obs.features.surface) and "touch" not in contact_story and cfg.figures:  # first touch
                contact_story.update(_touch_snapshots(belief, X, info, prev_snapshot))
            resampled = belief.update(X, generator=gen)  # lines 15-20
            prev_snapshot = _snapshot(belief, X, info, None) if cfg.figures else None
            if "touch" in contact_story and "after" not in contact_story:
                contact_story["after"] = prev_snapshot
                contact_story["resampled"] = resampled
            t3 = time.perf_counter()
            m = _step_metrics(obj, belief, info["true_pose"], device, X)
            row = {"step": t, **m, "n_features": len(X), "n_surface": len(X.surface), "n_free": len(X.free),
                   "in_contact": in_contact,
                   "resampled": resampled, "plan_s": t1 - t0, "update_s": t3 - t2, "step_s": t2 - t1, **timings}
            writer.write(row)
            rows.append(row)
            if pbar is not None:
                pbar.set_postfix(nll=f"{m['nll']:.1f}", apc=f"{m['apc'] * 1000:.1f}mm", contact=int(in_contact))
                pbar.update(1)  # after the postfix: a plain progress line prints this step's numbers
            if terminated or truncated:
                break
    if pbar is not None:
        pbar.close()
    snapshots["last"] = _snapshot(belief, X, info, planner)

    nlls = [r["nll"] for r in rows]
    # planning time of the steps that replanned (the others reuse the nominal plan and take ~1 ms)
    plan_times = [r["plan_s"] for r in rows if "plan_s" in r and r.get("replanned", True)]
    summary = {
        "task": cfg.task, "method": cfg.method, "seed": cfg.seed,
        "success": bool(min(nlls) < spec.nll_threshold), "nll_threshold": spec.nll_threshold,
        **metrics.success_fields(nlls, [r["mean_rot_err_deg"] for r in rows], spec.nll_threshold),
        "min_nll": min(nlls), "final_nll": nlls[-1], "cumulative_nll": float(sum(nlls)),
        "steps": len(rows) - 1, "converged": converged, "final_apc": rows[-1]["apc"],
        "initial_nll": nlls[0], "prior_apc": apc_prior, "apc_termination": terminate,
        "final_trans_err": rows[-1]["trans_err"], "final_rot_err_deg": rows[-1]["rot_err_deg"],
        "initial_mean_rot_err_deg": rows[0]["mean_rot_err_deg"], "final_mean_rot_err_deg": rows[-1]["mean_rot_err_deg"],
        "min_mean_rot_err_deg": min(r["mean_rot_err_deg"] for r in rows),
        **_contact_story(rows),
        "median_plan_s": float(np.median(plan_times)) if plan_times else None,
        "wall_s": time.perf_counter() - t_episode,
        "config": asdict(cfg),
        "platform": platform_info(),
    }
    if cfg.figures:  # before summary.json: a kill while plotting leaves an unfinished episode, not a figureless one
        write_figures(out, env, obj, rows, snapshots, spec, apc_stop, contact_story)
    write_json_atomic(out / "summary.json", summary)
    return summary


def _contact_story(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The first contact's step and the belief's weighted rotation error just before it (camera-only evidence
    until then), for the printout of what touching taught."""
    t = next((int(r["step"]) for r in rows if r.get("in_contact")), None)
    return {"first_contact_step": t,
            "mean_rot_err_deg_before_contact": None if t is None else rows[t - 1]["mean_rot_err_deg"]}


def _snapshot(belief, X, info, planner) -> dict[str, Any]:
    field = getattr(planner, "last_field", None)
    return {"poses": belief.poses.detach().clone(), "weights": belief.weights.detach().clone(), "features": X,
            "true_pose": np.asarray(info["true_pose"]), "field": field}


def _touch_snapshots(belief, X, info, before) -> dict[str, Any]:
    """The particles before the first contact and re-weighed by the contact's features (Algorithm 2 on X_t,
    without changing the belief), as in RUMI Fig. 6 (left, middle)."""
    from activetouch.belief import boltzmann_weights

    with torch.no_grad():
        w = boltzmann_weights(belief.discrepancy(X), belief.config.lam)
    story = {"touch": {**_snapshot(belief, X, info, None), "weights": w}}
    if before is not None:
        story["before"] = before
    return story


def write_figures(out: Path, env, obj, rows, snapshots, spec, apc_stop, contact_story=None) -> list[Path]:
    """NLL/APC curves, the information field + particles at the first and last step, and (when the robot touched
    the object) the particles before the first contact, weighed by it, and after its update (Fig. 6)."""
    from activetouch.experiments import plots

    paths = [plots.curves_figure(out / "curves.png", rows, nll_threshold=spec.nll_threshold, apc_threshold=apc_stop,
                                 title=f"{spec.name}")]
    panels = []
    for key, snap in snapshots.items():
        panels.append({**snap, "title": f"{key} step: information field + particles"})
    paths.append(plots.belief_figure(out / "belief.png", obj, panels, zoom=0.15))
    if contact_story and "touch" in contact_story:
        titles = {"before": "before contact", "touch": "weighed by the first contact",
                  "after": "after the update (resampled)" if contact_story.get("resampled") else "after the update"}
        story = [{**contact_story[k], "title": titles[k]} for k in ("before", "touch", "after") if k in contact_story]
        paths.append(plots.belief_figure(out / "contact.png", obj, story, zoom=0.08,
                                         title=f"{spec.name}: particles coloured by weight around the first contact"))
    return paths


def episode_dir(root: str | Path, task: str, method: str, seed: int) -> Path:
    return Path(root) / task / method / f"seed{seed:03d}"


def run_sweep(tasks, methods, seeds, root, base: EpisodeConfig | None = None, workers: int = 1,
              backend: str = "process") -> list[dict[str, Any]]:
    """Run every (task, method, seed) episode, skipping finished ones (resume), in a local process pool
    (default) or on Ray (``backend='ray'``, optional extra ``activetouch[ray]``)."""
    from activetouch.experiments.progress import progress
    from activetouch.experiments.records import load_summaries, settings_diff

    base = base or EpisodeConfig()
    tasks, methods, seeds = list(tasks), list(methods), list(seeds)
    for name, v in (("tasks", tasks), ("methods", methods), ("seeds", seeds)):
        if not v:
            raise ValueError(f"a sweep needs at least one of {name}")
        if len(set(v)) != len(v):
            raise ValueError(f"{name} repeats an entry: {v}")
    if any(not isinstance(x, int) or x < 0 for x in seeds):
        raise ValueError(f"seeds must be non-negative ints, got {seeds}")
    if not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers!r}")
    if backend not in ("process", "ray"):
        raise ValueError(f"backend must be 'process' or 'ray', got {backend!r}")
    check_output_dir(root)
    for task in tasks:  # names, device, particles and planner settings: checked before any episode starts
        for method in methods:
            check_config(replace(base, task=task, method=method, seed=seeds[0]))
    jobs = []
    for task in tasks:
        for method in methods:
            for seed in seeds:
                d = episode_dir(root, task, method, seed)
                cfg = replace(base, task=task, method=method, seed=seed, progress=False)
                if is_finished(d):
                    done = load_summaries([d])[0].get("config", {})
                    diff = settings_diff(done, asdict(cfg))
                    if diff:  # a resume never mixes runs of different settings
                        raise ValueError(f"{d} holds an episode run with other settings ({diff}): resume with "
                                         "the same settings or sweep into another --out folder")
                    continue
                jobs.append((cfg, d))
    log.info("%d episodes to run (%d already finished)", len(jobs), len(tasks) * len(methods) * len(seeds) - len(jobs))
    if jobs:
        bar = progress(len(jobs), "episodes", unit="episode", every_s=0.0)
        if backend == "ray":
            _run_ray(jobs, workers)
        elif workers <= 1:
            for c, d in jobs:
                run_episode(c, d)
                bar.update(1)
        else:
            import concurrent.futures as cf
            import multiprocessing as mp

            with cf.ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn")) as ex:
                futs = [ex.submit(_run_job, c, d) for c, d in jobs]
                for f in cf.as_completed(futs):
                    f.result()
                    bar.update(1)
        bar.close()
    return load_summaries(episode_dir(root, t, m, s) for t in tasks for m in methods for s in seeds)


def _run_job(cfg: EpisodeConfig, d: Path) -> dict[str, Any]:
    torch.set_num_threads(1)
    return run_episode(cfg, d)


def _run_ray(jobs, workers):  # pragma: no cover - optional extra
    try:
        import ray
    except ImportError as e:
        raise RuntimeError("backend='ray' needs the optional extra: pip install 'activetouch[ray]'") from e
    ray.init(ignore_reinit_error=True, num_cpus=workers or None)
    remote = ray.remote(_run_job)
    ray.get([remote.remote(c, d) for c, d in jobs])


def steps_of(out_dir: str | Path) -> list[dict[str, str]]:
    return read_steps(Path(out_dir) / "steps.csv")
