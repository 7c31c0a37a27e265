"""Table II ablation of the touch-only particle filter (paper Sec. VI-B, Fig. 4): Binary vs Smooth vs Smooth &
Resampled in a planar, quasi-static pushing scene.

Scene (MuJoCo, :func:`scene_xml`): a circular robot (a mocap cylinder, radius 25 mm) pushes a rectangular object of
the cracker box's footprint (0.072 x 0.164 m, 5 cm tall, 0.411 kg) along one straight line, from (-0.25, 0) to
(0.15, 0) at 0.1 m/s. The object has joints slide x, slide y and hinge z with viscous damping and dry joint friction
(``frictionloss``) and no floor contact, so it moves only while pushed and stops within ~20 ms
(quasi-static). Simplification: dry friction acts per joint (a box-shaped friction limit in x / y rather than the
isotropic Coulomb disc of a real table); it costs nothing for the comparison, which uses the same dynamics for
the truth and for every particle.

One run (:func:`simulate_run`):

1. Truth ``x* ~ N((0, 0, 0), diag(0.02^2, 0.02^2, 0.3^2))`` (so the straight push nearly always meets it); the prior
   is a broad Gaussian ``N(c, diag(0.05^2, 0.05^2, 0.5^2))`` whose centre ``c`` is itself drawn from that Gaussian
   about the truth, so the truth is a typical draw from the prior, not its mean; 100 particles from it.
2. The true push is simulated step by step; the binary contact ``z`` after each waypoint (5 sim steps, 5 mm) is
   the true robot-object contact flipped with probability ``flip_rate`` = 2 % (sensor noise; the filter's model
   ``alpha_tp = 0.5``, ``alpha_fp = 0.1`` is far more pessimistic, as in the paper).
3. Every particle is predicted by one batched ``mujoco.rollout`` of the same push (no per-particle loop).
4. Three filters, each updated every 8 waypoints (10 updates) with :meth:`TouchBelief.update`: Binary (the step
   model of ref. [3], contact predicted within ``ContactModelConfig.binary_tolerance`` = 2 mm) and Smooth (Eq. 10)
   never resample; Smooth & Resampled resamples (App. B) whenever the ESS
   test triggers, except at the final update (Sec. VI-B). After a resampling the next segment is rolled out
   again from the new particles (at rest: quasi-static); otherwise particles keep their full physics state.
5. Metrics (Sec. VI-B): MSE of position (m^2) and orientation (rad^2) over the 10 highest-weight particles against
   the final true state, and the final share of particles with weight > 1e-4. Orientation errors are taken
   modulo pi: the rectangle looks the same after a half turn, so contact cannot tell yaw from yaw + pi.

The paper does not state the units of its MSE, the prior width or the trajectory; these are our choices, so the
numbers are comparable in trend (ranking of the variants), not in value.
"""
from __future__ import annotations

import csv
import json
import math
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Callable

import mujoco
import numpy as np
import torch
from mujoco import rollout as mj_rollout

from ..belief.contact_model import ContactModelConfig, wrap_angle
from ..belief.touch_filter import TouchBelief, TouchFilterConfig
from ..geometry import invert, transform_points

__all__ = [
    "AblationConfig",
    "PlanarBox",
    "PlanarPushSim",
    "VARIANTS",
    "METRICS",
    "PAPER_TABLE_II",
    "belief_metrics",
    "save_summary",
    "scene_xml",
    "simulate_run",
    "run_ablation",
    "summarise",
    "write_table",
    "table_markdown",
    "plot_run",
]

#: Table II variants: key -> label.
VARIANTS = {"binary": "Binary", "smooth": "Smooth", "smooth_resampled": "Smooth & Resampled"}
METRICS = ("mse_pos", "mse_yaw", "active_share")
#: Paper Table II (mean, std over 1,000 runs): MSE position, MSE orientation, share of active particles.
PAPER_TABLE_II = {
    "binary": {"mse_pos": (0.023, 0.01), "mse_yaw": (0.208, 0.09), "active_share": (0.038, 0.02)},
    "smooth": {"mse_pos": (0.019, 0.01), "mse_yaw": (0.185, 0.10), "active_share": (0.077, 0.03)},
    "smooth_resampled": {"mse_pos": (0.018, 0.01), "mse_yaw": (0.164, 0.17), "active_share": (0.511, 0.14)},
}


