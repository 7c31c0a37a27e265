"""Episode logs: every run's observations, actions and timestamps in one file, and offline replay of any
estimator on a log (as MidasTouch re-runs its filter on recorded data).

Format: HDF5 (``episode.h5`` in the episode folder), written with h5py.

Why HDF5: a step holds arrays of many dtypes and shapes (float32 point clouds ``(72, 96, 3)``, bool contact
flags, int64 segmentations, uint8 RNG states, MuJoCo float64 states) plus small nested records (dataclasses,
dicts). HDF5 stores each array bit-exactly with its dtype and shape, nests them in groups with attributes, is one
self-describing file, is readable from C, C++, MATLAB, Julia and Python without this package, and is a
maintained format (The HDF Group, h5py). Parquet is columnar and tabular: ragged per-step arrays and nested
records become list columns or blobs, and a file is only readable once its footer is written, so a crashed run
leaves nothing. MCAP (the ROS 2 bag format) is a good fit for streams of typed messages from live robots, but it
needs a schema per message type (ROS msg / protobuf / flatbuffers) for arrays to be readable by other tools; the
observations here are Python dataclasses of numpy / torch arrays, which HDF5 stores directly.

Layout (``FORMAT_VERSION`` 1)::

    /                     attrs: format, format_version, task, method, seed, config (EpisodeConfig as JSON),
                                 platform (JSON), activetouch_version, created (time.time), complete, steps
    /config               the EpisodeConfig itself (encoded: exact, incl. tuples)
    /reset                obs, info, rng (the RNG states the estimator's initialisation starts from)
                          attrs: t_wall, t_episode, written
    /steps/000001 ...     action (the executed action), obs, info, ee_before (what the runner passed to observe),
                          planner (the planner's row fields: timings, replanned, expected IG, ...),
                          rng (global torch / numpy RNG and the episode generator before ``est.observe``)
                          attrs: step, t_wall (time.time()), t_episode (s since the reset), written

Each value is written by :func:`encode` as one node with a ``kind`` attribute; :func:`decode` reads it back
exactly (dtypes, shapes, bits, Python types). The file is opened in append mode, one step written, flushed and
closed at every step: a crash leaves a readable log of the finished steps (a step is finished when its ``written``
attribute is set). ``ACTIVETOUCH_NO_LOG=1`` turns logging off (e.g. for timing runs).

Replay (:func:`replay`, ``activetouch replay LOG --method M``): the estimator of any method compatible with the
logged task is initialised on the logged reset and updated with every logged step's observation, with the
global RNG states restored before each update (online, the planner draws from them between updates); the same
method reproduces the online ``steps.csv`` exactly (the test in ``tests/test_replay.py``).
"""
from __future__ import annotations

import dataclasses
import enum
import importlib
import json
import logging
import os
import time
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import torch

log = logging.getLogger(__name__)

FORMAT = "activetouch-episode-log"
FORMAT_VERSION = 1
LOG_NAME = "episode.h5"
NO_LOG_ENV = "ACTIVETOUCH_NO_LOG"

_INT64 = (-(2**63), 2**63 - 1)


def _h5py():
    try:
        import h5py
    except ImportError as e:  # pragma: no cover - a dependency
        raise RuntimeError("episode logs need h5py (pip install 'h5py>=3.8')") from e
    return h5py


def _open_for_append(path: Path, attempts: int = 40, wait_s: float = 0.05):
    """``h5py.File(path, "a")``, retried for about 2 s while another reader holds the file (HDF5 refuses a writer
    then): a viewer reading the log must delay the run, never end it."""
    h5py = _h5py()
    for k in range(attempts):
        try:
            return h5py.File(path, "a")
        except OSError:
            if k == attempts - 1:
                raise
            time.sleep(wait_s)


# ---------------------------------------------------------------------------------------------- serialiser
def _class_name(cls: type) -> str:
    return f"{cls.__module__}:{cls.__qualname__}"


