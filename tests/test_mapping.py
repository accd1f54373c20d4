"""The sequence pipeline: multi-constraint initialisation, methods, end-to-end targets."""

from pathlib import Path

import jax
import numpy as np
import pytest

from conftest import ring_of_views, upright_ellipsoid

from spdslam.geometry import project_box
from spdslam.synthetic import make_room_sequence
from spdslam.evaluation import cuboid_iou, orientation_error_deg
from spdslam.frontend import (
    InitializationError,
    multi_initialize,
    tracks_from_instances,
    triangulate_rays,
)
from spdslam.geometry import Cuboid
from spdslam.mapping import METHODS, Method, run_sequence
from spdslam.mapping._graph import mapping_sigmas
from spdslam.evaluation import evaluate_objects
from spdslam.io import Detection, Sequence, read_sequence
from spdslam.synthetic import DEFAULT_CAMERA

FR3 = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "tum_fr3_cabinet"


def test_multi_initialize_recovers_a_noise_free_upright_object():
    e = upright_ellipsoid()
    poses = ring_of_views(np.asarray(e.center))
    boxes = np.stack([np.asarray(project_box(e, T, DEFAULT_CAMERA)) for T in poses])
    got = multi_initialize(boxes, poses, DEFAULT_CAMERA, up=[0, 0, 1], support_plane=[0, 0, 1, 0])
    np.testing.assert_allclose(got.center, e.center, atol=1e-6)
    np.testing.assert_allclose(got.P, e.P, atol=1e-6)
    # without the support plane the height is free, and still recovered
    got = multi_initialize(boxes[:4], poses[:4], DEFAULT_CAMERA, up=[0, 0, 1])
    np.testing.assert_allclose(got.P, e.P, atol=1e-5)


def test_multi_initialize_errors():
    e = upright_ellipsoid()
    poses = ring_of_views(np.asarray(e.center), n=3)
    boxes = np.stack([np.asarray(project_box(e, T, DEFAULT_CAMERA)) for T in poses])
    with pytest.raises(InitializationError, match="at least 2 views"):
        multi_initialize(boxes[:1], poses[:1], DEFAULT_CAMERA, up=[0, 0, 1])
    with pytest.raises(ValueError, match="up direction"):
        multi_initialize(boxes, poses, DEFAULT_CAMERA, up=None)
    with pytest.raises(InitializationError, match="parallel"):
        triangulate_rays(np.zeros((3, 3)), np.tile([1.0, 0, 0], (3, 1)))


def test_methods_mirror_table_iii_and_validate():
    assert METHODS["quadric-slam"].initialization == "svd"
    assert METHODS["quadric-slam"].parameterization == "rts"
    assert METHODS["multi-rts"].orientation == "classic"
    assert METHODS["multi-rts"].shape_form == "classic"
    assert METHODS["multi-rts-nearest"].orientation == "classic-nearest"
    assert METHODS["multi-spd"].parameterization == "spd"
    with pytest.raises(ValueError, match="parameterization must be one of"):
        Method("x", parameterization="quat")
    with pytest.raises(ValueError, match="classic orientation"):
        Method("x", parameterization="spd", orientation="classic")
    with pytest.raises(ValueError, match="classic shape"):
        Method("x", parameterization="spd", orientation="improved", shape_form="classic")
    seq = make_room_sequence(0, frames=30, objects=1)
    with pytest.raises(ValueError, match="method: expected one of quadric-slam, .*, got 'orb-slam'"):
        run_sequence(seq, "orb-slam")
    with pytest.raises(ValueError, match="unknown sigma"):
        mapping_sigmas(seq, {"inverse_boxx": 1.0})
    assert mapping_sigmas(seq)["odometry_translation"] == seq.priors.trajectory_sigma[0]


def test_faithful_rts_baseline_constrains_the_third_axis_and_the_stored_scales():
    """multi-rts (the paper's baseline): classic orientation on the landmark's third axis,
    classic shape prior in its own axis order; multi-rts-nearest: the axis nearest up and
    the sorted ratios."""
    from spdslam.factors import ClassicOrientationFactor, ClassicShapeFactor, ShapeFactor
    from spdslam.frontend import tracks_from_instances
    from spdslam.mapping import build_graph
    from spdslam.mapping._run import initialize_objects
    from spdslam.mapping._run import as_landmark
    from spdslam.solver import L

    seq = make_room_sequence(0, frames=30, objects=2)
    tracks = tracks_from_instances(seq)
    built = {}
    for name in ("multi-rts", "multi-rts-nearest"):
        init, _, _ = initialize_objects(seq, tracks, METHODS[name])
        landmarks = {k: as_landmark(e, METHODS[name]) for k, e in init.items()}
        graph = build_graph(seq, [t for t in tracks if t.id in landmarks], landmarks, METHODS[name])
        built[name] = (graph, landmarks)
    g, lms = built["multi-rts"]
    orient = [f for f in g if isinstance(f, ClassicOrientationFactor)]
    assert orient and all(np.array_equal(f.args[1], [0.0, 0.0, 1.0]) for f in orient)
    assert any(isinstance(f, ClassicShapeFactor) for f in g.factors)
    assert not any(isinstance(f, ShapeFactor) for f in g.factors)
    g, lms = built["multi-rts-nearest"]
    nearest = [f for f in g if isinstance(f, ClassicOrientationFactor)]
    assert len(nearest) == len(orient)
    for f in nearest:
        R = np.asarray(next(v for k, v in lms.items() if L(k) == f.keys[0]).orientation.as_matrix())
        assert np.argmax(f.args[1]) == np.argmax(np.abs(R.T @ f.args[0]))
    assert any(isinstance(f, ShapeFactor) for f in g.factors)


