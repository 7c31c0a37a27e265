"""``activetouch`` command line.

    activetouch tasks                          list the registered tasks (and the methods that run on each)
    activetouch methods [--task T]             list the registered methods (which run on T, and why not)
    activetouch show mug-0 --out mug0.png      picture of a task's start
    activetouch run mug-0 --method rumi --seed 0 --out runs/mug0
    activetouch sweep --tasks mug-0 mug-1 --methods rumi info-only --seeds 10 --out runs/sweep --workers 2
    activetouch table runs/sweep               results next to the paper's Tables V/VI
    activetouch table runs/noterm --stop-at-beta-t 0.03 0.02   a --no-terminate sweep scored at other APC stops
    activetouch report runs/sweep              Tables V, VI, VII as CSV + Markdown and the Fig. 16 NLL curves
    activetouch demo                           RUMI on mug-2 with figures (the README's demo)
    activetouch bench {belief,step,planning,touch-ig,touch-step,grasp-env,poke-push,touch-ablation,tiqf,clutter,nbt,first-view,all}
    activetouch run grasp-box-0 --method touch-ig   the touch paper: poke, localise, grasp
    activetouch replay runs/mug0/episode.h5 [--method M]   re-run an estimator offline on a recorded episode
"""
from __future__ import annotations

import argparse
import logging
import os
import runpy
import sys
from pathlib import Path


def _episode_args(p: argparse.ArgumentParser, method: bool = True) -> None:
    if method:  # a sweep takes --methods instead (one spelling per command: no silently ignored --method)
        p.add_argument("--method", default="rumi", help="registered method (see `activetouch methods`)")
    p.add_argument("--steps", type=int, default=None, help="steps T (default: the task's, 40)")
    p.add_argument("--particles", type=int, default=100, help="pose particles P (Table IV: 100)")
    p.add_argument("--device", default="cuda" if _cuda() else "cpu", help="torch device (default: cuda if present)")
    p.add_argument("--no-chsel", action="store_true", help="skip CHSEL initialisation (faster, worse prior)")
    p.add_argument("--chsel-iterations", type=int, default=5)
    p.add_argument("--estimate-dT", action="store_true", help="estimate object motion with ObjMove (Alg. 5) "
                   "instead of observing it as the paper does in sim")
    p.add_argument("--samples", type=int, default=None, help="KMPPI samples (paper: 500)")
    p.add_argument("--rollouts", type=int, default=None, help="stochastic rollouts per sample (paper: 5)")
    p.add_argument("--horizon", type=int, default=None, help="KMPPI horizon H (paper: 15)")
    p.add_argument("--no-terminate", action="store_true", help="run all T steps even after APC convergence")
    p.add_argument("--beta-t", type=float, default=0.03,
                   help="RUMI tasks: stop when APC < BETA_T l_c (Eq. 33; paper, sim: 0.03)")
    p.add_argument("--planner", action="append", default=[], metavar="KEY=VALUE",
                   help="override a planner setting (repeatable), e.g. --planner predict=static (the method's config)")
    p.add_argument("--belief", action="append", default=[], metavar="KEY=VALUE",
                   help="override a belief setting (repeatable), e.g. --belief sigma_R=0.1 (BeliefConfig fields)")
    p.add_argument("--no-figures", action="store_true")


def _cuda() -> bool:
    try:
        import torch

        return torch.cuda.is_available()
    except Exception:  # pragma: no cover
        return False


def _episode_config(a, task: str, seed: int):
    from activetouch.experiments.runner import EpisodeConfig

    planner = {k: v for k, v in (("num_samples", a.samples), ("rollout_samples", a.rollouts), ("horizon", a.horizon))
               if v is not None}
    extra = _key_values(a.planner, "--planner")
    both = sorted(set(extra) & set(planner))
    if both:
        raise ValueError(f"--planner sets {both}, which --samples / --rollouts / --horizon already set")
    planner.update(extra)
    return EpisodeConfig(task=task, method=getattr(a, "method", "rumi"), seed=seed, steps=a.steps,
                         particles=a.particles, device=a.device, use_chsel=not a.no_chsel,
                         chsel_iterations=a.chsel_iterations, observe_dT=not a.estimate_dT,
                         terminate_on_convergence=not a.no_terminate, beta_t=a.beta_t,
                         planner=planner, figures=not a.no_figures, belief=_key_values(a.belief, "--belief"))


