"""Object constraints on one landmark, for any parameterisation (SPD, RTS or Full):
orientation against a world direction (improved, classic, per axis), class shape and size
priors, and the support plane.

Notation: landmark (P, t), P = R diag(s²) Rᵀ with the axes nᵢ = Rᵢ; Q* = [[P − ttᵀ, −t],
[−tᵀ, −1]]; m a unit world direction (gravity up); planes π = [n; d] with ‖n‖ = 1.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..geometry import EllipsoidRTS, as_ellipsoid, cuboid_half_axes, dual_quadric
from ..geometry.matfun import eigh, logm
from ._base import Factor, Sigma

__all__ = [
    "OrientationFactor",
    "ClassicOrientationFactor",
    "AxisOrientationFactor",
    "ShapeFactor",
    "ClassicShapeFactor",
    "SizeFactor",
    "SupportPlaneFactor",
    "RadiusFloorFactor",
    "orientation_residual",
    "classic_orientation_residual",
    "axis_orientation_residual",
    "shape_residual",
    "classic_shape_residual",
    "size_residual",
    "support_plane_residual",
    "radius_floor_residual",
]


def _unit(v):
    v = jnp.asarray(v, dtype=float)
    return v / jnp.linalg.norm(v, axis=-1, keepdims=True)


def _direction(direction) -> np.ndarray:
    m = np.asarray(direction, dtype=float)
    if m.shape != (3,) or not np.all(np.isfinite(m)) or np.linalg.norm(m) == 0:
        raise ValueError(f"direction must be a non-zero 3-vector, got {m.tolist()}")
    return m / np.linalg.norm(m)


# --- orientation -------------------------------------------------------------------------
def orientation_residual(landmark, direction):
    """Improved orientation constraint, smooth in P:

        r = (Log(P) m) × m = Σᵢ log(sᵢ²) (nᵢ × m)(nᵢ·m)   ∈ R³,

    the paper's per-axis term (nᵢ × m)(nᵢ·m) for every axis nᵢ, weighted by the log of its
    squared radius. It is zero iff every axis is parallel or perpendicular to m (m is an
    eigenvector of P), for any axis order and sign. The weights matter: with equal weights
    the sum is (Σ nᵢnᵢᵀ m) × m = m × m ≡ 0. It is scale-invariant (Log(cP) = Log P + log c·I)
    and stays differentiable at repeated radii, where the axes themselves are undefined
    (a sphere satisfies it for every m).
    """
    m = _unit(direction)
    L = logm(as_ellipsoid(landmark).P)
    return jnp.cross(L @ m, m)


def classic_orientation_residual(landmark, direction, axis):
    """Classic form: one fixed object axis n = R e_axis parallel to m,

        r = sign(n·m) (n × m)   ∈ R³,   ‖r‖ = sin θ,

    θ ∈ [0, 90°] the angle between the line of n and m: blind to the axis sign but not to
    its order (a fixed column of an RTS orientation), so an object whose rotation has
    another axis up is pulled by up to 90°. Smooth at θ = 0 (an angle θ ≥ 0 would have a
    kink there that stalls Gauss-Newton); the sign flips only at θ = 90°. ``axis`` is a
    one-hot 3-vector selecting the column.
    """
    if not isinstance(landmark, EllipsoidRTS):
        raise TypeError(
            "the classic orientation factor constrains a fixed axis of an RTS landmark "
            f"(EllipsoidRTS), got {type(landmark).__name__}; use OrientationFactor for SPD/Full"
        )
    m = _unit(direction)
    n = landmark.orientation.as_matrix() @ axis
    return jnp.where(n @ m < 0, -1.0, 1.0) * jnp.cross(n, m)


def axis_orientation_residual(landmark, direction):
    """Per-axis orientation constraint for cuboid-shaped objects, the paper's term for each
    axis nᵢ of the object stacked (not summed):

        r = [(n₁ × m)(n₁·m); (n₂ × m)(n₂·m); (n₃ × m)(n₃·m)]   ∈ R⁹,

    zero iff every axis is parallel or perpendicular to m, whatever their order and signs;
    each block has norm ½|sin 2θᵢ| ≈ θᵢ. Unlike (Log P m) × m its strength does not fade as
    two radii approach each other: a cuboid with two equal half-extents still has an
    orientation about the third axis, an ellipsoid does not. The axes are those of the
    circumscribed cuboid (``geometry.cuboid_half_axes``: eigenvectors of P, or the
    orientation of an RTS landmark), so like the cuboid itself it is undefined at exactly
    repeated radii (finite there, not continuous).
    """
    m = _unit(direction)
    H, _ = cuboid_half_axes(landmark)
    N = H / jnp.linalg.norm(H, axis=0, keepdims=True)  # unit axes as columns
    return (jnp.cross(N.T, m) * (N.T @ m)[:, None]).reshape(9)


class _LandmarkFactor(Factor):
    """A constraint on one landmark."""

    variables = ("landmark",)


class _OrientationFactor(_LandmarkFactor):
    """An orientation constraint against a world direction m (normalised here)."""

    group = "orientation"

    def __init__(self, landmark_key, direction, **noise):
        super().__init__((landmark_key,), (_direction(direction),), **noise)


class OrientationFactor(_OrientationFactor):
    """Improved orientation constraint (Log P m) × m against a world direction m."""

    kind = "orientation"
    residual = staticmethod(orientation_residual)
    dim = 3
    sigmas = (Sigma(0.05, "per component of (Log P m) × m"),)


class AxisOrientationFactor(_OrientationFactor):
    """Per-axis orientation constraint (cuboid-shaped objects) against a world direction m."""

    kind = "axis_orientation"
    residual = staticmethod(axis_orientation_residual)
    dim = 9
    sigmas = (Sigma(0.05, "per component of (nᵢ × m)(nᵢ·m) (≈ rad)"),)


class ClassicOrientationFactor(_LandmarkFactor):
    """Classic orientation constraint: column ``axis`` of an RTS landmark's orientation ∥ m."""

    kind = "classic_orientation"
    residual = staticmethod(classic_orientation_residual)
    dim = 3
    group = "orientation"
    sigmas = (Sigma(0.05, "per component of ±n × m (≈ rad)"),)

    def __init__(self, landmark_key, direction, axis: int = 2, **noise):
        if axis not in (0, 1, 2):
            raise ValueError(f"axis must be 0, 1 or 2, got {axis!r}")
        super().__init__((landmark_key,), (_direction(direction), np.eye(3)[axis]), **noise)


