"""Closed-form linearisations (``factors.closed_form``) against the general JAX path and
central differences, and the solver's use of them (``solver.closed_forms``)."""

from __future__ import annotations

import shutil

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest
from conftest import check_jacobians

from spdslam.factors import (
    BetweenFactor,
    Cauchy,
    Huber,
    InverseBoxFactor,
    PriorFactor,
    box_visible,
    closed_form,
    inverse_box_linearization,
    inverse_box_residual,
    pose_between_linearization,
    pose_between_residual,
    pose_prior_linearization,
    pose_prior_residual,
)
from spdslam.geometry import Camera, Ellipsoid, EllipsoidRTS, manifold, project_box
from spdslam.geometry import native, se3
from spdslam.geometry.se3 import quat_to_matrix
from spdslam.solver import L, NonlinearFactorGraph, Problem, Values, X, closed_forms
from spdslam.solver._linearize import pushforward


def _views(gen, n):
    """n (camera pose, SPD landmark, camera) triples: each camera 3–8 radii from its
    landmark, looking near it (general, spheroid and sphere shapes)."""
    poses, lms, cams = [], [], []
    kinds = ("general", "spheroid_oblate", "spheroid_prolate", "sphere")
    for i in range(n):
        R, t, s = gen.ellipsoid_params(kinds[i % len(kinds)])
        T, _, _ = gen.pose_looking_at(R, t, s, jitter=0.1)
        poses.append(T.wxyz_xyz)
        lms.append(Ellipsoid.from_axes(R, t, s))
        cams.append(gen.camera())
    lm = Ellipsoid(jnp.stack([e.P for e in lms]), jnp.stack([e.center for e in lms]))
    cam = Camera(*(np.array([getattr(c, f) for c in cams]) for f in ("fx", "fy", "cx", "cy", "width", "height")))
    return jaxlie.SE3(jnp.stack(poses)), lm, cam


def _host(x):
    return jax.tree.map(np.asarray, x)


def _noisy_boxes(gen, poses, lm, cam):
    boxes = np.asarray(jax.vmap(project_box)(lm, poses, jax.tree.map(jnp.asarray, cam)))
    return boxes + gen.rng.normal(scale=3.0, size=boxes.shape)


@pytest.mark.parametrize("truncated", [False, True])
def test_inverse_box_closed_form_matches_the_jax_jacobian_and_central_differences(gen, truncated):
    poses, lm, cam = _views(gen, 48)
    boxes = _noisy_boxes(gen, poses, lm, cam)
    keep = (gen.rng.random(boxes.shape) > 0.25).astype(float) if truncated else None
    args = (jnp.asarray(boxes), jax.tree.map(jnp.asarray, cam)) + (() if keep is None else (jnp.asarray(keep),))
    # the JAX Jacobians, themselves checked against central differences
    r_jax, (J_pose, J_lm) = check_jacobians(inverse_box_residual, (poses, lm), args)
    n = len(boxes)  # the solver's form: each type's pushforwards and the factors' rows in them
    Ts = ((_host(pushforward(jaxlie.SE3, poses)), np.arange(n)), (_host(pushforward(Ellipsoid, lm)), np.arange(n)))
    host_args = tuple(_host(a) for a in args)
    r, J, valid = inverse_box_linearization((_host(poses), _host(lm)), Ts, host_args)
    assert np.allclose(r, r_jax, rtol=1e-9, atol=1e-9)
    J_ref = np.concatenate([J_pose, J_lm], axis=2)
    assert np.max(np.abs(J - J_ref) / (1.0 + np.abs(J_ref).max(axis=(1, 2), keepdims=True))) < 1e-9
    assert np.array_equal(valid, np.asarray(jax.vmap(lambda T, e: box_visible(T, e, None, None))(poses, lm)))
    astray = _host(poses)  # a pose a step sent astray (NaN): not finite there, no error, the others as before
    astray = jaxlie.SE3(np.where(np.arange(len(r))[:, None] == 0, np.nan, np.asarray(astray.wxyz_xyz)))
    with np.errstate(all="ignore"):
        rb, Jb, _ = inverse_box_linearization((astray, _host(lm)), Ts, host_args)
    assert not np.isfinite(rb[0]).all() and np.array_equal(rb[1:], r[1:]) and np.array_equal(Jb[1:], J[1:])
    # central differences of the closed form's own residual, on the manifolds
    h = 1e-6
    for k in range(15):
        d_pose = np.zeros((len(r), 6))
        d_lm = np.zeros((len(r), 9))
        (d_pose if k < 6 else d_lm)[:, k % 6 if k < 6 else k - 6] = h

        def res(sign, d_pose=d_pose, d_lm=d_lm):
            p = jax.vmap(manifold.ops(jaxlie.SE3).retract)(poses, sign * jnp.asarray(d_pose))
            e = jax.vmap(manifold.ops(Ellipsoid).retract)(lm, sign * jnp.asarray(d_lm))
            return inverse_box_linearization((_host(p), _host(e)), None, host_args, False)[0]

        fd = (res(1.0) - res(-1.0)) / (2 * h)
        scale = 1.0 + np.abs(fd).max(axis=1, keepdims=True)
        assert np.max(np.abs(J[:, :, k] - fd) / scale) < 2e-5, f"tangent coordinate {k}"


