"""Via-point spline trajectories (touch paper App. C, after VP-STO [26]).

``u(s) = Phi_theta(s) theta + Phi_lambda(s) lambda`` with ``u(n / N_via) = theta_n`` for the via-points
``theta_1..N_via``, ``u(0) = u_0`` and zero velocity at both ends (``lambda = [u_0, 0, 0]``). We use scipy's
``CubicSpline`` with clamped boundary conditions (first derivative 0 at ``s = 0`` and ``s = 1``): it is exactly a
cubic spline through the via-points with the boundary conditions of App. C, from a maintained library, rather
than VP-STO's own basis (which is not packaged); both give C2 piecewise cubics through the via-points.
"""
from __future__ import annotations

import numpy as np
from scipy.interpolate import CubicSpline

__all__ = ["via_point_spline", "spline_waypoints"]


def via_point_spline(u0, via_points) -> CubicSpline:
    """The spline ``u(s)``, ``s in [0, 1]``, through ``u0 (D,)`` at ``s = 0`` and the via-points ``(N_via, D)`` at
    ``s = n / N_via``, with ``du/ds = 0`` at both ends (App. C)."""
    u0 = np.asarray(u0, dtype=np.float64).reshape(-1)
    vp = np.asarray(via_points, dtype=np.float64)
    if vp.ndim != 2 or vp.shape[1] != u0.shape[0] or len(vp) < 1:
        raise ValueError(f"via_points must be (N_via, {u0.shape[0]}) with N_via >= 1, got {vp.shape}")
    if not (np.isfinite(u0).all() and np.isfinite(vp).all()):
        raise ValueError("spline start and via-points must be finite")
    knots = np.arange(len(vp) + 1, dtype=np.float64) / len(vp)
    zero = np.zeros(u0.shape[0])
    return CubicSpline(knots, np.vstack([u0, vp]), bc_type=((1, zero), (1, zero)))


def spline_waypoints(u0, via_points, n: int) -> np.ndarray:
    """``n`` waypoints ``(n, D)`` of :func:`via_point_spline` at ``s = 1/n, 2/n, ..., 1`` (the start is excluded:
    it is where the robot already is)."""
    if not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"number of waypoints must be a positive int, got {n!r}")
    s = np.arange(1, n + 1, dtype=np.float64) / n
    return via_point_spline(u0, via_points)(s)
