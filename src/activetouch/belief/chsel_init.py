"""Initial pose particles by CHSEL quality-diversity registration (RUMI Algorithm 1 line 2, [54]).

Wraps chsel 0.2.1 (``chsel.CHSEL``), which does the real work. Notes (LIBRARY-NOTES):

* chsel's transforms map world -> object; we pass ``invert(prior)`` and invert its answer back.
* positions + semantics are passed directly (the README's ``surface_pts=`` form crashes).
* occupied points are ignored unless ``scale_known_occ`` is given: we pass C when there are any.
* SE(2): ``axis_of_rotation = [0, 0, 1]`` (the yaw is then CHSEL's QD measure) and
  ``offset_along_axis = -z`` (the world -> object translation of an upright pose at height z has
  z component -z). Results are projected back onto upright poses at the prior height.
* chsel draws random numbers from torch's and numpy's global generators (ribs emitters are seeded from
  numpy's): we seed both from the caller's generator and restore their state, so the same seed gives
  the same particles.
* chsel samples the object interior at ``resolution``; the thin-walled mug needs 4 mm.
* CHSEL's cost and ours share the SDF: an adapter exposes ``KnownObject``'s voxel-cached SDF as a
  ``pytorch_volumetric.ObjectFrameSDF``.
"""
from __future__ import annotations

import logging
import tempfile

import numpy as np
import torch

from ..geometry import check_poses, invert, pose_from_xyz_yaw, yaw_of
from .config import BeliefConfig, chsel_min_batch
from .discrepancy import FREE, OCCUPIED, SURFACE

__all__ = ["chsel_register", "KnownObjectSDF"]

log = logging.getLogger(__name__)


def _pv_sdf_class():
    import pytorch_volumetric as pv

    class KnownObjectSDF(pv.ObjectFrameSDF):
        """``pytorch_volumetric.ObjectFrameSDF`` view of a ``KnownObject``'s cached (or exact) SDF."""

        def __init__(self, obj, exact: bool = False):
            self.obj = obj
            self.exact = exact

        def __call__(self, points_in_object_frame, compute_grad=True):
            fn = self.obj.sdf if self.exact else self.obj.cached_sdf
            if compute_grad:
                return fn(points_in_object_frame)
            with torch.no_grad():
                v, _ = fn(points_in_object_frame)
            return v, None

        def surface_bounding_box(self, padding=0., padding_ratio=0.):
            b = torch.tensor(np.array(self.obj.mesh.bounds), dtype=torch.float32)  # (2, 3)
            ext = b[1] - b[0]
            pad = padding + padding_ratio * ext
            return torch.stack([b[0] - pad, b[1] + pad], dim=1)  # (3, 2) (min, max) per dimension

    return KnownObjectSDF


def KnownObjectSDF(obj, exact: bool = False):  # noqa: N802 - factory named like the class it returns
    """Adapter: a ``pytorch_volumetric.ObjectFrameSDF`` backed by ``obj.cached_sdf`` (or ``obj.sdf``)."""
    return _pv_sdf_class()(obj, exact)


def _seed_from(generator: torch.Generator | None) -> int:
    gdev = generator.device if generator is not None else torch.device("cpu")
    return int(torch.randint(0, 2**31 - 1, (1,), generator=generator, device=gdev))


def _registration_subset(obj, features, prior: torch.Tensor, max_points: int, generator):
    """At most ``max_points`` features of each semantics class, seeded; free points that cannot touch any prior
    particle are dropped first (see :func:`activetouch.belief.discrepancy.prune_far_free`)."""
    from .discrepancy import prune_far_free

    features = prune_far_free(obj, features, prior)
    keep = []
    gdev = generator.device if generator is not None else torch.device("cpu")
    for value in (SURFACE, FREE, OCCUPIED):
        idx = torch.nonzero(features.semantics == value).flatten()
        if len(idx) > max_points:
            perm = torch.randperm(len(idx), generator=generator, device=gdev).to(idx.device)
            idx = idx[perm[:max_points]].sort().values
        keep.append(idx)
    return features.select(torch.cat(keep))


