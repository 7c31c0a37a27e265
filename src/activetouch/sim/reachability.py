"""Reachability map r(x) of RUMI Eq. 30 (section IV-H, Fig. 7).

    r(x) = max(0, e_m - 1/|R| sum_{R_i in R} [e_x(x, R_i) + alpha_R e_R(x, R_i)]) / e_m

with e_x / e_R the position / rotation errors of IK with the end effector (the tip of the gripper,
where ``h_I`` gathers information) sent to position x and orientation R_i, over a fixed set R of
gripper-down orientations at several yaws. Defaults: e_m = 0.4, alpha_R = 0.1 (Table IV).

IK is pytorch_kinematics' batched ``PseudoInverseIK`` on the iiwa URDF (all goals at once, several
random restarts, best restart kept). The map is computed once per robot + gripper + workspace and
cached in ``platformdirs.user_cache_dir("activetouch")`` (or ``$ACTIVETOUCH_CACHE_DIR``).
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import os
import pathlib

import numpy as np
import torch

from .robot import ASSET_DIR, BASE_POS, FLANGE_OFFSET, GRIPPER

__all__ = ["ReachabilityConfig", "reachability_map", "compute_reachability", "cache_dir", "plot_reachability"]
log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class ReachabilityConfig:
    """Parameters of Eq. 30 and of the IK used to evaluate it."""

    e_m: float = 0.4  # IK error threshold (Table IV)
    alpha_R: float = 0.1  # rotation error scale (Table IV)
    yaws: tuple[float, ...] = tuple(i * math.pi / 4 for i in range(-4, 4))  # goal orientations: gripper down
    resolution: float = 0.04  # grid of the map (interpolated trilinearly in between)
    num_retries: int = 8
    max_iterations: int = 30
    seed: int = 0


def cache_dir() -> pathlib.Path:
    """``$ACTIVETOUCH_CACHE_DIR`` or ``platformdirs.user_cache_dir("activetouch")``."""
    env = os.environ.get("ACTIVETOUCH_CACHE_DIR")
    if env:
        return pathlib.Path(env)
    import platformdirs

    return pathlib.Path(platformdirs.user_cache_dir("activetouch"))


def _chain():
    import pytorch_kinematics as pk

    return pk.build_serial_chain_from_urdf((ASSET_DIR / "model.urdf").read_text(), "lbr_iiwa_link_7")


def _ee_in_link7() -> torch.Tensor:
    """Pose of the ee frame in the link-7 frame ``(4, 4)``: along link-7 z, rotated pi about x."""
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = torch.tensor([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]], dtype=torch.float64)
    T[2, 3] = FLANGE_OFFSET + GRIPPER.length
    return T


def compute_reachability(points: torch.Tensor, config: ReachabilityConfig = ReachabilityConfig()) -> torch.Tensor:
    """r(x) of Eq. 30 for world points ``(N, 3)`` -> ``(N,)`` in [0, 1]."""
    import pytorch_kinematics as pk

    pts = torch.as_tensor(points, dtype=torch.float64).reshape(-1, 3)
    if not torch.isfinite(pts).all():
        raise ValueError("reachability points must be finite")
    chain = _chain().to(dtype=torch.float64)
    lim = torch.as_tensor(chain.get_joint_limits(), dtype=torch.float64).T  # (7, 2)
    T_l7_ee_inv = torch.linalg.inv(_ee_in_link7())
    base = torch.tensor(BASE_POS, dtype=torch.float64)
    errs = torch.zeros(len(pts), dtype=torch.float64)
    g = torch.Generator().manual_seed(config.seed)
    retry = lim[:, 0] + (lim[:, 1] - lim[:, 0]) * torch.rand(config.num_retries, 7, generator=g, dtype=torch.float64)
    retry[0] = torch.tensor([0.0, 0.6, 0.0, -1.5, 0.0, 1.05, 0.0], dtype=torch.float64)  # the sim's nominal posture
    for yaw in config.yaws:
        c, s = math.cos(yaw), math.sin(yaw)
        goal_ee = torch.eye(4, dtype=torch.float64).repeat(len(pts), 1, 1)
        goal_ee[:, :3, :3] = torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1.0]], dtype=torch.float64)
        goal_ee[:, :3, 3] = pts - base
        goal_l7 = goal_ee @ T_l7_ee_inv
        ik = pk.PseudoInverseIK(chain, retry_configs=retry, joint_limits=lim.T if lim.shape[0] == 2 else lim,
                                max_iterations=config.max_iterations, early_stopping_any_converged=True,
                                early_stopping_no_improvement=None, lr=0.5, pos_tolerance=1e-3, rot_tolerance=1e-2)
        sol = ik.solve(pk.Transform3d(matrix=goal_l7, dtype=torch.float64))
        e = sol.err_pos + config.alpha_R * sol.err_rot  # (N, retries)
        errs += e.min(dim=1).values
    errs /= len(config.yaws)
    return (config.e_m - errs).clamp_min(0.0) / config.e_m


def _key(lower, upper, planar: bool, config: ReachabilityConfig) -> str:
    h = hashlib.sha256()
    h.update((ASSET_DIR / "model.urdf").read_bytes())
    h.update(json.dumps({"base": BASE_POS, "flange": FLANGE_OFFSET, "gripper": {"length": GRIPPER.length},  # r(x) only sees the tip offset
                         "lower": [round(float(v), 6) for v in lower], "upper": [round(float(v), 6) for v in upper],
                         "planar": planar, "cfg": dataclasses.asdict(config), "v": 1}, sort_keys=True).encode())
    return h.hexdigest()[:20]


def _shipped_map(name: str) -> pathlib.Path | None:
    """A reachability map shipped in ``activetouch/assets/reachability`` (regenerate: delete the file and the
    cache entry, call :func:`reachability_map`, copy the cache file back)."""
    from importlib.resources import files

    p = pathlib.Path(str(files("activetouch") / "assets" / "reachability" / name))
    return p if p.is_file() else None


def reachability_map(lower, upper, planar: bool = False, config: ReachabilityConfig = ReachabilityConfig()):
    """Reachability over the workspace box ``[lower, upper]`` (each ``(3,)``), cached on disk.

    Planar workspaces (``planar=True``) get one layer of cells at the mid height of ``[lower, upper]``.

    Returns:
        ``(VoxelGrid, values (nx, ny, nz) float32)``; interpolate with ``grid.interpolate(values, x)``.
    """
    from activetouch.geometry.voxel import VoxelGrid

    lo = np.asarray(lower, dtype=float).reshape(3).copy()
    up = np.asarray(upper, dtype=float).reshape(3).copy()
    if not (np.isfinite(lo).all() and np.isfinite(up).all() and (up >= lo).all()):
        raise ValueError(f"bad workspace bounds lower={lo.tolist()} upper={up.tolist()}")
    res = config.resolution
    if planar:
        zc = 0.5 * (lo[2] + up[2])
        lo[2], up[2] = zc - res / 2, zc + res / 2
    grid = VoxelGrid(lo, up, res)
    name = f"reachability-{_key(lo, up, planar, config)}.pt"
    path = cache_dir() / name
    shipped = _shipped_map(name)
    if shipped is not None and not path.is_file():
        path = shipped  # precomputed for the packaged tasks (same key: same robot, workspace and config)
    if path.is_file():
        try:
            vals = torch.load(path, weights_only=True)
            if tuple(vals.shape) == grid.shape:
                return grid, vals
        except Exception as e:  # noqa: BLE001 - a corrupt cache is recomputed
            log.warning("ignoring unreadable reachability cache %s: %s", path, e)
    log.info("computing the reachability map (%d cells x %d orientations); cached at %s", grid.num_cells,
             len(config.yaws), path)
    vals = compute_reachability(grid.points(dtype=torch.float64), config).reshape(grid.shape).to(torch.float32)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".tmp{os.getpid()}")
    torch.save(vals, tmp)
    os.replace(tmp, path)
    return grid, vals


def plot_reachability(grid, values, path, z: float | None = None, title: str = "reachability r(x)") -> pathlib.Path:
    """Save a Fig. 7-style top view of the map at height ``z`` (default: lowest layer) to ``path``.

    Red is r = 0, dark blue r = 1; the robot base and the workspace outline are drawn.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    vals = torch.as_tensor(values)
    xs, ys, zs = grid.axes(dtype=torch.float64)
    k = 0 if z is None else int(torch.argmin((zs - z).abs()))
    fig, ax = plt.subplots(figsize=(5.5, 5))
    im = ax.imshow(vals[:, :, k].T.numpy(), origin="lower", cmap="RdYlBu", vmin=0, vmax=1,
                   extent=[float(grid.lower[0]), float(grid.upper[0]), float(grid.lower[1]), float(grid.upper[1])])
    ax.plot([BASE_POS[0]], [BASE_POS[1]], "ks", ms=10, label="robot base")
    ax.set_xlim(min(BASE_POS[0] - 0.1, float(grid.lower[0])), float(grid.upper[0]) + 0.02)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"{title}, z = {float(zs[k]):.2f} m")
    ax.legend(loc="upper right")
    fig.colorbar(im, ax=ax, label="r(x)")
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path
