"""Contact-placed prior proposals at RUMI's resampling (activetouch.belief.reinvigorate, BeliefConfig.reinvigorate).

Scenario: the cracker box lies on its back; the robot has touched its top and one side (surface points on two
faces), and the particles all rest on a wrong face, as after a one-face contact pruned the true face on the box
tasks (issue 8). Algorithm 4 as published (sigma_R = 0) cannot change a particle's resting face; with the
proposals the belief gets particles on the true face back.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from activetouch import objects
from activetouch.belief import BeliefConfig, ParticleBelief, resting_face_prior
from activetouch.belief.priors import resting_faces
from activetouch.belief.reinvigorate import model_surface, place_on_surface, surface_normals
from activetouch.geometry import transform_points, yaw_matrix
from activetouch.observations import Features, voxel_downsample

XY = (0.40, -0.18)


@pytest.fixture(scope="module")
def box():
    return objects.load("cracker_box")


def _rest(box, face: int, yaw: float, xy=XY) -> torch.Tensor:
    """Pose ``(4, 4)`` resting face ``face`` (of ``resting_faces()``) on the table at ``xy`` with ``yaw``."""
    R = yaw_matrix(torch.tensor(yaw, dtype=torch.float64)) @ resting_faces()[face]
    V = torch.as_tensor(np.asarray(box.mesh.vertices), dtype=torch.float64) @ R.T
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = R
    T[0, 3], T[1, 3] = xy
    T[2, 3] = -float(V[:, 2].min())
    return T


def _face_of(box, T) -> int:
    """Index of the object axis pointing down under pose ``T``: 0..5 as in ``resting_faces()``."""
    down = T[:3, :3].T @ torch.tensor([0.0, 0.0, -1.0], dtype=T.dtype)
    a = int(torch.argmax(down.abs()))
    return 2 * a + (0 if float(down[a]) > 0 else 1)


@pytest.fixture(scope="module")
def truth(box):
    return _rest(box, 1, 0.5)  # -x of the box frame (its thin axis) down: lying on a broad face


@pytest.fixture(scope="module")
def touched(box, truth):
    """Surface points on the top face and one side face of the true box, 2 mm apart, plus floor free points."""
    pts, fi = trimesh.sample.sample_surface(box.mesh, 30000, seed=3)
    n = box.mesh.face_normals[fi]
    up = (torch.as_tensor(n, dtype=torch.float64) @ truth[:3, :3].T)[:, 2].numpy() > 0.9
    side = n[:, 1] > 0.9  # the +y side face
    keep = up | side
    surf = transform_points(truth, torch.as_tensor(pts[keep], dtype=torch.float64)).float()
    g = np.random.default_rng(0)
    floor = np.c_[g.uniform(0.2, 0.6, 400), g.uniform(-0.4, 0.05, 400), np.full(400, -0.01)]
    X = Features(torch.cat([surf, torch.tensor(floor, dtype=torch.float32)]),
                 torch.tensor([0] * len(surf) + [1] * len(floor)))
    return voxel_downsample(X, r_free=0.010, r_surface=0.002)


def _wrong_face_belief(box, config, seed=0):
    g = torch.Generator().manual_seed(seed)
    yaws = torch.rand(config.num_particles, generator=g, dtype=torch.float64) * 2 * math.pi
    poses = torch.stack([_rest(box, 5, float(y)) for y in yaws])  # all upright (-z down)
    return ParticleBelief(box, poses, None, config)


def test_place_on_surface_puts_a_model_point_on_the_contact_and_keeps_rotation_and_height(box, truth):
    g = torch.Generator().manual_seed(1)
    prior = resting_face_prior(torch.tensor([*XY, 0.0]), box.mesh.vertices, n=50, generator=g)
    model = box.sample_surface(2000, seed=0).double()
    contact = torch.tensor([[0.43, -0.15, 0.03]], dtype=torch.float64)
    placed = place_on_surface(model, prior, contact, generator=g)
    assert torch.equal(placed[:, :3, :3], prior[:, :3, :3])
    assert torch.equal(placed[:, 2, 3], prior[:, 2, 3])
    d = (transform_points(placed, model) - contact).norm(dim=-1).min(dim=1).values  # (50,) nearest model point
    reachable = (transform_points(prior, model)[..., 2] - 0.03).abs().min(dim=1).values <= 0.005
    assert bool(reachable.any())
    assert float(d[reachable].max()) < 0.0055  # within the height tolerance (x, y are exact)
    assert torch.equal(placed[~reachable], prior[~reachable])  # nothing at that height: unchanged


def _rot_err_mod_symmetry(R: torch.Tensor, R_true: torch.Tensor) -> torch.Tensor:
    """Rotation error ``(K,)`` (rad) of ``R (K, 3, 3)`` to ``R_true``, up to the box's 180 deg turns about its axes."""
    errs = []
    for d in ([1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]):
        rel = R.double() @ (R_true.double() @ torch.diag(torch.tensor(d, dtype=torch.float64))).T
        errs.append(torch.acos(((rel.diagonal(dim1=1, dim2=2).sum(-1) - 1) / 2).clamp(-1, 1)))
    return torch.stack(errs).min(dim=0).values