def _import_class(name: str) -> type:
    """The class ``module:qualname``; only classes under ``activetouch.`` are imported (a log is data, not code)."""
    mod, sep, qual = str(name).partition(":")
    if not sep or not qual or not (mod == "activetouch" or mod.startswith("activetouch.")):
        raise ValueError(f"refusing to import class {name!r} from a log: only classes under activetouch. are allowed")
    if "<locals>" in qual:
        raise ValueError(f"class {name!r} is local to a function and cannot be imported")
    try:
        obj: Any = importlib.import_module(mod)
        for part in qual.split("."):
            obj = getattr(obj, part)
    except (ImportError, AttributeError) as e:
        raise ValueError(f"class {name!r} named in the log does not exist here ({e})") from None
    if not isinstance(obj, type):
        raise ValueError(f"{name!r} named in the log is not a class")
    return obj


def _is_activetouch(cls: type) -> bool:
    m = getattr(cls, "__module__", "") or ""
    return m == "activetouch" or m.startswith("activetouch.")


def _slots(cls: type) -> list[str]:
    names: list[str] = []
    for c in cls.__mro__:
        s = c.__dict__.get("__slots__", ())
        for n in ((s,) if isinstance(s, str) else s):
            if n not in ("__dict__", "__weakref__") and n not in names:
                names.append(n)
    return names


def _safe_name(key: str, i: int) -> str:
    """HDF5 name of the ``i``-th dict entry: the key itself when it is a valid plain name, else ``@i``."""
    if key and "/" not in key and key not in (".", "..") and not key.startswith("@") and key.isprintable() \
            and key.isascii():
        return key
    return f"@{i}"


def _raw_array(group, name: str, a: np.ndarray):
    """An array of a dtype HDF5 has no type for (unicode, datetime, ...) as its raw bytes."""
    ds = group.create_dataset(name, data=np.frombuffer(a.tobytes(), dtype=np.uint8))
    ds.attrs["raw"] = True
    ds.attrs["shape"] = np.asarray(a.shape, dtype=np.int64)
    return ds


def _array(group, name: str, a: np.ndarray, kind: str):
    if a.dtype.kind == "O":
        raise TypeError(f"{group.name}/{name}: object arrays cannot be logged")
    if a.dtype.kind in "UMm":
        ds = _raw_array(group, name, a)
    else:
        try:
            ds = group.create_dataset(name, data=a)
        except (TypeError, ValueError):
            ds = _raw_array(group, name, a)
    ds.attrs["kind"] = kind
    ds.attrs["dtype"] = a.dtype.str if not a.dtype.fields else "compound"
    return ds


def _read_array(ds) -> np.ndarray:
    if ds.attrs.get("raw", False):
        shape = tuple(int(s) for s in ds.attrs["shape"])
        return np.frombuffer(ds[()].tobytes(), dtype=np.dtype(str(ds.attrs["dtype"]))).reshape(shape).copy()
    a = ds[()]
    if not isinstance(a, np.ndarray):  # a scalar dataset reads as a numpy scalar
        a = np.array(a)
    dt = str(ds.attrs.get("dtype", "compound"))
    if dt != "compound" and a.dtype.str != dt:
        a = a.astype(np.dtype(dt))
    return a


