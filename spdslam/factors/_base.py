"""The factor container, noise models and robust kernels.

A factor is a plain residual function of variable values and measurement data,

    r = residual(*variables, *args)  ∈ R^m,

plus a noise model and an optional robust kernel. Its contribution to the cost is
½ ρ(‖W r‖²), with W the square-root information matrix (WᵀW = Σ⁻¹) and ρ the kernel
(ρ(s) = s without one). Grouping factors of the same type and vectorising them is the
solver's job: factors whose residual function, variable types and data shapes agree are
stacked and linearised with one vmapped call.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Hashable

import jax
import jax.numpy as jnp
import numpy as np

from .. import manifold

__all__ = [
    "Factor",
    "tangent_jacobians",
    "robust_weighting",
    "RobustKernel",
    "Huber",
    "Cauchy",
    "sqrt_information",
]


@dataclass(frozen=True)
class RobustKernel:
    """A robust loss ρ(s) of the squared whitened residual norm s = ‖W r‖²."""

    k: float = 1.0

    def rho(self, s):  # pragma: no cover - abstract
        raise NotImplementedError

    def weight(self, s):
        """ρ'(s): the iteratively-reweighted-least-squares weight."""
        raise NotImplementedError  # pragma: no cover


@dataclass(frozen=True)
class Huber(RobustKernel):
    """ρ(s) = s for √s ≤ k, 2k√s − k² beyond."""

    def rho(self, s):
        r = jnp.sqrt(jnp.maximum(s, 1e-300))
        return jnp.where(r <= self.k, s, 2.0 * self.k * r - self.k**2)

    def weight(self, s):
        r = jnp.sqrt(jnp.maximum(s, 1e-300))
        return jnp.where(r <= self.k, 1.0, self.k / r)


@dataclass(frozen=True)
class Cauchy(RobustKernel):
    """ρ(s) = k² log(1 + s/k²)."""

    def rho(self, s):
        return self.k**2 * jnp.log1p(s / self.k**2)

    def weight(self, s):
        return 1.0 / (1.0 + s / self.k**2)


def robust_weighting(robust: RobustKernel | None, r, J=None):
    """(½ρ(s), √ρ'(s)·r, √ρ'(s)·J) for s = ‖r‖²: the cost term and the iteratively
    reweighted residual and Jacobian; (½s, r, J) without a kernel."""
    s = jnp.sum(r * r)
    if robust is None:
        return 0.5 * s, r, J
    sw = jnp.sqrt(robust.weight(s))
    return 0.5 * robust.rho(s), sw * r, (None if J is None else sw * J)


def sqrt_information(
    dim: int,
    sigma: Any = None,
    information: Any = None,
    covariance: Any = None,
) -> np.ndarray:
    """Square-root information W (dim×dim, upper triangular) with WᵀW = Σ⁻¹.

    Exactly one of ``sigma`` (scalar or per-component standard deviations),
    ``information`` (Σ⁻¹) or ``covariance`` (Σ) may be given; none means W = I.
    """
    given = [x is not None for x in (sigma, information, covariance)]
    if sum(given) > 1:
        raise ValueError("give at most one of sigma, information, covariance")
    if sigma is not None:
        s = np.broadcast_to(np.asarray(sigma, dtype=float), (dim,))
        if not np.all(np.isfinite(s)) or np.any(s <= 0):
            raise ValueError(f"sigma must be finite and positive, got {sigma!r}")
        return np.diag(1.0 / s)
    if covariance is not None:
        cov = np.asarray(covariance, dtype=float)
        if cov.shape != (dim, dim):
            raise ValueError(f"covariance must be {dim}x{dim}, got {cov.shape}")
        information = np.linalg.inv(cov)
    if information is not None:
        info = np.asarray(information, dtype=float)
        if info.shape != (dim, dim):
            raise ValueError(f"information must be {dim}x{dim}, got {info.shape}")
        info = 0.5 * (info + info.T)
        try:
            L = np.linalg.cholesky(info)
        except np.linalg.LinAlgError:
            raise ValueError("information matrix is not positive definite") from None
        return L.T
    return np.eye(dim)


@dataclass(frozen=True, eq=False)
class Factor:
    """One residual term of a factor graph.

    residual:  ``residual(*variables, *args) -> (m,)``, a JAX-traceable function of the
               values of ``keys`` (in order) and of the measurement data ``args``.
    keys:      the variable keys this factor connects.
    args:      measurement data: a tuple of arrays (or pytrees of arrays).
    sqrt_info: W, the (m, m) square-root information matrix; None means identity.
    robust:    optional robust kernel on ‖W r‖².
    valid:     optional ``valid(*variables, *args) -> bool``: False marks degenerate
               geometry (object behind the camera, camera inside the object). The solver
               rejects any step that makes a valid factor invalid.
    """

    residual: Callable[..., Any]
    keys: tuple[Hashable, ...]
    args: tuple = ()
    sqrt_info: Any = None
    robust: RobustKernel | None = None
    valid: Callable[..., Any] | None = None
    name: str = field(default="")

    def __post_init__(self):
        object.__setattr__(self, "keys", tuple(self.keys))
        object.__setattr__(self, "args", tuple(self.args))
        if self.sqrt_info is not None:
            object.__setattr__(self, "sqrt_info", np.asarray(self.sqrt_info, dtype=float))

    @property
    def kind(self) -> str:
        return self.name or getattr(self.residual, "__name__", "factor")

    def evaluate(self, *values):
        """Whitened residual W r at the given variable values (no robust kernel)."""
        r = jnp.atleast_1d(self.residual(*values, *self.args))
        if self.sqrt_info is None:
            return r
        return jnp.asarray(self.sqrt_info) @ r

    def error(self, *values) -> float:
        """½ ρ(‖W r‖²), this factor's contribution to the cost."""
        s = jnp.sum(self.evaluate(*values) ** 2)
        if self.robust is not None:
            s = self.robust.rho(s)
        return 0.5 * float(s)


def tangent_jacobians(residual: Callable, values: tuple, args: tuple = ()):
    """r and the Jacobians ∂r(x₁ ⊞ δ₁, …)/∂δₖ at δ = 0, one (m, dₖ) block per variable.

    Derivatives are with respect to each variable's tangent coordinates (its registered
    retraction), evaluated by forward-mode autodiff.
    """
    values = tuple(values)
    dims = [manifold.tangent_dim(v) for v in values]

    def perturbed(*deltas):
        xs = [manifold.retract(v, d) for v, d in zip(values, deltas)]
        return jnp.atleast_1d(residual(*xs, *args))

    zeros = tuple(jnp.zeros(d) for d in dims)
    r = perturbed(*zeros)
    J = jax.jacfwd(perturbed, argnums=tuple(range(len(values))))(*zeros)
    return r, list(J)