def test_surface_normals_fit_the_local_plane(box, truth):
    pts, fi = trimesh.sample.sample_surface(box.mesh, 20000, seed=4)
    side = box.mesh.face_normals[fi][:, 1] > 0.9  # the +y face
    world = transform_points(truth, torch.as_tensor(pts[side], dtype=torch.float64))
    n = surface_normals(world, world[::50])
    true_n = truth[:3, :3] @ torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    cos = (n @ true_n).abs()  # up to sign; the scanned YCB face is not quite flat
    assert float(cos.median()) > 0.99 and float(cos.min()) > 0.9
    assert torch.equal(surface_normals(world[:2], world[:1]), torch.zeros(1, 3, dtype=world.dtype))


def test_normal_aligned_placement_finds_the_true_orientation_far_more_often(box, truth):
    """Proposals placed on a one-face contact (the +y side of the true box): turning each draw about z so the
    model's normal matches the contact's makes ~9x more of them land within 5 deg of the true orientation (up
    to the box's symmetry) than keeping the drawn yaw, and every placement still puts a model point on the
    contact."""
    pts, fi = trimesh.sample.sample_surface(box.mesh, 30000, seed=3)
    side = box.mesh.face_normals[fi][:, 1] > 0.9
    contact = transform_points(truth, torch.as_tensor(pts[side], dtype=torch.float64))[::10]
    model, normals = model_surface(box, 2000, seed=0)
    assert torch.equal(model, box.sample_surface(2000, seed=0))  # the same samples the belief uses
    assert float((normals.norm(dim=1) - 1).abs().max()) < 1e-5
    shares = {}
    for aligned in (False, True):
        g = torch.Generator().manual_seed(0)
        prior = resting_face_prior(torch.tensor([*XY, 0.0]), box.mesh.vertices, n=2000, generator=g).double()
        placed = place_on_surface(model.double(), prior, contact, generator=g,
                                  model_normals=normals.double() if aligned else None)
        assert torch.allclose(placed[:, :3, :3] @ placed[:, :3, :3].transpose(1, 2),
                              torch.eye(3, dtype=torch.float64).expand(2000, 3, 3), atol=1e-9)
        assert torch.allclose(placed[:, 2, 3], prior[:, 2, 3])  # heights kept: still resting on the table
        if aligned:  # the normal-matching model point lies on a contact point (x, y exact, z within 5 mm)
            d = torch.cdist(transform_points(placed, model.double()).reshape(-1, 3), contact).min(dim=1).values
            assert float(d.reshape(2000, -1).min(dim=1).values.max()) < 0.0055
        shares[aligned] = float((_rot_err_mod_symmetry(placed[:, :3, :3], truth[:3, :3]) < math.radians(5))
                                .double().mean())
    assert shares[False] < 0.04 and shares[True] > 0.10 and shares[True] > 5 * shares[False], shares
    # the same generator state gives the same placements
    g1, g2 = torch.Generator().manual_seed(7), torch.Generator().manual_seed(7)
    prior = resting_face_prior(torch.tensor([*XY, 0.0]), box.mesh.vertices, n=50, generator=g1).double()
    prior2 = resting_face_prior(torch.tensor([*XY, 0.0]), box.mesh.vertices, n=50, generator=g2).double()
    assert torch.equal(place_on_surface(model.double(), prior, contact, g1, model_normals=normals.double()),
                       place_on_surface(model.double(), prior2, contact, g2, model_normals=normals.double()))


