"""The multi-constraint fit in NumPy (``frontend._multi_fit``): its residual's Jacobian
against forward-mode JAX through the model and central differences, the boxes' closed form
(``factors.ellipsoid_boxes``), its LM against the same LM in JAX, the batch."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest
from conftest import ring_of_views, upright_ellipsoid

from spdslam.factors import ellipsoid_boxes
from spdslam.frontend import InitializationError, MultiFit, multi_initialize, multi_initialize_batch
from spdslam.frontend._initialization import _multi_problem
from spdslam.frontend._multi_fit import MULTI_ITERS, PX_SIGMA, _Batch, _residuals, fit_multi
from spdslam.geometry import Ellipsoid, project_box, project_cuboid_box
from spdslam.synthetic import DEFAULT_CAMERA


def _model(theta, frame, has_plane):
    """The model of ``_multi_fit``'s docstring in JAX: the reference its closed form is
    checked against."""
    e1, e2, n, w0 = (jnp.asarray(f) for f in frame)
    r = jnp.exp(theta[3:6])
    psi = theta[6]
    x1 = jnp.cos(psi) * e1 + jnp.sin(psi) * e2
    x2 = -jnp.sin(psi) * e1 + jnp.cos(psi) * e2
    R = jaxlie.SO3.exp(theta[7] * e1 + theta[8] * e2).as_matrix() @ jnp.stack([x1, x2, n], axis=1)
    half = jnp.sqrt(jnp.sum((r * (n @ R)) ** 2))
    h = jnp.where(has_plane, w0 + half, theta[2])
    return Ellipsoid.from_axes(R, theta[0] * e1 + theta[1] * e2 + h * n, r)


def _reference_residual(p):
    box_of = project_cuboid_box if p.shape == "cuboid" else project_box
    poses = jaxlie.SE3(jnp.asarray(p.rows))

    def residual(theta):
        e = _model(theta, p.frame, p.has_plane)
        r_box = jax.vmap(lambda T, b: box_of(e, T, DEFAULT_CAMERA) - b)(poses, jnp.asarray(p.boxes))
        return jnp.concatenate([(r_box / PX_SIGMA * p.mask).ravel(), p.prior_w * (jnp.sort(theta[3:6]) - p.prior_log),
                                p.tilt_w * theta[7:9]])

    return residual


def _problem(shape="ellipsoid", plane=True, tilt=0.02, views=8, seed=0, prior=(0.5, 0.4, 0.3)):
    e = upright_ellipsoid()
    poses = ring_of_views(np.asarray(e.center), n=views)
    rng = np.random.default_rng(seed)
    boxes = np.stack([np.asarray(project_box(e, T, DEFAULT_CAMERA)) for T in poses]) + rng.normal(0, 1.0, (views, 4))
    fit = MultiFit(prior, 0.2, shape, None, tilt)
    return _multi_problem(boxes, poses, DEFAULT_CAMERA, [0, 0, 1], [0, 0, 1, 0] if plane else None, fit, 2)


CASES = [(shape, plane, tilt) for shape in ("ellipsoid", "cuboid") for plane in (True, False) for tilt in (0.02, None)]


@pytest.mark.parametrize("shape,plane,tilt", CASES)
def test_residual_and_jacobian_match_jax_and_central_differences(shape, plane, tilt):
    p = _problem(shape, plane, tilt)
    rng = np.random.default_rng(1)
    theta = p.starts[:3] + rng.normal(0, 0.05, (3, 9))
    theta[:, 7:9] += rng.normal(0, 0.1, (3, 2))  # a tilt away from upright
    b = _Batch.of([p], np.zeros(3, int), shape == "cuboid", DEFAULT_CAMERA)
    r, J = _residuals(theta, b, True)
    residual = _reference_residual(p)
    for i in range(3):
        ref = np.array(jax.jacfwd(residual)(jnp.asarray(theta[i])))
        if plane:
            ref[:, 2] = 0.0  # the height is the plane's: held
        if tilt is None:
            ref[:, 7:9] = 0.0  # upright: held
        np.testing.assert_allclose(r[i], np.asarray(residual(jnp.asarray(theta[i]))), atol=1e-9)
        np.testing.assert_allclose(J[i], ref, atol=1e-9 * np.abs(ref).max())
        # central differences along each free coordinate of θ
        for k in [k for k in range(9) if not (plane and k == 2) and not (tilt is None and k in (7, 8))]:
            h = 1e-6
            tp, tm = theta[i : i + 1].copy(), theta[i : i + 1].copy()
            tp[0, k] += h
            tm[0, k] -= h
            fd = (_residuals(tp, b.take([i]), False)[0] - _residuals(tm, b.take([i]), False)[0])[0] / (2 * h)
            np.testing.assert_allclose(J[i][:, k], fd, atol=1e-5 * max(1.0, np.abs(fd).max()))


def test_ellipsoid_boxes_and_their_derivatives():
    """The boxes of ``factors.ellipsoid_boxes`` are ``project_box``'s; their derivatives
    along symmetric directions of P and directions of the centre, central differences."""
    rng = np.random.default_rng(2)
    e = upright_ellipsoid()
    poses = ring_of_views(np.asarray(e.center), n=5)
    rows = np.stack([np.asarray(T.wxyz_xyz) for T in poses])
    A = np.stack([np.asarray(T.rotation().as_matrix()).T for T in poses])[None]
    c = rows[None, :, 4:]
    P, t = np.asarray(e.P)[None], np.asarray(e.center)[None]
    S = rng.normal(size=(4, 3, 3))
    dP = (S + np.swapaxes(S, 1, 2))[None] * 0.1
    dt = rng.normal(size=(1, 4, 3)) * 0.1
    box, dbox = ellipsoid_boxes(A, c, P, t, DEFAULT_CAMERA, (dP, dt))
    ref = np.stack([np.asarray(project_box(e, T, DEFAULT_CAMERA)) for T in poses])
    np.testing.assert_allclose(box[0], ref, atol=1e-9)
    h = 1e-6
    for q in range(4):
        up = ellipsoid_boxes(A, c, P + h * dP[:, q], t + h * dt[:, q], DEFAULT_CAMERA)[0]
        down = ellipsoid_boxes(A, c, P - h * dP[:, q], t - h * dt[:, q], DEFAULT_CAMERA)[0]
        np.testing.assert_allclose(dbox[0, :, :, q], (up - down)[0] / (2 * h), atol=1e-5)


def _reference_fit(p):
    """``_multi_fit``'s LM in JAX (fixed ``MULTI_ITERS`` steps, no member stopped early)."""
    residual = _reference_residual(p)

    def cost(th):
        r = residual(th)
        return jnp.sum(jnp.where(jnp.isfinite(r), r**2, jnp.inf))

    def body(_, state):
        th, lam, c = state
        r = residual(th)
        J = jax.jacfwd(residual)(th)
        J = J.at[:, 2].set(0.0) if p.has_plane else J
        J = J if p.tilt_w > 0 else J.at[:, 7:9].set(0.0)
        H, g = J.T @ J, J.T @ r
        d = jnp.diagonal(H)
        D = jnp.concatenate([jnp.full(3, jnp.max(d[:3])), jnp.full(3, jnp.max(d[3:6])), d[6:]])
        cand = th - jnp.linalg.solve(H + lam * jnp.diag(D + 1e-9), g)
        cc = cost(cand)
        ok = cc < c
        return jnp.where(ok, cand, th), jnp.where(ok, lam * 0.3, lam * 10.0), jnp.where(ok, cc, c)

    def fit(th):
        th, _, c = jax.lax.fori_loop(0, MULTI_ITERS, body, (th, 1e-3, cost(th)))
        e = _model(th, p.frame, p.has_plane)
        return c, e.P, e.center

    return [np.asarray(a) for a in jax.jit(jax.vmap(fit))(jnp.asarray(p.starts))]


