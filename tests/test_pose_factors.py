"""SE(3) prior and between factors: zero at the truth, Jacobians in tangent coordinates
against central differences, noise-model order, and agreement with gtsam's Pose3 factors."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

import spdslam  # noqa: F401  (float64)
from spdslam.factors import BetweenFactor, PriorFactor, pose_between_residual, pose_prior_residual

N = 64  # random poses per test


def random_poses(rng, n, scale=1.5):
    """n random poses: uniform rotations (quaternions), translations ~ N(0, scale²)."""
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return jaxlie.SE3(jnp.asarray(np.concatenate([q, rng.normal(size=(n, 3)) * scale], 1)))


def _retract(T, d):
    return T @ jaxlie.SE3.exp(d)


@functools.lru_cache(maxsize=None)
def _jac_fns(residual, k):
    """Jitted (autodiff, central-difference) Jacobians of residual(T₁ ⊞ δ₁, …, T_k ⊞ δ_k, data)
    with respect to δ at 0, vmapped over the poses (compiled once per residual)."""

    def autodiff(poses, data):
        def one(Ts, d):
            f = lambda delta: residual(
                *[_retract(T, delta[6 * i: 6 * i + 6]) for i, T in enumerate(Ts)], *d
            )
            return jax.jacfwd(f)(jnp.zeros(6 * k))

        return jax.vmap(one)(poses, data)

    def central(poses, data, h=1e-6):
        # the perturbation is applied outside any autodiff; all columns in one vmapped call
        def column(d):
            plus = [_retract(T, d[6 * i: 6 * i + 6]) for i, T in enumerate(poses)]
            minus = [_retract(T, -d[6 * i: 6 * i + 6]) for i, T in enumerate(poses)]
            return (jax.vmap(residual)(*plus, *data) - jax.vmap(residual)(*minus, *data)) / (2 * h)

        cols = jax.vmap(column)(jnp.eye(6 * k) * h)  # (6k, N, m)
        return jnp.moveaxis(cols, 0, -1)

    return jax.jit(autodiff), jax.jit(central)


def jacobians(residual, poses, data):
    """(J by jax.jacfwd, J by central differences), each (N, m, 6k)."""
    auto, central = _jac_fns(residual, len(poses))
    poses, data = tuple(poses), tuple(data)
    return np.asarray(auto(poses, data)), np.asarray(central(poses, data))


def test_prior_residual_zero_at_truth(rng):
    T = random_poses(rng, N)
    r = jax.vmap(pose_prior_residual)(T, T)
    np.testing.assert_allclose(np.asarray(r), 0.0, atol=1e-12)


def test_between_residual_zero_at_truth(rng):
    T1, T2 = random_poses(rng, N), random_poses(rng, N)
    T12 = jax.vmap(lambda a, b: a.inverse() @ b)(T1, T2)
    r = jax.vmap(pose_between_residual)(T1, T2, T12)
    np.testing.assert_allclose(np.asarray(r), 0.0, atol=1e-10)


def test_prior_residual_is_log_of_error(rng):
    """r = Log(T̄⁻¹T): moving T by T ⊞ ξ from T̄ gives back ξ."""
    Tbar = random_poses(rng, N)
    xi = rng.normal(size=(N, 6)) * 0.5
    T = jax.vmap(_retract)(Tbar, jnp.asarray(xi))
    r = jax.vmap(pose_prior_residual)(T, Tbar)
    np.testing.assert_allclose(np.asarray(r), xi, atol=1e-10)


NOISE = (0.0, 0.3, 1.5)


def test_prior_jacobian_matches_central_differences(rng):
    for noise in NOISE:
        Tbar = random_poses(rng, N)
        T = jax.vmap(_retract)(Tbar, jnp.asarray(rng.normal(size=(N, 6)) * noise))
        J, Jn = jacobians(pose_prior_residual, [T], [Tbar])
        np.testing.assert_allclose(J, Jn, atol=1e-6, rtol=1e-6)
        if noise == 0.0:  # at the truth: J = I
            np.testing.assert_allclose(J, np.broadcast_to(np.eye(6), J.shape), atol=1e-12)


def test_between_jacobian_matches_central_differences(rng):
    for noise in NOISE:
        _check_between(rng, noise)


def _check_between(rng, noise):
    T1, T2 = random_poses(rng, N), random_poses(rng, N)
    T12 = jax.vmap(lambda a, b, e: a.inverse() @ b @ jaxlie.SE3.exp(e))(
        T1, T2, jnp.asarray(rng.normal(size=(N, 6)) * noise)
    )
    J, Jn = jacobians(pose_between_residual, [T1, T2], [T12])
    np.testing.assert_allclose(J, Jn, atol=1e-6, rtol=1e-6)
    if noise == 0.0:  # at the truth: ∂/∂δ₂ = I, ∂/∂δ₁ = −Ad(T₂⁻¹T₁)
        np.testing.assert_allclose(J[:, :, 6:], np.broadcast_to(np.eye(6), (N, 6, 6)), atol=1e-9)
        Ad = jax.vmap(lambda a, b: (b.inverse() @ a).adjoint())(T1, T2)
        np.testing.assert_allclose(J[:, :, :6], -np.asarray(Ad), atol=1e-9)


def test_factor_data_and_noise_model_order(rng):
    """Measurements live in args (so factors stack); sigmas are (translation, rotation)."""
    T = random_poses(rng, 2)
    Ta, Tb = jaxlie.SE3(T.wxyz_xyz[0]), jaxlie.SE3(T.wxyz_xyz[1])
    sigma = np.array([0.1, 0.2, 0.3, 0.01, 0.02, 0.03])
    f = PriorFactor("a", Tb, sigma=sigma)
    assert f.keys == ("a",) and len(f.args) == 1 and isinstance(f.args[0], jaxlie.SE3)
    r = np.asarray(pose_prior_residual(Ta, Tb))
    np.testing.assert_allclose(np.asarray(f.evaluate(Ta)), r / sigma, rtol=1e-12)
    np.testing.assert_allclose(f.error(Ta), 0.5 * np.sum((r / sigma) ** 2), rtol=1e-12)
    # a 4x4 matrix is accepted for every pose argument
    g = BetweenFactor("a", "b", np.asarray((Ta.inverse() @ Tb).as_matrix()), sigma=sigma)
    np.testing.assert_allclose(np.asarray(g.evaluate(Ta, Tb)), 0.0, atol=1e-9)
    assert g.args[0].wxyz_xyz.shape == (7,)
    with pytest.raises(ValueError, match="4x4"):
        PriorFactor("a", np.eye(3))
    cov = np.diag(sigma**2)
    h = BetweenFactor("a", "b", Ta, covariance=cov)
    np.testing.assert_allclose(h.sqrt_info.T @ h.sqrt_info, np.linalg.inv(cov), rtol=1e-12)


def test_errors_match_gtsam(rng):
    """gtsam's Pose3 factors give the same errors with the sigmas permuted to (ω, v)."""
    gtsam = pytest.importorskip("gtsam")
    sigma = np.array([0.1, 0.2, 0.3, 0.01, 0.02, 0.03])
    gt_noise = gtsam.noiseModel.Diagonal.Sigmas(sigma[[3, 4, 5, 0, 1, 2]])
    T = random_poses(rng, 3, scale=1.0)
    Ts = [jaxlie.SE3(T.wxyz_xyz[i]) for i in range(3)]
    P = [gtsam.Pose3(np.asarray(t.as_matrix())) for t in Ts]
    vals = gtsam.Values()
    vals.insert(1, P[0])
    vals.insert(2, P[1])
    prior = gtsam.PriorFactorPose3(1, P[2], gt_noise)
    between = gtsam.BetweenFactorPose3(1, 2, P[2], gt_noise)
    np.testing.assert_allclose(PriorFactor(1, Ts[2], sigma=sigma).error(Ts[0]),
                               prior.error(vals), rtol=1e-9)
    np.testing.assert_allclose(BetweenFactor(1, 2, Ts[2], sigma=sigma).error(Ts[0], Ts[1]),
                               between.error(vals), rtol=1e-9)