def test_closed_form_applies_only_to_its_residual_rule_and_types():
    cf = closed_form(inverse_box_residual, box_visible, (jaxlie.SE3, Ellipsoid))
    assert cf is not None and cf.linearize is inverse_box_linearization
    assert closed_form(inverse_box_residual, box_visible, (jaxlie.SE3, EllipsoidRTS)) is None
    assert closed_form(inverse_box_residual, None, (jaxlie.SE3, Ellipsoid)) is None
    assert closed_form(project_box, box_visible, (jaxlie.SE3, Ellipsoid)) is None


def test_the_closed_forms_rotation_matrices_are_jaxlies(gen):
    """The closed form reads a pose's rotation with ``se3.quat_to_matrix`` (xyzw order)."""
    q = gen.rng.normal(size=(20, 4)) * 3.0  # not normalised: both normalise
    assert np.allclose(quat_to_matrix(q[:, [1, 2, 3, 0]]), np.asarray(jaxlie.SO3(jnp.asarray(q)).as_matrix()),
                       atol=1e-14)


def _graph(gen, n_poses=6, n_objects=3, behind=False):
    """Box factors of a few objects seen from a few poses (Cauchy, diagonal σ, some edges
    truncated), and when ``behind`` one object behind one camera (an invalid factor)."""
    values = Values()
    graph = NonlinearFactorGraph()
    cam = gen.camera()
    objects = [gen.ellipsoid_params() for _ in range(n_objects)]
    for j, (R, t, s) in enumerate(objects):
        values.insert(L(j), Ellipsoid.from_axes(R, t + gen.rng.normal(scale=0.1, size=3), s * 1.1))
    for i in range(n_poses):
        R, t, s = objects[i % n_objects]
        T, _, _ = gen.pose_looking_at(R, t, s, jitter=0.05)
        values.insert(X(i), T)
        for j, (Rj, tj, sj) in enumerate(objects):
            box = np.asarray(project_box(Ellipsoid.from_axes(Rj, tj, sj), T, cam))
            graph.add(InverseBoxFactor(X(i), L(j), box + gen.rng.normal(size=4), cam, sigma=[2.0, 2.5, 2.0, 3.0],
                                       robust=Cauchy(1.0), truncation_margin=5.0))
    if behind:  # an object 2 m behind the first camera
        T0 = values[X(0)]
        centre = np.asarray(T0.translation()) - 2.0 * np.asarray(T0.rotation().as_matrix())[:, 2]
        values.insert(L(n_objects), Ellipsoid.from_axes(np.eye(3), centre, np.full(3, 0.3)))
        graph.add(InverseBoxFactor(X(0), L(n_objects), np.array([10.0, 10.0, 50.0, 50.0]), cam,
                                   robust=Cauchy(1.0), truncation_margin=5.0))
    return graph, values


@pytest.mark.parametrize("behind", [False, True])
def test_a_problem_linearises_alike_with_and_without_the_closed_forms(gen, behind):
    graph, values = _graph(gen, behind=behind)
    with closed_forms(False):
        general = Problem(graph, values, fixed=[X(0)])
        H0, g0, c0, v0, f0 = general.linearize(general.vars)
        costs0 = general.cost()
    closed = Problem(graph, values, fixed=[X(0)])
    assert type(closed.kernels.groups[0]).__name__ == "ClosedFormGroup"
    assert type(general.kernels.groups[0]).__name__ == "_GroupKernels"
    H1, g1, c1, v1, f1 = closed.linearize(closed.vars)
    assert np.allclose(H1, H0, rtol=1e-10, atol=1e-10 * np.abs(H0).max())
    assert np.allclose(g1, g0, rtol=1e-10, atol=1e-10 * np.abs(g0).max())
    assert c1 == pytest.approx(c0, rel=1e-12) and closed.cost() == pytest.approx(costs0, rel=1e-12)
    assert f1 == f0
    assert all(np.array_equal(np.asarray(a), np.asarray(b)) for a, b in zip(v0, v1))
    assert (not np.asarray(v1[0]).all()) == behind
    r0, J0, _ = general.group_terms(0)
    r1, J1, _ = closed.group_terms(0)
    assert np.allclose(np.asarray(r1), np.asarray(r0), atol=1e-9)
    assert np.allclose(np.asarray(J1), np.asarray(J0), atol=1e-8)


