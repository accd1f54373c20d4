"""Ellipsoid landmarks in three parameterisations.

An ellipsoid with centre t and shape matrix P ∈ SPD(3) is the set {x : (x−t)ᵀ P⁻¹ (x−t) ≤ 1};
P = R diag(s²) Rᵀ with the semi-axes s along the columns of R. Its dual quadric (tangent
planes π satisfy πᵀ Q* π = 0), normalised to Q*₃₃ = −1, is

    Q* = T diag(P, −1) Tᵀ,  T = [[I, t], [0, 1]]   ⇒   Q* = [[P − ttᵀ, −t], [−tᵀ, −1]].

(The paper prints +t in the off-diagonal blocks; that sign is wrong for t the centre.)

Parameterisations, all registered as optimisation variables:

- ``Ellipsoid`` (SPD): (P, t) ∈ SPD(3) × R³. Tangent (c, δt) ∈ R⁶ × R³:
  P ⊞ c is the affine-invariant exponential (``spd.retract_vec``), t ⊞ δt = t + δt.
- ``EllipsoidRTS`` (Rot-Trans-Scale): parameters (``orientation`` R ∈ SO(3), ``center``
  t ∈ R³, ``scale`` s ∈ R³). Tangent (δθ, δt, δs): R·Exp(δθ), t + δt, s + δs (the baseline
  as gtsam-quadrics updates it). s is the raw parameter: its entries may be in any order
  and of either sign.
- ``EllipsoidFull``: the 10 independent entries of Q*, updated additively, and projected
  to the nearest ellipsoid after every step (QuadricSLAM's "constrain").

The views are the same on all three and mean the same thing: ``P``, ``center``,
``axes()`` = (``rotation``, ``radii``) with the radii sorted s₁ ≥ s₂ ≥ s₃ ≥ 0 and a
right-handed rotation whose columns are the axes, ``dual_quadric()``, ``volume()``,
``contains(x)``, ``cuboid_corners()``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from . import manifold, spd
from ._arrays import array_namespace
from ._cuboid import corners_of
from .matfun import eigh, sym

__all__ = [
    "Ellipsoid",
    "EllipsoidRTS",
    "EllipsoidFull",
    "Landmark",
    "as_ellipsoid",
    "dual_quadric",
    "dual_quadric_of",
    "sorted_axes",
    "cuboid_half_axes",
    "cuboid_corners",
    "moved_covariance",
]


def _pytree(cls, fields):
    jax.tree_util.register_dataclass(cls, data_fields=list(fields), meta_fields=[])
    return cls


def _rotation_matrix(rotation):
    if isinstance(rotation, jaxlie.SO3):
        return rotation.as_matrix()
    return jnp.asarray(rotation, dtype=float)


def sorted_axes(P):
    """(R, s) of shape matrices P (…, 3, 3): columns of R are the axes, s₁ ≥ s₂ ≥ s₃,
    det R = +1 (NumPy for a NumPy P, the same LAPACK decomposition as JAX's; else JAX)."""
    if isinstance(P, np.ndarray):
        w, V = np.linalg.eigh(0.5 * (P + np.swapaxes(P, -1, -2)))
        R = V[..., :, ::-1].copy()
        det = np.linalg.det(R)
        R[..., :, 2] *= (np.sign(det) + (det == 0))[..., None]
        return R, np.sqrt(np.maximum(w[..., ::-1], 0.0))
    w, V = eigh(P)
    s = jnp.sqrt(jnp.maximum(w[..., ::-1], 0.0))
    R = V[..., :, ::-1]
    det = jnp.linalg.det(R)
    R = R.at[..., :, 2].multiply((jnp.sign(det) + (det == 0))[..., None])
    return R, s


def dual_quadric_of(P, t):
    """Q* = [[P − ttᵀ, −t], [−tᵀ, −1]] of ellipsoids (P (…, 3, 3), t (…, 3)); NumPy or JAX."""
    xp = array_namespace(P, t)
    P, t = xp.asarray(P), xp.asarray(t)
    top = xp.concatenate([P - t[..., :, None] * t[..., None, :], -t[..., :, None]], axis=-1)
    bottom = xp.concatenate([-t, -xp.ones_like(t[..., :1])], axis=-1)[..., None, :]
    return xp.concatenate([top, bottom], axis=-2)


def _split_quadric(Q):
    """Normalise Q* to Q*₃₃ = −1 and return (P, t)."""
    Q = sym(jnp.asarray(Q, dtype=float))
    Q = Q / -Q[3, 3]
    t = -Q[:3, 3]
    return Q[:3, :3] + jnp.outer(t, t), t


class _Views:
    """The views every parameterisation shares, all from (P, t)."""

    if TYPE_CHECKING:
        def to_ellipsoid(self) -> Ellipsoid: ...  # each parameterisation defines it

    def axes(self):
        """(rotation, radii): columns of ``rotation`` are the world-frame axes, radii descending."""
        return sorted_axes(self.to_ellipsoid().P)

    @property
    def rotation(self) -> jax.Array:
        """The axes as the columns of a rotation matrix (sorted by radius, det +1)."""
        return self.axes()[0]

    @property
    def radii(self) -> jax.Array:
        """The semi-axes s₁ ≥ s₂ ≥ s₃ ≥ 0."""
        return self.axes()[1]

    def cuboid_corners(self) -> jax.Array:
        """The 8 corners (8×3) of the circumscribed oriented cuboid, t + R diag(s) σ, σ ∈ {±1}³."""
        R, s = self.axes()
        return corners_of(R * s, self.to_ellipsoid().center)

    def volume(self) -> jax.Array:
        """(4/3) π s₁s₂s₃ = (4/3) π √det P."""
        return 4.0 / 3.0 * jnp.pi * jnp.sqrt(jnp.linalg.det(self.to_ellipsoid().P))

    def contains(self, x) -> jax.Array:
        """True where (x−t)ᵀ P⁻¹ (x−t) < 1."""
        e = self.to_ellipsoid()
        xp = array_namespace(x, e.P, e.center)
        d = xp.asarray(x) - e.center
        return xp.einsum("...i,...ij,...j->...", d, xp.linalg.inv(e.P), d) < 1.0


@dataclass(frozen=True)
class Ellipsoid(_Views):
    """An ellipsoid as (P, t) ∈ SPD(3) × R³, the paper's parameterisation.

    P = R diag(s²) Rᵀ (shape and orientation together), ``center`` = t.
    """

    # JAX or NumPy arrays (readers, results and stacked factor data hold NumPy leaves)
    P: jax.Array | np.ndarray
    center: jax.Array | np.ndarray
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
        return dual_quadric_of(self.P, self.center)

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
class EllipsoidRTS(_Views):
    """Rot-Trans-Scale: ``orientation`` R ∈ SO(3), ``center`` t ∈ R³, ``scale`` s ∈ R³,
    P = R diag(s²) Rᵀ (s raw: any order, either sign; ``radii`` are |s| sorted).

    Tangent (δθ, δt, δs): R ⊞ δθ = R Exp(δθ), t + δt, s + δs.
    """

    orientation: jaxlie.SO3
    center: jax.Array | np.ndarray
    scale: jax.Array
    tangent_dim: ClassVar[int] = 9

    @classmethod
    def from_axes(cls, rotation, center, radii) -> "EllipsoidRTS":
        """R from a 3×3 matrix (columns = axes) or an SO3, s = ``radii`` along them."""
        R = rotation if isinstance(rotation, jaxlie.SO3) else jaxlie.SO3.from_matrix(
            jnp.asarray(rotation, dtype=float)
        )
        return cls(R, jnp.asarray(center, dtype=float), jnp.asarray(radii, dtype=float))

    @classmethod
    def from_ellipsoid(cls, e: Ellipsoid) -> "EllipsoidRTS":
        """The sorted axes of ``e`` as (R, t, s)."""
        R, s = e.axes()
        return cls(jaxlie.SO3.from_matrix(R), e.center, s)

    def to_ellipsoid(self) -> Ellipsoid:
        R = self.orientation.as_matrix()
        return Ellipsoid(sym((R * self.scale**2) @ R.T), self.center)

    @property
    def P(self) -> jax.Array | np.ndarray:
        return self.to_ellipsoid().P

    def dual_quadric(self) -> jax.Array:
        return self.to_ellipsoid().dual_quadric()

    def retract(self, delta) -> "EllipsoidRTS":
        delta = jnp.asarray(delta)
        return EllipsoidRTS(
            self.orientation @ jaxlie.SO3.exp(delta[:3]),
            self.center + delta[3:6],
            self.scale + delta[6:9],
        )

    def local(self, other: "EllipsoidRTS") -> jax.Array:
        return jnp.concatenate(
            [
                (self.orientation.inverse() @ other.orientation).log(),
                other.center - self.center,
                other.scale - self.scale,
            ]
        )


_TRIU = np.triu_indices(4)


@dataclass(frozen=True)
class EllipsoidFull(_Views):
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

    @property
    def P(self) -> jax.Array | np.ndarray:
        return self.to_ellipsoid().P

    @property
    def center(self) -> jax.Array | np.ndarray:
        return self.to_ellipsoid().center

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
        return EllipsoidFull(dual_quadric_of(sym(P), t)[_TRIU])

    def retract(self, delta) -> "EllipsoidFull":
        return EllipsoidFull(self.q + jnp.asarray(delta))

    def local(self, other: "EllipsoidFull") -> jax.Array:
        return other.q - self.q


_pytree(Ellipsoid, ["P", "center"])
_pytree(EllipsoidRTS, ["orientation", "center", "scale"])
_pytree(EllipsoidFull, ["q"])

#: Tangent blocks with an isotropic metric: SPD(3) (affine-invariant, orthonormal basis) and
#: R³; so(3), R³, R³; the 10 entries of Q*.
_BLOCKS = {Ellipsoid: (6, 3), EllipsoidRTS: (3, 3, 3), EllipsoidFull: (10,)}

def _host_spectral(A, f):
    """f(A) = V diag(f(λ)) Vᵀ of stacked symmetric matrices (…, 3, 3), NumPy; NaN where A is
    not finite (as the program's result there, where LAPACK would raise)."""
    w, V = spd.host_eigh(A)
    return (V * f(w)[..., None, :]) @ np.swapaxes(V, -1, -2)


def _host_sqrt(P):
    return _host_spectral(P, lambda w: np.sqrt(np.maximum(w, 1e-300)))


def _ellipsoid_host_retract(x, d):
    """``Ellipsoid.retract`` of stacked rows in NumPy: (P^½ Exp(Σ cₖ Eₖ) P^½, t + δt)."""
    P, t, d = np.asarray(x.P, float), np.asarray(x.center, float), np.asarray(d, float)
    with np.errstate(over="ignore", invalid="ignore"):  # a step too long: not finite, as the program's
        Ph = _host_sqrt(P)
        S = np.einsum("nk,kij->nij", d[:, :6], spd.BASIS)
        new = Ph @ _host_spectral(S, np.exp) @ Ph
    return Ellipsoid(0.5 * (new + np.swapaxes(new, -1, -2)), t + d[:, 6:])


def _ellipsoid_host_pushforward(x):
    """∂(x ⊞ δ)/∂δ|₀ of stacked rows in NumPy: (P^½ Eₖ P^½, 0) for the six SPD coordinates,
    (0, eⱼ) for the centre's three (Exp's derivative at 0 is the identity)."""
    P = np.asarray(x.P, float)
    n = len(P)
    Ph = _host_sqrt(P)
    dP = np.zeros((n, 9, 3, 3))
    dP[:, :6] = Ph[:, None] @ spd.BASIS[None] @ Ph[:, None]
    dt = np.zeros((n, 9, 3))
    dt[:, 6:] = np.eye(3)
    return Ellipsoid(dP, dt)


#: The types' NumPy retraction and pushforward (the other parameterisations have none).
_HOST: dict[type, tuple[Any, Any]] = {Ellipsoid: (_ellipsoid_host_retract, _ellipsoid_host_pushforward)}

for _cls in (Ellipsoid, EllipsoidRTS, EllipsoidFull):
    manifold.register(
        _cls,
        tangent_dim=_cls.tangent_dim,
        blocks=_BLOCKS[_cls],
        retract=_cls.retract,
        local=_cls.local,
        regularize=getattr(_cls, "regularized", None),
        host_retract=_HOST.get(_cls, (None, None))[0],
        host_pushforward=_HOST.get(_cls, (None, None))[1],
    )

#: Any landmark parameterisation.
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


def cuboid_half_axes(landmark):
    """(H, t): the columns of H are the circumscribed cuboid's half-edge vectors sᵢRᵢ, t its
    centre (a pair (H, t) is returned as it is).

    RTS landmarks use their orientation and |scale| directly (smooth in their parameters);
    SPD and Full go through P = V diag(λ) Vᵀ with the tie-safe ``matfun.eigh``, sᵢ = √λᵢ. The
    cuboid is invariant to the order and signs of the axes, but at repeated radii its
    orientation is not determined by P: there the box is that of one valid choice of axes
    and its derivative is finite (the coupling inside the tie is dropped), not a limit.
    """
    if isinstance(landmark, tuple):
        return landmark
    if isinstance(landmark, EllipsoidRTS):
        return landmark.orientation.as_matrix() * jnp.abs(landmark.scale), landmark.center
    e = as_ellipsoid(landmark)
    w, V = eigh(e.P)
    return V * jnp.sqrt(jnp.maximum(w, 1e-300)), e.center


def cuboid_corners(cuboid):
    """The 8 corners (…, 8, 3) t + H σ, σ ∈ {±1}³, of a circumscribed cuboid: a landmark
    (``cuboid_half_axes``: its axes in the order of P's eigenvectors, or of an RTS
    orientation) or a pair (H, t)."""
    return corners_of(*cuboid_half_axes(cuboid))


def moved_covariance(C, R, scale: float = 1.0) -> np.ndarray:
    """The covariance (9×9) of an ellipsoid's (centre, P's xx, xy, xz, yy, yz, zz), map.json's
    ``uncertainty.covariance``, after x ↦ s R x + t: J C Jᵀ with J = diag(s R, s² M), M the
    map of P ↦ R P Rᵀ on the upper triangle. NumPy."""
    R = np.asarray(R, float)
    iu = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))
    M = np.empty((6, 6))
    for k, (i, j) in enumerate(zip(*iu)):  # the image of the symmetric basis matrix of entry k
        E = np.zeros((3, 3))
        E[i, j] = E[j, i] = 1.0
        M[:, k] = (R @ E @ R.T)[iu]
    J = np.zeros((9, 9))
    J[:3, :3], J[3:, 3:] = scale * R, scale**2 * M
    return J @ np.asarray(C, float) @ J.T
