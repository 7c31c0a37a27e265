"""A few Adam steps on the discrepancy over local pose parameters (RUMI Algorithm 4 lines 4-6, Algorithm 5).

Local parametrisation around base poses ``T0 = [[R0, t0], [0, 1]]`` (object -> world):

* SE(2): ``T = [[Rz(psi) R0, t0 + (dx, dy, 0)], [0, 1]]``: only x, y and yaw change; height and tilt of
  the base pose are kept exactly (the paper restricts mug and drill poses to SE(2)).
* SE(3): ``T = [[exp([w]_x) R0, t0 + dt], [0, 1]]`` with ``exp`` the matrix exponential (``torch.linalg.
  matrix_exp``, smooth at ``w = 0``, unlike the quaternion route whose gradient is NaN at zero).

The paper says "SGD"; like chsel's own registration SGD (``chsel.sgd``) we use Adam, with separate step
sizes for translation (m) and rotation (rad). The step direction is the gradient of RUMI Eq. 7-9 (residual
times SDF gradient), i.e. of the squared-hinge :func:`activetouch.belief.discrepancy.optimisation_objective`,
when the cost function returns it alongside the discrepancy. Because Adam may overshoot within N_o = 10 steps,
each particle keeps its iterate with the lowest discrepancy C^ (the initial pose included), so optimisation
never makes a particle worse under the cost its weight is computed from.
"""
from __future__ import annotations

from typing import Callable

import torch

from ..geometry import make_pose, yaw_matrix

__all__ = ["local_poses", "optimise_poses"]


def _skew(w: torch.Tensor) -> torch.Tensor:
    z = torch.zeros_like(w[..., 0])
    return torch.stack(
        [torch.stack([z, -w[..., 2], w[..., 1]], -1),
         torch.stack([w[..., 2], z, -w[..., 0]], -1),
         torch.stack([-w[..., 1], w[..., 0], z], -1)], dim=-2)


def local_poses(base: torch.Tensor, rot: torch.Tensor, trans: torch.Tensor, se2: bool) -> torch.Tensor:
    """Poses ``(P, 4, 4)`` from base poses ``(P, 4, 4)`` and local parameters.

    Args:
        base: ``(P, 4, 4)`` base poses ``T0``.
        rot: SE(2) ``(P,)`` yaw increments; SE(3) ``(P, 3)`` world-frame rotation vectors.
        trans: SE(2) ``(P, 2)`` x, y increments; SE(3) ``(P, 3)`` world-frame translation increments.
    """
    R0, t0 = base[..., :3, :3], base[..., :3, 3]
    if se2:
        R = yaw_matrix(rot) @ R0
        t = t0 + torch.cat([trans, torch.zeros_like(trans[..., :1])], dim=-1)
    else:
        R = torch.linalg.matrix_exp(_skew(rot)) @ R0
        t = t0 + trans
    return make_pose(R, t)


def _cost_and_objective(cost_fn, T):
    out = cost_fn(T)
    if isinstance(out, tuple):
        return out
    return out, out


def optimise_poses(
    cost_fn: Callable[[torch.Tensor], torch.Tensor | tuple[torch.Tensor, torch.Tensor]],
    poses: torch.Tensor,
    n_steps: int,
    lr_t: float,
    lr_R: float,
    se2: bool,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Minimise over ``n_steps`` Adam steps per particle; ``cost_fn(poses (P, 4, 4))`` returns ``cost (P,)`` or
    ``(cost (P,), objective (P,))``.

    With a pair the steps descend ``objective`` (RUMI Algorithms 4 and 5: the squared-hinge objective whose
    gradient is Eq. 7-9) and each particle keeps its iterate with the lowest ``cost`` (the discrepancy C^);
    with a single tensor both are ``cost``. Particles are independent (the cost of one particle depends only on
    its pose), so the summed objective gives each particle its own gradient. Returns ``(best poses (P, 4, 4),
    their costs (P,))``, detached.
    """
    base = poses.detach()
    P = base.shape[0]
    rot = torch.zeros((P,) if se2 else (P, 3), dtype=base.dtype, device=base.device, requires_grad=True)
    trans = torch.zeros((P, 2) if se2 else (P, 3), dtype=base.dtype, device=base.device, requires_grad=True)
    best = base.clone()
    with torch.no_grad():
        best_cost = _cost_and_objective(cost_fn, base)[0].detach().clone()
    if n_steps <= 0:
        return best, best_cost
    opt = torch.optim.Adam([{"params": [trans], "lr": float(lr_t)}, {"params": [rot], "lr": float(lr_R)}])
    for k in range(n_steps + 1):
        T = local_poses(base, rot, trans, se2)
        if k == n_steps:  # evaluate the last iterate
            with torch.no_grad():
                c, J = _cost_and_objective(cost_fn, T)
        else:
            c, J = _cost_and_objective(cost_fn, T)
        with torch.no_grad():
            if k > 0:  # k == 0 is the base pose, already recorded
                better = torch.isfinite(c) & (c < best_cost)
                best = torch.where(better[:, None, None], T.detach(), best)
                best_cost = torch.where(better, c.detach(), best_cost)
        if k == n_steps:
            break
        opt.zero_grad(set_to_none=True)
        J.sum().backward()
        for p in (rot, trans):
            if p.grad is not None:
                p.grad.nan_to_num_(0.0, posinf=0.0, neginf=0.0)
        opt.step()
    return best, best_cost
