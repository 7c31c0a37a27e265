"""Built-in methods: RUMI, its two ablations and the two baselines of section V-H (GPVR, Slide); all share the
belief (Algorithm 1), the ablations and GPVR also share RUMI's KMPPI and dynamics."""
from __future__ import annotations

from activetouch.registry import register_belief, register_method

#: What RUMI's planners need besides the belief: end-effector delta actions and a reachability map (C_R).
RUMI_PLANNER_NEEDS = ("ee-delta-actions", "reachability")
#: KMPPI small enough for a two-step smoke run (the contract test); the defaults are the paper's.
QUICK_KMPPI = {"num_samples": 20, "rollout_samples": 1, "horizon": 8}


@register_belief("rumi-particles", "RUMI Algorithm 1: CHSEL-initialised SE(2)/SE(3) pose particles weighed by "
                                   "labelled point features (Alg. 2-6)", requires=("points",))
def make_rumi_belief(env, cfg, device):
    from activetouch.experiments.estimators import RumiEstimator

    return RumiEstimator(env, cfg, device)


def _check_rumi_belief(cfg) -> None:
    from activetouch.belief import chsel_min_batch

    if cfg.use_chsel and cfg.particles < chsel_min_batch(cfg.chsel_iterations):
        raise ValueError(f"particles = {cfg.particles}: CHSEL (Alg. 1 line 2) with {cfg.chsel_iterations} rounds needs "
                         f"at least {chsel_min_batch(cfg.chsel_iterations)} particles; use more or --no-chsel")


make_rumi_belief.check_config = _check_rumi_belief


@register_method("rumi", "RUMI: information gain C_I + reachability C_R (Eq. 31), KMPPI, stochastic dynamics f^",
                 requires=RUMI_PLANNER_NEEDS, quick=QUICK_KMPPI)
def make_rumi(env, belief_config, seed, **overrides):
    from activetouch.planning.rumi import RumiPlanner

    return RumiPlanner.from_env(env, belief_config, seed, **overrides)


@register_method("info-only", "RUMI ablation InfoOnly: C_R removed (beta_R = 0)", requires=RUMI_PLANNER_NEEDS, quick=QUICK_KMPPI)
def make_info_only(env, belief_config, seed, **overrides):
    from activetouch.planning.config import RumiPlannerConfig
    from activetouch.planning.rumi import RumiPlanner

    return RumiPlanner.from_env(env, belief_config, seed, config=RumiPlannerConfig.info_only(), **overrides)


@register_method("reach-only", "RUMI ablation ReachOnly: C_I removed (beta_I = 0)", requires=RUMI_PLANNER_NEEDS, quick=QUICK_KMPPI)
def make_reach_only(env, belief_config, seed, **overrides):
    from activetouch.planning.config import RumiPlannerConfig
    from activetouch.planning.rumi import RumiPlanner

    return RumiPlanner.from_env(env, belief_config, seed, config=RumiPlannerConfig.reach_only(), **overrides)


@register_method("scripted", "no planning: replays planner={'actions': [[...], ...]} (tests, benchmarks, replays)",
                 requires=("ee-delta-actions",), quick=lambda env: {"actions": [[0.5] * env.action_dim] * 2},
                 needs_arguments=True)
def make_scripted(env, belief_config, seed, actions=None):
    from activetouch.planning.scripted import ScriptedPlanner

    return ScriptedPlanner.from_env(env, actions)


@register_method("gpvr", "Baseline GPVR (V-H): GP implicit surface (Matern 1.5) variance, Eq. 37 running cost, "
                         "RUMI's KMPPI and dynamics f^", requires=RUMI_PLANNER_NEEDS, quick={**QUICK_KMPPI, "warmstart_iters": 1, "fit_steps": 10,
                                                                           "max_surface_points": 100, "max_free_points": 100})
def make_gpvr(env, belief_config, seed, **overrides):
    from activetouch.planning.gpvr import GpvrPlanner

    return GpvrPlanner.from_env(env, belief_config, seed, **overrides)


@register_method("slide", "Baseline Slide (V-H): slide tangentially along the contact (direction drawn per run), "
                          "else move toward the particles' centre", requires=("ee-delta-actions",))
def make_slide(env, belief_config, seed, **overrides):
    from activetouch.planning.slide import SlidePlanner

    return SlidePlanner.from_env(env, belief_config, seed, **overrides)