@dataclass(frozen=True)
class AblationConfig:
    """Set-up of the Table II ablation (Sec. VI-B). From the paper: ``num_particles`` = 100, the contact model
    (``TouchFilterConfig`` defaults: Eq. 10 with alpha_tp 0.5, alpha_fp 0.1, gamma 1000), ``top_k`` = 10,
    ``active_weight`` = 1e-4. Everything else is our choice (the paper gives no values); see the module notes."""

    num_particles: int = 100
    top_k: int = 10
    active_weight: float = 1e-4
    box_size: tuple[float, float] = (0.072, 0.164)  # cracker box footprint (m)
    box_height: float = 0.05
    box_mass: float = 0.411  # YCB 003_cracker_box
    robot_radius: float = 0.025
    start: tuple[float, float] = (-0.25, 0.0)
    end: tuple[float, float] = (0.15, 0.0)
    timestep: float = 0.01  # s; 0.4 m at 0.1 m/s = 400 steps
    num_waypoints: int = 80
    steps_per_waypoint: int = 5
    waypoints_per_update: int = 8
    slide_damping: float = 20.0  # N s/m: velocity time constant m / b = 20 ms
    slide_friction: float = 1.6  # N: mu m g with mu = 0.4
    hinge_damping: float = 0.05  # N m s/rad: I / b = 22 ms
    hinge_friction: float = 0.03  # N m
    robot_points: int = 64  # points on the robot's circle (distance error r (1 - cos(pi / n)) = 30 um)
    truth_sigma_pos: float = 0.02
    truth_sigma_yaw: float = 0.3
    prior_sigma_pos: float = 0.05
    prior_sigma_yaw: float = 0.5
    flip_rate: float = 0.02
    binary_tolerance: float = ContactModelConfig().binary_tolerance  # the Binary variant's step (m)

    def __post_init__(self):
        for name in ("num_particles", "top_k", "num_waypoints", "steps_per_waypoint", "waypoints_per_update",
                     "robot_points"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"AblationConfig.{name} must be a positive int, got {v!r}")
        if self.num_waypoints % self.waypoints_per_update:
            raise ValueError("AblationConfig.num_waypoints must be a multiple of waypoints_per_update")
        if self.top_k > self.num_particles:
            raise ValueError("AblationConfig.top_k must be <= num_particles")
        if not 0.0 <= self.flip_rate <= 1.0:
            raise ValueError(f"AblationConfig.flip_rate must lie in [0, 1], got {self.flip_rate}")

    @property
    def num_updates(self) -> int:
        return self.num_waypoints // self.waypoints_per_update

    @property
    def num_steps(self) -> int:
        return self.num_waypoints * self.steps_per_waypoint


