"""Episode logs (``episode.h5``) and offline replay (issue 11): the serialiser is lossless, a log survives a
crash of its writer, and a recorded sim episode replayed through the estimator reproduces the online
``steps.csv`` exactly, for each family (RUMI rummaging, touch-only grasping, visuo-tactile clutter)."""
from __future__ import annotations

import dataclasses
import enum
import json
import struct
import subprocess
import sys
import textwrap
from collections import namedtuple
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from activetouch.experiments import episode_log as EL
from activetouch.experiments.records import read_steps


# ------------------------------------------------------------------------------------------------ helpers
def same(a, b, path="value"):
    """Exact equality: same Python types, same dtypes and shapes, same bits (NaN payloads, -0.0 included)."""
    assert type(a) is type(b), f"{path}: {type(a).__name__} vs {type(b).__name__}"
    if isinstance(a, (np.ndarray, np.generic)):
        a, b = np.asarray(a), np.asarray(b)
        assert a.dtype == b.dtype and a.shape == b.shape, f"{path}: {a.dtype}{a.shape} vs {b.dtype}{b.shape}"
        assert a.tobytes() == b.tobytes(), f"{path}: bits differ"
    elif torch.is_tensor(a):
        assert a.dtype == b.dtype and a.shape == b.shape, f"{path}: {a.dtype}{tuple(a.shape)} vs {b.dtype}{tuple(b.shape)}"
        assert b.device.type == "cpu" and a.requires_grad == b.requires_grad, path

        def bits(t):
            return t.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy().tobytes()

        assert bits(a) == bits(b), f"{path}: bits differ"
    elif isinstance(a, dict):
        assert list(a) == list(b), f"{path}: keys {list(a)} vs {list(b)}"
        for k in a:
            same(a[k], b[k], f"{path}[{k!r}]")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), f"{path}: length {len(a)} vs {len(b)}"
        for i, (x, y) in enumerate(zip(a, b)):
            same(x, y, f"{path}[{i}]")
    elif dataclasses.is_dataclass(a):
        for f in dataclasses.fields(a):
            same(getattr(a, f.name), getattr(b, f.name), f"{path}.{f.name}")
    elif isinstance(a, float):
        assert struct.pack("<d", a) == struct.pack("<d", b), f"{path}: {a!r} vs {b!r}"
    elif hasattr(type(a), "__slots__") and not isinstance(a, enum.Enum):
        for n in type(a).__slots__:
            same(getattr(a, n), getattr(b, n), f"{path}.{n}")
    else:
        assert a == b, f"{path}: {a!r} vs {b!r}"


def roundtrip(value, tmp_path):
    path = tmp_path / "value.h5"
    with h5py.File(path, "w") as f:
        EL.encode(f, "x", value)
    with h5py.File(path, "r") as f:
        return EL.decode(f["x"])


# ------------------------------------------------------------------------------------------------ (a) serialiser
SCALARS = [None, True, False, 0, -7, 2**63 - 1, -(2**63), 2**80, 1.5, -0.0, float("nan"), float("inf"), 1e-310,
           3 + 4j, "", "plain", "ünïcödé ✓", "nul\x00inside", b"", b"\x00\xffbytes",
           np.float32(1.25), np.float64(-2.5), np.int8(-3), np.uint64(2**64 - 1), np.bool_(True), np.complex64(1j)]

ARRAYS = [np.arange(12, dtype=np.float32).reshape(3, 4), np.array([np.nan, -0.0, np.inf]),
          np.arange(6, dtype=np.int64).reshape(2, 3), np.array([True, False, True]), np.zeros((0, 3)),
          np.zeros((0,), dtype=bool), np.array(3.5), np.array(7, dtype=np.int16), np.arange(5, dtype=np.uint8),
          np.arange(4, dtype=np.float16), np.array([1 + 2j, 3j], dtype=np.complex64),
          np.arange(4, dtype=">f8"), np.arange(12.0).reshape(3, 4).T, np.array([b"ab", b"c"]),
          np.array(["mug", "drill"]), np.array(["2024-01-02"], dtype="datetime64[D]"),
          np.random.default_rng(0).normal(size=(72, 96, 3)).astype(np.float32)]

TENSORS = [torch.arange(6, dtype=torch.float32).reshape(2, 3), torch.tensor([float("nan"), -0.0]),
           torch.arange(5), torch.tensor([True, False]), torch.zeros(0, 3), torch.tensor(2.5),
           torch.tensor(3, dtype=torch.int32), torch.arange(4, dtype=torch.uint8), torch.eye(4, dtype=torch.float64),
           torch.arange(4, dtype=torch.bfloat16), torch.arange(4, dtype=torch.float16),
           torch.tensor([1 + 1j], dtype=torch.complex64), torch.arange(12.0).reshape(3, 4).t(),
           torch.ones(3, requires_grad=True), torch.get_rng_state()]


