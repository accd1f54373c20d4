"""Pose factors on SE(3): priors and relative-pose (odometry / loop-closure) constraints.

Poses are ``jaxlie.SE3`` (camera-to-world T_wc), perturbed on the right, T ⊞ δ = T·Exp(δ),
with tangent vectors δ = (v, ω) in jaxlie's order: translation first, rotation second.

    prior:    r(T)      = Log(T̄⁻¹ T)              ∈ R⁶
    between:  r(T₁, T₂) = Log(T̄₁₂⁻¹ T₁⁻¹ T₂)      ∈ R⁶

Log is the full SE(3) logarithm (gtsam's Pose3::Logmap with the expmap chart), so with the
same noise these residuals equal gtsam's PriorFactorPose3 / BetweenFactorPose3 errors up to
the order of the components: gtsam orders a Pose3 tangent (ω, v), rotation first. Sigmas,
information and covariance matrices given here are in jaxlie order (v, ω); permute gtsam's
with ``[3, 4, 5, 0, 1, 2]``.
"""

from __future__ import annotations

from typing import Any, Hashable

import jaxlie
import numpy as np

from ..se3 import as_pose
from ._base import Factor, RobustKernel, sqrt_information

__all__ = [
    "pose_prior_residual",
    "pose_between_residual",
    "PriorFactor",
    "BetweenFactor",
    "as_se3",
]


def pose_prior_residual(T: jaxlie.SE3, T_prior: jaxlie.SE3):
    """r = Log(T̄⁻¹ T) ∈ R⁶, (v, ω) order; zero when T = T̄."""
    return (T_prior.inverse() @ T).log()


def pose_between_residual(T1: jaxlie.SE3, T2: jaxlie.SE3, T12: jaxlie.SE3):
    """r = Log(T̄₁₂⁻¹ T₁⁻¹ T₂) ∈ R⁶, (v, ω) order; zero when T₁⁻¹T₂ = T̄₁₂ (T₂ = T₁ T̄₁₂)."""
    return (T12.inverse() @ (T1.inverse() @ T2)).log()


def as_se3(pose: Any) -> jaxlie.SE3:
    """``se3.as_pose`` with a numpy leaf, so that factor data stacks without device copies."""
    return jaxlie.SE3(np.asarray(as_pose(pose).wxyz_xyz, dtype=float))


def PriorFactor(
    key: Hashable,
    prior: Any,
    sigma: Any = None,
    information: Any = None,
    covariance: Any = None,
    robust: RobustKernel | None = None,
) -> Factor:
    """Prior T ≈ T̄ on a pose: r = Log(T̄⁻¹ T), cost ½ρ(‖W r‖²).

    ``sigma`` (scalar or 6 values), ``information`` or ``covariance`` (6×6) are in jaxlie
    order (v, ω): translation first. gtsam orders them (ω, v).
    """
    W = sqrt_information(6, sigma=sigma, information=information, covariance=covariance)
    return Factor(
        pose_prior_residual,
        (key,),
        args=(as_se3(prior),),
        sqrt_info=W,
        robust=robust,
        name="PriorFactor",
    )


def BetweenFactor(
    key1: Hashable,
    key2: Hashable,
    measured: Any,
    sigma: Any = None,
    information: Any = None,
    covariance: Any = None,
    robust: RobustKernel | None = None,
) -> Factor:
    """Relative pose T₁⁻¹T₂ ≈ T̄₁₂: r = Log(T̄₁₂⁻¹ T₁⁻¹ T₂), cost ½ρ(‖W r‖²).

    ``sigma`` (scalar or 6 values), ``information`` or ``covariance`` (6×6) are in jaxlie
    order (v, ω): translation first. gtsam orders them (ω, v).
    """
    W = sqrt_information(6, sigma=sigma, information=information, covariance=covariance)
    return Factor(
        pose_between_residual,
        (key1, key2),
        args=(as_se3(measured),),
        sqrt_info=W,
        robust=robust,
        name="BetweenFactor",
    )
