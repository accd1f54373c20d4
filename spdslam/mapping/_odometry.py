"""The odometry a run is given, in one place: its factors (the batch graph, the online
mapper's window and the loop closure's pose graph make them here), the spread of its
random walk, and the check of a trajectory against it.

Poses are T_wc (camera-to-world) as jaxlie parameters [qw qx qy qz x y z]; a step is
Sᵢ = Tᵢ⁻¹ Tᵢ₊₁; perturbations are on the right, T ⊞ δ = T Exp(δ), δ = (v, ω).

**The walk.** An odometry without a bound on each pose is modelled as the truth's steps
composed with noise, Ŝᵢ = Sᵢ Exp(εᵢ), εᵢ ~ N(0, Σ_step) (σ_step: ``odometry_translation``,
``odometry_rotation``). A pose chained from the first, T̂ᵢ = T₀ Ŝ₀ ⋯ Ŝᵢ₋₁, then departs
from the truth by δᵢ = Log(Tᵢ⁻¹ T̂ᵢ), to first order

    δᵢ = Ad(Ŝᵢ₋₁⁻¹) δᵢ₋₁ + εᵢ₋₁,    Σᵢ = Ad(Ŝᵢ₋₁⁻¹) Σᵢ₋₁ Ad(Ŝᵢ₋₁⁻¹)ᵀ + Σ_step,    Σ₀ = 0

(``walk_covariances``; a later segment of a joined sequence starts again from the σ that
places its first pose). The rotation's walk carries the camera sideways by its lever, which
Σᵢ holds in its translation block.

**The check.** A trajectory T̃ that a step of a run proposes (a replay's poses, a drift
correction, a pose graph closed by loops, an online window, the final optimisation) is
compared with the input T̂ pose by pose: dᵢ = Log(T̂ᵢ⁻¹ T̃ᵢ), mᵢ = √(dᵢᵀ Σᵢ⁻¹ dᵢ), the
departure in σ of the walk (``walk_departures``). Were T̃ the truth, mᵢ² would be χ²₆; a
departure beyond ``WALK_LIMIT`` σ anywhere is more than the odometry can have drifted, and
``check_trajectory`` refuses it (the caller keeps the input for that step and says so). A
change within the walk is not proven right by this check, only not impossible; a back end
moves a trajectory that far only with a verified loop (``_loops``).
"""

from __future__ import annotations

from dataclasses import dataclass

import jaxlie
import numpy as np

from ..factors import BetweenFactor, PriorFactor
from ..solver import X

__all__ = ["SEGMENT_PRIOR_SIGMA", "WALK_LIMIT", "TrajectoryCheck", "absolute_sigma", "check_trajectory",
           "odometry_factors", "step_sigma", "walk_covariances", "walk_departures"]

#: σ (v m, ω rad) of the prior on the first pose of each later segment of a joined sequence,
#: at the pose it was given (``Sequence.segments``): weak beside the objects it shares with
#: the first segment, it only fixes what they leave free.
SEGMENT_PRIOR_SIGMA = np.r_[np.full(3, 0.1), np.full(3, 0.05)]

#: The largest departure of a pose from its input, in σ of the odometry's walk (a Mahalanobis
#: distance with 6 degrees of freedom: 6σ is χ²₆ = 36, p ≈ 3·10⁻⁶), that ``check_trajectory``
#: lets a step of a run make.
WALK_LIMIT = 6.0


def step_sigma(s: dict) -> np.ndarray:
    """σ (6,) of one odometry step (v m, ω rad) from the run's sigmas."""
    return np.r_[np.full(3, s["odometry_translation"]), np.full(3, s["odometry_rotation"])]


def absolute_sigma(s: dict):
    """The σ (6,) of the absolute prior on each pose, or None when both are infinite."""
    t, r = s["absolute_translation"], s["absolute_rotation"]
    if np.isinf(t) and np.isinf(r):
        return None
    big = 1e6  # an infinite component: a prior that does not hold it
    return np.r_[np.full(3, big if np.isinf(t) else t), np.full(3, big if np.isinf(r) else r)]


