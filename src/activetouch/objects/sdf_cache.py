"""Voxel cache of an exact mesh SDF with trilinear lookup (the belief's hot path).

The exact SDF (``pytorch_volumetric.MeshSDF``, open3d closest-point + ray-parity inside test) costs about
5 us per point on one CPU core, far too slow for 100 particles x 5000 points per weighing. We precompute
signed distance and its gradient at the cell centres of a padded ``VoxelGrid`` once per
(mesh content, resolution, padding), store them in the user cache directory, and interpolate trilinearly.

Why not ``pytorch_volumetric.CachedSDF``: its cache file is keyed by a user-chosen name and defaults to
the working directory, and its lookup is a gather per corner; we need a content-hash key, a cache outside
the source tree, ``grid_sample`` speed, and a safe positive fallback outside the grid.

Outside the cached box the value is ``|x - p|`` with ``p = c - sdf(c) grad sdf(c)`` the surface point
closest to the clamped point ``c``: an upper bound of the true distance that is positive for every point
outside the padded box (as free points far from the object should be), continuous at the box faces and
exact along the closest-point direction; the gradient is ``(x - p) / |x - p|``.
"""
from __future__ import annotations

import hashlib
import logging
import os
import tempfile
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from ..geometry.voxel import VoxelGrid

__all__ = ["VoxelSDF", "cache_dir", "CACHE_FORMAT_VERSION"]

log = logging.getLogger(__name__)

CACHE_FORMAT_VERSION = 1
_ENV = "ACTIVETOUCH_CACHE_DIR"


def cache_dir() -> Path:
    """Directory for activetouch caches: ``$ACTIVETOUCH_CACHE_DIR`` or ``platformdirs.user_cache_dir("activetouch")``."""
    env = os.environ.get(_ENV)
    if env:
        return Path(env).expanduser()
    import platformdirs

    return Path(platformdirs.user_cache_dir("activetouch"))


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


