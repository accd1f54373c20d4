"""Maps that outlive a recording: the transform that puts a recording's objects into a saved
map's frame, found from the objects alone (docs/map-reuse.md).

Given the objects of a new recording (in its odometry's frame) and those of a map, find
T_map_sequence: x_map = s R x_seq + t (s = 1 for SE(3); Sim(3) when the recording's scale is
unknown, as from a monocular front end):

1. **Candidates**: pairs (recording object, map object) of one label whose sorted radii agree
   within ``size_ratio`` (SE(3)), or whose shapes (radii over the largest) agree (Sim(3)).
2. **Hypotheses**: every triple of candidates with distinct objects on both sides whose three
   pairwise centre distances agree (within ``tolerance`` m; as ratios under Sim(3)), aligned
   in closed form (Horn / Umeyama, ``geometry.align_rigid``).
3. **Consensus**: a hypothesis scores the recording objects whose centre lands within
   ``tolerance`` of a candidate partner; the best is refitted on its inliers, matched one to
   one (``scipy.optimize.linear_sum_assignment`` on the centre distances), twice, then
   refitted with Cauchy weights (scale ``tolerance``/3: an object that one recording mapped
   apart pulls less).
4. **Refusal** (``LocalizationError``, one line): fewer than three matches; matched centres
   on a line (the rotation about it is free); or a rival transform that pairs at least two
   objects differently, puts the matched objects elsewhere (their median displacement
   between the two over 2·``tolerance``) and matches as many, or all but ``RIVAL_MARGIN``
   − 1 as many (a symmetric layout, or one nearly so: a wrong transform matched 5 objects
   of a drifting office recording against a right one's 4).

With a ``gate`` (``TransformGate``: the transform known to within a distance and an angle of
a guess, as the odometry knows it between two stretches of one recording) only candidate
pairs whose centres the guess brings within the gate's distance, and hypotheses within the
gate, are considered: the matcher of the loop closure (``_loops``).

The covariance of the transform is that of the least-squares fit of the matched centres,
residual variance estimated from the fit (at least ``tolerance``/3 per axis, since the map's
marginals leave out model error), in the left-perturbation coordinates x ↦ Exp(ξ)·x,
ξ = (v, ω) in jaxlie's order, with log s last under Sim(3).

5. **Refinement with the boxes** (``refine_localization``): the recording's detections paired
   with the matched map objects projected from the localised poses (``_paired_detections``:
   same label, the object in front, IoU ≥ 0.3, the best per detection and one detection per
   object and frame, as ``spdslam check --map`` pairs them); then the frame
   (``jaxlie.SE3``, or ``geometry.Sim3``) and those objects optimised together, each box a
   ``factors.FrameBoxFactor`` (the inverse box model, σ and Cauchy kernel as ``spdslam
   run``'s), each object held by a ``factors.LandmarkPriorFactor`` at the map's estimate with
   σ from its marginals (centre σ, and 2 × log-radius σ on the SPD block, at least
   ``REFINE_CENTER_SIGMA`` and ``REFINE_SHAPE_SIGMA``: an object without them is all but
   fixed). Looser priors let the objects deform to the new boxes and the frame turn with
   them (docs/map-reuse.md measures it). Paired again at the refined frame and solved again
   (``REFINE_ROUNDS``). The covariance is then the frame's marginal, moved to the
   left-perturbation coordinates.

6. **Agreement of the boxes** (``box_agreement``): of the frames where a matched map object,
   projected from the localised poses, lies in front of the camera and inside the image,
   the share with a detection of its label that overlaps it (IoU ≥ 0.3). A transform that
   the boxes contradict puts objects where the camera sees none of their class: below
   ``MIN_BOX_AGREEMENT`` it is refused (``spdslam localize``, the loop closure).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field, replace
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..geometry import Ellipsoid, align_rigid, align_rigid_many, in_front, moved_covariance, project_box
from ..solver import Symbol
from ._graph import inverse_box_sigma

__all__ = ["Localization", "LocalizationError", "MIN_BOX_AGREEMENT", "RIVAL_MARGIN", "TransformGate",
           "box_agreement", "localize_objects", "refine_localization", "transform_ellipsoid", "transform_poses_tum",
           "localized_result", "moved_sequence", "joined_sequence"]


#: Reweighted refits of the matched centres (Cauchy, scale ``tolerance``/3).
IRLS_ITERATIONS = 5
#: Floors of the σ that hold a map object in ``refine_localization``: centre (m), and the
#: SPD block of its chart (≈ twice the relative change of a radius). Only a guard against a
#: zero σ: the marginals themselves hold best (docs/map-reuse.md, ``--floors``).
REFINE_CENTER_SIGMA = 1e-4
REFINE_SHAPE_SIGMA = 1e-4
#: Pairings and solves of ``refine_localization``.
REFINE_ROUNDS = 2
#: The IoU at which a recording's box pairs with a map object's projection.
REFINE_MIN_IOU = 0.3
#: The key of the frame variable in ``refine_localization``'s graph.
FRAME_KEY = Symbol("f", 0)
#: A transform is refused when the recording's boxes confirm fewer than this share of the
#: sightings of the matched map objects it predicts (``box_agreement``): ``spdslam localize``
#: and the loop closure's verification.
MIN_BOX_AGREEMENT = 0.5
#: A transform is refused when a rival matches at least its matches − ``RIVAL_MARGIN`` + 1
#: objects: it must match ``RIVAL_MARGIN`` more than any rival.
RIVAL_MARGIN = 2


@dataclass(frozen=True)
class TransformGate:
    """What is known of a transform before the objects are matched: within ``distance`` (m)
    of where ``T`` (4×4) puts the recording's objects, and within ``angle`` (rad) of its
    rotation (``localize_objects``' ``gate``)."""

    T: np.ndarray
    distance: float
    angle: float

    def admits(self, R, t, points) -> np.ndarray:
        """Whether each of h transforms (R (h, 3, 3), t (h, 3)) lies within the gate: its
        rotation within ``angle`` of T's, and the ``points`` (n, 3) of the recording it moves
        within ``distance`` of where T puts them (the largest displacement)."""
        R0, t0 = np.asarray(self.T, float)[:3, :3], np.asarray(self.T, float)[:3, 3]
        cos = (np.einsum("hij,ij->h", np.asarray(R), R0) - 1.0) / 2.0
        turn = np.arccos(np.clip(cos, -1.0, 1.0))
        p = np.asarray(points, float).reshape(-1, 3)
        moved = np.einsum("hij,nj->hni", R, p) + np.asarray(t)[:, None] - (p @ R0.T + t0)[None]
        far = np.linalg.norm(moved, axis=-1).max(axis=1) if len(p) else np.zeros(len(turn))
        return (turn <= self.angle) & (far <= self.distance)


class LocalizationError(ValueError):
    """The objects do not fix a unique transform (the message says why, in one line)."""


@dataclass(frozen=True)
class Localization:
    """x_map = ``scale`` · R x_seq + t, with ``T_map_sequence`` = [[R, t], [0, 1]] (the scale
    kept apart); ``covariance`` (6×6, or 7×7 with log s) in the module's coordinates;
    ``matches`` [(recording object id, map object id)]; ``residuals`` the matched centres'
    distances after the fit (m, map frame); ``runner_up`` the matches of the best distinct
    transform (0 when none)."""

    T_map_sequence: np.ndarray
    scale: float
    covariance: np.ndarray
    matches: list
    residuals: np.ndarray
    runner_up: int
    candidates: int
    sim3: bool = False
    notes: list = field(default_factory=list)

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean(self.residuals**2))) if len(self.residuals) else float("nan")

    def apply(self, x) -> np.ndarray:
        """Points (…, 3) of the recording's frame in the map's frame."""
        R, t = self.T_map_sequence[:3, :3], self.T_map_sequence[:3, 3]
        return self.scale * np.asarray(x, float) @ R.T + t

    def as_dict(self) -> dict:
        """localization.json's content."""
        return {
            "T_map_sequence": self.T_map_sequence.tolist(),
            "scale": float(self.scale),
            "sim3": bool(self.sim3),
            "covariance": self.covariance.tolist(),
            "covariance_coordinates": "left perturbation x -> Exp(xi) x, xi = (v [m], omega [rad])"
                                      + (", log scale" if self.sim3 else ""),
            "matches": [[int(a), int(b)] for a, b in self.matches],
            "center_residuals": [float(r) for r in self.residuals],
            "center_rms": self.rms,
            "runner_up_matches": int(self.runner_up),
            "candidate_pairs": int(self.candidates),
            "notes": list(self.notes),
        }


