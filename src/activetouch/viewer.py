"""A 3-D viewer of a finished episode (``activetouch view DIR``), built on viser.

Why viser (https://viser.studio): a maintained Python 3-D viewer made for robotics. It is pure Python (``pip
install viser``; no native build), serves a local web server whose client is any browser (a bundled three.js
page over a websocket), so it works on a headless or remote machine (open the URL, or forward the port with
``ssh -L``) and can be tested in headless Chromium; its scene is a tree of named nodes (``/object/true``,
``/points/step_3/surface``, ...) that the Python side can show, hide and move, and it has GUI widgets (the
step slider) wired to Python callbacks. Rerun's recording format + web viewer would fit as well, but it
records a timeline up front (a ``.rrd`` of several MB per episode), and its web viewer is a large wasm
bundle that software WebGL in headless Chromium loads slowly; with viser the episode log already is the
recording and the scene is built from it on demand.

What the scene shows, from ``episode.h5`` (and ``steps.csv`` for the metrics) of the episode folder:

* ``/table``: the table top (z = 0) as a thin box;
* ``/object/true``: the target object's mesh at its true pose of the selected step (grey);
* ``/objects/<i>`` (clutter tasks): the clutter object ``i`` (``info["object_names"][i]``, ``i >= 1``; object 0
  is the target) at its pose of the selected step;
* ``/points/step_<k>/<kind>``: the observations of step ``k`` (0 is the reset): ``surface`` and ``free`` points
  (RUMI features), ``visual`` (segmented depth points on the target) and ``tactile`` points (clutter),
  ``contacts`` (touch-only: the ee positions where contact was signalled); shown for all steps up to the
  selected one (the observations accumulated so far), the selected step's drawn larger;
* ``/robot/ee``: the end-effector pose after the selected step (a frame); ``/robot/path/step_<k>``: the ee path of
  a poke (touch-only), ``/camera/step_<k>``: the camera of a clutter view;
* a GUI slider ``step`` (0..T) and a text with the step's action and metrics (ADI, NLL, ... from ``steps.csv``).

* ``/belief/estimate`` and ``/belief/particles``: the belief after the selected step's update (the log records it):
  the heaviest hypothesis as the object mesh, every hypothesis's object centre coloured by its weight;
* ``/belief/field``: the information field the next action was planned on (RUMI's I~(x|X), GPVR's variance) as a
  voxel cloud of the cells above 5 % of its maximum, coloured by value, with a checkbox.
"""
from __future__ import annotations

import csv
import dataclasses
import logging
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

#: colours (RGB 0-255)
COLOURS = {
    "table": (205, 190, 165),
    "object": (150, 150, 150),
    "surface": (220, 40, 40),
    "free": (60, 120, 230),
    "occupied": (150, 60, 200),
    "visual": (30, 170, 70),
    "tactile": (240, 140, 20),
    "contacts": (240, 140, 20),
    "path": (40, 40, 40),
    "camera": (30, 30, 30),
    "estimate": (255, 120, 0),  # the belief's heaviest hypothesis
}
#: colours of clutter objects 1, 2, ... (cycled)
CLUTTER_COLOURS = ((90, 160, 220), (230, 170, 60), (120, 190, 120), (200, 110, 160), (160, 130, 90),
                   (100, 200, 200), (210, 210, 90), (170, 120, 220))
#: metrics of ``steps.csv`` shown next to the slider, in this order (those present)
METRICS = ("adi_mm", "nll", "apc", "trans_err_mm", "trans_err", "rot_err_deg", "xy_err", "yaw_err_deg", "entropy")
MAX_FACES = 4000
POINT_SIZE = 0.004
#: RUMI's free-space points fill the camera's view volume (tens of thousands a step): drawn small, at most this
#: many a step (an even subsample), and hidden with the "free space" checkbox
MAX_FREE_POINTS = 2000
FIELD_POINT_SIZE = 0.008
FREE_POINT_SIZE = 0.0012


