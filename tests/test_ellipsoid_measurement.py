"""The full-ellipsoid (RGB-D / LiDAR) measurement factor: zero and full rank at the truth
(spheres included; its Jacobian against central differences is in test_factor_jacobians),
the shape part against an independent eigenvalue computation, affine invariance, the
builder's input checks, and a small solve."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest
import scipy.linalg
from scipy.spatial.transform import Rotation

import spdslam  # noqa: F401  (float64)
from conftest import batched_landmarks, check_jacobians
from spdslam import Ellipsoid
from spdslam.synthetic import make_room_sequence
from spdslam.factors import (
    EllipsoidMeasurementFactor,
    GaussianNoise,
    PriorFactor,
    ellipsoid_measurement_residual,
)
from spdslam.frontend import tracks_from_instances
from spdslam.mapping import METHODS, build_graph, run_sequence
from spdslam.mapping._run import initialize_from_measurements
from spdslam.solver import L, X
from spdslam.evaluation import evaluate_objects
from spdslam.geometry.se3 import quat_to_matrix
from spdslam.io import EllipsoidDetection, Sequence, read_sequence, write_sequence
from spdslam.solver import LevenbergMarquardt, NonlinearFactorGraph, Values

N = 90
res = ellipsoid_measurement_residual


def _configs(seed, n=N):
    """World ellipsoids (R, t, s), poses T_wc (4×4), kinds (0 generic, 1 spheroid, 2 sphere)."""
    rng = np.random.default_rng(seed)
    R = Rotation.random(n, random_state=rng).as_matrix()
    s = rng.uniform(0.2, 1.0, size=(n, 3))
    kind = np.arange(n) % 3
    s[kind == 1, 1] = s[kind == 1, 0]
    s[kind == 2] = s[kind == 2, :1]
    t = rng.uniform(-1, 1, size=(n, 3))
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=rng).as_matrix()
    T[:, :3, 3] = rng.uniform(-3, 3, size=(n, 3))
    return R, t, s, kind, T


def _in_camera(T, R, t, s):
    """Independent numpy transform of world ellipsoids into the camera frames of T_wc."""
    Rwc, twc = T[:, :3, :3], T[:, :3, 3]
    Rc = np.einsum("nji,njk->nik", Rwc, R)  # R_cw R
    tc = np.einsum("nji,nj->ni", Rwc, t - twc)
    P = np.einsum("nij,nj,nkj->nik", Rc, s**2, Rc)
    return P, tc


def _measurements(T, R, t, s, kind, rng, noise=0.1):
    """Noisy camera-frame measurements; spheres are measured as (other) spheres."""
    Rm = np.einsum("nij,njk->nik", R, Rotation.from_rotvec(noise * rng.normal(size=(len(R), 3))).as_matrix())
    sm = s * np.exp(noise * rng.normal(size=s.shape))
    sm[kind == 2] = sm[kind == 2, :1]
    Rm[kind == 2] = R[kind == 2]
    P, tc = _in_camera(T, Rm, t + noise * rng.normal(size=t.shape), sm)
    P[kind == 2] = sm[kind == 2, 0, None, None] ** 2 * np.eye(3)  # exactly c·I
    return P, tc


@pytest.mark.parametrize("param", ["spd", "rts"])
def test_zero_and_finite_at_the_truth_spheres_included(param):
    R, t, s, kind, T = _configs(3)
    P, tc = _in_camera(T, R, t, s)
    P[kind == 2] = s[kind == 2, 0, None, None] ** 2 * np.eye(3)
    poses = jax.vmap(jaxlie.SE3.from_matrix)(jnp.asarray(T))
    r, J = check_jacobians(res, (poses, batched_landmarks(param, R, t, s)),
                           (jnp.asarray(P), jnp.asarray(tc)), kind)
    np.testing.assert_allclose(r, 0.0, atol=1e-9)
    # the Jacobian has full rank in the landmark's 9 directions (a sphere's rotation
    # directions excepted for RTS), so the factor constrains the landmark
    ranks = np.linalg.matrix_rank(J[1], tol=1e-6)
    want = np.where((kind == 2) & (param == "rts"), 6, 9)
    want = np.where((kind == 1) & (param == "rts"), 8, want)
    np.testing.assert_array_equal(ranks, want)


def test_shape_part_is_the_affine_invariant_distance(rng):
    R, t, s, kind, T = _configs(4, 30)
    P, tc = _measurements(T, R, t, s, kind, rng, noise=0.3)
    poses = jax.vmap(jaxlie.SE3.from_matrix)(jnp.asarray(T))
    r = np.asarray(jax.vmap(res)(poses, batched_landmarks("spd", R, t, s), jnp.asarray(P), jnp.asarray(tc)))
    Pc, tc_true = _in_camera(T, R, t, s)
    for i in range(len(R)):
        lam = scipy.linalg.eigh(Pc[i], P[i], eigvals_only=True)  # eigenvalues of P̄⁻¹ P_c
        assert np.linalg.norm(r[i, :6]) == pytest.approx(np.sqrt(np.sum(np.log(lam) ** 2)), rel=1e-9)
    np.testing.assert_allclose(r[:, 6:], tc_true - tc, atol=1e-12)
    assert np.all(np.linalg.norm(r[kind == 0, :6], axis=1) > 1e-3)  # it sees the perturbation


def test_affine_invariance_and_sign():
    """d(A P̄ Aᵀ, A P Aᵀ) = d(P̄, P) for any invertible A; a larger predicted ellipsoid gives
    positive diagonal log-components."""
    rng = np.random.default_rng(5)
    I = jaxlie.SE3.identity()
    for _ in range(10):
        P = Ellipsoid.from_axes(Rotation.random(random_state=rng).as_matrix(), np.zeros(3), rng.uniform(0.2, 1, 3))
        Pm = Ellipsoid.from_axes(Rotation.random(random_state=rng).as_matrix(), np.zeros(3), rng.uniform(0.2, 1, 3))
        A = rng.normal(size=(3, 3)) + 2 * np.eye(3)
        a = res(I, P, Pm.P, np.zeros(3))[:6]
        b = res(I, Ellipsoid(A @ P.P @ A.T, np.zeros(3)), A @ Pm.P @ A.T, np.zeros(3))[:6]
        assert float(jnp.linalg.norm(a)) == pytest.approx(float(jnp.linalg.norm(b)), rel=1e-9)
    e = Ellipsoid.from_axes(np.eye(3), [0, 0, 2.0], [0.5, 0.4, 0.3])
    r = res(I, e, np.diag([0.25, 0.16, 0.09]) / 1.21, np.zeros(3))  # measured 10 % smaller
    np.testing.assert_allclose(r[:3], 2 * np.log(1.1), rtol=1e-12)
    np.testing.assert_allclose(r[3:6], 0.0, atol=1e-12)
    np.testing.assert_allclose(r[6:], [0, 0, 2.0])


def test_builder_forms_defaults_and_validation():
    Rm = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix()
    radii = np.array([0.5, 0.3, 0.2])
    f1 = EllipsoidMeasurementFactor("x", "l", (Rm, radii), [0, 0, 2.0])
    f2 = EllipsoidMeasurementFactor("x", "l", (Rm * radii**2) @ Rm.T, [0, 0, 2.0])
    f3 = EllipsoidMeasurementFactor("x", "l", (jaxlie.SO3.from_matrix(Rm), radii), [0, 0, 2.0])
    np.testing.assert_allclose(f1.args[0], f2.args[0], atol=1e-15)
    np.testing.assert_allclose(f1.args[0], f3.args[0], atol=1e-12)
    # the default noise: 0.1 per log-shape coordinate, 0.05 m per centre coordinate
    np.testing.assert_allclose(np.diag(f1.sqrt_info), [10] * 6 + [20] * 3)
    np.testing.assert_array_equal(f1.sqrt_info, np.diag(np.diag(f1.sqrt_info)))
    sigma = [0.2] * 6 + [0.01, 0.01, 0.1]
    f4 = EllipsoidMeasurementFactor("x", "l", (Rm, radii), [0, 0, 2.0], sigma=sigma)
    np.testing.assert_allclose(np.diag(f4.sqrt_info), [5] * 6 + [100, 100, 10])
    cov = np.diag(np.square(sigma))
    for kw in ({"covariance": cov}, {"information": np.linalg.inv(cov)},
               {"noise": GaussianNoise.sigmas(sigma)}):
        f5 = EllipsoidMeasurementFactor("x", "l", (Rm, radii), [0, 0, 2.0], **kw)
        np.testing.assert_allclose(f5.sqrt_info, f4.sqrt_info, rtol=1e-12)
    assert f1.keys == ("x", "l") and f1.kind == "ellipsoid_measurement"
    bad = [
        (((Rm, [0.5, 0.0, 0.2]), [0, 0, 1]), {}, "radii must be 3 positive"),
        (((2 * Rm, radii), [0, 0, 1]), {}, "orthonormal"),
        ((np.diag([1.0, 1.0, -1.0]), [0, 0, 1]), {}, "positive definite"),
        ((np.array([[1.0, 0.5, 0], [0, 1, 0], [0, 0, 1]]), [0, 0, 1]), {}, "symmetric"),
        ((np.eye(2), [0, 0, 1]), {}, "3x3"),
        ((np.eye(3), [0, np.nan, 1]), {}, "centre"),
        ((np.eye(3), [0, 0, 1]), {"sigma": 0.0}, "sigma"),
        ((np.eye(3), [0, 0, 1]), {"sigma": [1.0, 2.0]}, "sigma"),
        ((np.eye(3), [0, 0, 1]), {"covariance": np.eye(6)}, "9x9"),
        ((np.eye(3), [0, 0, 1]), {"sigma": 1.0, "covariance": np.eye(9)}, "at most one"),
    ]
    for args, kw, msg in bad:
        with pytest.raises(ValueError, match=msg):
            EllipsoidMeasurementFactor("x", "l", *args, **kw)


def test_solve_recovers_the_landmark_from_measurements():
    """Three fixed views of an ellipsoid measured exactly: LM from a poor start recovers it."""
    rng = np.random.default_rng(6)
    truth = Ellipsoid.from_axes(Rotation.from_euler("z", 0.7).as_matrix(), [1.0, 0.5, 0.4], [0.6, 0.3, 0.2])
    g, v = NonlinearFactorGraph(), Values()
    R, t, s = (np.asarray(a)[None] for a in (truth.axes()[0], truth.center, truth.axes()[1]))
    for i in range(3):
        T = np.eye(4)
        T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
        T[:3, 3] = rng.uniform(-2, 2, 3)
        Tse3 = jaxlie.SE3.from_matrix(T)
        P, tc = _in_camera(T[None], R, t, s)
        g.add(PriorFactor(("x", i), Tse3, sigma=1e-4))
        g.add(EllipsoidMeasurementFactor(("x", i), "l", P[0], tc[0]))
        v[("x", i)] = Tse3
    v["l"] = Ellipsoid(np.eye(3) * 0.1, np.zeros(3))
    out = LevenbergMarquardt(max_iterations=50).optimize(g, v)
    got = out.values["l"]
    np.testing.assert_allclose(got.P, truth.P, atol=1e-6)
    np.testing.assert_allclose(got.center, truth.center, atol=1e-6)


# --- the sequence pipeline with measured ellipsoids -----------------------------------------


def _measure(seq, ids, step, rng, sc=0.02, sr=0.02, ss=0.03):
    """Measured ellipsoids of objects ``ids`` in every ``step``-th frame that boxes them,
    from the ground truth (cuboid half-extents = radii) in the TRUE camera frames, with
    noise: σ sc m on the centre, sr rad on the rotation, ss on log radii."""
    gt = {o.id: o for o in seq.objects_gt}
    out = []
    for k in ids:
        c = gt[k].cuboid
        for f in sorted({d.frame for d in seq.detections if d.instance == k})[::step]:
            row = seq.groundtruth_tum[f]
            Rwc, twc = quat_to_matrix(row[4:8]), row[1:4]
            Rc = Rwc.T @ c.rotation @ Rotation.from_rotvec(sr * rng.normal(size=3)).as_matrix()
            tc = Rwc.T @ (c.center - twc) + sc * rng.normal(size=3)
            radii = c.half_extents * np.exp(ss * rng.normal(size=3))
            out.append(EllipsoidDetection(f, seq.timestamps[f], gt[k].label, Rc, tc, radii, k))
    return out


def _with(seq, detections, ellipsoids):
    return Sequence(seq.name, seq.camera, seq.timestamps, seq.poses_tum, detections,
                    seq.objects_gt, seq.groundtruth_tum, seq.priors, None, ellipsoids)


@pytest.fixture(scope="module")
def room():
    """The demo room (seed 0, 60 frames, 4 objects) and measured ellipsoids (every 4th
    boxed frame) of objects 0, 1 and 3."""
    seq = make_room_sequence(seed=0, frames=60, objects=4)
    return seq, _measure(seq, [0, 1, 3], 4, np.random.default_rng(0))


@pytest.fixture(scope="module")
def mixed_run(room):
    """Object 3 only measured (its boxes removed), object 2 left with 2 boxes and no
    measurement; one multi-spd run."""
    seq, ells = room
    dets = [d for d in seq.detections if d.instance not in (2, 3)]
    dets += [d for d in seq.detections if d.instance == 2][:2]
    mixed = _with(seq, dets, ells)
    return mixed, run_sequence(mixed, "multi-spd", initial_poses="input")  # the boxes move the poses


def test_an_object_seen_only_as_measured_ellipsoids_is_mapped(room, mixed_run):
    seq = room[0]
    _, r = mixed_run
    rows, _ = evaluate_objects(r.objects, seq.objects_gt)
    iou = {x.id: x.iou for x in rows}
    print(f"IoU per object with measurements: {iou}")
    assert iou[3] >= 0.8  # no box at all
    assert iou[0] >= 0.8 and iou[1] >= 0.8  # boxes + measurements
    assert any("object 3: initialised from its 7 measured ellipsoids" in n for n in r.notes)
    # too few boxes and no measurement: still a failure, as without ellipsoids.txt
    assert list(r.failed) == [2] and "2 views" in r.failed[2]
    assert sorted(o.id for o in r.objects) == [0, 1, 3]
    init = {o.id: o for o in r.initial_objects}
    # the measurement mean, taken to the world by the drifted input trajectory (0.70 here);
    # the joint optimisation corrects the poses and the object
    assert 0.5 <= evaluate_objects([init[3]], seq.objects_gt)[0][0].iou < iou[3]


@pytest.mark.slow
def test_measurements_make_the_map_at_least_as_good_as_boxes_alone(room):
    """All boxes, vs all boxes but object 3's plus the measurements of 0, 1 and 3."""
    seq, ells = room
    mixed = _with(seq, [d for d in seq.detections if d.instance != 3], ells)
    _, s0 = evaluate_objects(run_sequence(seq, "multi-spd").objects, seq.objects_gt)
    rows, s1 = evaluate_objects(run_sequence(mixed, "multi-spd").objects, seq.objects_gt)
    print(f"mean IoU boxes only {s0['mean_iou']:.3f}, boxes + ellipsoids {s1['mean_iou']:.3f}")
    assert s1["matched"] == 4 and s1["mean_iou"] >= s0["mean_iou"]
    assert {x.id: x.iou for x in rows}[3] >= 0.8