def _parts(objects):
    ids = [int(o.id) for o in objects]
    labels = [str(o.label) for o in objects]
    centers = np.array([np.asarray(o.ellipsoid.center, float) for o in objects]).reshape(-1, 3)
    radii = np.array([np.sort(np.sqrt(np.linalg.eigvalsh(np.asarray(o.ellipsoid.P, float))))
                      for o in objects]).reshape(-1, 3)
    return ids, labels, centers, radii


def _candidates(seq, mp, sim3: bool, size_ratio: float, gate: TransformGate | None = None) -> np.ndarray:
    """(k, 2) index pairs (recording, map) that could be one object (within the ``gate``'s
    distance of each other where its guess puts the recording's, when given)."""
    _, la, ca, ra = seq
    _, lb, cb, rb = mp
    near = None
    if gate is not None and len(ca) and len(cb):
        T = np.asarray(gate.T, float)
        near = np.linalg.norm((ca @ T[:3, :3].T + T[:3, 3])[:, None] - cb[None], axis=-1) <= gate.distance
    out = []
    for i, j in itertools.product(range(len(la)), range(len(lb))):
        if la[i] != lb[j] or (near is not None and not near[i, j]):
            continue
        a, b = (ra[i] / ra[i][-1], rb[j] / rb[j][-1]) if sim3 else (ra[i], rb[j])
        if np.all(np.maximum(a / b, b / a) <= size_ratio):
            out.append((i, j))
    return np.array(out, int).reshape(-1, 2)


