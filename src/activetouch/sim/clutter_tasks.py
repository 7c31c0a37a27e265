"""The dense-clutter tasks of the visuo-tactile paper (Sec. III, Table I): a target in a pile of 4-8 YCB objects.

The paper's four targets (an olive-oil bottle, a cleaner, a spray bottle and a transparent wineglass) are not in
the YCB set we ship; we take the closest shipped shapes: two bottles (mustard, bleach cleanser), a can (tomato
soup) and a *transparent* mustard bottle (the camera's rays pass through it, touch still works), the case where
vision fails. Each seed drops a new pile (``ClutterEnv.reset``).
"""
from __future__ import annotations

import dataclasses

from .clutter_env import ClutterEnv, ClutterTaskSpec
from .tasks import with_overrides

__all__ = ["CLUTTER_TASKS", "MISCALIBRATION", "get_clutter_spec", "make_clutter_env"]

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

#: The camera calibration error of the ``clutter-miscal-*`` tasks (m, deg): our choice, the order of a two-arm
#: base-to-base or hand-eye calibration; the paper does not state its camera's.
MISCALIBRATION = (0.008, 1.0)

# the same four targets seen by a miscalibrated camera (touch is measured in the arm's frame and has no such error)
for _name in list(CLUTTER_TASKS):
    _spec = CLUTTER_TASKS[_name]
    _new = _name.replace("clutter-", "clutter-miscal-", 1)
    CLUTTER_TASKS[_new] = dataclasses.replace(
        _spec, name=_new, camera_calibration_error=MISCALIBRATION,
        description=f"{_spec.description}; the camera miscalibrated by {MISCALIBRATION[0] * 1000:.0f} mm and "
                    f"{MISCALIBRATION[1]:.0f} deg")


def get_clutter_spec(name: str, **overrides) -> ClutterTaskSpec:
    if name not in CLUTTER_TASKS:
        raise ValueError(f"unknown clutter task {name!r}; known: {', '.join(CLUTTER_TASKS)}")
    return with_overrides(CLUTTER_TASKS[name], overrides)


def make_clutter_env(name: str, seed: int = 0, **overrides) -> ClutterEnv:
    """``ClutterEnv`` of a registered clutter task; ``overrides`` replace ``ClutterTaskSpec`` fields."""
    return ClutterEnv(get_clutter_spec(name, **overrides), seed=seed)