def _print_grasp_summary(s: dict, out: Path) -> None:
    grasp = ("lifted the box" if s["success"] else "did not lift the box") if s.get("grasped") else "no grasp attempted"
    p = s.get("grasp_p_at_grasp")
    print(f"  grasp           {grasp}" + (f" (predicted P(success) {p:.2f}, App. D-d)" if p is not None else ""))
    print(f"  pokes           {s['iterations']:10d}   (localisation actions before the grasp, at most 15)")
    print(f"  final error     {s['final_trans_err'] * 1000:8.1f} mm, {s['final_rot_err_deg']:.1f} deg "
          "(maximum-likelihood particle)")
    print(f"  nll             {s['initial_nll']:.1f} at step 0 -> {s['final_nll']:.1f} at the end")
    if s.get("median_plan_s") is not None:
        print(f"  median plan s   {s['median_plan_s']:10.3f}")
    files = [f for f in ("steps.csv", "summary.json", "particles.png", "entropy.png") if (out / f).exists()]
    print(f"  results in      {out}/ ({', '.join(files)})")


def _print_clutter_summary(s: dict, out: Path) -> None:
    def rate(k):
        return "-" if s.get(k) is None else f"{100 * s[k]:.0f} %"

    print(f"  ADI (Eq. 28)    {s['initial_adi_mm']:8.1f} mm at the prior -> {s['final_adi_mm']:.1f} mm at the end "
          "(success: < 10 mm)")
    print(f"  final error     {s['final_trans_err_mm']:8.1f} mm (Eq. 26), {s['final_rot_err_deg_tiqf']:.1f} deg (Eq. 27)")
    print(f"  actions         {s['views']} views, {s['touches']} touches, {s['picks']} grasps ({rate('pick_success_rate')} "
          f"succeeded), {s['pushes']} pushes ({rate('push_success_rate')})")
    if s.get("stop_reason"):
        print(f"  stopped         {s['stop_reason']}")
    files = [f for f in ("steps.csv", "summary.json", "tiqf.png", "declutter.png", "views.png") if (out / f).exists()]
    print(f"  results in      {out}/ ({', '.join(files)})")


def _key_values(items: list[str], flag: str) -> dict:
    """``["sigma_R=0.1", "kind=binary"]`` -> ``{"sigma_R": 0.1, "kind": "binary"}`` (numbers, booleans parsed)."""
    import json

    out = {}
    for item in items:
        key, eq, raw = item.partition("=")
        if not eq or not key.strip():
            raise ValueError(f"{flag} takes KEY=VALUE, got {item!r}")
        try:
            value = json.loads(raw)
        except json.JSONDecodeError:
            value = raw
        out[key.strip()] = value
    return out


