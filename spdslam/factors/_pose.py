"""Pose factors on SE(3): priors and relative-pose (odometry / loop-closure) constraints.

Poses are ``jaxlie.SE3`` (camera-to-world T_wc), perturbed on the right, T ⊞ δ = T·Exp(δ),
with tangent vectors δ = (v, ω) in jaxlie's order: translation first, rotation second.

    prior:    r(T)      = Log(T̄⁻¹ T)              ∈ R⁶
    between:  r(T₁, T₂) = Log(T̄₁₂⁻¹ T₁⁻¹ T₂)      ∈ R⁶

Log is the full SE(3) logarithm (gtsam's Pose3::Logmap with the expmap chart), so with the
same noise these residuals equal gtsam's PriorFactorPose3 / BetweenFactorPose3 errors up to
the order of the components: gtsam orders a Pose3 tangent (ω, v), rotation first. Sigmas,
information and covariance matrices given here are in jaxlie order (v, ω); permute gtsam's
with ``[3, 4, 5, 0, 1, 2]``. Neither type has a default noise: without one, W = I.
"""

from __future__ import annotations

from typing import Any, Hashable

import jaxlie
import numpy as np

from ..geometry.se3 import as_pose
from ._base import Factor, FactorBatch, RobustKernel, diagonal_sqrt_information

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
    return jaxlie.SE3(np.asarray(as_pose(pose).wxyz_xyz, dtype=float))  # type: ignore[arg-type]  # numpy leaf


def _pose_rows(poses, n: int, what: str) -> np.ndarray:
    """(n, 7) jaxlie parameters of n poses: a batched ``jaxlie.SE3``, an (n, 7) array or a
    list of poses (each as ``as_se3`` takes it)."""
    if isinstance(poses, jaxlie.SE3) or (isinstance(poses, np.ndarray) and poses.shape[-1:] == (7,)):
        rows = np.asarray(poses.wxyz_xyz if isinstance(poses, jaxlie.SE3) else poses, dtype=float).reshape(-1, 7)
    else:
        rows = np.stack([np.asarray(as_se3(p).wxyz_xyz) for p in poses]) if len(poses) else np.zeros((0, 7))
    if len(rows) != n:
        raise ValueError(f"{n} factors but {len(rows)} {what}")
    if not np.all(np.isfinite(rows)):
        raise ValueError(f"{what} must be finite")
    return rows


def _pose_batch(cls, key_columns, rows, sigma, robust) -> FactorBatch:
    n = len(rows)
    first = cls(*([None] * len(key_columns)), jaxlie.SE3(rows[0] if n else np.r_[1.0, np.zeros(6)]))
    _, treedef, shapes = first.flat_args()
    W = diagonal_sqrt_information(1.0 if sigma is None else sigma, n, 6)
    return FactorBatch(cls, key_columns, [rows], treedef, shapes, W, robust)


class PriorFactor(Factor):
    """Prior T ≈ T̄ on a pose: r = Log(T̄⁻¹ T), cost ½ρ(‖W r‖²); noise in jaxlie order (v, ω)."""

    kind = "prior"
    residual = staticmethod(pose_prior_residual)
    variables = ("pose",)
    dim = 6
    group = "prior"

    def __init__(self, key: Hashable, prior: Any, **noise):
        super().__init__((key,), (as_se3(prior),), **noise)

    @classmethod
    def many(cls, keys, priors, *, sigma: Any = None, robust: RobustKernel | None = None) -> FactorBatch:
        """``PriorFactor(keys[i], priors[i], sigma=sigma[i])`` for n poses as one
        ``FactorBatch`` (priors: a batched ``jaxlie.SE3``, (n, 7) jaxlie parameters or a list;
        ``sigma`` a scalar, 6 values or (n, 6); None: W = I)."""
        keys = list(keys)
        return _pose_batch(cls, (keys,), _pose_rows(priors, len(keys), "priors"), sigma, robust)


class BetweenFactor(Factor):
    """Relative pose T₁⁻¹T₂ ≈ T̄₁₂ (odometry, loop closures): r = Log(T̄₁₂⁻¹ T₁⁻¹ T₂), cost
    ½ρ(‖W r‖²); noise in jaxlie order (v, ω)."""

    kind = "between"
    residual = staticmethod(pose_between_residual)
    variables = ("pose", "pose")
    dim = 6
    group = "odometry"

    def __init__(self, key1: Hashable, key2: Hashable, measured: Any, **noise):
        super().__init__((key1, key2), (as_se3(measured),), **noise)

    @classmethod
    def many(cls, keys1, keys2, measured, *, sigma: Any = None,
             robust: RobustKernel | None = None) -> FactorBatch:
        """``BetweenFactor(keys1[i], keys2[i], measured[i], sigma=sigma[i])`` for n relative
        poses as one ``FactorBatch`` (measured as ``PriorFactor.many``'s priors)."""
        keys1, keys2 = list(keys1), list(keys2)
        if len(keys1) != len(keys2):
            raise ValueError(f"BetweenFactor.many: {len(keys1)} first keys and {len(keys2)} second keys")
        rows = _pose_rows(measured, len(keys1), "relative poses")
        return _pose_batch(cls, (keys1, keys2), rows, sigma, robust)