@dataclasses.dataclass
class Frame:
    """What the scene shows at one step (0: the reset)."""

    step: int
    action: str
    true_pose: np.ndarray  # (4, 4)
    object_poses: np.ndarray | None  # (n, 4, 4), clutter
    points: dict[str, np.ndarray]  # kind -> (N, 3) world points observed at this step
    ee_pose: np.ndarray | None  # (4, 4)
    ee_path: np.ndarray | None  # (K, 3)
    camera: tuple[np.ndarray, np.ndarray, float, float] | None  # position, look-at, fov_y (rad), aspect
    metrics: dict[str, float]
    belief_poses: np.ndarray | None = None  # (P, 4, 4) the belief after this step's update
    belief_weights: np.ndarray | None = None  # (P,)
    field_points: np.ndarray | None = None  # (K, 3) cells of the information field this step's action was planned on
    field_values: np.ndarray | None = None  # (K,)


@dataclasses.dataclass
class Episode:
    path: Path
    task: str
    method: str
    seed: int
    target: str
    object_names: tuple[str, ...]
    frames: list[Frame]


# ---------------------------------------------------------------------------------------------- loading
def _np(x) -> np.ndarray | None:
    if x is None:
        return None
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def _target_name(task: str, info: dict) -> str:
    names = info.get("object_names")
    if names:
        return str(names[0])
    for mod, table in (("activetouch.sim.tasks", "TASKS"), ("activetouch.sim.grasp_tasks", "GRASP_TASKS"),
                       ("activetouch.sim.clutter_tasks", "CLUTTER_TASKS")):
        import importlib

        specs = getattr(importlib.import_module(mod), table)
        if task in specs:
            spec = specs[task]
            return str(getattr(spec, "object_name", None) or getattr(spec, "target"))
    raise ValueError(f"the viewer does not know task {task!r}'s object")


def _action_name(action) -> str:
    if action is None:
        return "reset"
    if isinstance(action, str):
        return action
    return type(action).__name__.removesuffix("Action").lower() or "action"


