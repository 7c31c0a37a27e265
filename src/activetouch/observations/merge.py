"""MergeObs (RUMI Algorithm 6): merge previous and new geometric features after an object move."""
from __future__ import annotations

import torch

from ..geometry import check_poses, near_any
from .downsample import voxel_downsample
from .features import Features, Semantics

__all__ = ["merge_obs", "covered_by_move"]


def covered_by_move(x: torch.Tensor, poses: torch.Tensor, dT_w: torch.Tensor, obj, chunk: int = 20000) -> torch.Tensor:
    """Which world points ``x (N, 3)`` the object's move ``dT_w (4, 4)`` covered under some particle -> ``(N,)`` bool.

    Particle ``T_i`` (object -> world, after the move) was at ``dT_w^-1 T_i`` before it; ``x`` is covered when
    ``sdf`` at the old pose is > 0 and at the new pose <= 0 (Algorithm 6 line 3 applied to what the move
    changed, see :func:`merge_obs`). Only points within the object's bounding radius of some particle origin
    (before or after) can be covered: the others are skipped exactly.
    """
    poses = poses.reshape(-1, 4, 4)
    out = torch.zeros(len(x), dtype=torch.bool, device=x.device)
    x = x.to(poses.device)  # computed where the particles live (features may sit on the CPU, particles on CUDA)
    dT_w = dT_w.to(poses.device, poses.dtype)
    before = torch.linalg.solve(dT_w, poses) if poses.numel() else poses  # dT_w^-1 T_i
    origins = torch.cat([poses[:, :3, 3], before[:, :3, 3]])
    idx = torch.nonzero(near_any(x, origins, obj.bounding_radius)).squeeze(1)
    with torch.no_grad():
        for s in range(0, len(idx), chunk):
            sel = idx[s : s + chunk]
            v_after, _ = obj.sdf_world(poses, x[sel])  # (P, n)
            v_before, _ = obj.sdf_world(before, x[sel])
            out[sel.to(out.device)] = ((v_before > 0) & (v_after <= 0)).any(dim=0).to(out.device)
    return out


def merge_obs(
    prev: Features,
    new: Features,
    poses: torch.Tensor,
    obj,
    dT_w: torch.Tensor | None = None,
    r_free: float = 0.010,
    r_surface: float = 0.002,
    r_occupied: float | None = None,
    chunk: int = 20000,
) -> Features:
    """RUMI Algorithm 6.

    1. ``X_o``: previous non-free features moved with the object, ``x <- dT_w x``.
    2. ``X_f``: previous free features stay where they are (the world did not move) ...
    3. ... minus those that the move may have covered: line 3 keeps ``x`` only if ``sdf(T_i^-1 x) > 0``
       for every particle ``T_i`` ("remove all that may be occupied now"). Read literally it also deletes
       every free point that merely contradicts some particle, whatever its weight, whenever the object
       moves at all: MuJoCo settles a resting object by 1-2e-6 m per step, so free space would only count in
       the step it is seen (measured on box-0: 678 free points lost in one zero-action step, max discrepancy
       48.3 -> 0). A point can only *become* occupied by the move, so we apply line 3 to the points the move
       covered: ``x`` is dropped when, for some particle, it lay outside the object before the move
       (at ``dT_w^-1 T_i``) and lies inside it after (at ``T_i``). A free point that contradicted particle
       ``i`` before the move still contradicts it; a zero move drops nothing; a push drops the points swept
       by every hypothesis, as line 3 intends. (DEVIATION from the literal line 3, named in README.)
    4. ``X = X_o u X'_f u X'`` and 5. per-semantics voxel downsampling (:func:`voxel_downsample`).

    Args:
        prev: ``X_{t-1}``.
        new: ``X'_t`` (new features, world frame, already at their observed place).
        poses: ``(P, 4, 4)`` object->world particles *after* the predict step (Alg. 1 line 13).
        obj: :class:`activetouch.objects.KnownObject` (its cached SDF is used).
        dT_w: ``(4, 4)`` world-frame change of the object's pose (``x_new = dT_w x_old``), or ``None``
            when the object did not move: then nothing is moved and no free feature is invalidated
            (a free point can only be covered by a move; dropping free points that merely contradict
            some particles would throw away the evidence against those particles).
        r_free, r_surface, r_occupied: downsampling resolutions (Table IV; occupied defaults to
            ``r_surface``).
    Returns:
        The merged, downsampled features ``X_t``.
    """
    if not isinstance(prev, Features) or not isinstance(new, Features):
        raise ValueError("merge_obs expects Features for prev and new")
    r_occupied = r_surface if r_occupied is None else r_occupied
    dev = new.device if len(new) else prev.device
    prev = prev.to(dev)
    new = new.to(dev, dtype=prev.positions.dtype) if len(new) else new
    objective = prev.select(prev.semantics != int(Semantics.FREE))
    free = prev.free
    if dT_w is not None:
        dT_w = check_poses(dT_w, "dT_w")
        if dT_w.shape != (4, 4):
            raise ValueError(f"dT_w must have shape (4, 4), got {tuple(dT_w.shape)}")
        objective = objective.transformed(dT_w.to(dev))
        if len(free):
            poses = check_poses(poses, "poses")
            if poses.ndim == 2:
                poses = poses.unsqueeze(0)
            if poses.ndim != 3:
                raise ValueError(f"poses must have shape (P, 4, 4), got {tuple(poses.shape)}")
            free = free.select(~covered_by_move(free.positions, poses.detach(), dT_w.to(dev), obj, chunk))
    merged = Features.concat([objective, free, new])
    return voxel_downsample(merged, r_free=r_free, r_surface=r_surface, r_occupied=r_occupied)
