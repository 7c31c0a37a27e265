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

Written here (no maintained library places pose hypotheses on contact points); the placement is the same
idea as the touch paper's contact-aware resampling (App. B), in SE(3) and against a labelled point cloud.
"""
from __future__ import annotations

import torch

from ..geometry import check_poses

__all__ = ["place_on_surface"]


def place_on_surface(model_points: torch.Tensor, poses: torch.Tensor, surface: torch.Tensor,
                     generator: torch.Generator | None = None, height_tol: float = 0.005) -> torch.Tensor:
    """Shift pose hypotheses in x, y so each puts a model surface point on an observed surface point.

    Args:
        model_points: ``(M, 3)`` object-frame surface samples.
        poses: ``(K, 4, 4)`` hypotheses (object -> world); rotation and height are kept.
        surface: ``(S, 3)`` observed world surface points, S >= 1.
        generator: torch generator (which observed point and which model point each hypothesis uses).
        height_tol: a model point qualifies when its world height under the pose is within this of the chosen
            observed point's height (m); a hypothesis with no qualifying point is returned unchanged.
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
    u = torch.rand(K, M, generator=generator, device=gdev, dtype=T.dtype).to(T.device)
    j = torch.argmax(torch.where(ok, u, torch.full_like(u, -1.0)), dim=1)  # a random qualifying point
    has = ok.any(dim=1)
    out = T.clone()
    shift = target[:, :2] - rotated[torch.arange(K, device=T.device), j, :2]
    out[:, :2, 3] = torch.where(has[:, None], shift, T[:, :2, 3])
    return out
