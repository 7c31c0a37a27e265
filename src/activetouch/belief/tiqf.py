"""Translation-invariant quaternion filter, TIQF (visuo-tactile clutter paper, Sec. II-C, Eq. 3-18).

Point-cloud registration as a Kalman filter on the rotation quaternion:

* Eq. 3-5: with correspondences ``s_i = R o_i + t``, the differences of two correspondences
  ``s_ji = s_j - s_i`` and ``o_ji = o_j - o_i`` obey ``s_ji = R o_ji``: they do not depend on ``t``.
* Eq. 8-12: in quaternions ``s~_ji x = x o~_ji`` is linear in ``x``: ``H x = 0`` with the 4 x 4
  pseudo-measurement matrix ``H`` of :func:`pseudo_measurement`.
* Eq. 13-16: a static-process Kalman filter with pseudo-measurements ``z^h = 0`` (:func:`kalman_update`),
  Eq. 17 the state-dependent measurement noise (:func:`measurement_noise`), Eq. 18 the renormalisation
  (:func:`normalise`), Eq. 6 the closed-form translation (:func:`translation_from_rotation`).
* :func:`register` alternates nearest-neighbour correspondences with those steps until the pose changes
  by less than 0.1 mm and 0.1 deg, or 100 iterations. Its posterior (:class:`TIQFState`) can seed the next
  call, so sparse tactile points refine a dense visual estimate (Sec. II-D, "correct and verify").

Conventions: quaternions are ``(w, x, y, z)`` (scalar first), Hamilton product, active rotation, the same
as ``pytorch_kinematics.transforms`` (its ``matrix_to_quaternion`` converts initial poses; the hot loop uses
an equivalent two-op ``quaternion -> matrix``, tested against it). The state ``x`` is the rotation that maps
model (object-frame) points into the scene (world) frame, so the pose ``T = [[R(x), t], [0, 1]]`` maps
object -> world as everywhere in activetouch (docs/INTERFACES.md). The filter algebra runs in float64
(4 x 4 matrices, so this is free) on the input tensors' device.

Where this departs from a literal reading of the paper (each is a documented option of :class:`TIQFConfig`,
with the measurements behind the choice): the prior covariance is tight along the quaternion itself
(``init_cov_norm``; an isotropic prior made Eq. 18 inflate the covariance geometrically), and the
iterations of one call are an iterated Kalman update of the call's prior (``iteration_prior``) rather than
a chain of updates that counts the same points once per iteration.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import torch

from ..geometry import check_poses, make_pose

__all__ = [
    "TIQFConfig",
    "TIQFState",
    "pseudo_measurement",
    "measurement_noise",
    "kalman_update",
    "normalise",
    "translation_from_rotation",
    "form_pairs",
    "random_matching",
    "initial_state",
    "register",
    "registration_residual",
    "state_at_pose",
    "yaw_shift_starts",
    "register_restarts",
]

PAIRINGS = ("random", "centroid")
NN_METHODS = ("kdtree", "cdist")
ITERATION_PRIORS = ("call", "previous")


@dataclass(frozen=True)
class TIQFConfig:
    """TIQF parameters (defaults: the paper's values where it gives one).

    Attributes:
        rho: correspondence uncertainty of Eq. 17 (paper: 0.05). activetouch works in metres; the
            paper does not state the unit of rho. In metres it is a noise of ``sqrt(rho / 4)`` = 0.11 m on
            each pair difference, so the posterior is modest: a 1,000-point view leaves a quaternion
            standard deviation of about 0.04 (a few degrees) after one update from an uninformative prior.
            The estimate itself does not depend on rho when the prior is uninformative.
        tol_translation: convergence threshold on the change in translation between iterations, metres
            (paper: 0.1 mm).
        tol_rotation_deg: convergence threshold on the change in rotation between iterations, degrees
            (paper: 0.1 deg).
        max_iterations: iteration cap ``max_it_TIQF`` (paper: 100).
        init_cov, init_cov_norm: the prior covariance when :func:`register` starts from a pose (the paper
            gives none): ``init_cov (I_4 - x x^T) + init_cov_norm x x^T`` for the initial quaternion ``x``.
            ``init_cov = 1`` (a standard deviation of 1 per component across the unit sphere's tangent) is
            uninformative: the initial pose only seeds the correspondences. A tight value anchors the
            estimate to the initial pose (0.01, about +-11 deg, left 2-11 deg of a 10-20 deg initial error
            on dense YCB clouds). ``init_cov_norm`` is the variance along ``x`` itself, i.e. of the
            quaternion's norm, which the unit constraint fixes; it must be small. The pseudo-measurement
            ``H x = 0`` is also met by shrinking ``x`` towards 0, and with an isotropic ``I_4`` prior the
            update did that (``|x_t|`` = 0.3-0.4 on dense clouds), so Eq. 18's ``Sigma / |x_t|^2`` inflated
            the whole covariance six- to tenfold per iteration (to 1e10 after 23 iterations with the
            accumulating prior below), and Eq. 17's noise, which grows with ``tr(Sigma)``, then made every
            new measurement worthless. With ``init_cov_norm = 1e-6``, ``|x_t|`` stays within 1e-3 of 1.
        iteration_prior: which prior each iteration of one :func:`register` call updates. ``"call"``
            (default): the call's prior ``(x_0, Sigma_0)``, with the correspondences re-associated at the
            current estimate (an iterated Kalman update, like the iterated EKF): the scene cloud is counted
            once, the fixed point is the MAP estimate of prior and scene, and the returned covariance is
            the prior plus this cloud's information, so carrying it to the next call is sound.
            ``"previous"``: the paper's Eq. 14-16 read literally with ``t`` = iteration: each iteration's
            posterior is the next prior. That counts the same points again every iteration and keeps the
            information of the first iterations' wrong correspondences, so the estimate locks in early
            (dense YCB views: 90% success, median ADI 5.3 mm, against 97% and 1.6 mm with "call";
            benchmarks/bench_tiqf.py).
        pairing: how the correspondence pairs ``(i, j)`` of Eq. 4 are formed; the paper only says "a pair
            of corresponding points". ``"random"`` (default): one random perfect matching of the scene
            points per call (``ceil(N / 2)`` disjoint pairs, an odd point paired twice; their noises are
            independent as the stacked Kalman update assumes; drawn once so that the iterations do not
            jitter with re-drawn pairs, which kept them from meeting the 0.1 deg criterion).
            ``"centroid"``: every correspondence paired with the centroid correspondence
            ``(s_bar, o_bar)``, which obeys Eq. 3 too (``N`` pairs, deterministic; their noises share the
            centroid's). Both gave the same accuracy within noise in benchmarks/bench_tiqf.py.
        seed: seed of the random matching (the results of :func:`register` are deterministic).
        nn: nearest-neighbour search, ``"kdtree"`` (``scipy.spatial.cKDTree`` built once on the model points
            in the object frame; each iteration queries the scene points mapped into the object frame, on
            the CPU: O(N log M), and only the (N, 3) query crosses devices) or ``"cdist"``
            (``torch.cdist`` on the inputs' device: O(N M) memory and time, for GPU tensors).
        max_correspondence_distance: drop correspondences farther apart than this (metres) before the
            update; ``None`` (paper) keeps all of them.
    """

    rho: float = 0.05
    tol_translation: float = 1e-4
    tol_rotation_deg: float = 0.1
    max_iterations: int = 100
    init_cov: float = 1.0
    init_cov_norm: float = 1e-6
    pairing: str = "random"
    seed: int = 0
    nn: str = "kdtree"
    max_correspondence_distance: float | None = None
    iteration_prior: str = "call"

    def __post_init__(self):
        for name in ("rho", "init_cov", "init_cov_norm"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"TIQFConfig.{name} must be finite and > 0, got {v!r}")
        for name in ("tol_translation", "tol_rotation_deg"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"TIQFConfig.{name} must be finite and >= 0, got {v!r}")
        if not isinstance(self.max_iterations, int) or self.max_iterations < 1:
            raise ValueError(f"TIQFConfig.max_iterations must be an int >= 1, got {self.max_iterations!r}")
        if self.pairing not in PAIRINGS:
            raise ValueError(f"TIQFConfig.pairing must be one of {PAIRINGS}, got {self.pairing!r}")
        if self.iteration_prior not in ITERATION_PRIORS:
            raise ValueError(f"TIQFConfig.iteration_prior must be one of {ITERATION_PRIORS}, "
                             f"got {self.iteration_prior!r}")
        if self.nn not in NN_METHODS:
            raise ValueError(f"TIQFConfig.nn must be one of {NN_METHODS}, got {self.nn!r}")
        d = self.max_correspondence_distance
        if d is not None and not (math.isfinite(d) and d > 0):
            raise ValueError(f"TIQFConfig.max_correspondence_distance must be None or > 0, got {d!r}")


@dataclass(frozen=True)
class TIQFState:
    """Gaussian belief over the rotation quaternion plus the translation estimate.

    Attributes:
        x: unit quaternion mean ``(4,)``, ``(w, x, y, z)``, rotating object-frame points into the world.
        Sigma: its covariance ``(4, 4)`` (symmetric positive definite).
        t: translation ``(3,)`` (m) of Eq. 6.
        iterations: iterations the producing :func:`register` call used (0 for a fresh state).
        converged: whether that call met the convergence thresholds before ``max_iterations``.
    """

    x: torch.Tensor
    Sigma: torch.Tensor
    t: torch.Tensor
    iterations: int = 0
    converged: bool = False

    @property
    def pose(self) -> torch.Tensor:
        """Pose ``(4, 4)`` object -> world, ``[[R(x), t], [0, 1]]``."""
        return make_pose(_quat_to_matrix(self.x), self.t)


# ----------------------------------------------------------------------------------------------- algebra
# R(q) of a unit quaternion is a quadratic form in q: R.flatten() = (q q^T).flatten() @ _R_BASIS (16, 9).
# Written here because pytorch_kinematics' quaternion_to_matrix costs ~60-100 us a call on the CPU, which
# is the largest per-iteration overhead of the filter after the nearest-neighbour query; the test suite
# checks this against pytorch_kinematics.
_R_BASIS = torch.zeros(16, 9, dtype=torch.float64)
for (_a, _b), _row in {
    (0, 0): (1, 0, 0, 0, 1, 0, 0, 0, 1), (1, 1): (1, 0, 0, 0, -1, 0, 0, 0, -1),
    (2, 2): (-1, 0, 0, 0, 1, 0, 0, 0, -1), (3, 3): (-1, 0, 0, 0, -1, 0, 0, 0, 1),
    (1, 2): (0, 2, 0, 2, 0, 0, 0, 0, 0), (1, 3): (0, 0, 2, 0, 0, 0, 2, 0, 0),
    (2, 3): (0, 0, 0, 0, 0, 2, 0, 2, 0), (0, 1): (0, 0, 0, 0, 0, -2, 0, 2, 0),
    (0, 2): (0, 0, 2, 0, 0, 0, -2, 0, 0), (0, 3): (0, -2, 0, 2, 0, 0, 0, 0, 0),
}.items():
    _R_BASIS[4 * _a + _b] = torch.tensor(_row, dtype=torch.float64)


def _quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrix ``(3, 3)`` of a unit quaternion ``q (4,)`` ``(w, x, y, z)``."""
    return (torch.outer(q, q).reshape(16) @ _R_BASIS.to(q)).reshape(3, 3)


def _matrix_to_quat(R: torch.Tensor) -> torch.Tensor:
    """Unit quaternion ``(4,)`` with ``w >= 0`` of a rotation matrix ``R (3, 3)``."""
    import pytorch_kinematics.transforms as pkt

    return pkt.standardize_quaternion(pkt.matrix_to_quaternion(R))


# H = [[0, -d^T], [d, [a]_x]] is linear in v = (d, a) = (s_ji - o_ji, s_ji + o_ji): H.flatten() = v @ _H_BASIS.
_H_BASIS_ENTRIES = (  # (row of v, flat index 4 * r + c of H, sign)
    (0, 1, -1.0), (1, 2, -1.0), (2, 3, -1.0),  # top row -d^T
    (0, 4, 1.0), (1, 8, 1.0), (2, 12, 1.0),  # left column d
    (5, 6, -1.0), (4, 7, 1.0), (5, 9, 1.0), (3, 11, -1.0), (4, 13, -1.0), (3, 14, 1.0),  # [a]_x
)
_H_BASIS = torch.zeros(6, 16, dtype=torch.float64)
for _m, _k, _v in _H_BASIS_ENTRIES:
    _H_BASIS[_m, _k] = _v


def pseudo_measurement(s_i: torch.Tensor, s_j: torch.Tensor, o_i: torch.Tensor, o_j: torch.Tensor) -> torch.Tensor:
    """Pseudo-measurement matrices ``H (N, 4, 4)`` of correspondence pairs (Eq. 9-12, READING-NOTES form).

    Args: scene points ``s_i, s_j (N, 3)`` and their model points ``o_i, o_j (N, 3)`` (broadcastable).

    Derivation. With ``s_ji = s_j - s_i = R o_ji`` (Eq. 5) and pure quaternions ``s~ = (0, s_ji)``,
    ``o~ = (0, o_ji)``, Eq. 8 ``s~ = x o~ x*`` times ``x`` on the right gives Eq. 9 ``s~ x - x o~ = 0``.
    Left and right quaternion products are linear in ``x``: ``s~ x = L(s~) x`` with
    ``L(s~) = [[0, -s^T], [s, [s]_x]]`` and ``x o~ = R(o~) x`` with ``R(o~) = [[0, -o^T], [o, -[o]_x]]``
    (Eq. 10). Their difference is

        H = [[0, -(s_ji - o_ji)^T], [s_ji - o_ji, [s_ji + o_ji]_x]],   H x = 0 for the true rotation.

    (The extracted Eq. 11/12 writes point sums ``s_j + s_i + o_j + o_i`` in the lower-right block; that
    is a transcription error, see READING-NOTES.) ``H`` is skew-symmetric, so ``x^T H x = 0`` for every
    ``x``: the residual ``H x`` is always orthogonal to ``x``.
    """
    s_ji = torch.as_tensor(s_j) - torch.as_tensor(s_i)
    o_ji = (torch.as_tensor(o_j) - torch.as_tensor(o_i)).to(s_ji)
    s_ji, o_ji = torch.broadcast_tensors(s_ji, o_ji)
    if s_ji.ndim < 1 or s_ji.shape[-1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {tuple(s_ji.shape)}")
    v = _pair_vectors(s_ji, o_ji)
    return (v @ _H_BASIS.to(v)).reshape(*v.shape[:-1], 4, 4)


def _pair_vectors(s_ji: torch.Tensor, o_ji: torch.Tensor) -> torch.Tensor:
    """``v = (s_ji - o_ji, s_ji + o_ji) (..., 6)``, the coordinates of ``H`` in ``_H_BASIS``."""
    return torch.cat([s_ji - o_ji, s_ji + o_ji], -1)


def _information_basis(W: torch.Tensor) -> torch.Tensor:
    """``C (36, 16)`` with ``C[6 m + n] = (B_m^T W B_n).flatten()`` for the basis matrices ``B_m`` of ``H``, so
    that ``sum_k H_k^T W H_k = ((v^T v).flatten() @ C).reshape(4, 4)`` for the pair coordinates ``v (K, 6)``."""
    B = _H_BASIS.to(W).reshape(6, 4, 4)
    return torch.einsum("mba,bc,ncd->mnad", B, W, B).reshape(36, 16)


def _information(v: torch.Tensor, C: torch.Tensor) -> torch.Tensor:
    """``sum_k H_k^T W H_k (4, 4)`` from the pair coordinates ``v (K, 6)`` and ``C = _information_basis(W)``:
    two small GEMMs instead of building ``K`` 4 x 4 matrices (exact, ``H`` is linear in ``v``)."""
    return ((v.T @ v).reshape(36) @ C).reshape(4, 4)


def measurement_noise(x: torch.Tensor, Sigma: torch.Tensor, rho: float = 0.05) -> torch.Tensor:
    """State-dependent pseudo-measurement noise ``Sigma_h (4, 4)`` (Eq. 17, from the paper's ref. [33]).

    ``Sigma_h = rho / 4 * [tr(x x^T + Sigma) I_4 - (x x^T + Sigma)]`` for the mean ``x (4,)`` and covariance
    ``Sigma (4, 4)``. For symmetric PSD ``M = x x^T + Sigma`` with eigenvalues ``l_k`` the eigenvalues are
    ``rho / 4 * (sum(l) - l_k) >= 0``: symmetric PSD, singular only when ``M`` has rank 1.
    """
    M = torch.outer(x, x) + Sigma
    M = 0.5 * (M + M.transpose(-1, -2))
    eye = torch.eye(4, dtype=M.dtype, device=M.device)
    return 0.25 * float(rho) * (torch.trace(M) * eye - M)


_EIG_FLOOR = 1e-12


def _spd_inverse(A: torch.Tensor, floor: float = _EIG_FLOOR) -> torch.Tensor:
    """Inverse of a symmetric PSD ``(4, 4)`` matrix with its eigenvalues floored at ``floor * max``.

    Written here (eigh + clamp) rather than ``torch.linalg.inv`` because Eq. 17's ``Sigma_h`` becomes
    near-singular along ``x`` as the covariance shrinks; the floor keeps the inverse finite.
    """
    A = 0.5 * (A + A.transpose(-1, -2))
    w, V = torch.linalg.eigh(A)
    w = w.clamp_min(w.max().clamp_min(1e-300) * floor)
    return (V / w) @ V.transpose(-1, -2)


def _pd_inverse(A: torch.Tensor) -> torch.Tensor:
    """Inverse of a symmetric positive definite ``(4, 4)`` matrix by Cholesky; eigenvalue floor if that fails."""
    L, bad = torch.linalg.cholesky_ex(A)
    if bool(bad):
        return _spd_inverse(A)
    Ainv = torch.cholesky_inverse(L)
    return 0.5 * (Ainv + Ainv.transpose(-1, -2))


def kalman_update(x: torch.Tensor, Sigma: torch.Tensor, H: torch.Tensor,
                  rho: float = 0.05) -> tuple[torch.Tensor, torch.Tensor]:
    """One Kalman update with all pseudo-measurements ``H (K, 4, 4)``, ``z^h = 0`` (Eq. 13-17).

    Args: prior mean ``x (4,)`` (normalised), covariance ``Sigma (4, 4)``. Returns the unnormalised
    posterior ``(x_t (4,), Sigma_t (4, 4))``; apply :func:`normalise` (Eq. 18) after it.

    The ``K`` pairs are stacked into one ``4K``-dimensional measurement with block-diagonal noise
    ``Sigma_h`` (Eq. 17, evaluated at the prior). Eq. 14-16 with that stack need a ``4K x 4K`` inverse;
    the information form computed here is algebraically identical (matrix inversion lemma) and needs only
    4 x 4 ones: ``Sigma_t = (Sigma^-1 + sum_k H_k^T Sigma_h^-1 H_k)^-1``, ``x_t = Sigma_t Sigma^-1 x``
    (``= x - K H x``). SIMPLIFICATION: processing the pairs one by one would re-evaluate the
    state-dependent ``Sigma_h`` after every pair; one batched update per iteration freezes it at the
    iteration's prior, which avoids a Python loop over pairs; the effect of re-evaluating it per pair was
    not measured.
    """
    if x.shape != (4,) or Sigma.shape != (4, 4):
        raise ValueError(f"x must be (4,) and Sigma (4, 4), got {tuple(x.shape)} and {tuple(Sigma.shape)}")
    if H.ndim != 3 or H.shape[-2:] != (4, 4):
        raise ValueError(f"H must have shape (K, 4, 4), got {tuple(H.shape)}")
    x64, S64, H64 = x.double(), Sigma.double(), H.to(device=x.device, dtype=torch.float64)
    W = _spd_inverse(measurement_noise(x64, S64, rho))  # Sigma_h^-1
    # sum_k H_k^T W H_k through the (16, 16) second moment of the flattened H (one GEMM instead of K 4x4 ones)
    Hf = H64.reshape(-1, 16)
    info = torch.einsum("bc,bacd->ad", W, (Hf.T @ Hf).reshape(4, 4, 4, 4))
    prior_info = _pd_inverse(S64)
    x_t, Sigma_t = _posterior(prior_info, prior_info @ x64, info)
    return x_t.to(x.dtype), Sigma_t.to(Sigma.dtype)


def _posterior(prior_info: torch.Tensor, prior_b: torch.Tensor, info: torch.Tensor):
    """Information-form posterior: ``Sigma_t = (Sigma^-1 + info)^-1`` and ``x_t = Sigma_t Sigma^-1 x``."""
    Sigma_t = _pd_inverse(prior_info + info)
    return Sigma_t @ prior_b, Sigma_t


def normalise(x: torch.Tensor, Sigma: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. 18: ``x_bar = x / |x|``, ``Sigma_bar = Sigma / |x|^2`` for ``x (4,)``, ``Sigma (4, 4)``.

    Raises ValueError when ``|x|`` is zero or not finite (the update never produces that from a valid
    prior: ``x_t`` is the prior mean mapped by a positive definite matrix).
    """
    n = torch.linalg.vector_norm(x)
    if not (torch.isfinite(n) and n > 1e-12):
        raise ValueError(f"quaternion norm {float(n):.3g} cannot be normalised")
    S = Sigma / n ** 2
    return x / n, 0.5 * (S + S.transpose(-1, -2))


def translation_from_rotation(R: torch.Tensor, scene: torch.Tensor, model: torch.Tensor) -> torch.Tensor:
    """Eq. 6: ``t = mean_i (s_i - R o_i)`` for ``R (3, 3)`` and corresponding ``scene, model (N, 3)`` -> ``(3,)``."""
    return (scene - model @ R.transpose(-1, -2).to(model)).mean(0)


def random_matching(n: int, generator: torch.Generator | None = None, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Index pairs ``(i, j)``, each ``(ceil(n / 2),)``: a random perfect matching of ``n >= 2`` items (an odd
    one out is paired with the first of the permutation)."""
    gdev = generator.device if generator is not None else torch.device("cpu")
    perm = torch.randperm(n, generator=generator, device=gdev).to(device)
    if n % 2:
        perm = torch.cat([perm, perm[:1]])
    return perm[0::2], perm[1::2]


def form_pairs(scene: torch.Tensor, model: torch.Tensor, pairing: str = "random",
               generator: torch.Generator | None = None) -> torch.Tensor:
    """Pseudo-measurements ``H (K, 4, 4)`` of correspondences ``scene[i] <-> model[i]`` (both ``(N, 3)``).

    ``"random"``: a random perfect matching of the ``N`` correspondences (:func:`random_matching`),
    ``K = ceil(N / 2)`` disjoint pairs. ``"centroid"``: ``K = N`` pairs of each correspondence with the
    centroids. Pairs of coincident points give ``H = 0``, which carries no information (the information-form
    update adds nothing for them), so degenerate pairs need no special case.
    """
    if pairing == "centroid":
        return pseudo_measurement(scene.mean(0, keepdim=True), scene, model.mean(0, keepdim=True), model)
    if pairing != "random":
        raise ValueError(f"pairing must be one of {PAIRINGS}, got {pairing!r}")
    i, j = random_matching(scene.shape[0], generator, scene.device)
    return pseudo_measurement(scene[i], scene[j], model[i], model[j])


# ---------------------------------------------------------------------------------------- registration
def _check_cloud(p, name: str, min_points: int) -> torch.Tensor:
    if not torch.is_tensor(p):
        p = torch.as_tensor(p)
    if not torch.is_floating_point(p):
        p = p.to(torch.get_default_dtype())
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {tuple(p.shape)}")
    if p.shape[0] < min_points:
        raise ValueError(f"{name} needs at least {min_points} points, got {p.shape[0]}")
    if not bool(torch.isfinite(p).all()):
        raise ValueError(f"{name} contains NaN or inf points")
    return p


def _check_state(state: TIQFState) -> None:
    if tuple(state.x.shape) != (4,) or tuple(state.Sigma.shape) != (4, 4) or tuple(state.t.shape) != (3,):
        raise ValueError("TIQFState must hold x (4,), Sigma (4, 4) and t (3,), got "
                         f"{tuple(state.x.shape)}, {tuple(state.Sigma.shape)}, {tuple(state.t.shape)}")
    for name in ("x", "Sigma", "t"):
        if not bool(torch.isfinite(getattr(state, name)).all()):
            raise ValueError(f"TIQFState.{name} contains NaN or inf")
    if float(torch.linalg.vector_norm(state.x)) < 1e-6:
        raise ValueError("TIQFState.x has zero norm")
    if float(torch.linalg.eigvalsh(0.5 * (state.Sigma + state.Sigma.T).double()).min()) <= 0:
        raise ValueError("TIQFState.Sigma must be symmetric positive definite")


def initial_state(pose, config: TIQFConfig = TIQFConfig()) -> TIQFState:
    """Prior state from a pose ``(4, 4)``: ``x`` its rotation quaternion (``w >= 0``), covariance
    ``init_cov (I_4 - x x^T) + init_cov_norm x x^T`` (see :class:`TIQFConfig`), ``t`` its translation."""
    T = check_poses(pose, "init")
    if T.shape != (4, 4):
        raise ValueError(f"init pose must have shape (4, 4), got {tuple(T.shape)}")
    x = _matrix_to_quat(T[:3, :3].double())
    x = x / torch.linalg.vector_norm(x)
    eye = torch.eye(4, dtype=torch.float64, device=T.device)
    xx = torch.outer(x, x)
    Sigma = config.init_cov * (eye - xx) + config.init_cov_norm * xx
    return TIQFState(x=x, Sigma=Sigma, t=T[:3, 3].double(), iterations=0, converged=False)


def _nearest(tree, model: torch.Tensor, local: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Distances and indices ``(N,)`` of the nearest model point to each row of ``local (N, 3)``."""
    if tree is not None:
        dist, idx = tree.query(local.detach().cpu().numpy(), k=1)
        return torch.as_tensor(dist, device=local.device), torch.as_tensor(idx, device=local.device)
    return torch.cdist(local, model).min(dim=1)


def register(model_points, scene_points, init, config: TIQFConfig = TIQFConfig()):
    """TIQF registration of a model cloud to a scene cloud (Sec. II-C).

    Args:
        model_points: ``(M, 3)`` object-frame model points (e.g. ``KnownObject.sample_surface``).
        scene_points: ``(N, 3)`` world-frame measured points (visual or tactile), ``N >= 3``.
        init: a pose ``(4, 4)`` (object -> world; prior from :func:`initial_state`) or a
            :class:`TIQFState` from an earlier call, whose mean, covariance and translation carry over.
        config: :class:`TIQFConfig`.

    Returns:
        ``(pose (4, 4), state, info)``: the estimate (dtype of ``scene_points``), the posterior
        :class:`TIQFState` (float64) and a dict with ``iterations``, ``converged``, ``mean_residual``
        (mean nearest-neighbour distance of the last iteration's correspondences, m),
        ``n_correspondences`` and ``time_s``.

    Each iteration: (1) for every scene point the nearest model point under the current pose
    (scene -> model, so partial views and sparse touches each get a correspondence); (2) pairs of
    correspondences -> ``H`` (Eq. 12), one Kalman update (Eq. 14-17) of the prior that
    ``config.iteration_prior`` names and the normalisation (Eq. 18); (3) translation from the new rotation
    (Eq. 6). It stops when the pose changes by less than ``tol_translation`` and ``tol_rotation_deg`` or
    after ``max_iterations``. The translation is not a filter state (as in the paper): every call
    re-estimates it from its own correspondences, so sparse touches fully re-determine it.
    """
    return _register(model_points, scene_points, init, config)


def _model_tree(model_points):
    """``scipy.spatial.cKDTree`` of the model points ``(M, 3)`` as :func:`register` builds it (float64, CPU)."""
    from scipy.spatial import cKDTree

    return cKDTree(_check_cloud(model_points, "model_points", 1).detach().to(torch.float64).cpu().numpy())


def _register(model_points, scene_points, init, config: TIQFConfig, tree=None):
    """:func:`register`; ``tree``: the model's KD-tree (:func:`_model_tree`) when the caller registers many times
    against the same model (``config.nn == "kdtree"``; built here when None)."""
    t0 = time.perf_counter()
    model = _check_cloud(model_points, "model_points", 1)
    scene = _check_cloud(scene_points, "scene_points", 3)
    out_dtype = scene.dtype
    dev = scene.device
    model = model.to(device=dev, dtype=torch.float64)
    scene = scene.to(torch.float64)
    if isinstance(init, TIQFState):
        _check_state(init)
        state = init
    else:
        state = initial_state(torch.as_tensor(init).to(dev), config)
    x = state.x.to(device=dev, dtype=torch.float64)
    x = x / torch.linalg.vector_norm(x)
    Sigma = state.Sigma.to(device=dev, dtype=torch.float64)
    t = state.t.to(device=dev, dtype=torch.float64)
    R = _quat_to_matrix(x)

    if config.nn != "kdtree":
        tree = None
    elif tree is None:
        from scipy.spatial import cKDTree

        tree = cKDTree(model.cpu().numpy())
    pair_i = pair_j = None
    if config.pairing == "random":  # one matching of the scene points per call (see TIQFConfig.pairing)
        gen = torch.Generator(device="cpu").manual_seed(config.seed)
        pair_i, pair_j = random_matching(scene.shape[0], gen, dev)
    tol_rot = math.radians(config.tol_rotation_deg)
    iterated = config.iteration_prior == "call"
    if iterated:  # the call's prior and its Eq. 17 noise are the same in every iteration: precompute
        C = _information_basis(_spd_inverse(measurement_noise(x, Sigma, config.rho)))
        prior_info = _pd_inverse(Sigma)
        prior_b = prior_info @ x
    converged = False
    it = 0
    n_corr = scene.shape[0]
    dist = torch.full((1,), float("nan"), dtype=torch.float64)
    for it in range(1, config.max_iterations + 1):
        # (1) correspondences: scene points into the object frame of the current pose, nearest model point
        dist, idx = _nearest(tree, model, (scene - t) @ R)  # (scene - t) @ R = R^T (s - t)
        o_all = model[idx]
        s, o, pi, pj = scene, o_all, pair_i, pair_j
        if config.max_correspondence_distance is not None:
            keep = dist <= config.max_correspondence_distance
            if int(keep.sum()) < 3:
                break  # too few correspondences left to update; keep the current estimate
            s, o = s[keep], o_all[keep]
            if pi is not None:
                kp = keep[pi] & keep[pj]
                pi, pj = pi[kp], pj[kp]
        n_corr = s.shape[0]
        # (2) Kalman update of the quaternion with the pairs' pseudo-measurements (Eq. 13-17; the same
        # algebra as kalman_update, on the pair coordinates v), then Eq. 18
        if pi is not None:  # the scene points' fixed random pairs
            v = _pair_vectors(scene[pj] - scene[pi], o_all[pj] - o_all[pi])
        else:  # every correspondence with the centroids
            v = _pair_vectors(s - s.mean(0), o - o.mean(0))
        if iterated:  # iterated Kalman update: the call's prior, correspondences re-associated at x
            x_new, Sigma_new = normalise(*_posterior(prior_info, prior_b, _information(v, C)))
            if torch.dot(x_new, x) < 0:  # keep the hemisphere of the running estimate (same rotation)
                x_new = -x_new
        else:  # the paper read literally: last iteration's posterior is the prior
            C_t = _information_basis(_spd_inverse(measurement_noise(x, Sigma, config.rho)))
            prior_info_t = _pd_inverse(Sigma)
            x_new, Sigma_new = normalise(*_posterior(prior_info_t, prior_info_t @ x, _information(v, C_t)))
        # (3) translation in closed form (Eq. 6); change of pose for the convergence test
        R_new = _quat_to_matrix(x_new)
        t_new = translation_from_rotation(R_new, s, o)
        cos_half = torch.dot(x_new, x).abs().clamp(max=1.0)  # rotation change = 2 acos |<x_new, x>|
        change = torch.stack([torch.linalg.vector_norm(t_new - t),
                              2.0 * torch.atan2(torch.sqrt((1.0 - cos_half ** 2).clamp_min(0.0)), cos_half)])
        x, Sigma, R, t = x_new, Sigma_new, R_new, t_new
        dt, dr = change.tolist()
        if dt < config.tol_translation and dr < tol_rot:
            converged = True
            break

    final = TIQFState(x=x, Sigma=Sigma, t=t, iterations=it, converged=converged)
    info = {"iterations": it, "converged": converged, "mean_residual": float(dist.mean()),
            "n_correspondences": n_corr, "time_s": time.perf_counter() - t0}
    return make_pose(R, t).to(out_dtype), final, info


def state_at_pose(state: TIQFState, pose) -> TIQFState:
    """``state`` with its mean moved to ``pose (4, 4)``: the quaternion of its rotation (on ``state.x``'s
    hemisphere) and its translation; the covariance, iterations and convergence flag stay."""
    T = check_poses(torch.as_tensor(pose), "pose").to(state.x)
    q = _matrix_to_quat(T[:3, :3])
    if float(q @ state.x) < 0:
        q = -q
    return TIQFState(x=q / torch.linalg.vector_norm(q), Sigma=state.Sigma, t=T[:3, 3].clone(),
                     iterations=state.iterations, converged=state.converged)


def registration_residual(model_points, scene_points, pose) -> float:
    """Mean distance (m) from each scene point ``(N, 3)`` (world) to its nearest model point ``(M, 3)`` (object
    frame) at ``pose (4, 4)``: how well the posed model explains the cloud (with a dense model, about 0.5 mm for
    exact touches at the true pose of a YCB object and 20,000 model points)."""
    return _tree_residual(_model_tree(model_points), scene_points, pose)


def _tree_residual(tree, scene_points, pose) -> float:
    """:func:`registration_residual` against a prebuilt model KD-tree (:func:`_model_tree`)."""
    scene = _check_cloud(scene_points, "scene_points", 1).detach().cpu().double()
    T = check_poses(torch.as_tensor(pose), "pose").detach().cpu().double()
    local = (scene - T[:3, 3]) @ T[:3, :3]
    dist, _ = tree.query(local.numpy(), k=1)
    return float(dist.mean())


def yaw_shift_starts(pose, num_yaw: int, shift: float) -> torch.Tensor:
    """Start poses ``(9 num_yaw, 4, 4)`` around ``pose (4, 4)``: its rotation turned about the world vertical through
    its origin by ``k 360 / num_yaw`` deg (k = 0..num_yaw-1), each shifted by ``{-shift, 0, shift}`` m in world x
    and y. The starts of :func:`register_restarts` for an object that stands on a table (yaw is what a coarse
    prior knows least)."""
    T = check_poses(torch.as_tensor(pose), "pose").detach().double()
    if not (isinstance(num_yaw, int) and not isinstance(num_yaw, bool) and num_yaw >= 1):
        raise ValueError(f"num_yaw must be an int >= 1, got {num_yaw!r}")
    if not (math.isfinite(shift) and shift >= 0):
        raise ValueError(f"shift must be finite and >= 0 m, got {shift!r}")
    a = torch.arange(num_yaw, dtype=torch.float64, device=T.device) * (2 * math.pi / num_yaw)
    Rz = torch.zeros(num_yaw, 3, 3, dtype=torch.float64, device=T.device)
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1] = a.cos(), -a.sin(), a.sin(), a.cos()
    Rz[:, 2, 2] = 1.0
    s = torch.tensor([-shift, 0.0, shift], dtype=torch.float64, device=T.device)
    dxy = torch.cartesian_prod(s, s)  # (9, 2)
    out = T.expand(num_yaw, 9, 4, 4).clone()
    out[:, :, :3, :3] = (Rz @ T[:3, :3])[:, None]
    out[:, :, :2, 3] = T[:2, 3] + dxy[None]
    return out.reshape(-1, 4, 4)


def register_restarts(model_points, scene_points, init, starts=None, config: TIQFConfig = TIQFConfig(),
                      restart_tol: float = 0.001, residual=None, refine_rounds: int = 3, refine_starts: int = 30,
                      refine_deg: float = 8.0, refine_shift: float = 0.005):
    """:func:`register` from ``init``, then, if the result explains the cloud worse than ``restart_tol`` (m), again
    from every start pose ``(S, 4, 4)`` (each with :func:`initial_state`'s prior), then, while the best result is
    still worse than ``restart_tol``, up to ``refine_rounds`` rounds of ``refine_starts`` starts around the best
    result (turned about a random axis by up to ``refine_deg`` deg and shifted by a normal ``refine_shift`` m per
    axis; drawn from ``config.seed``, so deterministic); the result with the smallest residual wins.
    ``residual(pose (4, 4)) -> float`` (m) scores a result: by default :func:`registration_residual` of the scene
    to the model cloud, whose floor is the cloud's spacing (about 1 mm on a cereal-box-sized object at 20,000
    points); an exact distance to the mesh has no such floor.

    Why (beyond the paper): with nearest-neighbour correspondences a sparse cloud (5-12 tactile points) keeps the
    registration in the basin it starts from: from the transparent target's wrong visual estimate (30-100 mm ADI)
    the touches alone ended at a median 13.7 mm, from the true pose at 0.5 mm, and a wrong basin shows as a
    residual of 1-10 mm against 0.4-0.7 mm at the truth (offline on logged touches, 20,000 model points).

    Returns:
        ``(pose (4, 4), state, info)`` as :func:`register`, with ``info["residual"]`` (m) and ``info["restarts"]``
        (how many start poses were tried; 0 when the first result was good enough or there were none).

    The refinement rounds exist because TIQF's own basin is narrow on a sparse cloud: 12 exact touches of the
    mustard bottle registered from starts 15 deg and 3 cm off ended 2.7 mm from the touches (ADI 4.7 mm), three
    rounds around the best took that to 0.6 mm (ADI 1.6 mm); from the true pose TIQF stays at 0.3 mm.
    """
    if not (math.isfinite(restart_tol) and restart_tol > 0):
        raise ValueError(f"restart_tol must be finite and > 0 m, got {restart_tol!r}")
    for name, v in (("refine_rounds", refine_rounds), ("refine_starts", refine_starts)):
        if isinstance(v, bool) or not isinstance(v, int) or v < 0:
            raise ValueError(f"{name} must be an int >= 0, got {v!r}")
    if not (math.isfinite(refine_deg) and refine_deg >= 0 and math.isfinite(refine_shift) and refine_shift >= 0):
        raise ValueError(f"refine_deg and refine_shift must be finite and >= 0, got {refine_deg!r}, {refine_shift!r}")
    tree = _model_tree(model_points)  # once for every registration below (it dominated a sparse registration)
    if residual is None:
        def residual(p):
            return _tree_residual(tree, scene_points, p)
    pose, state, info = _register(model_points, scene_points, init, config, tree)
    best = (float(residual(pose)), pose, state, info)
    n = 0
    if starts is not None and best[0] > restart_tol:
        S = check_poses(torch.as_tensor(starts), "starts")
        S = S.reshape(-1, 4, 4)
        for T0 in S:
            p, s, i = _register(model_points, scene_points, T0, config, tree)
            r = float(residual(p))
            if r < best[0]:
                best = (r, p, s, i)
        n = int(S.shape[0])
        from ..geometry import axis_angle_to_matrix

        gen = torch.Generator(device="cpu").manual_seed(config.seed)
        for _ in range(refine_rounds):
            if best[0] <= restart_tol:
                break
            base = best[1].detach().cpu().double()
            for _ in range(refine_starts):
                axis = torch.randn(3, generator=gen, dtype=torch.float64)
                angle = math.radians(refine_deg) * float(torch.rand((), generator=gen, dtype=torch.float64))
                dR = axis_angle_to_matrix(axis / axis.norm() * angle)
                dt = refine_shift * torch.randn(3, generator=gen, dtype=torch.float64)
                T0 = make_pose(dR @ base[:3, :3], base[:3, 3] + dt).to(S.device)
                p, s, i = _register(model_points, scene_points, T0, config, tree)
                r = float(residual(p))
                if r < best[0]:
                    best = (r, p, s, i)
                n += 1
    r, pose, state, info = best
    return pose, state, {**info, "residual": r, "restarts": n}
