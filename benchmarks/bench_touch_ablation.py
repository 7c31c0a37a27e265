"""Table II ablation of the touch-only particle filter (paper Sec. VI-B, Fig. 4): Binary vs Smooth vs Smooth &
Resampled over many planar pushing runs (:mod:`activetouch.experiments.touch_ablation`).

Usage: ``python benchmarks/bench_touch_ablation.py [--runs 1000] [--seed 0] [--out DIR] [--threads 1]``.

Writes into ``DIR`` as it goes: ``runs.csv`` (one row per run, flushed after each run, so an interrupted sweep keeps
its results), then ``table_ii.csv`` / ``table_ii.md`` (ours beside the paper's numbers), ``summary.json`` and
``fig4.png`` (run 0, Fig. 4-like). Prints the table and the wall time. Measured on this shared 2-core CPU with one
torch thread and one MuJoCo thread: ~0.6 s per run (two batched rollouts of 100 particles x 400 steps ~0.3 s each,
30 filter updates), so 1,000 runs take ~10 minutes.
"""
from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import torch

from activetouch.experiments.touch_ablation import (
    METRICS,
    VARIANTS,
    AblationConfig,
    PlanarPushSim,
    _run_seed,
    plot_run,
    run_ablation,
    save_summary,
    simulate_run,
    table_markdown,
    write_table,
)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("touch_ablation_out"))
    ap.add_argument("--threads", type=int, default=1, help="MuJoCo rollout threads")
    ap.add_argument("--torch-threads", type=int, default=1,
                    help="torch CPU threads (1: the filter's tensors are small; 2 OpenMP threads on a loaded "
                         "2-core machine spin)")
    ap.add_argument("--no-figure", action="store_true")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.torch_threads)
    args.out.mkdir(parents=True, exist_ok=True)
    cfg = AblationConfig()
    cols = ["run", "run_seed", "n_contacts", "n_observed_contacts"] + [f"{k}_{m}" for k in VARIANTS for m in METRICS] \
        + ["smooth_resampled_n_resamples", "smooth_resampled_n_replaced"]
    t0 = time.perf_counter()
    with open(args.out / "runs.csv", "w", newline="") as f:
        wr = csv.DictWriter(f, fieldnames=cols)
        wr.writeheader()

        def on_run(i: int, rec: dict) -> None:
            row = {c: rec.get(c) for c in cols[:4]}
            for k in VARIANTS:
                for m in METRICS:
                    row[f"{k}_{m}"] = rec[k][m]
            row["smooth_resampled_n_resamples"] = rec["smooth_resampled"]["n_resamples"]
            row["smooth_resampled_n_replaced"] = rec["smooth_resampled"]["n_replaced"]
            wr.writerow(row)
            f.flush()

        result = run_ablation(args.runs, args.seed, progress=True, config=cfg, threads=args.threads, on_run=on_run)
    wall = time.perf_counter() - t0
    write_table(result["summary"], args.out, runs=args.runs)
    save_summary(result, args.out / "summary.json")
    if not args.no_figure:
        rec = simulate_run(_run_seed(args.seed, 0), cfg, PlanarPushSim(cfg), keep=True)
        plot_run(rec, args.out / "fig4.png", cfg)
    print(table_markdown(result["summary"], args.runs))
    print(f"{args.runs} runs in {wall:.1f} s ({wall / args.runs:.2f} s per run); results in {args.out}")
    return result


if __name__ == "__main__":
    main()
