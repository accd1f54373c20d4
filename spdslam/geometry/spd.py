"""The manifold SPD(3) of symmetric positive definite 3×3 matrices.

Metric (affine-invariant):   ⟨A, B⟩_P = tr(P⁻¹ A P⁻¹ B),  A, B symmetric.
Retraction (paper eq. 21):   P ⊞ ξ = P^½ Exp(P^-½ ξ P^-½) P^½   (the Riemannian exponential).
Log map (paper eq. 22):      Q ⊟ P = P^½ Log(P^-½ Q P^-½) P^½.
Geodesic distance:           d(P, Q) = ‖Log(P^-½ Q P^-½)‖_F.

Tangent coordinates. The solver works with 6-vectors c. The symmetric matrices

    E₀ = e₀e₀ᵀ, E₁ = e₁e₁ᵀ, E₂ = e₂e₂ᵀ,  E₃ = (e₀e₁ᵀ+e₁e₀ᵀ)/√2, E₄ = (e₀e₂ᵀ+…)/√2, E₅ = (e₁e₂ᵀ+…)/√2

are Frobenius-orthonormal, so Bₖ = P^½ Eₖ P^½ is an orthonormal basis of T_P SPD(3) under the
affine-invariant metric: ξ = Σ cₖ Bₖ has ⟨ξ, ξ⟩_P = ‖c‖². ``retract_vec``/``local_vec`` use these
coordinates; ``retract``/``local`` take and return symmetric matrices ξ.

All functions broadcast over leading axes. ``distance`` and ``is_spd`` compute in NumPy for
NumPy input (no JAX dispatch: the front end calls them per pair of tracks); the others
compute in JAX and are differentiable at repeated eigenvalues (``matfun``).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ._arrays import array_namespace
from .matfun import expm, invsqrtm, logm, sqrtm, sym

__all__ = [
    "retract",
    "local",
    "exp",
    "log",
    "retract_vec",
    "local_vec",
    "sqrtm",
    "invsqrtm",
    "distance",
    "inner",
    "vec_to_sym",
    "sym_to_vec",
    "BASIS",
    "host_eigh",
    "tangent_basis",
    "is_spd",
]

_S = 2.0**-0.5
_IDX = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))

#: The basis E₀ … E₅ of ``vec_to_sym`` as a NumPy array (6, 3, 3) (the closed forms and the
#: NumPy retraction use it).
BASIS = np.zeros((6, 3, 3))
for _k, (_i, _j) in enumerate(_IDX):
    BASIS[_k, _i, _j] = BASIS[_k, _j, _i] = 1.0 if _i == _j else _S
BASIS.flags.writeable = False


def vec_to_sym(c):
    """6-vector → symmetric matrix Σ cₖ Eₖ (Frobenius-orthonormal basis)."""
    c = jnp.asarray(c)
    a, b, d, e, f, g = (c[..., k] for k in range(6))
    return jnp.stack(
        [
            jnp.stack([a, _S * e, _S * f], -1),
            jnp.stack([_S * e, b, _S * g], -1),
            jnp.stack([_S * f, _S * g, d], -1),
        ],
        -2,
    )


def sym_to_vec(S):
    """Symmetric matrix → its 6 coordinates in the basis Eₖ (inverse of ``vec_to_sym``)."""
    S = sym(S)
    return jnp.stack(
        [S[..., 0, 0], S[..., 1, 1], S[..., 2, 2]]
        + [S[..., i, j] / _S for i, j in _IDX[3:]],
        -1,
    )


def host_eigh(A):
    """(w ascending, V) of stacked symmetric matrices (…, 3, 3) symmetrised, NumPy; NaN rows
    where A is not finite (as a program's result there, where LAPACK would raise)."""
    A = np.asarray(A, dtype=float)
    A = 0.5 * (A + np.swapaxes(A, -1, -2))
    finite = np.all(np.isfinite(A), axis=(-2, -1))
    w, V = np.linalg.eigh(np.where(finite[..., None, None], A, np.eye(3)))
    return np.where(finite[..., None], w, np.nan), np.where(finite[..., None, None], V, np.nan)


def tangent_basis(P):
    """The six tangent vectors Bₖ = P^½ Eₖ P^½ at P, orthonormal under ⟨·,·⟩_P. Shape (6, 3, 3)."""
    Ph = sqrtm(P)
    E = vec_to_sym(jnp.eye(6))
    return Ph @ E @ Ph


def inner(P, A, B):
    """Affine-invariant inner product tr(P⁻¹ A P⁻¹ B)."""
    Pi = jnp.linalg.inv(P)
    return jnp.trace(Pi @ A @ Pi @ B, axis1=-2, axis2=-1)


def retract(P, xi):
    """P ⊞ ξ = P^½ Exp(P^-½ ξ P^-½) P^½ for a symmetric tangent matrix ξ (paper eq. 21)."""
    Ph, Pmh = sqrtm(P), invsqrtm(P)
    return sym(Ph @ expm(Pmh @ sym(xi) @ Pmh) @ Ph)


def local(P, Q):
    """Q ⊟ P = P^½ Log(P^-½ Q P^-½) P^½, the inverse of ``retract`` (paper eq. 22)."""
    Ph, Pmh = sqrtm(P), invsqrtm(P)
    return sym(Ph @ logm(Pmh @ Q @ Pmh) @ Ph)


exp = retract
log = local


def retract_vec(P, c):
    """P ⊞ c = P^½ Exp(Σ cₖ Eₖ) P^½ in orthonormal tangent coordinates c ∈ R⁶."""
    Ph = sqrtm(P)
    return sym(Ph @ expm(vec_to_sym(c)) @ Ph)


def local_vec(P, Q):
    """Coordinates c ∈ R⁶ of Q ⊟ P, the inverse of ``retract_vec``."""
    Pmh = invsqrtm(P)
    return sym_to_vec(logm(Pmh @ Q @ Pmh))


def distance(P, Q):
    """Affine-invariant geodesic distance d(P, Q) = ‖Log(P^-½ Q P^-½)‖_F (paper eq. 22).

    P^-½ Q P^-½ is similar to L⁻¹ Q L⁻ᵀ (P = L Lᵀ, Cholesky), so d = √(Σᵢ log² λᵢ) with λᵢ
    the eigenvalues of that symmetric matrix. NumPy input raises ``ValueError`` when P or Q
    is not symmetric positive definite; in JAX the result is then NaN.
    """
    xp = array_namespace(P, Q)
    if xp is np:
        P, Q = np.asarray(P, dtype=float), np.asarray(Q, dtype=float)
        try:
            L = np.linalg.cholesky(P)
        except np.linalg.LinAlgError:
            raise ValueError("spd.distance: P is not symmetric positive definite") from None
    else:
        L = jnp.linalg.cholesky(P)
    Li = xp.linalg.inv(L)
    S = Li @ Q @ xp.swapaxes(Li, -1, -2)
    lam = xp.linalg.eigvalsh(0.5 * (S + xp.swapaxes(S, -1, -2)))
    if xp is np and np.any(lam <= 0):
        raise ValueError("spd.distance: Q is not symmetric positive definite")
    return xp.sqrt(xp.sum(xp.log(lam) ** 2, axis=-1))


def is_spd(P, rtol: float = 0.0):
    """True where P is symmetric with all eigenvalues > rtol·max|λ|."""
    xp = array_namespace(P)
    P = xp.asarray(P, dtype=float)
    w = xp.linalg.eigvalsh(0.5 * (P + xp.swapaxes(P, -1, -2)))
    scale = xp.max(xp.abs(P), axis=(-2, -1), keepdims=True)
    symmetric = xp.all(xp.abs(P - xp.swapaxes(P, -1, -2)) <= 1e-9 * scale, axis=(-2, -1))
    return symmetric & (w[..., 0] > rtol * xp.max(xp.abs(w), axis=-1))

