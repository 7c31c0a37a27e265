"""RUMI trajectory costs: information gain C_I (Eq. 29), reachability C_R (Algorithm 8) and their sum (Eq. 31).

All costs take whole rolled-out state trajectories ``(S, H, 7)`` (``[ee x, y, z, yaw, d_x, d_y, d_z]``, see
planning.dynamics): Eq. 31 is a terminal cost over the whole trajectory (V-F).
"""
from __future__ import annotations

import time

import torch

from activetouch.geometry.voxel import VoxelGrid
from activetouch.information.field import InformationField
from activetouch.planning.dynamics import STATE_DIM, GripperModel

__all__ = ["InformationCost", "ReachabilityCost", "RumiCost", "TimedTrajectoryCost", "resample_to_grid"]


def _check_states(states: torch.Tensor) -> torch.Tensor:
    if states.ndim != 3 or states.shape[-1] != STATE_DIM:
        raise ValueError(f"states must have shape (S, H, {STATE_DIM}), got {tuple(states.shape)}")
    return states


class InformationCost:
    """Eq. 29: ``C_I = - sum_{x in D(U_t [h_I(q_t) - d_t], r_d)} I~(x | X)`` per trajectory.

    ``D`` is the voxel downsampling of section IV-D: cells of side ``r_d`` anchored at the workspace's lower
    corner, each occupied cell counted once, at its centre. ``I~`` at every cell centre is tabulated once per
    field; per call the cells hit by each trajectory are de-duplicated with a dense per-trajectory bitmap over
    the informative cells (``I~ > 0``; the others add exactly 0), then summed with one matrix-vector product.
    States whose ``h_I`` cannot reach an informative cell are skipped (they add exactly 0).

    Args:
        field: the cached information field.
        gripper: ``h_I`` = ``gripper.info_points``.
        r_d: downsampling resolution (m).
        chunk_points: bound on bitmap entries / points processed at once (memory).
    """

    def __init__(self, field: InformationField, gripper: GripperModel, r_d: float, chunk_points: int = 2_000_000):
        if not r_d > 0:
            raise ValueError(f"r_d must be > 0, got {r_d}")
        self.field = field
        device, dtype = field.device, field.info.dtype
        self.h_I = gripper.info_points.to(device=device, dtype=dtype)
        self.r_d = float(r_d)
        self.chunk_points = int(chunk_points)
        grid = field.grid
        self.origin = grid.lower.to(device=device, dtype=dtype)
        span = (grid.upper - grid.lower).to(torch.float64)
        n = torch.ceil(span / self.r_d - 1e-9).clamp_min(1).to(torch.long)
        self.n_cells = tuple(int(v) for v in n)
        self.dgrid = VoxelGrid(grid.lower, grid.lower + n.to(torch.float64) * self.r_d, self.r_d)
        table = field.information(self.dgrid.points(device=device, dtype=dtype)).reshape(self.n_cells)
        informative = table > 0
        self.n_informative = int(informative.sum())
        # compact id of every informative cell, with a one-cell border of "not informative" (= n_informative,
        # a dummy bitmap column) so that out-of-grid points need no separate test: indices are clamped into it
        cid = torch.full([k + 2 for k in self.n_cells], self.n_informative, dtype=torch.long, device=device)
        cid[1:-1, 1:-1, 1:-1][informative] = torch.arange(self.n_informative, device=device)
        self.cell_id = cid.reshape(-1)
        self.values = table[informative]  # (n_inf,)
        self.bounds = None
        if self.n_informative:
            idx = informative.nonzero()
            lo = self.origin + idx.min(0).values.to(dtype) * self.r_d
            hi = self.origin + (idx.max(0).values + 1).to(dtype) * self.r_d
            self.bounds = (lo, hi)

    def __call__(self, states: torch.Tensor) -> torch.Tensor:
        states = _check_states(states)
        S, H, _ = states.shape
        out = torch.zeros(S, device=states.device, dtype=states.dtype)
        if self.n_informative == 0:
            return out
        h = self.h_I
        z = states[..., 2]
        if bool((z == z.reshape(-1)[0]).all()):
            # every rollout at one height (planar actions): points above / below the D grid never count
            hz = h[:, 2] + z.reshape(-1)[0]
            lo_z = float(self.dgrid.lower[2])
            h = h[(hz >= lo_z) & (hz < lo_z + self.n_cells[2] * self.r_d)]
            if h.shape[0] == 0:
                return out
        per_traj = max(H * h.shape[0], self.n_informative)
        step = max(1, self.chunk_points // per_traj)
        for s in range(0, S, step):
            out[s : s + step] = self._chunk(states[s : s + step], h)
        return out

    def _chunk(self, states: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        S, H, _ = states.shape
        q = states[..., :4].reshape(S * H, 4)
        p = q[:, :3] - states[..., 4:].reshape(S * H, 3)  # ee position in the planning-time object frame
        radius = float(h.norm(dim=-1).max())
        lo, hi = self.bounds
        gap = (torch.clamp(lo - p, min=0) + torch.clamp(p - hi, min=0)).norm(dim=-1)
        near = (gap <= radius + self.r_d).nonzero().squeeze(-1)
        hit = torch.zeros(S, self.n_informative + 1, device=q.device, dtype=q.dtype)
        if near.numel():
            # cell coordinates (h_I(q) - d - origin) / r_d + 1 (the +1: border of the id table), written out
            # per component: cheaper than a batched matmul for (states x points) grids on CPU
            qn, pn = q[near], p[near]
            if self.cell_id.numel() >= 2**24:  # float32 holds the linear cell index exactly only below 2^24
                qn, pn, h = qn.double(), pn.double(), h.double()
            c, s = torch.cos(qn[:, 3:4]), torch.sin(qn[:, 3:4])
            hx, hy, hz = (h[:, k] / self.r_d for k in range(3))
            o = (pn - self.origin.to(pn.dtype)) / self.r_d + 1.0
            nx, ny, nz = self.n_cells
            ix = torch.floor(c * hx - s * hy + o[:, 0:1]).clamp_(0, nx + 1)
            iy = torch.floor(s * hx + c * hy + o[:, 1:2]).clamp_(0, ny + 1)
            iz = torch.floor(hz + o[:, 2:3]).clamp_(0, nz + 1)
            lin = ((ix * (ny + 2) + iy) * (nz + 2) + iz).to(torch.long)
            cid = self.cell_id[lin]  # (N', M): informative cell id or the dummy column
            traj = (near // H)[:, None] * (self.n_informative + 1)
            hit.view(-1).index_fill_(0, (traj + cid).reshape(-1), 1.0)  # D(.): each cell once per trajectory
        return -(hit[:, : self.n_informative] @ self.values)


def resample_to_grid(src_grid: VoxelGrid, values: torch.Tensor, dst_grid: VoxelGrid, device=None,
                     dtype=torch.float32) -> torch.Tensor:
    """Values of a field on ``src_grid`` at the cell centres of ``dst_grid`` -> ``dst_grid.shape`` (0 outside)."""
    values = torch.as_tensor(values, device=device, dtype=dtype)
    if tuple(values.shape) != tuple(src_grid.shape):
        raise ValueError(f"values must have shape {src_grid.shape}, got {tuple(values.shape)}")
    same = (src_grid.shape == dst_grid.shape and abs(src_grid.resolution - dst_grid.resolution) < 1e-12
            and bool(torch.allclose(src_grid.lower, dst_grid.lower, atol=1e-9)))
    if same:
        return values
    pts = dst_grid.points(device=values.device, dtype=dtype)
    return src_grid.interpolate(values, pts, outside=0.0).reshape(dst_grid.shape)


class ReachabilityCost:
    """Algorithm 8: ``C_R(d_1..H) = - (sum_x (1/H sum_t I~(x - d_t | X)) r(x)) / sum_x I~(x | X)``.

    The sum over ``x in W`` of ``I~(x - d) r(x)`` is, for every displacement ``d``, a cross-correlation of the
    two workspace grids, ``RI(d) = sum_y I~(y) r(y + d)``. We evaluate it once per field for every
    whole-cell shift with an FFT; because trilinear interpolation of ``I~`` at ``W - d`` uses the same
    weights at every cell, ``sum_x r(x) I~_interp(x - d)`` equals the trilinear interpolation of ``RI`` over
    the shift lattice (up to the field's border clamping at the workspace faces, where ``I~`` is 0). So each
    rollout step costs one trilinear look-up instead of ``|W|`` of them.

    Args:
        field: the cached information field (its grid is ``W``).
        reach: ``r(x)`` values ``(nx, ny, nz)`` on ``field.grid`` (see :func:`resample_to_grid`), in [0, 1].
    """

    def __init__(self, field: InformationField, reach: torch.Tensor):
        grid = field.grid
        reach = torch.as_tensor(reach, device=field.device, dtype=torch.float64)
        if tuple(reach.shape) != tuple(grid.shape):
            raise ValueError(f"reachability must have the workspace grid's shape {grid.shape}, got "
                             f"{tuple(reach.shape)}")
        if not bool(torch.isfinite(reach).all()) or bool((reach < -1e-6).any()) or bool((reach > 1 + 1e-6).any()):
            raise ValueError("reachability values must be finite and in [0, 1]")
        self.field = field
        info = field.info.to(torch.float64)
        self.total = float(info.sum())  # RI_m (line 3)
        n = grid.shape
        size = [2 * k - 1 for k in n]
        fi = torch.fft.rfftn(info, s=size)
        fr = torch.fft.rfftn(reach, s=size)
        corr = torch.fft.irfftn(torch.conj(fi) * fr, s=size)  # corr[s mod N] = sum_y I(y) r(y + s)
        corr = torch.roll(corr, shifts=[k - 1 for k in n], dims=(0, 1, 2)).clamp_min(0.0)
        self.ri = corr.to(field.info.dtype)  # (2nx-1, 2ny-1, 2nz-1), index k <-> shift (k - (n-1)) r_w
        res = grid.resolution
        half = torch.tensor([(k - 1) * res + 0.5 * res for k in n], dtype=torch.float64)
        self.shift_grid = VoxelGrid(-half, half, res)
        if self.shift_grid.shape != tuple(size):  # guard against rounding in VoxelGrid's cell count
            raise RuntimeError(f"shift grid shape {self.shift_grid.shape} != {tuple(size)}")

    def reachable_info(self, d: torch.Tensor) -> torch.Tensor:
        """``RI(d) = sum_x I~(x - d | X) r(x)`` for displacements ``d (..., 3)`` -> ``(...)``."""
        return self.shift_grid.interpolate(self.ri, d, outside=0.0)

    def __call__(self, states: torch.Tensor) -> torch.Tensor:
        states = _check_states(states)
        if self.total <= 0:
            return torch.zeros(states.shape[0], device=states.device, dtype=states.dtype)
        d = states[..., 4:]  # (S, H, 3)
        ri = self.reachable_info(d).mean(dim=1)  # line 1-2 (the mean over t commutes with the sum over x)
        return -ri / self.total  # line 4


class TimedTrajectoryCost:
    """Base of the KMPPI terminal costs: ``cost(states (M, K, H, 7), actions) -> (M, K)`` (pytorch_mppi's
    terminal_state_cost) over :meth:`evaluate` on flat batches ``(S, H, 7) -> (S,)``, accumulating the run time in
    ``elapsed`` (wall) and ``elapsed_cpu`` (process CPU seconds) for the timing tables (RUMI Table VII)."""

    elapsed: float = 0.0
    elapsed_cpu: float = 0.0

    def evaluate(self, states: torch.Tensor) -> torch.Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def __call__(self, states: torch.Tensor, actions: torch.Tensor | None = None) -> torch.Tensor:
        t0, c0 = time.perf_counter(), time.process_time()
        lead = states.shape[:-2]
        c = self.evaluate(states.reshape(-1, *states.shape[-2:])).reshape(lead)
        self.elapsed += time.perf_counter() - t0
        self.elapsed_cpu += time.process_time() - c0
        return c


class RumiCost(TimedTrajectoryCost):
    """Eq. 31: ``C = beta_I C_I + beta_R C_R`` as a KMPPI terminal cost over whole trajectories.

    Callable as ``cost(states (M, K, H, 7), actions) -> (M, K)`` (pytorch_mppi's terminal_state_cost);
    ``evaluate(states (S, H, 7)) -> (S,)`` for flat batches. Accumulates its run time in ``elapsed`` (wall) and
    ``elapsed_cpu`` (process CPU time).
    """

    def __init__(self, info_cost: InformationCost | None, reach_cost: ReachabilityCost | None, beta_I: float,
                 beta_R: float):
        if beta_I > 0 and info_cost is None:
            raise ValueError("beta_I > 0 needs an InformationCost")
        if beta_R > 0 and reach_cost is None:
            raise ValueError("beta_R > 0 needs a ReachabilityCost (give the planner a reachability map)")
        self.info_cost = info_cost
        self.reach_cost = reach_cost
        self.beta_I = float(beta_I)
        self.beta_R = float(beta_R)
        self.elapsed = 0.0
        self.elapsed_cpu = 0.0  # process CPU seconds

    def evaluate(self, states: torch.Tensor) -> torch.Tensor:
        states = _check_states(states)
        c = torch.zeros(states.shape[0], device=states.device, dtype=states.dtype)
        if self.beta_I > 0:
            c = c + self.beta_I * self.info_cost(states)
        if self.beta_R > 0:
            c = c + self.beta_R * self.reach_cost(states)
        return c
