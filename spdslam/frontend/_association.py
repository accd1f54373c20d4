"""Data association: grouping a sequence's detections into tracks, one per object.

Manual association (:func:`tracks_from_instances`) groups detections by their ``instance``
id. A negative instance id marks a detection known to be false (clutter, e.g. injected by
the demo generator): it belongs to no object and manual association leaves it out.

Automatic association (:func:`associate`) uses only the boxes, labels, trajectory, camera
and priors: per-frame Hungarian tracking on projected-box IoU, k-detection confirmation,
merging of duplicates by SPD log-map distance and centre distance, and batch re-assignment
of every frame against all landmarks. :func:`association_scores` measures precision and
recall against the instance ids.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from ..geometry import Ellipsoid, box_iou, in_front, project_box, spd, truncation_mask
from ..geometry.se3 import quat_to_matrix
from ..io import Sequence, class_prior

__all__ = [
    "Track",
    "tracks_from_instances",
    "AssociationSettings",
    "Association",
    "associate",
    "associate_detailed",
    "merge_tracks",
    "association_scores",
    "OnlineTracker",
]


@dataclass(frozen=True)
class Track:
    """The detections of one object: its id, label, frame indices and boxes (k, 4)."""

    id: int
    label: str
    frames: np.ndarray
    boxes: np.ndarray


def tracks_from_instances(seq: Sequence) -> list:
    """Group detections by their ``instance`` id (manual association); negative ids
    (known false detections) are left out."""
    missing = [d for d in seq.detections if d.instance is None]
    if missing:
        raise ValueError(
            f"{len(missing)} of {len(seq.detections)} detections have no instance id; "
            "manual association needs the instance column (or use automatic association)"
        )
    groups: dict = {}
    for d in seq.detections:
        if d.instance >= 0:
            groups.setdefault(d.instance, []).append(d)
    tracks = []
    for k in sorted(groups):
        ds = sorted(groups[k], key=lambda d: d.frame)
        labels = sorted({d.label for d in ds})
        label = max(labels, key=lambda lab: sum(d.label == lab for d in ds))
        tracks.append(
            Track(int(k), label, np.array([d.frame for d in ds]), np.array([d.box for d in ds]))
        )
    return tracks


# --- automatic association -------------------------------------------------------------------
#
# Everything below computes in NumPy (the geometry functions stay in NumPy for NumPy input):
# the association runs thousands of tiny geometric problems (one per frame, tracklet or pair
# of tracklets), where per-call JAX dispatch would dominate.

_BIG = 1e6  # cost of a forbidden pairing in the Hungarian assignment
_MIN_DEPTH = 0.05  # m: a landmark must lie this far in front of the camera to be predicted


@dataclass(frozen=True)
class AssociationSettings:
    """Parameters of :func:`associate` (defaults tuned on the demo rooms, checked on fr3).

    ``min_detections`` k: a track becomes a landmark once it has k detections; shorter ones
    are discarded. ``iou_gate``: least IoU between a detection and a predicted box (clipped
    to the image) for them to be paired. ``max_gap``: frames a tracklet may go unseen and
    still be continued. Merging: ``spd_gate`` is the largest affine-invariant log-map
    distance ‖Log(P₁^-½ P₂ P₁^-½)‖_F between the shapes of two tracks, ``centre_gate`` the
    largest Mahalanobis distance between their centres, with ``centre_tolerance``·(r̄₁ + r̄₂)
    (mean radii) added as isotropic model error and drift. ``window`` (frames): σ of the
    time weights of the landmarks used in the batch re-assignment; ``iterations``: its
    rounds at most. Landmark fit: ``ray_sigma`` (rad), angular accuracy of the ray through a
    box centre; ``size_sigma``, relative accuracy of the depth guessed from a box's size and
    its class prior (``default_radius`` m when the class has none); ``truncation_margin``
    (px): a box edge this close to the image border is truncated.
    """

    min_detections: int = 3
    iou_gate: float = 0.2
    max_gap: int = 10
    spd_gate: float = 2.5
    centre_gate: float = 3.0
    centre_tolerance: float = 0.5
    window: float = 15.0
    iterations: int = 3
    ray_sigma: float = 0.02
    size_sigma: float = 0.5
    default_radius: float = 0.3
    truncation_margin: float = 2.0

    def __post_init__(self):
        k = self.min_detections
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
            raise ValueError(f"min_detections must be an integer >= 1, got {k!r}")
        if not (isinstance(self.iterations, (int, np.integer)) and self.iterations >= 0):
            raise ValueError(f"iterations must be an integer >= 0, got {self.iterations!r}")
        if not (isinstance(self.max_gap, (int, np.integer)) and self.max_gap >= 0):
            raise ValueError(f"max_gap must be an integer >= 0, got {self.max_gap!r}")
        if not 0.0 < self.iou_gate < 1.0:
            raise ValueError(f"iou_gate must be in (0, 1), got {self.iou_gate!r}")
        for name in ("spd_gate", "centre_gate", "centre_tolerance", "window", "ray_sigma",
                     "size_sigma", "default_radius"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive finite number, got {v!r}")
        if not (np.isfinite(self.truncation_margin) and self.truncation_margin >= 0):
            raise ValueError(f"truncation_margin must be >= 0, got {self.truncation_margin!r}")


@dataclass(frozen=True)
class Association:
    """Result of :func:`associate_detailed`: the ``tracks``; ``assignment`` (n,), the track
    id of every detection of the sequence (in ``seq.detections`` order; −1: left out);
    ``centres`` (m, 3) and ``shapes`` (m, 3, 3) of the landmark fitted to each track (the
    association's own coarse model, not a map); ``stats`` counts and timing."""

    tracks: list
    assignment: np.ndarray
    centres: np.ndarray
    shapes: np.ndarray
    stats: dict


def _median(a: np.ndarray) -> float:
    """``np.median`` of a 1-D array (the same number: the middle order statistic, or the
    mean (x + y) / 2 of the two middle ones), without its general-purpose overhead, which
    dominated the tracker's refits of short tracks."""
    n = a.size
    if n == 0 or not np.all(np.isfinite(a)):
        return float(np.median(a))
    h = n // 2
    if n % 2:
        return float(np.partition(a, h)[h])
    p = np.partition(a, (h - 1, h))
    return float((p[h - 1] + p[h]) / 2.0)


@dataclass(frozen=True)
class _Fit:
    """A track's coarse landmark: centre X, shape P, mean radius r̄ = √(r_h r_v), the
    information matrix A of X (its covariance is A⁻¹), the support plane used (or None)
    and whether the fit is usable."""

    X: np.ndarray
    P: np.ndarray
    radius: float
    info: np.ndarray
    plane: np.ndarray | None
    ok: bool


_BAD_FIT = _Fit(np.zeros(3), np.eye(3), 0.0, np.eye(3), None, False)


def _check_boxes(box: np.ndarray, frames) -> None:
    """``ValueError`` naming the first box that is not finite or not proper (x2 > x1, y2 > y1)."""
    bad = ~np.all(np.isfinite(box), axis=1) | (box[:, 2] <= box[:, 0]) | (box[:, 3] <= box[:, 1])
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(f"detection {i} (frame {frames[i]}) has an invalid box {box[i].tolist()}")


class _Scene:
    """The sequence as arrays, and the per-detection terms of the landmark fit.

    Landmark model. A track's landmark is an ellipsoid (X, P): X minimises

        Σᵢ w⊥ᵢ ‖(I − dᵢdᵢᵀ)(X − oᵢ)‖² + (Σᵢ wρᵢ (dᵢᵀ(X − oᵢ) − ρᵢ)²) / n + w_π (nᵀX + δ − r_v)²

    over its n detections i (camera centre oᵢ, unit world ray dᵢ through the box centre):
    the rays' least-squares intersection (w⊥ = 1/(σ_ray ρᵢ)², σ ×4 for a truncated box),
    regularised by the range guessed from the box size and the class prior (ρᵢ =
    f̄·2r̄/√(wh) / (dᵢ·zᵢ), r̄ the geometric mean of the prior radii or ``default_radius``;
    wρ = 1/(σ_size ρᵢ)², averaged so that it weighs as one view) and, when the priors have
    support planes nᵀx + δ = 0, by resting on the nearest one (σ_π = 0.25 r_v + 2 cm; a second
    pass after a plane-free one). The shape is upright, P = r_h²(I − uuᵀ) + r_v² uuᵀ (u = up;
    a sphere without one), r_h = median wᵢzᵢ/(2f_x), r_v = median hᵢzᵢ/(2f_y) over the
    untruncated box widths and heights (zᵢ the depth of X in view i): the apparent ellipsoid
    of the boxes, enough to predict boxes, compare shapes and gate. Weighted fits (weights
    per detection) serve the time-local landmarks of the batch re-assignment.
    """

    # the per-detection arrays (``_terms``), set with setattr
    frame: np.ndarray
    box: np.ndarray
    label: np.ndarray
    w_ok: np.ndarray
    h_ok: np.ndarray
    ray: np.ndarray
    origin: np.ndarray
    radius0: np.ndarray
    terms: np.ndarray
    up: np.ndarray | None
    planes: np.ndarray | None

    def __init__(self, seq: Sequence, s: AssociationSettings):
        dets = seq.detections
        self._setup(seq.camera, seq.priors, s)
        n = len(dets)
        self.F = len(seq)
        frame = np.array([d.frame for d in dets], dtype=int).reshape(n)
        if n and (frame.min() < 0 or frame.max() >= self.F):
            raise ValueError(
                f"detection frames must lie in [0, {self.F}), got {frame.min()}..{frame.max()}"
            )
        box = np.array([d.box for d in dets], dtype=float).reshape(n, 4)
        _check_boxes(box, [d.frame for d in dets])
        self.labels = sorted({d.label for d in dets})
        lab_idx = {lab: k for k, lab in enumerate(self.labels)}
        label = np.array([lab_idx[d.label] for d in dets], dtype=int).reshape(n)
        poses = np.asarray(seq.poses_tum, dtype=float)
        if not np.all(np.isfinite(poses)):
            raise ValueError("the trajectory (poses_tum) has non-finite values")
        self.R = quat_to_matrix(poses[:, 3:7]).reshape(self.F, 3, 3)  # R_wc
        self.C = poses[:, :3]
        self.Rz = np.ascontiguousarray(self.R[:, :, 2])  # the optical axes, for depths
        for name, value in self._terms(frame, box, label).items():
            setattr(self, name, value)
        self.by_frame = [np.flatnonzero(self.frame == f) for f in range(self.F)]

    def _setup(self, camera, priors, s: AssociationSettings) -> None:
        """The camera, priors and per-class prior radius (what every detection's terms use)."""
        self.camera, self.priors, self.settings = camera, priors, s
        self.fx, self.fy, self.cx, self.cy = (float(v) for v in (camera.fx, camera.fy, camera.cx, camera.cy))
        self.W, self.H = float(camera.width), float(camera.height)
        self.up, self.planes = (None, None) if priors is None else priors.up_and_planes()
        self._class_radius: dict = {}

    def class_radius(self, label: str) -> float:
        """The geometric mean of the class prior's radii (``default_radius`` without one)."""
        if label not in self._class_radius:
            cp = class_prior(self.priors, label)
            self._class_radius[label] = (self.settings.default_radius if cp is None else
                                         float(np.exp(np.mean(np.log(np.asarray(cp.radii))))))
        return self._class_radius[label]

    def _terms(self, frame, box, label) -> dict:
        """The per-detection arrays of detections (frame (n,), box (n, 4), label index (n,))
        whose frames' poses are in ``self.R``, ``self.C``: ray, truncation, prior range and
        the fit's normal-equation terms (class docstring)."""
        s, n, b = self.settings, frame.size, box
        keep = np.asarray(truncation_mask(b, self.camera, s.truncation_margin)) > 0
        w_ok = keep[:, 0] & keep[:, 2]  # width untruncated
        h_ok = keep[:, 1] & keep[:, 3]
        u = 0.5 * (b[:, 0] + b[:, 2])
        v = 0.5 * (b[:, 1] + b[:, 3])
        ray_c = np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy, np.ones(n)], 1)
        ray_c /= np.linalg.norm(ray_c, axis=1, keepdims=True)
        ray = np.einsum("nij,nj->ni", self.R[frame], ray_c)
        origin = self.C[frame]
        radius = np.array([self.class_radius(lab) for lab in self.labels] or [0.0])[label].reshape(n)
        w, h = b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]
        size_px = np.where(w_ok & h_ok, np.sqrt(w * h), np.where(w_ok, w, np.where(h_ok, h, np.maximum(w, h))))
        range0 = np.sqrt(self.fx * self.fy) * 2.0 * radius / size_px / ray_c[:, 2]
        sig_ray = s.ray_sigma * np.where(w_ok & h_ok, 1.0, 4.0)
        w_perp = 1.0 / (sig_ray * range0) ** 2
        w_rng = 1.0 / (s.size_sigma * range0) ** 2
        w_rng = np.where(w_ok | h_ok, w_rng, 0.01 * w_rng)
        ddT = ray[:, :, None] * ray[:, None, :]
        A_perp = w_perp[:, None, None] * (np.eye(3)[None] - ddT)
        A_rng = w_rng[:, None, None] * ddT
        return dict(
            frame=frame, box=b, label=label, w_ok=w_ok, h_ok=h_ok, ray=ray, origin=origin,
            radius0=radius,
            # the centre fit's terms, side by side (n, 24): A_perp (9), b_perp (3), A_rng (9),
            # b_rng (3); ``_normal`` sums them with one matrix product
            terms=np.concatenate([
                A_perp.reshape(-1, 9), np.einsum("nij,nj->ni", A_perp, origin), A_rng.reshape(-1, 9),
                (w_rng * (np.einsum("ni,ni->n", ray, origin) + range0))[:, None] * ray], axis=1),
        )

    # -- landmark fit and prediction --------------------------------------------------------

    def _normal(self, idx, W, plane=None, r_v=None):
        """Normal equations (A, b) (leading axes of W (…, n) batch) of the centre fit."""
        tot = np.maximum(W.sum(-1), 1e-300)[..., None]
        # one matrix product per sum (W (…, n) against the stacked terms (n, 9 + 3 + 9 + 3))
        S = W @ self.terms[idx]
        A = (S[..., :9] + S[..., 12:21] / tot).reshape(S.shape[:-1] + (3, 3))
        b = S[..., 9:12] + S[..., 21:] / tot
        if plane is not None:
            nrm, delta = plane[:3], plane[3]
            w_pl = 1.0 / (0.25 * r_v + 0.02) ** 2
            A = A + w_pl * np.outer(nrm, nrm)
            b = b + w_pl * (r_v - delta) * nrm
        return A, b

    def _radii(self, idx, X):
        """(r_h, r_v) from the untruncated box sizes at the depths of X (the detections'
        median prior radius where no box side is whole)."""
        f = self.frame[idx]
        z = np.einsum("ni,ni->n", self.Rz[f], X - self.C[f])
        front = z > _MIN_DEPTH
        if not front.any():
            return None
        b = self.box[idx]
        wz = ((b[:, 2] - b[:, 0]) * z / (2 * self.fx))[front & self.w_ok[idx]]
        hz = ((b[:, 3] - b[:, 1]) * z / (2 * self.fy))[front & self.h_ok[idx]]
        r_h = _median(wz) if wz.size else None
        r_v = _median(hz) if hz.size else None
        if r_h is None and r_v is None:
            r_h = _median(self.radius0[idx])
        r_h = r_h if r_h is not None else r_v
        r_v = r_v if r_v is not None else r_h
        return r_h, r_v

    def fit(self, idx) -> _Fit:
        """The coarse landmark of detections ``idx`` (see the class docstring)."""
        idx = np.asarray(idx, dtype=int)
        W = np.ones(idx.size)
        plane = None
        r_v: Any = None  # none in the first pass, then the previous pass's vertical radius
        for _ in range(2 if self.planes is not None else 1):
            A, b = self._normal(idx, W, plane, r_v)
            try:
                X = np.linalg.solve(A, b)
            except np.linalg.LinAlgError:
                return _BAD_FIT
            radii = self._radii(idx, X) if np.all(np.isfinite(X)) else None
            if radii is None:
                return _BAD_FIT
            r_h, r_v = radii
            if self.planes is not None and plane is None:
                # the plane nearest to the bottom of the first estimate: |nᵀX + δ − r_v|
                gap = np.abs(self.planes[:, :3] @ X + self.planes[:, 3] - r_v)
                plane = self.planes[int(np.argmin(gap))]
        if self.up is None:
            P = r_h * r_v * np.eye(3)
        else:
            uu = np.outer(self.up, self.up)
            P = r_h**2 * (np.eye(3) - uu) + r_v**2 * uu
        return _Fit(X, P, float(np.sqrt(r_h * r_v)), A, plane, True)

    def local_centres(self, idx, fit: _Fit, frames, window: float) -> np.ndarray:
        """Centres (m, 3) of the landmark of ``idx`` seen at each of ``frames`` (m,): the fit
        with weights exp(−½((fᵢ − f)/window)²) on its detections, so that each frame sees a
        landmark consistent with the nearby (equally drifted) part of the trajectory."""
        W = (self.frame[idx][None, :] - np.asarray(frames)[:, None]) / window
        # exp(−½ df²) + 1e-12, in place (the same operations as written out; this (m, n)
        # array is the largest the association makes)
        np.square(W, out=W)
        W *= -0.5
        np.exp(W, out=W)
        W += 1e-12
        r_v = np.sqrt(fit.P[2, 2]) if self.up is None else float(np.sqrt(self.up @ fit.P @ self.up))
        A, b = self._normal(idx, W, fit.plane, r_v)
        return np.linalg.solve(A, b[..., None])[..., 0]

    def project(self, X, P, frames):
        """Boxes (m, 4) of landmarks (X (m, 3), P (m, 3, 3)) in ``frames`` (m,), clipped to
        the image (zeros where invisible), and whether each is visible (wholly in front,
        non-empty after clipping)."""
        landmark, pose = Ellipsoid(P, X), (self.R[frames], self.C[frames])
        ok = in_front(landmark, pose, _MIN_DEPTH)
        with np.errstate(divide="ignore", invalid="ignore"):  # boxes of landmarks not in front
            box = np.clip(project_box(landmark, pose, self.camera), 0.0, [self.W, self.H, self.W, self.H])
        ok &= (box[:, 2] > box[:, 0]) & (box[:, 3] > box[:, 1])
        return np.where(ok[:, None], box, 0.0), ok