def _print_summary(s: dict, out: Path) -> None:
    ok = "SUCCESS" if s["success"] else "failure"
    print(f"\n{s['method']} on {s['task']} (seed {s['seed']}): {ok}")
    if "final_adi_mm" in s:  # a visuo-tactile clutter task (success: final ADI < 10 mm)
        _print_clutter_summary(s, out)
        return
    if "nll_threshold" not in s:  # a touch-only grasp task (success: the box was lifted)
        _print_grasp_summary(s, out)
        return
    print(f"  min nll         {s['min_nll']:10.1f}   (success threshold {s['nll_threshold']:g}, Table III"
          + (", already met at step 0)" if s.get("success_at_step0") else ")"))
    if "strict_success" in s:
        t = s["first_strict_success_step"]
        print(f"  strict success  {'yes, at step ' + str(t) if t is not None else 'no':>10}   "
              "(nll below the threshold and weighted rotation error < 10 deg at the same step)")
    print(f"  final nll       {s['final_nll']:10.1f}")
    print(f"  cumulative nll  {s['cumulative_nll']:10.1f}")
    print(f"  steps           {s['steps']:10d}   converged (APC < beta_t l_c): {s['converged']}")
    if s.get("final_mean_rot_err_deg") is not None:
        t = s.get("first_contact_step")
        before = (f"{s['mean_rot_err_deg_before_contact']:.1f} deg before the first contact (step {t}) -> "
                  if t is not None else "no contact -> ")
        print(f"  weighted rotation error {s['initial_mean_rot_err_deg']:.1f} deg at step 0 (first view) -> "
              f"{before}{s['final_mean_rot_err_deg']:.1f} deg at the end")
    if s.get("median_plan_s") is not None:
        print(f"  median plan s   {s['median_plan_s']:10.3f}")
    files = [f for f in ("steps.csv", "summary.json", "curves.png", "belief.png", "contact.png") if (out / f).exists()]
    print(f"  results in      {out}/ ({', '.join(files)})")


def cmd_run(a) -> int:
    from activetouch.experiments.runner import run_episode

    out = Path(a.out or f"runs/{a.task}-{a.method}-seed{a.seed}")
    cfg = _episode_config(a, a.task, a.seed)
    live = None
    if getattr(a, "view", False):  # the 3-D viewer, updated after every step
        from activetouch.viewer import LiveViewer

        live = LiveViewer(out, port=a.port, host=a.host)
        print(f"live viewer at {live.url}", flush=True)
    try:
        s = run_episode(cfg, out)
        _print_summary(s, out)
        if live is not None:
            from activetouch.viewer import wait_for_interrupt

            live.refresh()
            print(f"the viewer stays at {live.url} (Ctrl-C to stop)", flush=True)
            wait_for_interrupt()
    finally:
        if live is not None:
            live.stop()
    return 0


DEMO_TASK = "mug-2"  # the handle faces away from the camera: the first view leaves the yaw open on any machine


def cmd_demo(a) -> int:
    from activetouch.experiments.runner import run_episode

    out = Path(a.out)
    print("activetouch demo: RUMI (information gain + reachability, KMPPI) rummaging for the pose of a mug whose\n"
          "handle faces away from the camera (task mug-2): the first view cannot tell the mug's yaw, touching the\n"
          "handle can. Writes figures and per-step results to", out)
    a.method = "rumi"
    s = run_episode(_episode_config(a, DEMO_TASK, a.seed), out)
    _print_summary(s, out)
    return 0


def _tables(summaries: list[dict]) -> str:
    """The tables of a set of finished episodes, by family: RUMI's Table III, the touch paper's Table I, the
    visuo-tactile paper's Table I."""
    from activetouch.experiments import clutter_tables
    from activetouch.experiments.tables import markdown_table
    from activetouch.experiments.touch_tables import is_grasp_summary, table_i_markdown

    clutter = [s for s in summaries if clutter_tables.is_clutter_summary(s)]
    grasp = [s for s in summaries if is_grasp_summary(s)]
    rumi = [s for s in summaries if not is_grasp_summary(s) and not clutter_tables.is_clutter_summary(s)]
    parts = []
    if rumi:
        parts.append(markdown_table(rumi))
    if grasp:
        parts.append("Touch-only localisation, Table I (grasp success; the paper's numbers are real-robot runs):\n"
                     + table_i_markdown(grasp))
    if clutter:
        parts.append("Visuo-tactile clutter, Table I (final ADI, Eq. 28, and translation error, Eq. 26; the paper's "
                     "numbers are real-robot runs on other objects):\n" + clutter_tables.table_i_markdown(clutter))
    return "\n\n".join(parts)