@pytest.mark.parametrize("value", SCALARS, ids=lambda v: f"{type(v).__name__}:{v!r}"[:40])
def test_scalars_roundtrip(value, tmp_path):
    same(value, roundtrip(value, tmp_path))


@pytest.mark.parametrize("value", ARRAYS, ids=lambda a: f"{a.dtype.str}{a.shape}")
def test_arrays_roundtrip(value, tmp_path):
    same(value, roundtrip(value, tmp_path))


@pytest.mark.parametrize("value", TENSORS, ids=lambda t: f"{t.dtype}{tuple(t.shape)}")
def test_tensors_roundtrip(value, tmp_path):
    same(value, roundtrip(value, tmp_path))


def test_containers_roundtrip(tmp_path):
    from activetouch.observations import Semantics

    g = torch.Generator().manual_seed(3)
    value = {"poses": torch.randn(5, 4, 4, generator=g), "nested": {"w": torch.rand(5, generator=g).double(),
                                                                   "ids": torch.arange(5), "deeper": {"b": True}},
             "tuple": (1, 2.0, "three", None, (np.zeros(2),)), "list": [[], [1], {"k": [b"x"]}], "empty": {},
             "a/b": 1, "": 2, ".": 3, "@0": 4, "ключ": 5, "semantics": Semantics.FREE,
             "numpy_rng": np.random.get_state()}
    same(value, roundtrip(value, tmp_path))
    assert list(roundtrip(value, tmp_path)) == list(value)  # key order kept


def test_observation_families_roundtrip(tmp_path):
    from activetouch.experiments.runner import EpisodeConfig
    from activetouch.observations import Features
    from activetouch.sim.camera import PinholeCamera
    from activetouch.sim.clutter_env import (ClutterObservation, PickAction, PushAction, StopAction, TouchAction,
                                             ViewAction)
    from activetouch.sim.env import Observation
    from activetouch.sim.grasp_env import GraspAction, PokeAction, RolloutResult, TouchObservation

    rng = np.random.default_rng(1)
    rumi = Observation(features=Features(torch.rand(6, 3), [0, 1, 1, 0, 2, 1]), ee_pose=torch.eye(4),
                       in_contact=True, dT=None)
    touch = TouchObservation(z=np.array([False, True]), q=rng.normal(size=(3, 7)), ee=rng.normal(size=(3, 4)),
                             stopped_early=True, contact_force=4.5, tau_norm=rng.random(2),
                             ctrl=rng.normal(size=(7, 9)), seg_end=np.array([3, 6]), init_state=rng.normal(size=27),
                             warmstart=None, ctrl0=rng.normal(size=9), z_period=np.array([3, 5]),
                             z_samples=rng.random(7) > 0.5, tau_samples=rng.random(7), force_samples=rng.random(7),
                             true_contact_samples=rng.random(7) > 0.5)
    cloud = rng.normal(size=(6, 8, 3))
    cloud[0, 0] = np.nan
    clutter = ClutterObservation(kind="view", points=rng.normal(size=(4, 3)), seg=rng.integers(-1, 3, (6, 8)),
                                 cloud=cloud, camera=PinholeCamera(pos=(0.5, 0.0, 0.6), target=(0.0, 0.0, 0.1)),
                                 in_contact=False, success=True, contact_label=2)
    actions = [PokeAction(np.array([[0.3, 0.0, 0.1, 0.0]])), GraspAction(np.array([0.1, 0.2, 0.3])),
               ViewAction((0.5, 0.0, 0.6), (0.0, 0.0, 0.1)), TouchAction((0.3, 0.0, 0.1), (-1.0, 0.0, 0.0)),
               PushAction(1, (0.3, 0.0, 0.05), (0.0, 1.0, 0.0)), PickAction(2, (0.1, 0.1, 0.1), 0.5, 0.06),
               StopAction("settled"), np.array([0.5, -0.5, 0.0], dtype=np.float32)]
    named = RolloutResult(torch.zeros(2, 1, 3), torch.tensor([True, False]), torch.tensor([-1, 0]))
    cfg = EpisodeConfig(task="grasp-box-0", planner={"pokes": [[[0.3, 0.0, 0.1, 0.0]]], "t": (1, 2)})
    for v in (rumi, touch, clutter, *actions, named, cfg):
        out = roundtrip(v, tmp_path)
        same(v, out, type(v).__name__)
    assert isinstance(roundtrip(rumi, tmp_path).features, Features)


