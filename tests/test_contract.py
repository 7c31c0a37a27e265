"""Every registered (task, method) pair that declares itself compatible runs two steps of the one episode loop,
keeps a finite, normalised belief of a fixed size and is deterministic for a seed (like gymnasium's check_env)."""
from __future__ import annotations

import pytest

from activetouch import registry
from activetouch.experiments.contract import check_pair

PAIRS = registry.compatible_pairs()


def _family_head(task: str) -> bool:
    """One task per object of each family is rerun for determinism (the others share its code path)."""
    obj = task.rsplit("-", 1)[0]
    return task == next(t for t in registry.tasks() if t.rsplit("-", 1)[0] == obj)


def test_every_method_runs_somewhere():
    runnable = {m for _, m in PAIRS}
    assert runnable == set(registry.methods()), f"methods without a task: {set(registry.methods()) - runnable}"
    assert {t for t, _ in PAIRS} == set(registry.tasks()), "a task no method can run"


@pytest.mark.parametrize("task,method", PAIRS, ids=[f"{t}:{m}" for t, m in PAIRS])
def test_pair_keeps_the_contract(task, method, tmp_path):
    check_pair(task, method, tmp_path, seed=1, steps=2, repeat=_family_head(task))


def test_incompatible_pair_is_refused_before_work(tmp_path):
    from activetouch.registry import BeliefEntry, _BELIEFS, _METHODS, register_method

    registry.methods()  # load the built-ins

    @register_method("needs-telepathy", "test only", requires=("telepathy",))
    def make(env, belief_config, seed, **kw):  # pragma: no cover - never built
        raise AssertionError("the planner must not be built for an incompatible pair")

    try:
        from activetouch.experiments.runner import EpisodeConfig, run_episode

        with pytest.raises(ValueError, match="does not provide telepathy"):
            run_episode(EpisodeConfig(task="mug-0", method="needs-telepathy", progress=False), tmp_path)
        assert not (tmp_path / "steps.csv").exists()
    finally:
        _METHODS.pop("needs-telepathy", None)
    assert isinstance(next(iter(_BELIEFS.values())), BeliefEntry)