def encode(group, name: str, value: Any):
    """Write ``value`` as the node ``name`` of the HDF5 ``group`` (lossless; see :func:`decode`).

    Supported: None, bool, int, float, complex, str, bytes, numpy arrays and scalars (any dtype but object),
    torch tensors (any dtype; recorded as tensors, decoded on the CPU), tuples, lists, dicts with str keys,
    enums, named tuples, dataclasses and ``__slots__`` classes of activetouch (``Features``). TypeError names
    the path of anything else."""
    h5py = _h5py()
    if value is None:
        ds = group.create_dataset(name, data=h5py.Empty("i1"))
        ds.attrs["kind"] = "none"
        return ds
    if isinstance(value, np.generic):  # before bool / int / float: np.float64 is a float
        return _array(group, name, np.asarray(value), "npscalar")
    if isinstance(value, np.ndarray):
        return _array(group, name, value, "ndarray")
    if torch.is_tensor(value):
        t = value.detach()
        if t.layout != torch.strided:
            raise TypeError(f"{group.name}/{name}: only dense tensors can be logged, got {t.layout}")
        t = t.cpu().resolve_conj().resolve_neg()
        try:
            a = t.numpy()
            raw = False
        except TypeError:  # bfloat16, float8, ...: no numpy dtype, keep the bits
            a = t.contiguous().reshape(-1).view(torch.uint8).numpy()
            raw = True
        ds = _array(group, name, a, "tensor")
        ds.attrs["torch_dtype"] = str(t.dtype).removeprefix("torch.")
        ds.attrs["device"] = str(value.device)
        ds.attrs["requires_grad"] = bool(value.requires_grad)
        if raw:
            ds.attrs["tensor_shape"] = np.asarray(tuple(t.shape), dtype=np.int64)
        return ds
    if isinstance(value, enum.Enum):
        g = group.create_group(name)
        g.attrs["kind"] = "enum"
        g.attrs["class"] = _class_name(type(value))
        encode(g, "value", value.value)
        return g
    if type(value) is bool:
        ds = group.create_dataset(name, data=np.bool_(value))
        ds.attrs["kind"] = "bool"
        return ds
    if type(value) is int:
        big = not (_INT64[0] <= value <= _INT64[1])
        ds = group.create_dataset(name, data=str(value) if big else np.int64(value))
        ds.attrs["kind"] = "int"
        return ds
    if type(value) is float:
        ds = group.create_dataset(name, data=np.float64(value))
        ds.attrs["kind"] = "float"
        return ds
    if type(value) is complex:
        ds = group.create_dataset(name, data=np.complex128(value))
        ds.attrs["kind"] = "complex"
        return ds
    if type(value) is str:
        if "\x00" in value:  # HDF5 strings end at a NUL: keep the UTF-8 bytes
            ds = group.create_dataset(name, data=np.frombuffer(value.encode("utf-8", "surrogatepass"), np.uint8))
            ds.attrs["utf8_bytes"] = True
        else:
            ds = group.create_dataset(name, data=value, dtype=h5py.string_dtype("utf-8"))
        ds.attrs["kind"] = "str"
        return ds
    if type(value) is bytes:
        ds = group.create_dataset(name, data=np.frombuffer(value, dtype=np.uint8))
        ds.attrs["kind"] = "bytes"
        return ds
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        g = group.create_group(name)
        g.attrs["kind"] = "dataclass"
        g.attrs["class"] = _class_name(type(value))
        for f in dataclasses.fields(value):
            encode(g, f.name, getattr(value, f.name))
        return g
    if isinstance(value, tuple) and hasattr(type(value), "_fields"):  # a named tuple
        g = group.create_group(name)
        g.attrs["kind"] = "namedtuple"
        g.attrs["class"] = _class_name(type(value))
        for i, v in enumerate(value):
            encode(g, str(i), v)
        g.attrs["len"] = len(value)
        return g
    if type(value) in (tuple, list):
        g = group.create_group(name)
        g.attrs["kind"] = type(value).__name__
        g.attrs["len"] = len(value)
        for i, v in enumerate(value):
            encode(g, str(i), v)
        return g
    if type(value) is dict:
        bad = [k for k in value if type(k) is not str]
        if bad:
            raise TypeError(f"{group.name}/{name}: dict keys must be str, got {bad[:3]!r}")
        g = group.create_group(name)
        g.attrs["kind"] = "dict"
        g.attrs["keys"] = json.dumps(list(value))
        for i, (k, v) in enumerate(value.items()):
            encode(g, _safe_name(k, i), v)
        return g
    cls = type(value)
    if _is_activetouch(cls) and _slots(cls) and not hasattr(value, "__dict__"):  # e.g. observations.Features
        g = group.create_group(name)
        g.attrs["kind"] = "slots"
        g.attrs["class"] = _class_name(cls)
        names = [n for n in _slots(cls) if hasattr(value, n)]
        g.attrs["slots"] = json.dumps(names)
        for n in names:
            encode(g, n, getattr(value, n))
        return g
    raise TypeError(f"{group.name}/{name}: cannot log a {cls.__module__}.{cls.__qualname__}")


def _new(cls: type, values: dict[str, Any]):
    """An instance of ``cls`` with exactly these attribute values (no ``__init__`` / ``__post_init__``: they
    could convert what was logged)."""
    obj = cls.__new__(cls)
    for k, v in values.items():
        object.__setattr__(obj, k, v)
    return obj


