"""RUMI's information gain field (Eq. 23), semantics probability field (Eq. 27) and per-feature costs."""
from .costs import per_semantics_costs
from .field import (
    FREE,
    OCCUPIED,
    SURFACE,
    InformationField,
    compute_field,
    field_margin,
    information_gain,
    semantics_probabilities,
)

__all__ = [
    "FREE",
    "OCCUPIED",
    "SURFACE",
    "InformationField",
    "compute_field",
    "field_margin",
    "information_gain",
    "per_semantics_costs",
    "semantics_probabilities",
]
