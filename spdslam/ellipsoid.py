"""Ellipsoid landmarks in three parameterisations.

An ellipsoid with centre t and shape matrix P ∈ SPD(3) is the set {x : (x−t)ᵀ P⁻¹ (x−t) ≤ 1};
P = R diag(s²) Rᵀ with the semi-axes s along the columns of R. Its dual quadric (tangent
planes π satisfy πᵀ Q* π = 0), normalised to Q*₃₃ = −1, is

    Q* = T diag(P, −1) Tᵀ,  T = [[I, t], [0, 1]]   ⇒   Q* = [[P − ttᵀ, −t], [−tᵀ, −1]].

(The paper prints +t in the off-diagonal blocks; that sign is wrong for t the centre.)

Parameterisations, all registered as optimisation variables:

- ``Ellipsoid`` (SPD): (P, t) ∈ SPD(3) × R³. Tangent (c, δt) ∈ R⁶ × R³:
  P ⊞ c is the affine-invariant exponential (``spd.retract_vec``), t ⊞ δt = t + δt.
- ``EllipsoidRTS`` (Rot-Trans-Scale): (R, t, s) ∈ SO(3) × R³ × R³. Tangent (δθ, δt, δs):
  R·Exp(δθ), t + δt, s + δs (the baseline as gtsam-quadrics updates it).
- ``EllipsoidFull``: the 10 independent entries of Q*, updated additively, and projected
  to the nearest ellipsoid after every step (QuadricSLAM's "constrain").

Axes are always reported sorted s₁ ≥ s₂ ≥ s₃, with a right-handed rotation.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import ClassVar

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from . import manifold, spd
from .matfun import eigh, sym

__all__ = ["Ellipsoid", "EllipsoidRTS", "EllipsoidFull", "as_ellipsoid", "dual_quadric"]

_CORNER_SIGNS = np.array(list(itertools.product((-1.0, 1.0), repeat=3)))[:, ::-1]


def _pytree(cls, fields):
    jax.tree_util.register_dataclass(cls, data_fields=list(fields), meta_fields=[])
    return cls


def _rotation_matrix(rotation):
    if isinstance(rotation, jaxlie.SO3):
        return rotation.as_matrix()
    return jnp.asarray(rotation, dtype=float)


def _sorted_axes(P):
    """(R, s): columns of R are the axes, s₁ ≥ s₂ ≥ s₃, det R = +1."""
    w, V = eigh(P)
    s = jnp.sqrt(jnp.maximum(w[..., ::-1], 0.0))
    R = V[..., :, ::-1]
    det = jnp.linalg.det(R)
    R = R.at[..., :, 2].multiply(jnp.sign(det)[..., None] + (det == 0))
    return R, s


def _quadric_from(P, t):
    """[[P − ttᵀ, −t], [−tᵀ, −1]], broadcasting over leading axes."""
    P, t = jnp.asarray(P), jnp.asarray(t)
    top = jnp.concatenate([P - t[..., :, None] * t[..., None, :], -t[..., :, None]], axis=-1)
    bottom = jnp.concatenate([-t, -jnp.ones_like(t[..., :1])], axis=-1)[..., None, :]
    return jnp.concatenate([top, bottom], axis=-2)


def _split_quadric(Q):
    """Normalise Q* to Q*₃₃ = −1 and return (P, t)."""
    Q = sym(jnp.asarray(Q, dtype=float))
    Q = Q / -Q[3, 3]
    t = -Q[:3, 3]
    return Q[:3, :3] + jnp.outer(t, t), t


@dataclass(frozen=True)
class Ellipsoid:
    """An ellipsoid as (P, t) ∈ SPD(3) × R³, the paper's parameterisation.

    P = R diag(s²) Rᵀ (shape and orientation together), ``center`` = t.
    """

    P: jax.Array
    center: jax.Array
    tangent_dim: ClassVar[int] = 9

    # --- construction -----------------------------------------------------------------
    @classmethod
    def from_axes(cls, rotation, center, radii) -> "Ellipsoid":
        """P = R diag(radii²) Rᵀ; ``rotation`` is a 3×3 matrix (columns = axes) or SO3."""
        R = _rotation_matrix(rotation)
        r = jnp.asarray(radii, dtype=float)
        return cls(sym((R * r**2) @ R.T), jnp.asarray(center, dtype=float))

    @classmethod
    def from_dual_quadric(cls, Q) -> "Ellipsoid":
        """From any scalar multiple of Q* = [[P − ttᵀ, −t], [−tᵀ, −1]]."""
        P, t = _split_quadric(Q)
        return cls(sym(P), t)

    # --- views ------------------------------------------------------------------------
    def dual_quadric(self) -> jax.Array:
        """Q* (4×4, or (..., 4, 4) for a batched Ellipsoid), normalised so that Q*[3, 3] == −1."""
        return _quadric_from(self.P, self.center)

    def axes(self):
        """(rotation, radii): columns of ``rotation`` are the world-frame axes, radii descending."""
        return _sorted_axes(self.P)

    @property
    def radii(self) -> jax.Array:
        return self.axes()[1]

    @property
    def rotation(self) -> jax.Array:
        return self.axes()[0]

    def cuboid_corners(self) -> jax.Array:
        """The 8 corners (8×3) of the circumscribed oriented cuboid, t + R diag(s) σ, σ ∈ {±1}³."""
        R, s = self.axes()
        return self.center + (jnp.asarray(_CORNER_SIGNS) * s) @ R.T

    def volume(self) -> jax.Array:
        """(4/3) π s₁s₂s₃ = (4/3) π √det P."""
        return 4.0 / 3.0 * jnp.pi * jnp.sqrt(jnp.linalg.det(self.P))

    def contains(self, x) -> jax.Array:
        """True where (x−t)ᵀ P⁻¹ (x−t) < 1."""
        d = jnp.asarray(x) - self.center
        return jnp.einsum("...i,ij,...j->...", d, jnp.linalg.inv(self.P), d) < 1.0

    # --- manifold ---------------------------------------------------------------------
    def retract(self, delta) -> "Ellipsoid":
        """(P ⊞ c, t + δt) with delta = (c ∈ R⁶ orthonormal SPD coordinates, δt ∈ R³)."""
        delta = jnp.asarray(delta)
        return Ellipsoid(spd.retract_vec(self.P, delta[:6]), self.center + delta[6:])

    def local(self, other: "Ellipsoid") -> jax.Array:
        return jnp.concatenate(
            [spd.local_vec(self.P, other.P), other.center - self.center]
        )

    # --- conversions ------------------------------------------------------------------
    def to_ellipsoid(self) -> "Ellipsoid":
        return self

    def to_rts(self) -> "EllipsoidRTS":
        return EllipsoidRTS.from_ellipsoid(self)

    def to_full(self) -> "EllipsoidFull":
        return EllipsoidFull.from_ellipsoid(self)


@dataclass(frozen=True)
class EllipsoidRTS:
    """Rot-Trans-Scale: (R ∈ SO(3), t ∈ R³, s ∈ R³), P = R diag(s²) Rᵀ.

    Tangent (δθ, δt, δs): R ⊞ δθ = R Exp(δθ), t + δt, s + δs.
    """

    rotation: jaxlie.SO3
    center: jax.Array
    radii: jax.Array
    tangent_dim: ClassVar[int] = 9

    @classmethod
    def from_axes(cls, rotation, center, radii) -> "EllipsoidRTS":
        R = rotation if isinstance(rotation, jaxlie.SO3) else jaxlie.SO3.from_matrix(
            jnp.asarray(rotation, dtype=float)
        )
        return cls(R, jnp.asarray(center, dtype=float), jnp.asarray(radii, dtype=float))

    @classmethod
    def from_ellipsoid(cls, e: Ellipsoid) -> "EllipsoidRTS":
        R, s = e.axes()
        return cls(jaxlie.SO3.from_matrix(R), e.center, s)

    def to_ellipsoid(self) -> Ellipsoid:
        R = self.rotation.as_matrix()
        return Ellipsoid(sym((R * self.radii**2) @ R.T), self.center)

    def dual_quadric(self) -> jax.Array:
        return self.to_ellipsoid().dual_quadric()

    def retract(self, delta) -> "EllipsoidRTS":
        delta = jnp.asarray(delta)
        return EllipsoidRTS(
            self.rotation @ jaxlie.SO3.exp(delta[:3]),
            self.center + delta[3:6],
            self.radii + delta[6:9],
        )

    def local(self, other: "EllipsoidRTS") -> jax.Array:
        return jnp.concatenate(
            [
                (self.rotation.inverse() @ other.rotation).log(),
                other.center - self.center,
                other.radii - self.radii,
            ]
        )


_TRIU = np.triu_indices(4)


@dataclass(frozen=True)
class EllipsoidFull:
    """The 10 independent entries of Q* (upper triangle, row-major), updated additively.

    ``regularized()`` maps any symmetric 4×4 back to the nearest ellipsoid: normalise to
    Q*₃₃ = −1, split into (P, t), and clip the eigenvalues of P to be positive. The solver
    applies it after every step. Q* is homogeneous, so the normalised quadric (and every
    residual built on it) does not change along q itself: that direction of the tangent
    space is unobservable and is held by the solver's damping.
    """

    q: jax.Array
    tangent_dim: ClassVar[int] = 10
    #: Smallest eigenvalue of P kept by ``regularized``, relative to the largest.
    min_eig_ratio: ClassVar[float] = 1e-6

    @classmethod
    def from_dual_quadric(cls, Q) -> "EllipsoidFull":
        Q = sym(jnp.asarray(Q, dtype=float))
        return cls(Q[_TRIU])

    @classmethod
    def from_ellipsoid(cls, e: Ellipsoid) -> "EllipsoidFull":
        return cls.from_dual_quadric(e.dual_quadric())

    def matrix(self) -> jax.Array:
        """The symmetric 4×4 matrix of the raw entries (not normalised)."""
        Q = jnp.zeros((4, 4), dtype=self.q.dtype).at[_TRIU].set(self.q)
        return Q + jnp.triu(Q, 1).T

    def dual_quadric(self) -> jax.Array:
        """Q* normalised to Q*[3, 3] == −1."""
        Q = self.matrix()
        return Q / -Q[3, 3]

    def to_ellipsoid(self) -> Ellipsoid:
        return Ellipsoid.from_dual_quadric(self.matrix())

    def regularized(self) -> "EllipsoidFull":
        Q = self.matrix()
        # Q*₃₃ ≈ 0 has no finite centre: normalise by −1 instead of dividing by ~0 (the
        # result is then clipped to an ellipsoid below).
        # (Relative to the scale of Q: Q* is homogeneous, any multiple of it is the same quadric.)
        q33 = jnp.where(jnp.abs(Q[3, 3]) > 1e-12 * jnp.max(jnp.abs(Q)), Q[3, 3], -1.0)
        Q = Q / -q33
        t = -Q[:3, 3]
        w, V = jnp.linalg.eigh(sym(Q[:3, :3] + jnp.outer(t, t)))
        floor = self.min_eig_ratio * jnp.maximum(jnp.max(jnp.abs(w)), 1e-12)
        P = (V * jnp.maximum(w, floor)) @ V.T
        return EllipsoidFull(_quadric_from(sym(P), t)[_TRIU])

    def retract(self, delta) -> "EllipsoidFull":
        return EllipsoidFull(self.q + jnp.asarray(delta))

    def local(self, other: "EllipsoidFull") -> jax.Array:
        return other.q - self.q


_pytree(Ellipsoid, ["P", "center"])
_pytree(EllipsoidRTS, ["rotation", "center", "radii"])
_pytree(EllipsoidFull, ["q"])

for _cls in (Ellipsoid, EllipsoidRTS, EllipsoidFull):
    manifold.register(
        _cls,
        tangent_dim=_cls.tangent_dim,
        retract=_cls.retract,
        local=_cls.local,
        regularize=getattr(_cls, "regularized", None),
    )

Landmark = Ellipsoid | EllipsoidRTS | EllipsoidFull


def as_ellipsoid(x) -> Ellipsoid:
    """Any landmark parameterisation → (P, t). Smooth in the parameters of each type."""
    if isinstance(x, Ellipsoid):
        return x
    if isinstance(x, (EllipsoidRTS, EllipsoidFull)):
        return x.to_ellipsoid()
    raise TypeError(f"not an ellipsoid landmark: {type(x).__name__}")


def dual_quadric(x) -> jax.Array:
    """Q* of any landmark parameterisation, normalised to Q*[3, 3] == −1 (a raw 4×4 array
    is passed through as it is)."""
    if isinstance(x, (Ellipsoid, EllipsoidRTS, EllipsoidFull)):
        return x.dual_quadric()
    return jnp.asarray(x, dtype=float)
