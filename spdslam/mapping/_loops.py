"""Loop closure with objects: a drifting odometry corrected where the camera comes back.

On a trajectory without a bound on each pose (odometry that drifts) the boxes alone do not
correct the drift on real recordings: a detector's boxes are biased by several pixels per
object and viewpoint, the same bias over hundreds of frames, and thousands of them pull each
pose where the model wants it (docs/drift.md measures it). So the run keeps two questions
apart, as ORB-SLAM's and ROMAN's loop closures do (``close_loops``):

1. **Submaps**: the recording cut into stretches of ``LOOP_SUBMAP_SECONDS`` (a short one into
   ``LOOP_MIN_SUBMAPS``); over one stretch the odometry drifts little.
2. **Candidates**: pairs of stretches far enough apart in time that the odometry's walk
   between them may have turned the camera by ``LOOP_MIN_WALK`` (one σ), whose cameras come
   back near each other in the input trajectory: centres within ``LOOP_RADIUS`` and optical
   axes within ``LOOP_ANGLE``, each widened by 3σ of the walk between the two
   (``_odometry.walk_covariances``). A revisit seen from about the same place sees the
   same objects with about the same box biases. At most ``LOOP_MAX_CANDIDATES``, the
   closest first, one per pair of stretches.
3. **Each stretch mapped alone** (``map_stretch``, the run's method with the poses held at
   the input): its objects where that stretch's poses put them.
4. **Verification** (``_verify``): the later stretch's objects matched to the earlier's by the
   relocaliser (``localize_objects``), only within the transform the odometry's walk allows
   (``TransformGate``: 4σ) and refused when a rival nearly matches as many; refined with the
   later stretch's boxes against the earlier's objects and, the other way, with the
   earlier's boxes against the later's (``refine_localization``). A loop is verified when at
   least ``LOOP_MIN_MATCHES`` objects match, the two ways agree (their difference within
   χ²₆ at ``LOOP_P`` of the two covariances), the boxes of each stretch confirm the other's
   objects where they should see them (``box_agreement`` ≥ ``MIN_BOX_AGREEMENT``), the
   correction it asks is one the odometry can have drifted (χ²₆ at ``LOOP_P`` against the
   walk between the two), and it is a correction: different from none beyond χ²₆ at
   ``LOOP_P`` of its own covariance. A loop that cannot tell the drift from its own error
   would only add that error (on real boxes it is as large as the drift over a minute).
   Then each verified loop must be confirmed by a second one from another place that agrees
   with it (``_confirmed``), as ORB-SLAM waits for consistent detections.
5. **Pose graph** (``solve_pose_graph``): every pose, the odometry (``odometry_factors``) and each
   verified loop as a ``BetweenFactor`` between the two stretches' middle frames (the
   revisit's closest frames), its
   covariance the two ways' mean plus their disagreement and ``LOOP_SIGMA_FLOOR``; solved
   by LM. A loop whose residual there exceeds χ²₆ at ``LOOP_P`` disagrees with the others
   and the odometry: the worst is rejected and the graph solved again, until all agree (a
   wrong loop must not bend the trajectory). The result is then checked against the
   odometry (``check_trajectory``); refused, the input is kept.

``run_sequence`` then maps the objects with each pose bounded near the corrected trajectory
(``RunSettings.initial_poses``). Without a verified loop the corrected trajectory is the
input: a back end does not take out drift that it cannot see.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Any, Callable

import jaxlie
import numpy as np

from ..factors import BetweenFactor
from ..frontend import Track
from ..geometry import as_ellipsoid
from ..io import MapObject
from ..solver import L, LevenbergMarquardt, NonlinearFactorGraph, Values, X
from ._context import SequenceContext
from ._graph import mapping_sigmas, object_factors, with_robust_by_type
from ._methods import Method
from ._odometry import TrajectoryCheck, check_trajectory, odometry_factors, step_sigma, walk_covariances
from ._reuse import (
    MIN_BOX_AGREEMENT,
    Localization,
    LocalizationError,
    TransformGate,
    box_agreement,
    localize_objects,
    refine_localization,
)
from ._run import degenerate, object_uncertainty

__all__ = ["LOOP_ANGLE", "LOOP_MAX_CANDIDATES", "LOOP_MIN_FRAMES", "LOOP_MIN_MATCHES",
           "LOOP_MIN_SUBMAPS", "LOOP_P", "LOOP_RADIUS", "LOOP_SIGMA_FLOOR", "LOOP_SUBMAP_SECONDS", "HeldMap", "Loop",
           "LoopClosure", "OnlineLoopClosure", "close_loops", "loop_covariance", "solve_pose_graph",
           "stretch_objects", "submaps_of"]

#: The length of a submap (s), at most; a recording shorter than ``LOOP_MIN_SUBMAPS`` of them
#: is cut into that many.
LOOP_SUBMAP_SECONDS = 5.0
LOOP_MIN_SUBMAPS = 8
#: Frames of a submap, at least.
LOOP_MIN_FRAMES = 10
#: A revisit: camera centres within this (m) …
LOOP_RADIUS = 0.75
#: … and optical axes within this (rad, 30°), each widened by 3σ of the walk between the two.
LOOP_ANGLE = float(np.radians(30.0))
#: Candidates tried at most, the closest revisits first.
LOOP_MAX_CANDIDATES = 12
#: A revisit is a candidate only when the odometry's walk between the two stretches may
#: have turned the camera this much (rad, 3°: one σ of the rotation's walk): nearer in time,
#: a loop measures less drift than its own error (docs/drift.md).
LOOP_MIN_WALK = float(np.radians(3.0))
#: Objects a verified loop matches at least.
LOOP_MIN_MATCHES = 4
#: The significance of the χ²₆ tests of a loop (two ways' agreement, the odometry, the graph).
LOOP_P = 1e-3
#: σ added to each loop's (v m, ω rad): what the two ways' agreement cannot show (both rest on
#: the same objects and boxes).
LOOP_SIGMA_FLOOR = np.r_[np.full(3, 0.01), np.full(3, np.radians(0.5))]
#: The gate of the matching in σ of the walk between the two stretches.
GATE_SIGMAS = 4.0


def _chi2_limit() -> float:
    """The χ²(6) quantile at 1 − ``LOOP_P`` (scipy.stats imported here, when a loop is tried)."""
    from scipy.stats import chi2

    return float(chi2.ppf(1.0 - LOOP_P, 6))


@dataclass(frozen=True)
class Loop:
    """A candidate loop and what became of it: the two stretches (first and last frames),
    the frames the constraint links (their middles), the transform ``T`` (4×4: x_earlier =
    T x_later, the later stretch's input frame into the earlier's) and its ``covariance``
    (6×6, left perturbation x ↦ Exp(ξ)·x, ξ = (v, ω)), the objects matched and the best
    rival's count, the share of expected sightings the boxes confirmed (later, earlier),
    the χ² of the two ways' difference, against the odometry and in the pose graph, and
    ``status`` "verified", "rejected" or "not verified" with ``reason``."""

    earlier: tuple
    later: tuple
    frames: tuple
    status: str
    reason: str = ""
    matches: int = 0
    rival: int = 0
    T: np.ndarray | None = None
    covariance: np.ndarray | None = None
    agreement: tuple = ()
    chi2_ways: float = float("nan")
    chi2_odometry: float = float("nan")
    chi2_graph: float = float("nan")

    def as_dict(self) -> dict:
        out: dict[str, Any] = {
            "earlier_frames": [int(f) for f in self.earlier], "later_frames": [int(f) for f in self.later],
            "frames": [int(f) for f in self.frames], "status": self.status, "reason": self.reason,
            "matches": int(self.matches), "rival_matches": int(self.rival),
            "box_agreement": [float(a) for a in self.agreement],
            "chi2_ways": float(self.chi2_ways), "chi2_odometry": float(self.chi2_odometry),
            "chi2_graph": float(self.chi2_graph)}
        if self.T is not None:
            out["T_earlier_later"] = np.asarray(self.T).tolist()
        if self.covariance is not None:
            out["covariance"] = np.asarray(self.covariance).tolist()
        return out

    def describe(self) -> str:
        what = f"frames {self.earlier[0]}–{self.earlier[1]} and {self.later[0]}–{self.later[1]}"
        if self.status == "verified":
            turn = np.degrees(np.linalg.norm(_log(self.T)[3:])) if self.T is not None else float("nan")
            return (f"loop {what}: {self.matches} objects, correction {turn:.2g}°, "
                    f"boxes agree {100 * min(self.agreement):.0f} %")
        return f"loop {what} {self.status}: {self.reason}"


@dataclass(frozen=True)
class LoopClosure:
    """``close_loops``' answer: the corrected poses (F, 7, jaxlie's wxyz_xyz; the input when
    no loop is verified), every candidate ``Loop``, the check of the corrected trajectory
    against the odometry (None when nothing moved), and the submaps (first, last frame)."""

    poses: np.ndarray
    loops: list
    check: TrajectoryCheck | None
    submaps: list = field(default_factory=list)

    @property
    def verified(self) -> list:
        return [lp for lp in self.loops if lp.status == "verified"]

    def notes(self) -> list:
        """Lines for the run's notes: the summary, then each loop."""
        v = self.verified
        rejected = sum(lp.status == "rejected" for lp in self.loops)
        head = (f"loop closure: {len(self.submaps)} submaps, {len(self.loops)} candidate revisits, {len(v)} loops "
                f"verified, {rejected} rejected, {len(self.loops) - len(v) - rejected} not verified")
        if not v:
            head += "; the trajectory is the input's"
        elif self.check is not None:
            head += f"; {self.check.note()}"
        return [head] + [lp.describe() for lp in self.loops]

    def as_dict(self) -> dict:
        return {"submaps": [[int(a), int(b)] for a, b in self.submaps], "loops": [lp.as_dict() for lp in self.loops],
                "check": None if self.check is None else self.check.as_dict()}