def test_manual_association_needs_instances():
    seq = make_room_sequence(0, frames=30, objects=1)
    d = seq.detections[0]
    stripped = Sequence(seq.name, seq.camera, seq.timestamps, seq.poses_tum,
                        [Detection(d.frame, d.timestamp, d.box, d.label, d.score)] + seq.detections[1:])
    with pytest.raises(ValueError, match="1 of .* detections have no instance id"):
        tracks_from_instances(stripped)


def test_too_few_views_is_reported_not_mapped():
    seq = make_room_sequence(3, frames=60, objects=3)
    lost = seq.detections[0].instance
    kept = [d for d in seq.detections if d.instance != lost]
    kept += [d for d in seq.detections if d.instance == lost][:2]
    seq2 = Sequence(seq.name, seq.camera, seq.timestamps, seq.poses_tum, kept,
                    seq.objects_gt, seq.groundtruth_tum, seq.priors)
    r = run_sequence(seq2, "multi-spd")
    assert lost in r.failed and "2 views" in r.failed[lost]
    assert lost not in {o.id for o in r.objects} and len(r.objects) == 2
    assert all(np.all(np.isfinite(np.asarray(o.ellipsoid.P))) for o in r.objects)


def test_demo_end_to_end_with_manual_association():
    """The issue's target: the default demo room, multi-spd, mean IoU ≥ 0.8, mapped as
    ``spdslam demo`` maps it (``initial_poses="input"``: its boxes move the poses; by default
    a drifting odometry's poses are held and only loops move them, docs/drift.md)."""
    seq = make_room_sequence(0)
    r = run_sequence(seq, "multi-spd", initial_poses="input")
    _, s = evaluate_objects(r.objects, seq.objects_gt)
    assert s["matched"] == len(seq.objects_gt)
    assert s["mean_iou"] >= 0.8, s
    # the back end improves on its front end and on the input trajectory
    _, s0 = evaluate_objects(r.initial_objects, seq.objects_gt)
    assert s["mean_iou"] > s0["mean_iou"]
    moved = np.linalg.norm(r.poses_tum[:, 1:4] - seq.groundtruth_tum[:, 1:4], axis=1).mean()
    before = np.linalg.norm(seq.poses_tum[:, :3] - seq.groundtruth_tum[:, 1:4], axis=1).mean()
    assert moved < before


@pytest.mark.skipif(not FR3.is_dir(), reason=f"fr3_cabinet data not found at {FR3}")
def test_fr3_cabinet_multi_spd_target():
    """The issue's target on real data: IoU ≥ 0.35 and orientation error ≤ 1.5°."""
    seq = read_sequence(FR3)
    r = run_sequence(seq, "multi-spd")
    (o,) = r.objects
    c = Cuboid.from_ellipsoid(o.ellipsoid)
    gt = seq.objects_gt[0].cuboid
    iou, rot = cuboid_iou(c, gt), orientation_error_deg(c.rotation, gt.rotation)
    print(f"fr3_cabinet multi-spd: IoU {iou:.3f}, orientation error {rot:.2f} deg")
    assert iou >= 0.35 and rot <= 1.5


def test_run_is_deterministic_and_finite():
    seq = make_room_sequence(5, frames=40, objects=2)
    a = run_sequence(seq, "multi-spd")
    b = run_sequence(seq, "multi-spd")
    assert [o.id for o in a.objects] == [o.id for o in b.objects]
    for x, y in zip(a.objects, b.objects):
        np.testing.assert_allclose(x.ellipsoid.P, y.ellipsoid.P, rtol=1e-9, atol=1e-12)
    assert np.all(np.isfinite(a.poses_tum))
    assert jax.tree_util.tree_all(jax.tree_util.tree_map(lambda v: bool(np.all(np.isfinite(v))),
                                                         [o.ellipsoid for o in a.objects]))


def test_degenerate_objects_are_reported_not_mapped(monkeypatch):
    """A singular initial ellipsoid does not enter the optimisation, and one that ends
    degenerate is listed under ``failed`` with its radii, never in the map (real data made
    both crash the run: a zero radius in the report's cuboid)."""
    import spdslam.mapping._run as run_mod
    from spdslam.geometry import Ellipsoid
    from spdslam.mapping import run_sequence
    from spdslam.mapping._run import degenerate

    assert degenerate(Ellipsoid(np.diag([1.0, 1.0, 1e-10]), np.zeros(3)))
    assert "non-finite" in degenerate(Ellipsoid(np.diag([1.0, np.nan, 1.0]), np.zeros(3)))
    assert not degenerate(Ellipsoid(np.diag([1.0, 1.0, 0.01]), np.zeros(3)))

    seq = make_room_sequence(3, frames=60, objects=3)
    real = run_mod.multi_initialize_batch

    def flat_first(objects, *a, **kw):  # the first object: a disc of zero thickness
        got = real(objects, *a, **kw)
        w, V = np.linalg.eigh(np.asarray(got[0].P))
        got[0] = Ellipsoid((V * np.r_[0.0, w[1:]]) @ V.T, got[0].center)
        return got

    monkeypatch.setattr(run_mod, "multi_initialize_batch", flat_first)
    r = run_sequence(seq, "multi-spd", initial_poses="input")  # the batch's initialisation
    assert len(r.objects) == 2 and len(r.failed) == 1
    (why,) = r.failed.values()
    assert "initial ellipsoid is singular" in why
    for o in r.objects:
        assert not degenerate(o.ellipsoid)
