"""Functions of symmetric matrices with derivatives that stay finite at repeated eigenvalues.

For a symmetric A = V diag(λ) Vᵀ and a scalar function f, the spectral function is
f(A) = V diag(f(λ)) Vᵀ. Autodiff through ``eigh`` divides by λᵢ − λⱼ and returns NaN at
repeated eigenvalues (spheres, the identity). Here the derivative is given in closed form
by the Daleckii-Krein formula

    Df(A)[E] = V (F ∘ (Vᵀ E V)) Vᵀ,   Fᵢⱼ = (f(λᵢ) − f(λⱼ)) / (λᵢ − λⱼ),  Fᵢᵢ = f'(λᵢ),

with Fᵢⱼ = f'((λᵢ+λⱼ)/2) when λᵢ ≈ λⱼ: the divided difference is smooth, so this is exact
at ties and continuous around them.

``eigh`` itself gets a derivative that is finite at ties too: eigenvalues that coincide
get the mean of their first-order changes, and the coupling of eigenvectors inside a tie is
dropped (they are not unique there). Sorted eigenvalues are not differentiable at a tie;
at a double tie this mean is exactly what a central difference measures. At a triple tie
(c·I) the central difference of the k-th eigenvalue is (μₖ + μ₄₋ₖ)/2 for the eigenvalues
μ of the perturbation, which is not linear in it, so no derivative can match it in every
direction: the mean agrees with it for perturbations whose eigenvalues are symmetric.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp

__all__ = [
    "sym",
    "eigh",
    "spectral",
    "sqrtm",
    "invsqrtm",
    "expm",
    "logm",
    "powm",
    "TIE_RTOL",
]

#: Relative tolerance under which two eigenvalues count as equal.
TIE_RTOL = 1e-9


def sym(A):
    """(A + Aᵀ)/2 over the last two axes."""
    A = jnp.asarray(A)
    return 0.5 * (A + jnp.swapaxes(A, -1, -2))


def _ties(w):
    scale = jnp.maximum(jnp.max(jnp.abs(w)), 1e-300)
    return jnp.abs(w[:, None] - w[None, :]) <= TIE_RTOL * scale


@jax.custom_jvp
def _eigh(A):
    return jnp.linalg.eigh(A)


@_eigh.defjvp
def _eigh_jvp(primals, tangents):
    (A,), (dA,) = primals, tangents
    w, V = _eigh(A)
    E = V.T @ sym(dA) @ V
    tie = _ties(w)
    tief = tie.astype(w.dtype)
    dw = (tief @ jnp.diag(E)) / jnp.sum(tief, axis=1)
    gap = w[None, :] - w[:, None]
    F = jnp.where(tie, 0.0, 1.0 / jnp.where(tie, 1.0, gap))
    dV = V @ (F * E)
    return (w, V), (dw, dV)


def eigh(A):
    """Eigen-decomposition of a symmetric matrix, ascending, with a tie-safe derivative."""
    A = sym(A)
    if A.ndim > 2:
        return jax.vmap(eigh)(A)
    return _eigh(A)


def spectral(f, fprime):
    """Build A ↦ f(A) for symmetric A, differentiable everywhere (Daleckii-Krein)."""

    @jax.custom_jvp
    def fun(A):
        w, V = jnp.linalg.eigh(A)
        return (V * f(w)) @ V.T

    @fun.defjvp
    def fun_jvp(primals, tangents):
        (A,), (dA,) = primals, tangents
        w, V = jnp.linalg.eigh(A)
        fw = f(w)
        wi, wj = w[:, None], w[None, :]
        tie = _ties(w)
        den = jnp.where(tie, 1.0, wi - wj)
        F = jnp.where(tie, fprime(0.5 * (wi + wj)), (fw[:, None] - fw[None, :]) / den)
        E = V.T @ sym(dA) @ V
        return (V * fw) @ V.T, V @ (F * E) @ V.T

    def apply(A):
        A = sym(A)
        if A.ndim > 2:
            return jax.vmap(apply)(A)
        return fun(A)

    return apply


def _safe_pos(w):
    # Spectral functions below are defined for positive definite input; clamp so that a
    # rounding-level negative eigenvalue cannot produce a NaN.
    return jnp.maximum(w, 1e-300)


sqrtm = spectral(lambda w: jnp.sqrt(_safe_pos(w)), lambda w: 0.5 / jnp.sqrt(_safe_pos(w)))
sqrtm.__doc__ = "Principal square root A^½ of an SPD matrix."
invsqrtm = spectral(
    lambda w: 1.0 / jnp.sqrt(_safe_pos(w)), lambda w: -0.5 * _safe_pos(w) ** -1.5
)
invsqrtm.__doc__ = "Inverse square root A^-½ of an SPD matrix."
expm = spectral(jnp.exp, jnp.exp)
expm.__doc__ = "Matrix exponential of a symmetric matrix."
logm = spectral(lambda w: jnp.log(_safe_pos(w)), lambda w: 1.0 / _safe_pos(w))
logm.__doc__ = "Principal logarithm of an SPD matrix."


@partial(jax.jit, static_argnums=1)
def powm(A, p: float):
    """A^p for SPD A (p a Python float)."""
    return spectral(lambda w: _safe_pos(w) ** p, lambda w: p * _safe_pos(w) ** (p - 1.0))(A)
