"""Spectral matrix functions: values against scipy, derivatives against central differences.

The derivatives are checked where autodiff through ``eigh`` breaks down: exact spheres c·I,
spheroids R diag(a, b, b) Rᵀ, the identity, and eigenvalue gaps on both sides of the tie
tolerance.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg as sla

from spdslam import matfun

KINDS = ("general", "sphere", "spheroid_oblate", "spheroid_prolate", "identity")


def _sym(A):
    return 0.5 * (A + A.T)


def _sqrtm(A):
    return np.real(sla.sqrtm(A))


# name -> (spdslam function, independent scipy reference, needs positive definite input)
FUNCS = {
    "sqrtm": (matfun.sqrtm, _sqrtm, True),
    "invsqrtm": (matfun.invsqrtm, lambda A: np.linalg.inv(_sqrtm(A)), True),
    "expm": (matfun.expm, sla.expm, False),
    "logm": (matfun.logm, lambda A: np.real(sla.logm(A)), True),
}

SCALAR = {"sqrtm": np.sqrt, "invsqrtm": lambda w: w**-0.5, "expm": np.exp, "logm": np.log}


# Jitted derivatives, compiled once per function for the whole module (eager jacfwd retraces
# op by op and costs seconds on a small machine).
JACFWD = {name: jax.jit(jax.jacfwd(f)) for name, (f, _, _) in FUNCS.items()}
JACREV = {name: jax.jit(jax.jacrev(f)) for name, (f, _, _) in FUNCS.items()}
_eigvals = lambda X: matfun.eigh(X)[0]  # noqa: E731
EIG_JACFWD = jax.jit(jax.jacfwd(_eigvals))
EIG_JACREV = jax.jit(jax.jacrev(_eigvals))
EIGVEC_JACFWD = jax.jit(jax.jacfwd(lambda X: matfun.eigh(X)[1]))
EIGH_JVP = jax.jit(lambda A, E: jax.jvp(matfun.eigh, (A,), (E,)))


def _np_spectral(name):
    """A plain-numpy reference f(A) = V f(λ) Vᵀ, used for the many central-difference
    evaluations (scipy's logm is too slow for that; values are checked against scipy)."""
    g = SCALAR[name]

    def f(A):
        w, V = np.linalg.eigh(_sym(A))
        return (V * g(w)) @ V.T

    return f


def _matrix(gen, kind, pd):
    """An SPD matrix of the given kind; for functions of any symmetric matrix, a general one
    is a random symmetric (indefinite) matrix and the others are shifted to straddle 0."""
    if pd:
        return gen.spd(kind, lo=0.3, hi=2.0)
    if kind == "general":
        return gen.symmetric()
    return gen.spd(kind, lo=0.3, hi=2.0) - 1.0 * np.eye(3)


def _fd_jacobian(f, A, h):
    """J[i, j, k, l] = ∂f(A)ᵢⱼ/∂Aₖₗ by central differences along sym(eₖ eₗᵀ).

    The spdslam functions apply sym() to their argument, so their derivative with respect to
    the entry Aₖₗ is the derivative along the symmetric direction sym(eₖ eₗᵀ).
    """
    J = np.zeros(np.shape(f(A)) + (3, 3))
    for k in range(3):
        for l in range(3):
            E = np.zeros((3, 3))
            E[k, l] = 1.0
            E = _sym(E)
            J[..., k, l] = (f(A + h * E) - f(A - h * E)) / (2 * h)
    return J


def _step(A):
    w = np.abs(np.linalg.eigvalsh(A))
    return 1e-4 * max(np.min(w[w > 0]) if np.any(w > 0) else 1.0, 1e-2)


# --- values ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(FUNCS))
@pytest.mark.parametrize("kind", KINDS)
def test_values_match_scipy(gen, name, kind):
    f, ref, pd = FUNCS[name]
    for _ in range(5):
        A = _matrix(gen, kind, pd)
        got = np.asarray(f(A))
        want = ref(A)
        np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-11 * np.abs(want).max())
        np.testing.assert_allclose(got, got.T, rtol=0, atol=1e-14 * np.abs(got).max())


def test_expm_of_indefinite_and_large_matrices(gen):
    for scale in (0.1, 1.0, 5.0, 15.0):
        S = gen.symmetric(scale)
        want = sla.expm(S)
        np.testing.assert_allclose(np.asarray(matfun.expm(S)), want, rtol=1e-9, atol=1e-12 * np.abs(want).max())


