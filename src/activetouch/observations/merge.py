"""MergeObs (RUMI Algorithm 6): merge previous and new geometric features after an object move."""
from __future__ import annotations

import torch

from ..geometry import check_poses, near_any
from .downsample import voxel_downsample
from .features import Features, Semantics

__all__ = ["merge_obs"]


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
    3. ... but only those with ``sdf(T_i^-1 x) > 0`` for **every** particle ``T_i`` survive: the moved
       object may now cover them.
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
            keep = torch.ones(len(free), dtype=torch.bool, device=dev)
            # only points within the bounding radius of some particle origin can be covered (exact pruning)
            near = near_any(free.positions, poses[:, :3, 3].detach(), obj.bounding_radius)
            idx = torch.nonzero(near).squeeze(1)
            with torch.no_grad():
                for s in range(0, len(idx), chunk):
                    sel = idx[s : s + chunk]
                    v, _ = obj.sdf_world(poses.detach(), free.positions[sel])
                    keep[sel] = (v > 0).all(dim=0).to(dev)
            free = free.select(keep)
    merged = Features.concat([objective, free, new])
    return voxel_downsample(merged, r_free=r_free, r_surface=r_surface, r_occupied=r_occupied)
