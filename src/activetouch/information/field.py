"""RUMI's information gain field (Eq. 23) and semantics probability field (Eq. 27), cached on a workspace grid.

Section IV-D / Algorithm 1 line 5: for every workspace position ``x in W`` compute

* ``p(S_x | X) = sum_i w_i p(S | sdf(T_i^-1 x))``                          (Eq. 27, sensor model of V-E)
* ``I~(x | X)  = lambda * sum_s p(S_x = s | X) * sum_i w_i C^((x, s), T_i)``  (Eq. 23, C^ of Eq. 4-6)

and cache them in voxel grids queried by trilinear interpolation; outside ``W`` the field returns
``I~ = 0`` and ``p = free``. The pushing-normal estimate of Algorithm 7 line 11,
``n^(x) = sum_j w_j R_j grad sdf(T_j^-1 x)`` (object-frame gradient rotated to the world), is cached on the
same grid because it needs exactly the SDF evaluations done here (every particle at every workspace
point); querying it inside the dynamics would otherwise cost ``P`` SDF look-ups per rolled-out contact.

Far from every particle the object is certainly absent: beyond a margin ``m`` from a particle's bounding
box ``sdf >= m`` so ``p(surface) <= exp(-alpha_s (m - zeta))``. Points farther than ``m`` from *all*
particle boxes are set to exactly ``p = free, I~ = 0, n^ = 0`` without evaluating the SDF, with ``m``
chosen so that the dropped probability is below ``negligible`` (default 1e-4). This is what makes the
field cheap (the mug's ~0.3 m neighbourhood instead of the whole 0.8 m workspace).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from activetouch.geometry.transforms import check_poses
from activetouch.geometry.voxel import VoxelGrid
from activetouch.information.costs import per_semantics_costs

__all__ = [
    "SURFACE",
    "FREE",
    "OCCUPIED",
    "InformationField",
    "compute_field",
    "field_margin",
    "semantics_probabilities",
    "information_gain",
]

SURFACE, FREE, OCCUPIED = 0, 1, 2


def _default_sensor():
    from activetouch.observations import SemanticSensorModel

    return SemanticSensorModel()


def _check_particles(poses: torch.Tensor, weights: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    poses = check_poses(poses, "poses")
    if poses.ndim != 3:
        raise ValueError(f"poses must have shape (P, 4, 4), got {tuple(poses.shape)}")
    weights = torch.as_tensor(weights, device=poses.device, dtype=poses.dtype)
    if weights.shape != (poses.shape[0],):
        raise ValueError(f"weights must have shape ({poses.shape[0]},), got {tuple(weights.shape)}")
    if not bool(torch.isfinite(weights).all()) or bool((weights < 0).any()):
        raise ValueError("weights must be finite and non-negative")
    total = weights.sum()
    if not total > 0:
        raise ValueError("weights must not all be zero")
    return poses, weights / total


def _check_points(x: torch.Tensor, name: str = "x") -> torch.Tensor:
    if not torch.is_tensor(x):
        x = torch.as_tensor(x, dtype=torch.get_default_dtype())
    if x.ndim < 1 or x.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (..., 3), got {tuple(x.shape)}")
    if not bool(torch.isfinite(x).all()):
        raise ValueError(f"{name} contains NaN or inf entries")
    return x


def field_margin(sensor, negligible: float = 1e-4) -> float:
    """Distance ``m`` beyond which ``p(surface | sdf >= m) < negligible`` for the sensor model of V-E.

    ``p(surface | v) = exp(-alpha (|v| - zeta))`` so ``m = zeta + ln(1 / negligible) / alpha``
    (0.095 m for zeta = 3 mm, alpha = 100, negligible = 1e-4).
    """
    if not 0 < negligible < 1:
        raise ValueError(f"negligible must be in (0, 1), got {negligible}")
    zeta = float(getattr(sensor, "zeta", 0.003))
    alpha = float(getattr(sensor, "alpha", 100.0))
    return zeta + math.log(1.0 / negligible) / alpha


def _particle_terms(obj, poses, weights, x, *, free_scale, alpha, sensor, chunk):
    """Weighted particle sums at world points ``x (N, 3)``.

    Returns ``p (N, 3)`` (Eq. 27), ``expected_cost (N, 3)`` (``sum_i w_i C^((x, s), T_i)`` per ``s``) and
    ``normal (N, 3)`` (Alg. 7 line 11, world frame, not normalised).
    """
    N = x.shape[0]
    P = poses.shape[0]
    p_out = torch.empty(N, 3, device=x.device, dtype=x.dtype)
    c_out = torch.empty(N, 3, device=x.device, dtype=x.dtype)
    n_out = torch.empty(N, 3, device=x.device, dtype=x.dtype)
    R = poses[:, :3, :3]
    step = max(1, chunk // max(P, 1))
    with torch.no_grad():
        for s in range(0, N, step):
            xs = x[s : s + step]
            v, g = obj.sdf_world(poses, xs)  # (P, n), (P, n, 3) object frame
            v = v.to(x.dtype)
            g = g.to(x.dtype)
            probs = sensor.probs(v).to(x.dtype)  # (P, n, 3)
            p_out[s : s + step] = torch.einsum("p,pnc->nc", weights, probs)
            costs = per_semantics_costs(v, free_scale, alpha)  # (P, n, 3)
            c_out[s : s + step] = torch.einsum("p,pnc->nc", weights, costs)
            # SIMPLIFICATION (used by Alg. 7 line 11): the weighted normal is cached on the grid and interpolated at
            # the contact candidate instead of summing P exact gradients there; cost: trilinear blur within one
            # cell (r_w) of thin walls; gain: no P-particle SDF query per rolled-out contact.
            n_out[s : s + step] = torch.einsum("p,pij,pnj->ni", weights, R, g)
    return p_out, c_out, n_out


def semantics_probabilities(obj, poses, weights, x, *, sensor=None, chunk: int = 400_000) -> torch.Tensor:
    """Eq. 27: ``p(S_x | X) = sum_i w_i p(S | sdf(T_i^-1 x))`` at world points ``x (N, 3)`` -> ``(N, 3)``.

    Columns are indexed by the Semantics value (SURFACE, FREE, OCCUPIED); rows sum to 1.
    Exact evaluation at the given points (no grid); ``chunk`` bounds ``P * points`` per SDF batch.
    """
    poses, weights = _check_particles(poses, weights)
    x = _check_points(x).to(device=poses.device, dtype=poses.dtype).reshape(-1, 3)
    sensor = sensor or _default_sensor()
    p, _, _ = _particle_terms(obj, poses, weights, x, free_scale=1.0, alpha=0.0, sensor=sensor, chunk=chunk)
    return p


def information_gain(obj, poses, weights, x, *, lam: float, free_scale: float, alpha: float, sensor=None,
                     chunk: int = 400_000) -> torch.Tensor:
    """Eq. 23: ``I~(x|X) = lam * sum_s p(S_x = s | X) sum_i w_i C^((x, s), T_i)`` at world points ``x (N, 3)``.

    Returns ``(N,)`` non-negative values. Exact evaluation at the given points (no grid).
    """
    poses, weights = _check_particles(poses, weights)
    x = _check_points(x).to(device=poses.device, dtype=poses.dtype).reshape(-1, 3)
    sensor = sensor or _default_sensor()
    p, c, _ = _particle_terms(obj, poses, weights, x, free_scale=free_scale, alpha=alpha, sensor=sensor,
                              chunk=chunk)
    return lam * (p * c).sum(-1)


@dataclass(eq=False, repr=False)
class InformationField:
    """Cached RUMI fields on a workspace grid (Algorithm 1 line 5).

    Attributes:
        grid: the workspace :class:`VoxelGrid` (cell size ``r_w``).
        probs: ``(nx, ny, nz, 3)`` ``p(S_x | X)`` (Eq. 27) at the cell centres.
        info: ``(nx, ny, nz)`` ``I~(x | X)`` (Eq. 23) at the cell centres.
        normals: ``(nx, ny, nz, 3)`` weighted world-frame SDF gradients ``sum_j w_j R_j grad sdf`` (Alg. 7).
        active_lower, active_upper: ``(3,)`` box outside which ``p = free`` and ``I~ = 0`` exactly (the
            neighbourhood of the particles where the SDF was evaluated), used to skip work in planning.
    """

    grid: VoxelGrid
    probs: torch.Tensor
    info: torch.Tensor
    normals: torch.Tensor
    active_lower: torch.Tensor
    active_upper: torch.Tensor

    def __post_init__(self):
        free = torch.zeros(3, device=self.probs.device, dtype=self.probs.dtype)
        free[FREE] = 1.0
        self._free = free
        # Stored as offsets from "free" so that interpolate(..., outside=0) returns exactly free outside W.
        self._probs_offset = self.probs - free
        self._free_offset = self.probs[..., FREE] - 1.0
        self.total_info = float(self.info.sum())
        # Fast path for the planner's hot loops (see grid_coords / sample_free): the affine map world ->
        # normalised grid coordinates (align_corners=True: -1/+1 at the outer cell centres; single-cell axes:
        # -1/+1 at the cell faces) and the grid_sample input.
        dtype, device = self.info.dtype, self.info.device
        n = torch.tensor(self.grid.shape, dtype=torch.float64)
        res = self.grid.resolution
        c0 = self.grid.lower + 0.5 * res
        span = torch.where(n > 1, (n - 1) * res, torch.full_like(n, res))
        scale = 2.0 / span
        self.coord_scale = scale.to(device=device, dtype=dtype)
        self.coord_offset = torch.where(n > 1, -1.0 - c0 * scale, -c0 * scale).to(device=device, dtype=dtype)
        # covered box [lower, upper] in normalised coordinates: half a cell beyond the outer centres
        self._coord_bound = torch.where(n > 1, 1.0 + 1.0 / (n - 1).clamp_min(1), torch.ones_like(n)).to(
            device=device, dtype=dtype)
        self._coord_keep = (n > 1).to(device=device, dtype=dtype)  # single-cell axes sample their only cell
        self._all_multi = bool((n > 1).all())
        self._free_inp = self._free_offset.permute(2, 1, 0)[None, None].contiguous()  # (1, 1, nz, ny, nx)
        self._free_inp2d = self._free_inp[:, :, 0] if self.grid.shape[2] == 1 else None  # (1, 1, ny, nx)

    def grid_coords(self, x: torch.Tensor) -> torch.Tensor:
        """Normalised grid coordinates ``(..., 3)`` of world points ``x (..., 3)`` (for :meth:`sample_free`)."""
        return x * self.coord_scale + self.coord_offset

    def sample_free(self, g: torch.Tensor, inside_known: bool = False) -> torch.Tensor:
        """``p(free)`` at normalised grid coordinates ``g (..., 3)`` (:meth:`grid_coords`) -> ``(...)``.

        ``g (..., 2)`` (x-y only) is accepted for single-layer grids when the caller knows the points lie in
        the layer's z range (planar tasks). ``inside_known=True``: the caller guarantees every point lies in the
        covered box (skips the outside test).

        Identical to :meth:`free_probability` (trilinear, border-clamped within the covered box, 1 outside);
        takes pre-transformed coordinates so the dynamics can fuse the robot transform into one matmul.
        """
        if g.shape[-1] == 2:
            # single z layer and points known to lie in it (planar tasks): bilinear in x-y only
            if self._free_inp2d is None:
                raise ValueError("2-D grid coordinates need a workspace grid with a single z layer")
            inside = (g.abs() <= self._coord_bound[:2]).all(-1)
            out = F.grid_sample(self._free_inp2d, g.reshape(1, -1, 1, 2), mode="bilinear", padding_mode="border",
                                align_corners=True)
            return out.reshape(g.shape[:-1]) * inside + 1.0
        gk = g if self._all_multi else g * self._coord_keep
        out = F.grid_sample(self._free_inp, gk.reshape(1, -1, 1, 1, 3), mode="bilinear", padding_mode="border",
                            align_corners=True).reshape(g.shape[:-1])
        if not inside_known:
            out = out * (g.abs() <= self._coord_bound).all(-1)
        return out + 1.0

    @property
    def device(self) -> torch.device:
        return self.info.device

    def __repr__(self) -> str:
        return (f"InformationField(grid={self.grid!r}, total_info={self.total_info:.4g}, "
                f"max_info={float(self.info.max()):.4g})")

    def semantics(self, x: torch.Tensor) -> torch.Tensor:
        """``p(S_x | X)`` at world points ``x (..., 3)`` -> ``(..., 3)`` (trilinear; free outside W)."""
        x = _check_points(x)
        return self.grid.interpolate(self._probs_offset, x, outside=0.0) + self._free.to(x.dtype)

    def free_probability(self, x: torch.Tensor) -> torch.Tensor:
        """``p(S_x = free | X)`` at ``x (..., 3)`` -> ``(...)`` (trilinear; 1 outside W)."""
        return self.grid.interpolate(self._free_offset, x, outside=0.0) + 1.0

    def information(self, x: torch.Tensor) -> torch.Tensor:
        """``I~(x | X)`` at ``x (..., 3)`` -> ``(...)`` (trilinear; 0 outside W)."""
        return self.grid.interpolate(self.info, x, outside=0.0)

    def normal(self, x: torch.Tensor) -> torch.Tensor:
        """Weighted surface normal estimate ``n^`` (Alg. 7 line 11) at ``x (..., 3)`` -> ``(..., 3)``."""
        return self.grid.interpolate(self.normals, x, outside=0.0)

    def info_bounds(self, threshold: float = 0.0) -> tuple[torch.Tensor, torch.Tensor] | None:
        """Box ``(lower (3,), upper (3,))`` of the cells with ``I~ > threshold`` (cell extents), or None."""
        mask = self.info > threshold
        if not bool(mask.any()):
            return None
        return _mask_bounds(self.grid, mask, self.info.device, self.info.dtype)


def _mask_bounds(grid: VoxelGrid, mask: torch.Tensor, device, dtype):
    idx = mask.nonzero()
    lo_i = idx.min(0).values.to(torch.float64).cpu()
    hi_i = idx.max(0).values.to(torch.float64).cpu()
    lower = grid.lower + lo_i * grid.resolution
    upper = grid.lower + (hi_i + 1.0) * grid.resolution
    return lower.to(device=device, dtype=dtype), upper.to(device=device, dtype=dtype)


def compute_field(obj, poses, weights, grid: VoxelGrid, *, lam: float, free_scale: float, alpha: float,
                  sensor=None, negligible: float = 1e-4, chunk: int = 400_000) -> InformationField:
    """Evaluate Eq. 27, Eq. 23 and the Alg. 7 normal field on every cell centre of ``grid``.

    Args:
        obj: :class:`activetouch.objects.KnownObject` (uses ``sdf_world`` and ``bounds``).
        poses: ``(P, 4, 4)`` particles (object -> world); weights ``(P,)`` (normalised here).
        grid: workspace grid ``W`` (resolution ``r_w``).
        lam: ``lambda`` (Table IV: 2); free_scale ``C`` (10); alpha: Eq. 4/5 tolerance.
        sensor: sensor model with ``probs(sdf) -> (..., 3)`` (default ``SemanticSensorModel()``).
        negligible: probability below which far points are set to exactly free (see module docstring).
        chunk: maximum ``P * points`` per SDF batch (memory bound).
    """
    poses, weights = _check_particles(poses, weights)
    if not isinstance(grid, VoxelGrid):
        raise ValueError(f"grid must be a VoxelGrid, got {type(grid).__name__}")
    if lam <= 0 or free_scale <= 0:
        raise ValueError(f"lam and free_scale must be > 0, got lam={lam}, free_scale={free_scale}")
    sensor = sensor or _default_sensor()
    device, dtype = poses.device, poses.dtype
    shape = grid.shape
    pts = grid.points(device=device, dtype=dtype)  # (N, 3)
    N = pts.shape[0]

    # SIMPLIFICATION: points farther than the margin from every particle's bounding box are set to exactly
    # free / zero information without evaluating the SDF. Cost: p(surface) < negligible (1e-4) is dropped there
    # (and the normals of far particles); gain: the SDF is evaluated on the particles' neighbourhood only.
    # Near mask: points within the margin of at least one particle's (world-frame) bounding box.
    margin = field_margin(sensor, negligible)
    bounds = torch.as_tensor(obj.bounds, device=device, dtype=dtype)  # (2, 3) object frame
    corners = torch.stack(torch.meshgrid(*[bounds[:, i] for i in range(3)], indexing="ij"), -1).reshape(8, 3)
    wc = torch.einsum("pij,kj->pki", poses[:, :3, :3], corners) + poses[:, None, :3, 3]  # (P, 8, 3)
    box_lo = wc.min(1).values - margin  # (P, 3)
    box_hi = wc.max(1).values + margin
    near = torch.zeros(N, dtype=torch.bool, device=device)
    step = max(1, 2_000_000 // poses.shape[0])
    for s in range(0, N, step):
        xs = pts[s : s + step, None, :]
        near[s : s + step] = ((xs >= box_lo) & (xs <= box_hi)).all(-1).any(-1)

    probs = torch.zeros(N, 3, device=device, dtype=dtype)
    probs[:, FREE] = 1.0
    info = torch.zeros(N, device=device, dtype=dtype)
    normals = torch.zeros(N, 3, device=device, dtype=dtype)
    if bool(near.any()):
        xn = pts[near]
        p, c, n = _particle_terms(obj, poses, weights, xn, free_scale=free_scale, alpha=alpha, sensor=sensor,
                                  chunk=chunk)
        probs[near] = p
        info[near] = lam * (p * c).sum(-1)
        normals[near] = n
        active = _mask_bounds(grid, near.reshape(shape), device, dtype)
    else:
        active = (grid.lower.to(device=device, dtype=dtype), grid.lower.to(device=device, dtype=dtype))
    if not (bool(torch.isfinite(probs).all()) and bool(torch.isfinite(info).all())):
        raise ValueError("information field has non-finite values (check the object SDF and the particles)")
    return InformationField(grid=grid, probs=probs.reshape(*shape, 3), info=info.reshape(shape),
                            normals=normals.reshape(*shape, 3), active_lower=active[0], active_upper=active[1])
