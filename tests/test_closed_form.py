"""Closed-form linearisations (``factors.closed_form``) against the general JAX path and
central differences, and the solver's use of them (``solver.closed_forms``)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest
from conftest import check_jacobians

from spdslam.factors import (
    Cauchy,
    InverseBoxFactor,
    box_visible,
    closed_form,
    inverse_box_linearization,
    inverse_box_residual,
)
from spdslam.geometry import Camera, Ellipsoid, EllipsoidRTS, manifold, project_box
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
    Ts = (_host(pushforward(jaxlie.SE3, poses)), _host(pushforward(Ellipsoid, lm)))
    host_args = tuple(_host(a) for a in args)
    r, J, valid = inverse_box_linearization((_host(poses), _host(lm)), Ts, host_args)
    assert np.allclose(r, r_jax, rtol=1e-9, atol=1e-9)
    J_ref = np.concatenate([J_pose, J_lm], axis=2)
    assert np.max(np.abs(J - J_ref) / (1.0 + np.abs(J_ref).max(axis=(1, 2), keepdims=True))) < 1e-9
    assert np.array_equal(valid, np.asarray(jax.vmap(lambda T, e: box_visible(T, e, None, None))(poses, lm)))
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