class PlanarBox:
    """Exact signed distance of a box resting on the table (object frame: origin at the base centre, half sizes
    ``half (3,)``): the filter's object model for the ablation, the very box MuJoCo simulates.

    Duck-types the two ``KnownObject`` methods the touch filter uses (``sdf_world_values``, ``sdf_world``).
    Hand-written (a closed form of a few lines) instead of a ``KnownObject`` of a box mesh: the voxel-cached SDF
    would add a cache build and up to ~1 mm of Taylor error at the edges, where gamma = 1000 / m makes 1 mm
    matter. No ``bounding_radius``: the distance cull is skipped and every distance is exact.
    """

    def __init__(self, half):
        self.half = torch.as_tensor(half, dtype=torch.float64)
        if self.half.shape != (3,) or not bool((self.half > 0).all()):
            raise ValueError(f"half must be 3 positive half sizes, got {half}")

    def _sdf(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h = self.half.to(x)
        c = torch.zeros_like(h)
        c[2] = h[2]
        p = x - c
        q = p.abs() - h
        out = q.clamp_min(0.0)
        on = out.norm(dim=-1)
        qmax, arg = q.max(dim=-1)
        v = on + qmax.clamp_max(0.0)
        g_out = out * torch.sign(p) / on.clamp_min(1e-12).unsqueeze(-1)
        g_in = torch.nn.functional.one_hot(arg, 3).to(x) * torch.sign(p)
        g = torch.where((on > 0).unsqueeze(-1), g_out, g_in)
        return v, g

    @torch.no_grad()
    def sdf_world(self, poses: torch.Tensor, x_world: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Values ``(P, N)`` and object-frame unit gradients ``(P, N, 3)`` at world points ``x (N, 3)``."""
        return self._sdf(transform_points(invert(poses), x_world))

    def sdf_world_values(self, poses: torch.Tensor, x_world: torch.Tensor, exact: bool = False,
                         far_positive_from: int | None = None) -> torch.Tensor:
        """Values ``(P, N)`` of :meth:`sdf_world` (``exact`` / ``far_positive_from`` accepted, always exact)."""
        return self.sdf_world(poses, x_world)[0]


def scene_xml(cfg: AblationConfig) -> str:
    """MJCF of the planar push scene (see the module notes). Object qpos = (x, y, yaw) of its base centre."""
    hx, hy = cfg.box_size[0] / 2, cfg.box_size[1] / 2
    hz = cfg.box_height / 2
    sx, sy = cfg.start
    return f"""<mujoco model="planar_push">
  <option timestep="{cfg.timestep}" integrator="implicitfast"/>
  <worldbody>
    <body name="object">
      <joint name="object_x" type="slide" axis="1 0 0" damping="{cfg.slide_damping}"
             frictionloss="{cfg.slide_friction}"/>
      <joint name="object_y" type="slide" axis="0 1 0" damping="{cfg.slide_damping}"
             frictionloss="{cfg.slide_friction}"/>
      <joint name="object_yaw" type="hinge" axis="0 0 1" damping="{cfg.hinge_damping}"
             frictionloss="{cfg.hinge_friction}"/>
      <geom name="object" type="box" size="{hx} {hy} {hz}" pos="0 0 {hz}" mass="{cfg.box_mass}"
            contype="0" conaffinity="1" friction="0.5 0.005 0.0001"/>
    </body>
    <body name="robot" mocap="true" pos="{sx} {sy} {hz}">
      <geom name="robot" type="cylinder" size="{cfg.robot_radius} {hz + 0.005}" contype="1" conaffinity="0"
            friction="0.5 0.005 0.0001"/>
    </body>
  </worldbody>
</mujoco>"""


class PlanarPushSim:
    """The planar push scene: the true run (step by step, with contacts) and batched particle rollouts.

    Args:
        cfg: :class:`AblationConfig`.
        threads: MuJoCo rollout threads (one ``MjData`` each).
    """

    def __init__(self, cfg: AblationConfig = AblationConfig(), threads: int = 1):
        self.cfg = cfg
        self.model = mujoco.MjModel.from_xml_string(scene_xml(cfg))
        self.datas = [mujoco.MjData(self.model) for _ in range(max(1, int(threads)))]
        self._spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
        self.nstate = mujoco.mj_stateSize(self.model, self._spec)
        # FULLPHYSICS = [time, qpos, qvel, ...] (mjtState bit order): qpos follows the time entry
        self.qpos_at = mujoco.mj_stateSize(self.model, mujoco.mjtState.mjSTATE_TIME)
        self.qvel_at = self.qpos_at + self.model.nq
        d = mujoco.MjData(self.model)
        self._template = np.empty(self.nstate)
        mujoco.mj_getState(self.model, d, self._template, self._spec)
        hz = cfg.box_height / 2
        n = cfg.num_steps
        a = np.array([*cfg.start, hz])
        b = np.array([*cfg.end, hz])
        #: mocap position before each sim step ``(num_steps, 3)``
        self.path = a + (b - a) * (np.arange(1, n + 1) / n)[:, None]
        #: robot centre after each waypoint ``(num_waypoints, 3)``
        self.waypoints = self.path[cfg.steps_per_waypoint - 1::cfg.steps_per_waypoint]
        ang = np.arange(cfg.robot_points) * 2 * np.pi / cfg.robot_points
        circle = cfg.robot_radius * np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], -1)
        #: robot points (its circle at the object's mid-height) after each waypoint ``(W, M, 3)``
        self.robot_points = torch.as_tensor(self.waypoints[:, None] + circle[None], dtype=torch.float64)
        self.box = PlanarBox([cfg.box_size[0] / 2, cfg.box_size[1] / 2, hz])
        self._gid = (mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, "robot"),
                     mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, "object"))

    def initial_states(self, states: np.ndarray, step: int = 0) -> np.ndarray:
        """Full physics states ``(P, nstate)`` at rest with object qpos ``states (P, 3)`` at sim step ``step``."""
        s = np.tile(self._template, (states.shape[0], 1))
        s[:, 0] = step * self.model.opt.timestep
        s[:, self.qpos_at:self.qpos_at + 3] = states
        return s

    def rollout(self, init: np.ndarray, step0: int, nsteps: int) -> np.ndarray:
        """Roll out full states ``init (P, nstate)`` through sim steps ``step0 .. step0 + nsteps`` of the push:
        one batched ``mujoco.rollout`` call; returns the states after every step ``(P, nsteps, nstate)``."""
        ctrl = self.path[step0:step0 + nsteps][None]
        st, _ = mj_rollout.rollout(self.model, self.datas, np.ascontiguousarray(init), ctrl,
                                   control_spec=mujoco.mjtState.mjSTATE_MOCAP_POS.value)
        return st

    def qpos(self, states: np.ndarray) -> np.ndarray:
        """Object qpos ``(..., 3)`` = (x, y, yaw) of full states ``(..., nstate)``."""
        return states[..., self.qpos_at:self.qpos_at + 3]

    def simulate_truth(self, state) -> tuple[np.ndarray, np.ndarray]:
        """The true push from object state ``(3,)``: the object's state ``(W, 3)`` and true contact ``(W,)`` bool
        after each waypoint (robot and object geoms penetrating, MuJoCo's contact distance < 0)."""
        cfg = self.cfg
        d = mujoco.MjData(self.model)
        mujoco.mj_setState(self.model, d, self.initial_states(np.asarray(state, float)[None])[0], self._spec)
        traj = np.empty((cfg.num_waypoints, 3))
        contact = np.zeros(cfg.num_waypoints, bool)
        for k in range(cfg.num_steps):
            d.mocap_pos[0] = self.path[k]
            mujoco.mj_step(self.model, d)
            if (k + 1) % cfg.steps_per_waypoint == 0:
                w = (k + 1) // cfg.steps_per_waypoint - 1
                traj[w] = d.qpos[:3]
                contact[w] = bool(d.ncon > 0 and float(np.min(d.contact.dist[:d.ncon])) < 0)
        return traj, contact


def _wrap_half_turn(a: torch.Tensor) -> torch.Tensor:
    """Angle differences modulo pi, in ``[-pi/2, pi/2)`` (the rectangle's half-turn symmetry)."""
    return torch.remainder(a + math.pi / 2, math.pi) - math.pi / 2


def belief_metrics(belief: TouchBelief, truth, top_k: int = 10) -> dict[str, float]:
    """Sec. VI-B metrics: MSE of position (m^2) and orientation (rad^2, modulo pi) over the ``top_k``
    highest-weight particles against ``truth (3,)``, and the share of particles with weight > 1e-4."""
    truth = torch.as_tensor(truth, dtype=belief.states.dtype)
    idx = torch.topk(belief.weights, top_k).indices
    s = belief.states[idx]
    dp = (s[:, :2] - truth[:2]).square().sum(-1)
    dy = _wrap_half_turn(s[:, 2] - truth[2]).square()
    return dict(mse_pos=float(dp.mean()), mse_yaw=float(dy.mean()), active_share=belief.active_share())


def _run_seed(seed: int, run: int) -> int:
    return int(np.random.SeedSequence([int(seed), int(run)]).generate_state(1)[0])


def simulate_run(run_seed: int, cfg: AblationConfig = AblationConfig(), sim: PlanarPushSim | None = None,
                 keep: bool = False) -> dict:
    """One ablation run (module notes, steps 1-5) from ``run_seed``; deterministic.

    Returns a record: ``truth0``, ``truth_final`` (3 lists), ``n_contacts``, per variant key of :data:`VARIANTS`
    its metrics (and for ``smooth_resampled`` the number of resamplings and replaced particles). ``keep=True``
    adds the arrays :func:`plot_run` draws (``particles0``, ``truth_traj``, ``z``, ``contact``, ``waypoints``,
    ``final`` states / weights per variant).
    """
    sim = sim if sim is not None else PlanarPushSim(cfg)
    g = torch.Generator().manual_seed(int(run_seed))
    P, W, spw, wpu = cfg.num_particles, cfg.num_waypoints, cfg.steps_per_waypoint, cfg.waypoints_per_update
    f64 = torch.float64
    sig_t = torch.tensor([cfg.truth_sigma_pos, cfg.truth_sigma_pos, cfg.truth_sigma_yaw], dtype=f64)
    sig_p = torch.tensor([cfg.prior_sigma_pos, cfg.prior_sigma_pos, cfg.prior_sigma_yaw], dtype=f64)
    truth0 = torch.randn(3, generator=g, dtype=f64) * sig_t
    centre = truth0 + torch.randn(3, generator=g, dtype=f64) * sig_p
    particles0 = centre + torch.randn(P, 3, generator=g, dtype=f64) * sig_p
    particles0[:, 2] = wrap_angle(particles0[:, 2])
    truth_traj, contact = sim.simulate_truth(truth0.numpy())
    flip = (torch.rand(W, generator=g, dtype=f64) < cfg.flip_rate).numpy()
    z = torch.as_tensor(contact ^ flip)
    rp = sim.robot_points
    base = TouchFilterConfig(num_particles=P, active_weight=cfg.active_weight)
    configs = {
        "binary": replace(base, contact=ContactModelConfig(kind="binary", binary_tolerance=cfg.binary_tolerance),
                          resample=False),
        "smooth": replace(base, resample=False),
        "smooth_resampled": base,
    }
    rec: dict = dict(run_seed=int(run_seed), truth0=truth0.tolist(), truth_final=truth_traj[-1].tolist(),
                     n_contacts=int(contact.sum()), n_observed_contacts=int(z.sum()))
    final = {}
    # Binary and Smooth never resample: one rollout of the whole push serves both
    full = sim.rollout(sim.initial_states(particles0.numpy()), 0, cfg.num_steps)
    q_wp = torch.as_tensor(sim.qpos(full[:, spw - 1::spw]))  # (P, W, 3)
    for key in ("binary", "smooth"):
        b = TouchBelief.from_prior(sim.box, particles0, configs[key])
        for u in range(cfg.num_updates):
            w0, w1 = u * wpu, (u + 1) * wpu
            b.update(z[w0:w1], rp[w0:w1], q_wp[:, w0:w1], generator=g)
        rec[key] = belief_metrics(b, truth_traj[-1], cfg.top_k)
        final[key] = b
    # Smooth & Resampled: roll each segment out from the current particles
    b = TouchBelief.from_prior(sim.box, particles0, configs["smooth_resampled"])
    state = sim.initial_states(particles0.numpy())
    n_res, n_rep = 0, 0
    for u in range(cfg.num_updates):
        w0, w1 = u * wpu, (u + 1) * wpu
        seg = sim.rollout(state, w0 * spw, wpu * spw)
        q = torch.as_tensor(sim.qpos(seg[:, spw - 1::spw]))
        out = b.update(z[w0:w1], rp[w0:w1], q, generator=g, resample=u < cfg.num_updates - 1)
        if out["resampled"] is None:
            state = seg[:, -1]
        else:  # new particles start the next segment at rest (quasi-static)
            state = sim.initial_states(b.states.numpy(), w1 * spw)
            n_res += 1
            n_rep += out["n_replaced"]
    rec["smooth_resampled"] = dict(belief_metrics(b, truth_traj[-1], cfg.top_k), n_resamples=n_res,
                                   n_replaced=n_rep)
    final["smooth_resampled"] = b
    if keep:
        rec.update(particles0=particles0.numpy(), truth_traj=truth_traj, z=z.numpy(), contact=contact,
                   waypoints=sim.waypoints,
                   final={k: (v.states.numpy().copy(), v.weights.numpy().copy()) for k, v in final.items()})
    return rec


def summarise(records: list[dict]) -> dict:
    """Mean and std (over runs) of every metric per variant: ``{variant: {metric: {"mean", "std"}}}``."""
    if not records:
        raise ValueError("no runs to summarise")
    out = {}
    for key in VARIANTS:
        out[key] = {}
        for m in METRICS:
            v = np.array([r[key][m] for r in records], dtype=float)
            out[key][m] = {"mean": float(v.mean()), "std": float(v.std(ddof=1)) if v.size > 1 else 0.0}
    return out


def run_ablation(runs: int = 1000, seed: int = 0, progress: bool = True, config: AblationConfig | None = None,
                 threads: int = 1, on_run: Callable[[int, dict], None] | None = None) -> dict:
    """Table II: ``runs`` independent runs (:func:`simulate_run`, run ``i`` seeded from ``(seed, i)``).

    Returns ``{"summary": summarise(records), "runs": records, "config": ..., "wall_s": ...}``; ``summary`` holds
    mean and std per variant of ``mse_pos`` (m^2), ``mse_yaw`` (rad^2) and ``active_share``. ``on_run(i, record)``
    is called after every run (e.g. to write results as they come).
    """
    if not isinstance(runs, int) or runs < 1:
        raise ValueError(f"runs must be a positive int, got {runs!r}")
    cfg = config if config is not None else AblationConfig()
    sim = PlanarPushSim(cfg, threads)
    records = []
    t0 = time.perf_counter()
    bar = None
    if progress:
        from .progress import progress as _progress

        bar = _progress(runs, "touch ablation", unit="run")
    try:
        for i in range(runs):
            rec = simulate_run(_run_seed(seed, i), cfg, sim)
            rec["run"] = i
            records.append(rec)
            if on_run is not None:
                on_run(i, rec)
            if bar is not None:
                bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    return dict(summary=summarise(records), runs=records, config=asdict(cfg), seed=seed,
                wall_s=time.perf_counter() - t0)


# ---------------------------------------------------------------------------------------------- outputs
def _fmt(mean: float, std: float) -> str:
    return f"{mean:.3f} ± {std:.3f}"


def table_markdown(summary: dict, runs: int | None = None) -> str:
    """Table II as Markdown: ours (mean ± std) beside the paper's."""
    head = ("| Method | MSE position (m²) | paper | MSE orientation (rad²) | paper | Active share | paper |\n"
            "|---|---|---|---|---|---|---|")
    rows = []
    for key, label in VARIANTS.items():
        cells = [label]
        for m in METRICS:
            cells += [_fmt(summary[key][m]["mean"], summary[key][m]["std"]), _fmt(*PAPER_TABLE_II[key][m])]
        rows.append("| " + " | ".join(cells) + " |")
    note = f"\n\n{runs} runs; mean ± std over runs." if runs else ""
    return head + "\n" + "\n".join(rows) + note + "\n"


def write_table(summary: dict, out_dir, runs: int | None = None) -> tuple[Path, Path]:
    """Write Table II beside the paper's numbers: ``table_ii.csv`` and ``table_ii.md`` in ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    csv_path, md_path = out / "table_ii.csv", out / "table_ii.md"
    with open(csv_path, "w", newline="") as f:
        wr = csv.writer(f)
        wr.writerow(["method"] + [f"{m}_{s}" for m in METRICS for s in ("mean", "std", "paper_mean", "paper_std")])
        for key, label in VARIANTS.items():
            row = [label]
            for m in METRICS:
                row += [summary[key][m]["mean"], summary[key][m]["std"], *PAPER_TABLE_II[key][m]]
            wr.writerow(row)
    md_path.write_text(table_markdown(summary, runs))
    return csv_path, md_path


def _rect(state, size) -> np.ndarray:
    """Closed footprint outline ``(5, 2)`` of a box state (x, y, yaw)."""
    hx, hy = size[0] / 2, size[1] / 2
    c = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy], [-hx, -hy]])
    ca, sa = math.cos(state[2]), math.sin(state[2])
    return c @ np.array([[ca, sa], [-sa, ca]]) + np.asarray(state[:2])


def plot_run(record: dict, path, cfg: AblationConfig = AblationConfig()) -> Path:
    """Fig. 4-like figure of a run simulated with ``keep=True``: initial particles and truth; the true rollout
    with contact events (red); the three variants' final particles coloured by weight (log scale)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm
    from matplotlib.patches import Circle

    if "final" not in record:
        raise ValueError("plot_run needs a record from simulate_run(..., keep=True)")
    size, r = cfg.box_size, cfg.robot_radius
    wp, z = record["waypoints"], record["z"]
    fig, axes = plt.subplots(1, 5, figsize=(20, 4.6), constrained_layout=True)
    cmap, norm = plt.get_cmap("viridis"), LogNorm(vmin=cfg.active_weight, vmax=1.0)
    pink = "#e7298a"

    def frame(ax, title):
        ax.plot(wp[:, 0], wp[:, 1], color="#a6d96a", lw=6, alpha=0.6, solid_capstyle="round", zorder=0)
        ax.set_aspect("equal")
        ax.set_xlim(-0.32, 0.32)
        ax.set_ylim(-0.25, 0.25)
        ax.set_title(title)
        ax.tick_params(labelsize=7)

    ax = axes[0]
    frame(ax, "initial particles and GT")
    for s in record["particles0"]:
        o = _rect(s, size)
        ax.plot(o[:, 0], o[:, 1], color="0.5", lw=0.6, alpha=0.6)
    ax.fill(*_rect(record["truth0"], size).T, color=pink, alpha=0.8)
    ax.add_patch(Circle(wp[0, :2], r, color="#1b7837"))
    ax = axes[1]
    frame(ax, f"GT rollout ({int(z.sum())} contacts observed)")
    tr = record["truth_traj"]
    for i in range(0, len(tr), max(1, len(tr) // 8)):
        o = _rect(tr[i], size)
        ax.plot(o[:, 0], o[:, 1], color=pink, lw=1.0, alpha=0.3 + 0.7 * i / len(tr))
    ax.fill(*_rect(tr[-1], size).T, color=pink, alpha=0.8)
    ax.add_patch(Circle(wp[-1, :2], r, color="#1b7837"))
    ax.scatter(wp[z, 0], wp[z, 1], s=10, color="red", zorder=3, label="contact observed")
    ax.legend(loc="lower left", fontsize=7)
    for ax, (key, label) in zip(axes[2:], VARIANTS.items()):
        st, w = record["final"][key]
        m = record[key]
        frame(ax, f"{label}\nMSE pos {m['mse_pos']:.4f}, yaw {m['mse_yaw']:.3f}, active {m['active_share']:.2f}")
        for i in np.argsort(w):
            o = _rect(st[i], size)
            ax.plot(o[:, 0], o[:, 1], color=cmap(norm(max(w[i], cfg.active_weight))), lw=0.8,
                    alpha=1.0 if w[i] > cfg.active_weight else 0.25)
        o = _rect(tr[-1], size)
        ax.plot(o[:, 0], o[:, 1], color=pink, lw=2.0, ls="--")
        ax.add_patch(Circle(wp[-1, :2], r, color="#1b7837"))
    fig.colorbar(plt.cm.ScalarMappable(norm=norm, cmap=cmap), ax=axes[2:], shrink=0.8, label="particle weight")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def save_summary(result: dict, path) -> Path:
    """``result`` of :func:`run_ablation` without the per-run records, as JSON."""
    path = Path(path)
    path.write_text(json.dumps({k: v for k, v in result.items() if k != "runs"}, indent=2))
    return path
