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
                                           (["--seed", "-1"], "seed must")])
def test_bad_episode_arguments_are_clear_errors(capsys, tmp_path, args, message):
    assert main(["run", "mug-0", "--out", str(tmp_path), *args]) == 2
    assert message in capsys.readouterr().err


def test_unknown_task_is_a_clear_error(capsys, tmp_path):
    assert main(["run", "mug-9", "--out", str(tmp_path)]) == 2
    assert "unknown task 'mug-9'" in capsys.readouterr().err