def test_residual_dimensions_come_from_the_closed_forms_without_tracing(gen, monkeypatch):
    """With the closed forms a problem of box factors and odometry learns each group's
    residual dimension from its closed form's residual of one row (NumPy), tracing nothing;
    the dimensions are ``jax.eval_shape``'s."""
    from spdslam.factors import BetweenFactor, PriorFactor
    from spdslam.solver import _problem

    graph, values = _graph(gen)
    graph.add(PriorFactor(X(0), values[X(0)], sigma=0.1))
    graph.add(BetweenFactor(X(0), X(1), values[X(0)].inverse() @ values[X(1)], sigma=0.1))
    traced = []
    eval_shape = jax.eval_shape
    monkeypatch.setattr(jax, "eval_shape", lambda *a, **k: traced.append(a[0]) or eval_shape(*a, **k))
    monkeypatch.setattr(_problem, "_RESIDUAL_DIM", {})
    Problem(graph, values)
    assert traced == []
    dims = dict(_problem._RESIDUAL_DIM)
    assert sorted(dims.values()) == [4, 6, 6]
    monkeypatch.setattr(_problem, "_RESIDUAL_DIM", {})
    with closed_forms(False):
        Problem(graph, values)
    assert len(traced) == 3
    assert _problem._RESIDUAL_DIM == dims


def _random_poses(gen, n, scale):
    """n poses Exp(ξ), ξ ~ N(0, scale²) per coordinate."""
    return jaxlie.SE3.exp(jnp.asarray(gen.rng.normal(size=(n, 6)) * scale))


def _near(gen, scale):
    return jaxlie.SE3.exp(jnp.asarray(gen.rng.normal(size=6) * scale))


@pytest.mark.parametrize("scale", [1e-6, 1e-3, 0.05, 1.0])
def test_the_group_operations_in_numpy_are_jaxlies(gen, scale):
    """se3's NumPy compose, inverse, log, adjoint and J_r⁻¹ against jaxlie (J_r⁻¹ against
    forward-mode JAX through Log(Exp(ξ) Exp(δ))) at rotations from 10⁻⁶ rad to about π."""
    A, B = _random_poses(gen, 40, scale), _random_poses(gen, 40, scale)
    a, b = np.asarray(A.wxyz_xyz), np.asarray(B.wxyz_xyz)
    assert np.allclose(se3.compose_params(a, b), np.asarray((A @ B).wxyz_xyz), rtol=0, atol=1e-14)
    assert np.allclose(se3.inverse_params(a), np.asarray(A.inverse().wxyz_xyz), rtol=0, atol=1e-14)
    xi = np.asarray(A.log())
    assert np.allclose(se3.log_params(a), xi, rtol=0, atol=1e-13)
    flipped = a * np.r_[-np.ones(4), np.ones(3)]  # −q: the same rotation
    assert np.allclose(se3.log_params(flipped), xi, rtol=0, atol=1e-13)
    assert np.allclose(se3.adjoint_params(a), np.asarray(A.adjoint()), rtol=0, atol=1e-14)
    assert np.allclose(se3.exp_params(xi), np.asarray(jaxlie.SE3.exp(jnp.asarray(xi)).wxyz_xyz), rtol=0,
                       atol=1e-14)
    J = jax.vmap(lambda x: jax.jacfwd(lambda d: (jaxlie.SE3.exp(x) @ jaxlie.SE3.exp(d)).log())(jnp.zeros(6)))(
        jnp.asarray(xi))
    # to 1e-11: below θ ≈ 1e-5 jaxlie's own Taylor branches are first order (~1e-12 off)
    assert np.allclose(se3.right_jacobian_inverse(xi), np.asarray(J), rtol=0, atol=1e-11)