def test_graph_has_one_factor_per_assigned_measurement(room):
    seq, ells = room
    extra = [EllipsoidDetection(0, 0.0, "x", np.eye(3), [0, 0, 2], [0.1, 0.1, 0.1], i) for i in (None, -1, 9)]
    s2 = _with(seq, seq.detections, ells + extra)
    landmarks = {g.id: Ellipsoid.from_axes(g.cuboid.rotation, g.cuboid.center, g.cuboid.half_extents)
                 for g in seq.objects_gt}
    tracks = tracks_from_instances(s2)
    g = build_graph(s2, tracks, landmarks, METHODS["multi-spd"])
    meas = [f for f in g.factors if f.kind == "ellipsoid_measurement"]
    assert len(meas) == len(ells)  # None / negative instance: no object; 9: no landmark
    assert {f.keys for f in meas} == {(X(m.frame), L(m.instance)) for m in ells}
    with pytest.raises(ValueError, match="unknown sigma"):
        build_graph(s2, tracks, landmarks, METHODS["multi-spd"], {"ellipsoid_shap": 1})
    # the sigmas are overridable like the others
    g2 = build_graph(s2, tracks, landmarks, METHODS["multi-spd"], {"ellipsoid_center": 0.5})
    w = [f.sqrt_info for f in g2.factors if f.kind == "ellipsoid_measurement"]
    np.testing.assert_allclose(np.diag(w[0]), [10] * 6 + [2] * 3)