def decode(node) -> Any:
    """The value :func:`encode` wrote as ``node`` (exact: dtypes, shapes, bits and Python types). Classes are
    imported by name, only from ``activetouch.`` (ValueError otherwise)."""
    kind = node.attrs.get("kind")
    if isinstance(kind, bytes):
        kind = kind.decode()
    if kind is None:
        raise ValueError(f"{node.name} is not an encoded value (no kind attribute)")
    if kind == "none":
        return None
    if kind == "ndarray":
        return _read_array(node)
    if kind == "npscalar":
        return _read_array(node)[()]
    if kind == "tensor":
        a = _read_array(node)
        dtype = getattr(torch, str(node.attrs["torch_dtype"]))
        if "tensor_shape" in node.attrs:
            t = torch.from_numpy(a.copy()).view(dtype).reshape(tuple(int(s) for s in node.attrs["tensor_shape"]))
        else:
            t = torch.from_numpy(a if a.flags.c_contiguous and a.flags.writeable else a.copy(order="C"))
            if t.dtype != dtype:
                t = t.to(dtype)
        if node.attrs.get("requires_grad", False):
            t.requires_grad_(True)
        return t
    if kind == "bool":
        return bool(node[()])
    if kind == "int":
        v = node[()]
        return int(v.decode() if isinstance(v, bytes) else v)
    if kind == "float":
        return float(node[()])
    if kind == "complex":
        return complex(node[()])
    if kind == "str":
        if node.attrs.get("utf8_bytes", False):
            return node[()].tobytes().decode("utf-8", "surrogatepass")
        return node.asstr()[()]
    if kind == "bytes":
        return node[()].tobytes()
    if kind in ("list", "tuple"):
        items = [decode(node[str(i)]) for i in range(int(node.attrs["len"]))]
        return items if kind == "list" else tuple(items)
    if kind == "dict":
        keys = json.loads(node.attrs["keys"])
        return {k: decode(node[_safe_name(k, i)]) for i, k in enumerate(keys)}
    if kind == "enum":
        return _import_class(node.attrs["class"])(decode(node["value"]))
    if kind == "namedtuple":
        cls = _import_class(node.attrs["class"])
        return cls(*(decode(node[str(i)]) for i in range(int(node.attrs["len"]))))
    if kind == "dataclass":
        cls = _import_class(node.attrs["class"])
        if not dataclasses.is_dataclass(cls):
            raise ValueError(f"{node.attrs['class']!r} named in the log is not a dataclass")
        values = {}
        for f in dataclasses.fields(cls):
            if f.name in node:
                values[f.name] = decode(node[f.name])
            elif f.default is not dataclasses.MISSING:  # a field added after the log was written
                values[f.name] = f.default
            elif f.default_factory is not dataclasses.MISSING:
                values[f.name] = f.default_factory()
            else:
                raise ValueError(f"{node.name}: the log's {cls.__qualname__} lacks the field {f.name!r}")
        return _new(cls, values)
    if kind == "slots":
        cls = _import_class(node.attrs["class"])
        return _new(cls, {n: decode(node[n]) for n in json.loads(node.attrs["slots"])})
    raise ValueError(f"{node.name}: unknown kind {kind!r} (a log of a newer format?)")


# ---------------------------------------------------------------------------------------------- RNG states
def rng_state(generator: torch.Generator | None = None) -> dict[str, Any]:
    """The global torch and numpy RNG states (and ``generator``'s), what an estimator update may draw from."""
    s: dict[str, Any] = {"torch": torch.get_rng_state(), "numpy": np.random.get_state()}
    if generator is not None:
        s["generator"] = generator.get_state()
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        s["cuda"] = torch.cuda.get_rng_state_all()
    return s


def restore_rng(state: dict[str, Any]) -> None:
    """Set the global RNG states of :func:`rng_state` (the generator's is the caller's business)."""
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    cuda = state.get("cuda")
    if cuda is not None and torch.cuda.is_available() and len(cuda) == torch.cuda.device_count():
        torch.cuda.set_rng_state_all(cuda)