def test_normal_aligned_placement_without_a_plane_keeps_the_drawn_orientation(box):
    """Fewer than 3 observed points fit no plane (zero normal): no normal condition and no turn, so a placement
    keeps its drawn rotation and any model point at the contact's height qualifies, as without normals."""
    model, normals = model_surface(box, 2000, seed=0)
    g = torch.Generator().manual_seed(2)
    prior = resting_face_prior(torch.tensor([*XY, 0.0]), box.mesh.vertices, n=40, generator=g).double()
    contact = torch.tensor([[0.43, -0.15, 0.03], [0.44, -0.15, 0.03]], dtype=torch.float64)
    placed = place_on_surface(model.double(), prior, contact, g, model_normals=normals.double())
    assert torch.equal(placed[:, :3, :3], prior[:, :3, :3])
    reachable = (transform_points(prior, model.double())[..., 2] - 0.03).abs().min(dim=1).values <= 0.005
    moved = (placed[:, :2, 3] - prior[:, :2, 3]).norm(dim=1) > 0
    assert bool(reachable.any()) and torch.equal(moved, reachable)


def test_place_on_surface_rejects_bad_shapes(box):
    model = box.sample_surface(10, seed=0)
    with pytest.raises(ValueError, match="surface"):
        place_on_surface(model, torch.eye(4).expand(2, 4, 4), torch.zeros(0, 3))
    with pytest.raises(ValueError, match="poses"):
        place_on_surface(model, torch.eye(4), torch.zeros(1, 3))


def test_config_checks_reinvigorate_settings():
    with pytest.raises(ValueError, match="reinvigorate"):
        BeliefConfig(reinvigorate=-1)
    with pytest.raises(ValueError, match="reinvigorate_share"):
        BeliefConfig(reinvigorate_share=0.0)
    with pytest.raises(ValueError, match="reinvigorate_normals"):
        BeliefConfig(reinvigorate_normals="yes")
    assert BeliefConfig().reinvigorate == 0  # the paper's Algorithm 4 by default


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_proposals_bring_the_true_face_back(box, truth, touched, seed):
    paper = BeliefConfig(se2=False)
    ours = BeliefConfig(se2=False, reinvigorate=100)
    prior = lambda n, g: resting_face_prior(torch.tensor([*XY, 0.0]), box.mesh.vertices, n=n, generator=g)

    b0 = _wrong_face_belief(box, paper, seed)
    b0.resample(touched, torch.Generator().manual_seed(seed))
    assert {_face_of(box, T) for T in b0.poses} == {5}  # sigma_R = 0: no particle leaves its face
    c0 = b0.discrepancy(touched)

    b1 = _wrong_face_belief(box, ours, seed)
    b1.proposal = prior
    b1.resample(touched, torch.Generator().manual_seed(seed))
    c1 = b1.discrepancy(touched)
    k = b1.last_reinvigorated
    assert 0 < k <= 20  # at most reinvigorate_share P = 20 moves
    faces = [_face_of(box, T) for T in b1.poses]
    assert sum(f != 5 for f in faces) <= k  # the replaced particles are the ones off the wrong face
    true_face = _face_of(box, truth)
    opposite = true_face ^ 1  # the box lying on its other broad face fits the same two touched faces' planes
    assert any(f in (true_face, opposite) for f in faces)
    assert float(c1.min()) < 0.5 * float(c0.min())  # far better fits than any wrong-face particle
    assert torch.isfinite(b1.weights).all() and abs(float(b1.weights.sum()) - 1) < 1e-6