@pytest.mark.parametrize("shape", ["sphere", "two equal radii", "elongated", "random"])
def test_the_ellipsoid_s_numpy_retraction_and_pushforward_are_the_programs(gen, shape):
    """``Ellipsoid``'s host retraction and pushforward (``geometry.manifold``) against the JAX
    retraction and its forward-mode pushforward, at repeated eigenvalues too."""
    from scipy.spatial.transform import Rotation

    from spdslam.geometry import spd

    assert np.array_equal(spd.BASIS, np.asarray(spd.vec_to_sym(jnp.eye(6))))  # the NumPy basis is the chart's
    n = 16
    R = Rotation.random(n, random_state=gen.rng).as_matrix()
    r = {"sphere": np.full((n, 3), 0.3), "two equal radii": np.tile([0.2, 0.2, 0.5], (n, 1)),
         "elongated": np.tile([0.01, 0.05, 2.0], (n, 1)), "random": gen.rng.uniform(0.02, 1.0, (n, 3))}[shape]
    P = np.einsum("nij,nj,nkj->nik", R, r**2, R)
    t = gen.rng.normal(size=(n, 3))
    d = gen.rng.normal(scale=0.3, size=(n, 9))
    ops = manifold.ops(Ellipsoid)
    host = ops.host_retract(Ellipsoid(P, t), d)
    prog = jax.vmap(lambda x, di: x.retract(di))(Ellipsoid(jnp.asarray(P), jnp.asarray(t)), jnp.asarray(d))
    assert np.allclose(host.P, np.asarray(prog.P), rtol=0, atol=1e-13 * np.abs(P).max())
    assert np.allclose(host.center, np.asarray(prog.center), rtol=0, atol=1e-15)
    assert np.all(np.linalg.eigvalsh(host.P) > 0) and np.allclose(host.P, np.swapaxes(host.P, 1, 2), atol=0)
    bad = d.copy()
    bad[0, 0], bad[1, 1] = np.nan, 1e5  # a step that is not finite, or too long: not finite, no error
    stepped = ops.host_retract(Ellipsoid(P, t), bad)
    assert not np.isfinite(stepped.P[0]).all() and not np.isfinite(stepped.P[1]).all()
    assert np.isfinite(stepped.P[2:]).all()
    pf = ops.host_pushforward(Ellipsoid(P, t))
    pj = pushforward(Ellipsoid, Ellipsoid(jnp.asarray(P), jnp.asarray(t)))
    assert np.allclose(pf.P, np.asarray(pj.P), rtol=0, atol=1e-13 * np.abs(P).max())
    assert np.array_equal(pf.center, np.asarray(pj.center))


def _landmarks(gen, shape: str, n: int = 24):
    """n Ellipsoids (NumPy) of a shape: random radii, two equal, all equal, elongated."""
    from scipy.spatial.transform import Rotation

    R = Rotation.random(n, random_state=gen.rng).as_matrix()
    r = {"sphere": np.full((n, 3), 0.3), "two equal radii": np.tile([0.2, 0.2, 0.5], (n, 1)),
         "elongated": np.tile([0.01, 0.05, 2.0], (n, 1)), "random": gen.rng.uniform(0.02, 1.0, (n, 3))}[shape]
    return Ellipsoid(np.einsum("nij,nj,nkj->nik", R, r**2, R), gen.rng.normal(size=(n, 3)))


@pytest.mark.parametrize("shape", ["random", "two equal radii", "sphere", "elongated"])
def test_object_prior_closed_forms_match_the_jax_jacobian(gen, shape):
    """Orientation, shape, size and radius-floor priors on SPD landmarks: residual and
    Jacobian against the JAX path (forward mode through the chart, ``matfun``'s tie rules;
    checked against central differences where the radii are distinct), the floor both active
    and not."""
    from spdslam.factors import (
        orientation_linearization,
        orientation_residual,
        radius_floor_linearization,
        radius_floor_residual,
        shape_linearization,
        shape_residual,
        size_linearization,
        size_residual,
        tangent_jacobians,
    )

    lm = _landmarks(gen, shape)
    n = len(lm.P)
    m = gen.rng.normal(size=(n, 3))
    m[0] = [0.0, 0.0, 1.0]
    cases = [(orientation_residual, orientation_linearization, m),
             (shape_residual, shape_linearization, gen.rng.uniform(1.0, 4.0, (n, 2))),
             (size_residual, size_linearization, gen.rng.normal(size=n)),
             (radius_floor_residual, radius_floor_linearization,
              np.log(np.sqrt(np.linalg.eigvalsh(lm.P)[:, 0])) + gen.rng.choice([-0.5, 0.5], n))]
    jl = Ellipsoid(jnp.asarray(lm.P), jnp.asarray(lm.center))
    for residual, linearize, data in cases:
        if shape == "random":
            r_jax, (J_jax,) = check_jacobians(residual, (jl,), (jnp.asarray(data),))
        else:
            r_jax, (J_jax,) = jax.vmap(lambda x, a, f=residual: tangent_jacobians(f, (x,), (a,)))(jl, jnp.asarray(data))
        r, J, valid = linearize((lm,), None, (data,), True)
        assert valid is None and J.shape == np.asarray(J_jax).shape, residual.__name__
        # to round-off at the radii's conditioning (LAPACK's eigh here, XLA's there)
        r_jax, J_jax = np.asarray(r_jax), np.asarray(J_jax)
        assert np.allclose(r, r_jax, rtol=0, atol=1e-10 * (1.0 + np.abs(r_jax).max())), residual.__name__
        assert np.allclose(J, J_jax, rtol=0, atol=1e-10 * (1.0 + np.abs(J_jax).max())), \
            (residual.__name__, np.abs(J - J_jax).max())
        r2, J2, _ = linearize((lm,), None, (data,), False)
        assert J2 is None and np.array_equal(r2, r)
        assert closed_form(residual, None, (Ellipsoid,)).linearize is linearize
        assert closed_form(residual, None, (EllipsoidRTS,)) is None  # the other charts: the JAX path
        P_bad = np.array(lm.P)
        P_bad[0] = np.nan  # a landmark a step sent astray: not finite, no error, the others as before
        with np.errstate(all="ignore"):
            rb, Jb, _ = linearize((Ellipsoid(P_bad, lm.center),), None, (data,), True)
        assert not np.isfinite(rb[0]).all(), residual.__name__
        assert np.allclose(rb[1:], r[1:], rtol=0, atol=0) and np.allclose(Jb[1:], J[1:], rtol=0, atol=0)


