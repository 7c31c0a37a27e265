"""Pose priors ``p(T)`` as P initial particles ``T_{0,1..P}`` (RUMI section V-B)."""
from __future__ import annotations

import math

import torch

from ..geometry import pose_from_xyz_yaw, yaw_matrix

__all__ = ["mug_prior", "gaussian_yaw_prior", "resting_face_prior", "resting_faces"]


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


def resting_faces() -> torch.Tensor:
    """The 6 rotations ``(6, 3, 3)`` that rest an object on one of its (object-frame, axis-aligned) bounding-box
    faces: each maps one of the object's +-x, +-y, +-z axes to world -z (down), about which any yaw may follow."""
    rots = []
    for axis in range(3):
        for sign in (1.0, -1.0):
            down = torch.zeros(3, dtype=torch.float64)
            down[axis] = sign  # object axis that should point down
            # rotation taking `down` to -z: Rodrigues about (down x -z)
            target = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
            v = torch.linalg.cross(down, target)
            c = float(down @ target)
            if float(v.norm()) < 1e-12:
                R = torch.eye(3, dtype=torch.float64) if c > 0 else torch.diag(torch.tensor([1.0, -1.0, -1.0],
                                                                                            dtype=torch.float64))
            else:
                K = torch.tensor([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]], dtype=torch.float64)
                R = torch.eye(3, dtype=torch.float64) + K + K @ K / (1.0 + c)
            rots.append(R)
    return torch.stack(rots)


def resting_face_prior(mean, vertices, sigma: float = 0.05, n: int = 100, table_z: float = 0.0,
                       generator: torch.Generator | None = None) -> torch.Tensor:
    """SE(3) prior ``(n, 4, 4)``: x, y ~ N(mean_xy, sigma^2), uniform yaw, and a uniformly drawn resting face.

    The paper's prior for occluded objects is "N(0, 0.05) x N(0, 0.05) x 0 and uniformly random yaw (assuming
    upright)"; for the SE(3) box tasks the diversity over which side lies on the floor then comes from CHSEL's
    quality diversity over orientation (Alg. 1 line 2). When the camera sees no surface point CHSEL has nothing
    to register and the upright-only prior could never represent a box lying on its back or side (sigma_R = 0),
    so the SE(3) prior draws each particle's resting face uniformly from the six bounding-box faces, with the
    height set so the object rests on ``table_z``.

    Args:
        mean: ``(3,)`` nominal position (its z is ignored: the height follows from the face).
        vertices: ``(V, 3)`` object-frame mesh vertices.
    """
    n = _check_n(n)
    m = _vec3(mean, "mean")
    if not math.isfinite(float(sigma)) or float(sigma) < 0:
        raise ValueError(f"sigma must be finite and >= 0, got {sigma!r}")
    verts = torch.as_tensor(vertices, dtype=torch.float64)
    faces = resting_faces()  # (6, 3, 3)
    gdev = generator.device if generator is not None else torch.device("cpu")
    face = torch.randint(0, 6, (n,), generator=generator, device=gdev).cpu()
    yaw = _uniform_yaw(n, generator, torch.float64, "cpu")
    xy = torch.randn(n, 2, generator=generator, device=gdev, dtype=torch.float64).cpu() * float(sigma)
    R = yaw_matrix(yaw) @ faces[face]  # (n, 3, 3)
    z = table_z - (verts @ R.transpose(1, 2))[..., 2].min(dim=1).values  # lowest point on the table
    T = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    T[:, :3, :3] = R
    T[:, :2, 3] = m[:2].to("cpu", torch.float64) + xy  # built on the CPU, moved to mean's device below
    T[:, 2, 3] = z
    return T.to(device=m.device, dtype=m.dtype)