# --- shape, size, support ----------------------------------------------------------------
def _sorted_radii(landmark):
    w, _ = eigh(as_ellipsoid(landmark).P)
    return jnp.sqrt(jnp.maximum(w[::-1], 1e-300))


def shape_residual(landmark, prior_ratios):
    """[s₁/s₃, s₂/s₃] − [a/c, b/c], radii sorted s₁ ≥ s₂ ≥ s₃ (and a ≥ b ≥ c).

    Sorting makes the prior blind to axis order. At repeated radii the sorted ratios have
    a kink; the derivative used there is the mean over the tie (see ``matfun.eigh``), which
    is what a central difference measures.
    """
    s = _sorted_radii(landmark)
    return s[:2] / s[2] - prior_ratios


def classic_shape_residual(landmark, prior_ratios):
    """Classic form, in the landmark's own axis order: [|s₁|/|s₃|, |s₂|/|s₃|] − [a/c, b/c]
    with s the scales of an RTS landmark as stored (columns 1, 2, 3 of its rotation) and
    (a, b, c) the class's semi-axes in their stated order (x, y horizontal, z up). Not blind
    to the axis order: a landmark whose axes the front end labelled otherwise than the
    class is pulled towards a wrong shape (the conflict the sorted ratios remove).
    """
    if not isinstance(landmark, EllipsoidRTS):
        raise TypeError(
            "the classic shape factor constrains the stored scales of an RTS landmark "
            f"(EllipsoidRTS), got {type(landmark).__name__}; use ShapeFactor for SPD/Full"
        )
    s = jnp.abs(landmark.scale)
    return s[:2] / s[2] - prior_ratios


def size_residual(landmark, log_prior_volume):
    """⅓ log(V / V̄) = log of the ratio of geometric-mean radii (s₁s₂s₃)^⅓ / (abc)^⅓.

    ``log_prior_volume`` is log(abc); the 4π/3 factors cancel.
    """
    logdet = jnp.linalg.slogdet(as_ellipsoid(landmark).P)[1]
    return jnp.atleast_1d((0.5 * logdet - log_prior_volume) / 3.0)


