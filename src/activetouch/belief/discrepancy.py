"""CHSEL discrepancy C^(X, T) between observed geometric features and pose particles (RUMI Eq. 3-9).

Poses are object -> world (docs/INTERFACES.md); a world point ``x`` is expressed in the object frame of
pose ``T`` as ``T^-1 x`` (the paper's ``T x``), which ``KnownObject.sdf_world`` does internally and
differentiably w.r.t. the poses. The gradients that flow back are those of Eq. 7-9: the SDF gradient
(unit norm) times the per-point residual, chained through ``T^-1 x``.

Sign convention of alpha: the paper writes ``c_f = C max(0, alpha - sdf)`` (Eq. 4) and
``c_o = C max(0, alpha + sdf)`` (Eq. 5) with "alpha > 0 allows small degrees of violation". chsel 0.2.1,
the reference implementation, uses ``alpha = -surface_threshold < 0`` (``FreeSpaceLookupCost``:
``max(0, -surface_threshold - sdf)``), i.e. a free point may penetrate the object by up to
``surface_threshold`` at no cost. We follow the code: ``alpha = -violation_tolerance``, so
``c_f = C max(0, -tol - sdf)`` and ``c_o = C max(0, sdf - tol)`` (an occupied point may lie up to ``tol``
outside). chsel's own occupied cost (``OccupiedLookupCost``) jumps from 0 to ``2 tol`` at ``sdf = tol``;
we keep the continuous hinge of Eq. 5.
"""
from __future__ import annotations

import torch

from ..geometry import check_poses, near_any

__all__ = ["discrepancy", "point_costs", "prune_far_free", "SURFACE", "FREE", "OCCUPIED"]

# chsel.SemanticsClass values (docs/INTERFACES.md); kept as ints so this module imports without chsel.
SURFACE, FREE, OCCUPIED = 0, 1, 2