@pytest.mark.parametrize("p", [0.5, -0.5, 2.0, 1.0 / 3.0, -1.7])
def test_powm_matches_scipy(gen, p):
    for kind in KINDS:
        A = gen.spd(kind, lo=0.3, hi=2.0)
        want = np.real(sla.fractional_matrix_power(A, p))
        np.testing.assert_allclose(np.asarray(matfun.powm(A, p)), want, rtol=1e-9, atol=1e-12)


def test_inverse_pairs(gen):
    for kind in KINDS:
        P = gen.spd(kind)
        S = gen.symmetric(2.0)
        np.testing.assert_allclose(np.asarray(matfun.expm(matfun.logm(P))), P, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(np.asarray(matfun.logm(matfun.expm(S))), S, rtol=1e-9, atol=1e-10)
        Ph = np.asarray(matfun.sqrtm(P))
        np.testing.assert_allclose(Ph @ Ph, P, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(Ph @ np.asarray(matfun.invsqrtm(P)), np.eye(3), atol=1e-10)
        # principal root: positive definite
        assert np.linalg.eigvalsh(Ph).min() > 0


def test_sym():
    A = np.arange(9.0).reshape(3, 3)
    np.testing.assert_array_equal(np.asarray(matfun.sym(A)), (A + A.T) / 2)
    B = np.stack([A, 2 * A])
    np.testing.assert_array_equal(np.asarray(matfun.sym(B)), (B + B.transpose(0, 2, 1)) / 2)


def test_symmetrises_its_input(gen):
    """f(A) is f(sym(A)): the functions are defined on symmetric matrices."""
    P = gen.spd()
    N = gen.rng.normal(size=(3, 3)) * 1e-3
    N = N - N.T
    for name, (f, ref, pd) in FUNCS.items():
        np.testing.assert_allclose(np.asarray(f(P + N)), ref(P), rtol=1e-10, atol=1e-12)


# --- derivatives ----------------------------------------------------------------------


@pytest.mark.parametrize("name", list(FUNCS))
@pytest.mark.parametrize("kind", KINDS)
def test_jacobian_matches_central_difference(gen, name, kind):
    f, ref, pd = FUNCS[name]
    A = _matrix(gen, kind, pd)
    np.testing.assert_allclose(_np_spectral(name)(A), ref(A), rtol=1e-10, atol=1e-12)
    J_fd = _fd_jacobian(_np_spectral(name), A, _step(A))
    J_fwd = np.asarray(JACFWD[name](jnp.asarray(A)))
    J_rev = np.asarray(JACREV[name](jnp.asarray(A)))
    scale = np.abs(J_fd).max()
    assert np.all(np.isfinite(J_fwd)) and np.all(np.isfinite(J_rev))
    np.testing.assert_allclose(J_fwd, J_fd, atol=1e-6 * scale)
    np.testing.assert_allclose(J_rev, J_fwd, atol=1e-12 * scale)


@pytest.mark.parametrize("name", list(FUNCS))
def test_derivative_at_scaled_identity_is_scalar(gen, name):
    """At A = c·I, Df(A)[E] = f'(c) E exactly (all divided differences are f'(c))."""
    f, _, _ = FUNCS[name]
    fprime = {
        "sqrtm": lambda c: 0.5 / np.sqrt(c),
        "invsqrtm": lambda c: -0.5 * c**-1.5,
        "expm": np.exp,
        "logm": lambda c: 1.0 / c,
    }[name]
    for c in (1.0, gen.rng.uniform(0.1, 5.0)):
        E = gen.symmetric()
        _, dF = jax.jvp(f, (c * jnp.eye(3),), (jnp.asarray(E),))
        np.testing.assert_allclose(np.asarray(dF), fprime(c) * E, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("name", list(FUNCS))
@pytest.mark.parametrize("gap", [1e-12, 1e-10, 1e-8, 1e-6])
def test_jacobian_near_ties(gen, name, gap):
    """Eigenvalue gaps on both sides of the tie tolerance: continuous and correct."""
    f, ref, _ = FUNCS[name]
    R = gen.rotation()
    A = gen.spd_from(R, np.array([1.3, 1.3 * (1 + gap), 0.7]))
    J_fd = _fd_jacobian(_np_spectral(name), A, 1e-5)
    J = np.asarray(JACFWD[name](jnp.asarray(A)))
    assert np.all(np.isfinite(J))
    np.testing.assert_allclose(J, J_fd, atol=1e-6 * np.abs(J_fd).max())


def test_gradient_of_scalar_loss_finite_at_sphere(gen):
    """Reverse mode through a typical loss (as the solver uses) at exact spheres."""

    def loss(P):
        L = matfun.logm(P)
        return jnp.sum(L * L) + jnp.sum(matfun.sqrtm(P)) + jnp.trace(matfun.invsqrtm(P))

    grad = jax.jit(jax.grad(loss))
    for c in (1.0, 2.5):
        P = c * jnp.eye(3)
        g = np.asarray(grad(P))
        assert np.all(np.isfinite(g))
        # analytic: d/dP [ ||log P||² + Σ sqrt(P)ᵢⱼ + tr P^-½ ] at c I
        ones = np.ones((3, 3))
        want = 2 * np.log(c) / c * np.eye(3) + 0.5 / np.sqrt(c) * ones - 0.5 * c**-1.5 * np.eye(3)
        np.testing.assert_allclose(g, want, rtol=1e-10, atol=1e-12)


# --- eigh -----------------------------------------------------------------------------


@pytest.mark.parametrize("kind", KINDS)
def test_eigh_decomposition(gen, kind):
    A = gen.spd(kind)
    w, V = (np.asarray(x) for x in matfun.eigh(A))
    np.testing.assert_allclose(w, np.linalg.eigvalsh(A), rtol=1e-12, atol=1e-14)
    assert np.all(np.diff(w) >= 0), "ascending"
    np.testing.assert_allclose(V.T @ V, np.eye(3), atol=1e-12)
    np.testing.assert_allclose((V * w) @ V.T, A, atol=1e-12 * np.abs(A).max())


def _double_ties(gen):
    R = gen.rotation()
    c, d = gen.rng.uniform(0.5, 3.0, size=2)
    return {
        "diag_double_low": np.diag([c, c, c + 1.0]),
        "diag_double_high": np.diag([c, d + c, d + c]),
        "spheroid_oblate": gen.spd_from(R, np.array([c, c, c + d])),
        "spheroid_prolate": gen.spd_from(R, np.array([c + d, c + d, c])),
        "indefinite_tie": gen.spd_from(R, np.array([-c, -c, d])),
    }


def test_eigh_eigenvalue_jacobian_at_double_ties_equals_central_difference(gen):
    """At a double tie λ ± h·(μ₁, μ₂) the central difference is (μ₁ + μ₂)/2 for both tied
    eigenvalues, the mean derivative of the tie; the Jacobian must equal it."""
    for name, A in _double_ties(gen).items():
        Jw = np.asarray(EIG_JACFWD(jnp.asarray(A)))
        Jw_rev = np.asarray(EIG_JACREV(jnp.asarray(A)))
        JV = np.asarray(EIGVEC_JACFWD(jnp.asarray(A)))
        assert np.all(np.isfinite(Jw)) and np.all(np.isfinite(JV)), name
        # At a tie the second-order terms of the two tied eigenvalues swap between +h and
        # −h, so the central difference is only O(h) accurate there: small h, loose atol.
        h = 1e-7
        J_fd = _fd_jacobian(np.linalg.eigvalsh, A, h)
        np.testing.assert_allclose(Jw, J_fd, atol=1e-6, err_msg=name)
        np.testing.assert_allclose(Jw_rev, Jw, atol=1e-12, err_msg=name)
        # Along random symmetric directions too (not only the coordinate ones).
        for _ in range(3):
            E = gen.symmetric()
            _, (dw, _) = EIGH_JVP(jnp.asarray(A), jnp.asarray(E))
            fd = (np.linalg.eigvalsh(A + h * E) - np.linalg.eigvalsh(A - h * E)) / (2 * h)
            np.testing.assert_allclose(np.asarray(dw), fd, atol=1e-6, err_msg=name)
            # ... and it is the mean of the one-sided derivatives of the tied pair, which
            # differ from each other (the split of the tie) for a generic E.
            w0 = np.linalg.eigvalsh(A)
            i = int(np.argmin(np.diff(w0)))
            one_sided = (np.linalg.eigvalsh(A + h * E) - w0) / h
            assert abs(one_sided[i] - one_sided[i + 1]) > 1e-3
            np.testing.assert_allclose(
                np.asarray(dw)[i : i + 2], np.full(2, one_sided[i : i + 2].mean()), atol=1e-6
            )


@pytest.mark.parametrize("c", [1.0, 0.37, 4.2])
def test_eigh_eigenvalue_jacobian_at_triple_tie(gen, c):
    """At c·I the eigenvalues of c·I ± hE are c ± h·μ(E): the central difference of the k-th
    one is (μₖ + μ₄₋ₖ)/2, not linear in E, so no Jacobian reproduces it in every direction.
    What must hold: (a) its mean over the tie, tr(E)/3, equals every Jacobian entry, and
    (b) in directions whose μ are symmetric about their mean, the central difference is the
    mean itself and equals the Jacobian exactly."""
    A = c * np.eye(3)
    Jw = np.asarray(EIG_JACFWD(jnp.asarray(A)))
    Jw_rev = np.asarray(EIG_JACREV(jnp.asarray(A)))
    assert np.all(np.isfinite(Jw)) and np.all(np.isfinite(Jw_rev))
    J_fd = _fd_jacobian(np.linalg.eigvalsh, A, 1e-5)
    np.testing.assert_allclose(Jw, np.broadcast_to(J_fd.mean(axis=0), Jw.shape), atol=1e-8)
    np.testing.assert_allclose(Jw_rev, Jw, atol=1e-12)
    h = 1e-6
    for _ in range(3):
        m, d = gen.rng.normal(size=2)
        E = gen.spd_from(gen.rotation(), np.array([m - d, m, m + d]))
        _, (dw, _) = EIGH_JVP(jnp.asarray(A), jnp.asarray(E))
        fd = (np.linalg.eigvalsh(A + h * E) - np.linalg.eigvalsh(A - h * E)) / (2 * h)
        np.testing.assert_allclose(fd, np.full(3, m), atol=1e-8)  # the premise
        np.testing.assert_allclose(np.asarray(dw), fd, atol=1e-8)


def test_eigh_tie_derivative_is_mean_of_block(gen):
    """Hand-computed: at c·I the tied eigenvalues all move by tr(E)/3."""
    E = gen.symmetric()
    _, (dw, _) = EIGH_JVP(2.0 * jnp.eye(3), jnp.asarray(E))
    np.testing.assert_allclose(np.asarray(dw), np.full(3, np.trace(E) / 3), atol=1e-14)


def test_eigh_jacobian_distinct_eigenvalues(gen):
    A = gen.spd("general")
    E = gen.symmetric()
    (w, V), (dw, dV) = EIGH_JVP(jnp.asarray(A), jnp.asarray(E))
    h = 1e-6
    wp, Vp = np.linalg.eigh(A + h * E)
    wm, Vm = np.linalg.eigh(A - h * E)
    V = np.asarray(V)
    # eigenvectors are defined up to sign: align with V
    Vp = Vp * np.sign(np.sum(Vp * V, axis=0))
    Vm = Vm * np.sign(np.sum(Vm * V, axis=0))
    gaps = np.min(np.abs(np.diff(np.asarray(w))))
    np.testing.assert_allclose(np.asarray(dw), (wp - wm) / (2 * h), atol=1e-7)
    np.testing.assert_allclose(np.asarray(dV), (Vp - Vm) / (2 * h), atol=1e-6 / min(gaps, 1.0))


# --- numpy / JAX / batch / vmap / jit -------------------------------------------------


@pytest.mark.parametrize("name", list(FUNCS))
def test_batch_vmap_jit_and_input_types(gen, name):
    f, ref, pd = FUNCS[name]
    As = np.stack([_matrix(gen, k, pd) for k in KINDS])
    want = np.stack([ref(A) for A in As])
    for out in (
        f(As),  # numpy, batched (leading axis)
        f(jnp.asarray(As)),
        jax.vmap(f)(jnp.asarray(As)),
        jax.jit(jax.vmap(f))(As),
        np.stack([f(A) for A in As]),
        np.stack([f(A.tolist()) for A in As]),
    ):
        np.testing.assert_allclose(np.asarray(out), want, rtol=1e-10, atol=1e-11)
    # nested batch axes
    np.testing.assert_allclose(
        np.asarray(f(As.reshape(1, 5, 3, 3))), want.reshape(1, 5, 3, 3), rtol=1e-10, atol=1e-11
    )
    # derivatives under vmap and jit
    J = jax.jit(jax.vmap(jax.jacfwd(f)))(As)
    assert J.shape == (5, 3, 3, 3, 3) and np.all(np.isfinite(np.asarray(J)))
    np.testing.assert_allclose(np.asarray(J[1]), np.asarray(JACFWD[name](As[1])), atol=1e-12)


def test_eigh_batched(gen):
    As = np.stack([gen.spd(k) for k in KINDS])
    w, V = matfun.eigh(As)
    np.testing.assert_allclose(np.asarray(w), np.linalg.eigvalsh(As), rtol=1e-12, atol=1e-14)
    wv, _ = jax.vmap(matfun.eigh)(jnp.asarray(As))
    np.testing.assert_allclose(np.asarray(wv), np.asarray(w), atol=1e-14)
    Jw = jax.jit(jax.vmap(EIG_JACFWD))(jnp.asarray(As))
    assert np.all(np.isfinite(np.asarray(Jw)))
