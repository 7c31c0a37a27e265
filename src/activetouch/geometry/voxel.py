"""Regular voxel grid of cell centres with trilinear interpolation.

Used for the cached SDF of known objects, the semantics / information-gain grids of RUMI (section IV-D:
"cache the results in voxel grids ... linear interpolation querying") and the reachability map.

Why our own class rather than ``pytorch_volumetric.VoxelGrid``: interpolation here goes through
``torch.nn.functional.grid_sample`` (one fused C++/CUDA kernel, differentiable w.r.t. both the values and
the query points), which is several times faster for the 100 particles x 5000 points hot path than a
gather-based trilinear lookup, and lets the caller choose the value returned outside the grid.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

__all__ = ["VoxelGrid"]


class VoxelGrid:
    """Axis-aligned regular grid of cubic cells of side ``resolution`` covering ``[lower, upper]``.

    The grid has ``n_i = ceil((upper_i - lower_i) / resolution)`` cells along axis i (at least 1); cell
    ``(i, j, k)`` has its centre at ``lower + (idx + 0.5) * resolution``. The covered box is
    ``[lower, lower + n * resolution]`` (``self.upper``), which contains the requested upper bound.

    Args:
        lower: ``(3,)`` lower corner (metres).
        upper: ``(3,)`` upper corner, strictly greater than ``lower`` on every axis.
        resolution: cell side (metres), > 0.
    """

    def __init__(self, lower, upper, resolution: float):
        lo = torch.as_tensor(lower, dtype=torch.float64).detach().cpu().reshape(-1)
        up = torch.as_tensor(upper, dtype=torch.float64).detach().cpu().reshape(-1)
        if lo.shape != (3,) or up.shape != (3,):
            raise ValueError(f"lower and upper must have shape (3,), got {tuple(lo.shape)} and {tuple(up.shape)}")
        if not (torch.isfinite(lo).all() and torch.isfinite(up).all()):
            raise ValueError("lower and upper must be finite")
        if not bool((up > lo).all()):
            raise ValueError(f"upper must be > lower on every axis, got lower={lo.tolist()} upper={up.tolist()}")
        resolution = float(resolution)
        if not math.isfinite(resolution) or resolution <= 0:
            raise ValueError(f"resolution must be finite and > 0, got {resolution}")
        self.resolution = resolution
        n = torch.ceil((up - lo) / resolution - 1e-9).clamp_min(1).to(torch.long)
        self._shape = tuple(int(v) for v in n)
        self.lower = lo
        self.upper = lo + n.to(torch.float64) * resolution

    # ------------------------------------------------------------------ geometry
    @property
    def shape(self) -> tuple[int, int, int]:
        """``(nx, ny, nz)`` number of cells per axis."""
        return self._shape

    @property
    def num_cells(self) -> int:
        return self._shape[0] * self._shape[1] * self._shape[2]

    def __repr__(self) -> str:
        return (
            f"VoxelGrid(lower={self.lower.tolist()}, upper={self.upper.tolist()}, "
            f"resolution={self.resolution}, shape={self.shape})"
        )

    def axes(self, device=None, dtype=torch.float32) -> list[torch.Tensor]:
        """Cell-centre coordinates along each axis: list of ``(n_i,)`` tensors."""
        return [
            (self.lower[i] + (torch.arange(self._shape[i], dtype=torch.float64) + 0.5) * self.resolution).to(
                device=device, dtype=dtype
            )
            for i in range(3)
        ]

    def points(self, device=None, dtype=torch.float32) -> torch.Tensor:
        """All cell centres ``(nx*ny*nz, 3)``, ordered so that ``points().reshape(nx, ny, nz, 3)`` indexes cells."""
        gx, gy, gz = torch.meshgrid(*self.axes(device=device, dtype=dtype), indexing="ij")
        return torch.stack([gx, gy, gz], dim=-1).reshape(-1, 3)

    def contains(self, x: torch.Tensor) -> torch.Tensor:
        """Whether points ``x (..., 3)`` lie in the covered box -> bool ``(...)``."""
        lo = self.lower.to(device=x.device, dtype=x.dtype)
        up = self.upper.to(device=x.device, dtype=x.dtype)
        return ((x >= lo) & (x <= up)).all(dim=-1)

    def cell_index(self, x: torch.Tensor) -> torch.Tensor:
        """Integer cell index ``(..., 3)`` of points ``x (..., 3)``, clamped into the grid."""
        lo = self.lower.to(device=x.device, dtype=x.dtype)
        idx = torch.floor((x - lo) / self.resolution).to(torch.long)
        hi = torch.tensor(self._shape, device=x.device) - 1
        return torch.minimum(idx.clamp_min(0), hi)

    def clamp(self, x: torch.Tensor) -> torch.Tensor:
        """Closest point of the covered box to each of ``x (..., 3)``."""
        lo = self.lower.to(device=x.device, dtype=x.dtype)
        up = self.upper.to(device=x.device, dtype=x.dtype)
        return torch.maximum(torch.minimum(x, up), lo)

    # ------------------------------------------------------------------ interpolation
    def interpolate(self, values: torch.Tensor, x: torch.Tensor, outside: float | None = 0.0) -> torch.Tensor:
        """Trilinear interpolation of cell-centre ``values (nx, ny, nz[, C])`` at points ``x (..., 3)``.

        Returns ``(...)`` (or ``(..., C)``). Between the outermost cell centres and the box faces the edge
        value is used (border clamping). Points outside the covered box get ``outside`` (``None``: border
        clamping everywhere). Differentiable w.r.t. ``values`` and ``x``; runs on ``x``'s device.
        """
        if not torch.is_tensor(values):
            values = torch.as_tensor(values)
        if not torch.is_tensor(x):
            x = torch.as_tensor(x)
        if values.ndim not in (3, 4) or tuple(values.shape[:3]) != self._shape:
            raise ValueError(f"values must have shape {self._shape} or {self._shape} + (C,), got {tuple(values.shape)}")
        if x.ndim < 1 or x.shape[-1] != 3:
            raise ValueError(f"x must have shape (..., 3), got {tuple(x.shape)}")
        if not torch.is_floating_point(values):
            values = values.to(torch.get_default_dtype())
        has_c = values.ndim == 4
        v = values if has_c else values.unsqueeze(-1)
        v = v.to(device=x.device)
        dtype = v.dtype
        batch = x.shape[:-1]
        xf = x.reshape(-1, 3).to(dtype)
        # grid_sample wants (N, C, D, H, W) with the grid's last coordinate order (W, H, D) = (x, y, z).
        inp = v.permute(3, 2, 1, 0).unsqueeze(0)  # (1, C, nz, ny, nx)
        n = torch.tensor(self._shape, device=x.device, dtype=dtype)
        c0 = (self.lower + 0.5 * self.resolution).to(device=x.device, dtype=dtype)
        span = (n - 1).clamp_min(1) * self.resolution
        g = 2.0 * (xf - c0) / span - 1.0
        g = torch.where(n > 1, g, torch.zeros_like(g))  # single-cell axes: constant
        out = F.grid_sample(
            inp, g.view(1, -1, 1, 1, 3), mode="bilinear", padding_mode="border", align_corners=True
        )  # (1, C, M, 1, 1)
        out = out.view(v.shape[-1], -1).transpose(0, 1)  # (M, C)
        if outside is not None:
            inside = self.contains(xf)
            out = torch.where(inside.unsqueeze(-1), out, torch.full_like(out, float(outside)))
        out = out.reshape(*batch, v.shape[-1])
        return out if has_c else out.squeeze(-1)
