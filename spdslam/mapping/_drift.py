"""Objects against drift: a recording's odometry corrected on knots in time.

With no bound on each pose (``trajectory_absolute_sigma: .inf``: odometry that drifts), the
boxes alone move every pose on its own, and on a real recording they fix a camera to a few
centimetres at best (docs/map-reuse.md): worse than a good odometry over a few seconds.
Drift is slow, so ``correct_drift`` models the trajectory as the odometry's poses T_i
composed with a correction that changes slowly in time,

    T̂_i = K(t_i) T_i,    K(t) = K_a Exp(w Log(K_a⁻¹ K_b)),  w = (t − t_a)/(t_b − t_a),

between knots K_0 … K_M spaced evenly over the recording, about ``interval`` seconds apart,
and fits the knots and the objects to the boxes (``factors.DriftBoxFactor``: the inverse box
model), with the objects' own factors. The knots follow the odometry's random walk: K_0 is
held at the identity (σ ``first_pose``) and K_j⁻¹ K_{j+1} ~ N(0, n_j σ²), n_j the frame steps
between them, σ the step's σ (``odometry_translation``, ``odometry_rotation``) with the
rotation's lever on the camera centres (their RMS distance r̄ from the origin) added to the
translation: σ_t + r̄ σ_r. A correction that cannot follow the drift between two knots
leaves at most the random walk's spread midway, σ √(n/4): the bound ``correct_drift``
returns for each pose around its corrected value.
"""

from __future__ import annotations

from dataclasses import dataclass

import jaxlie
import numpy as np

from ..factors import BetweenFactor, DriftBoxFactor, PriorFactor
from ..geometry import interpolated_frame
from ..geometry.se3 import to_tum
from ..solver import L, LevenbergMarquardt, NonlinearFactorGraph, Symbol, Values
from ._context import SequenceContext, object_shape
from ._graph import inverse_box_sigma, object_factors, with_robust_by_type
from ._methods import Method, robust_kernel

__all__ = ["DriftCorrection", "correct_drift", "drift_knots"]


def K(j: int) -> Symbol:
    """The key of the drift correction's knot j."""
    return Symbol("k", int(j))


