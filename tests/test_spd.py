"""SPD(3) with the affine-invariant metric, against pymanopt 2.2.1.

What pymanopt 2.2.1 implements (``pymanopt.manifolds.SymmetricPositiveDefinite``):

- ``exp(P, ξ) = P expm(P⁻¹ξ)``: the Riemannian exponential, equal to P^½ Exp(P^-½ξP^-½) P^½,
  i.e. the same map as ``spd.retract``/``spd.exp`` (paper eq. 21);
- ``retraction(P, ξ) = P + ξ + ½ ξ P⁻¹ ξ``: a *second-order* retraction, not the exponential;
  it agrees with ours only up to O(‖ξ‖³), which is what we check;
- ``log(P, Q) = C Log(C⁻¹QC⁻ᵀ) Cᵀ`` with C the Cholesky factor of P: the Riemannian log,
  equal to P^½ Log(P^-½ Q P^-½) P^½ (paper eq. 22), i.e. ``spd.local``/``spd.log``;
- ``dist``: ‖Log(C⁻¹QC⁻ᵀ)‖_F, and ``inner_product``: tr(P⁻¹AP⁻¹B).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from pymanopt.manifolds import SymmetricPositiveDefinite

from spdslam import spd

KINDS = ("general", "sphere", "spheroid_oblate", "spheroid_prolate", "identity")

M = SymmetricPositiveDefinite(3)


def _tangent(gen, P, norm):
    """A random symmetric ξ with ‖ξ‖_P = norm (affine-invariant norm, computed by pymanopt)."""
    xi = gen.symmetric()
    return xi * (norm / M.norm(P, xi))


# --- coordinates ----------------------------------------------------------------------


def test_vec_sym_round_trip_and_frobenius_orthonormal(gen):
    E = np.asarray(spd.vec_to_sym(np.eye(6)))
    assert E.shape == (6, 3, 3)
    np.testing.assert_array_equal(E, E.transpose(0, 2, 1))
    gram = np.einsum("kij,lij->kl", E, E)
    np.testing.assert_allclose(gram, np.eye(6), atol=1e-15)
    for _ in range(5):
        c = gen.rng.normal(size=6)
        S = gen.symmetric()
        np.testing.assert_allclose(np.asarray(spd.sym_to_vec(spd.vec_to_sym(c))), c, atol=1e-15)
        np.testing.assert_allclose(np.asarray(spd.vec_to_sym(spd.sym_to_vec(S))), S, atol=1e-15)
        # coordinates are isometric: ‖c‖ = ‖S‖_F
        np.testing.assert_allclose(np.linalg.norm(spd.sym_to_vec(S)), np.linalg.norm(S), rtol=1e-14)


@pytest.mark.parametrize("kind", KINDS)
def test_tangent_basis_orthonormal(gen, kind):
    P = gen.spd(kind)
    B = np.asarray(spd.tangent_basis(P))
    assert B.shape == (6, 3, 3)
    G = np.asarray(spd.inner(P, B[:, None], B[None, :]))
    np.testing.assert_allclose(G, np.eye(6), atol=1e-10)
    G_pm = np.array([[M.inner_product(P, B[k], B[l]) for l in range(6)] for k in range(6)])
    np.testing.assert_allclose(G_pm, np.eye(6), atol=1e-10)
    # it is a basis: ξ = Σ ⟨ξ, Bₖ⟩_P Bₖ for any symmetric ξ
    xi = gen.symmetric()
    coef = np.asarray(spd.inner(P, xi, B))
    np.testing.assert_allclose(np.einsum("k,kij->ij", coef, B), xi, atol=1e-10)


@pytest.mark.parametrize("kind", KINDS)
def test_inner_matches_pymanopt(gen, kind):
    P = gen.spd(kind)
    A, B = gen.symmetric(), gen.symmetric()
    np.testing.assert_allclose(
        float(spd.inner(P, A, B)), M.inner_product(P, A, B), rtol=1e-12, atol=1e-12
    )
    np.testing.assert_allclose(float(spd.inner(P, A, A)), M.norm(P, A) ** 2, rtol=1e-12)


# --- exp / log against pymanopt -------------------------------------------------------


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("norm", [1e-3, 0.5, 3.0])
def test_exp_matches_pymanopt_exp(gen, kind, norm):
    P = gen.spd(kind)
    xi = _tangent(gen, P, norm)
    want = M.exp(P, xi)
    for f in (spd.retract, spd.exp):
        got = np.asarray(f(P, xi))
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-11 * np.abs(want).max())


@pytest.mark.parametrize("kind", KINDS)
def test_log_matches_pymanopt_log(gen, kind):
    P = gen.spd(kind)
    for Q in (gen.spd("general"), gen.spd(kind), M.exp(P, _tangent(gen, P, 0.3))):
        want = M.log(P, Q)
        for f in (spd.local, spd.log):
            got = np.asarray(f(P, Q))
            np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-10 * np.abs(want).max())
        np.testing.assert_allclose(float(spd.distance(P, Q)), M.dist(P, Q), rtol=1e-10, atol=1e-12)


def test_pymanopt_retraction_is_exp_to_second_order_only(gen):
    """pymanopt's retraction P + ξ + ½ξP⁻¹ξ agrees with exp up to O(‖ξ‖³): halving ξ divides
    the difference by ≈ 8. It is a different map, so it is compared only at that order."""
    P = gen.spd("general")
    xi = _tangent(gen, P, 1.0)
    errs = []
    for t in (0.08, 0.04, 0.02):
        errs.append(np.linalg.norm(np.asarray(spd.retract(P, t * xi)) - M.retraction(P, t * xi)))
    ratios = np.array(errs[:-1]) / np.array(errs[1:])
    np.testing.assert_allclose(ratios, 8.0, rtol=0.1)
    assert errs[0] > 1e-6  # really a different map


@pytest.mark.parametrize("kind", KINDS)
def test_vec_coordinates_match_matrix_maps(gen, kind):
    P = gen.spd(kind)
    B = np.asarray(spd.tangent_basis(P))
    c = gen.rng.normal(size=6)
    xi = np.einsum("k,kij->ij", c, B)
    np.testing.assert_allclose(
        np.asarray(spd.retract_vec(P, c)), np.asarray(spd.retract(P, xi)), rtol=1e-10, atol=1e-12
    )
    Q = gen.spd("general")
    cq = np.asarray(spd.local_vec(P, Q))
    np.testing.assert_allclose(
        np.einsum("k,kij->ij", cq, B), np.asarray(spd.local(P, Q)), rtol=1e-9, atol=1e-10
    )
    # and ‖c‖ is the Riemannian norm of the tangent vector (orthonormal coordinates)
    np.testing.assert_allclose(np.linalg.norm(cq), M.norm(P, M.log(P, Q)), rtol=1e-10)


@pytest.mark.parametrize("kind", KINDS)
def test_retract_local_inverse(gen, kind):
    P = gen.spd(kind)
    for norm in (1e-6, 0.1, 1.0, 4.0):
        xi = _tangent(gen, P, norm)
        Q = spd.retract(P, xi)
        np.testing.assert_allclose(
            np.asarray(spd.local(P, Q)), xi, rtol=1e-8, atol=1e-10 * norm + 1e-13 * np.abs(P).max()
        )
    Q = gen.spd("general")
    np.testing.assert_allclose(np.asarray(spd.retract(P, spd.local(P, Q))), Q, rtol=1e-9, atol=1e-11)
    np.testing.assert_allclose(np.asarray(spd.retract(P, np.zeros((3, 3)))), P, rtol=1e-12, atol=1e-13)


# --- distance -------------------------------------------------------------------------


def test_distance_properties(gen):
    for _ in range(4):
        P, Q, S = gen.spd("general"), gen.spd("spheroid_oblate"), gen.spd("sphere")
        for X, Y in ((P, Q), (P, S), (Q, S)):
            dxy, dyx = float(spd.distance(X, Y)), float(spd.distance(Y, X))
            np.testing.assert_allclose(dxy, dyx, rtol=1e-10)
            assert dxy > 0
            # congruence invariance under general invertible A (det of either sign)
            for A in (gen.orthogonal(), gen.rng.normal(size=(3, 3)) + 2 * np.eye(3)):
                np.testing.assert_allclose(
                    float(spd.distance(A @ X @ A.T, A @ Y @ A.T)), dxy, rtol=1e-8
                )
            # invariance under inversion
            np.testing.assert_allclose(
                float(spd.distance(np.linalg.inv(X), np.linalg.inv(Y))), dxy, rtol=1e-8
            )
        # triangle inequality
        assert float(spd.distance(P, S)) <= float(spd.distance(P, Q)) + float(spd.distance(Q, S)) + 1e-12


@pytest.mark.parametrize("kind", KINDS)
def test_distance_zero_iff_equal(gen, kind):
    P = gen.spd(kind)
    assert float(spd.distance(P, P)) < 1e-12
    assert float(spd.distance(P, P.copy())) < 1e-12
    # any change, however small, gives a positive distance equal to the Riemannian norm
    for eps in (1e-7, 1e-4, 1e-1):
        xi = _tangent(gen, P, eps)
        Q = P + xi
        d = float(spd.distance(P, Q))
        assert d > 0
        np.testing.assert_allclose(d, M.dist(P, Q), rtol=1e-6)
    assert float(spd.distance(P, 1.0001 * P)) > 0


def test_distance_closed_forms(gen):
    for _ in range(3):
        P = gen.spd("general")
        c = gen.rng.uniform(0.1, 10.0)
        np.testing.assert_allclose(float(spd.distance(P, c * P)), np.sqrt(3) * abs(np.log(c)), rtol=1e-10)
        a = gen.rng.normal(size=3)
        R = gen.rotation()
        np.testing.assert_allclose(
            float(spd.distance(np.eye(3), gen.spd_from(R, np.exp(a)))), np.linalg.norm(a), rtol=1e-10
        )
        # geodesic: d(P, P ⊞ ξ) = ‖ξ‖_P
        for n in (0.01, 1.0, 5.0):
            xi = _tangent(gen, P, n)
            np.testing.assert_allclose(float(spd.distance(P, spd.retract(P, xi))), n, rtol=1e-8)


# --- is_spd ---------------------------------------------------------------------------


def test_is_spd(gen):
    P = gen.spd("general")
    assert bool(spd.is_spd(P))
    assert bool(spd.is_spd(np.eye(3)))
    assert not bool(spd.is_spd(-P))
    assert not bool(spd.is_spd(np.diag([1.0, 1.0, 0.0])))
    assert not bool(spd.is_spd(np.diag([1.0, -1e-3, 2.0])))
    N = np.zeros((3, 3))
    N[0, 1] = 0.1
    assert not bool(spd.is_spd(P + N)), "not symmetric"
    assert bool(spd.is_spd(np.diag([1.0, 1e-3, 2.0]), rtol=1e-4))
    assert not bool(spd.is_spd(np.diag([1.0, 1e-3, 2.0]), rtol=1e-2))


def test_is_spd_batched(gen):
    P = gen.spd("general")
    N = np.zeros((3, 3))
    N[0, 1] = 0.1
    batch = np.stack([P, -P, np.eye(3), P + N, 100.0 * np.eye(3)])
    want = [True, False, True, False, True]
    np.testing.assert_array_equal(np.asarray(spd.is_spd(batch)), want)
    np.testing.assert_array_equal(np.asarray(jax.vmap(spd.is_spd)(batch)), want)


# --- numpy / JAX / batch / vmap / jit / grad ------------------------------------------


def test_batch_vmap_jit(gen):
    n = 5
    Ps = np.stack([gen.spd(k) for k in KINDS])
    Qs = np.stack([gen.spd("general") for _ in range(n)])
    cs = gen.rng.normal(size=(n, 6))
    want_r = np.stack([spd.retract_vec(P, c) for P, c in zip(Ps, cs)])
    want_l = np.stack([spd.local_vec(P, Q) for P, Q in zip(Ps, Qs)])
    want_d = np.array([M.dist(P, Q) for P, Q in zip(Ps, Qs)])
    for f, args, want in (
        (spd.retract_vec, (Ps, cs), want_r),
        (spd.local_vec, (Ps, Qs), want_l),
        (spd.distance, (Ps, Qs), want_d),
    ):
        for out in (
            f(*args),
            f(*(jnp.asarray(a) for a in args)),
            jax.vmap(f)(*args),
            jax.jit(f)(*args),
            jax.jit(jax.vmap(f))(*args),
        ):
            np.testing.assert_allclose(np.asarray(out), want, rtol=1e-9, atol=1e-11)
    # broadcasting one P against many tangent vectors
    np.testing.assert_allclose(
        np.asarray(spd.retract_vec(Ps[0], cs)),
        np.stack([spd.retract_vec(Ps[0], c) for c in cs]),
        rtol=1e-10,
        atol=1e-12,
    )
    xis = np.stack([gen.symmetric() for _ in range(n)])
    np.testing.assert_allclose(
        np.asarray(jax.jit(spd.retract)(Ps, xis)),
        np.stack([M.exp(P, xi) for P, xi in zip(Ps, xis)]),
        rtol=1e-9,
        atol=1e-11,
    )


@pytest.mark.parametrize("kind", KINDS)
def test_gradients_finite_and_correct(gen, kind):
    """d/dc of a loss through retract_vec/local_vec at c = 0 (what the solver differentiates),
    at spheres and the identity too: finite and equal to central differences."""
    P, Q = gen.spd(kind), gen.spd("general")
    c0 = np.zeros(6)
    g = np.asarray(_GRAD(c0, P, Q))
    J = np.asarray(_JAC(c0, P, Q))
    assert np.all(np.isfinite(g)) and np.all(np.isfinite(J))
    h = 1e-6
    g_fd = np.array([(float(_LOSS(h * e, P, Q)) - float(_LOSS(-h * e, P, Q))) / (2 * h) for e in np.eye(6)])
    np.testing.assert_allclose(g, g_fd, rtol=1e-6, atol=1e-7)
    # at P itself the Jacobian of local(P, retract(P, c)) is the identity
    J0 = np.asarray(_JAC(c0, P, P))
    np.testing.assert_allclose(J0, np.eye(6), atol=1e-10)


def _residual(c, P, Q):
    return spd.local_vec(Q, spd.retract_vec(P, c))


_LOSS = jax.jit(lambda c, P, Q: jnp.sum(_residual(c, P, Q) ** 2))
_GRAD = jax.jit(jax.grad(lambda c, P, Q: jnp.sum(_residual(c, P, Q) ** 2)))
_JAC = jax.jit(jax.jacfwd(_residual))


def test_distance_in_numpy_and_jax_is_eq22(gen):
    """One implementation for both: NumPy in, NumPy out (the front end's per-pair calls), the
    same values as in JAX and as ‖Log(P^-½ Q P^-½)‖_F from the log map; NumPy input that is
    not SPD is a ValueError."""
    P = np.stack([gen.spd() for _ in range(5)])
    Q = np.stack([gen.spd() for _ in range(5)])
    d = spd.distance(P, Q)
    assert isinstance(d, np.ndarray)
    dj = spd.distance(jnp.asarray(P), jnp.asarray(Q))
    assert isinstance(dj, jax.Array)
    np.testing.assert_allclose(d, np.asarray(dj), rtol=1e-12)
    np.testing.assert_allclose(d, np.linalg.norm(np.asarray(spd.local_vec(P, Q)), axis=-1), rtol=1e-9)
    A = gen.rng.normal(size=(3, 3)) + 3 * np.eye(3)  # affine invariance d(APAᵀ, AQAᵀ) = d(P, Q)
    np.testing.assert_allclose(spd.distance(A @ P @ A.T, A @ Q @ A.T), d, rtol=1e-7)
    np.testing.assert_allclose(spd.distance(P, P), 0.0, atol=1e-9)
    with pytest.raises(ValueError, match="P is not symmetric positive definite"):
        spd.distance(-np.eye(3), np.eye(3))
    with pytest.raises(ValueError, match="Q is not symmetric positive definite"):
        spd.distance(np.eye(3), -np.eye(3))
