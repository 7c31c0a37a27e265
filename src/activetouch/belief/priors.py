"""Pose priors ``p(T)`` as P initial particles ``T_{0,1..P}`` (RUMI section V-B)."""
from __future__ import annotations

import math

import torch

from ..geometry import pose_from_xyz_yaw, yaw_matrix

__all__ = ["mug_prior", "gaussian_yaw_prior"]


def _vec3(x, name: str) -> torch.Tensor:
    t = torch.as_tensor(x)
    if not torch.is_floating_point(t):
        t = t.to(torch.get_default_dtype())
    if t.shape != (3,):
        raise ValueError(f"{name} must have shape (3,), got {tuple(t.shape)}")
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name} contains NaN or inf")
    return t


def _check_n(n) -> int:
    if not isinstance(n, int) or isinstance(n, bool) or n < 1:
        raise ValueError(f"n (number of particles) must be a positive int, got {n!r}")
    return n


def _uniform_yaw(n: int, generator, dtype, device) -> torch.Tensor:
    gdev = generator.device if generator is not None else torch.device("cpu")
    yaw = (torch.rand(n, generator=generator, device=gdev, dtype=dtype) * 2.0 - 1.0) * math.pi
    return yaw.to(device)


def mug_prior(center, n: int = 100, generator: torch.Generator | None = None, axis_offset=None) -> torch.Tensor:
    """Mug prior ``(n, 4, 4)``: the estimated mug centre and a uniform yaw in ``[-pi, pi)``.

    Args:
        center: ``(3,)`` world position of the estimated centre (e.g. a circle fit of the camera's surface
            points; z is the pose height, kept by the SE(2) filter).
        n: number of particles P.
        generator: torch generator for the yaws.
        axis_offset: optional ``(3,)`` object-frame point that ``center`` estimates (e.g. the body axis of
            the mug, which is not the mesh origin when the origin is the bounding-box centre including the
            handle). Each particle's origin is then placed so that this point lands on ``center``:
            ``t = center - Rz(yaw) axis_offset`` (z of the offset ignored). Default: the origin itself.
    """
    n = _check_n(n)
    c = _vec3(center, "center")
    yaw = _uniform_yaw(n, generator, c.dtype, c.device)
    t = c.expand(n, 3).clone()
    if axis_offset is not None:
        off = _vec3(axis_offset, "axis_offset").to(c)
        off = torch.stack([off[0], off[1], torch.zeros_like(off[2])])
        t = t - (yaw_matrix(yaw) @ off)
    return pose_from_xyz_yaw(t, yaw)


def gaussian_yaw_prior(mean, sigma: float = 0.05, n: int = 100,
                       generator: torch.Generator | None = None) -> torch.Tensor:
    """Prior ``(n, 4, 4)``: x, y ~ N(mean_xy, sigma^2) (sigma = 0.05 m in the paper), z = mean_z, yaw uniform."""
    n = _check_n(n)
    m = _vec3(mean, "mean")
    if not math.isfinite(float(sigma)) or float(sigma) < 0:
        raise ValueError(f"sigma must be finite and >= 0, got {sigma!r}")
    gdev = generator.device if generator is not None else torch.device("cpu")
    xy = torch.randn(n, 2, generator=generator, device=gdev, dtype=m.dtype).to(m.device) * float(sigma)
    t = m.expand(n, 3).clone()
    t[:, :2] = t[:, :2] + xy
    yaw = _uniform_yaw(n, generator, m.dtype, m.device)
    return pose_from_xyz_yaw(t, yaw)
