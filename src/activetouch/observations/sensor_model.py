"""Semantic sensor model ``p(S | sdf)`` (RUMI section V-E, Fig. 2)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

__all__ = ["SemanticSensorModel"]


@dataclass(frozen=True)
class SemanticSensorModel:
    """``p(S_x | sdf(T x))`` for the three semantics (RUMI section V-E, READING-NOTES).

    With ``v`` the SDF value (m) and ``v~ = sign(v) max(0, |v| - zeta)`` (``sign(0) = -1``):
    ``p(free) = max(0, 1 - exp(-alpha v~))``, ``p(occupied) = max(0, 1 - exp(alpha v~))``,
    ``p(surface) = exp(-alpha |v~|)``; they sum to 1 for every ``v``.

    Args:
        zeta: half-width of the band around the surface where ``surface`` has probability 1 (m), 3 mm.
        alpha: decay rate (1/m), 100.
    """

    zeta: float = 0.003
    alpha: float = 100.0

    def __post_init__(self):
        if not (math.isfinite(self.zeta) and self.zeta >= 0):
            raise ValueError(f"zeta must be finite and >= 0, got {self.zeta}")
        if not (math.isfinite(self.alpha) and self.alpha > 0):
            raise ValueError(f"alpha must be finite and > 0, got {self.alpha}")

    def probs(self, sdf) -> torch.Tensor:
        """Probabilities ``(..., 3)`` of (SURFACE, FREE, OCCUPIED) — indexed by ``Semantics`` value — for ``sdf (...)``.

        Differentiable w.r.t. ``sdf``. Raises ``ValueError`` on NaN (``+-inf`` are fine: certain free/occupied).
        """
        v = sdf if torch.is_tensor(sdf) else torch.as_tensor(sdf, dtype=torch.get_default_dtype())
        if not torch.is_floating_point(v):
            v = v.to(torch.get_default_dtype())
        if bool(torch.isnan(v).any()):
            raise ValueError("sensor model got NaN sdf values")
        mag = (v.abs() - self.zeta).clamp_min(0.0)
        pos = v > 0
        # p(surface) = exp(-alpha |v~|); the other class gets 1 - p(surface), the third 0.
        p_s = torch.exp(-self.alpha * mag)
        rest = -torch.expm1(-self.alpha * mag)  # 1 - exp(-alpha |v~|), accurate near 0
        zero = torch.zeros_like(rest)
        p_free = torch.where(pos, rest, zero)
        p_occ = torch.where(pos, zero, rest)
        return torch.stack([p_s, p_free, p_occ], dim=-1)

    def log_probs(self, sdf) -> torch.Tensor:
        """``log`` of :meth:`probs` (``-inf`` where a probability is exactly 0)."""
        return torch.log(self.probs(sdf))