def _hungarian(cost, allowed):
    """Pairs (rows, cols) of the min-cost assignment among allowed entries."""
    if cost.size == 0:
        return np.zeros(0, int), np.zeros(0, int)
    r, c = linear_sum_assignment(np.where(allowed, cost, _BIG))
    keep = allowed[r, c]
    return r[keep], c[keep]


# -- stage 1: tracklets ------------------------------------------------------------------------


@dataclass
class _Tracking:
    """Frame-by-frame tracking state: per tracklet its detections, label, last frame and
    coarse landmark (``_Fit``)."""

    groups: list = dataclasses.field(default_factory=list)
    label: list = dataclasses.field(default_factory=list)
    last: list = dataclasses.field(default_factory=list)
    fits: list = dataclasses.field(default_factory=list)


def _track_frame(sc: _Scene, s: AssociationSettings, st: _Tracking, f: int, dets: np.ndarray,
                 refit=None, always=(), candidates=None) -> np.ndarray:
    """Frame f of the tracking (``_tracklets``): its detections ``dets`` (indices into
    ``sc``) assigned to the tracklets of ``st`` seen in the last ``max_gap`` frames, or
    new ones; ``st`` is updated in place (``refit(t)``: tracklet t's new fit, default
    ``sc.fit`` of all its detections; tracklets in ``always`` are candidates however long
    unseen; ``candidates``: the tracklets to consider, default all). Returns the tracklet of
    each detection."""
    refit = refit or (lambda t: sc.fit(st.groups[t]))
    owner = np.full(dets.size, -1)
    act = [t for t in (range(len(st.groups)) if candidates is None else candidates)
           if st.fits[t].ok and (f - st.last[t] <= s.max_gap or t in always)]
    if act:
        boxes, vis = sc.project(
            np.array([st.fits[t].X for t in act]), np.array([st.fits[t].P for t in act]),
            np.full(len(act), f),
        )
        iou = box_iou(boxes[:, None], sc.box[dets][None])
        allowed = (
            vis[:, None]
            & (np.array([st.label[t] for t in act])[:, None] == sc.label[dets][None])
            & (iou >= s.iou_gate)
        )
        rows, cols = _hungarian(1.0 - iou, allowed)
        for r, c in zip(rows, cols):
            t = act[r]
            st.groups[t].append(dets[c])
            st.last[t] = f
            st.fits[t] = refit(t)
            owner[c] = t
    for c in np.flatnonzero(owner < 0):
        st.groups.append([dets[c]])
        st.label.append(sc.label[dets[c]])
        st.last.append(f)
        st.fits.append(sc.fit([dets[c]]))
        owner[c] = len(st.groups) - 1
    return owner