@pytest.mark.parametrize("scale", [1e-4, 0.05, 0.8])
def test_pose_closed_forms_match_the_jax_jacobian(gen, scale):
    """Prior and between factors: residual and Jacobian against the JAX path (checked by
    ``check_jacobians`` against central differences), the measurement near the truth
    (odometry-like residuals) and far from it."""
    n = 32
    T1 = _random_poses(gen, n, 1.0)
    T2 = T1 @ _random_poses(gen, n, scale)
    T12 = (T1.inverse() @ T2) @ _random_poses(gen, n, scale)
    prior = T1 @ _random_poses(gen, n, scale)
    r_jax, (J_jax,) = check_jacobians(pose_prior_residual, (T1,), (prior,))
    r, J, valid = pose_prior_linearization((_host(T1),), None, (_host(prior),))
    assert valid is None
    assert np.allclose(r, r_jax, rtol=0, atol=1e-12)
    assert np.allclose(J, J_jax, rtol=0, atol=1e-10)
    r_jax, (J1, J2) = check_jacobians(pose_between_residual, (T1, T2), (T12,))
    r, J, _ = pose_between_linearization((_host(T1), _host(T2)), None, (_host(T12),))
    assert np.allclose(r, r_jax, rtol=0, atol=1e-12)
    assert np.allclose(J, np.concatenate([J1, J2], axis=2), rtol=0, atol=1e-10)
    assert closed_form(pose_prior_residual, None, (jaxlie.SE3,)).linearize is pose_prior_linearization
    assert closed_form(pose_between_residual, None, (jaxlie.SE3, jaxlie.SE3)).linearize is pose_between_linearization


def test_a_pose_graph_linearises_alike_with_and_without_the_closed_forms(gen):
    """A chain with loop closures (Huber), priors (diagonal σ) and box factors: H, g, cost
    and terms equal with and without the closed forms; no pose pushforward is computed when
    every group that reads poses has a closed form."""
    graph, values = _graph(gen)
    keys = [X(i) for i in range(6)]
    for i in range(5):
        Ti, Tj = values[keys[i]], values[keys[i + 1]]
        graph.add(BetweenFactor(keys[i], keys[i + 1], (Ti.inverse() @ Tj) @ _near(gen, 0.02),
                                sigma=[0.01, 0.01, 0.02, 0.001, 0.002, 0.001]))
    graph.add(BetweenFactor(keys[0], keys[5], values[keys[0]].inverse() @ values[keys[5]], sigma=0.05,
                            robust=Huber(1.0)))
    graph.add(PriorFactor(keys[2], values[keys[2]] @ _near(gen, 0.1), sigma=[0.1] * 3 + [0.01] * 3))
    with closed_forms(False):
        general = Problem(graph, values, fixed=[X(0)])
        H0, g0, c0, v0, _ = general.linearize(general.vars)
    closed = Problem(graph, values, fixed=[X(0)])
    assert all(type(g).__name__ == "ClosedFormGroup" for g in closed.kernels.groups)
    pose_type = [i for i, ts in enumerate(closed.tspecs) if ts.cls is jaxlie.SE3][0]
    assert closed.kernels.pushforward[pose_type] is None
    H1, g1, c1, _, _ = closed.linearize(closed.vars)
    assert np.allclose(H1, H0, rtol=1e-10, atol=1e-10 * np.abs(H0).max())
    assert np.allclose(g1, g0, rtol=1e-10, atol=1e-10 * np.abs(g0).max())
    assert c1 == pytest.approx(c0, rel=1e-12)
    # a step: the poses retracted in NumPy (the manifold's host_retract) as by the program
    delta = gen.rng.normal(scale=0.05, size=closed.n)
    new0, c0s, bad0 = general.step(general.vars, delta, v0)
    new1, c1s, bad1 = closed.step(closed.vars, delta, v0)
    assert np.allclose(np.asarray(new1[pose_type].wxyz_xyz), np.asarray(new0[pose_type].wxyz_xyz), rtol=0,
                       atol=1e-13)
    assert c1s == pytest.approx(c0s, rel=1e-11) and bad1 == bad0
    lm_type = [i for i, ts in enumerate(closed.tspecs) if ts.cls is Ellipsoid][0]  # the landmarks too
    for a, b in zip(jax.tree.leaves(new1[lm_type]), jax.tree.leaves(new0[lm_type])):
        assert np.allclose(np.asarray(a), np.asarray(b), rtol=0, atol=1e-13 * max(1.0, np.abs(np.asarray(b)).max()))
    for k in range(len(closed.kernels.groups)):
        r0, J0, _ = general.group_terms(k)
        r1, J1, _ = closed.group_terms(k)
        assert np.allclose(np.asarray(r1), np.asarray(r0), atol=1e-9)
        assert np.allclose(np.asarray(J1), np.asarray(J0), atol=1e-8)