def drift_knots(timestamps, interval: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(knot times (M + 1,), each frame's interval j (F,), its weight w ∈ [0, 1] (F,)):
    M = max(1, round(duration / interval)) intervals of equal length from the first frame's
    time to the last's; frame i lies between knots j and j + 1 at t_i = (1 − w) t_j + w t_{j+1}."""
    t = np.asarray(timestamps, dtype=float)
    span = float(t[-1] - t[0])
    m = max(1, int(round(span / interval))) if span > 0 else 1
    knots = t[0] + (span if span > 0 else 1.0) * np.arange(m + 1) / m
    j = np.clip(np.searchsorted(knots, t, side="right") - 1, 0, m - 1)
    w = np.clip((t - knots[j]) / (knots[j + 1] - knots[j]), 0.0, 1.0)
    return knots, j, w


@dataclass(frozen=True)
class DriftCorrection:
    """``correct_drift``'s answer: the corrected poses (F, 7 TUM fields tx ty tz qx qy qz qw),
    the knots' times and frames (``jaxlie.SE3`` each), the objects {id: landmark} it ended at, the bound
    σ (6,) (v m, ω rad) left on each pose, the frame steps per interval, the LM result, and
    how far the correction moved each camera centre (F,) (m)."""

    poses_tum: np.ndarray
    knot_times: np.ndarray
    knots: list
    landmarks: dict
    bound: np.ndarray
    steps_per_interval: float
    result: object
    camera_shift: np.ndarray

    def note(self) -> str:
        """One line for the run's notes: what the correction did."""
        shift = 1e3 * np.asarray(self.camera_shift, dtype=float)
        turned = np.degrees(np.max([np.linalg.norm(np.asarray(k.rotation().log())) for k in self.knots]))
        gap = float(np.median(np.diff(self.knot_times)))
        return (f"drift corrected on {len(self.knots)} knots {gap:.3g} s apart (cameras moved by "
                f"{np.median(shift):.3g} mm median, {np.max(shift):.3g} mm most; knots turned {turned:.3g}° most); "
                f"each pose then within {1e3 * self.bound[0]:.3g} mm and {1e3 * self.bound[3]:.3g} mrad "
                "of its corrected value")


def correct_drift(ctx: SequenceContext, tracks, landmarks: dict, method: Method, s: dict, interval: float,
                  planes=None, optimizer: LevenbergMarquardt | None = None) -> DriftCorrection | None:
    """The drift correction of the trajectory of ``ctx`` (module docstring) from the boxes of
    ``tracks`` whose objects are in ``landmarks`` {id: landmark} and seen as ellipsoids
    (cuboid-shaped objects take no part), with the run's sigmas ``s``
    (``mapping_sigmas``), solved by ``optimizer`` (default: LM's defaults). None when no
    object takes part."""
    t = np.asarray(ctx.seq.timestamps, dtype=float)
    knot_times, j, w = drift_knots(t, interval)
    m = len(knot_times) - 1
    robust = robust_kernel(method.robust, method.robust_k)
    factors: list = []
    used = {}
    for tr in tracks:
        if tr.id not in landmarks or object_shape(method, ctx.priors, tr.label) != "ellipsoid":
            continue
        f = np.asarray(tr.frames, dtype=int)
        boxes = np.asarray(tr.boxes, dtype=float).reshape(-1, 4)
        sigma = inverse_box_sigma(boxes, s)
        factors.append(DriftBoxFactor.many([K(a) for a in j[f]], [K(a + 1) for a in j[f]], L(tr.id),
                                           ctx.wxyz_xyz[f], w[f], boxes, ctx.camera, sigma=sigma, robust=robust,
                                           truncation_margin=method.margin))
        factors += object_factors(ctx, tr, landmarks[tr.id], method, s, planes, boxes=False)
        used[tr.id] = landmarks[tr.id]
    if not used:
        return None
    steps = np.maximum(np.bincount(j, minlength=m)[:m], 1).astype(float)
    centres = ctx.wxyz_xyz[:, 4:]
    lever = float(np.sqrt(np.mean(np.sum(centres * centres, axis=1))))
    st, sr = s["odometry_translation"], s["odometry_rotation"]
    step_sigma = np.r_[np.full(3, st + lever * sr), np.full(3, sr)]
    factors.append(PriorFactor(K(0), jaxlie.SE3.identity(), sigma=s["first_pose"]))
    identity = np.tile(np.asarray(jaxlie.SE3.identity().wxyz_xyz), (m, 1))
    factors.append(BetweenFactor.many([K(i) for i in range(m)], [K(i + 1) for i in range(m)], identity,
                                      sigma=np.sqrt(steps)[:, None] * step_sigma))
    values = Values()
    for i in range(m + 1):
        values[K(i)] = jaxlie.SE3.identity()
    for k, lm in used.items():
        values[L(k)] = lm
    graph = NonlinearFactorGraph(with_robust_by_type(factors, method))
    res = (optimizer or LevenbergMarquardt()).optimize(graph, values)
    knots = [res.values[K(i)] for i in range(m + 1)]
    K_all = np.stack([np.asarray(k.wxyz_xyz) for k in knots])
    Ka, Kb = jaxlie.SE3(K_all[j]), jaxlie.SE3(K_all[j + 1])  # type: ignore[arg-type]
    corrected = interpolated_frame(Ka, Kb, w[:, None]) @ jaxlie.SE3(ctx.wxyz_xyz)  # type: ignore[arg-type]
    n = float(np.median(steps))
    bound = np.r_[np.full(3, st), np.full(3, sr)] * np.sqrt(max(n, 1.0) / 4.0)
    shift = np.linalg.norm(np.asarray(corrected.translation()) - ctx.wxyz_xyz[:, 4:], axis=1)
    return DriftCorrection(to_tum(corrected), knot_times, knots,
                           {k: res.values[L(k)] for k in used}, bound, n, res, shift)