def _steps(q: np.ndarray) -> np.ndarray:
    """The steps Tᵢ⁻¹ Tᵢ₊₁ (F − 1, 7) of poses q (F, 7)."""
    return np.asarray((jaxlie.SE3(q[:-1]).inverse() @ jaxlie.SE3(q[1:])).wxyz_xyz)  # type: ignore[arg-type]


def odometry_factors(wxyz_xyz, segments, s: dict, start: int = 0) -> list:
    """The trajectory's factors for the poses ``wxyz_xyz`` (F, 7) given as input, those that
    involve frames ``start`` … F − 1 (the batch: all; the online mapper: its window, whose
    earlier poses it holds): a prior on the first pose (σ ``first_pose``), the odometry
    between consecutive poses (σ_step, ``step_sigma``) and, unless unbounded
    (``absolute_sigma``), a prior on each later pose at its input. In a joined sequence
    (``segments``: the first frame of each later segment) no odometry across a segment's
    start; its first pose held weakly where it was placed (``SEGMENT_PRIOR_SIGMA``) and its
    later poses bounded relative to it (between factors with the per-pose σ) instead of
    where they were given, so that the segment moves as one body, placed by the objects it
    shares."""
    q = np.asarray(wxyz_xyz, dtype=float).reshape(-1, 7)
    n = len(q) - 1  # steps
    out: list = []
    if start == 0 and len(q):
        out.append(PriorFactor(X(0), jaxlie.SE3(q[0]), sigma=s["first_pose"]))
    starts = [int(k) for k in segments if 0 < k <= n]
    linked = np.ones(max(n, 0), bool)
    linked[[k - 1 for k in starts]] = False
    linked[: max(start - 1, 0)] = False  # the step into frame k is step k − 1
    i = np.flatnonzero(linked)
    if i.size:
        steps = _steps(q[i[0]:])[i - i[0]]
        out.append(BetweenFactor.many([X(int(k)) for k in i], [X(int(k) + 1) for k in i], steps,
                                      sigma=step_sigma(s)))
    for k in starts:  # a weak hold where the segment was placed: its gauge if objects do not fix it
        if k >= start:
            out.append(PriorFactor(X(k), jaxlie.SE3(q[k]), sigma=SEGMENT_PRIOR_SIGMA))
    pose_sigma = absolute_sigma(s)
    if pose_sigma is None:
        return out
    last = starts[0] if starts else n + 1  # frames 1 … last − 1 are bounded
    first = max(start, 1)
    if last > first:
        out.append(PriorFactor.many([X(k) for k in range(first, last)], q[first:last], sigma=pose_sigma))
    for k0, k1 in zip(starts, [*starts[1:], n + 1]):  # a later segment: each pose bounded relative to its first
        lo = max(k0 + 1, start)
        if k1 > lo:
            rel = np.asarray((jaxlie.SE3(np.broadcast_to(q[k0], (k1 - lo, 7))).inverse()  # type: ignore[arg-type]
                              @ jaxlie.SE3(q[lo:k1])).wxyz_xyz)  # type: ignore[arg-type]
            out.append(BetweenFactor.many([X(k0)] * (k1 - lo), [X(k) for k in range(lo, k1)], rel, sigma=pose_sigma))
    return out


def walk_covariances(wxyz_xyz, s: dict, segments=(), start=None) -> np.ndarray:
    """Σᵢ (F, 6, 6): the covariance of each input pose's departure from the truth under the
    odometry's random walk since the first pose (module docstring), in the pose's own frame.
    ``segments``: a later segment starts again from ``SEGMENT_PRIOR_SIGMA``; ``start``
    (6, 6): Σ₀ (default the first pose's prior, σ ``first_pose``; 0: from the first pose
    exactly)."""
    q = np.asarray(wxyz_xyz, dtype=float).reshape(-1, 7)
    F = len(q)
    out = np.zeros((F, 6, 6))
    if F:
        out[0] = np.eye(6) * s["first_pose"] ** 2 if start is None else start
    if F < 2:
        return out
    A = np.asarray(jaxlie.SE3(_steps(q)).inverse().adjoint())  # type: ignore[arg-type]  # Ad(Sᵢ⁻¹)
    S = np.diag(step_sigma(s) ** 2)
    restart = np.diag(SEGMENT_PRIOR_SIGMA**2)
    later = set(int(k) for k in segments)
    for i in range(1, F):
        if i in later:
            out[i] = restart
            continue
        out[i] = A[i - 1] @ out[i - 1] @ A[i - 1].T + S
    return out


