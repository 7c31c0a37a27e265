"""Contact-placed prior proposals for RUMI's resampling (beyond the paper: a fix for particle depletion).

Why (issue 8, measured): on the SE(3) box tasks the camera sees no surface point, so CHSEL (Algorithm 1 line 2)
has nothing to register and the particles are prior draws (six resting faces x uniform yaw). At the first
one-face contact Algorithm 4 resamples onto the few particles that fit that face; with sigma_R = 0 no other
face or yaw can come back, APC falls below beta_t l_c and the episode stops 90-180 deg off while the evidence
still fits the truth (its discrepancy stays at 1-9). The paper avoids this with CHSEL over the whole workspace
at initialisation; CHSEL at the first contact took 841 s per registration here (README "Where we differ").

This module is the cheap version of that registration: at each resample, ``K`` fresh draws from the task's
prior are *placed on the contact*: each keeps its orientation and height and is shifted in x, y so that one of
its surface points lands on an observed surface point at the same height. The best of them by C^ are
optimised with the same N_o Adam steps as the resampled particles (Algorithm 4 lines 4-6) and each replaces a
particle drawn at random with the Metropolis probability of the posterior (Eq. 10):
:meth:`ParticleBelief._reinvigorate`, a resample-move step. A proposal that the evidence cannot tell from the
particles thus enters the set, APC stays high while such alternatives exist, and APC termination then means
what Section V-J hopes it means: "pose particles likely only converge when p(T*|X) is high".

With model normals (``BeliefConfig.reinvigorate_normals``, the default; :func:`surface_normals` /
:func:`model_surface`) a placement also turns
the hypothesis about the world z axis so that the model's outward normal at the chosen model point matches the
observed patch's normal at the chosen observed point (a plane fit of its nearest observed neighbours, sign
drawn at random, since which side the object lies on is not known from the points alone; the wrong side puts
the object into the gripper's free space and is rejected there), and only model points whose normal has the
observed normal's vertical component qualify. Measured on box-1 seed 4 (exact contact points): after a
two-face contact the true pose had C^ 0.02 while every particle had C^ >= 2.1, i.e. the evidence had rejected
the particle set, yet no random-yaw placement had found the true mode; a yaw chosen at random lands within
the ~10 deg basin of the N_o optimisation steps about one draw in twenty, an aligned one whenever the model
point is on the right face.

Written here (no maintained library places pose hypotheses on contact points); the placement is the same
idea as the touch paper's contact-aware resampling (App. B), in SE(3) and against a labelled point cloud.
"""
from __future__ import annotations

import torch

from ..geometry import check_poses

__all__ = ["place_on_surface", "surface_normals", "model_surface"]


def model_surface(obj, n: int = 2000, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor | None]:
    """``(points (n, 3), normals (n, 3) or None)``: object-frame surface samples of ``obj`` and the outward
    normals of the mesh faces they lie on (``obj.mesh``, a trimesh; None for an object without one). The points
    are those of ``obj.sample_surface(n, seed)`` (the same trimesh call)."""
    import numpy as np
    import trimesh

    mesh = getattr(obj, "mesh", None)
    if not isinstance(mesh, trimesh.Trimesh):
        return obj.sample_surface(n, seed=seed), None
    pts, face = trimesh.sample.sample_surface(mesh, int(n), seed=int(seed))
    normals = np.asarray(mesh.face_normals)[face]
    return torch.as_tensor(np.asarray(pts), dtype=torch.float32), torch.as_tensor(normals, dtype=torch.float32)


def surface_normals(points: torch.Tensor, query: torch.Tensor, k: int = 12) -> torch.Tensor:
    """Unit normals ``(Q, 3)`` of an observed surface at ``query (Q, 3)``: the least-variance direction of the
    ``k`` nearest of ``points (S, 3)`` (a local plane fit, PCA); the sign is arbitrary (+z half-space for
    definiteness). Fewer than 3 neighbours: zero normals (no plane)."""
    pts = torch.as_tensor(points)
    q = torch.as_tensor(query).to(pts)
    if pts.shape[0] < 3:
        return torch.zeros_like(q)
    kk = min(int(k), pts.shape[0])
    idx = torch.cdist(q, pts).topk(kk, dim=1, largest=False).indices  # (Q, k)
    nb = pts[idx]  # (Q, k, 3)
    c = nb - nb.mean(dim=1, keepdim=True)
    cov = c.transpose(1, 2) @ c / kk  # (Q, 3, 3)
    _, vecs = torch.linalg.eigh(cov.double())
    n = vecs[..., 0].to(pts.dtype)  # eigenvector of the smallest eigenvalue
    return torch.where(n[:, 2:3] < 0, -n, n)


