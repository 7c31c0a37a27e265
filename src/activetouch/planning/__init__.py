"""RUMI planning: stochastic dynamics f^ (Alg. 7), costs C_I (Eq. 29), C_R (Alg. 8), Eq. 31 and the KMPPI planner."""
from .config import RumiPlannerConfig
from .costs import InformationCost, ReachabilityCost, RumiCost, resample_to_grid
from .dynamics import STATE_DIM, GripperModel, StochasticDynamics, action_indices
from .rumi import RumiPlanner

__all__ = [
    "STATE_DIM",
    "GripperModel",
    "InformationCost",
    "ReachabilityCost",
    "RumiCost",
    "RumiPlanner",
    "RumiPlannerConfig",
    "StochasticDynamics",
    "action_indices",
    "resample_to_grid",
]