# ---------------------------------------------------------------------------------------------- writer
class EpisodeLogWriter:
    """Writes ``episode.h5`` while an episode runs: the reset at construction, one step per :meth:`step`
    (file opened in append mode, the step written, flushed and closed), :meth:`close` marks it complete."""

    def __init__(self, path: str | os.PathLike, cfg, obs, info, generator: torch.Generator | None = None):
        from activetouch.experiments.runner import platform_info

        h5py = _h5py()
        self.path = Path(path)
        self.t0 = time.perf_counter()
        t_wall = time.time()
        rng = rng_state(generator)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with h5py.File(self.path, "w") as f:
            a = f.attrs
            a["format"], a["format_version"] = FORMAT, FORMAT_VERSION
            a["task"], a["method"], a["seed"] = cfg.task, cfg.method, int(cfg.seed)
            a["config"] = json.dumps(asdict(cfg), sort_keys=True, default=_json_default)
            a["platform"] = json.dumps(platform_info(), sort_keys=True, default=_json_default)
            a["activetouch_version"] = _version()
            a["created"] = t_wall
            a["complete"] = False
            a["steps"] = 0
            encode(f, "config", cfg)
            g = f.create_group("reset")
            encode(g, "obs", obs)
            encode(g, "info", info)
            encode(g, "rng", rng)
            g.attrs["t_wall"], g.attrs["t_episode"] = t_wall, 0.0
            g.attrs["written"] = True
            f.create_group("steps")
            f.flush()
        self.steps = 0

    def capture(self, generator: torch.Generator | None = None) -> dict[str, Any]:
        """What the step's update starts from (call right before ``est.observe``): RNG states and the time."""
        return {"rng": rng_state(generator), "t_wall": time.time(), "t_episode": time.perf_counter() - self.t0}

    def reset_belief(self, belief: dict | None) -> None:
        """The belief after the initialisation (``{"poses": (P, 4, 4), "weights": (P,)}``), for viewers."""
        if belief is None:
            return
        with _open_for_append(self.path) as f:
            if "belief" in f["reset"]:
                del f["reset"]["belief"]
            encode(f["reset"], "belief", belief)
            f.flush()

    def step(self, t: int, action, obs, info, ee_before, captured: dict[str, Any], planner: dict | None = None,
             belief: dict | None = None):
        """Append step ``t``: the executed ``action``, what it observed, ``ee_before``, the planner's fields and the
        belief after the update (``{"poses": (P, 4, 4), "weights": (P,)}``: what a viewer draws; replay recomputes
        it)."""
        with _open_for_append(self.path) as f:
            steps = f["steps"]
            name = f"{int(t):06d}"
            if name in steps:
                del steps[name]
            g = steps.create_group(name)
            encode(g, "action", action)
            encode(g, "obs", obs)
            encode(g, "info", info)
            encode(g, "ee_before", ee_before)
            encode(g, "planner", dict(planner or {}))
            encode(g, "rng", captured["rng"])
            if belief is not None:
                encode(g, "belief", belief)
            g.attrs["step"] = int(t)
            g.attrs["t_wall"], g.attrs["t_episode"] = captured["t_wall"], captured["t_episode"]
            g.attrs["written"] = True  # last: a step is finished once this is set
            f.attrs["steps"] = int(t)
            f.flush()
        self.steps = int(t)

    def close(self) -> None:
        with _open_for_append(self.path) as f:
            f.attrs["complete"] = True
            f.attrs["steps"] = self.steps
            f.attrs["wall_s"] = time.perf_counter() - self.t0


class _NoLog:
    """Stands in for :class:`EpisodeLogWriter` when ``ACTIVETOUCH_NO_LOG=1``."""

    path = None

    def capture(self, generator=None):
        return None

    def reset_belief(self, belief=None):
        return None

    def step(self, *args, **kwargs):
        return None

    def close(self):
        return None


def open_episode_log(out_dir: str | os.PathLike, cfg, obs, info, generator: torch.Generator | None = None):
    """The writer of ``out_dir/episode.h5`` after the reset (a no-op stand-in when ``ACTIVETOUCH_NO_LOG=1``).
    Call it right before ``est.initialise``: it records the RNG states the initialisation starts from."""
    if os.environ.get(NO_LOG_ENV, "").strip() not in ("", "0"):
        return _NoLog()
    return EpisodeLogWriter(Path(out_dir) / LOG_NAME, cfg, obs, info, generator)


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("activetouch")
    except Exception:  # pragma: no cover - not installed
        return "unknown"


def _json_default(o: Any):
    if hasattr(o, "tolist"):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    return repr(o)


