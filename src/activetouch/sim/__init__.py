"""Simulated rummaging tasks of RUMI (MuJoCo): scene, robot, sensors, the nine tasks.

Public API (docs/INTERFACES.md): ``make(task_id, seed=0, **overrides) -> RummageEnv``,
``registered()``, ``TaskSpec``, ``RummageEnv``, ``Observation``.
"""
from .env import Observation, RummageEnv, make
from .tasks import TASKS, TaskSpec, get_spec, registered

__all__ = ["make", "registered", "get_spec", "TaskSpec", "TASKS", "RummageEnv", "Observation"]