def _log(T) -> np.ndarray:
    """Log of a 4×4 rigid motion, (v, ω)."""
    return np.asarray(jaxlie.SE3.from_matrix(np.asarray(T, float)).log())


def _matrix(q) -> np.ndarray:
    return np.asarray(jaxlie.SE3(np.asarray(q, float)).as_matrix())  # type: ignore[arg-type]


def _adjoint(T) -> np.ndarray:
    return np.asarray(jaxlie.SE3.from_matrix(np.asarray(T, float)).adjoint())


def submaps_of(timestamps, seconds: float | None = None, min_frames: int = LOOP_MIN_FRAMES) -> list:
    """(first, last) frames of consecutive stretches of about ``seconds`` each (default
    ``LOOP_SUBMAP_SECONDS``, or the recording's duration over ``LOOP_MIN_SUBMAPS`` when
    shorter), of at least ``min_frames`` frames (the last one joined to the one before when
    shorter than half)."""
    t = np.asarray(timestamps, float)
    if seconds is None:
        duration = float(t[-1] - t[0]) if len(t) > 1 else 0.0
        rate = (len(t) - 1) / duration if duration > 0 else 1.0
        seconds = max(min(LOOP_SUBMAP_SECONDS, duration / LOOP_MIN_SUBMAPS), min_frames / rate)
    if len(t) < 2 * min_frames or seconds <= 0:
        return [(0, len(t) - 1)] if len(t) else []
    k = np.floor((t - t[0]) / seconds).astype(int)
    edges = np.flatnonzero(np.diff(k)) + 1
    starts = [0, *[int(e) for e in edges]]
    ends = [*[int(e) - 1 for e in edges], len(t) - 1]
    out = [(a, b) for a, b in zip(starts, ends)]
    if len(out) > 1 and (t[out[-1][1]] - t[out[-1][0]] < 0.5 * seconds or out[-1][1] - out[-1][0] + 1 < min_frames):
        out[-2:] = [(out[-2][0], out[-1][1])]
    return out


