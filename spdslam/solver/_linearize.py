"""The per-factor terms both drivers linearise with, written once.

For a factor with residual r(x₁, …, x_k, data), square-root information W and robust kernel
ρ, at s = ‖W r‖²:

    r̃ = √ρ'(s) W r,   J̃ = √ρ'(s) W ∂r(x ⊞ δ)/∂δ|₀,   cost term ½ρ(s)

(iteratively reweighted least squares; ρ(s) = s without a kernel), plus whether r and J are
finite and the factor's validity at x. Both layouts (``_problem``, ``_batched_layout``)
differentiate by the chain rule

    ∂r(x ⊞ δ)/∂δ|₀ = ∂r/∂x · ∂(x ⊞ δ)/∂δ|₀,

the pushforward ∂(x ⊞ δ)/∂δ|₀ of the tangent basis (``pushforward``) being computed once per
variable, not once per factor (for an ellipsoid it costs two eigendecompositions), and pushed
through the residual with ``jax.jvp`` (``jvp_jacobian``). Both whiten, weight and check
through these functions, and both retract with ``retract_rows``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..factors import robust_weighting
from ..geometry import manifold

__all__ = ["whitened", "finish", "retract_rows", "violates", "pushforward", "differentiable",
           "tangent_directions", "jvp_jacobian"]


def whitened(residual, W, xs, args):
    """W r(*xs, *args) as a flat vector (W None: identity)."""
    r = jnp.ravel(jnp.atleast_1d(residual(*xs, *args)))
    return r if W is None else W @ r


def finish(spec, r, J, xs, args):
    """(r̃, J̃, ½ρ(s), valid, finite) from the whitened r and J (J None: cost only);
    ``valid`` is None when the factor type has no validity rule."""
    finite = jnp.all(jnp.isfinite(r))
    if J is not None:
        finite &= jnp.all(jnp.isfinite(J))
    half_rho, r, J = robust_weighting(spec.robust, r, J)
    valid = jnp.asarray(spec.valid(*xs, *args), bool) if spec.valid is not None else None
    return r, J, half_rho, valid, finite


def retract_rows(cls, x, d):
    """regularize(x ⊞ δ) for every row of a stacked pytree x of type ``cls`` (δ: rows × dim)."""
    op = manifold.ops(cls)
    y = jax.vmap(op.retract)(x, d)
    if op.regularize is not None:
        y = jax.vmap(op.regularize)(y)
    return y


def differentiable(x) -> bool:
    """Whether every leaf of a variable is floating point (``pushforward`` applies)."""
    return all(jnp.issubdtype(jnp.result_type(a), jnp.inexact) for a in jax.tree.leaves(x))


def pushforward(cls, x):
    """∂(x ⊞ δ)/∂δ at δ = 0 for every row of a stacked pytree x of type ``cls``: the images
    of the tangent basis vectors eᵢ, as a pytree of leaves (rows, dim, ...)."""
    op = manifold.ops(cls)
    dim = op.tangent_dim
    eye, zero = jnp.eye(dim), jnp.zeros(dim)

    def one(xi):
        f = lambda d: op.retract(xi, d)  # noqa: E731
        return jax.vmap(lambda e: jax.jvp(f, (zero,), (e,))[1])(eye)

    return jax.vmap(one)(x)


def tangent_directions(Ts, dims):
    """The D = Σ dims tangent directions of a factor's variables: per variable p, a pytree
    with leading axis D holding p's pushforward ``Ts[p]`` (dims[p] rows) in its own block of
    rows and zeros elsewhere."""
    D = sum(dims)
    out, o = [], 0
    for T, d in zip(Ts, dims):
        if len(dims) > 1:
            T = jax.tree.map(
                lambda a, o=o, d=d: jnp.concatenate(
                    [jnp.zeros((o,) + a.shape[1:], a.dtype), a,
                     jnp.zeros((D - o - d,) + a.shape[1:], a.dtype)]), T)
        out.append(T)
        o += d
    return out


def jvp_jacobian(res, primals, directions):
    """(res(*primals), its Jacobian along ``directions`` (m, D)): one ``jax.jvp`` per
    direction, vmapped (``tangent_directions``)."""
    r, Jt = jax.vmap(lambda *t: jax.jvp(res, primals, t), out_axes=(None, 0))(*directions)
    return r, Jt.T


def violates(valid_cur, valid_new, axis=None):
    """True where a factor valid in ``valid_cur`` is invalid in ``valid_new`` (per group,
    None for groups without validity); reduced over ``axis`` (None: everything)."""
    bad = False
    for vc, vn in zip(valid_cur, valid_new):
        if vc is not None:
            bad = bad | jnp.any(vc & ~vn, axis=axis)
    return jnp.asarray(bad)
