"""Batched rigid transforms (SE(3) and its planar SE(2) subset) as ``(..., 4, 4)`` torch tensors.

Convention (docs/INTERFACES.md): a pose ``T`` maps object frame -> world frame, ``x_world = T @ x_obj``.
The RUMI paper writes ``T x`` for "world point x in the object frame of T"; here that is
``transform_points(invert(T), x)``.

Everything is differentiable with torch autograd and follows the device/dtype of its inputs.
"""
from __future__ import annotations

import math

import torch

__all__ = [
    "make_pose",
    "invert",
    "transform_points",
    "yaw_matrix",
    "pose_from_xyz_yaw",
    "yaw_of",
    "axis_angle_to_matrix",
    "perturb_transform",
    "check_poses",
    "RIGID_TOLERANCE",
]


def _as_float_tensor(x, name: str) -> torch.Tensor:
    if not torch.is_tensor(x):
        x = torch.as_tensor(x)
    if not torch.is_floating_point(x):
        x = x.to(torch.get_default_dtype())
    return x


#: Tolerance of :func:`check_poses` on ``|R R^T - I|``, ``|det R - 1|`` and the bottom row: float32 poses
#: composed over many steps stay within ~1e-5 of orthonormal; a scaled or sheared matrix is far outside.
RIGID_TOLERANCE = 1e-3


def check_poses(T, name: str = "T", rigid: bool = True, tol: float = RIGID_TOLERANCE) -> torch.Tensor:
    """Validate a pose batch: a float tensor of shape ``(..., 4, 4)`` with finite entries and, with
    ``rigid=True`` (default), rigid transforms: rotation block orthonormal with determinant +1 and bottom row
    ``[0, 0, 0, 1]``, each within ``tol`` (max absolute deviation).

    Returns the tensor (converted to float when given as a list/array). Raises ``ValueError`` naming the
    first offending pose. ``rigid=False`` checks shape and finiteness only (for general 4 x 4 matrices).
    """
    T = _as_float_tensor(T, name)
    if T.ndim < 2 or T.shape[-2:] != (4, 4):
        raise ValueError(f"{name} must have shape (..., 4, 4), got {tuple(T.shape)}")
    if not bool(torch.isfinite(T).all()):
        raise ValueError(f"{name} contains NaN or inf entries")
    if rigid and T.numel():
        with torch.no_grad():
            Tf = T.detach().reshape(-1, 4, 4)
            R = Tf[:, :3, :3]
            # one (P, 14) deviation matrix and one host sync: R R^T - I (9), det R - 1 (1), bottom row - e_4 (4)
            dev = torch.cat([(R @ R.transpose(-1, -2)).flatten(1), torch.linalg.det(R).unsqueeze(1), Tf[:, 3]], 1)
            dev.sub_(_RIGID_TARGET.to(dev)).abs_()
            worst = dev.amax(1)
            if not float(worst.max()) <= tol:  # also catches NaN
                i = int(torch.argmax(worst))
                where = f" (pose {i} of {Tf.shape[0]})" if Tf.shape[0] > 1 else ""
                raise ValueError(
                    f"{name} must be rigid transforms{where}: max |R R^T - I| = {float(dev[i, :9].max()):.3g}, "
                    f"det R = {float(torch.linalg.det(R[i])):.4g}, bottom row "
                    f"{[round(float(v), 4) for v in Tf[i, 3]]} (tolerance {tol:g})")
    return T


_RIGID_TARGET = torch.tensor([1.0, 0, 0, 0, 1, 0, 0, 0, 1, 1, 0, 0, 0, 1])


def make_pose(R, t) -> torch.Tensor:
    """Homogeneous matrix from rotation ``R (..., 3, 3)`` and translation ``t (..., 3)`` -> ``(..., 4, 4)``.

    Batch dimensions broadcast.
    """
    R = _as_float_tensor(R, "R")
    t = _as_float_tensor(t, "t").to(device=R.device, dtype=R.dtype)
    if R.ndim < 2 or R.shape[-2:] != (3, 3):
        raise ValueError(f"R must have shape (..., 3, 3), got {tuple(R.shape)}")
    if t.ndim < 1 or t.shape[-1] != 3:
        raise ValueError(f"t must have shape (..., 3), got {tuple(t.shape)}")
    batch = torch.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    R = R.expand(*batch, 3, 3)
    t = t.expand(*batch, 3)
    top = torch.cat([R, t.unsqueeze(-1)], dim=-1)  # (..., 3, 4)
    bottom = torch.zeros(*batch, 1, 4, dtype=R.dtype, device=R.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], dim=-2)


def invert(T) -> torch.Tensor:
    """Inverse of rigid transforms ``T (..., 4, 4)`` -> ``(..., 4, 4)`` using ``R^T`` (no general inverse)."""
    T = _as_float_tensor(T, "T")
    if T.ndim < 2 or T.shape[-2:] != (4, 4):
        raise ValueError(f"T must have shape (..., 4, 4), got {tuple(T.shape)}")
    Rt = T[..., :3, :3].transpose(-1, -2)
    t = T[..., :3, 3]
    return make_pose(Rt, -(Rt @ t.unsqueeze(-1)).squeeze(-1))


