"""The per-factor terms both drivers linearise with, written once.

For a factor with residual r(x₁, …, x_k, data), square-root information W and robust kernel
ρ, at s = ‖W r‖²:

    r̃ = √ρ'(s) W r,   J̃ = √ρ'(s) W ∂r(x ⊞ δ)/∂δ|₀,   cost term ½ρ(s)

(iteratively reweighted least squares; ρ(s) = s without a kernel), plus whether r and J are
finite and the factor's validity at x. The host layout (``_problem``) differentiates with
``jax.jacfwd`` per factor, the batched layout (``_batched_layout``) with pushforwards computed once
per variable; both whiten, weight and check through these functions, and both retract with
``retract_rows``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..factors import robust_weighting
from ..geometry import manifold

__all__ = ["whitened", "finish", "retract_rows", "violates"]


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


def violates(valid_cur, valid_new, axis=None):
    """True where a factor valid in ``valid_cur`` is invalid in ``valid_new`` (per group,
    None for groups without validity); reduced over ``axis`` (None: everything)."""
    bad = False
    for vc, vn in zip(valid_cur, valid_new):
        if vc is not None:
            bad = bad | jnp.any(vc & ~vn, axis=axis)
    return jnp.asarray(bad)
