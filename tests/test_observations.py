"""Tests for activetouch.observations: Features, voxel downsampling, MergeObs (Alg. 6), sensor model."""
import math

import pytest
import torch
import trimesh

from activetouch import objects
from activetouch.geometry import transforms as tf
from activetouch.observations import Features, SemanticSensorModel, Semantics, merge_obs, voxel_downsample

S, F, O = int(Semantics.SURFACE), int(Semantics.FREE), int(Semantics.OCCUPIED)


def test_semantics_match_chsel():
    chsel = pytest.importorskip("chsel")
    assert int(chsel.SemanticsClass.SURFACE) == S == 0
    assert int(chsel.SemanticsClass.FREE) == F == 1
    assert int(chsel.SemanticsClass.OCCUPIED) == O == 2


def test_features_validation():
    with pytest.raises(ValueError, match="NaN"):
        Features(torch.tensor([[0.0, float("nan"), 0.0]]), [F])
    with pytest.raises(ValueError, match="NaN or inf"):
        Features(torch.tensor([[0.0, float("inf"), 0.0]]), [F])
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        Features(torch.zeros(4, 2), [F] * 4)
    with pytest.raises(ValueError, match="shape"):
        Features(torch.zeros(4, 3), [F] * 3)
    with pytest.raises(ValueError, match="unknown values \\[3\\]"):
        Features(torch.zeros(2, 3), [F, 3])
    with pytest.raises(ValueError, match="unknown values"):
        Features(torch.zeros(1, 3), [-1])
    with pytest.raises(ValueError, match="non-integer"):
        Features(torch.zeros(1, 3), torch.tensor([0.5]))


def test_features_views_and_empty():
    e = Features.empty()
    assert len(e) == 0 and e.positions.shape == (0, 3) and e.semantics.dtype == torch.long
    assert len(e.free) == 0 and len(Features.concat([])) == 0
    f = Features(torch.arange(12.0).reshape(4, 3), [S, F, F, O])
    assert f.positions.dtype == torch.float32
    assert len(f.free) == 2 and len(f.surface) == 1 and len(f.occupied) == 1
    assert f.counts() == {Semantics.SURFACE: 1, Semantics.FREE: 2, Semantics.OCCUPIED: 1}
    g = f.cat(Features(torch.zeros(1, 3), Semantics.SURFACE))
    assert len(g) == 5 and g.semantics[-1] == S
    assert len(e.cat(f)) == 4
    assert torch.equal(f.select(torch.tensor([True, False, True, False])).semantics, torch.tensor([S, F]))
    assert f.to("cpu").positions.device.type == "cpu"
    T = tf.pose_from_xyz_yaw(torch.tensor([1.0, 0, 0]), torch.tensor(0.0))
    assert torch.allclose(f.transformed(T).positions, f.positions + torch.tensor([1.0, 0, 0]))


def test_voxel_downsample_keeps_the_point_nearest_each_cell_centre():
    r_f, r_s = 0.010, 0.002
    pts = torch.tensor(
        [
            [0.0011, 0.0012, 0.0013],  # free cell (0,0,0) (centre 5, 5, 5 mm): 6.1 mm from the centre
            [0.0061, 0.0042, 0.0049],  # same free cell, 1.4 mm from the centre -> kept
            [0.0101, 0.0, 0.0],  # next free cell (1,0,0)
            [-0.0001, 0.0, 0.0],  # free cell (-1,0,0)
            [0.0011, 0.0012, 0.0013],  # surface cell (0,0,0) of 2 mm (centre 1, 1, 1 mm) -> kept
            [0.0019, 0.0001, 0.0019],  # same surface cell, farther from the centre
            [0.0031, 0.0012, 0.0013],  # surface cell (1,0,0)
            [0.0011, 0.0012, 0.0013],  # occupied, kept separately
        ]
    )
    f = Features(pts, [F, F, F, F, S, S, S, O])
    d = voxel_downsample(f, r_free=r_f, r_surface=r_s)
    assert d.counts() == {Semantics.SURFACE: 2, Semantics.FREE: 3, Semantics.OCCUPIED: 1}
    assert torch.equal(d.surface.positions, pts[[4, 6]])
    assert torch.equal(d.free.positions, pts[[3, 1, 2]])  # sorted by cell index
    assert torch.equal(d.occupied.positions, pts[[7]])
    # idempotent (no drift when merging step after step), empty input allowed
    d2 = voxel_downsample(d, r_free=r_f, r_surface=r_s)
    assert torch.equal(d2.positions, d.positions) and torch.equal(d2.semantics, d.semantics)
    assert len(voxel_downsample(Features.empty())) == 0
    # random cloud: exactly one output per occupied cell, each an input point
    g = torch.Generator().manual_seed(0)
    x = torch.rand(5000, 3, generator=g) * 0.05
    dr = voxel_downsample(Features(x, Semantics.FREE))
    assert len(dr) == len(torch.unique(torch.floor(x / r_f).long(), dim=0))
    assert bool((dr.positions[:, None] == x[None]).all(-1).any(1).all())
    with pytest.raises(ValueError):
        voxel_downsample(f, r_free=0.0)