def cmd_sweep(a) -> int:
    from activetouch.experiments.runner import EpisodeConfig, run_sweep

    if a.seeds < 1:
        raise ValueError(f"--seeds must be >= 1, got {a.seeds}")
    if a.seed0 < 0:
        raise ValueError(f"--seed0 must be >= 0, got {a.seed0}")
    from activetouch import registry

    pairs = None
    if a.grid:  # every compatible pair among the given (default: all registered) tasks and methods
        tasks = a.tasks or registry.tasks()
        methods = a.methods or [m for m in registry.methods() if not registry.get_method(m).needs_arguments]
        for t in tasks:
            registry.get_task(t)
        for m in methods:
            registry.get_method(m)
        pairs = [(t, m) for t in tasks for m in methods if registry.compatible(t, m)]
        if not pairs:
            raise ValueError(f"no compatible (task, method) pair among tasks {tasks} and methods {methods}")
        a.tasks = [t for t, _ in pairs]
    elif not a.tasks:
        raise ValueError("sweep needs --tasks (or --grid for every compatible pair)")
    methods = a.methods or ["rumi"]
    backend = "ray" if a.ray_address else a.backend
    base = _episode_config(a, a.tasks[0], 0)
    summaries = run_sweep(a.tasks, methods, list(range(a.seed0, a.seed0 + a.seeds)), a.out,
                          base=EpisodeConfig(**{**base.__dict__, "figures": not a.no_figures}),
                          workers=a.workers, backend=backend, ray_address=a.ray_address, pairs=pairs,
                          retries=a.retries, allow_other_code=a.allow_other_code)
    table = _tables(summaries)
    Path(a.out, "table.md").write_text(table + "\n")
    print(table)
    if a.grid:
        from activetouch.experiments.grid_table import grid_markdown

        grid = grid_markdown(summaries)
        Path(a.out, "grid.md").write_text(grid + "\n")
        print("\nGrid (every compatible task x method):\n" + grid)
    return 0


def _code_line(summaries) -> str:
    """``code: commit 1a2b3c4d files 0123abcd (30 episodes), unrecorded (5)``: which code made the episodes of a
    table (``platform.commit`` in summary.json; ``+modified`` when the checkout's src/ differed from the commit;
    ``files``: the package digest ``platform.source``, which differs whenever the code or data did)."""
    from collections import Counter

    def label(s) -> str:
        p = s.get("platform") or {}
        files = f" files {p['source'][:8]}" if p.get("source") else ""
        if not p.get("commit"):
            return ("unrecorded" if "commit" not in p else "no git checkout") + files
        return f"commit {p['commit'][:8]}" + ("+modified" if p.get("modified") else "") + files

    counts = Counter(label(s) for s in summaries)
    return "code: " + ", ".join(f"{k} ({n} episodes)" for k, n in counts.most_common())


