"""A known rigid object: watertight mesh, exact and cached signed distance, surface samples.

Object frame convention (packaged YCB meshes, see ``assets/objects/README.md``): metres, right-handed,
+z up in the resting pose, origin at the **base centre** (x, y = centre of the axis-aligned bounding box,
z = 0 at the lowest point, so the object rests on the z = 0 plane). User meshes are taken as given
(metres assumed; a warning is logged when the size suggests millimetres).

SDF sign convention: **negative inside**, positive outside (``pytorch_volumetric``); gradients point
towards increasing SDF (outwards) and have unit norm. ``trimesh.proximity.signed_distance`` has the
opposite sign.
"""
from __future__ import annotations

import functools
import logging
from pathlib import Path

import numpy as np
import torch
import trimesh

from ..geometry.transforms import check_poses, invert, transform_points
from .sdf_cache import VoxelSDF, file_sha256

__all__ = ["KnownObject", "DEFAULT_SDF_RESOLUTION", "DEFAULT_SDF_PADDING"]

log = logging.getLogger(__name__)

#: Cell size of the cached SDF (m). Measured on the mug (walls ~1.2 mm thick above z = 4 cm): see
#: tests/test_objects.py::test_cached_sdf_matches_exact_near_surface for the error it gives.
DEFAULT_SDF_RESOLUTION = 0.001
#: Padding of the cached box around the mesh bounds (m).
DEFAULT_SDF_PADDING = 0.015


class _SDFLookup(torch.autograd.Function):
    """``values = sdf(x)`` whose backward uses the SDF gradient: ``dL/dx = dL/dv * grad sdf(x)``.

    This is how pytorch_volumetric's ``ObjectFrameSDF`` differentiates; it gives pose gradients through
    ``transform_points`` for the belief's SGD (RUMI Algorithms 4 and 5). First order only.
    """

    @staticmethod
    def forward(ctx, x, fn):
        v, g = fn(x.detach())
        ctx.save_for_backward(g)
        ctx.mark_non_differentiable(g)
        return v, g

    @staticmethod
    def backward(ctx, grad_v, grad_g):
        (g,) = ctx.saved_tensors
        return grad_v.unsqueeze(-1) * g, None


def _check_points(x, name: str = "points") -> torch.Tensor:
    if not torch.is_tensor(x):
        x = torch.as_tensor(np.asarray(x), dtype=torch.get_default_dtype())
    if not torch.is_floating_point(x):
        x = x.to(torch.get_default_dtype())
    if x.ndim < 1 or x.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (..., 3), got {tuple(x.shape)}")
    if not bool(torch.isfinite(x).all()):
        raise ValueError(f"{name} contains NaN or inf")
    return x