@pytest.mark.parametrize("shape,plane,tilt", [("ellipsoid", True, 0.02), ("cuboid", False, None)])
def test_the_lm_ends_where_the_same_lm_in_jax_does(shape, plane, tilt):
    p = _problem(shape, plane, tilt, views=12, seed=3)
    (cost, P, t), = fit_multi([p], DEFAULT_CAMERA)
    ref_cost, ref_P, ref_t = _reference_fit(p)
    np.testing.assert_allclose(cost, ref_cost, rtol=1e-6)
    np.testing.assert_allclose(P, ref_P, atol=1e-6 * np.abs(ref_P).max())
    np.testing.assert_allclose(t, ref_t, atol=1e-6)


def test_the_batch_is_each_object_alone_and_a_failure_is_its_own():
    e = upright_ellipsoid()
    poses = ring_of_views(np.asarray(e.center), n=6)
    rng = np.random.default_rng(4)
    boxes = np.stack([np.asarray(project_box(e, T, DEFAULT_CAMERA)) for T in poses])
    objects = [(boxes + rng.normal(0, 1.0, boxes.shape), poses, [0, 0, 1, 0], MultiFit()),
               (boxes[:1], poses[:1], None, MultiFit()),  # one view: fails alone
               (boxes + rng.normal(0, 1.0, boxes.shape), poses, None, MultiFit(shape="cuboid", tilt_sigma=None)),
               (boxes + rng.normal(0, 1.0, boxes.shape), poses, None, MultiFit((0.6, 0.35, 0.3)))]
    got = multi_initialize_batch(objects, DEFAULT_CAMERA, [0, 0, 1])
    assert isinstance(got[1], InitializationError) and "at least 2 views" in str(got[1])
    for k in (0, 2, 3):
        alone = multi_initialize(*objects[k][:2], DEFAULT_CAMERA, [0, 0, 1], *objects[k][2:])
        np.testing.assert_allclose(got[k].P, alone.P, atol=1e-9)
        np.testing.assert_allclose(got[k].center, alone.center, atol=1e-9)
    np.testing.assert_allclose(got[0].P, e.P, atol=0.02)
    with pytest.raises(InitializationError, match="at least 2 views"):
        multi_initialize(boxes[:1], poses[:1], DEFAULT_CAMERA, [0, 0, 1])