def cmd_table(a) -> int:
    from activetouch.experiments.records import check_same_settings, load_summaries, settings_key

    if not Path(a.root).is_dir():
        raise ValueError(f"{a.root!r} is not a folder")
    dirs = sorted({p.parent for p in Path(a.root).rglob("summary.json")})
    summaries = load_summaries(dirs)
    if not summaries:
        raise ValueError(f"no finished episodes (summary.json) under {a.root}")
    settings = check_same_settings(summaries)
    stop_betas = getattr(a, "stop_at_beta_t", None)
    if stop_betas:  # checked before anything is printed: a wrong folder gives one line, not a half answer
        from activetouch.experiments.records import read_steps
        from activetouch.experiments.stop_rule import stop_rule_markdown, stop_rule_rows

        episodes = []
        for s in summaries:
            p = Path(s["_dir"]) / "steps.csv"
            if not p.exists():
                raise ValueError(f"{s['_dir']} has no steps.csv: --stop-at-beta-t replays each episode's APC")
            episodes.append((s, read_steps(p)))
        stop_table = stop_rule_markdown(stop_rule_rows(episodes, stop_betas))
    print(f"{len(summaries)} episodes, settings {settings_key(summaries[0]['config'])}: "
          + ", ".join(f"{k}={v}" for k, v in settings.items()))
    print(_code_line(summaries))
    print(_tables(summaries))
    if stop_betas:
        print("\nHad each episode stopped at APC < beta_t l_c (RUMI Eq. 33; replayed from the --no-terminate "
              "episodes' steps.csv, exact: the stop rule never changes what the robot or the belief does):\n"
              + stop_table)
    if getattr(a, "grid", False):
        from activetouch.experiments.grid_table import grid_markdown

        print("\nGrid (every task x method that ran):\n" + grid_markdown(summaries))
    from activetouch.experiments import clutter_plots, clutter_tables

    if any(clutter_tables.is_clutter_summary(s) for s in summaries):  # Fig. 6 of the visuo-tactile paper
        episodes = {m: rows for m, rows in clutter_plots.load_episode_rows(a.root).items() if rows}
        if episodes:
            path = clutter_plots.error_curves_figure(Path(a.root) / "fig6.png", episodes,
                                                     title=f"Fig. 6: error after each view / touch ({a.root})")
            print(f"\nFig. 6 (ADI and translation error after each view and touch): {path}")
            # per target too: pooled, the later touches are only the episodes that needed them (the hard ones)
            for task in sorted({s["task"] for s in summaries if clutter_tables.is_clutter_summary(s)}):
                eps = {m: rows for m, rows in clutter_plots.load_episode_rows(a.root, task).items() if rows}
                if eps:
                    p = clutter_plots.error_curves_figure(Path(a.root) / f"fig6-{task}.png", eps,
                                                          title=f"Fig. 6: {task} ({a.root})")
                    print(f"  {task}: {p}")
    return 0


def cmd_report(a) -> int:
    from activetouch.experiments.report import build_report, format_report

    if not Path(a.root).is_dir():
        raise ValueError(f"{a.root!r} is not a folder")
    print(format_report(build_report(a.root, a.out)))
    return 0


#: what ``activetouch replay`` prints of the estimator's final metrics (the ones it reports, in this order)
REPLAY_METRICS = ("nll", "apc", "adi_mm", "trans_err", "rot_err_deg", "mean_rot_err_deg", "xy_err", "yaw_err_deg",
                  "entropy", "sigma_trace", "active_share")


def cmd_replay(a) -> int:
    from activetouch.experiments.episode_log import replay

    s = replay(a.log, method=a.method, out_dir=a.out, device=a.device)
    other = "" if s["method"] == s["logged_method"] else f" (recorded with {s['logged_method']})"
    print(f"\nreplayed {s['method']} on {s['task']} (seed {s['seed']}) from {s['source_log']}{other}")
    print(f"  steps           {s['steps']:10d}" + ("" if s["log_complete"] else
                                                   "   (an unfinished log: the run stopped before its end)"))
    final = s["final"]
    shown = [k for k in REPLAY_METRICS if k in final] or sorted(final)
    print("  final           " + ", ".join(f"{k} {final[k]:.4g}" for k in shown))
    if s.get("success") is not None:
        print(f"  success         {s['success']}")
    print(f"  results in      {s['out_dir']}/ (steps.csv, summary.json)")
    return 0


def cmd_tasks(a) -> int:
    from activetouch import registry

    for name in registry.tasks():
        t = registry.get_task(name)
        runs = [m for m in registry.methods() if registry.compatible(name, m)]
        print(f"{name:12s} [{t.family}] {t.description}")
        print(f"{'':12s}   methods: {', '.join(runs) or 'none'}")
    return 0


def cmd_methods(a) -> int:
    from activetouch import registry

    if a.task is not None:
        registry.get_task(a.task)  # ValueError naming the known tasks
    for name in registry.methods():
        m = registry.get_method(name)
        if a.task is None:
            print(f"{name:12s} [belief {m.belief}] {m.description}")
            print(f"{'':12s}   needs: {', '.join(sorted(m.requires))}")
            continue
        miss = registry.missing(a.task, name)
        status = "runs" if not miss else f"cannot run: {a.task} does not provide {', '.join(sorted(miss))}"
        print(f"{name:12s} {status}")
    return 0