def test_without_a_proposal_or_with_zero_candidates_resampling_is_the_papers(box, touched):
    """reinvigorate = 0 (the default) ignores a set proposal; a config asking for it without a proposal does
    nothing either: both give the paper's Algorithm 4 exactly."""
    ref = _wrong_face_belief(box, BeliefConfig(se2=False), 5)
    ref.resample(touched, torch.Generator().manual_seed(5))
    a = _wrong_face_belief(box, BeliefConfig(se2=False), 5)
    a.proposal = lambda n, g: torch.eye(4, dtype=torch.float64).expand(n, 4, 4).clone()
    a.resample(touched, torch.Generator().manual_seed(5))
    b = _wrong_face_belief(box, BeliefConfig(se2=False, reinvigorate=50), 5)  # no proposal set
    b.resample(touched, torch.Generator().manual_seed(5))
    assert torch.equal(a.poses, ref.poses) and torch.equal(b.poses, ref.poses)
    assert a.last_reinvigorated == 0 and b.last_reinvigorated == 0


@pytest.mark.parametrize("seed", [0, 1])
def test_a_belief_at_the_truth_is_not_replaced_by_worse_proposals(box, truth, touched, seed):
    """The Metropolis rule: proposals that fit the evidence worse than the particles they meet rarely enter.
    Particles 1 mm around the truth, which the touched faces fit: after the move no particle fits much worse
    than the worst one before (a proposal 3 units of C^ worse enters with probability exp(-6) = 0.25 %)."""
    from activetouch.belief.resample import perturb_poses

    g = torch.Generator().manual_seed(seed)
    poses = perturb_poses(truth.expand(100, 4, 4).clone(), 0.001, 0.0, False, g)
    b = ParticleBelief(box, poses, None, BeliefConfig(se2=False, reinvigorate=100))
    b.proposal = lambda n, gen: resting_face_prior(torch.tensor([*XY, 0.0]), box.mesh.vertices, n=n, generator=gen)
    before = b.discrepancy(touched)
    b._poses = b._reinvigorate(touched, b.poses, before, g)
    after = b.discrepancy(touched)
    assert float(after.max()) < float(before.max()) + 3.0
    assert float(after.median()) < float(before.median()) + 1.0


def test_every_step_move_brings_proposals_without_a_resample(box, truth, touched):
    """reinvigorate_every_step: the move also at an update that re-weighs (max C^ <= l_r, Alg. 1 line 20), where
    the default leaves the particles as they are. l_r is raised so that the wrong-face belief is not resampled."""
    prior = lambda n, g: resting_face_prior(torch.tensor([*XY, 0.0]), box.mesh.vertices, n=n, generator=g)
    base = dict(se2=False, reinvigorate=100, resample_threshold=1e9)
    a = _wrong_face_belief(box, BeliefConfig(**base), 3)
    a.proposal = prior
    before = a.poses.clone()
    assert a.update(touched, torch.Generator().manual_seed(3)) is False
    assert torch.equal(a.poses, before) and a.last_reinvigorated == 0
    b = _wrong_face_belief(box, BeliefConfig(**base, reinvigorate_every_step=True), 3)
    b.proposal = prior
    assert b.update(touched, torch.Generator().manual_seed(3)) is False
    assert 0 < b.last_reinvigorated <= 20
    faces = [_face_of(box, T) for T in b.poses]
    true_face = _face_of(box, truth)
    assert any(f in (true_face, true_face ^ 1) for f in faces)
    w = b.weights
    assert torch.isfinite(w).all() and abs(float(w.sum()) - 1) < 1e-6
    assert float(w[[f != 5 for f in faces]].sum()) > 0.5  # the new fits carry the posterior's weight
    with pytest.raises(ValueError, match="reinvigorate_every_step"):
        BeliefConfig(reinvigorate_every_step=1)