def _walk_between(q, a: int, b: int, s: dict) -> np.ndarray:
    """Σ (6, 6) of the walk from frame a to frame b (b's frame), as ``walk_covariances`` over
    frames a … b, from frame a exactly."""
    return walk_covariances(q[a:b + 1], s, start=np.zeros((6, 6)))[-1]


def candidates(ctx: SequenceContext, subs: list, s: dict, later=None) -> list:
    """The candidate revisits (module docstring, step 2): [(k, l, i, j)] with k < l − 1 the
    stretches and i, j the closest pair of their frames, the closest first; ``later``: only
    those whose later stretch l is one of these (an online run's new submaps)."""
    R, C = ctx.camera_axes
    z = R[:, :, 2]
    sub = [np.arange(a, b + 1, max(1, (b - a + 1) // 40)) for a, b in subs]  # ≤ ~40 frames a stretch
    sig = step_sigma(s)
    out = []
    allowed = set(range(len(subs)) if later is None else later)
    for k in range(len(subs)):
        for li in range(k + 2, len(subs)):
            if li not in allowed:
                continue
            fa, fb = sub[k], sub[li]
            n = max(int(fb[0] - fa[-1]), 1)
            if np.sqrt(n) * sig[3] < LOOP_MIN_WALK:
                continue
            # the walk's spread over n steps: rotation, and translation with the rotation's lever
            # over the cameras' distance from each other
            rot = 3.0 * np.sqrt(n) * sig[3]
            d = np.linalg.norm(C[fa][:, None] - C[fb][None], axis=-1)
            ang = np.arccos(np.clip(z[fa] @ z[fb].T, -1.0, 1.0))
            reach = 3.0 * np.sqrt(n) * sig[0] + rot * np.linalg.norm(C[fb] - C[fa[0]], axis=1).max()
            ok = (d <= LOOP_RADIUS + reach) & (ang <= LOOP_ANGLE + rot)
            if not ok.any():
                continue
            score = np.where(ok, d / LOOP_RADIUS + ang / LOOP_ANGLE, np.inf)
            i, j = np.unravel_index(int(np.argmin(score)), score.shape)
            out.append((float(score[i, j]), k, li, int(fa[i]), int(fb[j])))
    out.sort()
    return [(k, li, i, j) for _, k, li, i, j in out[:LOOP_MAX_CANDIDATES]]


def _world_walk(q, a: int, b: int, s: dict) -> np.ndarray:
    """Σ (6, 6) of the walk between frames a ≤ b as a correction T = Exp(ξ) in world
    coordinates: the departure e at b (b's frame) is Ad(T_b⁻¹) ξ, so ξ = Ad(T_b) e."""
    a, b = min(a, b), max(a, b)
    Ad = _adjoint(_matrix(q[b]))
    return Ad @ _walk_between(q, a, b, s) @ Ad.T


def _gate(q, a: int, b: int, s: dict, points) -> tuple[TransformGate, np.ndarray]:
    """The gate of the matching of stretch b's objects (``points``, world) to stretch a's,
    and Σ (6, 6) of the correction T = Exp(ξ) in world coordinates, from the walk between the
    two middle frames (module docstring, step 4)."""
    Sw = _world_walk(q, a, b, s)
    rot = GATE_SIGMAS * np.sqrt(np.linalg.eigvalsh(Sw[3:, 3:])[-1])
    # a point x moves by v + ω × x: its spread, at the points farthest from the world origin
    p = np.asarray(points, float).reshape(-1, 3)
    spread = 0.0
    for x in p:
        J = np.c_[np.eye(3), -np.array([[0, -x[2], x[1]], [x[2], 0, -x[0]], [-x[1], x[0], 0]])]
        spread = max(spread, float(np.sqrt(np.linalg.eigvalsh(J @ Sw @ J.T)[-1])))
    return TransformGate(np.eye(4), 0.15 + GATE_SIGMAS * spread, float(min(rot, np.pi))), Sw


def _reversed(loc: Localization) -> Localization:
    """The localisation the other way round (x_later = T⁻¹ x_earlier, matches swapped)."""
    return replace(loc, T_map_sequence=np.linalg.inv(loc.T_map_sequence), matches=[(b, a) for a, b in loc.matches],
                   notes=[])


def _mahalanobis2(e, S) -> float:
    try:
        return float(e @ np.linalg.solve(S, e))
    except np.linalg.LinAlgError:
        return float("inf")


def loop_covariance(S_f, S_r, delta, chi_ways) -> np.ndarray:
    """The covariance of a loop's transform from its two ways' (``S_f``, ``S_r``, world-left)
    and their difference ``delta``: the two ways' mean, scaled up by how much more they
    disagree than it says (χ²₆ over its mean 6), plus ``LOOP_SIGMA_FLOOR``."""
    scale = max(1.0, chi_ways / 6.0)
    return scale * 0.5 * (S_f + S_r) + np.diag(LOOP_SIGMA_FLOOR**2)


def _verify(ctx: SequenceContext, stretch: dict, earlier: tuple, later: tuple, frames: tuple, s: dict) -> Loop:
    """Step 4 of the module docstring for the stretches ``earlier`` and ``later`` (first, last
    frame) around the revisit's ``frames`` (a, b)."""
    a, b = frames
    base: dict[str, Any] = dict(earlier=earlier, later=later, frames=(a, b))
    (seq_a, objs_a), (seq_b, objs_b) = stretch[earlier], stretch[later]
    if len(objs_a) < LOOP_MIN_MATCHES or len(objs_b) < LOOP_MIN_MATCHES:
        return Loop(**base, status="not verified",
                    reason=f"{len(objs_a)} and {len(objs_b)} objects mapped, a loop needs {LOOP_MIN_MATCHES} matched")
    q = ctx.wxyz_xyz
    gate, S_walk = _gate(q, a, b, s, [np.asarray(o.ellipsoid.center) for o in objs_b])
    try:
        loc = localize_objects(objs_b, objs_a, gate=gate)
    except LocalizationError as e:
        return Loop(**base, status="not verified", reason=f"objects: {e}")
    if len(loc.matches) < LOOP_MIN_MATCHES:
        return Loop(**base, status="not verified", matches=len(loc.matches), rival=loc.runner_up,
                    reason=f"{len(loc.matches)} objects matched, a loop needs {LOOP_MIN_MATCHES}")
    rows_a = np.c_[seq_a.timestamps, seq_a.poses_tum]
    rows_b = np.c_[seq_b.timestamps, seq_b.poses_tum]
    fwd = refine_localization(seq_b, objs_b, objs_a, loc, poses_tum=rows_b)
    rev = refine_localization(seq_a, objs_a, objs_b, _reversed(fwd), poses_tum=rows_a)
    from ._reuse import transform_poses_tum

    ids_a = {int(m) for _, m in loc.matches}
    ids_b = {int(r) for r, _ in loc.matches}
    agree_b, n_b = box_agreement(seq_b, [o for o in objs_a if int(o.id) in ids_a],
                                 transform_poses_tum(rows_b, fwd.T_map_sequence)[:, 1:])
    agree_a, n_a = box_agreement(seq_a, [o for o in objs_b if int(o.id) in ids_b],
                                 transform_poses_tum(rows_a, rev.T_map_sequence)[:, 1:])
    G_f, G_r = fwd.T_map_sequence, np.linalg.inv(rev.T_map_sequence)
    # the two ways' difference, left perturbation: G_r = Exp(Δ) G_f
    delta = _log(G_r @ np.linalg.inv(G_f))
    S_f, S_r = np.asarray(fwd.covariance, float), np.asarray(rev.covariance, float)
    Ad_r = _adjoint(G_r)  # the reverse's covariance is of its own transform: move it to G_r = T_rev⁻¹
    S_r = Ad_r @ S_r @ Ad_r.T
    finite = np.all(np.isfinite(S_f)) and np.all(np.isfinite(S_r))
    chi_ways = _mahalanobis2(delta, S_f + S_r) if finite else float("inf")
    G = jaxlie.SE3.exp(0.5 * delta) @ jaxlie.SE3.from_matrix(G_f)
    T = np.asarray(G.as_matrix())
    cov = loop_covariance(S_f, S_r, delta, chi_ways) if finite else None
    xi = _log(T)
    chi_odo = _mahalanobis2(xi, S_walk + cov) if cov is not None else float("inf")
    out = Loop(**base, status="not verified", matches=len(loc.matches), rival=loc.runner_up, T=T, covariance=cov,
               agreement=(agree_b, agree_a), chi2_ways=chi_ways, chi2_odometry=chi_odo)
    limit = _chi2_limit()
    if not finite:
        return replace(out, reason="the boxes do not fix the transform (its covariance is not finite)")
    if not (min(agree_a, agree_b) >= MIN_BOX_AGREEMENT):
        return replace(out, reason=f"the boxes confirm {100 * agree_b:.0f} % and {100 * agree_a:.0f} % of the "
                                   f"sightings the other stretch's objects predict (of {n_b} and {n_a}), "
                                   f"below {100 * MIN_BOX_AGREEMENT:.0f} %")
    if chi_ways > limit:
        return replace(out, reason=f"the two ways disagree (χ² {chi_ways:.3g} > {limit:.3g})")
    if chi_odo > limit:
        return replace(out, reason=f"more correction than the odometry can have drifted (χ² {chi_odo:.3g} > "
                                   f"{limit:.3g})")
    chi_zero = _mahalanobis2(xi, cov)
    if chi_zero < limit:
        return replace(out, reason=f"the drift it measures is within its own error (χ² {chi_zero:.3g} < {limit:.3g} "
                                   "against no correction)")
    return replace(out, status="verified")


def _confirmed(q, loops: list, s: dict) -> list:
    """The loops, each verified one that no other confirms marked "not verified": a second
    verified loop from another place, its stretches on both sides less than half shared with
    this one's (their middles more than half a stretch apart), whose transform agrees with
    this one's (χ²₆ at ``LOOP_P`` of both covariances and the walk between their frames on
    each side). One loop alone, or loops of one place, cannot be told from wrong ones that
    passed every test by a bias their boxes share: on the office recording the revisit of
    its first seconds gave three loops 5–6° off that agreed with each other (docs/drift.md)."""
    limit = _chi2_limit()
    ok = [i for i, lp in enumerate(loops) if lp.status == "verified"]
    out = list(loops)
    for i in ok:
        li = loops[i]
        agree = False
        for j in ok:
            lj = loops[j]
            if j == i:
                continue
            if abs(li.frames[0] - lj.frames[0]) <= 0.5 * (li.earlier[1] - li.earlier[0]) or \
                    abs(li.frames[1] - lj.frames[1]) <= 0.5 * (li.later[1] - li.later[0]):
                continue  # the same place on one side at least
            S = li.covariance + lj.covariance + _world_walk(q, li.frames[0], lj.frames[0], s) \
                + _world_walk(q, li.frames[1], lj.frames[1], s)
            if _mahalanobis2(_log(li.T @ np.linalg.inv(lj.T)), S) <= limit:
                agree = True
                break
        if not agree:
            out[i] = replace(li, status="not verified", reason="no loop from another place confirms it")
    return out


def _loop_factor(q, lp: Loop, s: dict) -> BetweenFactor:
    """The loop as a ``BetweenFactor(X(a), X(b))``: Z = T̂_a⁻¹ T T̂_b with the input poses T̂;
    its covariance Ad(T T̂_b)⁻¹ Σ Ad(T T̂_b)⁻ᵀ (the world-left Σ moved to b's frame) plus the walk
    over half of each stretch."""
    a, b = lp.frames
    Ta, Tb = _matrix(q[a]), _matrix(q[b])
    Z = np.linalg.inv(Ta) @ lp.T @ Tb
    Ad = _adjoint(np.linalg.inv(lp.T @ Tb))
    half = 0.5 * ((lp.earlier[1] - lp.earlier[0]) + (lp.later[1] - lp.later[0])) / 2.0
    cov = Ad @ lp.covariance @ Ad.T + np.diag(max(half, 1.0) * step_sigma(s) ** 2)
    return BetweenFactor(X(a), X(b), jaxlie.SE3.from_matrix(Z), covariance=0.5 * (cov + cov.T))


def solve_pose_graph(ctx: SequenceContext, s: dict, loops: list, progress=None) -> tuple[np.ndarray, list]:
    """Step 5 of the module docstring: the poses of ``ctx`` (F, 7, jaxlie's wxyz_xyz) with the
    odometry and the verified ``loops`` (``Loop``; the step σ of ``s``), and the loops with
    their χ² in the graph and those that disagree marked rejected, the worst first."""
    progress = progress or (lambda message: None)
    q = ctx.wxyz_xyz
    F = len(q)
    base = odometry_factors(q, ctx.seq.segments, {**s, "absolute_translation": np.inf,
                                                  "absolute_rotation": np.inf})
    values = Values({X(i): jaxlie.SE3(q[i]) for i in range(F)})
    active = [i for i, lp in enumerate(loops) if lp.status == "verified"]
    factors = {i: _loop_factor(q, loops[i], s) for i in active}
    limit = _chi2_limit()
    poses = q
    optimizer = LevenbergMarquardt(max_iterations=50)
    while active:
        graph = NonlinearFactorGraph(base + [factors[i] for i in active])
        res = optimizer.optimize(graph, values)
        chis = {i: 2.0 * float(NonlinearFactorGraph([factors[i]]).error(res.values)) for i in active}
        worst = max(active, key=chis.__getitem__)
        for i in active:
            loops[i] = replace(loops[i], chi2_graph=chis[i])
        if chis[worst] <= limit:
            poses = np.stack([np.asarray(res.values[X(i)].wxyz_xyz) for i in range(F)])
            break
        loops[worst] = replace(loops[worst], status="rejected",
                               reason=f"disagrees with the odometry and the other loops (χ² {chis[worst]:.3g} > "
                                      f"{limit:.3g} in the pose graph)")
        progress(loops[worst].describe())
        active.remove(worst)
    return poses, loops


def _pairs(subs: list, cands: list, F: int) -> list:
    """Each candidate revisit's two stretches, a submap's length each, centred on its
    closest frames: [((first, last) earlier, (first, last) later, (i, j))]."""
    pairs = []
    for k, li, i, j in cands:
        h = max((subs[k][1] - subs[k][0]) // 2, (subs[li][1] - subs[li][0]) // 2, 1)
        pairs.append(((max(0, i - h), min(F - 1, i + h)), (max(0, j - h), min(F - 1, j + h)), (i, j)))
    return pairs


def _tried(ctx: SequenceContext, s: dict, pairs: list, map_stretches: Callable) -> list:
    """Steps 3–4 of the module docstring: each pair's stretches mapped alone, each loop
    verified (``Loop``, before the confirmation by another place)."""
    needed = sorted({w for ea, la, _ in pairs for w in (ea, la)})
    mapped = map_stretches(needed) if needed else []
    stretch = {w: (ctx.seq.subset(np.arange(w[0], w[1] + 1)), objs) for w, objs in zip(needed, mapped)}
    return [_verify(ctx, stretch, ea, la, fr, s) for ea, la, fr in pairs]


def _closed(ctx: SequenceContext, s: dict, tried: list, subs: list, say: Callable) -> LoopClosure:
    """Step 5 of the module docstring on the ``tried`` loops: those another place confirms
    (``_confirmed``) in the pose graph, its trajectory checked against the odometry."""
    q = ctx.wxyz_xyz
    loops = _confirmed(q, tried, s)
    for lp in loops:
        say(lp.describe())
    if not any(lp.status == "verified" for lp in loops):
        return LoopClosure(q, loops, None, subs)
    poses, loops = solve_pose_graph(ctx, s, loops, say)
    if not any(lp.status == "verified" for lp in loops):
        return LoopClosure(q, loops, None, subs)
    check = check_trajectory("loop closure", q, poses, walk_covariances(q, s, ctx.seq.segments))
    if not check.accepted:
        loops = [replace(lp, status="rejected", reason="the closed trajectory departs from the input beyond the "
                                                       "odometry's walk") if lp.status == "verified" else lp
                 for lp in loops]
        return LoopClosure(q, loops, check, subs)
    return LoopClosure(poses, loops, check, subs)


def close_loops(ctx: SequenceContext, s: dict, map_stretches: Callable, progress: Callable | None = None,
                seconds: float | None = None) -> LoopClosure:
    """The trajectory of ``ctx`` corrected by the loops its objects close (module docstring),
    with the run's sigmas ``s`` (``mapping_sigmas``; the step σ of the walk) and
    ``map_stretches([(first, last), …]) -> [objects, …]`` mapping each stretch alone with its
    poses held (``io.MapObject`` s in the input's frame; ``stretch_objects``)."""
    say = progress or (lambda message: None)
    subs = submaps_of(ctx.seq.timestamps, seconds)
    cands = candidates(ctx, subs, s)
    say(f"loop closure: {len(subs)} submaps, {len(cands)} candidate revisits")
    tried = _tried(ctx, s, _pairs(subs, cands, len(ctx.wxyz_xyz)), map_stretches)
    return _closed(ctx, s, tried, subs, say)


@dataclass(frozen=True)
class HeldMap:
    """Objects mapped with the poses held at ``ctx``'s (the batch run's first pass, or an
    online run's map on the odometry): the tracks, the landmarks {id: value}, the method, the
    sigmas, the support planes, ``min_views`` and the LM budget (``stretch_objects``)."""

    ctx: SequenceContext
    tracks: list
    landmarks: dict
    method: Method
    sigmas: dict
    planes: Any
    min_views: int
    max_iterations: int


def stretch_objects(mapped: HeldMap, stretches: list) -> list:
    """The objects of each stretch (first, last frame) of a run mapped with its poses held
    (``mapped``), each from that stretch's boxes alone (``MapObject`` s with the track's id
    and their marginal uncertainty; a stretch's object needs ``min_views`` of its boxes
    there; degenerate ones are left out): every stretch's objects in one optimisation with
    the poses held, each started from the run's estimate of it."""
    ctx, method, s = mapped.ctx, mapped.method, mapped.sigmas
    stage = method.replace(box_model="inverse" if method.box_model == "semi-then-inverse" else method.box_model)
    factors: list = []
    values = Values()
    keys: list = []
    frames: set = set()
    big = 1 + max([tr.id for tr in mapped.tracks], default=0)
    for m, (a, b) in enumerate(stretches):
        mine = []
        for tr in mapped.tracks:
            if tr.id not in mapped.landmarks:
                continue
            inside = (tr.frames >= a) & (tr.frames <= b)
            if inside.sum() < mapped.min_views:
                continue
            key = m * big + int(tr.id)
            part = Track(key, tr.label, tr.frames[inside], tr.boxes[inside])
            factors += object_factors(ctx, part, mapped.landmarks[tr.id], stage, s, mapped.planes)
            values[L(key)] = mapped.landmarks[tr.id]
            frames.update(int(f) for f in part.frames)
            mine.append((key, tr))
        keys.append(mine)
    if not factors:
        return [[] for _ in stretches]
    poses = [X(f) for f in sorted(frames)]
    for f in sorted(frames):
        values[X(f)] = ctx.poses[f]
    graph = NonlinearFactorGraph(with_robust_by_type(factors, method))
    res = LevenbergMarquardt(max_iterations=mapped.max_iterations).optimize(graph, values, fixed=poses)
    ids = [key for mine in keys for key, _ in mine if not degenerate(as_ellipsoid(res.values[L(key)]))]
    spread = object_uncertainty(graph, res.values, ids, poses, res)
    return [[MapObject(int(tr.id), tr.label, as_ellipsoid(res.values[L(key)]), spread[key])
             for key, tr in mine if key in spread] for mine in keys]


class OnlineLoopClosure:
    """The loop closure of an online run (``OnlineMapper`` on a trajectory without a bound on
    each pose, its poses held at the odometry): the batch's steps (module docstring) on the
    frames so far, attached with ``OnlineMapper.watch``. Each time a submap
    (``LOOP_SUBMAP_SECONDS``) and the one after it are complete, the candidate revisits of
    that submap to the earlier ones (``candidates``' rules) are mapped from the mapper's
    tracks with the poses held (``stretch_objects``) and verified (``_verify``); every loop
    tried so far then goes through the confirmation by another place, the pose graph and the
    check against the odometry (``_closed``), as in the batch. An accepted closure gives the
    corrected poses of the frames it covered (``corrections``: later frames follow the
    odometry from the last of them); a refused one keeps the last accepted. ``finish``
    tries the submaps left at the end. Read through the mapper's public state
    (``sequence``, ``tracks``, ``landmarks``, ``timestamps``)."""

    def __init__(self, mapper, progress: Callable | None = None, seconds: float | None = None):
        self.mapper = mapper
        self.seconds = float(LOOP_SUBMAP_SECONDS if seconds is None else seconds)
        self.say = progress or (lambda message: None)
        self.tried: list = []  # every loop tried so far, before the confirmation
        self.tried_through = -1  # the last submap whose revisits were tried
        self.closure: LoopClosure | None = None  # the last closure computed (accepted or not)
        self.poses: np.ndarray | None = None  # the last accepted corrected poses (F', 7)
        self.seconds_spent, self.tries = 0.0, 0
        mapper.watch(self.due, self.look)

    def _ready(self, timestamps, final: bool) -> int:
        """The last submap whose revisits can be tried: the one before the last complete
        one (its stretches reach half a submap into the next), every one at the end."""
        t = np.asarray(timestamps, float)
        if len(t) < 2:
            return -1
        if final:
            return len(submaps_of(t, self.seconds)) - 1
        return int(np.floor((t[-1] - t[0]) / self.seconds)) - 2

    def due(self, count: int, frames: int) -> bool:
        return self._ready(self.mapper.timestamps[:frames], False) > self.tried_through

    def look(self, objects: dict | None = None, frames: int | None = None, final: bool = False) -> None:
        """Try the revisits of the submaps ready since the last look (``final``: all left)."""
        t0 = time.perf_counter()
        mapper = self.mapper
        seq = mapper.sequence()
        ready = self._ready(seq.timestamps, final)
        if ready <= self.tried_through or not len(seq):
            return
        ctx = SequenceContext.of(seq)
        s = mapping_sigmas(ctx, dict(mapper.settings.sigma))
        subs = submaps_of(seq.timestamps, self.seconds)
        new = range(self.tried_through + 1, ready + 1)
        self.tried_through = ready
        cands = candidates(ctx, subs, s, later=new)
        self.tries += 1
        if cands:
            held = HeldMap(ctx, mapper.tracks(), dict(mapper.landmarks), mapper.method, s, None, mapper.min_views,
                           mapper.settings.max_iterations)
            self.say(f"loop closure: {len(cands)} candidate revisits of submaps {new.start}–{new.stop - 1}")
            self.tried += _tried(ctx, s, _pairs(subs, cands, len(seq)), lambda w: stretch_objects(held, w))
            if any(lp.status == "verified" for lp in self.tried):
                self.closure = _closed(ctx, s, list(self.tried), subs, self.say)
                if self.closure.verified:
                    self.poses = self.closure.poses
        self.seconds_spent += time.perf_counter() - t0

    def corrections(self, wxyz_xyz) -> np.ndarray | None:
        """C (F, 4, 4) with T_corrected = C T_input for the input poses ``wxyz_xyz`` (F, 7):
        from the accepted closure for the frames it covered, the last of those after; None
        before a closure is accepted."""
        if self.poses is None:
            return None
        q = np.asarray(wxyz_xyz, float)
        n = min(len(self.poses), len(q))
        C = np.empty((len(q), 4, 4))
        C[:n] = np.asarray((jaxlie.SE3(self.poses[:n]) @ jaxlie.SE3(q[:n]).inverse()).as_matrix())  # type: ignore[arg-type]
        C[n:] = C[n - 1]
        return C

    def notes(self) -> list:
        """The closure's notes (``LoopClosure.notes``), or a line saying none was tried or
        verified."""
        if self.closure is not None:
            return self.closure.notes()
        return [f"loop closure (online): {len(self.tried)} candidate revisits, none verified; the trajectory is "
                "the input's"]

    def as_dict(self) -> dict:
        out = self.closure.as_dict() if self.closure is not None else {"loops": [lp.as_dict() for lp in self.tried]}
        return {**out, "online": {"tries": self.tries, "seconds": self.seconds_spent}}
