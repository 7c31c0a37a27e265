"""Registries of tasks, beliefs and methods, so that any compatible (task, method) pair runs through the one
episode loop of :mod:`activetouch.experiments.runner`.

- A **task** (:class:`TaskEntry`) supplies its environment (scene, robot, sensors), the observation kinds and
  action kinds it provides (:attr:`TaskEntry.provides`), its prior over the object pose and its success criterion.
- A **belief** (:class:`BeliefEntry`) is an estimator factory ``make(env, episode_config, device) -> Estimator``
  (see :class:`activetouch.experiments.estimators.Estimator`): initialise from the task's prior, predict and
  update from one step's observation, report its metrics. It declares the observation kinds it needs.
- A **method** (:class:`MethodSpec`) is a belief plus a planner factory
  ``make_planner(env, belief_config, seed, **overrides) -> Planner``; a planner has ``reset()`` and
  ``next_action(belief, ee_state, in_contact, features=None) -> (action, timings)``. Its needs are its belief's
  plus the planner's own (:attr:`MethodSpec.requires`).

A pair runs when the task provides everything the method needs (:func:`compatible`); ``activetouch methods
--task T`` lists what runs where and why not.

Register your own::

    from activetouch.registry import register_method

    @register_method("my-method", "what it does", belief="rumi-particles", requires={"ee-delta-actions"})
    def make_my_planner(env, belief_config, seed, **overrides):
        return MyPlanner(...)

Kinds used by the built-in tasks (a task may add its own):

=====================  ===================================================================================
``points``             labelled surface / free point features each step (camera + tactile pads)
``contact``            a per-step contact flag
``object-motion``      the object's motion ``dT`` each step (observed in simulation; RUMI can estimate it)
``ee-delta-actions``   actions are end-effector deltas ``u in [-1, 1]^Nu`` (RUMI's action space)
``reachability``       a reachability map of the workspace (RUMI's C_R)
``se2-object``         the object's pose is searched in SE(2) (x, y, yaw on its support; RUMI's mug, drill)
``contact-signal``     a binary joint-torque contact signal per waypoint (touch paper App. D-a)
``proprioception``     the robot's joint configurations along every action
``physics-rollout``    object hypotheses can be rolled out in the simulator under the executed motion
``poke-actions``       actions are via-point trajectories (touch paper App. C)
``grasp``              a grasp primitive ends the episode and is scored (touch paper App. D-d)
``target-points``      segmented world points on the target object (camera, pads; the TIQF belief's input)
``segmentation``       per-pixel object labels of every view (the declutter graph)
``tactile-points``     contact points on the target from guarded touches
``view-actions``       the camera can be moved (next best view)
``touch-actions``      guarded touches along a ray (next best touch)
``push-actions``       straight pushes of an object (decluttering)
``pick-actions``       grasps that place an object outside the workspace (decluttering)
=====================  ===================================================================================
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Protocol

import numpy as np


class Planner(Protocol):
    def reset(self) -> None: ...

    def next_action(self, belief: Any, ee_state: np.ndarray, in_contact: bool,
                    features: Any = None) -> tuple[Any, dict[str, float]]: ...


@dataclass(frozen=True)
class TaskEntry:
    """A registered task.

    Attributes:
        name: task id (``mug-0``, ``grasp-box-1``).
        family: tasks of one family share an environment class, prior kind and success criterion.
        description: one line for ``activetouch tasks``.
        provides: observation and action kinds (module docstring).
        make_env: ``(seed, **overrides) -> env``; the env has ``reset(seed)``, ``step(action)``, ``ee_state()``,
            ``object`` (a ``KnownObject``) and ``max_steps``.
        prior: ``(env, obs0, n, generator, device) -> (n, 4, 4)`` prior pose particles from the first observation.
        success: ``(rows, last_info, env) -> dict`` the task's success fields of the summary (must hold ``success``).
        belief_defaults: ``((field, value), ...)`` belief settings the task runs with unless ``--belief`` overrides
            them (recorded in each summary as ``task_belief_defaults``: a resume or a table never mixes runs
            made under other task defaults).
        defaults_belief: the belief those settings are for (``rumi-particles`` for the RUMI tasks): a method
            with another belief runs without them (and records none), since its config has other fields.
    """

    name: str
    family: str
    description: str
    provides: frozenset[str]
    make_env: Callable[..., Any]
    prior: Callable[..., Any]
    success: Callable[..., dict[str, Any]]
    belief_defaults: tuple = ()
    defaults_belief: str = ""


@dataclass(frozen=True)
class BeliefEntry:
    name: str
    description: str
    requires: frozenset[str]
    make: Callable[..., Any]


@dataclass(frozen=True)
class MethodSpec:
    name: str
    description: str
    make_planner: Callable[..., Planner]
    belief: str = "rumi-particles"
    planner_requires: frozenset[str] = field(default_factory=frozenset)
    #: planner overrides that make a few steps cheap (the contract test, smoke runs): a dict or ``env -> dict``
    quick: Any = None
    #: the method only runs with planner arguments (the scripted replays): ``sweep --grid`` leaves it out
    needs_arguments: bool = False

    def quick_overrides(self, env) -> dict[str, Any]:
        q = self.quick(env) if callable(self.quick) else self.quick
        return dict(q or {})

    @property
    def requires(self) -> frozenset[str]:
        """Everything the method needs from a task: its belief's needs and its planner's."""
        return get_belief(self.belief).requires | self.planner_requires


_TASKS: dict[str, TaskEntry] = {}
_BELIEFS: dict[str, BeliefEntry] = {}
_METHODS: dict[str, MethodSpec] = {}


def belief_settings(task: str, overrides: dict[str, Any], belief: str) -> dict[str, Any]:
    """The settings a run of ``task`` with the belief named ``belief`` uses beyond the belief's defaults: the
    task's ``belief_defaults`` when they are for that belief (``TaskEntry.defaults_belief``), under the user's
    overrides (``--belief``)."""
    entry = get_task(task)
    defaults = dict(entry.belief_defaults) if entry.defaults_belief == belief else {}
    return {**defaults, **dict(overrides)}


def register_task(entry: TaskEntry) -> TaskEntry:
    if entry.name in _TASKS:
        raise ValueError(f"task {entry.name!r} is already registered")
    _TASKS[entry.name] = entry
    return entry


def register_belief(name: str, description: str = "", requires=()):
    """Decorator registering an estimator factory ``make(env, episode_config, device) -> Estimator``."""

    def deco(factory):
        if name in _BELIEFS:
            raise ValueError(f"belief {name!r} is already registered")
        _BELIEFS[name] = BeliefEntry(name, description, frozenset(requires), factory)
        return factory

    return deco


def register_method(name: str, description: str = "", belief: str = "rumi-particles", requires=(), quick=None,
                    needs_arguments: bool = False):
    """Decorator registering a planner factory under ``name``, run with the belief ``belief``; ``requires``: what
    the planner needs from a task; ``quick``: planner overrides for cheap smoke runs (dict or ``env -> dict``);
    ``needs_arguments``: it cannot run without planner arguments (left out of ``sweep --grid``)."""

    def deco(factory: Callable[..., Planner]) -> Callable[..., Planner]:
        if name in _METHODS:
            raise ValueError(f"method {name!r} is already registered")
        _METHODS[name] = MethodSpec(name, description, factory, belief, frozenset(requires), quick, needs_arguments)
        return factory

    return deco


def get_task(name: str) -> TaskEntry:
    _ensure_builtin()
    try:
        return _TASKS[name]
    except KeyError:
        raise ValueError(f"unknown task {name!r}; available: {', '.join(_TASKS)}") from None


def get_belief(name: str) -> BeliefEntry:
    _ensure_builtin()
    try:
        return _BELIEFS[name]
    except KeyError:
        raise ValueError(f"unknown belief {name!r}; available: {', '.join(sorted(_BELIEFS))}") from None


def get_method(name: str) -> MethodSpec:
    _ensure_builtin()
    try:
        return _METHODS[name]
    except KeyError:
        raise ValueError(f"unknown method {name!r}; available: {', '.join(sorted(_METHODS))}") from None


def tasks() -> list[str]:
    _ensure_builtin()
    return list(_TASKS)


def beliefs() -> list[str]:
    _ensure_builtin()
    return sorted(_BELIEFS)


def methods() -> list[str]:
    _ensure_builtin()
    return sorted(_METHODS)


def missing(task: str, method: str) -> frozenset[str]:
    """What ``method`` needs that ``task`` does not provide (empty: the pair runs)."""
    return get_method(method).requires - get_task(task).provides


def compatible(task: str, method: str) -> bool:
    return not missing(task, method)


def check_compatible(task: str, method: str) -> None:
    """ValueError naming what is missing when ``method`` cannot run on ``task``."""
    miss = missing(task, method)
    if miss:
        runs = [m for m in methods() if compatible(task, m)]
        raise ValueError(f"method {method!r} cannot run on task {task!r}: the task does not provide "
                         f"{', '.join(sorted(miss))}; methods for {task}: {', '.join(runs) or 'none'}")


def compatible_pairs() -> list[tuple[str, str]]:
    """Every registered (task, method) pair that runs."""
    return [(t, m) for t in tasks() for m in methods() if compatible(t, m)]


_LOADED = False


def _ensure_builtin() -> None:
    # Built-in tasks, beliefs and methods register themselves on import of these modules.
    global _LOADED
    if _LOADED:
        return
    _LOADED = True
    import activetouch.methods  # noqa: F401
    import activetouch.tasks  # noqa: F401