def test_an_object_whose_fit_fails_fails_alone():
    """NaN box edges: that object's error in the batch, the other fitted; within the LM a
    member whose cost is not finite anywhere ends not finite without touching the others."""
    e = upright_ellipsoid()
    poses = ring_of_views(np.asarray(e.center), n=6)
    boxes = np.stack([np.asarray(project_box(e, T, DEFAULT_CAMERA)) for T in poses])
    nan_boxes = boxes.copy()
    nan_boxes[:, 0] = np.nan
    got = multi_initialize_batch([(nan_boxes, poses, None, MultiFit()), (boxes, poses, None, MultiFit())],
                                 DEFAULT_CAMERA, [0, 0, 1])
    assert isinstance(got[0], ValueError) and not isinstance(got[1], Exception)
    np.testing.assert_allclose(got[1].P, e.P, atol=1e-4)
    p = _problem(views=6)
    broken = dataclasses.replace(p, boxes=np.where(np.arange(4) == 2, np.nan, p.boxes))
    (cost_b, _, _), (cost_p, P, _) = fit_multi([broken, p], DEFAULT_CAMERA)
    assert not np.isfinite(cost_b).any() and np.isfinite(cost_p).all()
    np.testing.assert_allclose(P, fit_multi([p], DEFAULT_CAMERA)[0][1], atol=1e-12)


def test_an_error_inside_the_batch_falls_back_to_each_object_alone(monkeypatch):
    """The batch's arithmetic raising: each object is fitted alone, and only the one that
    raises again fails."""
    import spdslam.frontend._initialization as init_mod

    real = init_mod.fit_multi

    def fragile(problems, camera):
        if len(problems) > 1 or problems[0].prior_w > 0:
            raise np.linalg.LinAlgError("Singular matrix")
        return real(problems, camera)

    monkeypatch.setattr(init_mod, "fit_multi", fragile)
    e = upright_ellipsoid()
    poses = ring_of_views(np.asarray(e.center), n=6)
    boxes = np.stack([np.asarray(project_box(e, T, DEFAULT_CAMERA)) for T in poses])
    got = multi_initialize_batch([(boxes, poses, None, MultiFit()), (boxes, poses, None, MultiFit((0.6, 0.35, 0.3)))],
                                 DEFAULT_CAMERA, [0, 0, 1])
    np.testing.assert_allclose(got[0].P, e.P, atol=1e-4)
    assert isinstance(got[1], np.linalg.LinAlgError)
