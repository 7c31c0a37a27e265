"""Geometric features: observed positions with semantics (RUMI section III: ``X = {(x, s)}``)."""
from __future__ import annotations

import enum
from typing import Iterable, Sequence

import numpy as np
import torch

__all__ = ["Semantics", "Features"]


class Semantics(enum.IntEnum):
    """Semantics of a geometric feature; values match ``chsel.SemanticsClass``."""

    SURFACE = 0
    FREE = 1
    OCCUPIED = 2


_N_SEM = len(Semantics)


def _to_positions(positions, device=None) -> torch.Tensor:
    if not torch.is_tensor(positions):
        positions = torch.as_tensor(np.asarray(positions, dtype=np.float32))
    if not torch.is_floating_point(positions):
        positions = positions.to(torch.float32)
    if device is not None:
        positions = positions.to(device)
    if positions.ndim == 1 and positions.numel() == 0:
        positions = positions.reshape(0, 3)
    if positions.ndim != 2 or positions.shape[1] != 3:
        raise ValueError(f"Features positions must have shape (N, 3), got {tuple(positions.shape)}")
    if positions.numel() and not bool(torch.isfinite(positions).all()):
        bad = int((~torch.isfinite(positions).all(dim=1)).sum())
        raise ValueError(f"Features positions contain NaN or inf ({bad} of {positions.shape[0]} points)")
    return positions


def _to_semantics(semantics, n: int, device) -> torch.Tensor:
    if isinstance(semantics, (int, Semantics)):
        semantics = torch.full((n,), int(semantics), dtype=torch.long)
    elif not torch.is_tensor(semantics):
        semantics = torch.as_tensor(np.asarray(semantics))
    if semantics.ndim == 0:
        semantics = semantics.expand(n)
    if semantics.dtype == torch.bool:
        raise ValueError("Features semantics must be integer Semantics values, got a bool tensor")
    if torch.is_floating_point(semantics):
        if semantics.numel() and not bool((semantics == semantics.round()).all()):
            raise ValueError(
                "Features semantics must be integer Semantics values (SURFACE=0, FREE=1, OCCUPIED=2); "
                "got non-integer floats (known non-zero SDF values are not supported)"
            )
    semantics = semantics.to(device=device, dtype=torch.long)
    if semantics.shape != (n,):
        raise ValueError(f"Features semantics must have shape ({n},) to match positions, got {tuple(semantics.shape)}")
    if n and bool(((semantics < 0) | (semantics >= _N_SEM)).any()):
        bad = torch.unique(semantics[(semantics < 0) | (semantics >= _N_SEM)]).tolist()
        raise ValueError(f"Features semantics has unknown values {bad}; allowed: SURFACE=0, FREE=1, OCCUPIED=2")
    return semantics


class Features:
    """A set of observed geometric features ``{(x, s)}``.

    Args:
        positions: ``(N, 3)`` float world positions (m). Finite.
        semantics: ``(N,)`` integer :class:`Semantics` values, or one value for all points.

    Raises:
        ValueError: wrong shapes, NaN/inf positions, or unknown semantics values.
    """

    __slots__ = ("positions", "semantics")

    def __init__(self, positions, semantics):
        pos = _to_positions(positions)
        self.positions: torch.Tensor = pos
        self.semantics: torch.Tensor = _to_semantics(semantics, pos.shape[0], pos.device)

    # ------------------------------------------------------------------ constructors
    @classmethod
    def empty(cls, device=None, dtype: torch.dtype = torch.float32) -> "Features":
        """No features: positions ``(0, 3)``, semantics ``(0,)``."""
        return cls(torch.zeros(0, 3, device=device, dtype=dtype), torch.zeros(0, dtype=torch.long, device=device))

    @classmethod
    def concat(cls, parts: Sequence["Features"] | Iterable["Features"]) -> "Features":
        """Union (concatenation) of several feature sets; device/dtype of the first. Empty list -> empty."""
        parts = list(parts)
        if not parts:
            return cls.empty()
        for p in parts:
            if not isinstance(p, Features):
                raise ValueError(f"Features.concat expects Features, got {type(p).__name__}")
        dev, dt = parts[0].positions.device, parts[0].positions.dtype
        return cls._unchecked(
            torch.cat([p.positions.to(device=dev, dtype=dt) for p in parts]),
            torch.cat([p.semantics.to(dev) for p in parts]),
        )

    @classmethod
    def _unchecked(cls, positions: torch.Tensor, semantics: torch.Tensor) -> "Features":
        f = cls.__new__(cls)
        f.positions = positions
        f.semantics = semantics
        return f

    # ------------------------------------------------------------------ views
    def __len__(self) -> int:
        return int(self.positions.shape[0])

    def __repr__(self) -> str:
        counts = self.counts()
        return (
            f"Features(n={len(self)}, surface={counts[Semantics.SURFACE]}, free={counts[Semantics.FREE]}, "
            f"occupied={counts[Semantics.OCCUPIED]}, device={self.device})"
        )

    @property
    def device(self) -> torch.device:
        return self.positions.device

    def counts(self) -> dict[Semantics, int]:
        """Number of features of each semantics."""
        bc = torch.bincount(self.semantics, minlength=_N_SEM).tolist() if len(self) else [0] * _N_SEM
        return {s: int(bc[s]) for s in Semantics}

    def select(self, mask) -> "Features":
        """Subset by a boolean mask ``(N,)`` or an index tensor."""
        mask = torch.as_tensor(mask, device=self.device)
        if mask.dtype == torch.bool and mask.shape != (len(self),):
            raise ValueError(f"select mask must have shape ({len(self)},), got {tuple(mask.shape)}")
        return Features._unchecked(self.positions[mask], self.semantics[mask])

    def of(self, semantics: Semantics | int) -> "Features":
        """Features with the given semantics value."""
        return self.select(self.semantics == int(semantics))

    @property
    def surface(self) -> "Features":
        return self.of(Semantics.SURFACE)

    @property
    def free(self) -> "Features":
        return self.of(Semantics.FREE)

    @property
    def occupied(self) -> "Features":
        return self.of(Semantics.OCCUPIED)

    def cat(self, other: "Features") -> "Features":
        """Union with ``other`` (concatenation, no de-duplication; see ``voxel_downsample``)."""
        return Features.concat([self, other])

    def to(self, device=None, dtype: torch.dtype | None = None) -> "Features":
        return Features._unchecked(
            self.positions.to(device=device, dtype=dtype or self.positions.dtype), self.semantics.to(device)
        )

    def transformed(self, T: torch.Tensor) -> "Features":
        """Positions mapped by a rigid transform ``T (4, 4)`` (``x' = T x``), semantics unchanged."""
        from ..geometry.transforms import check_poses, transform_points

        T = check_poses(T, "T")
        if T.shape != (4, 4):
            raise ValueError(f"T must have shape (4, 4), got {tuple(T.shape)}")
        if len(self) == 0:
            return self
        return Features._unchecked(transform_points(T.to(self.positions), self.positions), self.semantics)