def chsel_register(obj, prior_poses: torch.Tensor, features, config: BeliefConfig,
                   generator: torch.Generator | None = None) -> torch.Tensor:
    """CHSEL-registered pose particles ``(P, 4, 4)`` (object -> world) from prior particles ``(P, 4, 4)``.

    Uses ``config.chsel_iterations`` registration rounds (each: SGD from the current transforms, then
    ``config.chsel_qd_iterations`` CMA-MEGA quality-diversity iterations), ``config.chsel_resolution``,
    ``config.free_scale`` (C) for free (and occupied) points and ``config.violation_tolerance`` as chsel's
    ``surface_threshold``. ``config.chsel_batch = None`` registers every prior particle (the paper); a
    smaller batch registers the first ``chsel_batch`` prior particles and the P outputs are CHSEL's
    ``batch`` results repeated in turn (SIMPLIFICATION: fewer distinct initial particles, for speed; the
    first Resample perturbs them apart).
    """
    prior = check_poses(prior_poses, "prior_poses")
    if prior.ndim != 3:
        raise ValueError(f"prior_poses must have shape (P, 4, 4), got {tuple(prior.shape)}")
    P = prior.shape[0]
    B = P if config.chsel_batch is None else min(int(config.chsel_batch), P)
    need = chsel_min_batch(config.chsel_iterations)
    if B < need:
        raise ValueError(f"CHSEL initialisation with {config.chsel_iterations} round(s) needs at least {need} "
                         f"particles, got {B} (chsel 0.2.1 makes NaN poses or crashes below that); use more "
                         f"particles or skip CHSEL (use_chsel=False, --no-chsel)")
    import chsel  # after the cheap checks: importing chsel (pyribs, cma) takes seconds

    dtype, device = prior.dtype, prior.device
    features = _registration_subset(obj, features, prior, int(config.chsel_max_points), generator)
    x = features.positions.to(device=device, dtype=dtype)
    s = features.semantics.to(device=device, dtype=torch.long)
    if int((s == SURFACE).sum()) == 0:
        raise ValueError("CHSEL needs at least one SURFACE feature to register against")
    init = prior[:B]

    kwargs = {}
    z0 = None
    if config.se2:
        tilt = (init[:, 2, 2] - 1.0).abs().max()
        if float(tilt) > 1e-4:
            raise ValueError("SE(2) CHSEL initialisation needs upright prior poses (rotations about world z only)")
        z = init[:, 2, 3]
        if float(z.max() - z.min()) > 1e-6:
            raise ValueError("SE(2) CHSEL initialisation needs all prior poses at the same height")
        z0 = float(z[0])
        kwargs["axis_of_rotation"] = torch.tensor([0.0, 0.0, 1.0], dtype=dtype, device=device)
        kwargs["offset_along_axis"] = -z0
    has_occ = bool((s == OCCUPIED).any())
    sdf = KnownObjectSDF(obj, exact=config.exact_sdf)

    seed = _seed_from(generator)
    np_state = np.random.get_state()
    devices = [device] if device.type == "cuda" else []
    with torch.random.fork_rng(devices=devices), tempfile.TemporaryDirectory() as savedir:
        torch.manual_seed(seed)
        np.random.seed(seed % (2**32 - 1))
        try:
            reg = chsel.CHSEL(
                sdf, positions=x, semantics=s, resolution=float(config.chsel_resolution),
                qd_iterations=int(config.chsel_qd_iterations), savedir=savedir,
                scale_known_freespace=float(config.free_scale),
                scale_known_occ=float(config.free_scale) if has_occ else 0.0,
                surface_threshold=float(config.violation_tolerance),
                **kwargs,
            )
            res, _ = reg.register(iterations=int(config.chsel_iterations), initial_tsf=invert(init), batch=B)
            world_to_obj = chsel.solution_to_world_to_link_matrix(res)
        finally:
            np.random.set_state(np_state)
    poses = invert(world_to_obj.to(device=device, dtype=dtype))
    if config.se2:
        t = poses[:, :3, 3].clone()
        t[:, 2] = z0
        poses = pose_from_xyz_yaw(t, yaw_of(poses))
    if poses.shape[0] != P:
        reps = -(-P // poses.shape[0])
        poses = poses.repeat(reps, 1, 1)[:P]
    if not bool(torch.isfinite(poses).all()):
        raise RuntimeError("CHSEL returned non-finite poses")
    return poses
