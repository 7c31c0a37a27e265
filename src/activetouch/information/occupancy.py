"""Occupancy grid of the target's region and the expected information gain of a view (visuo-tactile clutter
paper ``visuo-tactile-clutter-tiqf.md``, Sec. II-D-1, Eq. 19, 22, 23).

Each cell ``c_i`` of the grid ``OG`` is an independent Bernoulli variable stored as log-odds
``l_i = log p(c_i) / (1 - p(c_i))``. A depth measurement updates every cell its ray traverses with the miss
log-odds and the cell of the measured point with the hit log-odds (Eq. 22, ``p_h = 0.7``, ``p_m = 0.4``),
clamped as in OctoMap [36]. The grid's entropy is the sum of the cells' Bernoulli entropies (Eq. 19, natural
log), and a view's expected information gain is the entropy drop when its *predicted* measurement is
integrated (Eq. 23).

Representation. The paper uses the OctoMap library. Its Python bindings do not install cleanly here, so this is
a **dense** torch tensor ``log_odds (X, Y, Z)`` over the axis-aligned box of the target's region (built with
:func:`region_around` from the segmented target cloud). Cost: memory and every update are O(number of cells),
not O(observed cells) as in an octree: a 30 cm box holds 27 000 cells at 1 cm and 216 000 at 5 mm (about
0.1 / 0.9 MB in float32), which is small; a whole-workspace map at these resolutions would not be. The tensors
live on the device the grid was built on (CPU by default, CUDA when given); every computation follows them.

Ray traversal. Both the update and the prediction use an **exact voxel traversal** (Amanatides & Woo), batched
over rays in torch with no Python loop over rays: a ray's cells are its start cell plus the cell it enters at
each crossing of a grid plane, and the crossings along each axis are generated in closed form from the start
and end cells. It is preferred over sampling every ``resolution / 2`` because sampling skips cells whose corner
the ray clips and visits cells in a way that depends on where the samples fall, while the traversal visits
exactly the cells the ray passes through at the same cost (one entry per plane crossing). Cells touched only at
a single corner or edge point (measure zero) may or may not be counted. Rays are clipped to the grid: the part
outside the box updates nothing.

Choices where the paper is silent (each says what it costs):

* ``resolution`` (the paper's ``g_res``) is not given; 1 cm by default (the camera's free points are thinned to
  1 cm cells elsewhere in this package). Finer cells cost memory and time as above.
* Clamping ``p_min = 0.12``, ``p_max = 0.97``: OctoMap's default clamping thresholds (the paper uses OctoMap
  but gives none). They bound how certain a cell can become, so repeated hits saturate at ``p_max``.
* In one :meth:`OccupancyGrid.integrate` call a cell is updated at most once **per ray** (a ray crossing a cell
  twice by float ties counts once; its end cell is a hit, not also a miss), but once for every ray that
  traverses it. The updates of all rays of one call are summed and clamped once, so a call does not depend on
  the order of its rays. OctoMap's ``insertPointCloud`` instead updates each cell once per scan; per-ray counting
  makes a cell crossed by many rays of one scan saturate in one call.
* The predicted measurement of a ray (Eq. 23) ends at the first cell whose occupancy probability exceeds 0.5
  (predicted hit); otherwise the ray runs to ``max_range`` or the grid's edge (predicted miss). Since a ray stops
  at the first occupied cell, every traversed cell with ``p > 0.5`` is a predicted hit and every other traversed
  cell a predicted miss, whichever ray reaches it: the predicted posterior of a cell depends only on its own
  state. Each cell reached by some ray of a view is counted **once per view** (one Eq. 22 update), however many
  rays cross it, so a view's gain measures how much uncertain space it covers and does not grow with the
  number of pixels that see the same cell (OctoMap's once-per-scan update).

A property of Eq. 22-23 to know when reading gains: the Bernoulli entropy is flat at ``p = 0.5``, so one miss
on an unknown cell (0.5 -> 0.4) removes only 0.020 nats, less than the second (0.4 -> 0.31: 0.056) or third
(0.080) miss on the same cell; the gain falls to 0 only at the clamp. A view that re-observes a region seen once
can therefore out-score a view of never-seen space until the seen region has been observed a few times.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

__all__ = [
    "OccupancyConfig",
    "OccupancyGrid",
    "bernoulli_entropy",
    "expected_information_gain",
    "region_around",
]


def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))


@dataclass(frozen=True)
class OccupancyConfig:
    """Occupancy grid parameters (Sec. II-D-1).

    Paper values: ``p_hit = 0.7``, ``p_miss = 0.4`` (Eq. 22, "as in [36]").

    Not in the paper (choices): ``resolution`` (``g_res``) = 0.01 m; ``p_prior = 0.5`` (unknown cells);
    clamping ``p_min = 0.12``, ``p_max = 0.97`` (OctoMap's defaults); ``max_range`` (m): a measured ray longer
    than this is cut at ``max_range`` and its end is not a hit (OctoMap's ``maxrange``); ``None``: no limit.
    """

    resolution: float = 0.01
    p_hit: float = 0.7
    p_miss: float = 0.4
    p_prior: float = 0.5
    p_min: float = 0.12
    p_max: float = 0.97
    max_range: float | None = None

    def __post_init__(self):
        def real(name):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"{name} must be a finite number, got {v!r}")
            return float(v)

        if not real("resolution") > 0:
            raise ValueError(f"resolution must be > 0, got {self.resolution}")
        if not 0.5 < real("p_hit") < 1.0:
            raise ValueError(f"p_hit must be in (0.5, 1), got {self.p_hit}")
        if not 0.0 < real("p_miss") < 0.5:
            raise ValueError(f"p_miss must be in (0, 0.5), got {self.p_miss}")
        if not 0.0 < real("p_min") < 0.5:
            raise ValueError(f"p_min must be in (0, 0.5), got {self.p_min}")
        if not 0.5 < real("p_max") < 1.0:
            raise ValueError(f"p_max must be in (0.5, 1), got {self.p_max}")
        if not self.p_min <= real("p_prior") <= self.p_max:
            raise ValueError(f"p_prior must be in [p_min, p_max] = [{self.p_min}, {self.p_max}], got {self.p_prior}")
        if self.max_range is not None and not real("max_range") > 0:
            raise ValueError(f"max_range must be > 0 or None, got {self.max_range}")

    @property
    def l_hit(self) -> float:
        """Eq. 22, hit: ``log p_h / (1 - p_h)`` (> 0)."""
        return _logit(self.p_hit)

    @property
    def l_miss(self) -> float:
        """Eq. 22, miss: ``log p_m / (1 - p_m)`` (< 0)."""
        return _logit(self.p_miss)

    @property
    def l_min(self) -> float:
        return _logit(self.p_min)

    @property
    def l_max(self) -> float:
        return _logit(self.p_max)

    @property
    def l_prior(self) -> float:
        return _logit(self.p_prior)


def bernoulli_entropy(log_odds: torch.Tensor) -> torch.Tensor:
    """Entropy (nats) of Bernoulli cells given their log-odds, elementwise (the summand of Eq. 19):
    ``-(p log p + (1 - p) log(1 - p))`` with ``p = sigmoid(l)``, written as ``p softplus(-l) + (1-p) softplus(l)``
    so it stays finite at any ``l``."""
    p = torch.sigmoid(log_odds)
    return p * torch.nn.functional.softplus(-log_odds) + (1 - p) * torch.nn.functional.softplus(log_odds)


def _as_tensor(x, name: str, shape_tail: tuple, device, dtype, allow_batch: bool = False) -> torch.Tensor:
    """``x`` as a finite ``dtype`` tensor on ``device`` whose trailing shape is ``shape_tail``."""
    try:
        t = torch.as_tensor(np.asarray(x) if not isinstance(x, torch.Tensor) else x)
    except Exception as e:  # noqa: BLE001
        raise ValueError(f"{name} must be array-like, got {type(x).__name__}") from e
    t = t.to(device=device, dtype=dtype)
    nd = len(shape_tail)
    ok = t.dim() == nd or (allow_batch and t.dim() == nd + 1)
    ok = ok and all(s is None or t.shape[t.dim() - nd + i] == s for i, s in enumerate(shape_tail))
    if not ok:
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape_tail) + ("," if nd == 1 else "") + ")"
        raise ValueError(f"{name} must have shape {want}{' (or batched)' if allow_batch else ''}, "
                         f"got {tuple(t.shape)}")
    if t.is_floating_point() and not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name} must be finite")
    return t


def region_around(points, margin: float = 0.05) -> tuple[torch.Tensor, torch.Tensor]:
    """The grid box around a segmented target cloud: ``points (N, 3)`` -> ``(lower (3,), upper (3,))``, the cloud's
    axis-aligned bounds grown by ``margin`` (m) on every side. Float64 tensors on the points' device."""
    if isinstance(margin, bool) or not isinstance(margin, (int, float)) or not math.isfinite(margin) or margin < 0:
        raise ValueError(f"margin must be a finite number >= 0, got {margin!r}")
    dev = points.device if isinstance(points, torch.Tensor) else None
    p = _as_tensor(points, "points", (None, 3), dev, torch.float64)
    if p.shape[0] == 0:
        raise ValueError("points must not be empty")
    lower, upper = p.amin(0) - margin, p.amax(0) + margin
    if margin == 0 and bool((upper <= lower).any()):
        raise ValueError("points span zero extent along some axis: give margin > 0")
    return lower, upper


class _Traversal:
    """Cells traversed by a batch of rays: ``lin (B, W)`` linear cell indices, ``t (B, W)`` the distance at
    which the ray enters each cell, ``mask (B, W)`` which entries are real; ``end_lin (B,)`` the last cell
    before the clipped end, ``valid (B,)`` whether the ray meets the grid at all."""

    __slots__ = ("lin", "t", "mask", "end_lin", "valid")

    def __init__(self, lin, t, mask, end_lin, valid):
        self.lin, self.t, self.mask, self.end_lin, self.valid = lin, t, mask, end_lin, valid


def _dir_floor(u: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Index of the cell a ray occupies just *after* coordinate ``u`` (in cell units) moving along ``d``."""
    return torch.where(d < 0, torch.ceil(u) - 1, torch.floor(u))


def _dir_floor_before(u: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Index of the cell a ray occupies just *before* reaching coordinate ``u`` moving along ``d``."""
    return torch.where(d > 0, torch.ceil(u) - 1, torch.floor(u))


def _traverse(lower: torch.Tensor, res: float, dims: torch.Tensor, o: torch.Tensor, d: torch.Tensor,
              length: torch.Tensor) -> _Traversal:
    """Exact voxel traversal of rays ``o + t d``, ``t in [0, length]`` (``o, d (B, 3)``, ``d`` unit or zero,
    ``length (B,)``), clipped to the box ``[lower, lower + dims * res]``."""
    B = o.shape[0]
    upper = lower + dims.to(o.dtype) * res
    zero = d == 0
    safe_d = torch.where(zero, torch.ones_like(d), d)
    t1, t2 = (lower - o) / safe_d, (upper - o) / safe_d
    inside_ax = (o >= lower) & (o <= upper)
    inf = torch.full_like(o, math.inf)
    tmin = torch.where(zero, torch.where(inside_ax, -inf, inf), torch.minimum(t1, t2))
    tmax = torch.where(zero, torch.where(inside_ax, inf, -inf), torch.maximum(t1, t2))
    t_enter = tmin.amax(1).clamp(min=0.0)
    t_exit = torch.minimum(tmax.amin(1), length)
    valid = (t_enter < t_exit) | ((length == 0) & inside_ax.all(1))
    t_enter = torch.where(valid, t_enter, torch.zeros_like(t_enter))
    t_exit = torch.where(valid, t_exit, torch.zeros_like(t_exit))
    hi = (dims - 1).to(o.dtype)
    u0 = (o + d * t_enter[:, None] - lower) / res
    u1 = (o + d * t_exit[:, None] - lower) / res
    i0 = torch.minimum(_dir_floor(u0, d).clamp(min=0.0), hi)  # (B, 3) start cell
    i1 = torch.minimum(_dir_floor_before(u1, d).clamp(min=0.0), hi)  # (B, 3) end cell
    n = ((i1 - i0) * torch.sign(d)).clamp(min=0.0) * valid[:, None]  # plane crossings per axis
    idx_parts, t_parts, m_parts = [i0[:, None, :]], [t_enter[:, None]], [valid[:, None]]
    for a in range(3):
        m_max = int(n[:, a].max().item()) if B else 0
        if m_max == 0:
            continue
        m = torch.arange(1, m_max + 1, device=o.device, dtype=o.dtype)[None, :]  # (1, M)
        pos = d[:, a:a + 1] > 0
        entered = torch.where(pos, i0[:, a:a + 1] + m, i0[:, a:a + 1] - m)  # (B, M) index along a
        plane = torch.where(pos, entered, entered + 1)
        t = (lower[a] + plane * res - o[:, a:a + 1]) / safe_d[:, a:a + 1]
        u = (o[:, None, :] + d[:, None, :] * t[..., None] - lower) / res  # (B, M, 3)
        idx = torch.minimum(_dir_floor(u, d[:, None, :]).clamp(min=0.0), hi)
        idx[..., a] = entered.clamp(min=0.0, max=float(hi[a]))
        idx_parts.append(idx)
        t_parts.append(t)
        m_parts.append(m <= n[:, a:a + 1])
    idx = torch.cat(idx_parts, 1).long()
    strides = torch.stack([dims[1] * dims[2], dims[2], torch.ones_like(dims[2])]).to(idx)
    lin = (idx * strides).sum(-1)
    end_lin = (i1.long() * strides).sum(-1)
    return _Traversal(lin, torch.cat(t_parts, 1), torch.cat(m_parts, 1), end_lin, valid)


class OccupancyGrid:
    """Dense 3-D occupancy grid of the box ``[lower, upper]`` (Sec. II-D-1).

    Args:
        lower, upper: ``(3,)`` corners (m). The grid has ``ceil((upper - lower) / resolution - 1e-4)`` cells per axis;
            ``self.upper`` is moved up to ``lower + shape * resolution``.
        config: :class:`OccupancyConfig`.
        device, dtype: of ``log_odds`` and of every computation on the grid (``None``: the device of ``lower``
            when it is a tensor, else CPU; float32).

    Attributes:
        log_odds: ``(X, Y, Z)`` tensor, every cell at ``config.p_prior`` initially. Cell ``(i, j, k)`` covers
            ``lower + [i, i+1) x [j, j+1) x [k, k+1) * resolution``.
    """

    def __init__(self, lower, upper, config: OccupancyConfig | None = None, *, device=None,
                 dtype: torch.dtype = torch.float32):
        self.config = config if config is not None else OccupancyConfig()
        if not isinstance(self.config, OccupancyConfig):
            raise ValueError(f"config must be an OccupancyConfig, got {type(config).__name__}")
        if dtype not in (torch.float32, torch.float64):
            raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
        if device is None:
            device = lower.device if isinstance(lower, torch.Tensor) else torch.device("cpu")
        lo = _as_tensor(lower, "lower", (3,), device, torch.float64)
        up = _as_tensor(upper, "upper", (3,), device, torch.float64)
        if bool((up <= lo).any()):
            raise ValueError(f"upper must exceed lower on every axis, got lower={lo.tolist()}, upper={up.tolist()}")
        res = self.config.resolution
        # 1e-4 of a cell of slack: float32 corners (0.1f = 0.1000000015) must not add a cell that a float64 box lacks
        shape = torch.ceil((up - lo) / res - 1e-4).clamp(min=1).long()
        self.resolution = res
        self.shape = tuple(int(s) for s in shape.tolist())
        self.dims = shape
        self.lower = lo.to(dtype)
        self.upper = (lo + shape.to(torch.float64) * res).to(dtype)
        self.log_odds = torch.full(self.shape, self.config.l_prior, device=device, dtype=dtype)

    # ---- properties --------------------------------------------------------------------------------------------
    @property
    def device(self) -> torch.device:
        return self.log_odds.device

    @property
    def dtype(self) -> torch.dtype:
        return self.log_odds.dtype

    @property
    def n_cells(self) -> int:
        return self.log_odds.numel()

    def clone(self) -> "OccupancyGrid":
        """An independent copy (same box, config, device; copied log-odds)."""
        g = object.__new__(OccupancyGrid)
        g.config, g.resolution, g.shape, g.dims = self.config, self.resolution, self.shape, self.dims
        g.lower, g.upper, g.log_odds = self.lower, self.upper, self.log_odds.clone()
        return g

    def prob(self) -> torch.Tensor:
        """Occupancy probabilities ``p(c_i)``, ``(X, Y, Z)``."""
        return torch.sigmoid(self.log_odds)

    def cell_entropy(self) -> torch.Tensor:
        """Per-cell Bernoulli entropy (nats), ``(X, Y, Z)`` (the summand of Eq. 19)."""
        return bernoulli_entropy(self.log_odds)

    def entropy(self) -> torch.Tensor:
        """Entropy of the whole grid, Eq. 19 (natural log, cells independent): a 0-d tensor."""
        return self.cell_entropy().sum()

    def cell_centers(self) -> torch.Tensor:
        """World coordinates of the cell centres, ``(X, Y, Z, 3)``."""
        axes = [self.lower[a] + (torch.arange(self.shape[a], device=self.device, dtype=self.dtype) + 0.5)
                * self.resolution for a in range(3)]
        return torch.stack(torch.meshgrid(*axes, indexing="ij"), -1)

    def index_of(self, points) -> torch.Tensor:
        """Cell indices ``(N, 3)`` (long) of world ``points (N, 3)``; ``-1`` rows for points outside the grid."""
        p = _as_tensor(points, "points", (None, 3), self.device, self.dtype)
        idx = torch.floor((p - self.lower) / self.resolution).long()
        inside = ((idx >= 0) & (idx < self.dims)).all(1)
        return torch.where(inside[:, None], idx, torch.full_like(idx, -1))

    # ---- update (Eq. 22) ---------------------------------------------------------------------------------------
    def integrate(self, origin, endpoints, hit) -> "OccupancyGrid":
        """Integrate one depth measurement (Eq. 22), in place; returns ``self``.

        Args:
            origin: ``(3,)`` sensor position (may lie outside the grid).
            endpoints: ``(N, 3)`` ray ends: the measured points; for rays that hit nothing, the max-range point.
            hit: ``(N,)`` bool: the endpoint is a measured surface point.

        Every cell the segment origin -> endpoint traverses inside the grid gets ``l_miss`` once; the endpoint's
        cell gets ``l_hit`` instead when ``hit`` and the endpoint lies inside the grid (a ray clipped by the grid's
        edge only frees cells). With ``config.max_range``, longer rays are cut there and end as misses. All the
        rays' updates are summed, then the log-odds are clamped to ``[logit p_min, logit p_max]``.
        """
        cfg = self.config
        o = _as_tensor(origin, "origin", (3,), self.device, self.dtype)
        e = _as_tensor(endpoints, "endpoints", (None, 3), self.device, self.dtype)
        h = torch.as_tensor(np.asarray(hit) if not isinstance(hit, torch.Tensor) else hit, device=self.device)
        if h.dtype != torch.bool:
            raise ValueError(f"hit must be a bool array, got dtype {h.dtype}")
        if tuple(h.shape) != (e.shape[0],):
            raise ValueError(f"hit must have shape ({e.shape[0]},) like endpoints, got {tuple(h.shape)}")
        if e.shape[0] == 0:
            return self
        vec = e - o
        length = vec.norm(dim=1)
        d = torch.where(length[:, None] > 0, vec / length.clamp(min=1e-30)[:, None], torch.zeros_like(vec))
        if cfg.max_range is not None:
            cut = length > cfg.max_range
            h = h & ~cut
            length = length.clamp(max=cfg.max_range)
            e = o + d * length[:, None]
        trav = _traverse(self.lower, self.resolution, self.dims, o.expand_as(e), d, length)
        n = self.n_cells
        end_hit = h & ((e >= self.lower) & (e <= self.upper)).all(1)
        # a ray that only touches the grid at its endpoint (on the boundary) traverses nothing: its hit goes
        # to the cell containing the endpoint
        hi = self.dims - 1
        e_idx = torch.minimum(torch.floor((e - self.lower) / self.resolution).long().clamp(min=0), hi)
        e_lin = (e_idx[:, 0] * self.shape[1] + e_idx[:, 1]) * self.shape[2] + e_idx[:, 2]
        end_lin = torch.where(trav.valid, trav.end_lin, e_lin)
        miss = trav.mask & ~(end_hit[:, None] & (trav.lin == end_lin[:, None]))
        lin = torch.where(miss, trav.lin, torch.full_like(trav.lin, n))
        lin, _ = torch.sort(lin, dim=1)
        first = torch.ones_like(lin, dtype=torch.bool)
        first[:, 1:] = lin[:, 1:] != lin[:, :-1]
        keep = first & (lin < n)
        delta = torch.zeros(n, device=self.device, dtype=self.dtype)
        delta.index_add_(0, lin[keep], torch.full((int(keep.sum()),), cfg.l_miss, device=self.device,
                                                  dtype=self.dtype))
        ends = end_lin[end_hit]
        delta.index_add_(0, ends, torch.full((ends.numel(),), cfg.l_hit, device=self.device, dtype=self.dtype))
        flat = (self.log_odds.reshape(-1) + delta).clamp(cfg.l_min, cfg.l_max)
        self.log_odds = flat.reshape(self.shape)
        return self

    # ---- prediction (Eq. 23) -----------------------------------------------------------------------------------
    def predicted_cell_gain(self) -> torch.Tensor:
        """Entropy drop of each cell under its predicted measurement, ``(X, Y, Z)`` (the summand of Eq. 23).

        A cell with ``p > 0.5`` is a predicted hit (``l + l_hit``), any other a predicted miss (``l + l_miss``),
        clamped. The clamp never moves a cell against its update (a cell already beyond a bound keeps its
        value), so every gain is >= 0.
        """
        cfg, l = self.config, self.log_odds
        up = torch.maximum(l, torch.clamp(l + cfg.l_hit, max=cfg.l_max))
        down = torch.minimum(l, torch.clamp(l + cfg.l_miss, min=cfg.l_min))
        after = torch.where(l > 0, up, down)
        return (bernoulli_entropy(l) - bernoulli_entropy(after)).clamp(min=0.0)


def expected_information_gain(grid: OccupancyGrid, origin, directions, max_range: float, *,
                              max_rays_per_chunk: int = 65536) -> torch.Tensor:
    """Expected information gain of candidate views (Eq. 23), ``(V,)`` on the grid's device and dtype.

    Args:
        grid: the current :class:`OccupancyGrid` (not modified).
        origin: ``(3,)`` (one position for all views) or ``(V, 3)`` camera positions.
        directions: ``(V, R, 3)`` per-view ray directions or ``(R, 3)`` shared by all views (normalised here;
            zero rows are rejected).
        max_range: the sensor's range ``d_ray`` (m).
        max_rays_per_chunk: views are processed in chunks of at most this many rays (memory bound only).

    Each ray's predicted measurement comes from a traversal of the current grid: it ends at the first cell
    with occupancy probability > 0.5 (predicted hit) or at ``max_range`` / the grid's edge (predicted miss).
    The gain of a view is ``sum_i H(p(c_i)) - H(p(c_i | a, z^))`` over the cells its rays reach, each cell counted
    once per view (module docstring), with the Eq. 22 posterior of :meth:`OccupancyGrid.predicted_cell_gain`.
    """
    if not isinstance(grid, OccupancyGrid):
        raise ValueError(f"grid must be an OccupancyGrid, got {type(grid).__name__}")
    if isinstance(max_range, bool) or not isinstance(max_range, (int, float)) or not (
            math.isfinite(max_range) and max_range > 0):
        raise ValueError(f"max_range must be a finite number > 0, got {max_range!r}")
    if int(max_rays_per_chunk) < 1:
        raise ValueError(f"max_rays_per_chunk must be >= 1, got {max_rays_per_chunk}")
    dev, dt = grid.device, grid.dtype
    o = _as_tensor(origin, "origin", (3,), dev, dt, allow_batch=True)
    dirs = _as_tensor(directions, "directions", (None, 3), dev, dt, allow_batch=True)
    V = None
    if o.dim() == 2:
        V = o.shape[0]
    if dirs.dim() == 3:
        if V is not None and dirs.shape[0] != V:
            raise ValueError(f"directions has {dirs.shape[0]} views but origin has {V}")
        V = dirs.shape[0]
    if V is None:
        V = 1
    if V == 0:
        return torch.zeros(0, device=dev, dtype=dt)
    o = o.expand(V, 3) if o.dim() == 1 else o
    dirs = dirs.expand(V, *dirs.shape) if dirs.dim() == 2 else dirs
    R = dirs.shape[1]
    if R == 0:
        raise ValueError("directions must hold at least one ray")
    norm = dirs.norm(dim=-1, keepdim=True)
    if bool((norm == 0).any()):
        raise ValueError("directions must not contain zero vectors")
    dirs = dirs / norm
    n = grid.n_cells
    gain = grid.predicted_cell_gain().reshape(-1)
    occupied = grid.log_odds.reshape(-1) > 0
    out = torch.zeros(V, device=dev, dtype=dt)
    step = max(1, int(max_rays_per_chunk) // R)
    for s in range(0, V, step):
        vc = min(step, V - s)
        oo = o[s:s + vc, None, :].expand(vc, R, 3).reshape(-1, 3)
        dd = dirs[s:s + vc].reshape(-1, 3)
        length = torch.full((vc * R,), float(max_range), device=dev, dtype=dt)
        trav = _traverse(grid.lower, grid.resolution, grid.dims, oo, dd, length)
        occ = trav.mask & occupied[trav.lin]
        t_hit = torch.where(occ, trav.t, torch.full_like(trav.t, math.inf)).amin(1, keepdim=True)
        keep = trav.mask & (trav.t <= t_hit)
        view = torch.arange(vc, device=dev).repeat_interleave(R)[:, None].expand_as(trav.lin)
        touched = torch.zeros(vc * n, device=dev, dtype=torch.bool)
        touched[(view * n + trav.lin)[keep]] = True
        out[s:s + vc] = touched.reshape(vc, n).to(dt) @ gain
    return out
