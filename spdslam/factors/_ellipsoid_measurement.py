"""Full-ellipsoid measurements (RGB-D or LiDAR front ends), in the camera frame.

A front end that sees depth measures a whole ellipsoid per frame: (P̄, t̄) in the camera frame
(P̄ = R̄ diag(s̄²) R̄ᵀ). The landmark (P, t) in the world, seen from T_wc (camera-to-world,
T_cw = T_wc⁻¹ = (R_cw, t_cw)), is predicted as

    P_c = R_cw P R_cwᵀ,    t_c = R_cw t + t_cw,

and the residual (∈ R⁹) is

    r = [ vec(Log(P̄^-½ P_c P̄^-½)) ;  t_c − t̄ ],

with vec the 6 coordinates of a symmetric matrix in a Frobenius-orthonormal basis (the three
diagonal entries, then √2 times the off-diagonal (0,1), (0,2), (1,2) ones:
``spd.sym_to_vec``), so the norm of the shape part is the affine-invariant distance

    d(P̄, P_c) = ‖Log(P̄^-½ P_c P̄^-½)‖_F = √(Σᵢ log² λᵢ),  λ the eigenvalues of P̄⁻¹P_c.

It is invariant under a common congruence P ↦ A P Aᵀ of both matrices, blind to the order
and signs of the axes, and smooth at repeated radii (spheres measured as spheres): ``matfun``
gives Log a derivative that is finite at repeated eigenvalues. A shape component of 0.1 is
about a 5 % error of a radius (log s² = 2 log s) or, for axes of ratio 2, 0.1 rad of
rotation.
"""

from __future__ import annotations

import jax.numpy as jnp
import jaxlie
import numpy as np

from ..geometry import as_ellipsoid
from ..geometry.matfun import invsqrtm, logm
from ..geometry.spd import sym_to_vec
from ._base import Factor, Sigma

__all__ = [
    "EllipsoidMeasurementFactor",
    "ellipsoid_measurement_residual",
]


def ellipsoid_measurement_residual(T_wc, landmark, P_meas, t_meas):
    """[vec Log(P̄^-½ R_cw P R_cwᵀ P̄^-½) ; R_cw t + t_cw − t̄] ∈ R⁹ (see the module docstring).

    ``T_wc`` a ``jaxlie.SE3`` (camera-to-world), ``landmark`` any parameterisation (SPD, RTS,
    Full), (``P_meas``, ``t_meas``) the measured ellipsoid in the camera frame.
    """
    e = as_ellipsoid(landmark)
    T_cw = T_wc.inverse()
    R = T_cw.rotation().as_matrix()
    P_c = R @ e.P @ R.T
    t_c = T_cw @ e.center
    W = invsqrtm(P_meas)
    L = logm(W @ P_c @ W)
    return jnp.concatenate([sym_to_vec(L), t_c - t_meas])


def _measured_shape(measurement) -> np.ndarray:
    """P̄ from a 3×3 SPD matrix or from (rotation, radii); raises ValueError on bad input."""
    if isinstance(measurement, (tuple, list)) and len(measurement) == 2:
        rot, radii = measurement
        if isinstance(rot, jaxlie.SO3):
            rot = rot.as_matrix()
        R = np.asarray(rot, dtype=float)
        s = np.asarray(radii, dtype=float)
        if R.shape != (3, 3) or not np.all(np.isfinite(R)):
            raise ValueError(f"the measured rotation must be a finite 3x3 matrix, got shape {R.shape}")
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-6):
            raise ValueError("the measured rotation must be orthonormal (RᵀR = I within 1e-6)")
        if s.shape != (3,) or not np.all(np.isfinite(s)) or np.any(s <= 0):
            raise ValueError(f"the measured radii must be 3 positive numbers, got {s.tolist()}")
        P = (R * s**2) @ R.T
    else:
        P = np.asarray(measurement, dtype=float)
        if P.shape != (3, 3) or not np.all(np.isfinite(P)):
            raise ValueError(
                "the measured shape must be a finite 3x3 SPD matrix or (rotation, radii), "
                f"got shape {P.shape}"
            )
        if not np.allclose(P, P.T, rtol=1e-9, atol=1e-12 * max(np.abs(P).max(), 1e-300)):
            raise ValueError("the measured shape matrix must be symmetric")
    P = 0.5 * (P + P.T)
    w = np.linalg.eigvalsh(P)
    if not (w[0] > 1e-12 * max(w[-1], 0.0) and w[0] > 0):
        raise ValueError(
            f"the measured shape matrix must be positive definite, got eigenvalues {w.tolist()}"
        )
    return P


class EllipsoidMeasurementFactor(Factor):
    """A measured ellipsoid in the camera frame: ``shape`` is P̄ (3×3 SPD) or
    ``(rotation, radii)`` (columns of the rotation = the axes, radii the semi-axes along
    them), ``t_meas`` its centre. Default noise: 0.1 per log-shape coordinate and 0.05 m per
    centre coordinate, independent (``sigma`` a scalar or 9 values to change it)."""

    kind = "ellipsoid_measurement"
    residual = staticmethod(ellipsoid_measurement_residual)
    variables = ("pose", "landmark")
    dim = 9
    group = "ellipsoid"
    sigmas = (
        Sigma(0.1, "per log-shape coordinate (≈ 5 % of a radius)", "ellipsoid_shape", 6),
        Sigma(0.05, "m per centre coordinate", "ellipsoid_center", 3),
    )

    def __init__(self, pose_key, landmark_key, shape, t_meas, **noise):
        P = _measured_shape(shape)
        t = np.asarray(t_meas, dtype=float)
        if t.shape != (3,) or not np.all(np.isfinite(t)):
            raise ValueError(f"the measured centre must be a finite 3-vector, got {t.tolist()}")
        super().__init__((pose_key, landmark_key), (P, t), **noise)
