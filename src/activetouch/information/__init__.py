"""RUMI's information gain field (Eq. 23), semantics probability field (Eq. 27) and per-feature costs; the touch
paper's shared-support entropy (Eq. 5, App. A) and expected information gain (Alg. 1, Eq. 6-9) in ``entropy``."""
from . import entropy
from .costs import per_semantics_costs
from .entropy import (
    IGResult,
    expected_information_gain,
    expected_weight_entropy,
    expected_weight_entropy_binary,
    log_support_volume,
    shared_support,
    spatial_entropy,
    weight_entropy,
)
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
    "entropy",
    "IGResult",
    "expected_information_gain",
    "expected_weight_entropy",
    "expected_weight_entropy_binary",
    "log_support_volume",
    "shared_support",
    "spatial_entropy",
    "weight_entropy",
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