def _triples(cand: np.ndarray, cs: np.ndarray, cm: np.ndarray, sim3: bool, tol: float,
             max_triples: int) -> np.ndarray:
    """(h, 3) candidate indices whose triangles agree (distinct objects on both sides)."""
    k = len(cand)
    if k < 3:
        return np.zeros((0, 3), int)
    ds = np.linalg.norm(cs[cand[:, 0], None] - cs[None, cand[:, 0]], axis=-1)
    dm = np.linalg.norm(cm[cand[:, 1], None] - cm[None, cand[:, 1]], axis=-1)
    distinct = (cand[:, 0, None] != cand[None, :, 0]) & (cand[:, 1, None] != cand[None, :, 1])
    if sim3:  # distances agree up to one scale: compare as ratios (a small distance says little)
        pair_ok = distinct & (ds > tol) & (dm > tol)
    else:
        pair_ok = distinct & (np.abs(ds - dm) <= 2.0 * tol)
    out: list[tuple[int, int, int]] = []
    for a in range(k):
        bs = np.flatnonzero(pair_ok[a, a + 1:]) + a + 1
        for b in bs:
            cs_ = bs[bs > b]
            cs_ = cs_[pair_ok[b, cs_]]
            if sim3 and cs_.size:
                s_ab = dm[a, b] / ds[a, b]
                ok = (np.abs(dm[a, cs_] / ds[a, cs_] / s_ab - 1.0) <= 0.1) & \
                     (np.abs(dm[b, cs_] / ds[b, cs_] / s_ab - 1.0) <= 0.1)
                cs_ = cs_[ok]
            out.extend((a, int(b), int(c)) for c in cs_)
            if len(out) >= max_triples:
                return np.asarray(out[:max_triples], dtype=np.int64)
    return np.asarray(out, dtype=np.int64).reshape(-1, 3)


def _fit(src, dst, sim3, weights=None):
    try:
        R, t, s = align_rigid(src, dst, with_scale=sim3, weights=weights)
    except ValueError:
        return None
    return R, t, s


def _assign(cand, cs, cm, R, t, s, tol):
    """One-to-one matches (candidate indices, ascending) within ``tol`` after the transform:
    the assignment of least total distance among the candidate pairs within it."""
    from scipy.optimize import linear_sum_assignment

    d = np.linalg.norm(s * cs[cand[:, 0]] @ R.T + t - cm[cand[:, 1]], axis=1)
    idx = np.flatnonzero(d <= tol)
    if not idx.size:
        return np.zeros(0, int)
    si, a = np.unique(cand[idx, 0], return_inverse=True)
    mj, b = np.unique(cand[idx, 1], return_inverse=True)
    cost = np.full((len(si), len(mj)), 1e6)
    np.minimum.at(cost, (a, b), d[idx])
    r, c = linear_sum_assignment(cost)
    keep = cost[r, c] < 1e6
    chosen = np.zeros(cost.shape, bool)
    chosen[r[keep], c[keep]] = True
    return idx[chosen[a, b]]


#: Hypotheses × candidate pairs per block of ``_hypotheses``' distances (bounds its memory).
_BLOCK = 1 << 20


class _Hypotheses:
    """The transforms of the triples that put at least three objects in place, as a sequence
    of (matches, R, t, s, inliers) from the most matches down (ties in the triples' order),
    the inliers of each made when it is read (``_assign``'s one-to-one matches)."""

    def __init__(self, cand, cs, cm, R, t, s, near, tol):
        self.cand, self.cs, self.cm, self.tol = cand, cs, cm, tol
        self.R, self.t, self.s, self.near = R, t, s, near
        n = near.sum(axis=1)
        # without two candidates of one object among the near ones, the one-to-one matches are
        # all of them; else (neighbours of one label) the assignment decides
        one_seq = np.zeros((len(cand), cand[:, 0].max() + 1))
        one_seq[np.arange(len(cand)), cand[:, 0]] = 1.0
        one_map = np.zeros((len(cand), cand[:, 1].max() + 1))
        one_map[np.arange(len(cand)), cand[:, 1]] = 1.0
        self.clash = ((near @ one_seq).max(axis=1) > 1) | ((near @ one_map).max(axis=1) > 1)
        self._inliers: dict = {}
        count = n.copy()
        for h in np.flatnonzero(self.clash & (n >= 3)):
            count[h] = len(self._inliers_of(h))
        keep = np.flatnonzero(count >= 3)
        self.order = keep[np.argsort(-count[keep], kind="stable")]
        self.count = count

    def _inliers_of(self, h: int) -> np.ndarray:
        if h not in self._inliers:
            self._inliers[h] = _assign(self.cand, self.cs, self.cm, self.R[h], self.t[h], self.s[h], self.tol) \
                if self.clash[h] else np.flatnonzero(self.near[h])
        return self._inliers[h]

    def __len__(self) -> int:
        return len(self.order)

    def __getitem__(self, i: int):
        h = int(self.order[i])
        return int(self.count[h]), self.R[h], self.t[h], float(self.s[h]), self._inliers_of(h)

    def __iter__(self):
        return (self[i] for i in range(len(self)))


