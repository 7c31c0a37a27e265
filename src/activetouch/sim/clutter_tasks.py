"""The dense-clutter tasks of the visuo-tactile paper (Sec. III, Table I): a target in a pile of 4-8 YCB objects.

The paper's four targets (an olive-oil bottle, a cleaner, a spray bottle and a transparent wineglass) are not in
the YCB set we ship; we take the closest shipped shapes: two bottles (mustard, bleach cleanser), a can (tomato
soup) and a *transparent* mustard bottle (the camera's rays pass through it, touch still works), the case where
vision fails. Each seed drops a new pile (``ClutterEnv.reset``).
"""
from __future__ import annotations

from .clutter_env import ClutterEnv, ClutterTaskSpec
from .tasks import with_overrides

__all__ = ["CLUTTER_TASKS", "get_clutter_spec", "make_clutter_env"]

CLUTTER_TASKS: dict[str, ClutterTaskSpec] = {
    spec.name: spec for spec in (
        ClutterTaskSpec("clutter-mustard", target="mustard_bottle",
                        description="mustard bottle (Obj 1, a bottle) in a pile of 4-8 YCB objects"),
        ClutterTaskSpec("clutter-bleach", target="bleach_cleanser",
                        description="bleach cleanser (Obj 2, a cleaner bottle) in a pile of 4-8 YCB objects"),
        ClutterTaskSpec("clutter-soup-can", target="tomato_soup_can",
                        description="tomato soup can (Obj 3, a can) in a pile of 4-8 YCB objects"),
        ClutterTaskSpec("clutter-transparent", target="mustard_bottle", transparent_target=True,
                        description="transparent mustard bottle (Obj 4, the wineglass case: the camera cannot "
                                    "see it) in a pile of 4-8 YCB objects"),
    )
}


def get_clutter_spec(name: str, **overrides) -> ClutterTaskSpec:
    if name not in CLUTTER_TASKS:
        raise ValueError(f"unknown clutter task {name!r}; known: {', '.join(CLUTTER_TASKS)}")
    return with_overrides(CLUTTER_TASKS[name], overrides)


def make_clutter_env(name: str, seed: int = 0, **overrides) -> ClutterEnv:
    """``ClutterEnv`` of a registered clutter task; ``overrides`` replace ``ClutterTaskSpec`` fields."""
    return ClutterEnv(get_clutter_spec(name, **overrides), seed=seed)