def transform_points(T, x) -> torch.Tensor:
    """Apply ``T (..., 4, 4)`` to points ``x (..., N, 3)`` -> ``(..., N, 3)``.

    Batch dimensions broadcast: ``T (P, 4, 4)`` with ``x (N, 3)`` gives ``(P, N, 3)``;
    ``T (4, 4)`` with ``x (N, 3)`` gives ``(N, 3)``; ``T (P, 4, 4)`` with ``x (P, N, 3)`` gives ``(P, N, 3)``.
    """
    T = _as_float_tensor(T, "T")
    x = _as_float_tensor(x, "x")
    if T.ndim < 2 or T.shape[-2:] != (4, 4):
        raise ValueError(f"T must have shape (..., 4, 4), got {tuple(T.shape)}")
    if x.ndim < 2 or x.shape[-1] != 3:
        raise ValueError(f"x must have shape (..., N, 3), got {tuple(x.shape)}")
    x = x.to(device=T.device, dtype=T.dtype)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    return x @ R.transpose(-1, -2) + t.unsqueeze(-2)


def yaw_matrix(yaw) -> torch.Tensor:
    """Rotation about +z by ``yaw (...)`` radians -> ``(..., 3, 3)``."""
    yaw = _as_float_tensor(yaw, "yaw")
    c, s = torch.cos(yaw), torch.sin(yaw)
    z, o = torch.zeros_like(yaw), torch.ones_like(yaw)
    return torch.stack(
        [torch.stack([c, -s, z], -1), torch.stack([s, c, z], -1), torch.stack([z, z, o], -1)], dim=-2
    )


def pose_from_xyz_yaw(xyz, yaw) -> torch.Tensor:
    """Pose with translation ``xyz (..., 3)`` and rotation ``yaw (...)`` about world z -> ``(..., 4, 4)``."""
    xyz = _as_float_tensor(xyz, "xyz")
    yaw = _as_float_tensor(yaw, "yaw").to(device=xyz.device, dtype=xyz.dtype)
    return make_pose(yaw_matrix(yaw), xyz)


def yaw_of(T) -> torch.Tensor:
    """Yaw (rotation about world z, in ``(-pi, pi]``) of poses ``T (..., 4, 4)`` -> ``(...)``.

    For a general SE(3) pose this is the heading of the rotated x axis projected on the xy plane.
    """
    T = _as_float_tensor(T, "T")
    if T.ndim < 2 or T.shape[-2:] != (4, 4):
        raise ValueError(f"T must have shape (..., 4, 4), got {tuple(T.shape)}")
    return torch.atan2(T[..., 1, 0], T[..., 0, 0])


def axis_angle_to_matrix(aa) -> torch.Tensor:
    """Rotation matrices ``(..., 3, 3)`` from axis-angle vectors ``aa (..., 3)`` (axis * angle), i.e. ``exp([aa]_x)``.

    Uses ``pytorch_kinematics.transforms`` (axis-angle -> quaternion -> matrix, stable at angle 0).
    """
    import pytorch_kinematics.transforms as pkt

    aa = _as_float_tensor(aa, "aa")
    if aa.shape[-1:] != (3,):
        raise ValueError(f"aa must have shape (..., 3), got {tuple(aa.shape)}")
    return pkt.quaternion_to_matrix(pkt.axis_angle_to_quaternion(aa))


def perturb_transform(
    n: int,
    sigma_t: float,
    sigma_R: float,
    se2: bool,
    generator: torch.Generator | None = None,
    device=None,
    dtype: torch.dtype | None = None,
) -> torch.Tensor:
    """Sample ``n`` random perturbation transforms ``(n, 4, 4)`` (RUMI Algorithm 3, PerturbTransform).

    ``dt ~ N(0, sigma_t^2 I)``, ``theta ~ N(0, sigma_R^2)`` (``sigma_R`` is a standard deviation in
    radians), axis ``e`` uniform on the unit sphere, ``dR = exp(theta e)``, ``dT = [[dR, dt], [0, 1]]``.

    With ``se2=True`` (poses restricted to x, y, yaw) the axis is world +z and the z translation is 0,
    so composing ``dT @ T`` keeps the pose's z axis and height unchanged.

    Random numbers are drawn on the generator's device (CPU by default) so results are reproducible for
    a given seed, then moved to ``device``.
    """
    if not isinstance(n, int) or n < 0:
        raise ValueError(f"n must be a non-negative int, got {n!r}")
    for nm, v in (("sigma_t", sigma_t), ("sigma_R", sigma_R)):
        if not math.isfinite(float(v)) or float(v) < 0:
            raise ValueError(f"{nm} must be finite and >= 0, got {v!r}")
    dtype = dtype or torch.get_default_dtype()
    gdev = generator.device if generator is not None else torch.device("cpu")
    dt = torch.randn(n, 3, generator=generator, device=gdev, dtype=dtype) * float(sigma_t)
    theta = torch.randn(n, generator=generator, device=gdev, dtype=dtype) * float(sigma_R)
    if se2:
        dt[:, 2] = 0.0
        R = yaw_matrix(theta)
    else:
        e = torch.randn(n, 3, generator=generator, device=gdev, dtype=dtype)
        e = e / e.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        R = axis_angle_to_matrix(e * theta.unsqueeze(-1))
    T = make_pose(R, dt)
    if device is not None:
        T = T.to(device)
    return T
