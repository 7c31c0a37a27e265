"""Importance resampling and pose perturbation (RUMI Algorithm 3 and Algorithm 4 lines 1-3).

Systematic resampling is written here (a dozen lines) because none of pytorch_volumetric /
pytorch_kinematics / pytorch_mppi / chsel offers one for weighted particle sets.
"""
from __future__ import annotations

import torch

from ..geometry import make_pose, perturb_transform

__all__ = ["systematic_resample", "apply_perturbation", "perturb_poses"]


def systematic_resample(weights: torch.Tensor, n: int | None = None,
                        generator: torch.Generator | None = None) -> torch.Tensor:
    """Indices ``(n,)`` (long) drawn by systematic importance resampling of ``weights (P,)``.

    One uniform offset ``u ~ U[0, 1/n)`` from ``generator``; particle ``i`` is picked for every position
    ``u + k/n`` that falls in its slice of the cumulative weights, so it appears ``floor(n w_i)`` or
    ``ceil(n w_i)`` times (low variance; Algorithm 4 line 1, "ImportanceResample").
    """
    if weights.ndim != 1 or weights.numel() == 0:
        raise ValueError(f"weights must have shape (P,) with P > 0, got {tuple(weights.shape)}")
    if not bool(torch.isfinite(weights).all()) or bool((weights < 0).any()):
        raise ValueError("weights must be finite and non-negative")
    total = weights.sum()
    if not float(total) > 0:
        raise ValueError("weights sum to zero; cannot resample")
    n = weights.numel() if n is None else int(n)
    gdev = generator.device if generator is not None else torch.device("cpu")
    w = (weights.detach().to(device="cpu", dtype=torch.float64) / float(total))
    cdf = torch.cumsum(w, 0)
    cdf[-1] = 1.0  # guard against round-off
    u = torch.rand((), generator=generator, device=gdev, dtype=torch.float64).cpu()
    positions = (u + torch.arange(n, dtype=torch.float64)) / n
    idx = torch.searchsorted(cdf, positions, right=True).clamp_(max=weights.numel() - 1)
    return idx.to(weights.device)


def apply_perturbation(poses: torch.Tensor, dT: torch.Tensor) -> torch.Tensor:
    """Perturb poses ``(P, 4, 4)`` by ``dT (P, 4, 4)`` about each particle's own origin -> ``(P, 4, 4)``.

    Returns ``[[dR R_i, t_i + dt], [0, 1]]``: ``dt`` is a world-frame translation and ``dR`` a world-frame
    rotation about the particle's origin. This is the paper's ``dT_sigma . T_i`` (its ``T`` maps world to
    object, so left multiplication perturbs in the object, not about the world origin). For SE(2) noise
    (``dR`` about z, ``dt_z = 0``) the particle's height and tilt stay unchanged.
    """
    R = dT[..., :3, :3] @ poses[..., :3, :3]
    t = poses[..., :3, 3] + dT[..., :3, 3]
    return make_pose(R, t)


def perturb_poses(poses: torch.Tensor, sigma_t: float, sigma_R: float, se2: bool,
                  generator: torch.Generator | None = None) -> torch.Tensor:
    """``T_i <- dT_sigma . T_i`` with ``dT_sigma`` from PerturbTransform (Algorithm 3) for every particle."""
    if sigma_t == 0 and sigma_R == 0:
        return poses.clone()
    dT = perturb_transform(poses.shape[0], sigma_t, sigma_R, se2, generator=generator, device=poses.device,
                           dtype=poses.dtype)
    return apply_perturbation(poses, dT)
