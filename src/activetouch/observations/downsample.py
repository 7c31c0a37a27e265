"""Per-semantics voxel downsampling ``D(X, r_d)`` (RUMI section IV-D, Algorithm 6 line 5)."""
from __future__ import annotations

import math

import torch

from .features import Features, Semantics

__all__ = ["voxel_downsample", "voxel_centres"]


def voxel_centres(positions: torch.Tensor, resolution: float) -> torch.Tensor:
    """Centres ``(M, 3)`` of the occupied cells of a world-aligned grid of cell size ``resolution``.

    The lattice is anchored at the world origin (cells ``[k r, (k+1) r)``), not at the data's minimum as
    the paper's wording ("grids that span the range of the positions") could suggest: an anchored lattice
    makes the downsampling idempotent, so merging observations step after step does not drift points by
    half a cell each time. Output is sorted by cell index (deterministic).
    """
    if not (math.isfinite(resolution) and resolution > 0):
        raise ValueError(f"downsample resolution must be finite and > 0, got {resolution}")
    if positions.shape[0] == 0:
        return positions.reshape(0, 3)
    idx = torch.floor(positions.to(torch.float64) / resolution).to(torch.long)
    cells = torch.unique(idx, dim=0)  # sorted lexicographically
    return ((cells.to(torch.float64) + 0.5) * resolution).to(positions.dtype)


def voxel_downsample(
    features: Features, r_free: float = 0.010, r_surface: float = 0.002, r_occupied: float = 0.002
) -> Features:
    """Downsample each semantics class on its own voxel grid and return the occupied cells' centres.

    Defaults are RUMI Table IV: ``r_{d,f} = 10 mm`` free, ``r_{d,s} = 2 mm`` surface (occupied uses the
    surface resolution). Output features are grouped by semantics value (SURFACE, FREE, OCCUPIED).
    """
    if not isinstance(features, Features):
        raise ValueError(f"voxel_downsample expects Features, got {type(features).__name__}")
    res = {Semantics.SURFACE: r_surface, Semantics.FREE: r_free, Semantics.OCCUPIED: r_occupied}
    parts = []
    for s in Semantics:
        sub = features.of(s)
        if len(sub) == 0:
            continue
        c = voxel_centres(sub.positions, float(res[s]))
        parts.append(Features._unchecked(c, torch.full((c.shape[0],), int(s), dtype=torch.long, device=c.device)))
    if not parts:
        return Features.empty(device=features.device, dtype=features.positions.dtype)
    return Features.concat(parts)