@pytest.mark.parametrize("shape", ["random", "two equal radii", "sphere", "elongated"])
def test_the_objects_uncertainty_jacobian_in_numpy_matches_the_jax_one(gen, shape):
    """The Jacobian of (centre, log sorted radii, P's upper triangle) in the SPD chart that
    carries each object's marginal covariance into map.json (``mapping``'s uncertainty):
    NumPy's, stacked, against JAX's forward mode through the chart and ``matfun.eigh`` (its
    tie rule at equal radii), to round-off; a landmark that is not finite gives NaN rows
    there only."""
    from spdslam.mapping._run import _summary_jacobian, _summary_jacobians

    lm = _landmarks(gen, shape, n=8)
    rows = [Ellipsoid(lm.P[i], lm.center[i]) for i in range(8)]
    J = _summary_jacobians(rows)
    J_jax = np.stack([np.asarray(_summary_jacobian(Ellipsoid(jnp.asarray(e.P), jnp.asarray(e.center))))
                      for e in rows])
    assert J.shape == J_jax.shape == (8, 12, 9)
    assert np.allclose(J, J_jax, rtol=0, atol=1e-10 * (1.0 + np.abs(J_jax).max())), np.abs(J - J_jax).max()
    bad = [Ellipsoid(np.full((3, 3), np.nan), rows[0].center)] + rows[1:]
    with np.errstate(all="ignore"):
        Jb = _summary_jacobians(bad)
    assert not np.isfinite(Jb[0]).all() and np.array_equal(Jb[1:], J[1:])


# --- the compiled kernels (geometry.native) ------------------------------------------------

compiled = pytest.mark.skipif(native.native_kernels() is None, reason="the compiled kernels were not built")


def test_the_kernels_are_built_where_a_c_compiler_is():
    """An install on a machine with a C compiler builds ``geometry/_kernels.c`` (setup.py);
    a build that fails there would silently leave every run on the NumPy code."""
    if shutil.which("cc") is None and shutil.which("gcc") is None:
        pytest.skip("no C compiler here")
    assert native.native_kernels() is not None, "geometry/_kernels.c was not built: pip install -e . again"


def _edge_cases(gen, n=40):
    """Stacked rows with every branch of the box kernel: general views, a camera inside its
    ellipsoid (Δ ≤ 0), an ellipsoid behind its camera, a pose sent astray (NaN), a zero
    quaternion, and per-row cameras."""
    poses, lm, cam = _views(gen, n)
    q = np.array(poses.wxyz_xyz)
    P, t = np.array(lm.P), np.array(lm.center)
    q[1, 4:] = t[1]  # the camera at the centre: inside
    q[2, 4:] = t[2] + 3.0 * quat_to_matrix(q[2, [1, 2, 3, 0]])[:, 2]  # looking away: behind
    q[3, 0] = np.nan
    q[4, :4] = 0.0
    return jaxlie.SE3(q), Ellipsoid(P, t), cam