def place_on_surface(model_points: torch.Tensor, poses: torch.Tensor, surface: torch.Tensor,
                     generator: torch.Generator | None = None, height_tol: float = 0.005,
                     model_normals: torch.Tensor | None = None, normal_tol: float = 0.25) -> torch.Tensor:
    """Shift pose hypotheses in x, y so each puts a model surface point on an observed surface point; with
    ``model_normals``, first turn each about the world z axis so the model's normal there matches the observed
    surface's normal (see the module docstring).

    Args:
        model_points: ``(M, 3)`` object-frame surface samples.
        poses: ``(K, 4, 4)`` hypotheses (object -> world); rotation and height are kept.
        surface: ``(S, 3)`` observed world surface points, S >= 1.
        generator: torch generator (which observed point and which model point each hypothesis uses).
        height_tol: a model point qualifies when its world height under the pose is within this of the chosen
            observed point's height (m); a hypothesis with no qualifying point is returned unchanged.
        model_normals: ``(M, 3)`` outward object-frame normals at ``model_points`` (None: no alignment).
        normal_tol: with normals, a model point also qualifies only if the vertical component of its world
            normal is within this of the observed normal's (of the drawn sign).
    Returns:
        ``(K, 4, 4)`` placed poses.
    """
    T = check_poses(poses, "poses")
    if T.ndim != 3:
        raise ValueError(f"poses must have shape (K, 4, 4), got {tuple(T.shape)}")
    s = torch.as_tensor(surface).to(T)
    m = torch.as_tensor(model_points).to(T)
    if s.ndim != 2 or s.shape[-1] != 3 or s.shape[0] == 0:
        raise ValueError(f"surface must have shape (S, 3) with S > 0, got {tuple(s.shape)}")
    if m.ndim != 2 or m.shape[-1] != 3 or m.shape[0] == 0:
        raise ValueError(f"model_points must have shape (M, 3) with M > 0, got {tuple(m.shape)}")
    K, M = T.shape[0], m.shape[0]
    gdev = generator.device if generator is not None else torch.device("cpu")
    pick = torch.randint(0, s.shape[0], (K,), generator=generator, device=gdev).to(T.device)
    target = s[pick]  # (K, 3)
    rotated = torch.einsum("kij,mj->kmi", T[:, :3, :3], m)  # (K, M, 3) = R m
    height = rotated[..., 2] + T[:, None, 2, 3]  # (K, M)
    ok = (height - target[:, None, 2]).abs() <= float(height_tol)
    align = model_normals is not None
    if align:
        nm = torch.as_tensor(model_normals).to(T)
        if nm.shape != m.shape:
            raise ValueError(f"model_normals must have shape {tuple(m.shape)}, got {tuple(nm.shape)}")
        sign = torch.randint(0, 2, (K,), generator=generator, device=gdev).to(T.device).to(T.dtype) * 2 - 1
        want = surface_normals(s, target) * sign[:, None]  # (K, 3) outward normal the object should have there
        known = want.norm(dim=1) > 0.5  # no plane (fewer than 3 observed points): no normal condition, no turn
        wn = torch.einsum("kij,mj->kmi", T[:, :3, :3], nm)  # (K, M, 3) model normals in world axes
        ok = ok & (~known[:, None] | ((wn[..., 2] - want[:, None, 2]).abs() <= float(normal_tol)))
    u = torch.rand(K, M, generator=generator, device=gdev, dtype=T.dtype).to(T.device)
    j = torch.argmax(torch.where(ok, u, torch.full_like(u, -1.0)), dim=1)  # a random qualifying point
    has = ok.any(dim=1)
    out = T.clone()
    ar = torch.arange(K, device=T.device)
    if align:  # turn about world z so the horizontal parts of the two normals point the same way
        a, b = want[:, :2], wn[ar, j, :2]
        turn = torch.atan2(a[:, 1], a[:, 0]) - torch.atan2(b[:, 1], b[:, 0])
        flat = (a.norm(dim=1) < 0.2) | (b.norm(dim=1) < 0.2) | ~has | ~known  # a horizontal face: any yaw fits
        turn = torch.where(flat, torch.zeros_like(turn), turn)
        c, sn = torch.cos(turn), torch.sin(turn)
        Rz = torch.zeros(K, 3, 3, dtype=T.dtype, device=T.device)
        Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -sn, sn, c, 1.0
        out[:, :3, :3] = Rz @ T[:, :3, :3]
        rotated_j = torch.einsum("kij,kj->ki", out[:, :3, :3], m[j])
    else:
        rotated_j = rotated[ar, j]
    shift = target[:, :2] - rotated_j[:, :2]
    out[:, :2, 3] = torch.where(has[:, None], shift, T[:, :2, 3])
    return out
