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

Only "free vs not free" matters in step 3-4, so sampling ``s`` is a Bernoulli draw with ``p(free)``.
Rollouts whose gripper is farther than its radius from the particles' neighbourhood (where the field is
exactly free, see information.field) skip the look-ups: their contact probability is below ``negligible``.
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
    """

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
        self._ws_box = (grid.lower.to(device=device, dtype=dtype), grid.upper.to(device=device, dtype=dtype))
        self.elapsed = 0.0  # accumulated seconds spent in __call__
        self.contacts = 0  # number of sampled contacts (diagnostics)
        self.cull_fraction = 0.6  # 3-D look-ups: mask out-of-box points when fewer than this share are in it

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
        t0 = time.perf_counter()
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
        return torch.cat([q, d], dim=-1)

    def _mini_step(self, q: torch.Tensor, d: torch.Tensor, u: torch.Tensor, pts: torch.Tensor,
                   planar_layer: bool = False):
        """One step of Algorithm 7 for ``q (B, 4)``, ``d (B, 3)``, ``u (B, Nu)`` using robot points ``pts (M, 3)``."""
        q_new = self.free_space(q, u)  # line 1
        if pts.shape[0] == 0:
            return q_new, d
        radius = float(pts.norm(dim=-1).max())
        near = _box_distance(q_new[:, :3] - d, self._box_lo, self._box_hi) <= radius
        ids = near.nonzero().squeeze(-1)
        if ids.numel() == 0:
            return q_new, d
        qn, qo, dn = q_new[ids], q[ids], d[ids]
        A = ids.numel()
        # line 2-3 fused: normalised grid coordinates of h(q') - d_t straight from the ee-frame points, then one
        # grid_sample; this loop dominates the planner's run time.
        sc, off = self.field.coord_scale, self.field.coord_offset
        c, s = torch.cos(qn[:, 3:4]), torch.sin(qn[:, 3:4])
        b = (qn[:, :3] - dn) * sc + off  # (A, 3)
        hx, hy = pts[:, 0], pts[:, 1]
        gx = (c * hx - s * hy) * sc[0] + b[:, 0:1]
        gy = (s * hx + c * hy) * sc[1] + b[:, 1:2]
        if planar_layer:  # single z layer and every point in it: 2-D look-up
            p_free = self.field.sample_free(torch.stack([gx, gy], dim=-1))  # (A, M)
        else:
            gz = pts[:, 2] * sc[2] + b[:, 2:3]
            # every point of every near rollout inside the workspace box? then skip the per-point outside test
            pos = qn[:, :3] - dn
            rxy = float(pts[:, :2].norm(dim=-1).max())
            lo, up = self._ws_box
            inside_known = bool(((pos[:, :2] - rxy >= lo[:2]).all() & (pos[:, :2] + rxy <= up[:2]).all()
                                 & (pos[:, 2] + pts[:, 2].min() >= lo[2]).all()
                                 & (pos[:, 2] + pts[:, 2].max() <= up[2]).all()))
            # exact culling: points above / below the particles' neighbourhood read p(free) = 1; count them per
            # rollout from the sorted point heights first (cheap) and mask only when enough points drop out
            hz = pts[:, 2].sort().values
            n_in = (torch.searchsorted(hz, self._box_hi[2] - pos[:, 2], right=True)
                    - torch.searchsorted(hz, self._box_lo[2] - pos[:, 2]))
            if float(n_in.sum()) > self.cull_fraction * gz.numel():
                p_free = self.field.sample_free(torch.stack([gx, gy, gz], dim=-1), inside_known)  # (A, M)
            else:
                zlo, zhi = self._box_lo[2] * sc[2] + off[2], self._box_hi[2] * sc[2] + off[2]
                keep = (gz >= zlo) & (gz <= zhi)
                p_free = torch.ones_like(gz)
                g = torch.stack([gx[keep], gy[keep], gz[keep]], dim=-1)
                if g.shape[0]:
                    p_free[keep] = self.field.sample_free(g, inside_known)
        pmin, i = p_free.min(dim=1)  # line 3
        r = torch.rand(A, generator=self.generator, device=q.device, dtype=q.dtype)
        contact = r >= pmin  # line 4-5: s != free with probability 1 - p(free)
        if not bool(contact.any()):
            return q_new, d
        self.contacts += int(contact.sum())
        h_i = pts[i]  # (A, 3) the chosen point in the ee frame
        before = _transform_rows(h_i, qo)  # line 9-10: h(q_t)[i]
        after = _transform_rows(h_i, qn)  # h(q')[i]
        x_i = after - dn  # the contact candidate in the planning-time object frame
        d_prime = after - before
        n = self.field.normal(x_i)  # line 11
        dn_norm = n.norm(dim=-1) * d_prime.norm(dim=-1)
        cos = (n * -d_prime).sum(-1) / dn_norm.clamp_min(1e-12)
        push = contact & (dn_norm > 1e-12) & (cos > self.cos_theta_p)  # line 12
        hold = contact & ~push
        dn = dn + torch.where(push[:, None], d_prime, torch.zeros_like(d_prime))  # line 14
        qn = torch.where(hold[:, None], qo, qn)  # line 16
        q_new = q_new.index_copy(0, ids, qn)
        d = d.index_copy(0, ids, dn)
        return q_new, d


def _transform_rows(p: torch.Tensor, ee: torch.Tensor) -> torch.Tensor:
    """One ee-frame point per row: ``p (B, 3)`` at ``ee (B, 4)`` -> world ``(B, 3)``."""
    c, s = torch.cos(ee[:, 3]), torch.sin(ee[:, 3])
    return torch.stack(
        [c * p[:, 0] - s * p[:, 1] + ee[:, 0], s * p[:, 0] + c * p[:, 1] + ee[:, 1], p[:, 2] + ee[:, 2]], dim=-1
    )
