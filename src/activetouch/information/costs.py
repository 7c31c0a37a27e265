"""Per-feature discrepancy costs ``C^((x, s), T)`` of RUMI Eq. 4-6, for every semantics value at once.

The information gain field (Eq. 23) needs, for a query position ``x`` and every particle ``T_i``, the cost the
feature ``(x, s)`` *would* add to the discrepancy if it were observed with semantics ``s`` (the additivity of
Eq. 11). These are the per-point terms of the belief's discrepancy (Eq. 3); the belief package exposes the
same terms per *observed* feature (``activetouch.belief.discrepancy.point_costs``); here every semantics
value is evaluated at once for hypothetical features. Sign of alpha: the belief follows chsel 0.2.1 and uses
``alpha = -violation_tolerance`` (a free point may penetrate by the tolerance at no cost); pass that alpha
here so the field and the particle weights agree (tests/test_information.py checks they do).
"""
from __future__ import annotations

import torch

__all__ = ["per_semantics_costs"]


def per_semantics_costs(sdf: torch.Tensor, free_scale: float, alpha: float) -> torch.Tensor:
    """Cost of observing each semantics value at points with object SDF values ``sdf (...)`` -> ``(..., 3)``.

    Columns are indexed by the ``Semantics`` value (SURFACE = 0, FREE = 1, OCCUPIED = 2):

    * surface  (Eq. 6, known SDF value 0): ``|sdf|``
    * free     (Eq. 4): ``C * max(0, alpha - sdf)``
    * occupied (Eq. 5): ``C * max(0, alpha + sdf)``

    Args:
        sdf: ``(...)`` object-frame SDF values (metres) of the query points under each particle.
        free_scale: ``C`` (Table IV: 10).
        alpha: ``alpha`` of Eq. 4/5 (metres); the belief's value is ``-violation_tolerance``.
    """
    if not torch.is_tensor(sdf) or not torch.is_floating_point(sdf):
        raise ValueError("sdf must be a floating point tensor")
    surface = sdf.abs()
    free = free_scale * torch.clamp(alpha - sdf, min=0.0)
    occupied = free_scale * torch.clamp(alpha + sdf, min=0.0)
    return torch.stack([surface, free, occupied], dim=-1)