def _features_tensors(features, device, dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """``(positions (N, 3), semantics (N,))`` of a ``Features`` on ``device``; validates finiteness."""
    if not hasattr(features, "positions") or not hasattr(features, "semantics"):
        raise ValueError(f"features must be an activetouch.observations.Features, got {type(features).__name__}")
    x = features.positions
    s = features.semantics
    if x.ndim != 2 or x.shape[-1] != 3 or s.shape != x.shape[:1]:
        raise ValueError(f"features must have positions (N, 3) and semantics (N,), got {tuple(x.shape)} and "
                         f"{tuple(s.shape)}")
    if not bool(torch.isfinite(x).all()):
        raise ValueError("features.positions contains NaN or inf")
    return x.to(device=device, dtype=dtype), s.to(device=device)


def _hinge_terms(obj, features, poses, free_scale, violation_tolerance, exact):
    """SDF values and per-point hinge coefficients.

    Every summand of Eq. 3 is ``k1 * relu(v - o1) + k2 * relu(-v - o2)`` with ``v = sdf(T^-1 x)``:
    surface ``|v|`` (k1 = k2 = 1, o1 = o2 = 0), free ``C relu(-tol - v)`` (k2 = C, o2 = tol), occupied
    ``C relu(v - tol)`` (k1 = C, o1 = tol). This avoids three full ``(P, N)`` selects and lets the sum over
    features be a matrix-vector product.
    Returns ``v (P, N)``, ``k1, o1, k2, o2`` each ``(N,)``; ``v`` is None when there are no features.
    """
    poses = check_poses(poses, "poses")
    if poses.ndim != 3:
        raise ValueError(f"poses must have shape (P, 4, 4), got {tuple(poses.shape)}")
    x, s = _features_tensors(features, poses.device, poses.dtype)
    if x.shape[0] == 0:
        return poses, None, None, None, None, None
    surface = s == SURFACE
    free = s == FREE
    occ = s == OCCUPIED
    if not bool((surface | free | occ).all()):
        raise ValueError("features.semantics must be SURFACE (0), FREE (1) or OCCUPIED (2)")
    C = float(free_scale)
    tol = float(violation_tolerance)
    one = torch.ones_like(x[:, 0])
    zero = torch.zeros_like(one)
    k1 = torch.where(surface, one, torch.where(occ, one * C, zero))
    o1 = torch.where(occ, one * tol, zero)
    k2 = torch.where(surface, one, torch.where(free, one * C, zero))
    o2 = torch.where(free, one * tol, zero)
    values, _ = obj.sdf_world(poses, x, exact=exact)  # (P, N), differentiable w.r.t. poses
    return poses, values, k1, o1, k2, o2


def point_costs(
    obj,
    features,
    poses: torch.Tensor,
    *,
    free_scale: float = 10.0,
    violation_tolerance: float = 0.004,
    exact: bool = False,
) -> torch.Tensor:
    """Per-feature discrepancy ``(P, N)`` (the summands of RUMI Eq. 3: Eq. 4 free, Eq. 5 occupied, Eq. 6 surface).

    Args:
        obj: ``KnownObject`` (uses ``obj.sdf_world``).
        features: ``Features`` with ``positions (N, 3)`` (world) and ``semantics (N,)``.
        poses: ``(P, 4, 4)`` object -> world pose particles; gradients flow to them.
        free_scale: C of Eq. 4-5 (Table IV: 10).
        violation_tolerance: ``-alpha`` in metres (see module docstring).
        exact: use the exact mesh SDF instead of the voxel cache.
    """
    poses, v, k1, o1, k2, o2 = _hinge_terms(obj, features, poses, free_scale, violation_tolerance, exact)
    if v is None:
        # No features: every pose is equally consistent (Eq. 3 is an empty sum).
        return poses.new_zeros(poses.shape[0], 0) + 0.0 * poses.sum()
    return k1 * torch.relu(v - o1) + k2 * torch.relu(-v - o2)


def discrepancy(
    obj,
    features,
    poses: torch.Tensor,
    *,
    free_scale: float = 10.0,
    violation_tolerance: float = 0.004,
    exact: bool = False,
) -> torch.Tensor:
    """CHSEL discrepancy ``C^(X, T_i)`` for every pose particle -> ``(P,)`` (RUMI Eq. 3).

    Sum over features of Eq. 4 (free), Eq. 5 (occupied) and Eq. 6 (surface, known SDF 0). Differentiable
    w.r.t. ``poses (P, 4, 4)`` (the backward gives Eq. 7-9); empty ``features`` give zeros. See
    :func:`point_costs` for the arguments.
    """
    features = prune_far_free(obj, features, poses)
    poses, v, k1, o1, k2, o2 = _hinge_terms(obj, features, poses, free_scale, violation_tolerance, exact)
    if v is None:
        return poses.new_zeros(poses.shape[0]) + 0.0 * poses.sum()
    return torch.relu(v - o1) @ k1 + torch.relu(-v - o2) @ k2


def prune_far_free(obj, features, poses: torch.Tensor):
    """Drop free features that cannot cost anything for any particle (exact, a speed-up only).

    A free point costs ``C max(0, -tol - sdf)`` > 0 only when it lies inside the object of some particle,
    which needs its object-frame position within the bounding radius ``R`` of the origin, i.e.
    ``|x - t_i| <= R`` for the particle's translation ``t_i``. Free points farther than ``R`` from every
    particle origin therefore add exactly 0 to Eq. 3 (and to its gradient) and are skipped. Camera views hold
    tens of thousands of free points of which only those near the belief matter; this is what makes weighing
    100 particles cheap on a CPU (hand-written: neither chsel nor pytorch_volumetric prunes).
    """
    s = features.semantics
    free = s == FREE
    if not bool(free.any()) or poses.ndim != 3:
        return features
    x = features.positions.to(poses.device, poses.dtype)
    origins = poses[:, :3, 3].detach()
    keep = ~free.to(poses.device) | near_any(x, origins, obj.bounding_radius)
    if bool(keep.all()):
        return features
    return features.select(keep.to(features.positions.device))