def walk_departures(input_wxyz_xyz, wxyz_xyz, covariances) -> np.ndarray:
    """mᵢ (F,): each pose's departure from its input in σ of the walk, √(dᵢᵀ Σᵢ⁻¹ dᵢ) with
    dᵢ = Log(T̂ᵢ⁻¹ T̃ᵢ) (module docstring); a pose whose Σᵢ is singular (held exactly) is 0
    where it did not move and inf where it did."""
    a = np.asarray(input_wxyz_xyz, dtype=float).reshape(-1, 7)
    b = np.asarray(wxyz_xyz, dtype=float).reshape(-1, 7)
    d = np.asarray((jaxlie.SE3(a).inverse() @ jaxlie.SE3(b)).log())  # type: ignore[arg-type]
    C = np.asarray(covariances, dtype=float)
    m = np.zeros(len(d))
    ok = np.linalg.det(C) > 0
    if ok.any():
        sol = np.linalg.solve(C[ok], d[ok][..., None])[..., 0]
        m[ok] = np.sqrt(np.maximum(np.einsum("ij,ij->i", d[ok], sol), 0.0))
    held = ~ok & (np.linalg.norm(d, axis=1) > 1e-9)
    m[held] = np.inf
    return m


@dataclass(frozen=True)
class TrajectoryCheck:
    """``check_trajectory``'s answer for one step of a run: whether it is ``accepted``, how
    far it moved the cameras from the input (median and most, m), its largest departure in
    σ of the walk and at which frame, and the limit."""

    step: str
    accepted: bool
    moved_median: float
    moved_max: float
    worst: float
    frame: int
    limit: float = WALK_LIMIT

    def note(self) -> str:
        """One line for the run's notes."""
        moved = (f"it moved the cameras by {1e3 * self.moved_median:.3g} mm median, {1e3 * self.moved_max:.3g} mm "
                 f"most, at most {self.worst:.3g}σ of the odometry's walk (frame {self.frame})")
        if self.accepted:
            return f"{self.step}: {moved}, within the {self.limit:g}σ the odometry allows"
        return (f"{self.step} refused: {moved}, beyond the {self.limit:g}σ the odometry allows; the input "
                "poses are kept for this step")

    def as_dict(self) -> dict:
        return {"step": self.step, "accepted": bool(self.accepted), "moved_median_m": float(self.moved_median),
                "moved_max_m": float(self.moved_max), "worst_sigma": float(self.worst), "frame": int(self.frame),
                "limit_sigma": float(self.limit)}


def check_trajectory(step: str, input_wxyz_xyz, wxyz_xyz, covariances, limit: float = WALK_LIMIT
                     ) -> TrajectoryCheck:
    """The check of a trajectory a ``step`` proposes against the input and the walk's
    covariances (``walk_covariances``): refused when a pose departs by more than ``limit`` σ
    (module docstring) or is not finite."""
    a = np.asarray(input_wxyz_xyz, dtype=float).reshape(-1, 7)
    b = np.asarray(wxyz_xyz, dtype=float).reshape(-1, 7)
    if not np.all(np.isfinite(b)):
        return TrajectoryCheck(step, False, float("nan"), float("nan"), float("inf"),
                               int(np.flatnonzero(~np.all(np.isfinite(b), axis=1))[0]), limit)
    m = walk_departures(a, b, covariances)
    moved = np.linalg.norm(b[:, 4:] - a[:, 4:], axis=1)
    k = int(np.argmax(m)) if len(m) else 0
    worst = float(m[k]) if len(m) else 0.0
    return TrajectoryCheck(step, bool(worst <= limit), float(np.median(moved)) if len(moved) else 0.0,
                           float(np.max(moved)) if len(moved) else 0.0, worst, k, limit)
