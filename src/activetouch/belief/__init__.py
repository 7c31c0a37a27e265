"""RUMI pose particle belief ``p(T | X)``: CHSEL discrepancy, weighing, resampling, prediction, ObjMove.

* :mod:`.config` - ``BeliefConfig`` (Table IV defaults).
* :mod:`.discrepancy` - ``C^(X, T)`` (Eq. 3-6, weighing) and the squared-hinge objective whose gradient is
  Eq. 7-9 (Algorithms 4 and 5), batched over particles, differentiable.
* :mod:`.particle_filter` - ``ParticleBelief`` (Algorithms 1, 2, 4; predict; from_prior).
* :mod:`.resample` - systematic importance resampling, PerturbTransform application (Alg. 3, 4).
* :mod:`.optimise` - N_o Adam steps on the discrepancy over local SE(2)/SE(3) pose parameters.
* :mod:`.objmove` - ObjMove (Algorithm 5) and its frame algebra.
* :mod:`.priors` - mug and Gaussian-position/uniform-yaw priors.
* :mod:`.chsel_init` - CHSEL quality-diversity initialisation (Algorithm 1 line 2).

The touch paper's SE(2) contact filter (Sec. V):

* :mod:`.contact_model` - the proximity contact model (Eq. 10) and the binary one of its ref. [3], the
  whole-robot / object distance, SE(2) <-> pose helpers.
* :mod:`.touch_filter` - ``TouchBelief`` (re-weighing, contact-aware resampling App. B) and the GMM prior (D-c).
"""
from . import priors
from .contact_model import ContactModelConfig, contact_likelihood, robot_object_distance, se2_to_pose, pose_to_se2
from .touch_filter import TouchBelief, TouchFilterConfig, gmm_prior
from .config import MIN_PARTICLES, BeliefConfig, chsel_min_batch
from .discrepancy import discrepancy, discrepancy_and_objective, optimisation_objective, point_costs
from .particle_filter import ParticleBelief, boltzmann_weights
from .priors import gaussian_yaw_prior, mug_prior, resting_face_prior
from .resample import systematic_resample

__all__ = [
    "ContactModelConfig",
    "TouchBelief",
    "TouchFilterConfig",
    "contact_likelihood",
    "gmm_prior",
    "pose_to_se2",
    "robot_object_distance",
    "se2_to_pose",
    "BeliefConfig",
    "MIN_PARTICLES",
    "chsel_min_batch",
    "discrepancy_and_objective",
    "optimisation_objective",
    "ParticleBelief",
    "boltzmann_weights",
    "discrepancy",
    "point_costs",
    "priors",
    "mug_prior",
    "resting_face_prior",
    "gaussian_yaw_prior",
    "systematic_resample",
]