def _hypotheses(cand, cs, cm, triples, sim3: bool, tol: float, gate: TransformGate | None = None) -> _Hypotheses:
    """Each triple's transform (``geometry.align_rigid_many``; none where its centres are
    degenerate, or under Sim(3) its scale is outside (0.05, 20), or outside the ``gate``) and
    the candidate pairs it puts within ``tol`` of each other, in array operations
    (``_Hypotheses``)."""
    R, t, s, ok = (np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, bool)) if not len(triples) \
        else align_rigid_many(cs[cand[triples, 0]], cm[cand[triples, 1]], with_scale=sim3)
    if sim3:
        ok &= (0.05 < s) & (s < 20.0)
    if gate is not None and len(R):
        ok &= gate.admits(R, t, cs[np.unique(cand[:, 0])])
    R, t, s = R[ok], t[ok], s[ok]
    a, b = cs[cand[:, 0]], cm[cand[:, 1]]
    near = np.zeros((len(R), len(cand)), bool)
    step = max(1, _BLOCK // max(len(cand), 1))
    for i in range(0, len(R), step):
        moved = s[i:i + step, None, None] * np.einsum("hij,kj->hki", R[i:i + step], a) + t[i:i + step, None]
        near[i:i + step] = np.linalg.norm(moved - b, axis=-1) <= tol
    return _Hypotheses(cand, cs, cm, R, t, s, near, tol)


def _angle_deg(Ra, Rb) -> float:
    c = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def _covariance(cs, R, t, s, residuals, tol, sim3):
    """Covariance of the fit in left-perturbation coordinates (module docstring): for each
    matched centre y = s R c + t, ∂(Exp(ξ)·y)/∂ξ = [I, −[y]×, y] (the last under Sim(3))."""
    y = s * cs @ R.T + t
    n = len(y)
    rows = []
    for p in y:
        J = np.zeros((3, 7 if sim3 else 6))
        J[:, :3] = np.eye(3)
        J[:, 3:6] = -np.array([[0, -p[2], p[1]], [p[2], 0, -p[0]], [-p[1], p[0], 0]])
        if sim3:  # Exp of the scale multiplies the transformed point
            J[:, 6] = p
        rows.append(J)
    J = np.concatenate(rows)
    dof = max(3 * n - J.shape[1], 1)
    var = max(float(np.sum(residuals**2)) / dof, (tol / 3.0) ** 2)
    try:
        return var * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return np.full((J.shape[1],) * 2, np.inf)


def localize_objects(seq_objects, map_objects, *, sim3: bool = False, tolerance: float = 0.15,
                     size_ratio: float = 2.0, max_triples: int = 20_000,
                     gate: TransformGate | None = None) -> Localization:
    """The transform that puts ``seq_objects`` (``io.MapObject``, the recording's frame) onto
    ``map_objects`` (the map's frame): module docstring. ``gate``: what is known of it
    before (SE(3) only). Raises ``LocalizationError`` when the objects do not fix one."""
    if gate is not None and sim3:
        raise ValueError("localize_objects: a gate is an SE(3) guess; it takes no Sim(3)")
    seq, mp = _parts(list(seq_objects)), _parts(list(map_objects))
    cs, cm = seq[2], mp[2]
    cand = _candidates(seq, mp, sim3, size_ratio, gate)
    usable = min(len(np.unique(cand[:, 0])), len(np.unique(cand[:, 1]))) if len(cand) else 0
    if usable < 3:
        raise LocalizationError(
            f"fewer than three usable matches: {usable} recording object(s) share a label and "
            f"a size with a map object ({len(seq[0])} in the recording, {len(mp[0])} in the map)")
    triples = _triples(cand, cs, cm, sim3, tolerance, max_triples)
    hyps = _hypotheses(cand, cs, cm, triples, sim3, tolerance, gate)
    if not hyps:
        raise LocalizationError(
            f"fewer than three usable matches: no three of the {len(cand)} candidate pairs "
            f"agree on a transform within {tolerance} m")
    _, R, t, s, inl = hyps[0]
    for _ in range(2):  # refit on the inliers, then match again
        fit = _fit(cs[cand[inl, 0]], cm[cand[inl, 1]], sim3)
        if fit is None:
            raise LocalizationError(
                "the matched objects' centres lie on a line: the rotation about it is not fixed")
        R, t, s = fit
        new = _assign(cand, cs, cm, R, t, s, tolerance)
        if len(new) < 3:
            break
        inl = new
    # the best rival: a transform that pairs at least two objects differently and puts the
    # matched objects elsewhere (median displacement over 2·tolerance); a nearby transform
    # that swaps two neighbouring objects of one label is the same answer
    best = np.zeros(len(cand), bool)  # candidate pairs are distinct: a pair is its index
    best[inl] = True
    mine = cs[cand[inl, 0]]
    runner_up, apart = 0, 0.0
    for n, R2, t2, s2, inl2 in hyps:
        differs = np.count_nonzero(~best[inl2]) >= 2
        moved = np.median(np.linalg.norm(s * mine @ R.T + t - (s2 * mine @ R2.T + t2), axis=1))
        if differs and moved > 2.0 * tolerance:
            runner_up, apart = n, _angle_deg(R, R2)
            break
    if runner_up > len(inl) - RIVAL_MARGIN:
        raise LocalizationError(
            f"the layout is ambiguous: a transform matches {len(inl)} objects and another {apart:.0f}° "
            f"apart {runner_up} (a symmetric arrangement, or nearly)")
    pairs = cand[inl]
    res = np.linalg.norm(s * cs[pairs[:, 0]] @ R.T + t - cm[pairs[:, 1]], axis=1)
    for _ in range(IRLS_ITERATIONS):  # Cauchy weights: an object mapped apart in one recording counts less
        w = 1.0 / (1.0 + (res / (tolerance / 3.0)) ** 2)
        fit = _fit(cs[pairs[:, 0]], cm[pairs[:, 1]], sim3, w)
        if fit is None:
            break
        R, t, s = fit
        res = np.linalg.norm(s * cs[pairs[:, 0]] @ R.T + t - cm[pairs[:, 1]], axis=1)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    cov = _covariance(cs[pairs[:, 0]], R, t, s, res, tolerance, sim3)
    order = np.argsort(pairs[:, 0])
    matches = [(seq[0][pairs[i, 0]], mp[0][pairs[i, 1]]) for i in order]
    return Localization(T, float(s), cov, matches, res[order], int(runner_up), len(cand), sim3)


def _left_covariance(frame, cov_right: np.ndarray, sim3: bool) -> np.ndarray:
    """The frame's covariance in the solver's chart moved to the left-perturbation coordinates
    of ``Localization.covariance``. SE3 (T ⊞ δ = T Exp(δ)): ξ = Ad_T δ. Sim3 ((R, t, σ) ⊞
    (v, ω, ρ) = (R Exp(ω), t + v, σ + ρ)): a left ξ = (v', ω', ρ) moves t by
    v' + ω' × t + ρ t and R by R Exp(Rᵀ ω'), so δ = A ξ with A = [[I, −[t]×, t], [0, Rᵀ, 0], [0, 0, 1]]."""
    if not sim3:
        Ad = np.asarray(frame.adjoint())
        return Ad @ cov_right @ Ad.T
    R = np.asarray(frame.rotation.as_matrix())
    t = np.asarray(frame.translation)
    A = np.eye(7)
    A[:3, 3:6] = -np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    A[:3, 6] = t
    A[3:6, 3:6] = R.T
    Ai = np.linalg.inv(A)
    return Ai @ cov_right @ Ai.T


@jax.jit
def _project_all(P, c, poses, camera):
    """Boxes (F, K, 4) and in-front flags (F, K) of K ellipsoids (P, c) from F poses."""
    def one(Pk, ck, T):
        e = Ellipsoid(Pk, ck)
        return project_box(e, T, camera), in_front(e, T, 1e-3)

    return jax.vmap(jax.vmap(one, in_axes=(0, 0, None)), in_axes=(None, None, 0))(P, c, poses)


def _paired_detections(seq, ellipsoids, labels, poses_tum, min_iou: float = 0.3):
    """(detection indices, object indices, IoU) of ``seq``'s detections paired with
    ``ellipsoids`` (labels ``labels``) projected from ``poses_tum`` ((F, 7) rows tx ty tz qx
    qy qz qw, one per frame of ``seq``, in the objects' frame): for each detection the object
    of its label, wholly in front of the camera, whose box overlaps it most, if IoU ≥
    ``min_iou``; of several detections of one object in one frame, the one that overlaps most."""
    from ..geometry import box_iou
    from ..geometry.se3 import from_tum

    dets = seq.detections
    if not dets or not len(ellipsoids):
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    frames = np.array([d.frame for d in dets])
    boxes = np.stack([np.asarray(d.box, float) for d in dets])
    used, slot = np.unique(frames, return_inverse=True)
    P = jnp.asarray(np.stack([np.asarray(e.P, float) for e in ellipsoids]))
    c = jnp.asarray(np.stack([np.asarray(e.center, float) for e in ellipsoids]))
    proj, front = _project_all(P, c, from_tum(np.asarray(poses_tum, float)[used]), seq.camera)
    proj, front = np.asarray(proj), np.asarray(front) & np.all(np.isfinite(np.asarray(proj)), -1)
    same = np.array([d.label for d in dets])[:, None] == np.asarray(labels)[None, :]
    iou = np.where(same & front[slot], box_iou(boxes[:, None, :], proj[slot]), 0.0)
    k = np.argmax(iou, axis=1)
    best = iou[np.arange(len(dets)), k]
    d = np.flatnonzero(best >= min_iou)
    order = np.lexsort((-best[d], k[d], frames[d]))  # by frame, object, then best first
    d = d[order]
    key = frames[d] * (len(ellipsoids) + 1) + k[d]
    d = d[np.r_[True, key[1:] != key[:-1]]] if len(d) else d
    return d, k[d], best[d]


def box_agreement(seq, objects, poses_tum, min_iou: float = 0.3) -> tuple[float, int]:
    """(share, predicted) of the projections of ``objects`` (``io.MapObject`` s, in the frame
    of ``poses_tum``: (F, 7) TUM rows, one per frame of ``seq``) that a detection of ``seq``
    confirms (module docstring, step 6): ``predicted`` counts the (frame, object) pairs
    where the object lies in front of the camera with its box inside the image, the share
    those with a detection of its label overlapping it by IoU ≥ ``min_iou``. (nan, 0) when
    no object is predicted anywhere."""
    from ..geometry import box_iou
    from ..geometry.se3 import from_tum

    objects = list(objects)
    if not objects or not len(seq):
        return float("nan"), 0
    P = jnp.asarray(np.stack([np.asarray(o.ellipsoid.P, float) for o in objects]))
    c = jnp.asarray(np.stack([np.asarray(o.ellipsoid.center, float) for o in objects]))
    proj, front = _project_all(P, c, from_tum(np.asarray(poses_tum, float)), seq.camera)
    proj, front = np.asarray(proj), np.asarray(front)
    cam = seq.camera
    inside = front & np.all(np.isfinite(proj), -1) & (proj[..., 0] >= 0) & (proj[..., 1] >= 0) \
        & (proj[..., 2] <= cam.width) & (proj[..., 3] <= cam.height)
    if not inside.any():
        return float("nan"), 0
    seen = np.zeros(inside.shape, bool)
    labels = np.array([str(o.label) for o in objects])
    for d in seq.detections:
        f = int(d.frame)
        ks = np.flatnonzero(inside[f] & (labels == d.label))
        if ks.size:
            iou = box_iou(np.asarray(d.box, float)[None], proj[f, ks])
            seen[f, ks] |= np.asarray(iou) >= min_iou
    n = int(inside.sum())
    return float(seen[inside].mean()), n


def confirm_by_boxes(seq, loc: Localization, map_objects, poses_tum) -> tuple[float, int]:
    """(share, predicted) of ``box_agreement`` of the recording ``seq`` with the map objects
    ``loc`` matched, seen from ``poses_tum`` (the recording's poses moved into the map's
    frame); ``LocalizationError`` when the boxes contradict the transform (confirm fewer
    than ``MIN_BOX_AGREEMENT`` of the sightings it predicts)."""
    matched = {int(b) for _, b in loc.matches}
    share, predicted = box_agreement(seq, [o for o in map_objects if int(o.id) in matched], poses_tum)
    if predicted and not share >= MIN_BOX_AGREEMENT:
        raise LocalizationError(
            f"the recording's boxes contradict the transform: they confirm {100 * share:.0f} % of the "
            f"{predicted} sightings of the {len(matched)} matched map objects it predicts, below "
            f"{100 * MIN_BOX_AGREEMENT:.0f} %")
    return share, predicted


def refine_localization(seq, seq_objects, map_objects, loc: Localization, *, poses_tum=None,
                        refine_scale: bool = False,
                        floors: tuple[float, float] = (REFINE_CENTER_SIGMA, REFINE_SHAPE_SIGMA)) -> Localization:
    """``loc`` refined with the recording's boxes against the matched map objects (module
    docstring, step 5): the recording ``seq`` (its detections), its objects ``seq_objects``
    (for the centre residuals) and the map's; ``poses_tum`` the recording's camera poses, one
    TUM row with its timestamp per frame (its run's ``MapResult.poses_tum``, which
    ``localized_result`` moves), default the sequence's own. Returns ``loc``
    with the refined transform, its covariance and a note; ``loc`` unchanged (with a note)
    when fewer than three objects have a paired box. Under Sim(3) the scale stays the one
    of the objects' layout unless ``refine_scale`` (a ``geometry.Sim3`` frame then): on
    fr2_desk the boxes fix it no better than the layout does (docs/map-reuse.md); its
    variance and the rest of the covariance are then kept apart.
    ``floors``: (centre m, shape) the floors of the σ that hold the map's objects."""
    import jaxlie

    from ..geometry import Sim3

    by_id = {int(o.id): o for o in map_objects}
    mine = {int(o.id): o for o in seq_objects}
    matched = [by_id[int(b)] for _, b in loc.matches if int(b) in by_id]
    if len(seq.detections) == 0 or len(matched) < 3:
        return replace(loc, notes=[*loc.notes, "not refined with the boxes: fewer than three matched objects"])
    rows = np.c_[seq.timestamps, seq.poses_tum] if poses_tum is None else np.asarray(poses_tum, float)
    if rows.shape != (len(seq), 8):
        raise ValueError(f"refine_localization: {len(seq)} frames but poses of shape {rows.shape}")
    scaled = loc.sim3 and not refine_scale  # the recording pre-scaled, a rigid frame refined
    s0 = float(loc.scale) if scaled else 1.0
    frame: Any = Sim3.from_matrix(loc.T_map_sequence, loc.scale) if loc.sim3 and not scaled \
        else jaxlie.SE3.from_matrix(loc.T_map_sequence)
    fit = _refine_frame(seq, rows, matched, frame, s0, floors)
    if isinstance(fit, str):
        return replace(loc, notes=[*loc.notes, fit])
    frame, res, before, seen, n_boxes = fit
    T = np.asarray(frame.as_matrix(), float)
    s_new = float(frame.scale) if isinstance(frame, Sim3) else s0
    _, _, iou = _paired_detections(seq, [o.ellipsoid for o in matched], [o.label for o in matched],
                                  transform_poses_tum(rows, T, s_new)[:, 1:], REFINE_MIN_IOU)
    after = float(np.median(iou)) if len(iou) else None
    try:
        cov_r = np.asarray(res.marginal_covariances([FRAME_KEY])[FRAME_KEY], dtype=float)
        cov = _left_covariance(frame, cov_r, isinstance(frame, Sim3))
        if scaled:  # the scale's variance from the objects' fit, apart from the rigid part
            cov = np.pad(cov, (0, 1))
            cov[6, 6] = loc.covariance[6, 6]
    except (ValueError, np.linalg.LinAlgError):
        cov = np.full_like(loc.covariance, np.inf)
    pairs = [(mine[int(a)], by_id[int(b)]) for a, b in loc.matches if int(a) in mine and int(b) in by_id]
    resid = np.array([np.linalg.norm(s_new * T[:3, :3] @ np.asarray(a.ellipsoid.center, float) + T[:3, 3]
                                     - np.asarray(b.ellipsoid.center, float)) for a, b in pairs])

    def fmt(v):
        return "—" if v is None else f"{v:.3f}"

    note = (f"refined with {n_boxes} boxes of {len(seen)} matched objects: median IoU of the boxes and the "
            f"map's projected objects {fmt(before)} → {fmt(after)}")
    return replace(loc, T_map_sequence=T, scale=s_new, covariance=cov,
                   residuals=resid if len(resid) == len(loc.residuals) else loc.residuals,
                   notes=[*loc.notes, note])


def _refine_frame(seq, rows: np.ndarray, matched: list, frame, s0: float, floors: tuple[float, float]):
    """``REFINE_ROUNDS`` rounds of pairing the recording's boxes (cameras ``rows`` moved by
    ``frame``, pre-scaled by ``s0``) with the projected ``matched`` map objects and fitting
    the frame to them, the objects held by priors (σ no smaller than ``floors``): (frame,
    the last LM result, the median IoU before, the ids seen, boxes used), or why not (str)."""
    from ..factors import DEFAULT_TRUNCATION_MARGIN, FrameBoxFactor, LandmarkPriorFactor
    from ..geometry import Sim3
    from ..solver import L, LevenbergMarquardt, NonlinearFactorGraph, Values
    from ._methods import AUTO_BOX_KERNEL, DEFAULT_MAPPING_SIGMAS, robust_kernel

    by_id = {int(o.id): o for o in matched}
    frames = np.array([d.frame for d in seq.detections])
    boxes = np.stack([np.asarray(d.box, float) for d in seq.detections])
    # the recording's camera poses, jaxlie's wxyz_xyz (TUM rows are xyz, then xyzw)
    q = rows[:, 1:].copy()
    q[:, 3:7] /= np.linalg.norm(q[:, 3:7], axis=1, keepdims=True)
    wxyz_xyz = np.c_[q[:, 6], q[:, 3:6], s0 * q[:, :3]][frames]
    sigma = inverse_box_sigma(boxes, DEFAULT_MAPPING_SIGMAS)
    robust = robust_kernel(*AUTO_BOX_KERNEL)
    ells = {o.id: o.ellipsoid for o in matched}
    before, res, n_boxes, seen = None, None, 0, []
    for _ in range(max(int(REFINE_ROUNDS), 1)):
        T_now = np.asarray(frame.as_matrix(), float)
        s_now = float(frame.scale) if isinstance(frame, Sim3) else s0
        d, k, iou = _paired_detections(seq, [ells[o.id] for o in matched], [o.label for o in matched],
                                      transform_poses_tum(rows, T_now, s_now)[:, 1:], REFINE_MIN_IOU)
        if before is None:
            before = float(np.median(iou)) if len(iou) else None
        seen = sorted({int(matched[j].id) for j in k})
        if len(seen) < 3:
            return (f"not refined with the boxes: {len(seen)} matched object(s) have a box that overlaps "
                    "their projection")
        graph = NonlinearFactorGraph()
        keys = [L(int(matched[j].id)) for j in k]
        graph.add(FrameBoxFactor.many(FRAME_KEY, keys, wxyz_xyz[d], boxes[d], seq.camera, sigma=sigma[d],
                                      robust=robust, truncation_margin=DEFAULT_TRUNCATION_MARGIN))
        values = Values({FRAME_KEY: frame})
        for oid in seen:
            o = by_id[oid]
            u = o.uncertainty or {}
            sc = max(float(u.get("center_sigma_max", 0.0) or 0.0), floors[0])
            sr = max(2.0 * float(np.max(u.get("log_radius_sigma", [0.0]))), floors[1])
            if not (np.isfinite(sc) and np.isfinite(sr)):
                sc, sr = max(sc, 1.0) if np.isfinite(sc) else 1.0, 1.0
            graph.add(LandmarkPriorFactor(L(oid), o.ellipsoid, sigma=np.r_[np.full(6, sr), np.full(3, sc)]))
            values[L(oid)] = ells[oid]
        res = LevenbergMarquardt().optimize(graph, values)
        frame = res.values[FRAME_KEY]
        ells.update({oid: res.values[L(oid)] for oid in seen})
        n_boxes = len(d)
    return frame, res, before, seen, n_boxes


def transform_ellipsoid(e: Ellipsoid, T: np.ndarray, scale: float = 1.0) -> Ellipsoid:
    """The ellipsoid moved by x ↦ s R x + t: (s² R P Rᵀ, s R c + t)."""
    R, t = np.asarray(T, float)[:3, :3], np.asarray(T, float)[:3, 3]
    P = scale**2 * R @ np.asarray(e.P, float) @ R.T
    return Ellipsoid(0.5 * (P + P.T), scale * R @ np.asarray(e.center, float) + t)


def transform_poses_tum(rows, T: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """TUM rows (timestamp tx ty tz qx qy qz qw) of camera-to-world poses moved by
    x ↦ s R x + t: the camera centre moves as a point, the orientation is R·R_wc."""
    from scipy.spatial.transform import Rotation

    rows = np.asarray(rows, float)
    R, t = np.asarray(T, float)[:3, :3], np.asarray(T, float)[:3, 3]
    out = rows.copy()
    out[:, 1:4] = scale * rows[:, 1:4] @ R.T + t
    q = (Rotation.from_matrix(R) * Rotation.from_quat(rows[:, 4:8])).as_quat()
    out[:, 4:8] = q
    return out


def _moved_object(o, T, scale):
    """A ``MapObject`` moved by x ↦ s R x + t; its centre's σ per axis rotated (the diagonal of
    R diag(σ²) Rᵀ, times s), its log-radius σ unchanged, its covariance ``moved_covariance``."""
    u = o.uncertainty
    if u:
        R = np.asarray(T, float)[:3, :3]
        u = dict(u)
        sig = np.asarray(u["center_sigma"], float)
        u["center_sigma"] = (scale * np.sqrt(np.diag(R @ np.diag(sig**2) @ R.T))).tolist()
        u["center_sigma_max"] = scale * float(u["center_sigma_max"])
        if u.get("covariance") is not None:
            u["covariance"] = moved_covariance(u["covariance"], R, scale).tolist()
    return replace(o, ellipsoid=transform_ellipsoid(o.ellipsoid, T, scale), uncertainty=u)


def localized_result(result, loc: Localization):
    """A ``MapResult`` moved into the map's frame: its objects, first estimates and poses."""
    T, s = loc.T_map_sequence, loc.scale
    note = (f"localised against a map from {len(loc.matches)} objects: centre rms {loc.rms:.3f} m"
            + (f", scale {s:.4f}" if loc.sim3 else ""))
    return replace(result, objects=[_moved_object(o, T, s) for o in result.objects],
                   initial_objects=[_moved_object(o, T, s) for o in result.initial_objects],
                   poses_tum=transform_poses_tum(result.poses_tum, T, s),
                   notes=[*result.notes, note])


def moved_sequence(seq, T: np.ndarray, scale: float = 1.0):
    """``seq`` re-expressed in another frame, x ↦ s R x + t: its poses, and the priors that
    live in its frame (support planes [n; d] ↦ [R n; s d − (R n)·t], the up direction, and the
    translation parts of the trajectory's sigmas, times s). Camera-frame data (boxes,
    measured ellipsoids) and the ground truth (evaluation aligns to it) are unchanged."""
    T = np.asarray(T, float)
    R, t = T[:3, :3], T[:3, 3]
    rows = transform_poses_tum(np.c_[seq.timestamps, seq.poses_tum], T, scale)[:, 1:]
    pr = seq.priors
    if pr is not None:
        def plane(p):
            n = R @ np.asarray(p[:3], float)
            return np.r_[n, scale * float(p[3]) - n @ t]

        def scaled(sig):
            return None if sig is None else np.asarray(sig, float) * np.r_[scale, 1.0]

        pr = replace(pr, support_planes=[plane(p) for p in pr.support_planes],
                     up=None if pr.up is None else R @ np.asarray(pr.up, float),
                     trajectory_sigma=scaled(pr.trajectory_sigma),
                     trajectory_absolute_sigma=scaled(pr.trajectory_absolute_sigma))
    return replace(seq, poses_tum=rows, priors=pr)


def joined_sequence(a, b, name: str | None = None):
    """One sequence of ``a`` then ``b`` (both in one frame: ``b`` moved there first, e.g. by
    ``moved_sequence``), b starting a segment (``Sequence.segments``: no odometry links the
    two, and b's poses move together when it is mapped); b's frames, detections and
    measured ellipsoids renumbered after a's;
    b's times shifted, when they do not follow a's, to start one median frame step after a's
    last (images keyed alike). Camera, priors and ground truth are a's (the evaluation of a
    join reads a's ground truth)."""
    from dataclasses import replace as _replace

    ta, tb = np.asarray(a.timestamps, float), np.asarray(b.timestamps, float)
    shift = 0.0
    if len(ta) and len(tb) and tb[0] <= ta[-1]:
        steps = np.diff(ta)
        shift = float(ta[-1] - tb[0] + (np.median(steps) if steps.size else 1.0))
    n = len(a)
    dets = list(a.detections) + [_replace(d, frame=d.frame + n, timestamp=d.timestamp + shift)
                                 for d in b.detections]
    ells = None
    if a.ellipsoids is not None or b.ellipsoids is not None:
        ells = list(a.ellipsoids or []) + [_replace(e, frame=e.frame + n, timestamp=e.timestamp + shift)
                                           for e in b.ellipsoids or []]
    images = None
    if a.images or b.images:
        images = dict(a.images or {})
        images.update({t + shift: p for t, p in (b.images or {}).items()})
    return _replace(a, name=name or f"{a.name}+{b.name}", timestamps=np.r_[ta, tb + shift],
                    poses_tum=np.r_[np.asarray(a.poses_tum), np.asarray(b.poses_tum)],
                    detections=dets, ellipsoids=ells, images=images,
                    segments=(*a.segments, n, *(k + n for k in b.segments)))