def _tracklets(sc: _Scene, s: AssociationSettings, dets_mask=None) -> list:
    """Frame-by-frame tracking: Hungarian on 1 − IoU(predicted box, detection) between the
    tracklets seen in the last ``max_gap`` frames and the frame's detections (same label,
    IoU ≥ ``iou_gate``); a detection that passes no gate starts a new tracklet. Only the
    detections where ``dets_mask`` is True take part (all by default)."""
    st = _Tracking()
    for f in range(sc.F):
        dets = sc.by_frame[f]
        if dets_mask is not None:
            dets = dets[dets_mask[dets]]
        if dets.size:
            _track_frame(sc, s, st, f, dets)
    return [np.array(g, dtype=int) for g in st.groups]


# -- stage 2: merging --------------------------------------------------------------------------


def _merge_cost(sc: _Scene, s: AssociationSettings, ga, fa: _Fit, cov_a, gb, fb: _Fit, cov_b):
    """The cost of merging tracks a and b (detections ``ga``, ``gb``; fits and centre
    covariances), or None where a gate forbids it (``_merge``)."""
    if sc.label[ga[0]] != sc.label[gb[0]] or not (fa.ok and fb.ok):
        return None
    if np.intersect1d(sc.frame[ga], sc.frame[gb]).size:
        return None
    d_spd = float(spd.distance(fa.P, fb.P))
    if d_spd > s.spd_gate:
        return None
    tau = s.centre_tolerance * (fa.radius + fb.radius)
    delta = fa.X - fb.X
    d_x = float(np.sqrt(delta @ np.linalg.solve(cov_a + cov_b + tau**2 * np.eye(3), delta)))
    if d_x > s.centre_gate:
        return None
    return d_x / s.centre_gate + d_spd / s.spd_gate


