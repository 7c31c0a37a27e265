"""Which points lie near any of a set of centres (chunked, no (N, P) distance matrix kept)."""
from __future__ import annotations

import torch

__all__ = ["near_any"]


@torch.no_grad()
def near_any(x: torch.Tensor, centres: torch.Tensor, radius: float, chunk: int = 65536) -> torch.Tensor:
    """``(N,)`` bool mask: points ``x (N, 3)`` within ``radius`` of at least one of ``centres (P, 3)``.

    Used to skip points that are outside the object for every pose particle (farther than the object's
    bounding radius from every particle origin); pytorch_volumetric and chsel have no such pruning.
    """
    out = torch.empty(x.shape[0], dtype=torch.bool, device=x.device)
    if centres.shape[0] == 0:
        return out.fill_(False)
    centres = centres.to(x)
    for i in range(0, x.shape[0], chunk):
        out[i:i + chunk] = torch.cdist(x[i:i + chunk], centres).min(dim=1).values <= radius
    return out