# ---------------------------------------------------------------------------------------------- reader
class EpisodeLog:
    """A recorded episode (read-only): ``meta`` (root attributes), ``config`` (the ``EpisodeConfig``),
    :meth:`reset` and :meth:`steps` (the finished steps, in order). Use as a context manager."""

    def __init__(self, path: str | os.PathLike):
        h5py = _h5py()
        self.path = Path(path)
        if not self.path.exists():
            raise ValueError(f"no episode log at {str(self.path)!r}")
        if self.path.is_dir():
            if (self.path / LOG_NAME).exists():
                self.path = self.path / LOG_NAME
            else:
                raise ValueError(f"{str(self.path)!r} is a folder without an {LOG_NAME}")
        try:
            self._f = h5py.File(self.path, "r")
        except OSError:
            raise ValueError(f"{str(self.path)!r} is not an episode log (not an HDF5 file)") from None
        try:
            meta = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in self._f.attrs.items()}
            if meta.get("format") != FORMAT:
                raise ValueError(f"{str(self.path)!r} is not an activetouch episode log (format "
                                 f"{meta.get('format')!r})")
            version = int(meta.get("format_version", -1))
            if version != FORMAT_VERSION:
                raise ValueError(f"{str(self.path)!r} has episode-log format version {version}; this activetouch "
                                 f"reads version {FORMAT_VERSION}")
            if "reset" not in self._f or not self._f["reset"].attrs.get("written", False):
                raise ValueError(f"{str(self.path)!r} holds no reset (the run died before it was written)")
            self.meta = meta
            self.config = decode(self._f["config"])
        except (OSError, KeyError) as e:
            self._f.close()
            raise ValueError(f"{str(self.path)!r} is a damaged episode log ({e})") from None
        except Exception:
            self._f.close()
            raise

    def reset(self) -> dict[str, Any]:
        g = self._f["reset"]
        return {"obs": decode(g["obs"]), "info": decode(g["info"]), "rng": decode(g["rng"]),
                "belief": decode(g["belief"]) if "belief" in g else None,
                **{k: g.attrs[k] for k in ("t_wall", "t_episode")}}

    def step_names(self) -> list[str]:
        """The finished steps' group names in order (a step a crash interrupted is left out)."""
        steps = self._f.get("steps")
        if steps is None:
            return []
        names = []
        for n in sorted(steps, key=int):
            try:
                if steps[n].attrs.get("written", False):
                    names.append(n)
            except (KeyError, OSError):  # pragma: no cover - a step a crash left half written
                break
        return names

    def __len__(self) -> int:
        return len(self.step_names())

    def step(self, name: str) -> dict[str, Any]:
        g = self._f["steps"][name]
        return {"step": int(g.attrs["step"]), "action": decode(g["action"]), "obs": decode(g["obs"]),
                "info": decode(g["info"]), "ee_before": decode(g["ee_before"]), "planner": decode(g["planner"]),
                "rng": decode(g["rng"]), "belief": decode(g["belief"]) if "belief" in g else None,
                "t_wall": float(g.attrs["t_wall"]), "t_episode": float(g.attrs["t_episode"])}

    def steps(self) -> Iterator[dict[str, Any]]:
        for n in self.step_names():
            yield self.step(n)

    def close(self) -> None:
        self._f.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def read_log(path: str | os.PathLike) -> EpisodeLog:
    """Open a log (a file or an episode folder holding ``episode.h5``); ValueError for anything else."""
    return EpisodeLog(path)


