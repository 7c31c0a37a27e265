"""Next best view (visuo-tactile clutter paper ``visuo-tactile-clutter-tiqf.md``, Sec. II-D-1, Eq. 20-24) and the
stop rule shared by next best view and next best touch (Sec. II-D-2).

1. **Candidates** (:func:`hemisphere_views`): ``N`` camera positions on the upper hemisphere of radius ``radius``
   above the target's centroid ``o_centroid``. The paper says "Markov Monte-Carlo sampling"; the hemisphere cap
   is sampled directly instead: i.i.d. positions uniform in area on the cap above ``min_elevation_deg`` (height
   ``z = radius * u``, ``u ~ U(sin(min_elevation), 1)``, azimuth ``~ U(0, 2 pi)``), which needs no Markov chain.
   An optional ``reachable`` callable (the robot's kinematic workspace) filters them by rejection.
2. **Orientation** (:func:`view_rotations`, Eq. 20-21): ``h = (p_view - o_centroid) / |.|``,
   ``theta = acos(h . Z)``, ``e = h x Z / |h x Z|``. The rotation ``Rot(e, theta)`` (Rodrigues) turns ``h`` onto
   ``Z``, so its inverse ``Rot(e, -theta)`` turns ``Z`` onto ``h`` and ``-Z`` onto ``-h``, the direction from the
   camera to the centroid. The camera frame (columns right, down, forward, as :class:`PinholeCamera`) is
   therefore ``R_view = Rot(e, -theta) @ R_down`` with ``R_down = diag(1, -1, -1)``, the camera looking straight
   down (forward ``-Z``, right ``+X``, down ``-Y``; a proper rotation). Its forward axis is ``-h``: the optical
   axis points at the centroid. Straight above (``h = Z``, ``h x Z = 0``): ``theta = 0``, ``R_view = R_down``;
   straight below (``h = -Z``): ``theta = pi`` about ``X``. The roll about the optical axis is the one Eq. 21
   implies (the minimal rotation from the straight-down camera); the paper fixes no other.
3. **Rays** (:func:`view_ray_directions`): the pixel rays of each candidate in the world, from the intrinsics of
   :class:`~activetouch.sim.camera.PinholeCamera` (same pixel order and conventions) and ``R_view``.
4. **Selection** (:func:`select_next_best_view`, Eq. 24): the argmax of the expected information gain of Eq. 23
   (:func:`activetouch.information.occupancy.expected_information_gain`).
5. **Stop** (:func:`pose_change_below`): the pose estimate changed by less than ``5 mm`` and ``2 deg`` between two
   sensor acquisitions.

Not in the paper (choices, in :class:`NBVConfig`): ``num_views`` N = 50; ``radius`` = 0.45 m (limited by the
robot's workspace); ``min_elevation_deg`` = 20; the camera's 64 x 48 pixels, 55 deg vertical field of view and
1.5 m range (the range is ``d_ray``). Functions are pure: they return new tensors and modify nothing.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from activetouch.information.occupancy import OccupancyGrid, expected_information_gain
from activetouch.sim.camera import PinholeCamera

__all__ = [
    "NBVConfig",
    "hemisphere_views",
    "view_rotations",
    "view_ray_directions",
    "cameras_for",
    "select_next_best_view",
    "pose_change_below",
]

_R_DOWN = ((1.0, 0.0, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, -1.0))


@dataclass(frozen=True)
class NBVConfig:
    """Next-best-view parameters (Sec. II-D-1, II-D-2).

    Paper values: ``stop_translation`` = 5 mm, ``stop_rotation_deg`` = 2 deg (``xi^stop``).

    Not in the paper (choices): ``num_views`` (N) = 50; ``radius`` = 0.45 m (hemisphere radius, limited by the
    robot's workspace); ``min_elevation_deg`` = 20 (views lower than this graze the table); the camera model
    ``width`` x ``height`` = 64 x 48 pixels, ``fov_y_deg`` = 55, ``max_depth`` = 1.5 m (``d_ray``).
    """

    num_views: int = 50
    radius: float = 0.45
    min_elevation_deg: float = 20.0
    width: int = 64
    height: int = 48
    fov_y_deg: float = 55.0
    max_depth: float = 1.5
    stop_translation: float = 0.005
    stop_rotation_deg: float = 2.0

    def __post_init__(self):
        for name in ("num_views", "width", "height"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {v!r}")
        for name in ("radius", "min_elevation_deg", "fov_y_deg", "max_depth", "stop_translation",
                     "stop_rotation_deg"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"{name} must be a finite number, got {v!r}")
        if not self.radius > 0:
            raise ValueError(f"radius must be > 0, got {self.radius}")
        if not 0.0 <= self.min_elevation_deg < 90.0:
            raise ValueError(f"min_elevation_deg must be in [0, 90), got {self.min_elevation_deg}")
        if not 0.0 < self.fov_y_deg < 180.0:
            raise ValueError(f"fov_y_deg must be in (0, 180), got {self.fov_y_deg}")
        if not self.max_depth > 0:
            raise ValueError(f"max_depth must be > 0, got {self.max_depth}")
        if not self.stop_translation > 0:
            raise ValueError(f"stop_translation must be > 0, got {self.stop_translation}")
        if not self.stop_rotation_deg > 0:
            raise ValueError(f"stop_rotation_deg must be > 0, got {self.stop_rotation_deg}")


def _vec(x, name: str, shape: tuple, dtype=torch.float64, device=None) -> torch.Tensor:
    """``x`` as a finite float tensor; ``shape`` entries ``None`` are free."""
    t = x if isinstance(x, torch.Tensor) else torch.as_tensor(np.asarray(x, dtype=float))
    t = t.to(dtype=dtype, device=device if device is not None else t.device)
    if t.dim() != len(shape) or any(s is not None and t.shape[i] != s for i, s in enumerate(shape)):
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
        raise ValueError(f"{name} must have shape {want}, got {tuple(t.shape)}")
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name} must be finite")
    return t


def _axis_angle(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Rodrigues: rotations ``(N, 3, 3)`` by ``angle (N,)`` about unit ``axis (N, 3)``."""
    x, y, z = axis.unbind(-1)
    zero = torch.zeros_like(x)
    K = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(-1, 3, 3)
    s, c = torch.sin(angle)[:, None, None], torch.cos(angle)[:, None, None]
    eye = torch.eye(3, dtype=axis.dtype, device=axis.device).expand_as(K)
    return eye + s * K + (1 - c) * (K @ K)


def view_rotations(positions, centroid) -> torch.Tensor:
    """Camera-to-world rotations ``(N, 3, 3)`` (columns right, down, forward) of cameras at ``positions (N, 3)``
    looking at ``centroid (3,)``: Eq. 20-21 composed with the straight-down camera (module docstring, item 2).
    Float64 on the positions' device."""
    p = _vec(positions, "positions", (None, 3))
    c = _vec(centroid, "centroid", (3,), device=p.device)
    diff = p - c
    dist = diff.norm(dim=1)
    if bool((dist < 1e-9).any()):
        raise ValueError("positions must differ from centroid (Eq. 20 needs p_view != o_centroid)")
    h = diff / dist[:, None]  # Eq. 20
    Z = torch.tensor([0.0, 0.0, 1.0], dtype=p.dtype, device=p.device).expand_as(h)
    cross = torch.linalg.cross(h, Z)
    cn = cross.norm(dim=1)
    cos = (h * Z).sum(1)
    theta = torch.atan2(cn, cos)  # Eq. 21, acos(h . Z) written with atan2 for accuracy near 0 and pi
    degenerate = cn < 1e-12  # straight above (theta = 0) or below (theta = pi): any horizontal axis works
    X = torch.tensor([1.0, 0.0, 0.0], dtype=p.dtype, device=p.device).expand_as(h)
    e = torch.where(degenerate[:, None], X, cross / cn.clamp(min=1e-300)[:, None])
    theta = torch.where(degenerate, torch.where(cos > 0, torch.zeros_like(theta), torch.full_like(theta, math.pi)),
                        theta)
    R_down = torch.tensor(_R_DOWN, dtype=p.dtype, device=p.device)
    return _axis_angle(e, -theta) @ R_down


def hemisphere_views(centroid, config: NBVConfig | None, generator: torch.Generator | np.random.Generator,
                     reachable: Callable | None = None, *, max_rounds: int = 100
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """``config.num_views`` candidate views above the target: ``(positions (N, 3), rotations (N, 3, 3))``, float64.

    Positions are uniform in area on the cap of the sphere of radius ``config.radius`` about ``centroid (3,)``
    above elevation ``config.min_elevation_deg``; rotations from :func:`view_rotations` (Eq. 20-21).

    Args:
        config: :class:`NBVConfig` (``None``: the defaults).
        generator: ``torch.Generator`` or ``np.random.Generator`` (required, so runs are reproducible).
        reachable: optional ``reachable(points (M, 3) float64 tensor) -> (M,) bool`` (tensor or array): positions
            it rejects are redrawn, in batches, for at most ``max_rounds`` rounds.
    """
    cfg = config if config is not None else NBVConfig()
    if not isinstance(cfg, NBVConfig):
        raise ValueError(f"config must be an NBVConfig, got {type(config).__name__}")
    c = _vec(centroid, "centroid", (3,))
    if not isinstance(generator, (torch.Generator, np.random.Generator)):
        raise ValueError(f"generator must be a torch.Generator or np.random.Generator, got {type(generator).__name__}")
    if reachable is not None and not callable(reachable):
        raise ValueError("reachable must be callable or None")
    if int(max_rounds) < 1:
        raise ValueError(f"max_rounds must be >= 1, got {max_rounds}")

    def draw(m: int) -> torch.Tensor:
        if isinstance(generator, np.random.Generator):
            r = torch.as_tensor(generator.random((m, 2)), dtype=torch.float64)
        else:
            r = torch.rand((m, 2), generator=generator, dtype=torch.float64, device=generator.device).cpu()
        z0 = math.sin(math.radians(cfg.min_elevation_deg))
        u = z0 + (1.0 - z0) * r[:, 0]
        phi = 2 * math.pi * r[:, 1]
        s = torch.sqrt((1 - u * u).clamp(min=0.0))
        return torch.stack([s * torch.cos(phi), s * torch.sin(phi), u], 1) * cfg.radius + c.cpu()

    n = cfg.num_views
    if reachable is None:
        pos = draw(n)
    else:
        kept, total = [], 0
        for _ in range(int(max_rounds)):
            cand = draw(max(2 * n, 64))
            res = reachable(cand.to(c.device))
            ok = (res if isinstance(res, torch.Tensor) else torch.as_tensor(np.asarray(res))).cpu()
            if ok.dtype != torch.bool or tuple(ok.shape) != (cand.shape[0],):
                raise ValueError(f"reachable must return a ({cand.shape[0]},) bool array, got "
                                 f"{tuple(ok.shape)} {ok.dtype}")
            kept.append(cand[ok])
            total += int(ok.sum())
            if total >= n:
                break
        if total < n:
            raise ValueError(f"reachable accepted only {total} of {n} views in {max_rounds} rounds")
        pos = torch.cat(kept)[:n]
    pos = pos.to(c.device)
    return pos, view_rotations(pos, c)


def view_ray_directions(rotations, config: NBVConfig | None = None) -> torch.Tensor:
    """World ray directions ``(N, H*W, 3)`` (unit, row-major over pixels) of cameras with camera-to-world
    ``rotations (N, 3, 3)`` (columns right, down, forward) and the intrinsics of ``config``: the same pixel rays
    :meth:`PinholeCamera.ray_directions` gives for a camera of that rotation."""
    cfg = config if config is not None else NBVConfig()
    if not isinstance(cfg, NBVConfig):
        raise ValueError(f"config must be an NBVConfig, got {type(config).__name__}")
    R = _vec(rotations, "rotations", (None, 3, 3))
    K = PinholeCamera(pos=(0.0, 0.0, 0.0), target=(1.0, 0.0, 0.0), width=cfg.width, height=cfg.height,
                      fov_y_deg=cfg.fov_y_deg, max_depth=cfg.max_depth).intrinsics()
    u, v = np.meshgrid(np.arange(cfg.width), np.arange(cfg.height))
    pix = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=0)
    d_cam = torch.as_tensor(np.linalg.solve(K, pix), dtype=R.dtype, device=R.device)  # (3, H*W)
    d = (R @ d_cam).transpose(1, 2)
    return d / d.norm(dim=-1, keepdim=True)


def cameras_for(positions, rotations, config: NBVConfig | None = None) -> list[PinholeCamera]:
    """:class:`PinholeCamera` objects for the views ``positions (N, 3)``, ``rotations (N, 3, 3)``: each looks at
    the point ``config.radius`` along its forward axis (the centroid for :func:`hemisphere_views`' views).

    :class:`PinholeCamera` derives its own roll with ``look_at`` (right axis horizontal), so its image is turned
    about the optical axis relative to the Eq. 21 frame; the optical axis and the frustum's footprint are the
    same up to that roll. ``look_at`` cannot look exactly along the world's up axis: for such a view the target is
    moved 1e-6 m sideways (an optical-axis error of ~2e-6 rad at 0.45 m).
    """
    cfg = config if config is not None else NBVConfig()
    if not isinstance(cfg, NBVConfig):
        raise ValueError(f"config must be an NBVConfig, got {type(config).__name__}")
    p = _vec(positions, "positions", (None, 3)).cpu().numpy()
    R = _vec(rotations, "rotations", (p.shape[0], 3, 3)).cpu().numpy()
    cams = []
    for pi, Ri in zip(p, R):
        f = Ri[:, 2]
        target = pi + cfg.radius * f
        if np.linalg.norm(np.cross(f, (0.0, 0.0, 1.0))) < 1e-6:
            target = target - 1e-6 * Ri[:, 1]
        cams.append(PinholeCamera(pos=tuple(map(float, pi)), target=tuple(map(float, target)), width=cfg.width,
                                  height=cfg.height, fov_y_deg=cfg.fov_y_deg, max_depth=cfg.max_depth))
    return cams


def select_next_best_view(grid: OccupancyGrid, positions, directions, max_range: float
                          ) -> tuple[int, torch.Tensor]:
    """Eq. 24: the index of the candidate view with the largest expected information gain (Eq. 23) and the gains
    ``(N,)``. ``positions (N, 3)``, ``directions (N, R, 3)`` (e.g. :func:`view_ray_directions`) or ``(R, 3)``;
    ``max_range`` is ``d_ray``. Ties go to the lowest index."""
    p = _vec(positions, "positions", (None, 3), dtype=grid.dtype if isinstance(grid, OccupancyGrid) else None)
    if p.shape[0] == 0:
        raise ValueError("positions must hold at least one view")
    gains = expected_information_gain(grid, p, directions, max_range)
    return int(torch.argmax(gains).item()), gains


def _rotation_angle(R: torch.Tensor) -> float:
    """Angle (rad) of a rotation matrix, from ``atan2(|vee(R - R^T)| / 2, (tr R - 1) / 2)`` (accurate near 0)."""
    w = torch.stack([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return float(torch.atan2(w.norm() / 2, (torch.trace(R) - 1) / 2))


def pose_change_below(prev_pose, pose, translation: float = 0.005, rotation_deg: float = 2.0) -> bool:
    """The stop rule of Sec. II-D-2 (``xi^stop``): ``True`` when the homogeneous poses ``prev_pose (4, 4)`` and
    ``pose (4, 4)`` differ by less than ``translation`` (m, position) **and** less than ``rotation_deg``
    (the angle of ``R_prev^T R``)."""
    for name, v in (("translation", translation), ("rotation_deg", rotation_deg)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
            raise ValueError(f"{name} must be a finite number > 0, got {v!r}")
    A = _vec(prev_pose, "prev_pose", (4, 4))
    B = _vec(pose, "pose", (4, 4), device=A.device)
    dt = float((B[:3, 3] - A[:3, 3]).norm())
    ang = math.degrees(_rotation_angle(A[:3, :3].T @ B[:3, :3]))
    return dt < translation and ang < rotation_deg