@dataclasses.dataclass
class NotOurs:
    x: int = 1


def test_serialiser_refuses(tmp_path):
    with h5py.File(tmp_path / "bad.h5", "w") as f:
        EL.encode(f, "foreign", NotOurs())  # written, but a log may only name activetouch classes
        with pytest.raises(ValueError, match="only classes under activetouch"):
            EL.decode(f["foreign"])
        g = f.create_group("forged")
        g.attrs["kind"], g.attrs["class"] = "dataclass", "os:system"
        with pytest.raises(ValueError, match="only classes under activetouch"):
            EL.decode(g)
        with pytest.raises(TypeError, match="cannot log"):
            EL.encode(f, "obj", object())
        with pytest.raises(TypeError, match="keys must be str"):
            EL.encode(f, "intkeys", {1: 2})
        with pytest.raises(TypeError, match="object arrays"):
            EL.encode(f, "objarr", np.array([None, 1], dtype=object))
        with pytest.raises(TypeError, match="cannot log"):
            EL.encode(f, "set", {1})
        EL.encode(f, "nt", namedtuple("P", "a")(1))
        with pytest.raises(ValueError, match="only classes under activetouch"):
            EL.decode(f["nt"])


# ------------------------------------------------------------------------------------------------ (b) crash safety
WRITER = """
import os, sys, numpy as np, torch, h5py
from activetouch.experiments import episode_log as EL
from activetouch.experiments.runner import EpisodeConfig
from activetouch.sim.grasp_env import PokeAction
cfg = EpisodeConfig(task="grasp-box-0", method="scripted-poke", steps=5)
w = EL.EpisodeLogWriter(sys.argv[1], cfg, {"points": np.zeros((0, 3))}, {"true_pose": torch.eye(4)})
for t in (1, 2):
    c = w.capture()
    w.step(t, PokeAction(np.full((1, 4), 0.1 * t)), {"points": np.full((t, 3), float(t))},
           {"true_pose": torch.eye(4) * t}, None, c, {"replanned": 1.0})
# step 3: the process dies in the middle of writing it, the file still open
f = h5py.File(sys.argv[1], "a")
g = f["steps"].create_group("000003")
EL.encode(g, "action", PokeAction(np.zeros((1, 4))))
EL.encode(g, "obs", {"points": np.ones((1000, 3))})
os._exit(3)
"""


