"""The noise model of the input trajectory.

The odometry factors of a run say two things about the input trajectory T₀ … T_{F−1}:

- its relative motion per frame step is accurate to σ_step (``odometry_translation`` m,
  ``odometry_rotation`` rad): a ``BetweenFactor`` per step;
- each pose is accurate to σ_abs (``absolute_translation``, ``absolute_rotation``): a
  ``PriorFactor`` per pose at its input value. A SLAM trajectory with loop closures is
  globally consistent: its error is bounded, not a random walk that grows as √F σ_step,
  which is what the step factors alone would allow (on fr2_desk, 2893 steps: the boxes bent
  ORB-SLAM2's trajectory from 8 mm to 71 mm ATE). An infinite σ_abs leaves the steps alone:
  odometry that drifts.

Where each comes from, first found: ``--sigma``; the sequence's ``priors.yaml``
(``trajectory_sigma``, ``trajectory_absolute_sigma``); for σ_step, the input trajectory's own
jitter (``estimate_step_sigma``); for σ_abs, ``DEFAULT_MAPPING_SIGMAS`` (docs/sequences.md
gives the measurement behind it).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ["estimate_step_sigma", "MIN_JITTER_TRIPLETS", "STEP_SIGMA_FLOOR"]

#: The estimate needs this many frame triplets; a shorter trajectory takes the table's σ_step.
MIN_JITTER_TRIPLETS = 20
#: The smallest σ_step an estimate returns (m and rad): a perfectly smooth input (a
#: synthetic or interpolated trajectory) must not become a rigid one.
STEP_SIGMA_FLOOR = 1e-5
_MAD = 1.4826  # the MAD of a normal distribution is 0.6745 σ


def _robust_std(x: np.ndarray) -> float:
    """1.4826 × the median absolute deviation, pooled over the columns of x (n, 3)."""
    return float(_MAD * np.median(np.abs(x - np.median(x, axis=0))))


def estimate_step_sigma(timestamps, poses_tum) -> tuple[float, float] | None:
    """(σ_t m, σ_r rad) of a trajectory's relative motion per frame step, from its jitter, or
    None with fewer than ``MIN_JITTER_TRIPLETS`` usable frames.

    Each interior pose Tᵢ is predicted from its neighbours by interpolating at tᵢ (linear
    centre, spherical-linear rotation); the residual eᵢ = T̂ᵢ⁻¹Tᵢ (centre difference in m,
    rotation vector in rad). For independent pose errors of σ per axis, eᵢ has variance
    σ²(1 + a² + (1 − a)²) with a the interpolation fraction (1.5 σ² at a = ½), and a
    relative motion 2σ²: σ_step = √2 σ, σ from the robust spread (1.4826 MAD) of eᵢ. The
    camera's own acceleration adds to eᵢ (≈ ¼ a Δt²), so the estimate errs large. Triplets
    whose two steps differ in duration by more than a factor 2 (dropped frames) are left out.
    """
    t = np.asarray(timestamps, float)
    P = np.asarray(poses_tum, float)
    if len(t) < 3:
        return None
    d1, d2 = t[1:-1] - t[:-2], t[2:] - t[1:-1]
    ok = (d1 > 0) & (d2 > 0) & (np.maximum(d1, d2) <= 2 * np.minimum(d1, d2))
    if ok.sum() < MIN_JITTER_TRIPLETS:
        return None
    i = np.flatnonzero(ok) + 1
    a = (t[i] - t[i - 1]) / (t[i + 1] - t[i - 1])
    c = P[i - 1, :3] + a[:, None] * (P[i + 1, :3] - P[i - 1, :3])
    r0, r1, ri = (Rotation.from_quat(P[j, 3:7]) for j in (i - 1, i + 1, i))
    rhat = r0 * Rotation.from_rotvec((r0.inv() * r1).as_rotvec() * a[:, None])
    e_t = P[i, :3] - c
    e_r = (rhat.inv() * ri).as_rotvec()
    scale = np.sqrt(2.0 / np.median(1.0 + a**2 + (1.0 - a) ** 2))
    return (max(STEP_SIGMA_FLOOR, scale * _robust_std(e_t)),
            max(STEP_SIGMA_FLOOR, scale * _robust_std(e_r)))