# ---------------------------------------------------------------------------------------------- replay
def replay(log_path: str | os.PathLike, method: str | None = None, out_dir: str | os.PathLike | None = None,
           device: str = "cpu", on_step=None) -> dict[str, Any]:
    """Re-run an estimator offline on a recorded episode and write ``steps.csv`` and ``summary.json``.

    ``method`` (default: the logged one) must be compatible with the logged task; its estimator is built with
    the logged ``EpisodeConfig`` (method and device replaced), seeded as :func:`run_episode` seeds it, initialised
    on the logged reset and updated with every logged step's observation in order. The global torch / numpy RNG
    states are restored before the initialisation and every update (online, the planner draws from them between
    updates). The planner is not run: the planner's row fields (``replanned``, expected IG, ...) are copied from
    the log, they belong to the executed actions. ``out_dir`` defaults to ``<log folder>/replay-<method>``.
    ``on_step(t, estimator, row)`` as in ``run_episode``. Returns the summary."""
    from activetouch.experiments.records import STEP_COLUMNS, StepWriter, write_json_atomic
    from activetouch.experiments.runner import _in_contact, check_device, check_output_dir, platform_info
    from activetouch.registry import check_compatible, get_belief, get_method, get_task

    t_start = time.perf_counter()
    with read_log(log_path) as lg:
        cfg = lg.config
        logged = cfg.method
        method = method or logged
        spec = get_method(method)  # ValueError naming the known methods
        check_compatible(cfg.task, method)
        check_device(device)
        cfg = replace(cfg, method=method, device=device, progress=False)
        out = Path(out_dir) if out_dir is not None else lg.path.parent / f"replay-{method}"
        check_output_dir(out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "summary.json").unlink(missing_ok=True)
        task = get_task(cfg.task)
        belief = get_belief(spec.belief)
        check = getattr(belief.make, "check_config", None)
        if check is not None:
            check(cfg)
        env = task.make_env(seed=cfg.seed, observe_dT=cfg.observe_dT) if "object-motion" in task.provides \
            else task.make_env(seed=cfg.seed)
        torch.manual_seed(cfg.seed)  # as run_episode
        gen = torch.Generator(device="cpu").manual_seed(cfg.seed)
        est = belief.make(env, cfg, torch.device(device))
        env.reset(seed=cfg.seed)  # the env's state at the logged reset (estimators may read the env)
        r = lg.reset()
        restore_rng(r["rng"])
        same = method == logged
        warned = _check_generator(gen, r["rng"], same, 0, False)
        info = r["info"]
        counts = est.initialise(task, r["obs"], info, gen)
        columns = STEP_COLUMNS + tuple(c for c in getattr(est, "COLUMNS", ()) if c not in STEP_COLUMNS)
        rows: list[dict[str, Any]] = []
        converged_at = None
        with StepWriter(out / "steps.csv", columns) as writer:
            m = est.metrics(info)
            row = {"step": 0, **m, **counts, "in_contact": False, "resampled": False}
            last = {**m, **counts}
            writer.write(row)
            rows.append(row)
            if on_step is not None:
                on_step(0, est, row)
            for s in lg.steps():
                t = s["step"]
                if converged_at is None and est.converged():
                    converged_at = t - 1
                obs, info = s["obs"], s["info"]
                in_contact = _in_contact(obs)
                restore_rng(s["rng"])
                warned = _check_generator(gen, s["rng"], same, t, warned)
                t2 = time.perf_counter()
                fields = est.observe(obs, info, s["ee_before"], gen)
                t3 = time.perf_counter()
                m = est.metrics(info)
                row = {"step": t, **m, **fields, "in_contact": in_contact, "update_s": t3 - t2, **s["planner"]}
                last = {**m, **fields}
                writer.write(row)
                rows.append(row)
                if on_step is not None:
                    on_step(t, est, row)
        if converged_at is None and est.converged():
            converged_at = rows[-1]["step"]
        meta = lg.meta
        src = str(lg.path)
    final = {k: v for k, v in last.items() if not k.endswith("_s") and isinstance(v, (int, float))
             and not isinstance(v, bool)}  # what the estimator reported at the last step
    summary = {"task": cfg.task, "method": method, "seed": cfg.seed, "logged_method": logged,
               "source_log": src, "log_complete": bool(meta.get("complete", False)),
               "steps": len(rows) - 1, "converged_step": converged_at, **task.success(rows, info, env),
               **est.summary(), "final": final, "wall_s": time.perf_counter() - t_start,
               "config": asdict(cfg), "platform": platform_info()}
    write_json_atomic(out / "summary.json", summary)
    summary["out_dir"] = str(out)
    return summary


def _check_generator(gen: torch.Generator, rng: dict[str, Any], same_method: bool, t: int, warned: bool) -> bool:
    """The replay's episode generator must be where the online run's was (same method): a warning otherwise
    (once). Returns whether a warning has been given."""
    logged = rng.get("generator")
    if not warned and same_method and logged is not None and not torch.equal(gen.get_state(), logged):
        log.warning("step %d: the episode generator differs from the logged run's (something else drew from it "
                    "online); the replay will not reproduce the online belief exactly", t)
        return True
    return warned