def cmd_show(a) -> int:
    from activetouch import registry, sim

    if registry.get_task(a.task).family != "rummage":
        raise ValueError(f"`show` draws the RUMI tasks; {a.task} has no picture yet: run it and look at particles.png")
    env = sim.make(a.task, seed=a.seed)
    env.reset(seed=a.seed)
    out = Path(a.out or f"{a.task}.png")
    env.render(out)
    print(f"saved {out}")
    return 0


#: ``activetouch bench NAME`` runs ``benchmarks/bench_NAME.py`` (hyphens for underscores)
BENCHMARKS = ("belief", "step", "planning", "touch-ig", "touch-step", "grasp-env", "poke-push", "touch-ablation", "tiqf",
              "clutter", "nbt", "first-view")


def _repo_benchmarks() -> Path:
    for base in (Path.cwd(), Path(__file__).resolve().parents[2]):
        if (base / "benchmarks").is_dir():
            return base / "benchmarks"
    raise SystemExit("benchmarks/ not found: run `activetouch bench` from a clone of the repository")


def cmd_bench(a) -> int:
    bdir = _repo_benchmarks()
    names = list(BENCHMARKS) if a.which == "all" else [a.which]
    for n in names:
        script = bdir / f"bench_{n.replace('-', '_')}.py"
        if not script.exists():
            print(f"missing {script}", file=sys.stderr)
            return 1
        print(f"== {script.name} ==", flush=True)
        sys.argv = [str(script), *a.args]
        runpy.run_path(str(script), run_name="__main__")
    return 0


