"""Built-in methods: RUMI, its two ablations and the two baselines of section V-H (GPVR, Slide); all share the
belief (Algorithm 1), the ablations and GPVR also share RUMI's KMPPI and dynamics."""
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


@register_method("scripted", "no planning: replays planner={'actions': [[...], ...]} (tests, benchmarks, replays)")
def make_scripted(env, belief_config, seed, actions=None):
    from activetouch.planning.scripted import ScriptedPlanner

    return ScriptedPlanner.from_env(env, actions)


@register_method("gpvr", "Baseline GPVR (V-H): GP implicit surface (Matern 1.5) variance, Eq. 37 running cost, "
                         "RUMI's KMPPI and dynamics f^")
def make_gpvr(env, belief_config, seed, **overrides):
    from activetouch.planning.gpvr import GpvrPlanner

    return GpvrPlanner.from_env(env, belief_config, seed, **overrides)


@register_method("slide", "Baseline Slide (V-H): slide tangentially along the contact (direction drawn per run), "
                          "else move toward the particles' centre")
def make_slide(env, belief_config, seed, **overrides):
    from activetouch.planning.slide import SlidePlanner

    return SlidePlanner.from_env(env, belief_config, seed, **overrides)