# ---------------------------------------------------------------------------------------------- touch paper
@register_belief("touch-particles", "touch paper Sec. V: SE(2) particles, Eq. 10 proximity contact model on the "
                                    "joint-torque signal, MuJoCo rollouts, contact-aware resampling (App. B)",
                 requires=("contact-signal", "proprioception", "physics-rollout"))
def make_touch_belief(env, cfg, device):
    from activetouch.experiments.estimators import TouchEstimator

    return TouchEstimator(env, cfg, device)


TOUCH_PLANNER_NEEDS = ("poke-actions", "grasp")
#: a two-step smoke run: few candidates and waypoints
QUICK_TOUCH = {"num_samples": 3, "waypoints": 6}


def _touch(criterion):
    def make(env, belief_config, seed, **overrides):
        from activetouch.planning.touch_ig import TouchIGPlanner, TouchPlannerConfig

        return TouchIGPlanner.from_env(env, belief_config, seed, config=TouchPlannerConfig(criterion=criterion),
                                       **overrides)

    return make


register_method("touch-ig", "touch paper: expected information gain (Alg. 1, shared-support entropy Eq. 5) over "
                            "20 spline pokes, grasp at P(success) >= 0.8 or after 15 pokes",
                belief="touch-particles", requires=TOUCH_PLANNER_NEEDS, quick=QUICK_TOUCH)(_touch("ig"))
register_method("touch-uninformed", "touch paper baseline Uninformed (VI-A-b): a random spline poke, no "
                                    "information metric", belief="touch-particles", requires=TOUCH_PLANNER_NEEDS,
                quick=QUICK_TOUCH)(_touch("uninformed"))
register_method("touch-max-contact", "touch paper baseline MaxContact (VI-A-b): the poke contacting the most "
                                     "particles", belief="touch-particles", requires=TOUCH_PLANNER_NEEDS,
                quick=QUICK_TOUCH)(_touch("max-contact"))


def _quick_pokes(env):
    """Two pokes from the home pose toward the middle of the table (a smoke run)."""
    return {"pokes": [[[0.30, 0.0, 0.10, 0.0], [0.38, 0.0, 0.08, 0.0]], [[0.30, -0.1, 0.10, 0.0]]]}


@register_method("scripted-poke", "no planning: replays planner={'pokes': [[[x, y, z, yaw], ...], ...]} then grasps "
                                  "the ML state (tests, replays)", belief="touch-particles",
                 requires=TOUCH_PLANNER_NEEDS, quick=_quick_pokes, needs_arguments=True)
def make_scripted_poke(env, belief_config, seed, pokes=None):
    from activetouch.planning.scripted import ScriptedPokePlanner

    return ScriptedPokePlanner.from_env(env, pokes)


# ---------------------------------------------------------------------------------------------------------------
# The visuo-tactile clutter paper (TIQF belief; declutter graph, next best view, next best touch)

@register_belief("tiqf", "visuo-tactile paper Sec. II-C: TIQF (translation-invariant quaternion filter), a Gaussian "
                         "over the target's rotation + Eq. 6 translation from segmented depth and tactile points",
                 requires=("target-points",))
def make_tiqf_belief(env, cfg, device):
    from activetouch.experiments.estimators import TiqfEstimator

    return TiqfEstimator(env, cfg, device)


@register_belief("tiqf-verify", "TIQF whose touches verify the views: after each touch, the visual and tactile points "
                                "are registered together when the touches lie on the surface of the estimate the views "
                                "gave (median within 4 mm), else the tactile points alone (touch_cloud=verify)",
                 requires=("target-points",))
def make_tiqf_verify_belief(env, cfg, device):
    from dataclasses import replace

    from activetouch.experiments.estimators import TiqfEstimator

    return TiqfEstimator(env, replace(cfg, belief={"touch_cloud": "verify", **cfg.belief}), device)


#: Smoke-run budgets (the contract test): few candidates, few actions.
QUICK_CLUTTER = {"num_views": 4, "rays_per_face": 3, "max_declutter": 1, "max_views": 1, "max_touches": 1}


def _clutter(**phases):
    def make(env, belief_config, seed, **overrides):
        from activetouch.planning.clutter import ClutterPlanner

        both = sorted(set(phases) & set(overrides))
        if both:
            raise TypeError(f"{both} are fixed by the method")
        return ClutterPlanner.from_env(env, belief_config, seed, **phases, **overrides)

    return make