class VoxelSDF:
    """Signed distance + gradient sampled at the cell centres of ``grid``.

    Args:
        grid: the voxel grid.
        data: ``(nx, ny, nz, 4)`` float32: ``[..., 0]`` signed distance (m, negative inside),
            ``[..., 1:]`` unit SDF gradient.
    """

    def __init__(self, grid: VoxelGrid, data: torch.Tensor):
        if tuple(data.shape) != grid.shape + (4,):
            raise ValueError(f"data must have shape {grid.shape + (4,)}, got {tuple(data.shape)}")
        self.grid = grid
        self.data = data.to(torch.float32).contiguous()
        self._per_device: dict[tuple, dict] = {}

    # ------------------------------------------------------------------ construction
    @classmethod
    def build(
        cls,
        exact: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]],
        lower,
        upper,
        resolution: float,
        chunk: int = 250_000,
    ) -> "VoxelSDF":
        """Evaluate ``exact(points (M, 3)) -> (values (M,), gradients (M, 3))`` at every cell centre."""
        grid = VoxelGrid(lower, upper, resolution)
        pts = grid.points(dtype=torch.float32)
        out = torch.empty(pts.shape[0], 4, dtype=torch.float32)
        try:
            from tqdm.auto import tqdm

            it = tqdm(range(0, pts.shape[0], chunk), desc=f"SDF cache {grid.shape}", disable=None, leave=False)
        except ImportError:  # pragma: no cover
            it = range(0, pts.shape[0], chunk)
        for s in it:
            v, g = exact(pts[s : s + chunk])
            out[s : s + chunk, 0] = v.to(torch.float32)
            out[s : s + chunk, 1:] = g.to(torch.float32)
        return cls(grid, out.reshape(*grid.shape, 4))

    @classmethod
    def load_or_build(
        cls,
        key: str,
        exact: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]],
        lower,
        upper,
        resolution: float,
        directory: Path | None = None,
    ) -> "VoxelSDF":
        """Load the cache file for ``key`` from ``directory`` (default :func:`cache_dir`), or build and save it."""
        directory = Path(directory) if directory is not None else cache_dir() / "sdf"
        lo = np.asarray(lower, dtype=np.float64)
        up = np.asarray(upper, dtype=np.float64)
        path = directory / f"{key}-v{CACHE_FORMAT_VERSION}.npz"
        if path.exists():
            try:
                with np.load(path) as z:
                    grid = VoxelGrid(z["lower"], z["upper_requested"], float(z["resolution"]))
                    if np.allclose(z["lower"], lo) and np.allclose(z["upper_requested"], up) and np.isclose(
                        float(z["resolution"]), resolution
                    ):
                        log.debug("loaded SDF cache %s", path)
                        return cls(grid, torch.from_numpy(z["data"]))
                log.warning("SDF cache %s does not match the requested grid; rebuilding", path)
            except Exception as e:  # corrupt / partial file: rebuild
                log.warning("could not read SDF cache %s (%s); rebuilding", path, e)
        log.info("building SDF cache %s (resolution %.4f m)", path, resolution)
        sdf = cls.build(exact, lo, up, resolution)
        try:
            directory.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=directory, suffix=".tmp.npz")
            os.close(fd)
            np.savez(
                tmp,
                data=sdf.data.numpy(),
                lower=lo,
                upper_requested=up,
                resolution=np.float64(resolution),
            )
            os.replace(tmp, path)  # atomic: concurrent readers never see a partial file
        except OSError as e:
            log.warning("could not write SDF cache %s (%s); continuing without it", path, e)
        return sdf

    # ------------------------------------------------------------------ queries
    def _consts(self, device: torch.device) -> dict:
        key = (device.type, device.index)
        if key not in self._per_device:
            g = self.grid
            big = g.num_cells >= 2**24  # float32 holds integers exactly only below 2^24
            self._per_device[key] = dict(
                data=self.data.reshape(-1, 4).to(device),
                data_grid=self.data.to(device),
                lo=g.lower.to(device=device, dtype=torch.float32),
                up=g.upper.to(device=device, dtype=torch.float32),
                c0=(g.lower + 0.5 * g.resolution).to(device=device, dtype=torch.float32),
                nmax=(torch.tensor(g.shape, dtype=torch.float32) - 1).to(device),
                strides=torch.tensor(
                    [g.shape[1] * g.shape[2], g.shape[2], 1], dtype=torch.float64 if big else torch.float32
                ).to(device),
            )
        return self._per_device[key]

    def _taylor(self, k: dict, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Nearest cell centre ``c`` plus first-order correction: ``v(x) ~ v(c) + g(c) . (x - c)``.

        ``x`` must lie in the grid box. One gather of 16 contiguous bytes per point (trilinear needs 8):
        about 2x faster than a gather-based trilinear lookup and 4x faster than ``grid_sample`` with 4
        channels on CPU. The error is second order in the cell size except next to kinks of the SDF
        (thin walls, medial axis), where it stays below half a cell diagonal.
        """
        res = self.grid.resolution
        u = torch.round((x - k["c0"]) * (1.0 / res))
        u = torch.minimum(u.clamp_(min=0.0), k["nmax"])
        idx = (u.to(k["strides"].dtype) @ k["strides"]).to(torch.long)
        d = k["data"].index_select(0, idx.reshape(-1)).reshape(*x.shape[:-1], 4)
        grad = d[..., 1:]
        c = torch.add(k["c0"], u, alpha=res)
        v = d[..., 0] + ((x - c) * grad).sum(-1)
        return v, grad

    @torch.no_grad()
    def query(self, x: torch.Tensor, method: str = "taylor") -> tuple[torch.Tensor, torch.Tensor]:
        """SDF values ``(...)`` and unit gradients ``(..., 3)`` at object-frame points ``x (..., 3)`` (no autograd).

        ``method="taylor"`` (default, fastest): nearest cell + first-order Taylor step (see :meth:`_taylor`).
        ``method="linear"``: trilinear interpolation of values and gradients (``grid_sample``; continuous,
        slower on CPU, fast on CUDA).
        """
        k = self._consts(x.device)
        xf = x.to(torch.float32)
        xc = torch.clamp(xf, min=k["lo"], max=k["up"])
        if method == "taylor":
            v, g = self._taylor(k, xc)
        elif method == "linear":
            out = self.grid.interpolate(k["data_grid"], xc, outside=None)  # (..., 4)
            v, g = out[..., 0], out[..., 1:]
            g = g / torch.linalg.vector_norm(g, dim=-1, keepdim=True).clamp_min(1e-9)
        else:
            raise ValueError(f"unknown SDF lookup method {method!r}; use 'taylor' or 'linear'")
        outside = (xf != xc).any(dim=-1)
        if bool(outside.any()):
            # Outside the box: p = xc - sdf(xc) grad(xc) is (approximately) the surface point closest to the
            # clamped point; |x - p| is an upper bound of the distance to the surface, positive, continuous
            # at the box faces, and exact when x lies along the closest-point direction.
            # dense where() instead of boolean indexing: nonzero/index_put dominate the CPU time otherwise
            d = xf - torch.addcmul(xc, g, v.unsqueeze(-1), value=-1.0)
            dist = torch.linalg.vector_norm(d, dim=-1, keepdim=True)
            v = torch.where(outside, dist.squeeze(-1), v)
            g = torch.where(outside.unsqueeze(-1), d / dist.clamp_min(1e-12), g)
        return v.to(x.dtype), g.to(x.dtype)
