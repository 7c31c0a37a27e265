"""RUMI planning: stochastic dynamics f^ (Alg. 7), costs C_I (Eq. 29), C_R (Alg. 8), Eq. 31 and the KMPPI planner;
the baselines of section V-H: GPVR (Eq. 37) and Slide. The touch paper's controller: spline pokes (App. C) scored by
expected information gain (Alg. 1) and its baselines Uninformed and MaxContact (``touch_ig``)."""
from .config import RumiPlannerConfig
from .costs import InformationCost, ReachabilityCost, RumiCost, resample_to_grid
from .dynamics import STATE_DIM, GripperModel, StochasticDynamics, action_indices
from .gpvr import GPImplicitSurface, GpvrConfig, GpvrPlanner, GPVarianceCost, gp_training_data
from .rumi import RumiPlanner
from .slide import SlideConfig, SlidePlanner
from .splines import spline_waypoints, via_point_spline
from .touch_ig import TouchIGPlanner, TouchPlannerConfig

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
    "TouchIGPlanner",
    "TouchPlannerConfig",
    "spline_waypoints",
    "via_point_spline",
    "action_indices",
    "gp_training_data",
    "resample_to_grid",
]