def radius_floor_residual(landmark, log_floor):
    """max(0, log ρ − log s₃): zero while the smallest radius s₃ is above the floor ρ, the
    log of how far it is below otherwise. One-sided, so it biases no object whose extent
    the data fix; it keeps one whose extent they do not (a flat start, boxes with little
    parallax, a support plane satisfied by the flat solution) off the boundary of SPD(3),
    for every parameterisation."""
    w, _ = eigh(as_ellipsoid(landmark).P)
    return jnp.atleast_1d(jnp.maximum(0.0, log_floor - 0.5 * jnp.log(jnp.maximum(w[0], 1e-300))))


def support_plane_residual(landmark, plane):
    """πᵀQ*π for the plane the object stands on (unit normal): zero when it touches it."""
    return jnp.atleast_1d(plane @ dual_quadric(landmark) @ plane)


def _prior_radii(radii, sort: bool = True):
    """The class's semi-axes, validated; sorted descending unless ``sort`` is False."""
    r = np.asarray(radii, dtype=float)
    if r.shape != (3,) or not np.all(np.isfinite(r)) or np.any(r <= 0):
        raise ValueError(f"prior radii must be 3 positive numbers, got {r.tolist()}")
    return np.sort(r)[::-1] if sort else r


class _ClassPriorFactor(_LandmarkFactor):
    """A prior from the semi-axes (a, b, c) of the object's class, in any order."""

    def __init__(self, landmark_key, prior_radii, **noise):
        super().__init__((landmark_key,), (self.prior_data(_prior_radii(prior_radii)),), **noise)


class ShapeFactor(_ClassPriorFactor):
    """Class shape prior: the sorted ratios [a/c, b/c] (a ≥ b ≥ c)."""

    kind = "shape"
    residual = staticmethod(shape_residual)
    dim = 2
    group = "shape"
    sigmas = (Sigma(0.1, "per axis ratio"),)

    @staticmethod
    def prior_data(r):
        return np.array([r[0] / r[2], r[1] / r[2]])


class ClassicShapeFactor(_LandmarkFactor):
    """Classic class shape prior on an RTS landmark: its stored ratios [s₁/s₃, s₂/s₃] against
    [a/c, b/c] of the class's semi-axes in their stated order (not sorted)."""

    kind = "classic_shape"
    residual = staticmethod(classic_shape_residual)
    dim = 2
    group = "shape"
    sigmas = (Sigma(0.1, "per axis ratio, in the landmark's own axis order"),)

    def __init__(self, landmark_key, prior_radii, **noise):
        r = _prior_radii(prior_radii, sort=False)
        super().__init__((landmark_key,), (r[:2] / r[2],), **noise)


class SizeFactor(_ClassPriorFactor):
    """Class volume prior: log(abc)."""

    kind = "size"
    residual = staticmethod(size_residual)
    dim = 1
    group = "size"
    sigmas = (Sigma(0.1, "log of the geometric-mean radius ratio"),)

    @staticmethod
    def prior_data(r):
        return np.array(np.sum(np.log(r)))


class RadiusFloorFactor(_LandmarkFactor):
    """The smallest radius stays above a floor ρ (m): ``radius_floor_residual``."""

    kind = "radius_floor"
    residual = staticmethod(radius_floor_residual)
    dim = 1
    group = "radius_floor"
    sigmas = (Sigma(0.1, "log of the smallest radius below the floor"),)

    def __init__(self, landmark_key, floor, **noise):
        f = float(floor)
        if not (np.isfinite(f) and f > 0):
            raise ValueError(f"floor must be a positive radius (m), got {floor!r}")
        super().__init__((landmark_key,), (np.array(np.log(f)),), **noise)


class SupportPlaneFactor(_LandmarkFactor):
    """The object touches the plane a·x + b·y + c·z + d = 0 (e.g. the floor)."""

    kind = "support_plane"
    residual = staticmethod(support_plane_residual)
    dim = 1
    group = "support_plane"
    sigmas = (Sigma(0.01, "m² (πᵀQ*π)"),)

    def __init__(self, landmark_key, plane, **noise):
        p = np.asarray(plane, dtype=float)
        if p.shape != (4,) or not np.all(np.isfinite(p)) or np.linalg.norm(p[:3]) == 0:
            raise ValueError(f"plane must be [a, b, c, d] with a non-zero normal, got {p.tolist()}")
        super().__init__((landmark_key,), (p / np.linalg.norm(p[:3]),), **noise)
