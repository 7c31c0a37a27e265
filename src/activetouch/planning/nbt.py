"""Next best touch, NBT (visuo-tactile clutter paper, Sec. II-D-2, Eq. 25), on the TIQF belief (Sec. II-C).

An action is a ray ``a = (s, d)``: start ``s`` and unit direction ``d`` (world frame). One NBT step:

1. **Candidates** (:func:`touch_candidates`): "Monte-Carlo sampling of actions around each face of a bounding
   box placed on the current estimate": uniform points on each touchable face of the object-frame box
   ``[lower, upper]`` posed by the estimate, each ray starting ``standoff`` outside its face and pointing
   along the face's inward normal.
2. **Predicted measurement** (:func:`ray_mesh_intersect`): the first intersection of the ray with the object
   mesh at the estimate ("ray-mesh intersection algorithm"); open3d's ``RaycastingScene`` (an Embree BVH),
   with the hit distance refined in float64 on the hit triangle's plane.
3. **Expected information gain** (:func:`expected_information_gain`, Eq. 25): the gain is the closed-form KL
   divergence between the predicted posterior and the current one (:func:`kl_gaussian`). The predicted
   posterior (``prediction=``, :data:`PREDICTIONS`) is by default (``"kalman"``) one closed-form Kalman update
   (Eq. 14-17) of the current posterior with the pairs the predicted contact adds, batched over all
   candidates: at the estimate the contact lies on the posed model, so its pseudo-measurements ``H x = 0``,
   the mean stays and only the covariance shrinks. ``"register"`` runs the full TIQF registration of the
   touches so far plus the predicted contact per candidate (a Python loop). For 200 candidates on the YCB
   cracker box and mustard bottle (benchmarks/bench_nbt.py, one thread): a whole selection takes ~7 ms with
   ``"kalman"`` (~6 ms of it the ray casting, ~1 ms the gains) and ~330 ms with ``"register"``.
4. **Selection** (:func:`select_next_best_touch`): the arg max over the candidates whose ray hits the
   estimate. The first ``min_touches`` touches (TIQF and NBT start from >= 3 points, Sec. II-D-2) are random
   candidates that hit the estimate (:func:`random_touches`).

The stop rule of Sec. II-D-2 (pose change between touches below ``xi_T = 5 mm`` and ``xi_R = 2 deg``) is
:func:`should_stop_touching`, which applies ``planning.nbv.pose_change_below`` with :class:`NBTConfig`'s
thresholds (not duplicated here).

Object frame: the packaged YCB meshes stand on ``z = 0`` with ``+z`` up (objects.known_object), so the
bottom face ``-z`` of the box rests on the table and is not touchable by default. All functions are pure
(no state between calls; randomness only from the ``generator`` argument); tensors come back on the device
of the main inputs (``pose`` / ``starts`` / ``predicted``), the ray casting itself runs on the CPU (open3d),
the KL algebra in float64.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ..belief.tiqf import (
    TIQFConfig,
    TIQFState,
    _information_basis,
    _pair_vectors,
    _pd_inverse,
    _quat_to_matrix,
    _spd_inverse,
    measurement_noise,
    random_matching,
    register,
)
from ..geometry import check_poses

__all__ = [
    "FACE_NAMES",
    "PREDICTIONS",
    "NBTConfig",
    "TouchCandidates",
    "touch_candidates",
    "ray_mesh_intersect",
    "kl_gaussian",
    "predicted_covariance",
    "expected_information_gain",
    "select_next_best_touch",
    "random_touches",
    "should_stop_touching",
]

#: Faces of an axis-aligned box, indexed by :attr:`TouchCandidates.face`: ``"+x"`` is the face ``x = upper_x``
#: (outward normal ``+e_x``), ``"-x"`` the face ``x = lower_x``, and so on.
FACE_NAMES = ("+x", "-x", "+y", "-y", "+z", "-z")

#: Predicted-posterior modes of :func:`expected_information_gain`: ``"kalman"`` (default, batched closed form)
#: and ``"register"`` (one TIQF registration per candidate).
PREDICTIONS = ("kalman", "register")


@dataclass(frozen=True)
class NBTConfig:
    """Next-best-touch parameters (Sec. II-D-2).

    Attributes:
        rays_per_face: Monte-Carlo samples per face of the bounding box. The paper gives no number; 20 (so 100
            candidates on the default five faces) is our choice, from when every candidate cost one TIQF
            registration (``prediction="register"``, ~0.26 s per selection on the CPU). The default batched
            closed form (``prediction="kalman"``) scores 200 candidates in ~7 ms, most of it the ray
            casting (benchmarks/bench_nbt.py), so more rays are affordable.
        faces: the touchable faces (names of :data:`FACE_NAMES`, object frame). Default: the five faces but
            the bottom ``-z``, on which the object stands on the table.
        standoff: distance (m) of each ray's start outside its face, along the outward normal.
        min_touches: random touches before NBT takes over (paper: TIQF and active touch start from a minimum
            of 3 points, sampled randomly given the visual estimate).
        stop_translation: stop threshold ``xi_T`` on the change in position between touches (paper: 5 mm).
        stop_rotation_deg: stop threshold ``xi_R`` on the change in rotation between touches (paper: 2 deg).
        face_margin: fraction of each face side kept free of samples at each edge (0.1: samples lie in the
            middle 80% of each side), so a ray near an edge of the box does not miss a rounded or slightly
            smaller object, or graze the edge. Our choice; the paper does not say.
    """

    rays_per_face: int = 20
    faces: tuple[str, ...] = ("+x", "-x", "+y", "-y", "+z")
    standoff: float = 0.05
    min_touches: int = 3
    stop_translation: float = 0.005
    stop_rotation_deg: float = 2.0
    face_margin: float = 0.1

    def __post_init__(self):
        if not isinstance(self.rays_per_face, (int, np.integer)) or isinstance(self.rays_per_face, bool) \
                or self.rays_per_face < 1:
            raise ValueError(f"NBTConfig.rays_per_face must be an int >= 1, got {self.rays_per_face!r}")
        faces = tuple(self.faces) if not isinstance(self.faces, str) else (self.faces,)
        if not faces or any(f not in FACE_NAMES for f in faces) or len(set(faces)) != len(faces):
            raise ValueError(f"NBTConfig.faces must be distinct names from {FACE_NAMES}, got {self.faces!r}")
        object.__setattr__(self, "faces", faces)
        if not (math.isfinite(self.standoff) and self.standoff > 0):
            raise ValueError(f"NBTConfig.standoff must be finite and > 0, got {self.standoff!r}")
        if not isinstance(self.min_touches, (int, np.integer)) or isinstance(self.min_touches, bool) \
                or self.min_touches < 1:
            raise ValueError(f"NBTConfig.min_touches must be an int >= 1, got {self.min_touches!r}")
        for name in ("stop_translation", "stop_rotation_deg"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"NBTConfig.{name} must be finite and > 0, got {v!r}")
        if not (math.isfinite(self.face_margin) and 0 <= self.face_margin < 0.5):
            raise ValueError(f"NBTConfig.face_margin must be in [0, 0.5), got {self.face_margin!r}")


@dataclass(frozen=True)
class TouchCandidates:
    """Candidate touch actions (rays), world frame.

    Attributes:
        starts: ray start points ``s`` ``(N, 3)``.
        directions: unit ray directions ``d`` ``(N, 3)``.
        face: index into :data:`FACE_NAMES` of the box face each ray was sampled on ``(N,)`` (int64).
    """

    starts: torch.Tensor
    directions: torch.Tensor
    face: torch.Tensor

    def __len__(self) -> int:
        return int(self.starts.shape[0])

    def subset(self, index) -> "TouchCandidates":
        """The candidates ``index`` (an int, index tensor or boolean mask) as a new :class:`TouchCandidates`."""
        if isinstance(index, (int, np.integer)):
            index = [int(index)]
        index = torch.as_tensor(index, device=self.starts.device)
        return TouchCandidates(self.starts[index], self.directions[index], self.face[index])


# ------------------------------------------------------------------------------------------- validation
def _points(x, name: str, min_rows: int = 0, ref: torch.Tensor | None = None) -> torch.Tensor:
    if not torch.is_tensor(x):
        x = torch.as_tensor(np.asarray(x))
    if not torch.is_floating_point(x):
        x = x.to(torch.get_default_dtype())
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {tuple(x.shape)}")
    if x.shape[0] < min_rows:
        raise ValueError(f"{name} needs at least {min_rows} rows, got {x.shape[0]}")
    if not bool(torch.isfinite(x).all()):
        raise ValueError(f"{name} contains NaN or inf")
    return x if ref is None else x.to(device=ref.device, dtype=ref.dtype)


def _vector3(x, name: str) -> torch.Tensor:
    if not torch.is_tensor(x):
        x = torch.as_tensor(np.asarray(x))
    if not torch.is_floating_point(x):
        x = x.to(torch.get_default_dtype())
    if x.shape != (3,):
        raise ValueError(f"{name} must have shape (3,), got {tuple(x.shape)}")
    if not bool(torch.isfinite(x).all()):
        raise ValueError(f"{name} contains NaN or inf")
    return x


def _pose(pose, name: str = "pose") -> torch.Tensor:
    T = check_poses(pose, name)
    if T.shape != (4, 4):
        raise ValueError(f"{name} must have shape (4, 4), got {tuple(T.shape)}")
    return T


def _generator(generator) -> torch.Generator:
    if generator is None:
        return torch.Generator().manual_seed(0)
    if isinstance(generator, (int, np.integer)) and not isinstance(generator, bool):
        return torch.Generator().manual_seed(int(generator))
    if isinstance(generator, torch.Generator):
        return generator
    raise ValueError(f"generator must be a torch.Generator, an int seed or None, got {type(generator).__name__}")


# ------------------------------------------------------------------------------------------- candidates
def touch_candidates(pose, lower, upper, config: NBTConfig = NBTConfig(), generator=None) -> TouchCandidates:
    """Monte-Carlo touch actions around the faces of a bounding box on the estimate (Sec. II-D-2).

    Args:
        pose: ``(4, 4)`` estimate, object -> world.
        lower, upper: ``(3,)`` object-frame box corners (e.g. ``KnownObject.bounds``), ``lower < upper``.
        config: :class:`NBTConfig` (``faces``, ``rays_per_face``, ``standoff``, ``face_margin``).
        generator: ``torch.Generator`` (CPU), an int seed, or ``None`` (seed 0: deterministic).

    Returns:
        :class:`TouchCandidates` with ``N = rays_per_face * len(faces)`` rays, face by face in the order of
        ``config.faces``: for a point ``p`` drawn uniformly on the face (its middle ``1 - 2 face_margin`` of each
        side) with outward normal ``n`` (object frame), start ``T (p + standoff n)`` and direction ``R (-n)``.
        Device and dtype of ``pose``.
    """
    T = _pose(pose)
    lo = _vector3(lower, "lower").to(T)
    hi = _vector3(upper, "upper").to(T)
    if not bool((hi > lo).all()):
        raise ValueError(f"upper must exceed lower on every axis, got lower {lo.tolist()}, upper {hi.tolist()}")
    g = _generator(generator)
    k = config.rays_per_face
    m = config.face_margin
    starts, dirs, face_idx = [], [], []
    for name in config.faces:
        axis = "xyz".index(name[1])
        sign = 1.0 if name[0] == "+" else -1.0
        u = torch.rand(k, 3, generator=g, device=g.device, dtype=torch.float64).to(T)
        p = lo + (m + (1.0 - 2.0 * m) * u) * (hi - lo)  # (k, 3), uniform on the face's inner part
        p[:, axis] = hi[axis] if sign > 0 else lo[axis]
        n = torch.zeros(3, dtype=T.dtype, device=T.device)
        n[axis] = sign
        starts.append(p + config.standoff * n)
        dirs.append((-n).expand(k, 3))
        face_idx.append(torch.full((k,), FACE_NAMES.index(name), dtype=torch.int64, device=T.device))
    R, t = T[:3, :3], T[:3, 3]
    s = torch.cat(starts) @ R.T + t
    d = torch.cat(dirs) @ R.T
    return TouchCandidates(starts=s, directions=d, face=torch.cat(face_idx))


# ------------------------------------------------------------------------------------------- ray casting
def ray_mesh_intersect(vertices, faces, pose, starts, directions, max_distance: float = math.inf):
    """First intersection of rays with a triangle mesh at a pose: the predicted touch (Sec. II-D-2).

    Args:
        vertices: ``(V, 3)`` mesh vertices, object frame (e.g. ``KnownObject.mesh.vertices``).
        faces: ``(F, 3)`` triangle vertex indices.
        pose: ``(4, 4)`` mesh pose, object -> world.
        starts: ``(N, 3)`` world ray starts.
        directions: ``(N, 3)`` world ray directions (non-zero; normalised here).
        max_distance: rays whose first hit lies farther than this (m, along the unit direction) miss.

    Returns:
        ``(hit (N,) bool, points (N, 3), distance (N,))``: world contact points (NaN where missed) and
        distances from the starts (``inf`` where missed), on the device and in the dtype of ``starts``.

    The rays are mapped into the object frame (so the acceleration structure is built on the mesh as given)
    and cast with ``open3d.t.geometry.RaycastingScene`` (Embree BVH, float32). The hit distance is then
    refined in float64 on the plane of the hit triangle, ``t = n . (v_0 - s) / (n . d)``, so the points are
    exact to float64 rounding rather than float32's ~1e-7 m. One scene is built per call (a few ms for the
    16k-triangle YCB meshes).
    """
    import open3d as o3d

    V = np.asarray(vertices.detach().cpu() if torch.is_tensor(vertices) else vertices, dtype=np.float64)
    Fc = np.asarray(faces.detach().cpu() if torch.is_tensor(faces) else faces)
    if V.ndim != 2 or V.shape[1] != 3 or V.shape[0] < 3 or not np.isfinite(V).all():
        raise ValueError(f"vertices must be finite with shape (V >= 3, 3), got {V.shape}")
    if Fc.ndim != 2 or Fc.shape[1] != 3 or Fc.shape[0] < 1 or not np.issubdtype(Fc.dtype, np.integer):
        raise ValueError(f"faces must be integer indices with shape (F >= 1, 3), got {Fc.shape} {Fc.dtype}")
    if Fc.min() < 0 or Fc.max() >= V.shape[0]:
        raise ValueError(f"faces index vertices out of range [0, {V.shape[0]})")
    T = _pose(pose)
    s = _points(starts, "starts")
    d = _points(directions, "directions")
    if d.shape != s.shape:
        raise ValueError(f"directions must have the shape of starts {tuple(s.shape)}, got {tuple(d.shape)}")
    if not (max_distance > 0):  # also rejects NaN
        raise ValueError(f"max_distance must be > 0, got {max_distance!r}")
    out_dev, out_dtype = s.device, s.dtype
    n_rays = s.shape[0]
    dn = torch.linalg.vector_norm(d.double(), dim=1)
    if n_rays and not bool((dn > 1e-12).all()):
        raise ValueError("directions must be non-zero")
    T64 = T.detach().to("cpu", torch.float64)
    R, t = T64[:3, :3], T64[:3, 3]
    s64 = s.detach().to("cpu", torch.float64)
    d64 = d.detach().to("cpu", torch.float64) / dn.cpu()[:, None]
    s_obj = ((s64 - t) @ R).numpy()  # R^T (s - t)
    d_obj = (d64 @ R).numpy()
    if n_rays == 0:
        return (torch.zeros(0, dtype=torch.bool, device=out_dev), s.new_zeros(0, 3), s.new_zeros(0))

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(V.astype(np.float32)), o3d.core.Tensor(Fc.astype(np.uint32)))
    rays = np.concatenate([s_obj, d_obj], axis=1).astype(np.float32)
    ans = scene.cast_rays(o3d.core.Tensor(rays))
    t_hit = ans["t_hit"].numpy().astype(np.float64)
    prim = ans["primitive_ids"].numpy().astype(np.int64)
    hit = np.isfinite(t_hit)
    dist = np.full(n_rays, np.inf)
    if hit.any():  # float64 refinement on the hit triangle's plane
        tri = V[Fc[prim[hit]]]  # (H, 3, 3)
        nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        denom = np.einsum("ij,ij->i", nrm, d_obj[hit])
        num = np.einsum("ij,ij->i", nrm, tri[:, 0] - s_obj[hit])
        ok = np.abs(denom) > 1e-12 * np.linalg.norm(nrm, axis=1)
        refined = np.where(ok, num / np.where(ok, denom, 1.0), t_hit[hit])
        # keep open3d's value when the refinement disagrees (degenerate triangle, grazing ray)
        refined = np.where(np.abs(refined - t_hit[hit]) < 1e-4 + 1e-4 * t_hit[hit], refined, t_hit[hit])
        dist[hit] = refined
    hit &= dist <= max_distance
    dist[~hit] = np.inf
    dist_t = torch.as_tensor(dist, dtype=torch.float64)
    pts = s64 + d64 * torch.where(torch.as_tensor(hit), dist_t, torch.nan)[:, None]
    return (torch.as_tensor(hit, device=out_dev), pts.to(out_dev, out_dtype), dist_t.to(out_dev, out_dtype))


# ------------------------------------------------------------------------------------------- Eq. 25
def kl_gaussian(mean0, cov0, mean1, cov1, align_hemisphere: bool = True) -> torch.Tensor:
    """Closed-form ``KL(N(mean0, cov0) || N(mean1, cov1))`` (Eq. 25; textbook form, e.g. ref. [37]).

    ``KL = 1/2 [ log(det cov1 / det cov0) + tr(cov1^-1 cov0) - d + (mean0 - mean1)^T cov1^-1 (mean0 - mean1) ]``

    Args:
        mean0, cov0: ``(..., d)``, ``(..., d, d)``: the first argument of the KL (Eq. 25: the predicted
            posterior ``x^_t, Sigma^_t``).
        mean1, cov1: ``(..., d)``, ``(..., d, d)``: the second (Eq. 25: the current belief, the prior
            ``x_{t-1}, Sigma_{t-1}``). Batch dimensions broadcast; covariances symmetric positive definite.
        align_hemisphere: for quaternion states (``x`` and ``-x`` are the same rotation) flip ``mean0`` to the
            hemisphere of ``mean1`` where ``mean0 . mean1 < 0`` before differencing. ``N(-m, S)`` is the
            same rotation belief as ``N(m, S)`` (the covariance is invariant under the sign flip), so the
            KL no longer depends on which of the two signs a filter returned. ``False`` for plain vectors.

    Returns:
        ``(...)`` float64, >= 0 (clamped at 0 against rounding), on the device of ``mean0``.

    Direction. Eq. 25's log term ``log det(Sigma_{t-1}) / det(Sigma^_t)`` and trace term
    ``tr(Sigma_{t-1}^-1 Sigma^_t)`` are those of ``KL(posterior || prior)`` with ``cov0 = Sigma^_t`` and
    ``cov1 = Sigma_{t-1}``, as the text says ("KL divergence between the posterior ... and the prior"). Its
    Mahalanobis term is printed with ``Sigma_t^-1`` (the posterior's); the textbook ``KL(post || prior)``
    weighs it with the *prior's* inverse ``Sigma_{t-1}^-1``, which is what this function does (so it is a
    true KL divergence, 0 iff the Gaussians are equal). The deviation from the printed equation is only in
    that term.
    """
    m0 = torch.as_tensor(mean0)
    dev = m0.device
    m0 = m0.to(torch.float64)
    S0 = torch.as_tensor(cov0).to(device=dev, dtype=torch.float64)
    m1 = torch.as_tensor(mean1).to(device=dev, dtype=torch.float64)
    S1 = torch.as_tensor(cov1).to(device=dev, dtype=torch.float64)
    for name, m in (("mean0", m0), ("mean1", m1)):
        if m.ndim < 1 or not bool(torch.isfinite(m).all()):
            raise ValueError(f"{name} must be a finite (..., d) tensor, got shape {tuple(m.shape)}")
    d = m0.shape[-1]
    if m1.shape[-1] != d:
        raise ValueError(f"mean1 must have dimension {d} like mean0, got {tuple(m1.shape)}")
    for name, S in (("cov0", S0), ("cov1", S1)):
        if S.ndim < 2 or S.shape[-2:] != (d, d) or not bool(torch.isfinite(S).all()):
            raise ValueError(f"{name} must be a finite (..., {d}, {d}) tensor, got shape {tuple(S.shape)}")
    S0 = 0.5 * (S0 + S0.transpose(-1, -2))
    S1 = 0.5 * (S1 + S1.transpose(-1, -2))
    L0, bad0 = torch.linalg.cholesky_ex(S0)
    if bool(bad0.any()):
        raise ValueError("cov0 must be symmetric positive definite")
    L1, bad1 = torch.linalg.cholesky_ex(S1)
    if bool(bad1.any()):
        raise ValueError("cov1 must be symmetric positive definite")
    if align_hemisphere:
        m0 = torch.where(((m0 * m1).sum(-1, keepdim=True) < 0), -m0, m0)
    batch = torch.broadcast_shapes(m0.shape[:-1], m1.shape[:-1], S0.shape[:-2], S1.shape[:-2])
    L0 = L0.expand(*batch, d, d)
    L1 = L1.expand(*batch, d, d)
    diff = (m0 - m1).expand(*batch, d)
    logdet0 = 2.0 * torch.log(torch.diagonal(L0, dim1=-2, dim2=-1)).sum(-1)
    logdet1 = 2.0 * torch.log(torch.diagonal(L1, dim1=-2, dim2=-1)).sum(-1)
    A = torch.linalg.solve_triangular(L1, L0, upper=False)  # L1^-1 L0: tr(S1^-1 S0) = |A|_F^2
    trace = (A ** 2).sum((-2, -1))
    z = torch.linalg.solve_triangular(L1, diff.unsqueeze(-1), upper=False).squeeze(-1)
    maha = (z ** 2).sum(-1)
    kl = 0.5 * (logdet1 - logdet0 + trace - d + maha)
    return kl.clamp_min(0.0)


def _new_point_partners(k: int, seed: int, device) -> torch.Tensor:
    """Indices ``(P,)`` into the ``k`` touched points of the partners TIQF's random matching gives the new
    point: ``register`` on the ``k + 1`` points ``cat(touched, p_n)`` (the new point is row ``k``, as the
    loop appends it) draws ``random_matching(k + 1)`` from ``TIQFConfig.seed``; the pairs containing row ``k``
    are the new point's. ``P = 1``, or ``P = 2`` when ``k + 1`` is odd and row ``k`` is the twice-paired first
    point of the permutation. The matching depends only on ``k + 1`` and the seed: the same for every
    candidate."""
    gen = torch.Generator(device="cpu").manual_seed(seed)  # exactly as register draws it
    i, j = random_matching(k + 1, gen, device)
    return torch.cat([j[i == k], i[j == k]])


def _new_point_pairs(touched: torch.Tensor, predicted: torch.Tensor, config: TIQFConfig) -> torch.Tensor:
    """Scene-side pair differences ``s_ji (N, P, 3)`` the predicted points ``p_n (N, 3)`` add (see
    :func:`predicted_covariance`): ``p_n - s_j`` for the new point's partners ``j`` in TIQF's seeded random
    matching (``"random"``, ``P`` = 1 or 2) or ``p_n - c_n`` with ``c_n`` the centroid of the ``K + 1`` points
    (``"centroid"``, ``P = 1``)."""
    k = touched.shape[0]
    if config.pairing == "centroid":
        centroid = (touched.sum(0) + predicted) / (k + 1)  # (N, 3): the centroid register would use
        return (predicted - centroid).unsqueeze(1)
    partners = _new_point_partners(k, config.seed, touched.device)
    return predicted[:, None, :] - touched[partners][None, :, :]


def predicted_covariance(state: TIQFState, touched, predicted, tiqf_config: TIQFConfig = TIQFConfig()):
    """Closed-form predicted posterior of one more touch at each predicted contact, batched (Eq. 14-18).

    Args:
        state: the current TIQF posterior ``(x_{t-1} (4,), Sigma_{t-1} (4, 4), t (3,))``.
        touched: ``(K, 3)`` world contacts measured so far, ``K >= 2`` (the points ``state`` was registered on).
        predicted: ``(N, 3)`` predicted world contacts ``p_n`` (on the mesh posed at ``state.pose``).
        tiqf_config: its ``rho`` (Eq. 17), ``pairing`` and ``seed`` choose the noise and the pairs.

    Returns:
        ``(x_hat (N, 4), Sigma_hat (N, 4, 4))`` float64 on the device of ``touched``: the normalised (Eq. 18)
        predicted posteriors. ``x_hat`` equals the normalised ``state.x`` to rounding.

    The update. One Kalman update in information form (the algebra of ``tiqf.kalman_update`` / ``register``):
    ``Sigma_n = (Sigma^-1 + sum_pairs H_p^T Sigma_h^-1 H_p)^-1`` and ``x_n = Sigma_n Sigma^-1 x``, with
    ``Sigma_h`` Eq. 17 at the current ``(x, Sigma)`` (as ``register`` evaluates it at its call's prior) and
    ``H_p`` Eq. 12 from ``tiqf._pair_vectors``, the information summed through ``tiqf._information_basis``.

    Assumptions (what the closed form drops against ``prediction="register"``):

    * Correspondences are exact at the estimate: each scene point ``s`` corresponds to ``R^T (s - t)``, so a
      pair's model difference is ``o_ji = R^T s_ji`` (``R = R(x)``; the translation cancels). Then
      ``H x = 0`` exactly for every pair, the information matrix annihilates ``x``, and the update leaves
      the mean where it is (``x_n = x``) and changes only the covariance. For ``p_n`` this is true by
      construction (it lies on the mesh at the estimate); for the touched points it neglects their residual
      to the model. No nearest-neighbour search (so ``max_correspondence_distance`` does not apply), no
      re-association of correspondences, no mean shift and no translation update: one update, not the
      iterated registration, so a touch that would move the estimate gains only through the covariance.
    * Only the new point's pairs are counted. The current state already holds the information of the
      ``K`` touches (``register`` put it there), so it is not added again; the re-pairing of the old touches
      that the next registration would do (a new random matching, or the centroid shifted by ``p_n``) is
      ignored. Pairs, with ``s_j`` the touched points:

      - ``pairing="random"``: the pairs ``(s_j, p_n)`` for the partner(s) ``j`` of row ``K`` in the random
        perfect matching that ``register`` on ``cat(touched, p_n)`` draws from ``TIQFConfig.seed``
        (``tiqf.random_matching(K + 1)``): one partner, or two when ``K + 1`` is odd and the new point is
        the one paired twice. The matching depends only on ``K + 1`` and the seed, so every candidate
        gets the same partner(s), and these are the pairs through which the loop's next registration of the
        ``K + 1`` touches (same seed, new touch appended last) takes the new point's information. Measured
        on scenes like benchmarks/bench_nbt.py's (cracker box and mustard bottle, K = 3, 4, 5, 10, three
        seeds each, 200 candidates): Spearman rank correlation with the register path 0.76-0.999 (median
        0.99); the expectation over the matching instead (every ``j`` with weight ~``1 / K``, seed-free)
        gave -0.48-0.95, because the register path's gains are dominated by the one drawn partner.
      - ``pairing="centroid"``: the one pair of ``p_n`` with the centroid ``c_n`` of the ``K + 1`` points
        (the centroid ``register`` would use), ``s_ji = p_n - c_n = K / (K + 1) (p_n - mean_j s_j)``.

    Cost: ``O(N)`` pair vectors (``O(1)`` pairs per candidate) and one ``(N, 36) x (36, 16)`` product, then
    batched 4 x 4 Cholesky factorisations; no Python loop over candidates, no model points.
    """
    if not isinstance(state, TIQFState):
        raise ValueError(f"state must be a TIQFState, got {type(state).__name__}")
    touched_t = _points(touched, "touched", min_rows=2)
    pred = _points(predicted, "predicted")
    dev = touched_t.device
    touched64 = touched_t.to(torch.float64)
    pred64 = pred.to(device=dev, dtype=torch.float64)
    x = state.x.to(device=dev, dtype=torch.float64)
    x = x / torch.linalg.vector_norm(x)  # as register normalises its prior mean
    Sigma = state.Sigma.to(device=dev, dtype=torch.float64)
    n = pred64.shape[0]
    if n == 0:
        return x.new_zeros(0, 4), x.new_zeros(0, 4, 4)
    R = _quat_to_matrix(x)
    s_ji = _new_point_pairs(touched64, pred64, tiqf_config)  # (N, P, 3)
    v = _pair_vectors(s_ji, s_ji @ R)  # (N, P, 6); o_ji = R^T s_ji: exact correspondences at the estimate
    C = _information_basis(_spd_inverse(measurement_noise(x, Sigma, tiqf_config.rho)))  # Eq. 17, (36, 16)
    second = v.transpose(-1, -2) @ v  # (N, 6, 6) second moment of each candidate's pair vectors
    info = (second.reshape(n, 36) @ C).reshape(n, 4, 4)  # sum_p H_p^T Sigma_h^-1 H_p (tiqf._information)
    prior_info = _pd_inverse(Sigma)
    A = prior_info + 0.5 * (info + info.transpose(-1, -2))
    L, bad = torch.linalg.cholesky_ex(A)
    if bool(bad.any()):  # cannot happen for a valid state (PD + PSD); eigenvalue floor as tiqf does
        wv, V = torch.linalg.eigh(A)
        wv = wv.clamp_min(wv.amax(-1, keepdim=True).clamp_min(1e-300) * 1e-12)
        S_hat = (V / wv[..., None, :]) @ V.transpose(-1, -2)
    else:
        S_hat = torch.cholesky_inverse(L)
    # x_n = Sigma_n Sigma^-1 x, written as x - Sigma_n info x (the same, since Sigma_n (Sigma^-1 + info) = I):
    # info x = 0 to rounding, and this form does not amplify rounding by Sigma^-1's ~1e6 condition number
    x_hat = x - (S_hat @ (info @ x)[..., None])[..., 0]  # (N, 4)
    norm = torch.linalg.vector_norm(x_hat, dim=-1)  # Eq. 18
    x_hat = x_hat / norm[:, None]
    S_hat = S_hat / norm[:, None, None] ** 2
    return x_hat, 0.5 * (S_hat + S_hat.transpose(-1, -2))


def _check_prediction(prediction) -> str:
    if prediction not in PREDICTIONS:
        raise ValueError(f"prediction must be one of {PREDICTIONS}, got {prediction!r}")
    return prediction


def expected_information_gain(model_points, state: TIQFState, touched, predicted,
                              tiqf_config: TIQFConfig = TIQFConfig(), prediction: str = "kalman") -> torch.Tensor:
    """Expected information gain of each predicted touch, Eq. 25 (Sec. II-D-2).

    Args:
        model_points: ``(M, 3)`` object-frame model cloud of the TIQF registration (validated always, used
            only by ``prediction="register"``).
        state: the current TIQF posterior ``(x_{t-1}, Sigma_{t-1}, t)`` (after the touches so far).
        touched: ``(K, 3)`` world contact points measured so far, ``K >= 2``.
        predicted: ``(N, 3)`` predicted contact points of the candidates (:func:`ray_mesh_intersect` at
            ``state.pose``).
        tiqf_config: :class:`TIQFConfig` of the loop (``rho``, ``pairing`` and ``seed`` for both modes; the
            whole configuration for the registrations of ``"register"``).
        prediction: how the predicted posterior ``(x^_n, Sigma^_n)`` is formed, one of :data:`PREDICTIONS`:

            * ``"kalman"`` (default): :func:`predicted_covariance`, one closed-form Kalman update with the
              pairs the new point adds (with its partner(s) in TIQF's seeded random matching of the
              ``K + 1`` points, or with their centroid), batched over the ``N`` candidates. The mean does not
              move, so the gain is the covariance part of the KL only. Its assumptions (exact correspondences at the
              estimate, no re-association, old touches not counted again) are listed there. ~1 ms for
              200 candidates (benchmarks/bench_nbt.py).
            * ``"register"``: the state of ``register(model_points, cat(touched, p_n), init=state,
              config=tiqf_config)`` per candidate: the measurement set the loop would register after that
              touch, from the current posterior, with nearest-neighbour re-association and the mean shift
              the touch causes. With TIQF's default iterated update (``iteration_prior="call"``) that
              posterior is the current one plus the information of all ``K + 1`` points, so the ``K`` old
              touches are counted again; that part is the same for every candidate (with
              ``pairing="random"`` the matching depends only on ``K + 1`` and the seed, so every candidate
              gets the same pairs of old touches) and the ranking is decided by the new point's pair and the
              mean shift it causes. A Python loop over ``N`` registrations (each small: ``K + 1`` scene
              points, a few iterations from the current estimate), one batched KL at the end; ~0.3 s for
              200 candidates.

    Returns:
        ``(N,)`` float64 gains ``KL(N(x^_n, Sigma^_n) || N(x_{t-1}, Sigma_{t-1}))`` (:func:`kl_gaussian`,
        quaternion hemisphere aligned), finite and >= 0, on the device of ``predicted``.
    """
    prediction = _check_prediction(prediction)
    touched_t = _points(touched, "touched", min_rows=2)
    pred = _points(predicted, "predicted")
    if not isinstance(state, TIQFState):
        raise ValueError(f"state must be a TIQFState, got {type(state).__name__}")
    model = _points(model_points, "model_points", min_rows=1)
    out_dev = pred.device
    dev = touched_t.device
    n = pred.shape[0]
    if n == 0:
        return torch.zeros(0, dtype=torch.float64, device=out_dev)
    if prediction == "kalman":
        x_hat, S_hat = predicted_covariance(state, touched_t, pred, tiqf_config)
    else:
        touched64 = touched_t.to(torch.float64)
        pred64 = pred.to(device=dev, dtype=torch.float64)
        model64 = model.to(device=dev, dtype=torch.float64)
        xs, Ss = [], []
        scene = torch.cat([touched64, touched64[:1]])  # (K + 1, 3); the last row is replaced per candidate
        for i in range(n):
            scene[-1] = pred64[i]
            _, post, _ = register(model64, scene, init=state, config=tiqf_config)
            xs.append(post.x)
            Ss.append(post.Sigma)
        x_hat = torch.stack(xs).to(dev)
        S_hat = torch.stack(Ss).to(dev)
    gains = kl_gaussian(x_hat, S_hat, state.x.to(dev), state.Sigma.to(dev))
    return gains.to(out_dev)


def select_next_best_touch(model_points, vertices, faces, state: TIQFState, touched,
                           candidates: TouchCandidates, tiqf_config: TIQFConfig = TIQFConfig(),
                           max_distance: float = math.inf, prediction: str = "kalman"):
    """The next best touch ``a* = argmax_a IG(a)`` among candidate rays (Eq. 25, Sec. II-D-2).

    Args:
        model_points: ``(M, 3)`` object-frame TIQF model cloud.
        vertices, faces: the object mesh ``(V, 3)``, ``(F, 3)`` (object frame) for the predicted contacts.
        state: current TIQF posterior; the contacts are predicted at ``state.pose``.
        touched: ``(K, 3)`` world contacts so far (``K >= 2``).
        candidates: :class:`TouchCandidates` (:func:`touch_candidates` on ``state.pose``).
        tiqf_config: TIQF configuration of the loop (see :func:`expected_information_gain`).
        max_distance: ray length (m); a ray hitting the estimate farther away counts as a miss.
        prediction: ``"kalman"`` (default, batched closed form) or ``"register"`` (one TIQF registration per
            candidate); see :func:`expected_information_gain`.

    Returns:
        ``(index, gains)``: the chosen candidate's index (int) and the gains ``(N,)`` float64, ``-inf`` for
        rays that miss the estimate (they predict no measurement). Raises ValueError when no ray hits.
    """
    prediction = _check_prediction(prediction)
    if not isinstance(candidates, TouchCandidates):
        raise ValueError(f"candidates must be TouchCandidates, got {type(candidates).__name__}")
    if not isinstance(state, TIQFState):
        raise ValueError(f"state must be a TIQFState, got {type(state).__name__}")
    pose = state.pose
    hit, points, _ = ray_mesh_intersect(vertices, faces, pose, candidates.starts, candidates.directions,
                                        max_distance)
    if not bool(hit.any()):
        raise ValueError("candidates: no candidate ray hits the object at the estimate")
    gains = torch.full((len(candidates),), -math.inf, dtype=torch.float64, device=candidates.starts.device)
    gains[hit] = expected_information_gain(model_points, state, touched, points[hit], tiqf_config,
                                           prediction).to(gains.device)
    return int(torch.argmax(gains)), gains


def random_touches(vertices, faces, pose, lower, upper, config: NBTConfig = NBTConfig(), generator=None,
                   n: int | None = None, max_distance: float = math.inf):
    """The first touches, drawn at random given the (visual) estimate (Sec. II-D-2).

    Args:
        vertices, faces: object mesh ``(V, 3)``, ``(F, 3)`` (object frame).
        pose: ``(4, 4)`` estimate, object -> world.
        lower, upper: ``(3,)`` object-frame bounding box.
        config: :class:`NBTConfig`.
        generator: ``torch.Generator``, int seed or ``None`` (seed 0); draws the candidates and the choice.
        n: number of touches; default ``config.min_touches``.
        max_distance: ray length (m).

    Returns:
        ``(actions, predicted)``: :class:`TouchCandidates` of ``n`` distinct random candidates of
        :func:`touch_candidates` whose rays hit the mesh at ``pose``, and their predicted contacts ``(n, 3)``.
        Raises ValueError when fewer than ``n`` of the candidates hit.
    """
    n = config.min_touches if n is None else n
    if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or n < 1:
        raise ValueError(f"n must be an int >= 1, got {n!r}")
    g = _generator(generator)
    cands = touch_candidates(pose, lower, upper, config, g)
    hit, points, _ = ray_mesh_intersect(vertices, faces, pose, cands.starts, cands.directions, max_distance)
    hit_idx = torch.nonzero(hit.cpu()).squeeze(1)
    if hit_idx.numel() < n:
        raise ValueError(f"n: only {hit_idx.numel()} of {len(cands)} candidate rays hit the estimate, need {n}")
    pick = hit_idx[torch.randperm(hit_idx.numel(), generator=g, device=g.device)[:n].cpu()]
    pick = pick.to(cands.starts.device)
    return cands.subset(pick), points[pick]


def should_stop_touching(prev_pose, cur_pose, n_touches: int, config: NBTConfig = NBTConfig()) -> bool:
    """Stop rule of Sec. II-D-2: ``True`` once at least ``config.min_touches`` touches were made and the
    estimate changed by less than ``stop_translation`` (5 mm) and ``stop_rotation_deg`` (2 deg) between two
    touches. The pose comparison is ``planning.nbv.pose_change_below`` (shared with next best view)."""
    if not isinstance(n_touches, (int, np.integer)) or isinstance(n_touches, bool) or n_touches < 0:
        raise ValueError(f"n_touches must be an int >= 0, got {n_touches!r}")
    if n_touches < config.min_touches:
        return False
    from .nbv import pose_change_below  # written alongside (next best view); imported lazily

    return bool(pose_change_below(prev_pose, cur_pose, config.stop_translation, config.stop_rotation_deg))
