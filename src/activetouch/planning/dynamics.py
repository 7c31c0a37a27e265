"""RUMI's stochastic robot + object displacement dynamics f^ (Algorithm 7, section IV-G).

State (``nx = 7``): ``[ee_x, ee_y, ee_z, ee_yaw, d_x, d_y, d_z]`` - the end-effector state of the
interfaces contract and the predicted object displacement ``d`` (world frame) accumulated since planning.
Free-space dynamics ``f_f``: ``ee' = clip(ee + scale * u)`` (80 mm / 0.5 rad per unit control, positions
clipped to the workspace). Planar action space: ``u = [dx, dy, dyaw]`` (z fixed); 3D: ``[dx, dy, dz, dyaw]``.

One step of Algorithm 7 per mini step (each action is split into ``mini_steps`` equal parts, V-F):

1. ``q' = f_f(q_t, u)``; ``R~ = h(q') - d_t`` (robot points in the planning-time object frame);
2. ``i = argmin_x p(S_x = free | X)`` over ``R~``; sample ``s ~ p(S_{x_i} | X)``;
3. free: ``q_{t+1} = q'``, ``d_{t+1} = d_t``;
4. otherwise ``d' = h(q')[i] - h(q_t)[i]`` (the displacement of that robot point; the pseudo-code's
   ``x_i - R_b[i]`` mixes the displaced and undisplaced frames, the text says "the change in position from
   where x_i was before the action"), ``n^ = sum_j w_j grad sdf(T_j^-1 x_i)`` rotated to the world; if the
   angle between ``n^`` and ``-d'`` is below ``theta_p`` the contact pushes (``q' `` and ``d_t + d'``),
   otherwise the robot is held at ``q_t`` and nothing moves.

Only "free vs not free" matters in step 3-4, so sampling ``s`` is a Bernoulli draw with ``p(free)``:
contact iff ``r >= min_x p(free)`` for ``r ~ U[0, 1)``. Rollouts whose gripper is farther than its radius
from the particles' neighbourhood (where the field is exactly free, see information.field) skip the look-ups:
their contact probability is below ``negligible``.

Speed (exact, no change of semantics): ``r`` is drawn first and ``p(free)`` is bounded from below by min
filters of the grid (trilinear interpolation is a convex combination of its 8 corner cells), per rollout over
the gripper's whole extent and per point over its 8 corners. Only points whose bound is ``<= r`` are
interpolated; the others provably can be neither a contact nor the argmin of line 3, so the outcome is the
one of interpolating every point (``StochasticDynamics.screen = False``, compared bit for bit in the tests).
On the 3-D box / drill tasks this leaves ~20 % of the rollouts and ~1 % of the (rollout, point) pairs to
interpolate (3.6 s -> 0.33 s CPU per planning call).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import torch

from activetouch.information.field import InformationField

__all__ = ["GripperModel", "StochasticDynamics", "STATE_DIM", "action_indices"]

STATE_DIM = 7


def action_indices(action_space: str) -> list[int]:
    """State indices (of ``[x, y, z, yaw]``) driven by each control dimension."""
    if action_space == "planar":
        return [0, 1, 3]
    if action_space == "3d":
        return [0, 1, 2, 3]
    raise ValueError(f"action_space must be 'planar' or '3d', got {action_space!r}")


@dataclass
class GripperModel:
    """Robot interior points ``h`` (and the information-gathering subset ``h_I``, section IV-F).

    Args:
        points: ``(M, 3)`` points in the end-effector frame ``pose_from_xyz_yaw(ee[:3], ee[3])``.
        info_mask: ``(M,)`` bool, True for the points of ``h_I``.
    """

    points: torch.Tensor
    info_mask: torch.Tensor

    def __post_init__(self):
        pts = torch.as_tensor(self.points, dtype=torch.get_default_dtype())
        mask = torch.as_tensor(self.info_mask, dtype=torch.bool, device=pts.device)
        if pts.ndim != 2 or pts.shape[-1] != 3 or pts.shape[0] == 0:
            raise ValueError(f"gripper points must have shape (M, 3) with M > 0, got {tuple(pts.shape)}")
        if not bool(torch.isfinite(pts).all()):
            raise ValueError("gripper points contain NaN or inf entries")
        if mask.shape != (pts.shape[0],):
            raise ValueError(f"info_mask must have shape ({pts.shape[0]},), got {tuple(mask.shape)}")
        if not bool(mask.any()):
            raise ValueError("info_mask selects no point: h_I must not be empty")
        self.points = pts
        self.info_mask = mask
        self.radius = float(pts.norm(dim=-1).max())

    def to(self, device=None, dtype=None) -> "GripperModel":
        return GripperModel(self.points.to(device=device, dtype=dtype), self.info_mask.to(device=device))

    @property
    def info_points(self) -> torch.Tensor:
        """``(M_I, 3)`` the ``h_I`` points in the end-effector frame."""
        return self.points[self.info_mask]

    @staticmethod
    def transform(points: torch.Tensor, ee: torch.Tensor) -> torch.Tensor:
        """Points ``(M, 3)`` (ee frame) at end-effector states ``ee (..., 4)`` -> world ``(..., M, 3)``."""
        c, s = torch.cos(ee[..., 3]), torch.sin(ee[..., 3])
        px, py, pz = points[:, 0], points[:, 1], points[:, 2]
        x = c[..., None] * px - s[..., None] * py + ee[..., 0:1]
        y = s[..., None] * px + c[..., None] * py + ee[..., 1:2]
        z = pz + ee[..., 2:3]
        return torch.stack([x, y, z], dim=-1)

    def world(self, ee: torch.Tensor) -> torch.Tensor:
        """``h(q)``: all points at ``ee (..., 4)`` -> ``(..., M, 3)``."""
        return self.transform(self.points, ee)

    def world_info(self, ee: torch.Tensor) -> torch.Tensor:
        """``h_I(q)`` at ``ee (..., 4)`` -> ``(..., M_I, 3)``."""
        return self.transform(self.info_points, ee)


def _box_distance(x: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    """Euclidean distance of points ``x (B, 3)`` to the box ``[lo, hi]`` (0 inside) -> ``(B,)``."""
    return (torch.clamp(lo - x, min=0) + torch.clamp(x - hi, min=0)).norm(dim=-1)


class StochasticDynamics:
    """Algorithm 7 (f^) with ``mini_steps`` sub-steps per action; callable ``(state (B, 7), u (B, Nu)) -> (B, 7)``.

    Args:
        field: cached :class:`InformationField` (``p(S|X)`` and the weighted normals ``n^``).
        gripper: :class:`GripperModel` (``h``: all its points are used, section IV-F).
        action_space: ``"planar"`` or ``"3d"``.
        ws_lower, ws_upper: ``(3,)`` box the end-effector position is clipped to, or ``(4,)`` bounds of
            ``[x, y, z, yaw]`` (the sim's ``TaskSpec.ee_lower / ee_upper``). Only controlled axes are clipped.
        translation_scale, rotation_scale: metres / radians per unit control (80 mm, 0.5 rad).
        theta_p: pushing angle threshold (rad, Table IV 45 deg).
        mini_steps: sub-steps per action (V-F: 4).
        generator: ``torch.Generator`` on the field's device for the contact samples.
        negligible: contact probability below which a rollout far from the particles is taken as free.

    ``screen`` (class attribute, default True): exact lazy evaluation of Alg. 7 lines 2-5 with lower bounds of
    ``p(free)`` (:class:`_FreeBounds`); False looks up every robot point (same result, for tests / benchmarks).
    """

    screen = True

    def __init__(self, field: InformationField, gripper: GripperModel, action_space: str, ws_lower, ws_upper, *,
                 translation_scale: float = 0.08, rotation_scale: float = 0.5, theta_p: float = math.radians(45),
                 mini_steps: int = 4, generator: torch.Generator | None = None, negligible: float = 1e-4):
        self.field = field
        device, dtype = field.device, field.info.dtype
        self.gripper = gripper.to(device=device, dtype=dtype)
        self.idx = action_indices(action_space)
        self.nu = len(self.idx)
        scale = [rotation_scale if i == 3 else translation_scale for i in self.idx]
        self.scale = torch.tensor(scale, device=device, dtype=dtype)
        lo = torch.as_tensor(ws_lower, device=device, dtype=dtype).reshape(-1)
        up = torch.as_tensor(ws_upper, device=device, dtype=dtype).reshape(-1)
        if lo.shape != up.shape or lo.shape[0] not in (3, 4):
            raise ValueError(f"ws_lower/ws_upper must both have shape (3,) or (4,), got {tuple(lo.shape)}, "
                             f"{tuple(up.shape)}")
        if lo.shape[0] == 3:
            lo = torch.cat([lo, lo.new_tensor([-math.inf])])
            up = torch.cat([up, up.new_tensor([math.inf])])
        self.ws_lower, self.ws_upper = lo, up
        # only the controlled axes are clipped (planar: z stays at the fixed ee height)
        self._clip_lo, self._clip_hi = lo[self.idx], up[self.idx]
        self.cos_theta_p = math.cos(theta_p)
        if mini_steps < 1:
            raise ValueError(f"mini_steps must be >= 1, got {mini_steps}")
        self.mini_steps = int(mini_steps)
        self.generator = generator
        self.negligible = negligible
        # Box where p(free) may differ from 1: the particles' neighbourhood, grown by one cell on multi-cell
        # axes for the trilinear blending (single-cell axes, e.g. the z slab of planar tasks, are exact).
        grid = field.grid
        grow = torch.tensor([grid.resolution if k > 1 else 0.0 for k in grid.shape], device=device, dtype=dtype)
        self._box_lo = field.active_lower.to(device=device, dtype=dtype) - grow
        self._box_hi = field.active_upper.to(device=device, dtype=dtype) + grow
        self.elapsed = 0.0  # accumulated seconds spent in __call__
        self.elapsed_cpu = 0.0  # accumulated process CPU seconds spent in __call__
        self.contacts = 0  # number of sampled contacts (diagnostics)
        self._bounds = _FreeBounds(field, self.gripper.points)

    def _points_for(self, state: torch.Tensor) -> tuple[torch.Tensor, bool]:
        """Robot points that can ever be in the box (exact pruning, planar action spaces) and whether they all
        lie in a single-layer grid's z range.

        With z uncontrolled and yaw about z, a point's world height is ``ee_z + h_z`` for every rollout;
        points above or below the box always read ``p(free) = 1`` and never change the argmin of Alg. 7 line 3.
        """
        pts = self.gripper.points
        if 2 in self.idx:
            return pts, False
        z = state[:, 2]
        if not bool((z == z[0]).all()):
            return pts, False
        hz = pts[:, 2] + z[0]
        keep = (hz >= self._box_lo[2]) & (hz <= self._box_hi[2])
        # single-layer grid: the kept points all lie in the layer, x-y look-ups suffice
        return pts[keep], self.field.grid.shape[2] == 1

    def free_space(self, ee: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """``f_f``: ``clip(ee + scale * u)`` for ``ee (B, 4)``, ``u (B, Nu)`` -> ``(B, 4)``."""
        out = ee.clone()
        out[:, self.idx] = torch.clamp(out[:, self.idx] + u * self.scale, self._clip_lo, self._clip_hi)
        return out

    def __call__(self, state: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        t0, c0 = time.perf_counter(), time.process_time()
        if state.ndim != 2 or state.shape[-1] != STATE_DIM:
            raise ValueError(f"state must have shape (B, {STATE_DIM}), got {tuple(state.shape)}")
        if u.shape != (state.shape[0], self.nu):
            raise ValueError(f"u must have shape ({state.shape[0]}, {self.nu}), got {tuple(u.shape)}")
        q = state[:, :4].clone()
        d = state[:, 4:].clone()
        du = u / self.mini_steps
        pts, planar_layer = self._points_for(state)
        for _ in range(self.mini_steps):
            q, d = self._mini_step(q, d, du, pts, planar_layer)
        self.elapsed += time.perf_counter() - t0
        self.elapsed_cpu += time.process_time() - c0
        return torch.cat([q, d], dim=-1)

    def _mini_step(self, q: torch.Tensor, d: torch.Tensor, u: torch.Tensor, pts: torch.Tensor,
                   planar_layer: bool = False):
        """One step of Algorithm 7 for ``q (B, 4)``, ``d (B, 3)``, ``u (B, Nu)`` using robot points ``pts (M, 3)``.

        Lines 2-5 are evaluated lazily but exactly (see :class:`_FreeBounds`): the contact sample ``r`` is drawn
        first, then rollouts / points whose ``p(free)`` lower bound exceeds ``r`` are dropped before any
        trilinear look-up. The outcome (contact or not, the argmin point ``i``) is identical to evaluating
        ``p(free)`` at every point (``screen = False``; checked in the tests).
        """
        q_new = self.free_space(q, u)  # line 1
        if pts.shape[0] == 0:
            return q_new, d
        radius = float(pts.norm(dim=-1).max())
        near = _box_distance(q_new[:, :3] - d, self._box_lo, self._box_hi) <= radius
        ids = near.nonzero().squeeze(-1)
        A = ids.numel()
        if A == 0:
            return q_new, d
        # line 4-5: s != free with probability 1 - p(free), i.e. contact iff r >= min_x p(free); r is drawn for
        # every near rollout first (same stream as evaluating p first)
        r = torch.rand(A, generator=self.generator, device=q.device, dtype=q.dtype)
        qn = q_new[ids]
        pos = qn[:, :3] - d[ids]  # ee position in the planning-time object frame (A, 3)
        bounds = self._bounds
        sub = None
        if self.screen:
            # level 1: one look-up per rollout bounds p(free) of every gripper point from below
            cand = r >= bounds.rollout_lower_bound(pos) - bounds.tol
            sub = cand.nonzero().squeeze(-1)
            if sub.numel() == 0:
                return q_new, d
            if sub.numel() == A:
                sub = None
        qs, ps, rs = (qn, pos, r) if sub is None else (qn[sub], pos[sub], r[sub])
        # line 2: robot points h(q') - d_t in grid index coordinates (A', M)
        tx, ty, tz = bounds.index_coords(pts, qs[:, 3], ps)
        if self.screen:
            # level 2: per point, the min of p(free) over its trilinear corners; only points that could
            # sample "not free" are looked up exactly (the others can be neither the contact nor the argmin)
            keep = bounds.point_lower_bound(tx, ty, tz) <= rs[:, None] + bounds.tol
            flat = keep.view(-1).nonzero().squeeze(-1)  # one nonzero, then index_select (cheaper than masks)
            if flat.numel() == 0:
                return q_new, d
            exact = bounds.exact(tx.view(-1).index_select(0, flat), ty.view(-1).index_select(0, flat),
                                 tz.view(-1).index_select(0, flat), planar_layer)
            p_free = torch.full_like(tx, 2.0)  # never the argmin and never <= r
            p_free.view(-1).index_copy_(0, flat, exact)
        else:
            p_free = bounds.exact(tx, ty, tz, planar_layer)
        pmin, i = p_free.min(dim=1)  # line 3
        contact = rs >= pmin
        if not bool(contact.any()):
            return q_new, d
        # back to the near rollouts (A,)
        if sub is not None:
            hit = sub[contact]
            i_all = torch.zeros(A, dtype=torch.long, device=q.device)
            i_all[hit] = i[contact]
            c_all = torch.zeros(A, dtype=torch.bool, device=q.device)
            c_all[hit] = True
            contact, i = c_all, i_all
        ids = ids[contact]
        i = i[contact]
        self.contacts += int(ids.numel())
        qn, qo, dn = q_new[ids], q[ids], d[ids]
        h_i = pts[i]  # (C, 3) the chosen point in the ee frame
        before = _transform_rows(h_i, qo)  # line 9-10: h(q_t)[i]
        after = _transform_rows(h_i, qn)  # h(q')[i]
        x_i = after - dn  # the contact candidate in the planning-time object frame
        d_prime = after - before
        n = self.field.normal(x_i)  # line 11
        dn_norm = n.norm(dim=-1) * d_prime.norm(dim=-1)
        cos = (n * -d_prime).sum(-1) / dn_norm.clamp_min(1e-12)
        push = (dn_norm > 1e-12) & (cos > self.cos_theta_p)  # line 12
        dn = dn + torch.where(push[:, None], d_prime, torch.zeros_like(d_prime))  # line 14
        qn = torch.where(push[:, None], qn, qo)  # line 16: not pushing -> held at q_t
        q_new = q_new.index_copy(0, ids, qn)
        d = d.index_copy(0, ids, dn)
        return q_new, d


class _FreeBounds:
    """Exact lazy evaluation of ``min_x p(S_x = free | X)`` for Algorithm 7 (lines 2-5).

    Why: the dynamics need, per rollout and mini step, only whether a uniform sample ``r`` is ``>= min_x p(free)``
    over the robot points and, if so, the argmin. Most rollouts are far from the object, where ``p(free)`` is
    close to 1, so ``r`` is below every point's ``p(free)`` and no look-up is needed. Trilinear interpolation
    is a convex combination of the 8 surrounding cell values, so it is bounded below by their minimum:

    * ``rollout_lower_bound``: min of ``p(free)`` over every cell any gripper point of a rollout can touch
      (a min filter of the grid over the gripper's extent, looked up at the ee cell) -> ``(A,)``;
    * ``point_lower_bound``: min over a point's 2 x 2 x 2 trilinear corners (a 2-cell min filter looked up at
      the point's floor cell) -> ``(A, M)``.

    A rollout / point is skipped only when ``r < bound - tol``; ``tol`` (1e-4) covers the float32 rounding of
    grid_sample's weights and of the two coordinate computations (< 1e-5), so the skipped points' exact values
    are provably ``> r``: they can be neither a contact nor the argmin, and the result equals the full
    evaluation. Points outside the covered box read exactly 1 (>= any bound).

    Args:
        field: the cached field (``p(free)`` offsets and grid).
        gripper_points: ``(M, 3)`` all robot points (ee frame), for the rollout filter's extent.
    """

    tol = 1e-4

    def __init__(self, field: InformationField, gripper_points: torch.Tensor):
        grid = field.grid
        self.field = field
        device, dtype = field.device, field.info.dtype
        self.res = grid.resolution
        self.shape = grid.shape
        n = torch.tensor(grid.shape, dtype=torch.float64)
        self.c0 = (grid.lower + 0.5 * self.res).to(device=device, dtype=dtype)  # centre of cell (0, 0, 0)
        self.n_max = (n - 1).to(device=device, dtype=dtype)
        # index -> normalised grid_sample coordinates (align_corners=True; single-cell axes: -1/+1 at the faces)
        self.g_scale = torch.where(n > 1, 2.0 / (n - 1).clamp_min(1), torch.full_like(n, 2.0)).to(
            device=device, dtype=dtype)
        self.g_offset = torch.where(n > 1, -torch.ones_like(n), torch.zeros_like(n)).to(device=device, dtype=dtype)
        self.strides = (float(grid.shape[1] * grid.shape[2]), float(grid.shape[2]))
        p_free = field._free_offset + 1.0  # (nx, ny, nz)
        self.corner_min = _window_min(p_free, [(0, 1)] * 3).reshape(-1)
        h = gripper_points.to(torch.float64) / self.res
        a = int(math.ceil(float(h[:, :2].norm(dim=-1).max()) + 1e-6)) + 1  # +1: margin for rounding
        zlo = int(math.floor(float(h[:, 2].min()) - 1e-6)) - 1
        zhi = int(math.ceil(float(h[:, 2].max()) + 1e-6)) + 2
        self.gripper_min = _window_min(p_free, [(-a, a + 1), (-a, a + 1), (zlo, zhi)]).reshape(-1)

    def _linear(self, fx: torch.Tensor, fy: torch.Tensor, fz: torch.Tensor) -> torch.Tensor:
        """Linear cell index of floor cells (floats, clamped in place) -> long."""
        fx = fx.clamp_(0, float(self.n_max[0]))
        fy = fy.clamp_(0, float(self.n_max[1]))
        fz = fz.clamp_(0, float(self.n_max[2]))
        return (fx.mul_(self.strides[0]).add_(fy.mul_(self.strides[1])).add_(fz)).long()

    def rollout_lower_bound(self, pos: torch.Tensor) -> torch.Tensor:
        """Lower bound of ``p(free)`` at every gripper point of ee positions ``pos (A, 3)`` -> ``(A,)``."""
        t = torch.floor((pos - self.c0) / self.res)
        return self.gripper_min[self._linear(t[:, 0], t[:, 1], t[:, 2])]

    def index_coords(self, pts: torch.Tensor, yaw: torch.Tensor, pos: torch.Tensor):
        """Continuous grid indices of ``pts (M, 3)`` at yaws ``(A,)`` and positions ``(A, 3)`` -> 3 x ``(A, M)``."""
        inv = 1.0 / self.res
        b = (pos - self.c0) * inv  # (A, 3)
        c, s = torch.cos(yaw)[:, None], torch.sin(yaw)[:, None]
        hx, hy = pts[:, 0] * inv, pts[:, 1] * inv
        tx = torch.addcmul(b[:, 0:1], c, hx).sub_(s * hy)
        ty = torch.addcmul(b[:, 1:2], s, hx).add_(c * hy)
        tz = b[:, 2:3] + pts[:, 2] * inv
        return tx, ty, tz

    def point_lower_bound(self, tx: torch.Tensor, ty: torch.Tensor, tz: torch.Tensor) -> torch.Tensor:
        """Min of ``p(free)`` over the trilinear corners of points at indices ``(A, M)`` each -> ``(A, M)``."""
        return self.corner_min[self._linear(tx.floor(), ty.floor(), tz.floor())]

    def exact(self, tx: torch.Tensor, ty: torch.Tensor, tz: torch.Tensor, planar_layer: bool) -> torch.Tensor:
        """Trilinear ``p(free)`` (:meth:`InformationField.sample_free`) at grid indices of equal shape -> same shape."""
        gs, go = self.g_scale, self.g_offset
        if planar_layer:  # single z layer and every point in it: 2-D look-up
            return self.field.sample_free(torch.stack([tx * gs[0] + go[0], ty * gs[1] + go[1]], dim=-1))
        return self.field.sample_free(torch.stack([tx * gs[0] + go[0], ty * gs[1] + go[1], tz * gs[2] + go[2]],
                                                  dim=-1))


def _window_min(values: torch.Tensor, windows) -> torch.Tensor:
    """``out[c] = min values[clamp(c + lo .. c + hi)]`` per axis (separable box min filter, border clamped).

    ``values (nx, ny, nz)``; ``windows``: one ``(lo, hi)`` integer offset pair per axis -> ``(nx, ny, nz)``.
    """
    out = values
    for axis, (lo, hi) in enumerate(windows):
        n = out.shape[axis]
        idx = (torch.arange(n, device=out.device)[:, None] + torch.arange(lo, hi + 1, device=out.device)[None])
        idx = idx.clamp_(0, n - 1)
        moved = out.movedim(axis, 0)
        out = moved[idx.reshape(-1)].reshape(n, idx.shape[1], *moved.shape[1:]).amin(dim=1).movedim(0, axis)
    return out.contiguous()


def _transform_rows(p: torch.Tensor, ee: torch.Tensor) -> torch.Tensor:
    """One ee-frame point per row: ``p (B, 3)`` at ``ee (B, 4)`` -> world ``(B, 3)``."""
    c, s = torch.cos(ee[:, 3]), torch.sin(ee[:, 3])
    return torch.stack(
        [c * p[:, 0] - s * p[:, 1] + ee[:, 0], s * p[:, 0] + c * p[:, 1] + ee[:, 1], p[:, 2] + ee[:, 2]], dim=-1
    )