def _merge(sc: _Scene, groups: list, s: AssociationSettings) -> tuple[list, int]:
    """Agglomerative merging of tracks (duplicates: re-entries after a gap, split tracks).

    Two tracks a, b may merge when they have the same label, share no frame, their shapes
    are within ``spd_gate`` in the affine-invariant log-map distance
    d_P = ‖Log(P_a^-½ P_b P_a^-½)‖_F, and their centres within ``centre_gate`` in the
    Mahalanobis distance d_X² = δᵀ(A_a⁻¹ + A_b⁻¹ + τ²I)⁻¹δ, δ = X_a − X_b, A the fits'
    information matrices, τ = ``centre_tolerance``·(r̄_a + r̄_b) (model error and drift).
    Cost d_X/centre_gate + d_P/spd_gate; the cheapest pair merges first, then the merged
    track's costs are recomputed. Returns (groups, number of merges)."""
    groups = [np.sort(np.asarray(g, dtype=int)) for g in groups]
    fits = [sc.fit(g) for g in groups]
    alive = [True] * len(groups)
    covs = [np.linalg.inv(f.info) if f.ok else None for f in fits]

    def pair_cost(a, b):
        return _merge_cost(sc, s, groups[a], fits[a], covs[a], groups[b], fits[b], covs[b])

    costs = {}
    for a in range(len(groups)):
        for b in range(a + 1, len(groups)):
            c = pair_cost(a, b)
            if c is not None:
                costs[(a, b)] = c
    merges = 0
    while costs:
        a, b = min(costs, key=costs.__getitem__)
        groups.append(np.sort(np.concatenate([groups[a], groups[b]])))
        fits.append(sc.fit(groups[-1]))
        covs.append(np.linalg.inv(fits[-1].info) if fits[-1].ok else None)
        alive[a] = alive[b] = False
        alive.append(True)
        merges += 1
        costs = {k: v for k, v in costs.items() if a not in k and b not in k}
        new = len(groups) - 1
        for o in range(new):
            if alive[o]:
                c = pair_cost(o, new)
                if c is not None:
                    costs[(o, new)] = c
    return [g for g, al in zip(groups, alive) if al], merges


