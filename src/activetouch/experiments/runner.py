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

from activetouch.experiments.records import (STEP_COLUMNS, StepWriter, effective_belief, is_finished, read_steps,
                                             write_json_atomic)
from activetouch.registry import belief_settings, get_method

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
    belief: dict[str, Any] = field(default_factory=dict)  # overrides of the belief config (BeliefConfig fields, ...)
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
    the task and method exist and are compatible, the device is available, the particle count is one the belief
    handles, the output folder is writable and the planner accepts ``cfg.planner`` (built once on the task's env).
    Returns ``(task, method, env)``."""
    from activetouch.registry import check_compatible, get_belief, get_method, get_task

    task = get_task(cfg.task)
    method = get_method(cfg.method)
    check_compatible(cfg.task, cfg.method)
    check_device(cfg.device)
    if out_dir is not None:
        check_output_dir(out_dir)
    belief = get_belief(method.belief)
    check = getattr(belief.make, "check_config", None)
    if check is not None:  # the belief's own checks (e.g. CHSEL's minimum batch)
        check(cfg)
    env = task.make_env(seed=cfg.seed, observe_dT=cfg.observe_dT) if "object-motion" in task.provides \
        else task.make_env(seed=cfg.seed)
    est = belief.make(env, cfg, cfg.device)
    if cfg.beta_t != EpisodeConfig.beta_t and not hasattr(est, "terminate"):  # RumiEstimator stops on APC
        raise ValueError(f"--beta-t sets RUMI's APC stop (Eq. 33), but {cfg.method!r} on {cfg.task!r} uses the belief "
                         f"{method.belief!r}, which never stops on APC")
    try:
        method.make_planner(env, est.config, cfg.seed, **cfg.planner)
    except TypeError as e:  # an override the factory does not take
        raise ValueError(f"method {cfg.method!r} does not accept the planner settings {cfg.planner}: {e}") from None
    return task, method, env


def task_belief_defaults(task: str, method: str) -> dict[str, Any]:
    """The belief settings a registered task runs ``method``'s belief with unless ``--belief`` overrides them
    (``{}`` for most: only the task's own belief has task defaults, ``TaskEntry.defaults_belief``)."""
    return belief_settings(task, {}, get_method(method).belief)


_CODE_VERSION: dict[str, Any] | None = None


#: Files of the package that cannot change a result: left out of :func:`source_digest`.
_NOT_CODE = {".pyc", ".md", ".txt", ".orig", ".rej", ".swp", ".bak"}


def source_digest() -> str | None:
    """Short SHA-256 (16 hex digits) of the imported ``activetouch`` package's code and data files (not
    ``__pycache__``, hidden files or :data:`_NOT_CODE` such as the assets' README and SOURCE notes), by relative path
    and content: equal digests, the same code and data. Unlike the git commit it does not change with a commit
    that touches only docs, tests or benchmarks, and it exists for an installed wheel too. None if a file cannot
    be read."""
    import hashlib

    import activetouch

    pkg = Path(activetouch.__file__).resolve().parent
    h = hashlib.sha256()
    for f in sorted(pkg.rglob("*")):
        rel = f.relative_to(pkg)
        if f.is_file() and "__pycache__" not in rel.parts and f.suffix not in _NOT_CODE \
                and not any(p.startswith(".") for p in rel.parts):
            h.update(rel.as_posix().encode() + b"\0")
            try:
                h.update(f.read_bytes())
            except OSError:
                return None
            h.update(b"\0")
    return h.hexdigest()[:16]


def code_version() -> dict[str, Any]:
    """Which code ran: ``{"activetouch": version, "commit": git commit or None, "modified": bool or None,
    "source": source_digest()}``.

    ``commit`` is the ``HEAD`` of the git checkout the package is imported from (None for an installed wheel or
    without git) and ``modified`` whether that checkout's ``src/`` differs from it; ``source`` is the digest of
    the package's files (:func:`source_digest`), which a sweep's resume compares. Recorded in every
    ``summary.json`` so results kept across sessions (``benchmarks/results``) say which code made them; asked
    once per process (two ``git`` calls)."""
    global _CODE_VERSION
    if _CODE_VERSION is None:
        import subprocess

        import activetouch

        pkg = Path(activetouch.__file__).resolve().parent
        commit = modified = None
        try:
            run = lambda *a: subprocess.run(["git", "-C", str(pkg), *a], capture_output=True, text=True,  # noqa: E731
                                            timeout=10)
            head = run("rev-parse", "HEAD")
            if head.returncode == 0 and len(head.stdout.strip()) == 40:
                commit = head.stdout.strip()
                st = run("status", "--porcelain", "--", str(pkg))
                modified = bool(st.stdout.strip()) if st.returncode == 0 else None
        except (OSError, subprocess.SubprocessError):
            pass
        _CODE_VERSION = {"activetouch": activetouch.__version__, "commit": commit, "modified": modified,
                         "source": source_digest()}
    return dict(_CODE_VERSION)


def platform_info() -> dict[str, Any]:
    """What makes two machines' numbers differ: CPU, library versions, threads (for ``summary.json``), and which
    code ran (:func:`code_version`)."""
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
            "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None, **code_version()}


#: Figures any episode may write (removed before a re-run so a folder never shows another run's figures).
FIGURES = ("curves.png", "belief.png", "contact.png", "particles.png", "entropy.png", "tiqf.png", "declutter.png",
           "views.png")


def build_prior(env, features, n: int, generator: torch.Generator, device="cpu") -> torch.Tensor:
    """RUMI's prior ``(P, 4, 4)`` for a rummaging env from the first features (see ``tasks.rummage_prior``)."""
    from activetouch.tasks import rummage_prior

    return rummage_prior(env, n, generator, device, features=features)


def run_episode(cfg: EpisodeConfig, out_dir: str | Path, on_step=None) -> dict[str, Any]:
    """Run one episode of any compatible (task, method) pair and write ``steps.csv``, ``summary.json`` and
    figures to ``out_dir``.

    The loop is RUMI's Algorithm 1 written for any method: plan (lines 5-6), act (7), observe (8-9), and let
    the method's estimator predict and update its belief (10-20); stop when the estimator has converged (RUMI:
    APC), the environment ends the episode (a grasp) or after ``T`` steps. ``on_step(t, estimator, row)`` is
    called after every step's update (step 0: after the initialisation), e.g. by the contract test.
    """
    from activetouch.experiments.episode_log import open_episode_log
    from activetouch.registry import get_belief

    task, method, env = check_config(cfg, out_dir)  # every check before the long work (CHSEL, planning)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "summary.json").unlink(missing_ok=True)  # a re-run is unfinished until its new summary is written
    for name in FIGURES:  # figures of an earlier run in this folder are not this run's
        (out / name).unlink(missing_ok=True)
    torch.manual_seed(cfg.seed)
    gen = torch.Generator(device="cpu").manual_seed(cfg.seed)
    device = torch.device(cfg.device)

    T_max = cfg.steps if cfg.steps is not None else _max_steps(env)
    est = get_belief(method.belief).make(env, cfg, device)
    planner = method.make_planner(env, est.config, cfg.seed, **cfg.planner)

    obs, info = env.reset(seed=cfg.seed)
    elog = open_episode_log(out, cfg, obs, info, gen)  # episode.h5: the reset, then every step (episode_log)
    counts = est.initialise(task, obs, info, gen)
    elog.reset_belief(_belief_record(est))
    planner.reset()

    snapshots: dict[str, Any] = {}
    rows: list[dict[str, Any]] = []
    converged = False
    in_contact = False
    t_episode = time.perf_counter()
    pbar = None
    if cfg.progress:
        from activetouch.experiments.progress import progress

        pbar = progress(T_max, f"{cfg.method} on {cfg.task} (seed {cfg.seed})", unit="step")
    columns = STEP_COLUMNS + tuple(c for c in getattr(est, "COLUMNS", ()) if c not in STEP_COLUMNS)
    with StepWriter(out / "steps.csv", columns) as writer:
        m = est.metrics(info)
        row = {"step": 0, **m, **counts, "in_contact": False, "resampled": False}
        writer.write(row)
        rows.append(row)
        if on_step is not None:
            on_step(0, est, row)
        snapshots["first"] = est.snapshot(info, planner)
        est.first_snapshot(info, planner)
        for t in range(1, T_max + 1):
            if est.converged():
                converged = True
                break
            t0 = time.perf_counter()
            u, timings = planner.next_action(est.belief, env.ee_state(), in_contact, features=est.features)  # 5-6
            t1 = time.perf_counter()
            if t == 1:
                snapshots["first"] = est.snapshot(info, planner)
            ee_before = env.ee_pose() if hasattr(env, "ee_pose") else None
            obs, _, terminated, truncated, info = env.step(u)  # lines 7-9
            in_contact = _in_contact(obs)
            logged = elog.capture(gen)  # the RNG states the update starts from (an exact replay restores them)
            t2 = time.perf_counter()
            fields = est.observe(obs, info, ee_before, gen)  # lines 10-20
            t3 = time.perf_counter()
            elog.step(t, u, obs, info, ee_before, logged, timings,  # appended, flushed and closed per step
                      belief=_belief_record(est, planner))
            m = est.metrics(info)
            row = {"step": t, **m, **fields, "in_contact": in_contact,
                   "plan_s": t1 - t0, "update_s": t3 - t2, "step_s": t2 - t1, **timings}
            writer.write(row)
            rows.append(row)
            if on_step is not None:
                on_step(t, est, row)
            if pbar is not None:
                pbar.set_postfix(**_progress_fields(m, in_contact))
                pbar.update(1)  # after the postfix: a plain progress line prints this step's numbers
            if terminated or truncated:
                break
    elog.close()
    if pbar is not None:
        pbar.close()
    snapshots["last"] = est.snapshot(info, planner)

    nlls = [r["nll"] for r in rows if "nll" in r]  # a Gaussian belief (TIQF) reports ADI instead of RUMI's NLL
    # planning time of the steps that replanned (the others reuse the nominal plan and take ~1 ms)
    plan_times = [r["plan_s"] for r in rows if "plan_s" in r and r.get("replanned", True)]
    success = task.success(rows, info, env)
    est_summary = est.summary()
    summary = {
        "task": cfg.task, "method": cfg.method, "seed": cfg.seed,
        **success,
        "min_nll": min(nlls) if nlls else None, "final_nll": nlls[-1] if nlls else None,
        "cumulative_nll": float(sum(nlls)) if nlls else None,
        "steps": len(rows) - 1, "converged": converged, "final_apc": rows[-1].get("apc"),
        "initial_nll": nlls[0] if nlls else None, **est_summary,
        "final_trans_err": rows[-1]["trans_err"], "final_rot_err_deg": rows[-1]["rot_err_deg"],
        "initial_mean_rot_err_deg": rows[0]["mean_rot_err_deg"], "final_mean_rot_err_deg": rows[-1]["mean_rot_err_deg"],
        "min_mean_rot_err_deg": min(r["mean_rot_err_deg"] for r in rows),
        **_contact_story(rows),
        "median_plan_s": float(np.median(plan_times)) if plan_times else None,
        "wall_s": time.perf_counter() - t_episode,
        "config": asdict(cfg),
        "task_belief_defaults": task_belief_defaults(cfg.task, cfg.method),
        "platform": platform_info(),
    }
    if cfg.figures:  # before summary.json: a kill while plotting leaves an unfinished episode, not a figureless one
        est.write_figures(out, rows, snapshots, cfg.task, success.get("nll_threshold"))
    write_json_atomic(out / "summary.json", summary)
    return summary


#: Cells of an information field kept in the episode log: those above this share of the field's maximum.
FIELD_LOG_SHARE = 0.05


def _belief_record(est, planner=None) -> dict[str, Any]:
    """The belief for the episode log's viewers: ``poses (P, 4, 4)`` and ``weights (P,)`` (float32, CPU); with a
    planner that exposes ``last_field`` (RUMI's I~(x|X), GPVR's variance: the field this step's action was planned
    on), also ``field_points (K, 3)`` and ``field_values (K,)``: the cell centres above FIELD_LOG_SHARE of its
    maximum (a sparse copy; the viewer draws it as a voxel cloud)."""
    rec = {"poses": est.poses.detach().to("cpu", torch.float32).clone(),
           "weights": est.weights.detach().to("cpu", torch.float32).clone()}
    field = getattr(planner, "last_field", None) if planner is not None else None
    if field is not None:
        grid, values = field
        v = torch.as_tensor(values).detach().to("cpu", torch.float32).reshape(-1)
        vmax = float(v.max()) if v.numel() else 0.0
        if vmax > 0 and math.isfinite(vmax):
            keep = v > FIELD_LOG_SHARE * vmax
            rec["field_points"] = grid.points().reshape(-1, 3)[keep].to(torch.float32)
            rec["field_values"] = v[keep]
    return rec


def _max_steps(env) -> int:
    """The task's step budget T: ``env.max_steps`` when the env defines it (grasp tasks: pokes + the grasp), else
    its spec's (RUMI: 40)."""
    return int(getattr(env, "max_steps", None) or env.spec.max_steps)


def _in_contact(obs) -> bool:
    """The step's contact flag: ``obs.in_contact``, or any contact sample ``obs.z`` (touch observations)."""
    if hasattr(obs, "in_contact"):
        return bool(obs.in_contact)
    z = getattr(obs, "z", None)
    return bool(np.asarray(z).any()) if z is not None else False


def _progress_fields(m: dict[str, float], in_contact: bool) -> dict[str, str]:
    fields = {"nll": f"{m['nll']:.1f}"} if "nll" in m else {}
    if "adi_mm" in m:
        fields["adi"] = f"{m['adi_mm']:.1f}mm"
    if "apc" in m:
        fields["apc"] = f"{m['apc'] * 1000:.1f}mm"
    fields["contact"] = str(int(in_contact))
    return fields


def _contact_story(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The first contact's step and the belief's weighted rotation error just before it (camera-only evidence
    until then), for the printout of what touching taught."""
    t = next((int(r["step"]) for r in rows if r.get("in_contact")), None)
    return {"first_contact_step": t,
            "mean_rot_err_deg_before_contact": None if t is None else rows[t - 1]["mean_rot_err_deg"]}


def episode_dir(root: str | Path, task: str, method: str, seed: int) -> Path:
    return Path(root) / task / method / f"seed{seed:03d}"


def run_sweep(tasks, methods, seeds, root, base: EpisodeConfig | None = None, workers: int = 1,
              backend: str = "process", ray_address: str | None = None, pairs=None,
              retries: int = 2, allow_other_code: bool = False) -> list[dict[str, Any]]:
    """Run every (task, method, seed) episode, skipping finished ones (resume), in a local process pool
    (default) or on Ray (``backend='ray'``, optional extra ``activetouch[ray]``): a local Ray instance, or the
    existing cluster at ``ray_address``, one Ray task per episode retried up to ``retries`` times when its worker
    dies. ``pairs``: run these ``(task, method)`` pairs instead of every task x method (``sweep --grid``).

    A finished episode is reused only if it ran with the same settings (else ValueError) and, unless
    ``allow_other_code``, with the same package files (``platform.source``, :func:`source_digest`; an episode that
    records no digest, run before activetouch recorded one, counts as other code): a code change can change every
    result without changing a setting (the contact-point fix moved box RUMI from 8/30 to 13/30), so a resume must
    not pool the two silently."""
    from activetouch.experiments.progress import progress
    from activetouch.experiments.records import load_summaries, settings_diff

    base = base or EpisodeConfig()
    tasks, methods, seeds = list(tasks), list(methods), list(seeds)
    if pairs is not None:
        pairs = [tuple(p) for p in pairs]
        if not pairs:
            raise ValueError("a grid sweep needs at least one compatible (task, method) pair")
        tasks = list(dict.fromkeys(t for t, _ in pairs))
        methods = list(dict.fromkeys(m for _, m in pairs))
    else:
        pairs = [(t, m) for t in tasks for m in methods]
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
    if ray_address is not None and backend != "ray":
        raise ValueError("ray_address needs backend='ray'")
    if not isinstance(retries, int) or retries < 0:
        raise ValueError(f"retries must be an int >= 0, got {retries!r}")
    check_output_dir(root)
    for task, method in pairs:  # names, device, particles and planner settings: checked before any episode starts
        check_config(replace(base, task=task, method=method, seed=seeds[0]))
    jobs = []
    for task, method in pairs:
        for seed in seeds:
            d = episode_dir(root, task, method, seed)
            cfg = replace(base, task=task, method=method, seed=seed, progress=False)
            if is_finished(d):
                done_summary = load_summaries([d])[0]
                done = done_summary.get("config", {})
                diff = settings_diff(done, asdict(cfg))
                was = effective_belief(done_summary)
                now = belief_settings(task, cfg.belief, get_method(method).belief)
                if was != now:
                    diff = ", ".join(x for x in (diff, f"belief settings with the task's defaults: {was} != {now}")
                                     if x)
                if diff:  # a resume never mixes runs of different settings
                    raise ValueError(f"{d} holds an episode run with other settings ({diff}): resume with "
                                     "the same settings or sweep into another --out folder")
                ran = (done_summary.get("platform") or {}).get("source")
                here = code_version()["source"]
                if not allow_other_code and (ran is None or here is None or ran != here):
                    what = f"package digest {ran}, this is {here}" if ran is not None else \
                        "it records no package digest: run by an activetouch older than the digest"
                    raise ValueError(f"{d} holds an episode run by other code ({what}): sweep into another --out "
                                     "folder, or pass --allow-other-code if the change cannot affect these episodes")
                continue
            jobs.append((cfg, d))
    log.info("%d episodes to run (%d already finished)", len(jobs), len(pairs) * len(seeds) - len(jobs))
    if jobs:
        bar = progress(len(jobs), "episodes", unit="episode", every_s=0.0)
        if backend == "ray":
            _run_ray(jobs, workers, ray_address, retries, bar)
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
    return load_summaries(episode_dir(root, t, m, s) for t, m in pairs for s in seeds)


def _run_job(cfg: EpisodeConfig, d: Path) -> dict[str, Any]:
    torch.set_num_threads(1)
    return run_episode(cfg, d)


def _run_ray(jobs, workers: int, address: str | None = None, retries: int = 2, bar=None) -> None:
    """One Ray task per episode (``max_retries=retries``: re-run when its worker process dies); on the cluster at
    ``address`` (``ray.init(address=...)``, e.g. ``ray://head:10001`` or ``auto``), else on a local Ray instance with
    ``workers`` CPUs. Episode folders must be on storage every node sees (the results are files)."""
    try:
        import ray
    except ImportError as e:
        raise ValueError("backend='ray' needs the optional extra: pip install 'activetouch[ray]'") from e
    started = not ray.is_initialized()
    if started:
        if address is not None:
            ray.init(address=address, log_to_driver=False)
        else:
            ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
    try:
        remote = ray.remote(num_cpus=1, max_retries=retries)(_run_job)
        pending = [remote.remote(c, d) for c, d in jobs]
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            ray.get(done)  # re-raises an episode's error (after its retries) here
            if bar is not None:
                bar.update(len(done))
    finally:
        if started:
            ray.shutdown()


def steps_of(out_dir: str | Path) -> list[dict[str, str]]:
    return read_steps(Path(out_dir) / "steps.csv")
