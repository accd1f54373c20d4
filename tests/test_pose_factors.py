"""SE(3) prior and between factors: zero at the truth, their Jacobians' closed forms there,
noise-model order, and agreement with gtsam's Pose3 factors."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

import spdslam  # noqa: F401  (float64)
from spdslam.factors import (
    BetweenFactor,
    PriorFactor,
    pose_between_residual,
    pose_prior_residual,
    tangent_jacobians,
)

N = 64  # random poses per test


def random_poses(rng, n, scale=1.5):
    """n random poses: uniform rotations (quaternions), translations ~ N(0, scale²)."""
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return jaxlie.SE3(jnp.asarray(np.concatenate([q, rng.normal(size=(n, 3)) * scale], 1)))


def _retract(T, d):
    return T @ jaxlie.SE3.exp(d)


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


def test_jacobians_at_the_truth_are_the_closed_forms(rng):
    """At the measurement: ∂r/∂δ = I for the prior; ∂/∂δ₂ = I, ∂/∂δ₁ = −Ad(T₂⁻¹T₁) for the
    between factor (the central-difference check is in test_factor_jacobians)."""
    T = random_poses(rng, N)
    _, (J,) = jax.vmap(lambda a: tangent_jacobians(pose_prior_residual, (a,), (a,)))(T)
    np.testing.assert_allclose(np.asarray(J), np.broadcast_to(np.eye(6), (N, 6, 6)), atol=1e-12)
    T1, T2 = random_poses(rng, N), random_poses(rng, N)
    T12 = jax.vmap(lambda a, b: a.inverse() @ b)(T1, T2)
    _, (J1, J2) = jax.vmap(lambda a, b, m: tangent_jacobians(pose_between_residual, (a, b), (m,)))(
        T1, T2, T12)
    np.testing.assert_allclose(np.asarray(J2), np.broadcast_to(np.eye(6), (N, 6, 6)), atol=1e-9)
    Ad = jax.vmap(lambda a, b: (b.inverse() @ a).adjoint())(T1, T2)
    np.testing.assert_allclose(np.asarray(J1), -np.asarray(Ad), atol=1e-9)


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
