"""ObjMove: estimate the object's motion from new observations (RUMI Algorithm 5).

Frame algebra. The paper's poses map world -> object and it optimises ``dT`` in the hypothesis
``dT . T_i``, then returns ``dT_w = T_i^-1 . dT . T_i`` "that can be applied to world frame positions".
Here poses map object -> world (``x_world = T x_obj``), so:

* the world-frame motion ``dT_w`` moves the object's world points, ``x' = dT_w x``, and its poses,
  ``T' = dT_w T`` (what ``ParticleBelief.predict`` and ``merge_obs`` take);
* the object-frame (body) motion is ``dT = T_i^-1 dT_w T_i`` (``T' = T_i dT``): the paper's formula with
  its world->object ``T_i`` replaced by our ``T_i^-1``. For a particle ``T_j != T_i`` the body motions
  differ, which is why the particles are all moved by the same world-frame ``dT_w``.

We optimise the hypothesis new pose ``T' = dT_w T_i`` with the same local parametrisation as Resample
(rotation about the particle's origin, world-frame translation; SE(2): x, y, yaw only), initialised at the
sticking-contact prior ``dT_w = dT_r`` (``dT_r``: world-frame end-effector motion in contact), for N_o Adam
steps that descend the Eq. 7-9 gradient (the squared-hinge
:func:`~activetouch.belief.discrepancy.optimisation_objective` on X') keeping the iterate with the lowest
``C^(X', T')``, and read ``dT_w = T' T_i^-1`` back.
"""
from __future__ import annotations

import torch

from ..geometry import check_poses, invert, make_pose, yaw_of, yaw_matrix
from .optimise import optimise_poses

__all__ = ["obj_move", "project_se2_motion"]


def project_se2_motion(dT: torch.Tensor) -> torch.Tensor:
    """Closest planar world-frame motion ``(4, 4)``: yaw about world z and x, y translation (no z, tilt)."""
    yaw = yaw_of(dT)
    t = torch.stack([dT[..., 0, 3], dT[..., 1, 3], torch.zeros_like(dT[..., 2, 3])], dim=-1)
    return make_pose(yaw_matrix(yaw), t)


def obj_move(cost_fn, prev_cost: torch.Tensor, poses: torch.Tensor, dT_r: torch.Tensor | None,
             n_opt: int, lr_t: float, lr_R: float, se2: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """Algorithm 5 given the discrepancies; see :meth:`ParticleBelief.obj_move` for the user-facing call.

    Args:
        cost_fn: ``poses (K, 4, 4) -> (K,)`` or ``-> ((K,), (K,))``: ``C^(X', .)`` on the newly observed features
            ``X'``, or ``(C^, J)`` with ``J`` the objective to descend (see :func:`optimise_poses`).
        prev_cost: ``(P,)`` ``C^(X, T_{1..P})`` on the previous features (line 2).
        poses: ``(P, 4, 4)`` particles.
        dT_r: ``(4, 4)`` world-frame end-effector motion while in contact (None: identity).
    Returns:
        ``(dT (4, 4) body frame, dT_w (4, 4) world frame)``.
    """
    dT_r = torch.eye(4, dtype=poses.dtype, device=poses.device) if dT_r is None else check_poses(dT_r, "dT_r")
    if dT_r.shape != (4, 4):
        raise ValueError(f"dT_r must have shape (4, 4), got {tuple(dT_r.shape)}")
    dT_r = dT_r.to(poses)
    if se2:
        dT_r = project_se2_motion(dT_r)
    finite = torch.isfinite(prev_cost)
    i = int(torch.argmin(torch.where(finite, prev_cost, torch.full_like(prev_cost, float("inf"))))) \
        if bool(finite.any()) else 0  # line 3
    Ti = poses[i]
    # Sticking-contact prior (line 1), expressed in the local parametrisation about T_i's origin:
    # T' = dT_r T_i.
    T0 = (dT_r @ Ti).unsqueeze(0)
    T_new, _ = optimise_poses(cost_fn, T0, n_opt, lr_t, lr_R, se2)  # lines 4-6
    dT_w = T_new[0] @ invert(Ti)  # world frame (the paper's line 7 in our convention)
    if se2:
        dT_w = project_se2_motion(dT_w)
    dT = invert(Ti) @ dT_w @ Ti  # body frame
    return dT, dT_w