# -- stage 3: batch re-assignment --------------------------------------------------------------


def _reassign(sc: _Scene, groups: list, s: AssociationSettings) -> list:
    """Every frame's detections against every landmark: Hungarian on 1 − IoU(projected
    box clipped to the image, detection), same label, IoU ≥ ``iou_gate``. The landmark seen
    from frame f is its time-local fit (``_Scene.local_centres``, σ = ``window`` frames), so
    that odometry drift between distant parts of the sequence does not break the boxes.
    Returns the new groups (possibly empty or short: the caller filters them)."""
    fits = [sc.fit(g) for g in groups]
    keep = [i for i, fit in enumerate(fits) if fit.ok]
    owner = np.full(sc.frame.size, -1)
    if not keep or sc.frame.size == 0:
        return []
    L = len(keep)
    iou = np.zeros((sc.frame.size, L))
    labs = np.array([sc.label[groups[i][0]] for i in keep])
    for j, i in enumerate(keep):
        di = np.flatnonzero(sc.label == labs[j])
        frames, inv = np.unique(sc.frame[di], return_inverse=True)
        X = sc.local_centres(groups[i], fits[i], frames, s.window)[inv]
        boxes, vis = sc.project(X, np.broadcast_to(fits[i].P, (di.size, 3, 3)), sc.frame[di])
        iou[di, j] = np.where(vis, box_iou(boxes, sc.box[di]), 0.0)
    allowed = (sc.label[:, None] == labs[None, :]) & (iou >= s.iou_gate)
    for dets in sc.by_frame:
        if dets.size == 0 or not allowed[dets].any():
            continue
        rows, cols = _hungarian(1.0 - iou[dets], allowed[dets])
        owner[dets[rows]] = cols
    return [np.flatnonzero(owner == j) for j in range(L)]