def cmd_view(a) -> int:
    from activetouch.experiments.episode_log import LOG_NAME

    folder = Path(a.dir)
    log_file = folder if folder.is_file() else folder / LOG_NAME
    if not log_file.is_file():
        raise ValueError(f"{a.dir!r} has no {LOG_NAME}: pass a finished episode folder (every run writes one)")
    from activetouch import viewer

    server = viewer.serve(log_file, port=a.port, host=a.host, block=False)
    print(f"viewer of {log_file} at http://{a.host}:{server.get_port()} (Ctrl-C to stop)", flush=True)
    try:
        viewer.wait_for_interrupt()
    finally:
        server.stop()
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="activetouch", description="Active tactile pose estimation of known objects.",
                                allow_abbrev=False)
    p.add_argument("-v", "--verbose", action="store_true")
    sub = p.add_subparsers(dest="cmd", required=True)

    r = sub.add_parser("run", help="run one episode of a method on a task", allow_abbrev=False)
    r.add_argument("task")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--out", default=None, help="output folder (default runs/TASK-METHOD-seedS)")
    r.add_argument("--view", action="store_true", help="serve the 3-D viewer, updated after every step (viser)")
    r.add_argument("--port", type=int, default=8080, help="the viewer's port (with --view)")
    r.add_argument("--host", default="127.0.0.1", help="the viewer's host (with --view)")
    _episode_args(r)
    r.set_defaults(func=cmd_run)

    d = sub.add_parser("demo", help="RUMI on mug-2 with figures (the README's demo)", allow_abbrev=False)
    d.add_argument("--out", default="runs/demo")
    d.add_argument("--seed", type=int, default=0)
    _episode_args(d)
    d.set_defaults(func=cmd_demo)

    s = sub.add_parser("sweep", help="run tasks x methods x seeds (resumes: finished episodes are skipped)",
                       allow_abbrev=False)
    s.add_argument("--tasks", nargs="+", default=None)
    s.add_argument("--methods", nargs="+", default=None, help="methods (default: rumi; with --grid: all)")
    s.add_argument("--grid", action="store_true",
                   help="every compatible (task, method) pair of --tasks x --methods (default: all registered); "
                        "writes grid.md, one row per pair")
    s.add_argument("--seeds", type=int, default=10, help="number of seeds")
    s.add_argument("--seed0", type=int, default=0)
    s.add_argument("--out", default="runs/sweep")
    s.add_argument("--workers", type=int, default=1)
    s.add_argument("--backend", choices=["process", "ray"], default="process")
    s.add_argument("--ray-address", default=None,
                   help="run on the existing Ray cluster at this address (e.g. ray://head:10001 or auto); implies "
                        "--backend ray; episode folders must be on storage every node sees")
    s.add_argument("--retries", type=int, default=2, help="Ray: re-runs of an episode whose worker died")
    s.add_argument("--allow-other-code", action="store_true",
                   help="resume a folder whose finished episodes were run by other package files (by default a "
                        "resume refuses: a code change can change results without changing any setting)")
    _episode_args(s, method=False)
    s.set_defaults(func=cmd_sweep)

    t = sub.add_parser("table", help="table of finished episodes under a folder, next to the paper's")
    t.add_argument("root")
    t.add_argument("--grid", action="store_true", help="also the one-row-per-(task, method) grid table")
    t.add_argument("--stop-at-beta-t", type=float, nargs="+", default=None, metavar="BETA",
                   help="also the successes had each episode stopped at APC < BETA l_c (RUMI tasks; needs episodes "
                        "run with --no-terminate), e.g. --stop-at-beta-t 0.03 0.02")
    t.set_defaults(func=cmd_table)

    rp = sub.add_parser("report", help="Tables V, VI, VII (CSV + Markdown) and Fig. 16 curves of a finished sweep")
    rp.add_argument("root")
    rp.add_argument("--out", default=None, help="output folder (default ROOT/report)")
    rp.set_defaults(func=cmd_report)

    rl = sub.add_parser("replay", help="re-run a method's estimator offline on a recorded episode (episode.h5)",
                        allow_abbrev=False)
    rl.add_argument("log", help="an episode.h5 (every run writes one) or the episode folder holding it")
    rl.add_argument("--method", default=None, help="method whose estimator to run (default: the recorded one)")
    rl.add_argument("--out", default=None, help="output folder (default: LOG_FOLDER/replay-METHOD)")
    rl.add_argument("--device", default="cpu", help="torch device (default: cpu)")
    rl.set_defaults(func=cmd_replay)

    sub.add_parser("tasks", help="list tasks and the methods that run on each").set_defaults(func=cmd_tasks)
    me = sub.add_parser("methods", help="list methods and what they need; --task T: which run on T and why not")
    me.add_argument("--task", default=None)
    me.set_defaults(func=cmd_methods)

    sh = sub.add_parser("show", help="save a picture of a task's start")
    sh.add_argument("task")
    sh.add_argument("--seed", type=int, default=0)
    sh.add_argument("--out", default=None)
    sh.set_defaults(func=cmd_show)

    vw = sub.add_parser("view", help="3-D viewer of a finished episode in the browser (needs viser)",
                        allow_abbrev=False)
    vw.add_argument("dir", help="an episode folder holding episode.h5 (every run writes one)")
    vw.add_argument("--port", type=int, default=8080)
    vw.add_argument("--host", default="127.0.0.1")
    vw.set_defaults(func=cmd_view)

    b = sub.add_parser("bench", help="run a benchmark script from benchmarks/")
    b.add_argument("which", choices=[*BENCHMARKS, "all"])
    b.add_argument("args", nargs=argparse.REMAINDER)
    b.set_defaults(func=cmd_bench)
    return p


def main(argv: list[str] | None = None) -> int:
    a = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if a.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        return a.func(a)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # the reader of our output left (`activetouch table DIR | head`): stop quietly, as `cat` does, and keep the
        # interpreter's final flush from raising again (the recipe of Python's signal module docs)
        try:
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        except (AttributeError, OSError, ValueError):  # stdout replaced by an object without a file descriptor
            pass
        return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
