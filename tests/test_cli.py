"""The command line: argument handling and clear errors."""
import pytest

from activetouch.cli import build_parser, main


def test_run_parses_paper_defaults():
    a = build_parser().parse_args(["run", "mug-0"])
    assert (a.method, a.seed, a.particles, a.steps) == ("rumi", 0, 100, None)


def test_methods_lists_rumi_and_ablations(capsys):
    assert main(["methods"]) == 0
    out = capsys.readouterr().out
    for name in ("rumi", "info-only", "reach-only"):
        assert name in out


def test_unknown_method_is_a_clear_error(capsys, tmp_path):
    assert main(["run", "mug-0", "--method", "nope", "--out", str(tmp_path)]) == 2
    assert "unknown method 'nope'" in capsys.readouterr().err


def test_tasks_lists_nine(capsys):
    assert main(["tasks"]) == 0
    out = capsys.readouterr().out
    assert all(f"{o}-{i}" in out for o in ("mug", "drill", "box") for i in range(3))


@pytest.mark.parametrize("args, message", [(["--steps", "0"], "steps must be"), (["--particles", "0"], "particles must"),
                                           (["--seed", "-1"], "seed must"),
                                           (["--particles", "1"], "needs at least 10 particles"),
                                           (["--particles", "2", "--chsel-iterations", "1"], "needs at least 3")])
def test_bad_episode_arguments_are_clear_errors(capsys, tmp_path, args, message):
    assert main(["run", "mug-0", "--out", str(tmp_path), *args]) == 2
    assert message in capsys.readouterr().err


def test_unknown_task_is_a_clear_error(capsys, tmp_path):
    assert main(["run", "mug-9", "--out", str(tmp_path)]) == 2
    assert "unknown task 'mug-9'" in capsys.readouterr().err


def _err(capsys):
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err
    return err


def test_sweep_has_one_spelling_for_methods(capsys, tmp_path):
    # `--method` used to parse too and was silently ignored (the sweep ran rumi)
    with pytest.raises(SystemExit) as e:
        main(["sweep", "--tasks", "mug-0", "--method", "info-only", "--out", str(tmp_path)])
    assert e.value.code == 2
    assert "unrecognized arguments: --method" in _err(capsys)


@pytest.mark.parametrize("args, message", [
    (["--tasks", "mug-0", "mug-9"], "unknown task 'mug-9'"),
    (["--tasks", "mug-0", "--methods", "rumi", "nope"], "unknown method 'nope'"),
    (["--tasks", "mug-0", "--seeds", "0"], "--seeds must be >= 1"),
    (["--tasks", "mug-0", "--workers", "0"], "workers must be >= 1"),
    (["--tasks", "mug-0", "--horizon", "2"], "num_support_pts (8) must be <= horizon (2)"),
    (["--tasks", "mug-0", "--device", "cuda:7" if __import__("torch").cuda.is_available() else "cuda"], "cuda"),
    (["--tasks", "mug-0", "--device", "tpu"], "is not a torch device"),
])
def test_bad_sweeps_fail_before_any_episode(capsys, tmp_path, args, message):
    out = tmp_path / "sweep"
    assert main(["sweep", *args, "--out", str(out)]) == 2
    assert message in _err(capsys)
    assert not out.exists() or not any(out.iterdir()), "a rejected sweep left folders behind"


def test_output_that_is_a_file_is_a_clear_error(capsys, tmp_path):
    f = tmp_path / "file"
    f.write_text("x")
    assert main(["run", "mug-0", "--out", str(f)]) == 2
    assert "is not a folder" in _err(capsys)


def test_bad_planner_override_fails_before_work(capsys, tmp_path):
    assert main(["run", "mug-0", "--horizon", "2", "--out", str(tmp_path / "r")]) == 2
    assert "horizon" in _err(capsys)
    assert not (tmp_path / "r").exists()


def _fake_episode(root, task, method, seed, **cfg):
    from dataclasses import asdict

    from activetouch.experiments.records import write_json_atomic
    from activetouch.experiments.runner import EpisodeConfig, episode_dir

    d = episode_dir(root, task, method, seed)
    config = asdict(EpisodeConfig(task=task, method=method, seed=seed, **cfg))
    write_json_atomic(d / "summary.json", {"task": task, "method": method, "seed": seed, "success": True,
                                           "strict_success": True, "first_strict_success_step": 1,
                                           "cumulative_nll": 10.0, "initial_nll": 5.0, "config": config})
    return d