def associate_detailed(seq: Sequence, settings: AssociationSettings | None = None, **overrides) -> Association:
    """Automatic data association over the whole sequence (batch mode), from the boxes,
    labels, trajectory ``seq.poses_tum``, camera and priors only (never ``Detection.instance``).

    1. Tracklets: per frame, Hungarian assignment of the detections to the recent tracklets on
       1 − IoU between the detection and the tracklet's landmark projected into the frame
       (clipped to the image: truncated detections), different labels forbidden, IoU gated;
       an unassigned detection starts a tentative tracklet. A tracklet's landmark is the
       coarse ellipsoid of ``_Scene`` (rays' intersection, box sizes, class and plane priors).
    2. Landmarks: tracklets with at least ``min_detections`` (k) detections; shorter ones
       are discarded (this removes false detections).
    3. Merging of duplicates (an object re-entering view, split tracks) by label, shared
       frames, SPD log-map distance of the shapes and Mahalanobis distance of the centres
       (``_merge``).
    4. ``iterations`` rounds of batch re-assignment: each frame's detections are assigned
       afresh to all landmarks by Hungarian on the projected-box IoU (time-local landmarks,
       robust to drift); the detections left over are tracked again (step 1) into new
       candidate tracks; tracks shorter than k are discarded and duplicates merged (step 3).

    Tracks are numbered 0, 1, … in order of their first frame. ``settings`` (or keyword
    ``overrides`` of :class:`AssociationSettings`) tune it.
    """
    t0 = time.perf_counter()
    if settings is None:
        settings = AssociationSettings(**overrides)
    elif overrides:
        settings = dataclasses.replace(settings, **overrides)
    s = settings
    sc = _Scene(seq, s)
    tracklets = _tracklets(sc, s)
    groups = [g for g in tracklets if g.size >= s.min_detections]
    stats: dict[str, int | float] = {"tracklets": len(tracklets),
                                     "tentative_discarded": len(tracklets) - len(groups)}
    groups, merges = _merge(sc, groups, s)
    rounds = 0
    for _ in range(s.iterations):
        rounds += 1
        new = _reassign(sc, groups, s)
        left = np.ones(sc.frame.size, bool)
        for g in new:
            left[g] = False
        new += _tracklets(sc, s, left)
        new = [g for g in new if g.size >= s.min_detections]
        new, m = _merge(sc, new, s)
        merges += m
        new = sorted((np.sort(g) for g in new), key=lambda g: g[0])
        same = len(new) == len(groups) and all(
            np.array_equal(a, b) for a, b in zip(new, sorted(groups, key=lambda g: g[0]))
        )
        groups = new
        if same:
            break
    groups.sort(key=lambda g: (sc.frame[g].min(), g[0]))
    assignment = np.full(sc.frame.size, -1)
    tracks, centres, shapes = [], [], []
    for k, g in enumerate(groups):
        g = g[np.argsort(sc.frame[g], kind="stable")]
        assignment[g] = k
        tracks.append(Track(k, sc.labels[sc.label[g[0]]], sc.frame[g].copy(), sc.box[g].copy()))
        fit = sc.fit(g)
        centres.append(fit.X)
        shapes.append(fit.P)
    stats.update(
        merges=merges,
        rounds=rounds,
        tracks=len(tracks),
        assigned=int((assignment >= 0).sum()),
        detections=int(sc.frame.size),
        seconds=time.perf_counter() - t0,
    )
    return Association(
        tracks, assignment, np.array(centres).reshape(-1, 3), np.array(shapes).reshape(-1, 3, 3), stats
    )


class _Grow:
    """Arrays that grow by rows (capacity doubled when full): ``add(**rows)``, ``view(name)``."""

    def __init__(self):
        self.n, self._buf = 0, {}

    def add(self, **rows) -> None:
        k = len(next(iter(rows.values())))
        for name, r in rows.items():
            r = np.asarray(r)
            buf = self._buf.get(name)
            if buf is None:
                buf = self._buf[name] = np.zeros((max(64, k),) + r.shape[1:], r.dtype)
            if self.n + k > len(buf):
                bigger = np.zeros((max(2 * len(buf), self.n + k),) + buf.shape[1:], buf.dtype)
                bigger[: self.n] = buf[: self.n]
                buf = self._buf[name] = bigger
            buf[self.n : self.n + k] = r
        self.n += k

    def view(self, name: str) -> np.ndarray:
        return self._buf[name][: self.n]