def test_log_survives_a_crash(tmp_path):
    path = tmp_path / "episode.h5"
    p = subprocess.run([sys.executable, "-c", textwrap.dedent(WRITER), str(path)], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 3, p.stderr
    with EL.read_log(path) as lg:
        assert not lg.meta["complete"]
        assert len(lg) == 2, "the finished steps are readable, the interrupted one is left out"
        steps = list(lg.steps())
        assert [s["step"] for s in steps] == [1, 2]
        same(steps[1]["obs"], {"points": np.full((2, 3), 2.0)})
        same(steps[1]["info"], {"true_pose": torch.eye(4) * 2})
        assert steps[0]["t_wall"] <= steps[1]["t_wall"] and steps[0]["t_episode"] <= steps[1]["t_episode"]
        assert lg.config.task == "grasp-box-0"


def test_no_log_switch(tmp_path, monkeypatch):
    from activetouch.experiments.runner import EpisodeConfig

    monkeypatch.setenv(EL.NO_LOG_ENV, "1")
    w = EL.open_episode_log(tmp_path, EpisodeConfig(), None, {})
    w.step(1, None, None, {}, None, w.capture(), {})
    w.close()
    assert not (tmp_path / EL.LOG_NAME).exists()


# ------------------------------------------------------------------------------------------------ (c) replay
PAIRS = [("clutter-mustard", "tiqf-static"), ("grasp-box-0", "scripted-poke"), ("mug-0", "scripted")]


@pytest.fixture(scope="module")
def online(tmp_path_factory):
    """One short recorded episode of each family (the contract's quick settings, 2 steps)."""
    from activetouch.experiments.contract import quick_config
    from activetouch.experiments.runner import run_episode

    root = tmp_path_factory.mktemp("online")
    runs = {}
    for task, method in PAIRS:
        d = root / task
        summary = run_episode(quick_config(task, method, steps=2), d)
        runs[task] = (d, summary)
    return runs


def _assert_same_rows(online_csv: Path, replay_csv: Path):
    a, b = read_steps(online_csv), read_steps(replay_csv)
    assert list(a[0]) == list(b[0]), "the replay writes the runner's columns"
    assert len(a) == len(b), f"{len(a)} online rows vs {len(b)} replayed"
    for ra, rb in zip(a, b):
        diff = {k: (ra[k], rb[k]) for k in ra if not k.endswith("_s") and ra[k] != rb[k]}
        assert not diff, f"step {ra['step']}: online vs replay {diff}"


@pytest.mark.parametrize("task,method", PAIRS)
def test_replay_reproduces_the_online_belief(online, task, method):
    d, summary = online[task]
    log = d / EL.LOG_NAME
    with EL.read_log(log) as lg:
        assert (lg.meta["task"], lg.meta["method"], int(lg.meta["seed"])) == (task, method, 0)
        assert lg.meta["complete"] and len(lg) == summary["steps"] == 2
        assert json.loads(lg.meta["config"])["task"] == task
        steps = list(lg.steps())
        assert all("torch" in s["rng"] and "numpy" in s["rng"] and "generator" in s["rng"] for s in steps)
        assert 0 < steps[0]["t_episode"] <= steps[1]["t_episode"]
    rep = EL.replay(log)
    out = d / f"replay-{method}"
    assert Path(rep["out_dir"]) == out and (out / "summary.json").exists()
    _assert_same_rows(d / "steps.csv", out / "steps.csv")
    saved = json.loads((out / "summary.json").read_text())
    assert (saved["task"], saved["method"], saved["seed"], saved["steps"]) == (task, method, 0, 2)
    assert saved["source_log"] == str(log) and saved["success"] == summary["success"]


def test_replay_with_another_method(online, tmp_path):
    """Any compatible method's estimator runs on a log (here: the clutter belief of the paper's method on a
    static-vision log; it is the same TIQF belief, so the rows agree too)."""
    d, _ = online["clutter-mustard"]
    rep = EL.replay(d, method="tiqf-visuo-tactile", out_dir=tmp_path / "vt")
    assert rep["method"] == "tiqf-visuo-tactile" and rep["logged_method"] == "tiqf-static"
    _assert_same_rows(d / "steps.csv", tmp_path / "vt" / "steps.csv")


# ------------------------------------------------------------------------------------------------ (d) bad inputs
def test_replay_refuses_bad_input(online, tmp_path):
    d, _ = online["clutter-mustard"]
    log = d / EL.LOG_NAME
    with pytest.raises(ValueError, match="unknown method"):
        EL.replay(log, method="no-such-method", out_dir=tmp_path / "x")
    with pytest.raises(ValueError, match="cannot run on task"):
        EL.replay(log, method="rumi", out_dir=tmp_path / "x")
    text = tmp_path / "steps.csv"
    text.write_text("step,nll\n0,1\n")
    with pytest.raises(ValueError, match="not an episode log"):
        EL.replay(text)
    with pytest.raises(ValueError, match="no episode log"):
        EL.replay(tmp_path / "missing.h5")
    with h5py.File(tmp_path / "other.h5", "w") as f:
        f["x"] = 1
    with pytest.raises(ValueError, match="not an activetouch episode log"):
        EL.replay(tmp_path / "other.h5")
    newer = tmp_path / "newer.h5"
    newer.write_bytes(log.read_bytes())
    with h5py.File(newer, "a") as f:
        f.attrs["format_version"] = 99
    with pytest.raises(ValueError, match="format version 99"):
        EL.replay(newer)


def test_cli_replay(online, tmp_path, capsys):
    from activetouch.cli import main

    d, _ = online["clutter-mustard"]
    assert main(["replay", str(d / EL.LOG_NAME), "--out", str(tmp_path / "cli")]) == 0
    out = capsys.readouterr().out
    assert "replayed tiqf-static on clutter-mustard" in out and "adi_mm" in out and str(tmp_path / "cli") in out
    assert (tmp_path / "cli" / "steps.csv").exists()
    text = tmp_path / "notalog.txt"
    text.write_text("hello")
    assert main(["replay", str(text)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "not an episode log" in err and "\n" not in err
    assert main(["replay", str(d / EL.LOG_NAME), "--method", "touch-ig"]) == 2
    assert "cannot run on task" in capsys.readouterr().err


def test_config_of_an_older_log_gets_new_fields_defaults(tmp_path):
    from activetouch.experiments.runner import EpisodeConfig

    with h5py.File(tmp_path / "c.h5", "w") as f:
        EL.encode(f, "config", EpisodeConfig(task="mug-1", belief={"lam": 1.0}))
        del f["config"]["belief"]  # as if the log predates the field
        cfg = EL.decode(f["config"])
    assert cfg.task == "mug-1" and cfg.belief == {}