def test_object_features_do_not_drift_over_many_moves():
    """Alg. 6 moves object features by dT and downsamples again at every push: 40 pushes of a surface
    patch and 40 moves back must leave it where it was (cell-centre snapping drifted +-8 mm on the mug)."""
    g = torch.Generator().manual_seed(3)
    patch = Features(torch.rand(300, 3, generator=g) * 0.03, S)
    X = voxel_downsample(patch, r_surface=0.002)
    start = X.positions.clone()
    moves = [tf.pose_from_xyz_yaw(torch.rand(3, generator=g) * 0.05, torch.rand((), generator=g)) for _ in range(40)]
    for dT in moves:
        X = voxel_downsample(X.transformed(dT), r_surface=0.002)
    for dT in reversed(moves):
        X = voxel_downsample(X.transformed(tf.invert(dT)), r_surface=0.002)
    # float32 round-off only; points that share a cell after a move merge, so compare each to the start set
    assert len(X) <= len(start)
    assert (X.positions[:, None] - start[None]).norm(dim=-1).min(dim=1).values.max() < 1e-5


@pytest.fixture()
def box_obj(tmp_path, monkeypatch):
    """Analytic 4 x 6 x 8 cm box (base-centred), coarse SDF cache in a temporary cache dir."""
    monkeypatch.setenv("ACTIVETOUCH_CACHE_DIR", str(tmp_path / "cache"))
    m = trimesh.creation.box(extents=[0.04, 0.06, 0.08])
    m.apply_translation([0, 0, 0.04])
    p = tmp_path / "box.obj"
    m.export(p)
    return objects.load(str(p), sdf_resolution=0.002)


def test_merge_obs_moves_object_features_and_drops_covered_free_points(box_obj):
    dT_w = tf.pose_from_xyz_yaw(torch.tensor([0.1, 0.0, 0.0]), torch.tensor(0.3))  # object pushed 10 cm, turned
    poses = dT_w.unsqueeze(0)  # particle after the predict step: dT @ I
    prev = Features(
        torch.tensor(
            [
                [0.02, 0.0, 0.04],  # surface point on the old +x face
                [0.1, 0.0, 0.04],  # free before the move, inside the moved box now -> dropped
                [-0.2, 0.0, 0.04],  # free, far from both -> kept
                [0.0, 0.0, 0.1],  # free, above both -> kept
            ]
        ),
        [S, F, F, F],
    )
    new = Features(torch.tensor([[0.3, 0.3, 0.3]]), [F])
    out = merge_obs(prev, new, poses, box_obj, dT_w)
    free = out.free.positions
    assert len(out.free) == 3
    assert torch.cdist(free, torch.tensor([[0.1, 0.0, 0.04]])).min() > 0.02
    for keep in ([-0.2, 0.0, 0.04], [0.0, 0.0, 0.1], [0.3, 0.3, 0.3]):
        assert torch.cdist(free, torch.tensor([keep])).min() < 1e-6
    moved = tf.transform_points(dT_w, torch.tensor([[0.02, 0.0, 0.04]]))
    assert len(out.surface) == 1
    assert (out.surface.positions - moved).norm() < 1e-6
    # the moved surface point is on the moved box
    v, _ = box_obj.sdf_world(poses, out.surface.positions, exact=True)
    assert v.abs().max() < 2e-3


def test_merge_obs_keeps_free_point_only_if_free_for_all_particles(box_obj):
    dT_w = tf.pose_from_xyz_yaw(torch.tensor([0.05, 0.0, 0.0]), torch.tensor(0.0))
    far = tf.pose_from_xyz_yaw(torch.tensor([0.5, 0.5, 0.0]), torch.tensor(0.0))
    covering = tf.pose_from_xyz_yaw(torch.tensor([0.1, 0.0, 0.0]), torch.tensor(0.0))
    prev = Features(torch.tensor([[0.1, 0.0, 0.04]]), [F])
    assert len(merge_obs(prev, Features.empty(), far.unsqueeze(0), box_obj, dT_w).free) == 1
    both = torch.stack([far, covering])
    assert len(merge_obs(prev, Features.empty(), both, box_obj, dT_w)) == 0
    # no move (dT_w None): nothing can have been covered, free evidence is kept
    assert len(merge_obs(prev, Features.empty(), both, box_obj, None)) == 1
    # empty everything
    assert len(merge_obs(Features.empty(), Features.empty(), both, box_obj, dT_w)) == 0