def test_sweep_resumed_with_other_settings_is_refused(capsys, tmp_path):
    _fake_episode(tmp_path, "mug-0", "rumi", 0, steps=40)
    assert main(["sweep", "--tasks", "mug-0", "--seeds", "1", "--steps", "30", "--out", str(tmp_path)]) == 2
    err = _err(capsys)
    assert "other settings" in err and "steps: 40 != 30" in err


def test_sweep_resumed_with_other_code_is_refused_unless_allowed(capsys, tmp_path):
    """A code change can change every result without changing a setting: a finished episode whose recorded package
    digest differs from the running code's is not reused unless --allow-other-code says so."""
    import json

    from activetouch.experiments.records import write_json_atomic
    from activetouch.experiments.runner import code_version, source_digest

    here = code_version()["source"]
    assert here == source_digest() and len(here) == 16
    d = _fake_episode(tmp_path, "mug-0", "rumi", 0)
    s = json.loads((d / "summary.json").read_text())
    write_json_atomic(d / "summary.json", {**s, "platform": {"source": "0" * 16}})
    args = ["sweep", "--tasks", "mug-0", "--seeds", "1", "--no-figures", "--out", str(tmp_path)]
    assert main(args) == 2
    err = _err(capsys)
    assert "other code" in err and "0" * 16 in err and here in err and "--allow-other-code" in err
    assert main([*args, "--allow-other-code"]) == 0  # reused: nothing left to run
    write_json_atomic(d / "summary.json", {**s, "platform": {**s.get("platform", {}), "source": here}})
    assert main(args) == 0  # the same code resumes
    capsys.readouterr()
    assert main(["table", str(tmp_path)]) == 0 and f"files {here[:8]}" in capsys.readouterr().out  # names the digest
    write_json_atomic(d / "summary.json", s)  # recorded before the digest existed: other code, unless allowed
    assert main(args) == 2 and "records no package digest" in _err(capsys)


def test_box_episode_run_before_the_task_defaults_changed_is_not_resumed(capsys, tmp_path):
    """box-* run with the contact-placed proposals (TaskSpec.belief_defaults); an episode recorded without them
    (an older sweep folder) must not be counted as finished by a resume, nor pooled with newer ones in a table."""
    from activetouch.experiments.records import write_json_atomic
    from activetouch.experiments.runner import task_belief_defaults

    assert task_belief_defaults("box-0", "rumi") == {"reinvigorate": 100}
    assert task_belief_defaults("mug-0", "rumi") == {}
    # the task's defaults are RUMI belief settings: a method with another belief runs (and records) without them
    assert task_belief_defaults("box-0", "contact-slide") == {}
    _fake_episode(tmp_path, "box-0", "rumi", 0)  # no task_belief_defaults recorded: the old default
    assert main(["sweep", "--tasks", "box-0", "--seeds", "1", "--out", str(tmp_path)]) == 2
    assert "belief settings with the task's defaults: {} != {'reinvigorate': 100}" in _err(capsys)
    d = _fake_episode(tmp_path / "t", "box-0", "rumi", 1)
    s = __import__("json").loads((d / "summary.json").read_text())
    write_json_atomic(d / "summary.json", {**s, "task_belief_defaults": {"reinvigorate": 100}})
    _fake_episode(tmp_path / "t", "box-0", "rumi", 2)
    assert main(["table", str(tmp_path / "t")]) == 2
    assert "different belief settings" in _err(capsys)
    _fake_episode(tmp_path / "u", "box-0", "rumi", 1, belief={"reinvigorate": 100})  # the same, said explicitly
    assert main(["table", str(tmp_path / "u")]) == 0
    # another method on the same task records its own belief's defaults (none): one table holds both
    for method, td in (("rumi", {"reinvigorate": 100}), ("tiqf-slide", {})):
        d = _fake_episode(tmp_path / "v", "box-0", method, 0)
        s = __import__("json").loads((d / "summary.json").read_text())
        write_json_atomic(d / "summary.json", {**s, "task_belief_defaults": td})
    assert main(["table", str(tmp_path / "v")]) == 0