class OnlineTracker:
    """Automatic association one frame at a time: the tracking stage of
    :func:`associate_detailed` (step 1), with the same landmark model and gates.

    ``add_frame(R_wc, centre, boxes, labels)`` assigns a frame's detections to the tracks
    seen in the last ``max_gap`` frames (Hungarian on the IoU of the predicted box) or starts
    new ones, and returns the track of each detection. A track's prediction is its coarse
    landmark fitted to its latest ``fit_window`` detections, or the ellipsoid given by
    ``set_landmark`` (the mapped object). ``merge(keep, drop)`` joins two tracks. Work per
    frame is bounded by the tracks alive and ``fit_window``, not by the frames seen.
    """

    def __init__(self, camera, priors=None, settings: AssociationSettings | None = None,
                 fit_window: int = 200, **overrides):
        s = settings or AssociationSettings(**overrides)
        if settings is not None and overrides:
            s = dataclasses.replace(settings, **overrides)
        self.settings, self.fit_window = s, int(fit_window)
        sc = _Scene.__new__(_Scene)
        sc._setup(camera, priors, s)
        sc.labels, sc.F = [], 0
        self._sc = sc
        self._lab: dict = {}
        self._dets, self._frames = _Grow(), _Grow()
        self._state = _Tracking()
        self._mapped: dict = {}
        self._alive: set = set()  # tracks seen in the last max_gap frames

    def _sync(self) -> None:
        sc = self._sc
        for name in ("frame", "box", "label", "w_ok", "h_ok", "ray", "origin", "radius0",
                     "terms"):
            setattr(sc, name, self._dets.view(name))

    def add_frame(self, R_wc, centre, boxes, labels) -> np.ndarray:
        """The track index of each of the frame's detections (boxes (n, 4), labels (n,))."""
        sc, s = self._sc, self.settings
        f = sc.F
        R_wc = np.asarray(R_wc, float)
        self._frames.add(R=R_wc[None], C=np.asarray(centre, float)[None], Rz=R_wc[None, :, 2])
        sc.R, sc.C, sc.F = self._frames.view("R"), self._frames.view("C"), f + 1
        sc.Rz = self._frames.view("Rz")
        boxes = np.asarray(boxes, float).reshape(-1, 4)
        if not len(boxes):
            return np.zeros(0, int)
        _check_boxes(boxes, [f] * len(boxes))
        for lab in labels:
            if lab not in self._lab:
                self._lab[lab] = len(sc.labels)
                sc.labels.append(lab)
        idx = np.array([self._lab[lab] for lab in labels], dtype=int)
        start = self._dets.n
        self._dets.add(**sc._terms(np.full(len(boxes), f), boxes, idx))
        self._sync()
        dets = np.arange(start, self._dets.n)
        st = self._state
        self._alive = {t for t in self._alive if f - st.last[t] <= s.max_gap}
        owner = _track_frame(sc, s, st, f, dets, refit=self._refit, always=self._mapped,
                             candidates=sorted(self._alive | set(self._mapped)))
        self._alive.update(int(t) for t in owner)
        return owner

    def _refit(self, t: int) -> _Fit:
        if t in self._mapped:
            return self._mapped[t]
        return self._sc.fit(self._state.groups[t][-self.fit_window:])

    def set_landmark(self, t: int, centre, P) -> None:
        """Predict track t's boxes from the ellipsoid (centre, P) from now on."""
        fit = self._state.fits[t]
        self._mapped[t] = _Fit(np.asarray(centre, float), np.asarray(P, float), fit.radius,
                               fit.info, fit.plane, True)
        self._state.fits[t] = self._mapped[t]

    def merge(self, keep: int, drop: int) -> None:
        """Track ``drop``'s detections join ``keep``; ``drop`` is no longer continued."""
        st = self._state
        st.groups[keep] = sorted(st.groups[keep] + st.groups[drop])
        st.last[keep] = max(st.last[keep], st.last[drop])
        st.groups[drop] = []
        st.fits[drop] = _BAD_FIT
        self._mapped.pop(drop, None)
        if keep not in self._mapped:
            st.fits[keep] = self._refit(keep)

    def match(self, t: int, candidates) -> int | None:
        """The track among ``candidates`` that track t is a re-entry of (the batch merging's
        gates and cost on the coarse fits of both, ``_merge``), or None."""
        st, sc = self._state, self._sc
        ga = np.array(st.groups[t][-self.fit_window:], dtype=int)
        if not ga.size:
            return None
        fa = sc.fit(ga)
        if not fa.ok:
            return None
        cov_a = np.linalg.inv(fa.info)
        best, best_cost = None, np.inf
        for c in candidates:
            gb = np.array(st.groups[c][-self.fit_window:], dtype=int)
            if c == t or not gb.size:
                continue
            fb = sc.fit(gb)
            if not fb.ok:
                continue
            cost = _merge_cost(sc, self.settings, ga, fa, cov_a, gb, fb, np.linalg.inv(fb.info))
            if cost is not None and cost < best_cost:
                best, best_cost = c, cost
        return best

    def __len__(self) -> int:
        return len(self._state.groups)

    def track(self, t: int) -> tuple[np.ndarray, np.ndarray, str]:
        """(frames, boxes, label) of track t, in frame order."""
        g = np.array(self._state.groups[t], dtype=int)
        frames = self._dets.view("frame")[g] if g.size else np.zeros(0, int)
        boxes = self._dets.view("box")[g] if g.size else np.zeros((0, 4))
        return frames, boxes, self._sc.labels[self._state.label[t]]

    def size(self, t: int) -> int:
        """The number of detections of track t."""
        return len(self._state.groups[t])