def test_sensor_model_sums_to_one_and_shape():
    sm = SemanticSensorModel()
    assert (sm.zeta, sm.alpha) == (0.003, 100.0)
    z = sm.zeta
    v = torch.cat(
        [
            torch.linspace(-1.0, 1.0, 20001, dtype=torch.float64),
            torch.tensor([0.0, z, -z, z + 1e-9, -z - 1e-9, 1e6, -1e6, float("inf"), -float("inf")], dtype=torch.float64),
        ]
    )
    p = sm.probs(v)
    assert p.shape == (len(v), 3)
    assert torch.allclose(p.sum(-1), torch.ones(len(v), dtype=p.dtype), atol=1e-12)
    assert (p >= 0).all() and (p <= 1).all()
    # known values
    p0 = sm.probs(torch.tensor([0.0, z, -z, z + 0.01, -(z + 0.01), 1.0, -1.0], dtype=torch.float64))
    e = math.exp(-1.0)
    ref = torch.tensor(
        [[1, 0, 0], [1, 0, 0], [1, 0, 0], [e, 1 - e, 0], [e, 0, 1 - e], [0, 1, 0], [0, 0, 1]], dtype=torch.float64
    )
    assert torch.allclose(p0, ref, atol=1e-12)
    # monotone: p(free) grows with v, p(occupied) shrinks
    assert (p[:20001, F].diff() >= 0).all() and (p[:20001, O].diff() <= 0).all()
    assert sm.probs(torch.zeros(2, 5)).shape == (2, 5, 3)
    with pytest.raises(ValueError, match="NaN"):
        sm.probs(torch.tensor([float("nan")]))
    with pytest.raises(ValueError):
        SemanticSensorModel(alpha=0.0)


def test_merge_obs_keeps_free_evidence_against_particles_under_settling_motions(box_obj):
    # MuJoCo settles a resting object by 1-2e-6 m per step. Free points inside some particles are the evidence
    # against those particles: a motion that covers none of them must keep every one (Algorithm 6 line 3 is
    # about points the move may have covered).
    gen = torch.Generator().manual_seed(0)
    free_pts = torch.rand(400, 3, generator=gen) * torch.tensor([0.2, 0.2, 0.1]) - torch.tensor([0.1, 0.1, 0.0])
    prev = voxel_downsample(Features(free_pts, [F] * len(free_pts)))
    xy = torch.rand(30, 2, generator=gen) * 0.1 - 0.05
    poses = tf.pose_from_xyz_yaw(torch.cat([xy, torch.zeros(30, 1)], 1), torch.rand(30, generator=gen) * 6.28)
    v, _ = box_obj.sdf_world(poses, prev.positions)
    assert int((v < 0).any(0).sum()) > 20  # many free points contradict some particle
    X = prev
    for step in range(5):
        settle = tf.pose_from_xyz_yaw(torch.tensor([1.5e-6, -1e-6, 0.0]), torch.tensor(2e-6))
        poses = settle @ poses
        X = merge_obs(X, Features.empty(), poses, box_obj, settle)
        assert len(X.free) == len(prev.free), f"step {step}: free points lost to a settling motion"


def test_merge_obs_drops_only_what_the_move_covered(box_obj):
    # a particle that already covered the point before the move and still covers it: the point is evidence
    # against that particle and stays; the literal "free for every particle" rule would drop it
    dT_w = tf.pose_from_xyz_yaw(torch.tensor([0.005, 0.0, 0.0]), torch.tensor(0.0))
    covering = tf.pose_from_xyz_yaw(torch.tensor([0.1, 0.0, 0.0]), torch.tensor(0.0))
    prev = Features(torch.tensor([[0.1, 0.0, 0.04], [0.118, 0.0, 0.04]]), [F, F])
    out = merge_obs(prev, Features.empty(), covering.unsqueeze(0), box_obj, dT_w)
    # the box spans x in [0.075, 0.115] before and [0.08, 0.12] after: (0.1, 0, 0.04) was inside both times: kept;
    # (0.118, 0, 0.04) entered the box: dropped
    assert len(out.free) == 1
    assert torch.allclose(out.free.positions[0], torch.tensor([0.1, 0.0, 0.04]))
