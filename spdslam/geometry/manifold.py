"""Variable types the solver can optimise, and their manifold operations.

Every optimisation variable is a JAX pytree of one registered type. For each type we know

- ``tangent_dim``: the dimension of its tangent space;
- ``retract(x, delta)``: x ⊞ delta, a point of the manifold for a tangent vector ``delta``;
- ``local(x, y)``: y ⊟ x, the tangent vector with ``retract(x, local(x, y)) == y``;
- ``regularize(x)``: an optional projection applied by the solver after every accepted step
  (identity for true manifolds; the QuadricSLAM "constrain" for the Full quadric);
- ``blocks``: the split of the tangent coordinates into consecutive blocks in which the
  metric is isotropic (default: one block), e.g. (3, 3) for SE3's (v, ω); the solver's
  isotropic damping scales each block by its own curvature;
- ``host_retract(xs, deltas)``: optionally, ``retract`` of stacked rows in NumPy (leaves
  and deltas (rows, …)), equal to it to round-off: the solver then steps that type without
  a compiled program (``solver.closed_forms``);
- ``host_pushforward(xs)``: optionally, ∂(x ⊞ δ)/∂δ|₀ of stacked rows in NumPy, the images of
  the tangent basis vectors as a pytree of leaves (rows, dim, …) (``solver``'s
  ``pushforward``), equal to it to round-off.

The functions act on one element; the solver vmaps them over all variables of a type.
``jaxlie.SE3`` (camera-to-world poses ``T_wc``) is registered here with jaxlie's right
perturbation ``T ⊞ δ = T · exp(δ)``, δ = (v, ω) in jaxlie's order (translation first).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from .se3 import compose_params, exp_params

__all__ = [
    "ManifoldOps",
    "register",
    "ops",
    "tangent_dim",
    "retract",
    "local",
    "regularize",
    "is_registered",
]


@dataclass(frozen=True)
class ManifoldOps:
    tangent_dim: int
    retract: Callable[[Any, jax.Array], Any]
    local: Callable[[Any, Any], jax.Array]
    regularize: Callable[[Any], Any] | None = None
    blocks: tuple[int, ...] = ()
    host_retract: Callable[[Any, Any], Any] | None = None
    host_pushforward: Callable[[Any], Any] | None = None


_REGISTRY: dict[type, ManifoldOps] = {}


def register(
    cls: type,
    *,
    tangent_dim: int,
    retract: Callable,
    local: Callable,
    regularize: Callable | None = None,
    blocks: tuple[int, ...] | None = None,
    host_retract: Callable | None = None,
    host_pushforward: Callable | None = None,
) -> None:
    """Register a pytree class as an optimisation variable type."""
    blocks = (int(tangent_dim),) if blocks is None else tuple(int(b) for b in blocks)
    if sum(blocks) != tangent_dim or min(blocks, default=1) < 1:
        raise ValueError(f"blocks {blocks} must be positive and sum to tangent_dim {tangent_dim}")
    _REGISTRY[cls] = ManifoldOps(tangent_dim, retract, local, regularize, blocks, host_retract, host_pushforward)


def is_registered(cls: type) -> bool:
    return cls in _REGISTRY


def ops(x_or_cls: Any) -> ManifoldOps:
    cls = x_or_cls if isinstance(x_or_cls, type) else type(x_or_cls)
    try:
        return _REGISTRY[cls]
    except KeyError:
        known = ", ".join(sorted(c.__name__ for c in _REGISTRY))
        raise TypeError(
            f"{cls.__name__} is not an optimisation variable type (known: {known})"
        ) from None


def tangent_dim(x_or_cls: Any) -> int:
    return ops(x_or_cls).tangent_dim


def retract(x: Any, delta: jax.Array) -> Any:
    """x ⊞ delta."""
    return ops(x).retract(x, jnp.asarray(delta))


def local(x: Any, y: Any) -> jax.Array:
    """y ⊟ x, so that retract(x, local(x, y)) == y."""
    return ops(x).local(x, y)


def regularize(x: Any) -> Any:
    """Project x back to the feasible set after a step (identity unless registered)."""
    reg = ops(x).regularize
    return x if reg is None else reg(x)


def _se3_host_retract(T, d):
    """T · Exp(δ) of stacked poses in NumPy (``se3.compose_params``, ``se3.exp_params``)."""
    return jaxlie.SE3(compose_params(np.asarray(T.wxyz_xyz), exp_params(d)))  # type: ignore[arg-type]


register(
    jaxlie.SE3,
    tangent_dim=6,
    blocks=(3, 3),
    retract=lambda T, d: jaxlie.manifold.rplus(T, d),
    local=lambda T, U: jaxlie.manifold.rminus(T, U),
    host_retract=_se3_host_retract,
)
register(
    jaxlie.SO3,
    tangent_dim=3,
    retract=lambda R, d: jaxlie.manifold.rplus(R, d),
    local=lambda R, U: jaxlie.manifold.rminus(R, U),
)
