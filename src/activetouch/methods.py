"""Built-in methods: RUMI and its two ablations of section V-H (same belief, same parameters otherwise)."""
from __future__ import annotations

from activetouch.registry import register_method


@register_method("rumi", "RUMI: information gain C_I + reachability C_R (Eq. 31), KMPPI, stochastic dynamics f^")
def make_rumi(env, belief_config, seed, **overrides):
    from activetouch.planning.rumi import RumiPlanner

    return RumiPlanner.from_env(env, belief_config, seed, **overrides)


@register_method("info-only", "RUMI ablation InfoOnly: C_R removed (beta_R = 0)")
def make_info_only(env, belief_config, seed, **overrides):
    from activetouch.planning.config import RumiPlannerConfig
    from activetouch.planning.rumi import RumiPlanner

    return RumiPlanner.from_env(env, belief_config, seed, config=RumiPlannerConfig.info_only(), **overrides)


@register_method("reach-only", "RUMI ablation ReachOnly: C_I removed (beta_I = 0)")
def make_reach_only(env, belief_config, seed, **overrides):
    from activetouch.planning.config import RumiPlannerConfig
    from activetouch.planning.rumi import RumiPlanner

    return RumiPlanner.from_env(env, belief_config, seed, config=RumiPlannerConfig.reach_only(), **overrides)
