"""Registry of methods (belief + information + planner triples) so any method runs on any task.

A method is a factory ``make_planner(env, belief_config, seed, **overrides) -> Planner``. A planner has
``reset()`` and ``next_action(belief, ee_state, in_contact) -> (u, timings)`` where ``u`` is an ``(Nu,)``
numpy action in ``[-1, 1]`` and ``timings`` a dict of seconds (``field_s``, ``dynamics_s``, ``cost_s``).

Register your own::

    from activetouch.registry import register_method

    @register_method("my-method", "what it does")
    def make_my_planner(env, belief_config, seed, **overrides):
        return MyPlanner(...)
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Protocol

import numpy as np


class Planner(Protocol):
    def reset(self) -> None: ...

    def next_action(self, belief: Any, ee_state: np.ndarray, in_contact: bool) -> tuple[np.ndarray, dict[str, float]]: ...


@dataclass(frozen=True)
class MethodSpec:
    name: str
    description: str
    make_planner: Callable[..., Planner]


_METHODS: dict[str, MethodSpec] = {}


def register_method(name: str, description: str = ""):
    """Decorator registering a planner factory under ``name``."""

    def deco(factory: Callable[..., Planner]) -> Callable[..., Planner]:
        if name in _METHODS:
            raise ValueError(f"method {name!r} is already registered")
        _METHODS[name] = MethodSpec(name, description, factory)
        return factory

    return deco


def get_method(name: str) -> MethodSpec:
    _ensure_builtin()
    try:
        return _METHODS[name]
    except KeyError:
        raise ValueError(f"unknown method {name!r}; available: {', '.join(sorted(_METHODS))}") from None


def methods() -> list[str]:
    _ensure_builtin()
    return sorted(_METHODS)


def _ensure_builtin() -> None:
    # Built-in methods register themselves on import of activetouch.methods.
    import activetouch.methods  # noqa: F401
