"""A planner that replays a fixed action sequence: the belief driven by known actions.

A closed loop is chaotic (another CPU's floating point gives another trajectory), a scripted one is not: tests
and benchmarks that check the belief, the features and the result files use it to assert properties that hold
on any machine. Registered as the method ``scripted`` (``EpisodeConfig(method="scripted",
planner={"actions": [[dx, dy, dyaw], ...]})``).
"""
from __future__ import annotations

import numpy as np

__all__ = ["ScriptedPlanner"]


class ScriptedPlanner:
    """Replays ``actions (T, Nu)`` in order, then zero actions.

    Args:
        actions: ``(T, Nu)`` actions in ``[-1, 1]`` (planar tasks ``Nu = 3``: ``[dx, dy, dyaw]``; 3D tasks
            ``Nu = 4``: ``[dx, dy, dz, dyaw]``).
        action_dim: the task's ``Nu``.
    """

    def __init__(self, actions, action_dim: int):
        a = np.asarray(actions, dtype=np.float32)
        if a.ndim != 2 or a.shape[1] != action_dim or len(a) == 0:
            raise ValueError(f"scripted actions must have shape (T, {action_dim}) with T >= 1, got {a.shape}")
        if not np.isfinite(a).all() or np.abs(a).max() > 1.0:
            raise ValueError("scripted actions must be finite and within [-1, 1]")
        self.actions = a
        self.reset()

    def reset(self) -> None:
        self._t = 0

    def next_action(self, belief, ee_state, in_contact: bool, features=None) -> tuple[np.ndarray, dict[str, float]]:
        u = self.actions[self._t] if self._t < len(self.actions) else np.zeros(self.actions.shape[1], np.float32)
        self._t += 1
        return u.copy(), {"replanned": 0.0}

    @classmethod
    def from_env(cls, env, actions=None) -> "ScriptedPlanner":
        if actions is None:
            raise ValueError("method 'scripted' needs its actions: planner={'actions': [[...], ...]}")
        return cls(actions, env.action_dim)


class ScriptedPokePlanner:
    """Replays fixed pokes ``[(K_i, 4) waypoints, ...]`` on a grasp task (``PokeAction``), then grasps the belief's
    maximum-likelihood state (``GraspAction``): the touch belief driven by known actions (tests, replays)."""

    def __init__(self, pokes):
        from activetouch.sim.grasp_env import PokeAction

        if not isinstance(pokes, (list, tuple)) or not pokes:
            raise ValueError("scripted pokes must be a non-empty list of (K, 4) waypoint arrays")
        self.pokes = [PokeAction(np.asarray(p, dtype=np.float64)).waypoints for p in pokes]
        self.reset()

    def reset(self) -> None:
        self._t = 0

    def next_action(self, belief, ee_state, in_contact: bool, features=None):
        from activetouch.sim.grasp_env import GraspAction, PokeAction

        self._t += 1
        if self._t <= len(self.pokes):
            return PokeAction(self.pokes[self._t - 1].copy()), {"replanned": 0.0}
        return GraspAction(belief.best_state.detach().cpu().double().numpy()), {"replanned": 0.0}

    @classmethod
    def from_env(cls, env, pokes=None) -> "ScriptedPokePlanner":
        if pokes is None:
            raise ValueError("method 'scripted-poke' needs its pokes: planner={'pokes': [[[x, y, z, yaw], ...], ...]}")
        return cls(pokes)