@compiled
@pytest.mark.parametrize("truncated", [False, True])
def test_the_compiled_box_kernel_is_the_numpy_closed_form(gen, truncated):
    poses, lm, cam = _edge_cases(gen)
    n = len(lm.center)
    boxes = gen.rng.uniform(0.0, 600.0, size=(n, 4))
    keep = (gen.rng.random(boxes.shape) > 0.25).astype(float) if truncated else None
    host_args = (boxes, _host(cam)) + (() if keep is None else (keep,))
    landmarks = jax.tree.map(lambda a: a[::2], lm)  # every landmark seen by two rows
    index = np.arange(n) // 2
    Ts = (None, (_host(pushforward(Ellipsoid, landmarks)), index))
    xs = (poses, Ellipsoid(np.asarray(landmarks.P)[index], np.asarray(landmarks.center)[index]))
    out = {}
    for on in (False, True):
        with native.compiled_kernels(on), np.errstate(all="ignore"):
            out[on] = (inverse_box_linearization(xs, Ts, host_args), inverse_box_linearization(xs, None, host_args, False))
    (r0, J0, v0), (c0, _, w0) = out[False]
    (r1, J1, v1), (c1, _, w1) = out[True]
    assert np.array_equal(v0, v1) and np.array_equal(w0, w1) and not v1[2] and not v1[3]
    for a, b in ((r0, r1), (c0, c1), (J0, J1)):
        assert np.array_equal(np.isfinite(a), np.isfinite(b))
        ok = np.isfinite(a)
        scale = 1.0 + np.abs(np.where(ok, a, 0.0)).max()
        assert np.max(np.abs(np.where(ok, a - b, 0.0))) < 1e-12 * scale
    assert not np.isfinite(r1[3]).any() and not np.isfinite(r1[4]).any()  # astray and zero: NaN, no error
    with pytest.raises(ValueError, match="one landmark index per row"):  # never a read outside the directions
        native.box_linearize(native.native_kernels(), np.asarray(poses.wxyz_xyz), xs[1].P, xs[1].center, boxes,
                             (520.0, 520.0, 320.0, 240.0), None, np.zeros((2, 12, 9)), index, 1e-3)


@compiled
def test_the_compiled_gram_and_scatter_are_numpys(gen):
    J = gen.rng.normal(size=(50, 4, 15))
    r = gen.rng.normal(size=(50, 4))
    H, g = native.gram_upper(native.native_kernels(), J, r)
    iu, ju = np.triu_indices(15)
    assert np.allclose(H, (np.swapaxes(J, 1, 2) @ J)[:, iu, ju], rtol=1e-14, atol=1e-13)
    assert np.allclose(g, np.einsum("nmi,nm->ni", J, r), rtol=1e-14, atol=1e-13)
    slots = gen.rng.integers(0, 30, size=H.size)  # repeated slots sum up
    out = np.ones(30)
    native.scatter_add(native.native_kernels(), slots, H, out)
    assert np.allclose(out, 1.0 + np.bincount(slots, weights=H.ravel(), minlength=30), rtol=1e-13, atol=1e-12)
    with pytest.raises(ValueError, match="as many slots as values"):
        native.scatter_add(native.native_kernels(), slots[:-1], H, out)


def test_the_kernels_setting(monkeypatch):
    monkeypatch.setenv(native.KERNELS_ENV, "numpy")
    assert native.native_kernels() is None
    monkeypatch.setenv(native.KERNELS_ENV, "fast")
    with pytest.raises(ValueError, match=f"{native.KERNELS_ENV} must be 'compiled' or 'numpy', got 'fast'"):
        native.native_kernels()
    monkeypatch.delenv(native.KERNELS_ENV)
    with native.compiled_kernels(False):
        assert native.native_kernels() is None


@compiled
def test_a_problem_linearises_alike_with_and_without_the_compiled_kernels(gen):
    graph, values = _graph(gen, n_poses=8, n_objects=4)
    problem = Problem(graph, values)
    out = {}
    for on in (False, True):
        with native.compiled_kernels(on):
            out[on] = problem.linearize(problem.vars)[:3]
    (H0, g0, c0), (H1, g1, c1) = out[False], out[True]
    assert np.allclose(H1, H0, rtol=1e-12, atol=1e-12 * np.abs(H0).max())
    assert np.allclose(g1, g0, rtol=1e-12, atol=1e-12 * np.abs(g0).max())
    assert c1 == pytest.approx(c0, rel=1e-14)


