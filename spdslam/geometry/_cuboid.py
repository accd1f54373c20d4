"""Oriented cuboids: the ground-truth object model and every landmark's circumscribed box.

A cuboid is C = {c + R q : |q_k| ≤ h_k}: centre c, axes the columns of R, half-extents h.
Its half-edge vectors are the columns of H = R diag(h), its corners c + H σ for the 8 sign
vectors σ ∈ {±1}³ of ``CORNER_SIGNS`` (x varying fastest), and corners i and i + 2ᵏ share
the edge along axis k (``CUBOID_EDGES``). A landmark's circumscribed cuboid has c = t and
H = R diag(s) for P = R diag(s²) Rᵀ (``cuboid_half_axes``).

``OBJECT_SHAPES`` names the two silhouette models: a detector boxes an object as an
ellipsoid or as its circumscribed cuboid (box-like objects: cabinets, monitors, tables).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from ._arrays import array_namespace

__all__ = [
    "CORNER_SIGNS",
    "CUBOID_EDGES",
    "OBJECT_SHAPES",
    "Cuboid",
    "as_cuboid",
    "corners_of",
    "checked_vector",
    "checked_rotation",
]

#: The silhouette models of an object: its ellipsoid, or its circumscribed cuboid.
OBJECT_SHAPES = ("ellipsoid", "cuboid")

#: Corner signs σ ∈ {±1}³ (8×3), x varying fastest.
CORNER_SIGNS = np.array(list(itertools.product((-1.0, 1.0), repeat=3)))[:, ::-1].copy()
CORNER_SIGNS.setflags(write=False)
#: The 12 edges as pairs of corner indices: corners i and i + 2ᵏ differ in the sign of axis k.
CUBOID_EDGES = np.array([(i, i | (1 << k)) for k in range(3) for i in range(8) if not i & (1 << k)])
CUBOID_EDGES.setflags(write=False)

#: Tolerance on ‖RᵀR − I‖ (entrywise) for a matrix to count as orthonormal.
_ORTHO_TOL = 1e-6


def corners_of(H, t):
    """The corners (…, 8, 3) t + H σ of the cuboids with half-edge vectors the columns of H
    (…, 3, 3) and centres t (…, 3); NumPy or JAX."""
    xp = array_namespace(H, t)
    return t[..., None, :] + xp.asarray(CORNER_SIGNS) @ xp.swapaxes(H, -1, -2)


# --- validation ---------------------------------------------------------------------------


def checked_vector(x, name: str) -> np.ndarray:
    """A finite (3,) NumPy copy of x, else ValueError naming ``name``."""
    v = np.array(x, dtype=float)  # a copy: Cuboid freezes it
    if v.shape != (3,):
        raise ValueError(f"{name} must have shape (3,), got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must be finite, got {v.tolist()}")
    return v


def checked_rotation(x, name: str) -> np.ndarray:
    """x as a finite orthonormal 3×3 NumPy matrix (RᵀR = I within 1e-6), else ValueError."""
    R = np.asarray(x, dtype=float)
    if R.shape != (3, 3):
        raise ValueError(f"{name} must have shape (3, 3), got {R.shape}")
    if not np.all(np.isfinite(R)):
        raise ValueError(f"{name} must be finite")
    err = float(np.max(np.abs(R.T @ R - np.eye(3))))
    if err > _ORTHO_TOL:
        raise ValueError(f"{name} must be orthonormal (max |RᵀR − I| = {err:.3g})")
    return R


@dataclass(frozen=True, eq=False)
class Cuboid:
    """C = {c + R q : |q_k| ≤ h_k}: ``center`` c, ``rotation`` R (columns = axes, det +1),
    ``half_extents`` h > 0. NumPy, validated.

    A reflection (det R = −1) describes the same solid; its third axis is negated.
    """

    center: np.ndarray
    rotation: np.ndarray
    half_extents: np.ndarray

    def __post_init__(self):
        c = checked_vector(self.center, "center")
        R = checked_rotation(self.rotation, "rotation").copy()
        h = checked_vector(self.half_extents, "half_extents")
        if not np.all(h > 0):
            raise ValueError(f"half_extents must be positive, got {h.tolist()}")
        if np.linalg.det(R) < 0:
            R[:, 2] = -R[:, 2]
        for name, v in (("center", c), ("rotation", R), ("half_extents", h)):
            v.setflags(write=False)
            object.__setattr__(self, name, v)

    # --- construction -------------------------------------------------------------------
    @classmethod
    def from_ellipsoid(cls, x) -> "Cuboid":
        """The circumscribed cuboid of any landmark: c = t, R and h = s of ``axes()``."""
        R, s = x.axes()
        return cls(np.asarray(x.center, float), np.asarray(R, float), np.asarray(s, float))

    @classmethod
    def from_yaw(cls, center, yaw: float, half_extents) -> "Cuboid":
        """R = R_z(yaw), a rotation about +z (the convention of ground truth boxes)."""
        yaw = float(yaw)
        if not np.isfinite(yaw):
            raise ValueError(f"yaw must be finite, got {yaw}")
        cy, sy = np.cos(yaw), np.sin(yaw)
        R = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
        return cls(center, R, half_extents)

    @classmethod
    def from_row(cls, row) -> "Cuboid":
        """From a ground truth row ``x y z yaw hx hy hz``."""
        v = np.asarray(row, dtype=float).ravel()
        if v.shape != (7,):
            raise ValueError(f"a cuboid row is 'x y z yaw hx hy hz' (7 numbers), got {v.size}")
        return cls.from_yaw(v[:3], v[3], v[4:])

    # --- views --------------------------------------------------------------------------
    def corners(self) -> np.ndarray:
        """The 8 corners (8×3), c + R diag(h) σ, σ ∈ ``CORNER_SIGNS``."""
        return corners_of(self.rotation * self.half_extents, self.center)

    def volume(self) -> float:
        """8 h₁h₂h₃."""
        return float(8.0 * np.prod(self.half_extents))

    def to_local(self, points) -> np.ndarray:
        """Rᵀ(x − c) for points (…×3)."""
        return (np.asarray(points, dtype=float) - self.center) @ self.rotation

    def contains(self, points, tol: float = 0.0) -> np.ndarray:
        """True where |Rᵀ(x − c)|_k ≤ h_k + tol for all k."""
        return np.all(np.abs(self.to_local(points)) <= self.half_extents + tol, axis=-1)

    def transformed(self, rotation, translation) -> "Cuboid":
        """The image under x ↦ Q x + u: centre Q c + u, axes Q R."""
        Q = checked_rotation(rotation, "rotation")
        u = checked_vector(translation, "translation")
        return Cuboid(Q @ self.center + u, Q @ self.rotation, self.half_extents)


def as_cuboid(x) -> Cuboid:
    """A ``Cuboid`` as is; any landmark (anything with ``axes()`` and ``center``) → its
    circumscribed cuboid."""
    if isinstance(x, Cuboid):
        return x
    if hasattr(x, "axes") and hasattr(x, "center"):
        return Cuboid.from_ellipsoid(x)
    raise TypeError(f"not a cuboid or ellipsoid landmark: {type(x).__name__}")