class KnownObject:
    """Known object model used by the belief, planners, metrics and simulator.

    Args:
        name: short name (``"mug"`` or the file stem).
        mesh: watertight ``trimesh.Trimesh`` in the object frame (metres).
        mesh_path: file the mesh was read from (its bytes key the SDF cache).
        device: default device for returned tensors (``sample_surface``, ``bounds``); SDF queries follow
            their inputs' device.
        sdf_resolution: cached SDF cell size (m).
        sdf_padding: margin of the cached SDF box around the mesh bounds (m).
        hull_dir: optional folder of convex hull meshes for :attr:`collision_hulls`.
        sdf_method: lookup of the cached SDF, ``"taylor"`` (default) or ``"linear"``.
    """

    def __init__(
        self,
        name: str,
        mesh: trimesh.Trimesh,
        mesh_path: Path,
        *,
        device=None,
        sdf_resolution: float = DEFAULT_SDF_RESOLUTION,
        sdf_padding: float = DEFAULT_SDF_PADDING,
        hull_dir: Path | None = None,
        sdf_method: str = "taylor",
    ):
        if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
            raise ValueError(f"{name}: mesh must be a non-empty trimesh.Trimesh")
        if not mesh.is_watertight:
            raise ValueError(
                f"{name}: mesh {mesh_path} is not watertight (has boundary or non-manifold edges); "
                "a signed distance needs a closed surface - repair it first (e.g. pymeshfix, manifold3d)"
            )
        if not mesh.is_winding_consistent:
            raise ValueError(f"{name}: mesh {mesh_path} has inconsistent face winding")
        if mesh.volume < 0:
            log.warning("%s: mesh faces point inwards; inverting them", name)
            mesh = mesh.copy()
            mesh.invert()
        if sdf_resolution <= 0 or sdf_padding < 0:
            raise ValueError(f"sdf_resolution must be > 0 and sdf_padding >= 0, got {sdf_resolution}, {sdf_padding}")
        self.name = name
        self.mesh = mesh
        self.mesh_path = Path(mesh_path)
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        self.sdf_resolution = float(sdf_resolution)
        self.sdf_padding = float(sdf_padding)
        if sdf_method not in ("taylor", "linear"):
            raise ValueError(f"sdf_method must be 'taylor' or 'linear', got {sdf_method!r}")
        self.sdf_method = sdf_method
        self._hull_dir = hull_dir
        self._hulls: list[trimesh.Trimesh] | None = None
        self._factory = None
        self._voxel_sdf: VoxelSDF | None = None
        ext = float(np.linalg.norm(mesh.extents))
        if ext > 3.0:
            log.warning("%s: bounding-box diagonal %.1f m - is the mesh in millimetres? activetouch uses metres", name, ext)

    def __repr__(self) -> str:
        return f"KnownObject({self.name!r}, faces={len(self.mesh.faces)}, diagonal={self.diagonal:.4f} m)"

    # ------------------------------------------------------------------ geometry
    @functools.cached_property
    def content_hash(self) -> str:
        """sha256 of the mesh file bytes (keys the SDF cache)."""
        return file_sha256(self.mesh_path)

    @property
    def bounds(self) -> torch.Tensor:
        """Axis-aligned bounds ``(2, 3)`` (min row, max row) in the object frame (m)."""
        return torch.tensor(np.array(self.mesh.bounds), dtype=torch.float32, device=self.device)

    @property
    def diagonal(self) -> float:
        """Bounding-box diagonal ``l_c`` (m), RUMI's characteristic length."""
        return float(np.linalg.norm(self.mesh.bounds[1] - self.mesh.bounds[0]))

    @functools.cached_property
    def bounding_radius(self) -> float:
        """Radius ``R`` (m) of the smallest ball about the object-frame origin that holds the mesh (max vertex
        norm): a world point farther than ``R`` from a pose's origin is outside the object in that pose."""
        return float(np.linalg.norm(np.asarray(self.mesh.vertices), axis=1).max())

    def sample_surface(self, n: int, seed: int = 0) -> torch.Tensor:
        """``n`` points uniformly (by area) on the surface, object frame ``(n, 3)`` float32; seeded."""
        if not isinstance(n, (int, np.integer)) or n < 0:
            raise ValueError(f"n must be a non-negative int, got {n!r}")
        if n == 0:
            return torch.zeros(0, 3, device=self.device)
        pts, _ = trimesh.sample.sample_surface(self.mesh, int(n), seed=int(seed))
        return torch.as_tensor(np.asarray(pts), dtype=torch.float32, device=self.device)

    @property
    def collision_hulls(self) -> list[trimesh.Trimesh]:
        """Convex pieces for collision (shipped in ``hulls/`` next to the mesh; else the single convex hull)."""
        if self._hulls is None:
            hulls: list[trimesh.Trimesh] = []
            d = self._hull_dir if self._hull_dir is not None else self.mesh_path.parent / "hulls"
            if d.is_dir():
                for p in sorted(d.iterdir()):
                    if p.suffix.lower() in (".obj", ".stl", ".ply", ".off"):
                        hulls.append(trimesh.load(p, force="mesh", process=True))
            if not hulls:
                log.warning("%s: no convex decomposition found in %s; using the single convex hull", self.name, d)
                hulls = [self.mesh.convex_hull]
            self._hulls = hulls
        return self._hulls

    # ------------------------------------------------------------------ exact SDF
    def _mesh_factory(self):
        if self._factory is None:
            import open3d as o3d
            import pytorch_volumetric as pv

            o3m = o3d.geometry.TriangleMesh(
                o3d.utility.Vector3dVector(np.asarray(self.mesh.vertices, dtype=np.float64)),
                o3d.utility.Vector3iVector(np.asarray(self.mesh.faces, dtype=np.int32)),
            )
            self._factory = pv.MeshObjectFactory(str(self.mesh_path), mesh=o3m)
        return self._factory

    def _exact_raw(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Exact SDF of ``x (..., 3)`` (no autograd) via ``pytorch_volumetric`` (open3d, CPU)."""
        shape = x.shape[:-1]
        xf = x.reshape(-1, 3)
        if xf.shape[0] == 0:
            return x.new_zeros(shape), x.new_zeros(*shape, 3)
        factory = self._mesh_factory()
        # pytorch_volumetric jitters the inside-test rays with the *global* numpy RNG: seed it for
        # reproducibility and restore the caller's state.
        state = np.random.get_state()
        np.random.seed(0)
        try:
            res = factory.object_frame_closest_point(xf.detach().to("cpu", torch.float32))
        finally:
            np.random.set_state(state)
        v = res.distance.to(device=x.device, dtype=x.dtype).reshape(shape)
        g = res.gradient.to(device=x.device, dtype=x.dtype)
        g = (g / g.norm(dim=-1, keepdim=True).clamp_min(1e-12)).reshape(*shape, 3)
        return v, g

    def sdf(self, points_obj) -> tuple[torch.Tensor, torch.Tensor]:
        """Exact signed distance ``(...)`` and unit gradient ``(..., 3)`` of object-frame points ``(..., 3)``.

        Negative inside. Differentiable w.r.t. the points (backward uses the gradient). Slow (~5 us/point).
        """
        x = _check_points(points_obj, "points_obj")
        return _SDFLookup.apply(x, self._exact_raw)

    # ------------------------------------------------------------------ cached SDF
    @property
    def voxel_sdf(self) -> VoxelSDF:
        """The cached SDF grid (built on first use, stored in the user cache dir)."""
        if self._voxel_sdf is None:
            lo = self.mesh.bounds[0] - self.sdf_padding
            up = self.mesh.bounds[1] + self.sdf_padding
            key = f"{self.name}-{self.content_hash[:16]}-r{round(self.sdf_resolution * 1e6)}um-p{round(self.sdf_padding * 1e6)}um"
            exact = lambda p: self._exact_raw(p)  # noqa: E731
            self._voxel_sdf = VoxelSDF.load_or_build(key, exact, lo, up, self.sdf_resolution)
        return self._voxel_sdf

    def cached_sdf(self, points_obj, method: str | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Voxel-cached SDF ``(...)`` and unit gradient ``(..., 3)`` of object-frame points ``(..., 3)``.

        Same sign convention as :meth:`sdf`; differentiable w.r.t. the points. ``method``: ``"taylor"``
        (nearest cell + first-order step, fastest) or ``"linear"`` (trilinear); default
        :attr:`sdf_method`. Outside the padded box: distance to the surface point closest to the clamped point (an upper bound,
        positive; see :mod:`activetouch.objects.sdf_cache`).
        """
        x = _check_points(points_obj, "points_obj")
        vs = self.voxel_sdf
        m = method or self.sdf_method
        return _SDFLookup.apply(x, lambda p: vs.query(p, m))

    def sdf_world(self, poses, x_world, exact: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """SDF of world points under each pose particle: ``sdf(T_i^-1 x)`` (the paper's ``sdf(T_i x)``).

        Args:
            poses: ``(P, 4, 4)`` object->world poses (also ``(4, 4)``).
            x_world: ``(N, 3)`` world points (or ``(P, N, 3)``: one set per pose).
            exact: use the exact mesh SDF instead of the cache.
        Returns:
            values ``(P, N)`` and object-frame unit gradients ``(P, N, 3)``. Values are differentiable
            w.r.t. ``poses`` and ``x_world``.
        """
        poses = check_poses(poses, "poses")
        x = _check_points(x_world, "x_world")
        if x.ndim < 2:
            raise ValueError(f"x_world must have shape (N, 3) or (P, N, 3), got {tuple(x.shape)}")
        x_obj = transform_points(invert(poses), x)  # finite: poses and x were checked
        if exact:
            return _SDFLookup.apply(x_obj, self._exact_raw)
        vs, m = self.voxel_sdf, self.sdf_method
        return _SDFLookup.apply(x_obj, lambda p: vs.query(p, m))

    @torch.no_grad()
    def sdf_world_values(self, poses, x_world, exact: bool = False,
                         far_positive_from: int | None = None) -> torch.Tensor:
        """Values only of :meth:`sdf_world`, without autograd: ``sdf(T_i^-1 x)`` ``(P, N)`` (``(N,)`` for one pose).

        The fast path for everything that needs no gradient (weighing, RUMI Algorithm 2; metrics): with the
        default ``sdf_method="taylor"`` it is :meth:`VoxelSDF.posed_values` (transform and lookup fused, ~3x
        faster than :meth:`sdf_world`), which gives the values of :meth:`sdf_world` up to float rounding
        (tests/test_objects.py). ``exact=True`` and ``sdf_method="linear"`` take the same route as
        :meth:`sdf_world`. Shapes as :meth:`sdf_world`; nothing here is differentiable.
        ``far_positive_from=j``: the points ``x_world[..., j:, :]`` may come back as ``+inf`` where they lie
        outside the cached box (all outside the object) instead of a finite positive distance: enough for
        free-space costs, and cheaper (see :meth:`VoxelSDF.posed_values`).
        """
        poses = check_poses(poses, "poses")
        x = _check_points(x_world, "x_world")
        if x.ndim < 2:
            raise ValueError(f"x_world must have shape (N, 3) or (P, N, 3), got {tuple(x.shape)}")
        single = poses.ndim == 2
        P = poses[None] if single else poses
        fast = (not exact and self.sdf_method == "taylor" and P.ndim == 3
                and (x.ndim == 2 or (x.ndim == 3 and x.shape[0] == P.shape[0])))
        if not fast:
            x_obj = transform_points(invert(poses), x)
            return (self._exact_raw(x_obj) if exact else self.voxel_sdf.query(x_obj, self.sdf_method))[0]
        # on the poses' device, in their dtype, like sdf_world (transform_points casts the points to the poses)
        v = self.voxel_sdf.posed_values(invert(P), x.to(P.device), far_positive_from).to(P.dtype)
        return v[0] if single and x.ndim == 2 else v