def test_table_refuses_mixed_settings_and_repeated_seeds(capsys, tmp_path):
    _fake_episode(tmp_path / "a", "mug-0", "rumi", 0)
    _fake_episode(tmp_path / "a", "mug-0", "rumi", 1, particles=10)
    assert main(["table", str(tmp_path / "a")]) == 2
    assert "different settings" in _err(capsys)
    _fake_episode(tmp_path / "b" / "x", "mug-0", "rumi", 3)
    _fake_episode(tmp_path / "b" / "y", "mug-0", "rumi", 3)
    assert main(["table", str(tmp_path / "b")]) == 2
    assert "occurs twice" in _err(capsys)
    assert main(["table", str(tmp_path / "b" / "x")]) == 0
    out = capsys.readouterr().out
    assert "1 episodes" in out and "| mug-0 | rumi | 1/1 |" in out


def test_table_header_names_the_code_that_made_the_episodes():
    from activetouch.cli import _code_line

    a = {"platform": {"commit": "a" * 40, "modified": False}}
    b = {"platform": {"commit": "b" * 40, "modified": True}}
    line = _code_line([a, a, b, {"platform": {"cpu": "x"}}, {"platform": {"commit": None, "modified": None}}])
    assert line == ("code: commit aaaaaaaa (2 episodes), commit bbbbbbbb+modified (1 episodes), "
                    "unrecorded (1 episodes), no git checkout (1 episodes)")


def test_output_cut_short_by_a_closed_pipe_is_not_a_traceback(monkeypatch):
    """`activetouch tasks | head -1`: the reader leaves, writes raise BrokenPipeError; the CLI stops quietly."""
    import sys

    class Closed:
        def write(self, s):
            raise BrokenPipeError(32, "Broken pipe")

        def flush(self):
            raise BrokenPipeError(32, "Broken pipe")

    monkeypatch.setattr(sys, "stdout", Closed())
    assert main(["tasks"]) == 0


def test_table_stop_at_beta_t_replays_no_terminate_episodes_and_refuses_terminated_ones(capsys, tmp_path):
    import json

    from activetouch.experiments.stop_rule import object_diagonal

    lc = object_diagonal("box-0")
    for seed, (nll_late, apc_late) in enumerate([(100.0, 0.025), (100.0, 0.015)]):
        d = _fake_episode(tmp_path / "free", "box-0", "rumi", seed, terminate_on_convergence=False)
        s = json.loads((d / "summary.json").read_text())
        write = {**s, "nll_threshold": 150.0, "prior_apc": 0.3, "apc_termination": False}
        (d / "summary.json").write_text(json.dumps(write))
        rows = [(0, 900.0, 0.3), (1, 400.0, 0.025), (2, nll_late, apc_late)]
        (d / "steps.csv").write_text("step,nll,apc\n" + "".join(f"{k},{n},{a * lc}\n" for k, n, a in rows))
    assert main(["table", str(tmp_path / "free"), "--stop-at-beta-t", "0.03", "0.02"]) == 0
    out = capsys.readouterr().out
    # beta 0.03: both stop at step 1 (APC 0.025 l_c) before their NLL reaches 150; beta 0.02: seed 0 never stops
    # (runs to step 2, a success), seed 1 stops at step 2 (APC 0.015 l_c) with its success
    assert "| 0.03 | box-0 | rumi | 0/2 |" in out and "| 0.02 | box-0 | rumi | 2/2 |" in out
    d = _fake_episode(tmp_path / "stopped", "box-0", "rumi", 0)  # terminated (the default)
    assert main(["table", str(tmp_path / "stopped"), "--stop-at-beta-t", "0.03"]) == 2
    assert "has no steps.csv" in _err(capsys)
    (d / "steps.csv").write_text("step,nll,apc\n0,900.0,0.3\n")
    s = json.loads((d / "summary.json").read_text())
    s.update(nll_threshold=150.0, prior_apc=0.3, apc_termination=True)
    (d / "summary.json").write_text(json.dumps(s))
    assert main(["table", str(tmp_path / "stopped"), "--stop-at-beta-t", "0.03"]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and "ran with APC termination" in captured.err and captured.err.count("\n") == 1


def test_beta_t_is_refused_where_no_belief_stops_on_apc(capsys, tmp_path):
    # the touch-only grasp tasks' particle filter ends with the grasp, not on APC: a --beta-t there would be ignored
    assert main(["run", "grasp-box-0", "--method", "touch-uninformed", "--beta-t", "0.02", "--out", str(tmp_path)]) == 2
    err = _err(capsys)
    assert "--beta-t" in err and "never stops on APC" in err
    assert main(["run", "mug-0", "--beta-t", "1.5", "--out", str(tmp_path / "m")]) == 2
    assert "beta_t must be in (0, 1)" in _err(capsys)