register_method("tiqf-static", "visuo-tactile paper Table I (a), static vision: one view from a random point of the "
                               "hemisphere, TIQF", belief="tiqf", requires=("view-actions",),
                quick=QUICK_CLUTTER)(_clutter(declutter=False, active_vision=False, touch=False))
register_method("tiqf-active-vision", "Table I (b), active vision without decluttering: next best views (Eq. 19-24) "
                                      "until the estimate settles (5 mm, 2 deg)", belief="tiqf",
                requires=("view-actions",), quick=QUICK_CLUTTER)(_clutter(declutter=False, active_vision=True, touch=False))
register_method("tiqf-declutter-vision", "Table I (c), active vision after decluttering (declutter graph, Eq. 1-2: "
                                         "grasp or push the next object)", belief="tiqf",
                requires=("view-actions", "segmentation", "push-actions", "pick-actions"),
                quick=QUICK_CLUTTER)(_clutter(declutter=True, active_vision=True, touch=False))
register_method("tiqf-visuo-tactile", "Table I (d), the paper's method: decluttering, next best views, then next best "
                                      "touches (Eq. 25)", belief="tiqf",
                requires=("view-actions", "segmentation", "push-actions", "pick-actions", "touch-actions",
                          "tactile-points"), quick=QUICK_CLUTTER)(_clutter(declutter=True, active_vision=True, touch=True))
register_method("tiqf-visuo-tactile-verify", "beyond the paper: Table I (d) whose touches verify the visual estimate "
                                             "(belief tiqf-verify) instead of replacing it", belief="tiqf-verify",
                requires=("view-actions", "segmentation", "push-actions", "pick-actions", "touch-actions",
                          "tactile-points"), quick=QUICK_CLUTTER)(_clutter(declutter=True, active_vision=True, touch=True))


# ---------------------------------------------------------------------------------------------------------------
# Mixed methods: a belief of one paper with a planner of another (issue 11)

@register_method("tiqf-slide", "mixed: the visuo-tactile paper's TIQF (a Gaussian over the pose, registered to the "
                               "camera and pad surface points, moved by the observed object motion) with RUMI's Slide "
                               "baseline on the rummaging tasks", belief="tiqf", requires=("ee-delta-actions",))
def make_tiqf_slide(env, belief_config, seed, **overrides):
    from activetouch.planning.slide import SlidePlanner

    return SlidePlanner.from_env(env, belief_config, seed, **overrides)


@register_method("rumi-touch-ig", "mixed: RUMI's CHSEL-weighted particles with the touch paper's planner: pokes into "
                                  "importance-sampled particles scored by expected IG (Alg. 1, shared-support entropy "
                                  "Eq. 5, Eq. 10 contact model), static prediction", requires=("ee-delta-actions",),
                 quick={"num_candidates": 4, "waypoints": 3})
def make_rumi_touch_ig(env, belief_config, seed, **overrides):
    from activetouch.planning.particle_ig import ParticleIGPlanner

    return ParticleIGPlanner.from_env(env, belief_config, seed, **overrides)


@register_belief("contact-particles", "mixed: the touch paper's binary-contact filter (Eq. 10 on the step's contact "
                                      "flag, App. B contact-aware resampling) over SE(2) particles from RUMI's prior, "
                                      "moved by the observed object motion", requires=("contact", "object-motion",
                                                                                        "se2-object"))
def make_contact_belief(env, cfg, device):
    from activetouch.experiments.estimators import RummageContactEstimator

    return RummageContactEstimator(env, cfg, device)


@register_method("contact-slide", "mixed: the touch paper's binary-contact filter (belief contact-particles) with "
                                  "RUMI's Slide baseline on the SE(2) rummaging tasks", belief="contact-particles",
                 requires=("ee-delta-actions",))
def make_contact_slide(env, belief_config, seed, **overrides):
    from activetouch.planning.slide import SlidePlanner

    return SlidePlanner.from_env(env, belief_config, seed, **overrides)


@register_method("contact-touch-ig", "mixed: the touch paper's filter and planner on the SE(2) rummaging tasks: "
                                     "binary-contact particles, pokes scored by expected IG (Alg. 1, Eq. 5, Eq. 10)",
                 belief="contact-particles", requires=("ee-delta-actions",),
                 quick={"num_candidates": 4, "waypoints": 3})
def make_contact_touch_ig(env, belief_config, seed, **overrides):
    from activetouch.planning.particle_ig import ParticleIGPlanner

    return ParticleIGPlanner.from_env(env, belief_config, seed, **overrides)