def _observation(obs, info: dict) -> tuple[dict[str, np.ndarray], Any, Any, Any]:
    """(points by kind, ee pose, ee path, camera) of one observation of any task family."""
    points: dict[str, np.ndarray] = {}
    ee_pose = ee_path = camera = None
    feats = getattr(obs, "features", None)
    if feats is not None:  # RUMI: Features (positions, semantics SURFACE 0 / FREE 1 / OCCUPIED 2)
        pos, sem = _np(feats.positions), np.asarray(_np(feats.semantics)).astype(int)
        for code, kind in ((0, "surface"), (1, "free"), (2, "occupied")):
            if (sem == code).any():
                points[kind] = pos[sem == code]
        ee_pose = _np(getattr(obs, "ee_pose", None))
    elif hasattr(obs, "ee") and hasattr(obs, "z"):  # touch-only: TouchObservation
        ee = _np(obs.ee)
        if ee is not None and len(ee):
            ee_path = ee[:, :3]
            c, s = math.cos(ee[-1, 3]), math.sin(ee[-1, 3])
            ee_pose = np.eye(4)
            ee_pose[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
            ee_pose[:3, 3] = ee[-1, :3]
            z = np.asarray(obs.z, dtype=bool).reshape(-1)
            if z.any():
                points["contacts"] = ee[1:][: len(z)][z[: len(ee) - 1], :3]
    elif hasattr(obs, "points"):  # clutter: ClutterObservation
        pts = _np(obs.points).reshape(-1, 3)
        if len(pts):
            points["visual" if getattr(obs, "kind", "") == "view" else "tactile"] = pts
        cam = getattr(obs, "camera", None)
        if cam is not None:
            aspect = float(cam.width) / float(cam.height)
            camera = (np.asarray(cam.pos, float), np.asarray(cam.target, float), math.radians(cam.fov_y_deg), aspect)
    points = {k: v[np.isfinite(v).all(1)] for k, v in points.items()}
    return {k: v for k, v in points.items() if len(v)}, ee_pose, ee_path, camera


def _metrics(folder: Path) -> dict[int, dict[str, float]]:
    f = folder / "steps.csv"
    if not f.exists():
        return {}
    out: dict[int, dict[str, float]] = {}
    with open(f, newline="") as fh:
        for row in csv.DictReader(fh):
            try:
                k = int(row["step"])
            except (KeyError, TypeError, ValueError):
                continue
            vals = {}
            for m in METRICS:
                try:
                    v = float(row.get(m) or "nan")
                except ValueError:
                    continue
                if math.isfinite(v):
                    vals[m] = v
            out[k] = vals
    return out


def load_episode(path: str | Path, folder: str | Path | None = None) -> Episode:
    """The frames of a recorded episode (a folder with ``episode.h5``, or the file); ValueError otherwise.
    ``folder``: where its ``steps.csv`` lies (default: beside the log)."""
    from activetouch.experiments.episode_log import read_log

    with read_log(path) as log:
        folder = Path(folder) if folder is not None else log.path.parent
        metrics = _metrics(folder)
        reset = log.reset()
        records = [(0, None, reset["obs"], reset["info"], reset.get("belief"))]
        records += [(int(s["step"]), s["action"], s["obs"], s["info"], s.get("belief")) for s in log.steps()]
        task, method, seed = str(log.meta.get("task")), str(log.meta.get("method")), int(log.meta.get("seed", 0))
    frames = []
    for k, action, obs, info, belief in records:
        info = info if isinstance(info, dict) else {}
        pts, ee_pose, ee_path, cam = _observation(obs, info)
        op = info.get("object_poses")
        bp = bw = fp = fv = None
        if isinstance(belief, dict) and belief.get("poses") is not None:
            bp, bw = _np(belief["poses"]).reshape(-1, 4, 4), _np(belief["weights"]).reshape(-1)
        if isinstance(belief, dict) and belief.get("field_points") is not None:
            fp, fv = _np(belief["field_points"]).reshape(-1, 3), _np(belief["field_values"]).reshape(-1)
        frames.append(Frame(step=k, action=str(info.get("action") or _action_name(action)),
                            true_pose=_np(info["true_pose"]).reshape(4, 4),
                            object_poses=None if op is None else _np(op).reshape(-1, 4, 4),
                            points=pts, ee_pose=ee_pose, ee_path=ee_path, camera=cam, metrics=metrics.get(k, {}),
                            belief_poses=bp, belief_weights=bw, field_points=fp, field_values=fv))
    info0 = records[0][3] if isinstance(records[0][3], dict) else {}
    return Episode(path=folder, task=task, method=method, seed=seed, target=_target_name(task, info0),
                   object_names=tuple(str(n) for n in (info0.get("object_names") or ())), frames=frames)


# ---------------------------------------------------------------------------------------------- scene
def light_mesh(mesh, max_faces: int = MAX_FACES):
    """A copy of ``mesh`` with at most about ``max_faces`` faces, so that the browser loads it fast: trimesh's
    quadric decimation when its backend (fast_simplification) is installed, else vertex clustering (vertices
    merged on a grid whose cell grows until the mesh is small enough; keeps the shape closed, unlike dropping
    faces)."""
    import trimesh

    if len(mesh.faces) <= max_faces:
        return mesh
    try:
        out = mesh.simplify_quadric_decimation(face_count=max_faces)
        if 0 < len(out.faces) <= 2 * max_faces:
            return out
    except Exception:  # no fast_simplification, or an old trimesh
        pass
    v, f = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
    size = float(np.linalg.norm(v.max(0) - v.min(0))) or 1.0
    out = mesh
    for cells in (96, 72, 56, 44, 34, 26, 20, 15, 11, 8):
        keys = np.floor((v - v.min(0)) / (size / cells)).astype(np.int64)
        _, inv = np.unique(keys, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        nv = np.zeros((inv.max() + 1, 3))
        np.add.at(nv, inv, v)
        nv /= np.bincount(inv)[:, None]
        nf = inv[f]
        nf = nf[(nf[:, 0] != nf[:, 1]) & (nf[:, 1] != nf[:, 2]) & (nf[:, 0] != nf[:, 2])]
        _, first = np.unique(np.sort(nf, axis=1), axis=0, return_index=True)
        nf = nf[np.sort(first)]
        out = trimesh.Trimesh(nv, nf, process=False)
        if len(nf) <= max_faces:
            break
    out.remove_unreferenced_vertices()
    return out


def _wxyz_pos(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    from scipy.spatial.transform import Rotation

    T = np.asarray(T, dtype=np.float64)
    x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()
    return np.array([w, x, y, z]), T[:3, 3].copy()


def _look_at(pos: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Rotation of a camera at ``pos`` looking at ``target`` in the OpenCV convention viser's frustum uses
    (+z forward, +y down), world z up."""
    f = target - pos
    f = f / (np.linalg.norm(f) + 1e-12)
    r = np.cross(f, [0.0, 0.0, 1.0])
    if np.linalg.norm(r) < 1e-6:
        r = np.array([1.0, 0.0, 0.0])
    r = r / np.linalg.norm(r)
    T = np.eye(4)
    T[:3, :3] = np.stack([r, np.cross(f, r), f], axis=1)
    T[:3, 3] = pos
    return T


class EpisodeScene:
    """The viser scene of an episode: ``nodes`` lists the added node names; :meth:`show` sets the scene to step
    ``k`` (what the ``step`` slider calls)."""

    def __init__(self, server, episode: Episode):
        from activetouch import objects

        self.server, self.episode = server, episode
        self.nodes: list[str] = []
        self.handles: dict[str, Any] = {}
        sc = server.scene
        f0 = episode.frames[0]

        centre = f0.true_pose[:3, 3].copy()
        self._add("/table", sc.add_box("/table", color=COLOURS["table"], dimensions=(0.7, 0.7, 0.01),
                                        position=(centre[0], centre[1], -0.005)))
        target = light_mesh(objects.load(episode.target).mesh)
        self._add_mesh("/object/true", target, COLOURS["object"], f0.true_pose)
        if f0.object_poses is not None:
            for i in range(1, len(f0.object_poses)):
                name = episode.object_names[i] if i < len(episode.object_names) else None
                if name is None:
                    continue
                mesh = light_mesh(objects.load(name).mesh)
                self._add_mesh(f"/objects/{i}", mesh, CLUTTER_COLOURS[(i - 1) % len(CLUTTER_COLOURS)],
                               f0.object_poses[i])
        self._step_nodes: dict[int, list[str]] = {}
        for fr in episode.frames:
            names = self._step_nodes.setdefault(fr.step, [])
            for kind, pts in fr.points.items():
                n = f"/points/step_{fr.step}/{kind}"
                if kind == "free" and len(pts) > MAX_FREE_POINTS:
                    pts = pts[np.linspace(0, len(pts) - 1, MAX_FREE_POINTS).astype(int)]
                self._add(n, sc.add_point_cloud(n, points=pts.astype(np.float32), colors=COLOURS[kind],
                                                point_size=self._size(kind, False), point_shape="circle"))
                names.append(n)
            if fr.ee_path is not None and len(fr.ee_path) > 1:
                n = f"/robot/path/step_{fr.step}"
                seg = np.stack([fr.ee_path[:-1], fr.ee_path[1:]], axis=1).astype(np.float32)
                self._add(n, sc.add_line_segments(n, points=seg, colors=COLOURS["path"], thickness=0.003))
                names.append(n)
            if fr.camera is not None:
                pos, look, fov, aspect = fr.camera
                wxyz, p = _wxyz_pos(_look_at(pos, look))
                n = f"/camera/step_{fr.step}"
                self._add(n, sc.add_camera_frustum(n, fov=fov, aspect=aspect, scale=0.05, thickness=0.002,
                                                   color=COLOURS["camera"], wxyz=wxyz, position=p))
                names.append(n)
        if any(fr.ee_pose is not None for fr in episode.frames):
            self._add("/robot/ee", sc.add_frame("/robot/ee", axes_length=0.05, axes_radius=0.003))
        # the belief: the heaviest hypothesis as the object mesh (orange) and every hypothesis's object centre as a
        # point coloured by its weight (dark: light, yellow: heavy); updated by the slider
        self._centre_local = np.asarray(target.bounds, np.float64).mean(0) if hasattr(target, "bounds") else np.zeros(3)
        if any(fr.belief_poses is not None for fr in episode.frames):
            fb = next(fr for fr in episode.frames if fr.belief_poses is not None)
            self._add_mesh("/belief/estimate", target, COLOURS["estimate"], fb.belief_poses[int(np.argmax(fb.belief_weights))])
            self.handles["/belief/estimate"].opacity = 0.55
            c, col = self._particles(fb)
            self._add("/belief/particles", sc.add_point_cloud("/belief/particles", points=c, colors=col,
                                                              point_size=0.006, point_shape="circle"))

        # the information field (RUMI's I~(x|X), GPVR's variance) as a voxel cloud: the cells above 5 % of the
        # field's maximum, coloured by value (dark: low, bright: high), with a checkbox
        self.has_field = any(fr.field_points is not None and len(fr.field_points) for fr in episode.frames)
        if self.has_field:
            ff = next(fr for fr in episode.frames if fr.field_points is not None and len(fr.field_points))
            p, col = self._field(ff)
            self._add("/belief/field", sc.add_point_cloud("/belief/field", points=p, colors=col,
                                                          point_size=FIELD_POINT_SIZE, point_shape="square"))

        radius = float(np.linalg.norm(target.extents)) if hasattr(target, "extents") else 0.3
        dist = max(0.35, 2.0 * radius)
        server.initial_camera.look_at = tuple(centre + [0.0, 0.0, 0.05])
        server.initial_camera.position = tuple(centre + np.array([-0.8, -0.6, 0.7]) * dist)
        server.initial_camera.up = (0.0, 0.0, 1.0)

        T = episode.frames[-1].step
        server.gui.add_markdown(f"**{episode.task}** · {episode.method} · seed {episode.seed}")
        self.slider = server.gui.add_slider("step", min=0, max=max(T, 1), step=1, initial_value=T,
                                            disabled=T == 0)
        self.text = server.gui.add_markdown("")
        self.free = server.gui.add_checkbox("free space", initial_value=True,
                                            visible=any("free" in f.points for f in episode.frames))
        self.show_field = server.gui.add_checkbox("information field", initial_value=True, visible=self.has_field)
        self.show_field.on_update(lambda _event: self.show(self.step))
        self.slider.on_update(lambda _event: self.show(int(self.slider.value)))
        self.free.on_update(lambda _event: self.show(self.step))
        self.step = -1
        self.show(T)

    def _particles(self, fr: Frame) -> tuple[np.ndarray, np.ndarray]:
        """Object centres ``(P, 3)`` of the belief's hypotheses and their colours ``(P, 3)`` by weight (viridis)."""
        import matplotlib

        P = fr.belief_poses
        c = P[:, :3, :3] @ self._centre_local + P[:, :3, 3]
        w = fr.belief_weights
        span = float(w.max() - w.min())
        x = (w - w.min()) / span if span > 0 else np.ones_like(w)
        col = (np.asarray(matplotlib.colormaps["viridis"](x))[:, :3] * 255).astype(np.uint8)
        return c.astype(np.float32), col

    @staticmethod
    def _field(fr: Frame) -> tuple[np.ndarray, np.ndarray]:
        """Field cells ``(K, 3)`` and their colours ``(K, 3)`` (inferno over the frame's values)."""
        import matplotlib

        v = fr.field_values
        x = v / float(v.max()) if len(v) and float(v.max()) > 0 else np.ones_like(v)
        col = (np.asarray(matplotlib.colormaps["inferno"](0.25 + 0.75 * x))[:, :3] * 255).astype(np.uint8)
        return fr.field_points.astype(np.float32), col

    @staticmethod
    def _size(kind: str, current: bool) -> float:
        return (FREE_POINT_SIZE if kind == "free" else POINT_SIZE) * (1.8 if current else 1.0)

    def _add(self, name: str, handle) -> None:
        self.nodes.append(name)
        self.handles[name] = handle

    def _add_mesh(self, name: str, mesh, colour, pose) -> None:
        wxyz, pos = _wxyz_pos(pose)
        self._add(name, self.server.scene.add_mesh_simple(
            name, vertices=np.asarray(mesh.vertices, np.float32), faces=np.asarray(mesh.faces, np.uint32),
            color=colour, side="double", wxyz=wxyz, position=pos))

    def frame(self, k: int) -> Frame:
        """The last recorded frame at or before step ``k``."""
        best = self.episode.frames[0]
        for fr in self.episode.frames:
            if fr.step <= k:
                best = fr
        return best

    def show(self, k: int) -> None:
        """Poses of step ``k``, the observations of steps ``0..k`` (step ``k``'s drawn larger)."""
        fr = self.frame(k)
        self.step = fr.step
        with self.server.atomic():
            h = self.handles["/object/true"]
            h.wxyz, h.position = _wxyz_pos(fr.true_pose)
            if fr.object_poses is not None:
                for i in range(1, len(fr.object_poses)):
                    h = self.handles.get(f"/objects/{i}")
                    if h is not None:
                        h.wxyz, h.position = _wxyz_pos(fr.object_poses[i])
            for step, names in self._step_nodes.items():
                for n in names:
                    h = self.handles[n]
                    h.visible = step <= fr.step
                    if n.startswith("/points/"):
                        kind = n.rsplit("/", 1)[1]
                        h.point_size = self._size(kind, step == fr.step)
                        if kind == "free" and not self.free.value:
                            h.visible = False
            fb = next((f for f in reversed(self.episode.frames) if f.step <= fr.step and f.belief_poses is not None),
                      None)
            if fb is not None and "/belief/estimate" in self.handles:
                h = self.handles["/belief/estimate"]
                h.wxyz, h.position = _wxyz_pos(fb.belief_poses[int(np.argmax(fb.belief_weights))])
                c, col = self._particles(fb)
                h = self.handles["/belief/particles"]
                h.points, h.colors = c, col
            if self.has_field:
                ff = next((f for f in self.episode.frames if f.step >= fr.step and f.field_points is not None
                           and len(f.field_points)), None)  # the field the next action was planned on
                h = self.handles["/belief/field"]
                h.visible = ff is not None and bool(self.show_field.value)
                if ff is not None:
                    h.points, h.colors = self._field(ff)
            ee = next((f.ee_pose for f in reversed(self.episode.frames) if f.step <= fr.step and f.ee_pose is not None),
                      None)
            if "/robot/ee" in self.handles:
                h = self.handles["/robot/ee"]
                h.visible = ee is not None
                if ee is not None:
                    h.wxyz, h.position = _wxyz_pos(ee)
        n_pts = {kind: sum(len(f.points.get(kind, ())) for f in self.episode.frames if f.step <= fr.step)
                 for kind in COLOURS}
        pts = ", ".join(f"{v} {k}" for k, v in n_pts.items() if v)
        mets = " · ".join(f"{m} {fr.metrics[m]:.4g}" for m in METRICS if m in fr.metrics)
        self.text.content = (f"step **{fr.step}** / {self.episode.frames[-1].step}: {fr.action}  \n"
                             f"{mets or 'no metrics'}  \npoints so far: {pts or 'none'}")


def build_scene(server, log) -> EpisodeScene:
    """Add an episode's scene (an :class:`Episode`, or a path to its folder / ``episode.h5``) to a viser server."""
    episode = log if isinstance(log, Episode) else load_episode(log)
    return EpisodeScene(server, episode)


def _viser():
    try:
        import viser
    except ImportError as e:
        raise ValueError("the viewer needs viser: pip install 'activetouch[viewer]' (or pip install viser)") from e
    return viser


def serve(path: str | Path, port: int = 8080, host: str = "127.0.0.1", block: bool = True):
    """Serve the 3-D viewer of the episode at ``path`` on ``http://host:port``; ``block``: until Ctrl-C, then stop
    the server. Returns the ``viser.ViserServer`` (its ``episode_scene`` attribute is the :class:`EpisodeScene`)."""
    episode = load_episode(path)  # ValueError before a server starts
    viser = _viser()
    server = viser.ViserServer(host=host, port=port, label=f"activetouch {episode.task}", verbose=False)
    try:
        server.episode_scene = build_scene(server, episode)
    except BaseException:
        server.stop()
        raise
    if block:
        try:
            wait_for_interrupt()
        finally:
            server.stop()
    return server


def wait_for_interrupt() -> None:
    """Sleep until Ctrl-C (a served viewer stays up meanwhile)."""
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass


class LiveViewer:
    """The viewer of an episode that is still running (``activetouch run ... --view``): a thread polls the episode
    folder's ``episode.h5`` every ``poll_s`` seconds and rebuilds the scene whenever a step was added (the slider
    jumps to the newest step). Reads that meet the writer mid-step are retried at the next poll."""

    def __init__(self, folder: str | Path, port: int = 8080, host: str = "127.0.0.1", poll_s: float = 1.0):
        import threading

        viser = _viser()
        self.folder = Path(folder)
        self.server = viser.ViserServer(host=host, port=port, label="activetouch (live)", verbose=False)
        self.server.gui.add_markdown(f"waiting for the first step of {self.folder} ...")
        self.poll_s = float(poll_s)
        self.steps_shown = -1
        self.scene: EpisodeScene | None = None
        self._stop = threading.Event()
        self._lock = threading.Lock()  # one rebuild at a time (the polling thread and callers of refresh)
        self._thread = threading.Thread(target=self._run, name="activetouch-live-viewer", daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        return f"http://{self.server.get_host()}:{self.server.get_port()}"

    def refresh(self) -> bool:
        """Rebuild the scene if the log has new steps; True when it did."""
        with self._lock:
            return self._refresh()

    def _refresh(self) -> bool:
        from activetouch.experiments.episode_log import LOG_NAME

        path = self.folder / LOG_NAME
        if not path.is_file():
            return False
        import shutil
        import tempfile

        # read a byte copy, never the log itself: an HDF5 reader holding the file would make the run's writer fail
        with tempfile.TemporaryDirectory() as tmp:
            copy = Path(tmp) / LOG_NAME
            try:
                shutil.copyfile(path, copy)
                episode = load_episode(copy, folder=self.folder)
            except (OSError, KeyError, ValueError):  # copied mid-step (the writer was appending): next poll
                return False
        n = episode.frames[-1].step
        if n == self.steps_shown:
            return False
        if self.scene is not None:  # remove the previous build's nodes one by one (a scene reset would also mark
            for h in self.scene.handles.values():  # the new nodes of the same names as removed)
                h.remove()
        self.server.gui.reset()
        self.scene = build_scene(self.server, episode)
        self.steps_shown = n
        return True

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.refresh()
            except Exception:  # pragma: no cover - a viewer must not kill the run it watches
                logging.getLogger(__name__).exception("live viewer refresh failed")
            self._stop.wait(self.poll_s)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.server.stop()