def associate(seq: Sequence, settings: AssociationSettings | None = None, **overrides) -> list:
    """Automatic data association: the tracks (see :func:`associate_detailed`)."""
    return associate_detailed(seq, settings, **overrides).tracks


def _detection_indices(tracks, seq: Sequence) -> list:
    """For each track, the indices in ``seq.detections`` of its (frame, box) pairs; raises
    ``ValueError`` for a pair that is no detection or a detection used twice."""
    lookup: dict = {}
    for i, d in enumerate(seq.detections):
        lookup.setdefault((d.frame, np.asarray(d.box, dtype=float).tobytes()), []).append(i)
    used = np.zeros(len(seq.detections), bool)
    out = []
    for tr in tracks:
        frames = np.asarray(tr.frames, dtype=int).reshape(-1)
        boxes = np.asarray(tr.boxes, dtype=float).reshape(-1, 4)
        if frames.size != boxes.shape[0]:
            raise ValueError(f"track {tr.id}: {frames.size} frames but {boxes.shape[0]} boxes")
        idx = []
        for f, b in zip(frames.tolist(), boxes):
            free = [i for i in lookup.get((f, b.tobytes()), []) if not used[i]]
            if not free:
                raise ValueError(
                    f"track {tr.id}: frame {f} box {b.tolist()} is not a detection of the "
                    "sequence (or is already in another track)"
                )
            used[free[0]] = True
            idx.append(free[0])
        out.append(np.array(idx, dtype=int))
    return out


def merge_tracks(tracks, seq: Sequence, settings: AssociationSettings | None = None, **overrides) -> list:
    """Merge duplicate tracks of the same object (the merging step of :func:`associate`):
    same label, no shared frame, log-map shape distance, centre distance and joint
    reprojection within the gates of ``settings``. Returns new tracks numbered by first
    frame; each track's boxes must be detections of ``seq``."""
    s = settings if settings is not None else AssociationSettings(**overrides)
    if settings is not None and overrides:
        s = dataclasses.replace(settings, **overrides)
    sc = _Scene(seq, s)
    groups, _ = _merge(sc, _detection_indices(tracks, seq), s)
    groups = [g[np.argsort(sc.frame[g], kind="stable")] for g in groups if g.size]
    groups.sort(key=lambda g: (sc.frame[g[0]], g[0]))
    return [Track(k, sc.labels[sc.label[g[0]]], sc.frame[g].copy(), sc.box[g].copy())
            for k, g in enumerate(groups)]


def association_scores(tracks, seq: Sequence) -> dict:
    """Precision and recall of ``tracks`` against the sequence's instance ids.

    Each track maps to the ground-truth instance (id ≥ 0) holding the majority of its
    detections (ties: the smaller id; a track of false detections only maps to none), and
    each instance keeps at most one track: the one with the most of its detections (ties:
    the earlier track); the other tracks map to none. A detection is *correct* when its
    track maps to the detection's own instance. Then

        precision = correct / detections in tracks,
        recall    = correct / detections with instance ≥ 0,

    so false detections (instance < 0) in a track count against precision only. An empty
    denominator gives 1.0 (nothing claimed, nothing to find). Tracks are matched to the
    detections by (frame, box); a box that is no detection of ``seq`` raises ``ValueError``,
    and so does a sequence without instance ids.

    Returns {precision, recall, correct, assigned, true_detections, false_assigned,
    tracks, instances, matched_instances, mapping {track id: instance or None}}.
    """
    inst = np.array([-1 if d.instance is None else d.instance for d in seq.detections], dtype=int)
    if any(d.instance is None for d in seq.detections):
        raise ValueError("association scores need the instance ids of the detections")
    idx = _detection_indices(tracks, seq)
    best: dict = {}  # instance -> (count, -order, track order)
    target: list[int | None] = []
    m: int | None  # an instance id
    for k, g in enumerate(idx):
        ids, counts = np.unique(inst[g][inst[g] >= 0], return_counts=True)
        if ids.size == 0:
            target.append(None)
            continue
        m = int(ids[np.argmax(counts)])  # np.unique sorts: argmax takes the smaller id on ties
        target.append(m)
        c = int(counts.max())
        if m not in best or c > best[m][0]:
            best[m] = (c, k)
    mapping = {}
    correct = 0
    for k, (tr, g) in enumerate(zip(tracks, idx)):
        m = target[k]
        if m is not None and best[m][1] != k:
            m = None
        mapping[int(tr.id)] = m
        if m is not None:
            correct += int(np.sum(inst[g] == m))
    assigned = int(sum(g.size for g in idx))
    n_true = int(np.sum(inst >= 0))
    false_assigned = int(sum(np.sum(inst[g] < 0) for g in idx))
    return {
        "precision": correct / assigned if assigned else 1.0,
        "recall": correct / n_true if n_true else 1.0,
        "correct": correct,
        "assigned": assigned,
        "true_detections": n_true,
        "false_assigned": false_assigned,
        "tracks": len(tracks),
        "instances": int(np.unique(inst[inst >= 0]).size),
        "matched_instances": len(best),
        "mapping": mapping,
    }
