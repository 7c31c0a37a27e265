"""RUMI planning: stochastic dynamics f^ (Alg. 7), costs C_I (Eq. 29), C_R (Alg. 8), Eq. 31 and the KMPPI planner;
the baselines of section V-H: GPVR (Eq. 37) and Slide."""
from .config import RumiPlannerConfig
from .costs import InformationCost, ReachabilityCost, RumiCost, resample_to_grid
from .dynamics import STATE_DIM, GripperModel, StochasticDynamics, action_indices
from .gpvr import GPImplicitSurface, GpvrConfig, GpvrPlanner, GPVarianceCost, gp_training_data
from .rumi import RumiPlanner
from .slide import SlideConfig, SlidePlanner

__all__ = [
    "STATE_DIM",
    "GPImplicitSurface",
    "GPVarianceCost",
    "GpvrConfig",
    "GpvrPlanner",
    "GripperModel",
    "InformationCost",
    "ReachabilityCost",
    "RumiCost",
    "RumiPlanner",
    "RumiPlannerConfig",
    "SlideConfig",
    "SlidePlanner",
    "StochasticDynamics",
    "action_indices",
    "gp_training_data",
    "resample_to_grid",
]
