"""Benchmark of the touch-only localisation information gain (Alg. 1) on this machine.

* ``expected_information_gain``: C = 20 candidates x T = 30 steps x P = 100 SE(2) particles (target: well under
  100 ms on the CPU), in two cases: every step moves every particle (worst case: C T = 600 shared supports),
  and a poking rollout where only 1 step in 5 moves the particles (the rest are carried forward).
* ``shared_support`` alone on the C T = 600 particle sets (the nearest-neighbour search is the dominant cost).

Usage: ``python benchmarks/bench_touch_ig.py [--C 20 --T 30 --P 100] [--repeats 20] [--threads 1]
[--device cpu] [--dtype float32]``. Prints medians of wall and process CPU time (on a loaded shared machine
the CPU time is the steadier number, and ``--threads 1`` avoids OpenMP spinning against other jobs).
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from activetouch.information.entropy import SE2_PERIODIC, expected_information_gain, se2_scale, shared_support


def _median_s(fn, repeats: int, sync) -> tuple[float, float]:
    """Median wall time and median CPU time of this process (all its threads) per call, seconds."""
    fn()  # warm-up
    wall, cpu = [], []
    for _ in range(repeats):
        sync()
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        sync()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return statistics.median(wall), statistics.median(cpu)


def inputs(C: int, T: int, P: int, device, dtype, moving_every: int = 1, seed: int = 0):
    """SE(2) belief of the paper's App. D c) (two modes, sigma_pos = 0.06 m, sigma_ori = 0.5 rad) and C
    predicted rollouts; particles move (a small random push) on every ``moving_every``-th step only."""
    g = torch.Generator().manual_seed(seed)
    mode = torch.randint(0, 2, (P,), generator=g)
    centres = torch.tensor([[0.5, -0.2, 0.0], [0.5, 0.2, 1.0]])
    x0 = centres[mode] + torch.randn(P, 3, generator=g) * torch.tensor([0.06, 0.06, 0.5])
    push = 0.005 * torch.randn(C, T, P, 3, generator=g)
    push[:, [t for t in range(T) if t % moving_every]] = 0
    x_traj = x0 + push.cumsum(1)
    p_contact = 0.1 + 0.4 * torch.rand(C, T, P, generator=g)  # Eq. 10 range [alpha_fp, alpha_tp]
    z_hyp = p_contact > 0.3
    w0 = torch.full((P,), 1.0 / P)
    return [t.to(device=device, dtype=dtype) if t.is_floating_point() else t.to(device)
            for t in (w0, x0, x_traj, p_contact, z_hyp)]


def main(argv=None) -> dict[str, float]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--C", type=int, default=20)
    ap.add_argument("--T", type=int, default=30)
    ap.add_argument("--P", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's choice)")
    args = ap.parse_args(argv)
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    device, dtype = torch.device(args.device), getattr(torch, args.dtype)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    kw = dict(periodic=SE2_PERIODIC, scale=se2_scale(0.1))

    results = {}
    for name, every in (("ig_all_steps_move", 1), ("ig_every_5th_step_moves", 5)):
        w0, x0, x_traj, p, z = inputs(args.C, args.T, args.P, device, dtype, every)
        results[name] = _median_s(lambda: expected_information_gain(w0, x0, x_traj, p, z, **kw), args.repeats, sync)
    w0, x0, x_traj, p, z = inputs(args.C, args.T, args.P, device, dtype)
    results["shared_support_CT_sets"] = _median_s(lambda: shared_support(x_traj, **kw), args.repeats, sync)

    print(f"device {device}, {dtype}, torch threads {torch.get_num_threads()}, C = {args.C}, T = {args.T}, "
          f"P = {args.P}, {args.repeats} repeats")
    for name, (wall, cpu) in results.items():
        print(f"{name:28s} median wall {wall * 1e3:8.1f} ms   median CPU {cpu * 1e3:8.1f} ms")
    return {k: v[0] for k, v in results.items()}


if __name__ == "__main__":
    main()