@compiled
def test_the_compiled_gram_scatter_is_gram_then_scatter(gen):
    J = gen.rng.normal(size=(40, 6, 12))
    r = gen.rng.normal(size=(40, 6))
    hs, gs = gen.rng.integers(0, 50, size=40 * 78), gen.rng.integers(0, 20, size=40 * 12)
    lib = native.native_kernels()
    H, g = native.gram_upper(lib, J, r)
    h0, g0 = np.full(50, 2.0), np.full(20, 3.0)
    h1, g1 = h0.copy(), g0.copy()
    native.scatter_add(lib, hs, H, h0)
    native.scatter_add(lib, gs, g, g0)
    native.gram_scatter(lib, J, r, hs, gs, h1, g1)
    assert np.allclose(h1, h0, rtol=1e-13, atol=1e-12) and np.allclose(g1, g0, rtol=1e-13, atol=1e-12)
    with pytest.raises(ValueError, match="a slot per JᵀJ entry"):
        native.gram_scatter(lib, J, r, hs[:-1], gs, h1, g1)


@compiled
def test_the_compiled_pose_factors_are_the_numpy_closed_forms(gen):
    """Every branch: residuals near zero (θ² < 1e-10 and θ < 1e-2, the series), rotations
    near π (the quaternion's w near 0, of both signs), general ones, unnormalised and NaN
    quaternions."""
    n = 48
    T1 = _random_poses(gen, n, 1.0)
    steps = [_random_poses(gen, 12, s) for s in (1e-7, 3e-3, 0.5)]
    near_pi = np.array(_random_poses(gen, 12, 0.3).wxyz_xyz)
    near_pi[:, :4] = np.c_[np.full(12, 1e-11) * np.where(np.arange(12) % 2, 1, -1), gen.rng.normal(size=(12, 3))]
    near_pi[:, :4] /= np.linalg.norm(near_pi[:, :4], axis=1, keepdims=True)
    E = np.concatenate([np.asarray(s.wxyz_xyz) for s in steps] + [near_pi])
    T2 = np.asarray((T1 @ jaxlie.SE3(E)).wxyz_xyz)
    T12 = np.asarray((T1.inverse() @ jaxlie.SE3(T2)).wxyz_xyz) @ np.diag([1, 1, 1, 1, 1, 1, 1.0])
    T12[:, :4] *= 1.3  # unnormalised: both normalise when they rotate
    T1h = np.array(T1.wxyz_xyz)
    T1h[0, 5] = np.nan
    out = {}
    for on in (False, True):
        with native.compiled_kernels(on), np.errstate(all="ignore"):
            out[on] = (pose_prior_linearization((jaxlie.SE3(T2),), None, (jaxlie.SE3(T1h),)),
                       pose_between_linearization((jaxlie.SE3(T1h), jaxlie.SE3(T2)), None, (jaxlie.SE3(T12),)),
                       pose_between_linearization((jaxlie.SE3(T1h), jaxlie.SE3(T2)), None, (jaxlie.SE3(T12),), False))
    for (r0, J0, _), (r1, J1, _) in zip(out[False], out[True]):
        for a, b in ((r0, r1), (J0, J1)):
            if a is None:
                assert b is None
                continue
            assert np.array_equal(np.isfinite(a), np.isfinite(b)) and not np.isfinite(a[0]).all()
            ok = np.isfinite(a)
            assert np.max(np.abs(np.where(ok, a - b, 0.0)) / (1.0 + np.abs(np.where(ok, a, 0.0)))) < 1e-11


@compiled
def test_the_compiled_whitening_is_numpys(gen):
    lib = native.native_kernels()
    W = gen.rng.normal(size=(30, 4, 4))
    r = gen.rng.normal(size=(30, 4))
    J = gen.rng.normal(size=(30, 4, 15))
    J[3, 2, 7] = np.nan
    r[5, 1] = np.inf
    with np.errstate(all="ignore"):
        rw, Jw, finite, s = native.whiten(lib, W, r, J)
        r0, J0 = (W @ r[:, :, None])[:, :, 0], W @ J
    ok = np.isfinite(r0)
    assert np.allclose(rw[ok], r0[ok], rtol=1e-14, atol=1e-13) and np.array_equal(np.isfinite(rw), ok)
    okJ = np.isfinite(J0)
    assert np.allclose(Jw[okJ], J0[okJ], rtol=1e-14, atol=1e-13)
    assert np.array_equal(finite, np.isfinite(r0).all(axis=1) & np.isfinite(J0).all(axis=(1, 2)))
    assert not finite[3] and not finite[5] and finite.sum() == 28
    assert np.allclose(s[finite], np.sum(r0 * r0, axis=1)[finite], rtol=1e-14)
    r1, J1, f1, s1 = native.whiten(lib, None, r, None)  # no whitening, no Jacobian
    assert J1 is None and np.array_equal(r1, r) and np.array_equal(f1, np.isfinite(r).all(axis=1))
    with pytest.raises(ValueError, match="whiten needs W"):
        native.whiten(lib, W[:, :3], r, J)