def test_initialisation_from_exact_measurements_is_exact():
    seq = make_room_sequence(seed=1, frames=30, objects=2, drift=0.0)
    truth = Sequence(seq.name, seq.camera, seq.timestamps, seq.groundtruth_tum[:, 1:], [])
    ms = _measure(seq, [0], 3, np.random.default_rng(1), 0.0, 0.0, 0.0)
    e = initialize_from_measurements(truth, ms)
    c = seq.objects_gt[0].cuboid
    np.testing.assert_allclose(e.P, (c.rotation * c.half_extents**2) @ c.rotation.T, atol=1e-9)
    np.testing.assert_allclose(e.center, c.center, atol=1e-9)


def test_mixed_sequence_round_trip(room, tmp_path):
    seq, ells = room
    mixed = _with(seq, [d for d in seq.detections if d.instance != 3], ells)
    back = read_sequence(write_sequence(mixed, tmp_path / mixed.name))
    assert back == mixed and len(back.ellipsoids) == len(ells) > 0
    assert (tmp_path / mixed.name / "ellipsoids.txt").is_file()


def test_measurements_are_left_out_under_automatic_association(room):
    """Measured ellipsoids are attached by instance id; automatic track ids are not instance
    ids, so with automatic association they must not be attached (and say so)."""
    seq, ells = room
    mixed = _with(seq, seq.detections, ells)
    r = run_sequence(mixed, "multi-spd", associate="auto", max_iterations=1)
    assert any("measured ellipsoids left out" in n for n in r.notes)
    assert not any("initialised from" in n for n in r.notes)
    g = build_graph(mixed, [], {}, r.method, measured={})
    assert not any(f.kind == "ellipsoid_measurement" for f in g)
