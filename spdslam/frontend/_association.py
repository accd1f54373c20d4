"""Data association: grouping a sequence's detections into tracks, one per object.

Manual association (:func:`tracks_from_instances`) groups detections by their ``instance``
id. A negative instance id marks a detection known to be false (clutter, e.g. injected by
the demo generator): it belongs to no object and manual association leaves it out.

Automatic association (:func:`associate`) uses only the boxes, labels, trajectory, camera
and priors: per-frame Hungarian tracking on projected-box IoU, k-detection confirmation,
merging of duplicates by SPD log-map distance and centre distance, and batch re-assignment
of every frame against all landmarks. Their precision and recall against the instance ids
are the evaluation's (``evaluation.association_scores``).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.sparse import csr_matrix

from ..geometry import box_iou, native, spd, truncation_mask
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
# Everything below computes in NumPy: the association runs thousands of tiny geometric
# problems (one per frame, tracklet or pair of tracklets), where per-call JAX dispatch would
# dominate, and even NumPy's per-call cost does. So the work of a frame, or of all tracks, is
# done as a few array operations, with the box of a projected ellipsoid, the IoU of predicted
# boxes and the SPD distance of the coarse (upright) shapes written out for that here (the same numbers as
# ``geometry.project_box``, ``in_front``, ``box_iou`` and ``spd.distance``: checked in
# tests/test_association.py).

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

    @classmethod
    def of(cls, settings: AssociationSettings | None = None, **overrides) -> AssociationSettings:
        """``settings`` (default the defaults) with ``overrides`` of its fields: the one way
        the association's functions take their settings."""
        if settings is None:
            return cls(**overrides)
        return dataclasses.replace(settings, **overrides) if overrides else settings


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


def _segment_sums(x: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """Sums over consecutive segments (sizes (k,)) of the last axis of ``x``."""
    if sizes.size and sizes.all():
        return np.add.reduceat(x, np.cumsum(sizes) - sizes, axis=-1)
    c = np.concatenate([np.zeros(x.shape[:-1] + (1,)), np.cumsum(x, axis=-1)], axis=-1)
    return np.diff(c[..., np.concatenate([[0], np.cumsum(sizes)])], axis=-1).astype(int)


def _segment_medians(v: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The median of each of the k consecutive segments of the values ``v`` (sizes
    ``counts`` (k,)), and whether the segment has values (median 0.0 where not). The same
    numbers as ``np.median`` of each segment: the middle order statistic, or the mean
    (x + y) / 2 of the two middle ones.

    One ``np.sort`` serves all segments: for positive finite floats the bit patterns (uint64)
    order like the values, so the keys s·n_e·2⁵² + bits − e_min·2⁵² (segment s, e the
    exponent field, e_min … e_min + n_e − 1 its range) order by (segment, value) and give
    each value back exactly. Segments are taken in chunks that keep the keys below 2⁶⁴;
    values that are not positive and finite fall back to ``np.median`` per segment. With the
    compiled kernels (``geometry.native``) finite values are selected in C instead, the same
    numbers."""
    k = counts.size
    has = counts > 0
    if v.size == 0:
        return np.zeros(k), has
    ends = counts.cumsum()
    v_min, v_max = float(np.minimum.reduce(v)), float(np.maximum.reduce(v))
    lib = native.native_kernels()
    if lib is not None and math.isfinite(v_min) and math.isfinite(v_max):  # the same, by selection in C
        return native.segment_medians(lib, v, counts), has
    if not (v_min > 0 and v_max < math.inf):  # zero, negative, NaN or infinite values
        med = np.zeros(k)
        for s in np.flatnonzero(has):
            med[s] = np.median(v[ends[s] - counts[s] : ends[s]])
        return med, has
    # the exponent fields of the extremes (x = m·2^e with ½ ≤ m < 1: field e + 1022, 0 if subnormal)
    e_min, e_max = max(math.frexp(v_min)[1] + 1022, 0), math.frexp(v_max)[1] + 1022
    n_e = e_max - e_min + 1
    chunk = 4096 // n_e  # segments per sort: keys < chunk·n_e·2⁵² ≤ 2⁶⁴
    if k > chunk:
        med = np.zeros(k)
        for s0 in range(0, k, chunk):
            s1 = min(s0 + chunk, k)
            med[s0:s1] = _segment_medians(v[ends[s0] - counts[s0] : ends[s1 - 1]], counts[s0:s1])[0]
        return med, has
    # key − off[s]: the value's bits (off wraps around in uint64, and so does the sum)
    off = np.arange(k, dtype=np.uint64) * np.uint64(n_e << 52) - np.uint64(e_min << 52)
    key = np.ascontiguousarray(v, dtype=float).view(np.uint64) + off.repeat(counts)
    key.sort()
    lo, hi = ends - 1 - (counts >> 1), ends - ((counts + 1) >> 1)  # the middle ones (the same if odd)
    if np.minimum.reduce(counts) == 0:
        lo, hi = np.clip(lo, 0, v.size - 1), np.clip(hi, 0, v.size - 1)
    mid = (key[lo] - off).view(np.float64) + (key[hi] - off).view(np.float64)
    return np.where(has, mid / 2.0, 0.0), has  # odd: (x + x) / 2 = x


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
_NONE = np.zeros(0, int)  # no indices
_NONE.flags.writeable = False


@dataclass(frozen=True)
class _Fits:
    """k coarse landmarks as arrays: the fields of ``_Fit`` stacked, ``plane`` the index of
    the support plane used (−1: none), and the radii (r_h, r_v) of each (k, 2); rows that are
    not ``ok`` hold ``_BAD_FIT``'s values (radii 0)."""

    X: np.ndarray
    P: np.ndarray
    radius: np.ndarray
    info: np.ndarray
    plane: np.ndarray
    ok: np.ndarray
    radii: np.ndarray

    def one(self, i: int, planes) -> _Fit:
        """Landmark i as a ``_Fit`` (``planes``: the scene's support planes)."""
        if not self.ok[i]:
            return _BAD_FIT
        plane = None if self.plane[i] < 0 else planes[self.plane[i]]
        return _Fit(self.X[i], self.P[i], float(self.radius[i]), self.info[i], plane, True)


def _check_boxes(box: np.ndarray, frames) -> None:
    """``ValueError`` naming the first box that is not finite or not proper (x2 > x1, y2 > y1)."""
    bad = ~np.all(np.isfinite(box), axis=1) | (box[:, 2] <= box[:, 0]) | (box[:, 3] <= box[:, 1])
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(f"detection {i} (frame {frames[i]}) has an invalid box {box[i].tolist()}")


def _solve3(A: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """X (k, 3) with A X = b for k 3×3 systems (A (k, 3, 3), b (k, 3)), and which are usable:
    not singular, X finite (zeros where not)."""
    try:
        X = np.linalg.solve(A, b[..., None])[..., 0]
    except np.linalg.LinAlgError:  # one singular system: each one alone
        X = np.zeros((len(A), 3))
        for i in range(len(A)):
            try:
                X[i] = np.linalg.solve(A[i], b[i])
            except np.linalg.LinAlgError:
                X[i] = np.nan
    ok = np.asarray(np.isfinite(X).all(axis=1))
    return (X, ok) if ok.all() else (np.where(ok[:, None], X, 0.0), ok)


def _equations(S: np.ndarray, tot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normal equations (A (…, 3, 3), b (…, 3)) of the centre fit from the weighted sums S
    (…, 24) of the detections' terms and the sums of the weights tot (…,) (``_Scene``)."""
    rng = S[..., 12:] / np.maximum(tot, 1e-300)[..., None]  # the range terms, averaged
    return (S[..., :9] + rng[..., :9]).reshape(S.shape[:-1] + (3, 3)), S[..., 9:12] + rng[..., 9:]


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

    The normal equations are sums over the detections of per-detection terms (``terms``), so
    a fit needs only their sum: the tracker keeps one running sum per tracklet, and fits all
    the tracklets a frame changes at once (``fit_sums``).
    """

    # the per-detection arrays (``detection_terms``), set with setattr
    frame: np.ndarray
    box: np.ndarray
    label: np.ndarray
    w_ok: np.ndarray
    h_ok: np.ndarray
    ray: np.ndarray
    origin: np.ndarray
    radius0: np.ndarray
    terms: np.ndarray
    rec: np.ndarray
    area: np.ndarray
    recT: np.ndarray | None = None  # ``rec`` by field (batch association: fixed detections)
    up: np.ndarray | None
    planes: np.ndarray | None

    def __init__(self, seq: Sequence, s: AssociationSettings):
        dets = seq.detections
        self.setup(seq.camera, seq.priors, s)
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
        for name, value in self.detection_terms(frame, box, label).items():
            setattr(self, name, value)
        self.recT = np.ascontiguousarray(self.rec.T)  # the records by field, for the tracker
        order = np.argsort(self.frame, kind="stable")
        self.by_frame = np.split(order, np.searchsorted(self.frame[order], np.arange(1, self.F)))
        self.cache: dict = {}  # the batch re-assignment's per-label and per-landmark arrays

    @classmethod
    def empty(cls, camera, priors, s: AssociationSettings) -> "_Scene":
        """A scene without frames or detections (the online tracker's, grown frame by frame)."""
        sc = cls.__new__(cls)
        sc.setup(camera, priors, s)
        sc.labels, sc.F = [], 0
        return sc

    def setup(self, camera, priors, s: AssociationSettings) -> None:
        """The camera, priors and per-class prior radius (what every detection's terms use)."""
        self.camera, self.priors, self.settings = camera, priors, s
        self.fx, self.fy, self.cx, self.cy = (float(v) for v in (camera.fx, camera.fy, camera.cx, camera.cy))
        self.W, self.H = float(camera.width), float(camera.height)
        self.up, self.planes = (None, None) if priors is None else priors.up_and_planes()
        self._class_radius: dict = {}
        self._I3 = np.eye(3)
        self._centre4, self._focal4 = np.array([self.cx, self.cy] * 2), np.array([self.fx, self.fy] * 2)
        self._size4 = np.array([self.W, self.H] * 2)
        self._two_f = np.array([[2 * self.fx], [2 * self.fy]])
        if self.up is not None:  # P = r_h²(I − uuᵀ) + r_v² uuᵀ
            self._uu = np.outer(self.up, self.up)
            self._across = np.eye(3) - self._uu

    def class_radius(self, label: str) -> float:
        """The geometric mean of the class prior's radii (``default_radius`` without one)."""
        if label not in self._class_radius:
            cp = class_prior(self.priors, label)
            self._class_radius[label] = (self.settings.default_radius if cp is None else
                                         float(np.exp(np.mean(np.log(np.asarray(cp.radii))))))
        return self._class_radius[label]

    def detection_terms(self, frame, box, label) -> dict:
        """The per-detection arrays of detections (frame (n,), box (n, 4), label index (n,))
        whose frames' poses are in ``self.R``, ``self.C``: ray, truncation, prior range,
        the fit's normal-equation terms (class docstring) and what its radii need (``rec``)."""
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
            radius0=radius, area=w * h,
            # the centre fit's terms, side by side (n, 24): A_perp (9), b_perp (3), A_rng (9),
            # b_rng (3); a fit sums them (a matrix product, or the tracker's running sums)
            terms=np.concatenate([
                A_perp.reshape(-1, 9), np.einsum("nij,nj->ni", A_perp, origin), A_rng.reshape(-1, 9),
                (w_rng * (np.einsum("ni,ni->n", ray, origin) + range0))[:, None] * ray], axis=1),
            # the radii's inputs, one row per detection (n, 9), to gather once per fit:
            # optical axis (3), camera centre (3), box width and height (negative where
            # truncated), prior radius
            rec=np.column_stack([self.Rz[frame], origin, np.where(w_ok, w, -w), np.where(h_ok, h, -h), radius]),
        )

    # -- landmark fit and prediction --------------------------------------------------------

    def _radii(self, X, ok, R, sizes):
        """(r_h, r_v, ok) (k,) of k landmarks with centres X (k, 3) from the untruncated box
        sizes at the depths of X (the detections' median prior radius where no box side is
        whole); ``R`` (9, N) the records of their detections (``rec``, transposed), the
        first sizes[0] of landmark 0, and so on. Not ``ok`` where no detection has X in front."""
        k = len(X)
        p = R[:3] * (X.T.repeat(sizes, axis=1) - R[3:6])
        z = p[0] + p[1] + p[2]  # depths: optical axis · (X − camera centre)
        M = np.empty((3, z.size), bool)  # X in front; and the box width, height whole
        np.greater(z, _MIN_DEPTH, out=M[0])
        np.greater(R[6:8], 0.0, out=M[1:])
        M[1:] &= M[0]
        n = _segment_sums(M, sizes)
        ok = ok & (n[0] > 0)
        # the medians of w z/(2f_x) and h z/(2f_y)
        med, has = _segment_medians((R[6:8] * z / self._two_f)[M[1:]], n[1:].reshape(-1))
        r_h, r_v = med[:k], med[k:]
        has_w, has_h = has[:k], has[k:]
        if not (has_w & has_h).all():  # the other side's median; no side: the prior radii's
            none = ok & ~(has_w | has_h)
            med0 = np.zeros(k)
            if none.any():
                med0 = _segment_medians(R[8][np.repeat(none, sizes)], np.where(none, sizes, 0))[0]
            r_h, r_v = (np.where(has_w, r_h, np.where(has_h, r_v, med0)),
                        np.where(has_h, r_v, np.where(has_w, r_h, med0)))
        return r_h, r_v, ok

    def fit_sums(self, S, tot, R, sizes, full: bool = True) -> Any:
        """The coarse landmarks (class docstring) of k sets of detections at once, from the
        sums S (k, 24) of their terms (unit weights: tot (k,) the numbers of detections)
        and the records ``R`` (9, N) of their detections (``_radii``; ``sizes`` (k,)), as
        ``_Fits``; not ``full``: only (X, P, ok) (the tracker's; not as ``_BAD_FIT`` where not
        ok)."""
        k = len(S)
        if k == 0:
            return _Fits(np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0), np.zeros((0, 3, 3)),
                         np.zeros(0, int), np.zeros(0, bool), np.zeros((0, 2)))
        A, b = _equations(S, tot)
        X, ok = _solve3(A, b)
        r_h, r_v, ok = self._radii(X, ok, R, sizes)
        plane = _NONE
        if self.planes is not None:
            # the plane nearest to the bottom of the first estimate: |nᵀX + δ − r_v|
            gap = np.abs(X @ self.planes[:, :3].T + self.planes[:, 3] - r_v[:, None])
            plane = np.where(ok, np.argmin(gap, axis=1), -1)
            nrm, delta = self.planes[plane, :3], self.planes[plane, 3]
            w_pl = 1.0 / (0.25 * r_v + 0.02) ** 2
            A = A + w_pl[:, None, None] * (nrm[:, :, None] * nrm[:, None, :])
            b = b + (w_pl * (r_v - delta))[:, None] * nrm
            X, solved = _solve3(A, b)
            r_h, r_v, ok = self._radii(X, ok & solved, R, sizes)
        if self.up is None:
            P = (r_h * r_v)[:, None, None] * self._I3
        else:
            P = (r_h**2)[:, None, None] * self._across + (r_v**2)[:, None, None] * self._uu
        if not full:
            return X, P, ok
        plane = np.full(k, -1) if self.planes is None else plane
        if not ok.all():
            bad = ~ok
            P[bad], A[bad], X[bad], plane[bad] = self._I3, self._I3, 0.0, -1
        radii = np.where(ok[:, None], np.stack([r_h, r_v], axis=1), 0.0)
        return _Fits(X, P, np.sqrt(radii[:, 0] * radii[:, 1]), A, plane, ok, radii)

    def records(self, idx) -> np.ndarray:
        """The records (9, N) of detections ``idx`` (``rec``, transposed)."""
        return self.rec[idx].T if self.recT is None else self.recT.take(idx, axis=1)

    def fit(self, idx) -> _Fit:
        """The coarse landmark of detections ``idx`` (see the class docstring)."""
        idx = np.asarray(idx, dtype=int).reshape(-1)
        S = self.terms[idx].sum(axis=0)
        fits = self.fit_sums(S[None], np.array([float(idx.size)]), self.records(idx), np.array([idx.size]))
        return fits.one(0, self.planes)

    def fit_groups(self, groups) -> _Fits:
        """The coarse landmarks of each of ``groups`` (lists of detections), as arrays."""
        groups = [np.asarray(g, dtype=int).reshape(-1) for g in groups]
        sizes = np.array([g.size for g in groups], dtype=int)
        cat = np.concatenate(groups) if groups else np.zeros(0, int)
        return self.fit_sums(self.sums(cat, sizes), sizes.astype(float), self.records(cat), sizes)

    def sums(self, cat: np.ndarray, sizes: np.ndarray) -> np.ndarray:
        """The sums (k, 24) of the terms of k consecutive groups of detections ``cat``."""
        S = np.zeros((sizes.size, 24))
        if cat.size:  # (the empty groups left out of the segments)
            S[sizes > 0] = np.add.reduceat(self.terms[cat], (np.cumsum(sizes) - sizes)[sizes > 0], axis=0)
        return S

    def _window(self, window: float) -> tuple[np.ndarray, int, int, np.ndarray]:
        """The time weights g(d) = exp(−½(d/window)²) of the frame offsets d = −(F−1) … F−1
        (index d + F − 1), zero where below 10⁻³⁰; the largest offset D with a weight; the
        frames B of a block of ``local_centres`` and its Toeplitz matrix (B, B + 2D) of
        weights g(i + D − r), frame i of the block, detection row r of its window."""
        key = ("window", window)
        if key not in self.cache:

            def weights(d):
                w = d / window
                np.square(w, out=w)
                w *= -0.5
                np.exp(w, out=w)
                w[w < 1e-30] = 0.0
                return w

            d = np.arange(-(self.F - 1), self.F)
            table = weights(d)
            D = int(np.abs(d[table > 0]).max())
            # the most frames whose products (B × (B + 2D)) @ ((B + 2D) × 19) BLAS keeps to one thread
            B = max(1, int((math.sqrt((2 * D + 1) ** 2 + 4 * _BLAS_ONE_THREAD / 19) - (2 * D + 1)) / 2))
            toeplitz = weights(np.arange(B)[:, None] + D - np.arange(B + 2 * D)[None, :])
            self.cache[key] = (table, D, B, toeplitz)
        return self.cache[key]

    def local_centres(self, idx, fit: _Fit, frames, window: float) -> np.ndarray:
        """Centres (m, 3) of the landmark of ``idx`` seen at each of ``frames`` (m,): the fit
        with weights exp(−½((fᵢ − f)/window)²) + 10⁻¹² on its detections, so that each frame
        sees a landmark consistent with the nearby (equally drifted) part of the trajectory.

        The weighted sums Σᵢ wᵢ tᵢ of the detections' terms are Σᵢ gᵢ tᵢ + 10⁻¹² Σᵢ tᵢ (g the
        Gaussian), with g left out where below 10⁻³⁰ (|fᵢ − f| > D ≈ 11.7·window): each
        left-out weight is under 10⁻¹⁸ of the 10⁻¹² that every detection keeps, so the sums
        are those of the full (m, n) weights to round-off. Frames with no detection within D
        share one centre (the floor's alone). For the others, Σᵢ gᵢ tᵢ is a convolution over
        the frames: where the detections are dense, one product per block of B frames of a
        Toeplitz matrix of weights with the terms laid out by frame (a window of B + 2D
        frames, zero where no detection; B small enough for BLAS to keep the products to one
        thread, as several threads cost far more than they save on them); where sparse, a
        sparse matrix of the weights of the detections within D of each frame."""
        idx = np.asarray(idx, dtype=int).reshape(-1)
        frames = np.asarray(frames, dtype=int).reshape(-1)
        table, D, B, toeplitz = self._window(window)
        order = np.argsort(self.frame[idx], kind="stable")
        g = self.frame[idx][order]
        # the distinct terms (the matrices are symmetric) and a column of ones (the weights' sum)
        T = np.empty((idx.size, 19))
        T[:, :18], T[:, 18] = self.terms[idx[order]][:, _DISTINCT], 1.0
        lo = np.searchsorted(g, frames - D, "left")
        hi = np.searchsorted(g, frames + D, "right")
        near = np.flatnonzero(hi > lo)
        S = np.zeros((near.size + 1, 19))  # the near frames, then one far frame
        if near.size:
            q, count = frames[near], (hi - lo)[near]
            o = g[0] - D  # the first frame of block 0
            blocks, at = np.unique((q - o) // B, return_inverse=True)
            if blocks.size * B * (B + 2 * D) <= 5 * count.sum():  # dense: Toeplitz blocks
                grid = np.zeros((max((blocks[-1] + 1) * B + 2 * D, g[-1] - o + D + 1), 19))  # row f − o + D: frame f
                if np.all(g[1:] > g[:-1]):
                    grid[g - o + D] = T
                else:
                    np.add.at(grid, g - o + D, T)
                windows = np.lib.stride_tricks.as_strided(
                    grid, (blocks[-1] + 1, B + 2 * D, 19), (B * grid.strides[0],) + grid.strides, writeable=False)
                S[:-1] = (toeplitz @ windows[blocks])[at, (q - o) % B]
            else:  # sparse: the weights of the detections lo … hi − 1 of each frame
                ptr = np.concatenate([[0], np.cumsum(count)])
                det = np.arange(ptr[-1]) - np.repeat(ptr[:-1] - lo[near], count)
                w = table[np.repeat(q, count) - g[det] + (self.F - 1)]
                S[:-1] = csr_matrix((w, det, ptr), shape=(near.size, idx.size)) @ T
        S += 1e-12 * T.sum(axis=0)  # the floor: 10⁻¹² Σᵢ tᵢ and n·10⁻¹²
        A, b = _equations(S[:, _ALL], S[:, 18])
        if fit.plane is not None:
            r_v = np.sqrt(fit.P[2, 2]) if self.up is None else float(np.sqrt(self.up @ fit.P @ self.up))
            nrm, delta = fit.plane[:3], fit.plane[3]
            w_pl = 1.0 / (0.25 * r_v + 0.02) ** 2
            A = A + w_pl * np.outer(nrm, nrm)
            b = b + w_pl * (r_v - delta) * nrm
        Xs = np.linalg.solve(A, b[..., None])[..., 0]
        X = np.broadcast_to(Xs[-1], (frames.size, 3)).copy()
        X[near] = Xs[:-1]
        return X

    def project(self, X, P, frames):
        """Boxes (m, 4) of landmarks (X (m, 3), P (m, 3, 3) or (3, 3)) in ``frames`` (m,), or
        all in one frame (an int), clipped to the image (zeros where invisible), and whether
        each is visible (wholly in front, non-empty after clipping).

        In the camera frame (centre y = R_wcᵀ(X − c), shape P_c = R_wcᵀ P R_wc) the dual
        conic is K Q Kᵀ, Q = P_c − y yᵀ, so its box (``geometry.project_box``) is u = c_x +
        f_x (Q₁₃ ± √(Q₁₃² − Q₁₁Q₃₃)) / Q₃₃, v = c_y + f_y (Q₂₃ ± √(Q₂₃² − Q₂₂Q₃₃)) / Q₃₃. In
        front (``geometry.in_front``): the depth y₃ − √(P_c,₃₃) of its nearest point exceeds
        the least depth; then Q₃₃ < 0, and the + sign gives the smaller bound. Boxes are
        computed for the landmarks in front only."""
        R, c = self.R[frames], self.C[frames]
        m = len(X)
        if R.ndim == 2:  # one frame
            y, Q = (X - c) @ R, R.T @ P @ R
            Q = Q if Q.ndim == 3 else np.repeat(Q[None], m, axis=0)
            front = y[:, 2] - np.sqrt(np.maximum(Q[:, 2, 2], 0.0)) > _MIN_DEPTH
        else:  # many frames: the depth first, the rest where in front
            y, axis = np.einsum("mi,mij->mj", X - c, R), R[:, :, 2]
            depth = np.einsum("mi,ij,mj->m", axis, P, axis) if P.ndim == 2 else \
                np.einsum("mi,mij,mj->m", axis, P, axis)
            front = y[:, 2] - np.sqrt(np.maximum(depth, 0.0)) > _MIN_DEPTH
            sel = np.flatnonzero(front)
            R, y = R[sel], y[sel]
            Q = np.swapaxes(R, -1, -2) @ (P if P.ndim == 2 else P[sel]) @ R
        Q -= y[:, :, None] * y[:, None, :]
        diag, q = Q.diagonal(0, 1, 2), Q[:, :2, 2]  # (Q₁₁, Q₂₂, Q₃₃), (Q₁₃, Q₂₃)
        q33 = np.where(front if R.ndim == 2 else True, diag[:, 2], -1.0)[:, None]  # no box: not in front
        d = np.sqrt(np.maximum(q * q - diag[:, :2] * q33, 0.0))
        box = self._centre4 + self._focal4 * np.concatenate([q + d, q - d], axis=1) / q33
        box = np.minimum(np.maximum(box, 0.0), self._size4)
        ok = (box[:, 2:] > box[:, :2]).all(axis=1)
        if len(box) < m:
            box_all, ok_all = np.zeros((m, 4)), np.zeros(m, bool)
            box_all[sel], ok_all[sel] = box, ok
            box, ok = box_all, ok_all
        else:
            ok &= front
        return np.where(ok[:, None], box, 0.0), ok

    def iou(self, boxes, dets):
        """IoU (m, d) of boxes (m, 4) from ``project`` (proper, or zeros) with detections
        ``dets`` (d,): ``geometry.box_iou``, whose clipping and empty-union guard change
        nothing for such boxes (a detection's box has a positive area, so the union too)."""
        b = self.box[dets]
        w = np.minimum(boxes[:, None, 2], b[:, 2]) - np.maximum(boxes[:, None, 0], b[:, 0])
        h = np.minimum(boxes[:, None, 3], b[:, 3]) - np.maximum(boxes[:, None, 1], b[:, 1])
        inter = np.maximum(w, 0.0) * np.maximum(h, 0.0)
        area = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
        return inter / (area[:, None] + self.area[dets] - inter)


# the most multiply-adds (m·n·k) of a matrix product that OpenBLAS keeps to one thread
_BLAS_ONE_THREAD = 65536 * 4
# the 18 distinct of the 24 terms of a detection (``_Scene.detection_terms``: the 3×3 matrices are
# symmetric), and the 24 from them
_DISTINCT = np.array([0, 1, 2, 4, 5, 8, 9, 10, 11, 12, 13, 14, 16, 17, 20, 21, 22, 23])
_ALL = np.array([0, 1, 2, 1, 3, 4, 2, 4, 5, 6, 7, 8, 9, 10, 11, 10, 12, 13, 11, 13, 14, 15, 16, 17])


def _hungarian(cost, allowed):
    """Pairs (rows, cols) of the min-cost assignment among allowed entries."""
    if cost.size == 0:
        return np.zeros(0, int), np.zeros(0, int)
    r, c = linear_sum_assignment(np.where(allowed, cost, _BIG))
    keep = allowed[r, c]
    return r[keep], c[keep]


# -- stage 1: tracklets ------------------------------------------------------------------------


def _grown(a: np.ndarray, n: int) -> np.ndarray:
    """``a`` with room for at least n rows (capacity doubled), its rows kept."""
    if n <= len(a):
        return a
    out = np.zeros((max(2 * len(a), n, 64),) + a.shape[1:], a.dtype)
    out[: len(a)] = a
    return out


class _Tracking:
    """Frame-by-frame tracking state: per tracklet its detections (``members``), label, last
    frame and coarse landmark (centre X, shape P, usable or not) as arrays (the first ``n``
    rows), the running sums S of its detections' fit terms (the batch tracker's refits), and
    for the online tracker the full ``_Fit`` of each tracklet (``fits``)."""

    def __init__(self, keep_fits: bool = False):
        self.n = 0
        self._members: list = []  # per tracklet a buffer; its first size[t] entries are used
        self.size = np.zeros(0, int)
        self.label, self.last = np.zeros(0, int), np.zeros(0, int)
        self.ok = np.zeros(0, bool)
        self.X, self.P, self.S = np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 24))
        self.fits: list | None = [] if keep_fits else None

    def add(self, dets: np.ndarray, labels: np.ndarray, f: int) -> np.ndarray:
        """New tracklets, one per detection of ``dets`` seen in frame f; their indices."""
        new = np.arange(self.n, self.n + dets.size)
        for name in ("size", "label", "last", "ok", "X", "P", "S"):
            setattr(self, name, _grown(getattr(self, name), self.n + dets.size))
        self.size[new], self.label[new], self.last[new], self.ok[new] = 1, labels, f, False
        for d in dets.tolist():
            buf = np.zeros(8, int)
            buf[0] = d
            self._members.append(buf)
        if self.fits is not None:
            self.fits.extend([_BAD_FIT] * dets.size)
        self.n += dets.size
        return new

    def append(self, t: int, d: int) -> None:
        """Detection d joins tracklet t (its buffer doubled when full)."""
        buf, k = self._members[t], self.size[t]
        if k == buf.size:
            buf = self._members[t] = np.concatenate([buf, np.zeros(buf.size, int)])
        buf[k] = d
        self.size[t] = k + 1

    def members(self, t: int) -> np.ndarray:
        """Tracklet t's detections, in the order they joined (a view)."""
        return self._members[t][: self.size[t]]

    def set_members(self, t: int, dets) -> None:
        self._members[t] = np.array(dets, dtype=int).reshape(-1)
        self.size[t] = self._members[t].size

    def set_fit(self, t: int, fit: _Fit) -> None:
        self.X[t], self.P[t], self.ok[t] = fit.X, fit.P, fit.ok
        if self.fits is not None:
            self.fits[t] = fit

    def refit(self, sc: _Scene, ts: np.ndarray) -> None:
        """New landmarks of tracklets ``ts`` from all their detections (running sums S)."""
        sizes = self.size[ts]
        cat = np.concatenate([self._members[t][:k] for t, k in zip(ts.tolist(), sizes.tolist())])
        self.X[ts], self.P[ts], self.ok[ts] = sc.fit_sums(
            self.S[ts], sizes.astype(float), sc.records(cat), sizes, full=False)


def _track_frame(sc: _Scene, s: AssociationSettings, st: _Tracking, f: int, dets: np.ndarray,
                 refit=None, always=(), candidates=None) -> np.ndarray:
    """Frame f of the tracking (``_tracklets``): its detections ``dets`` (indices into
    ``sc``) assigned to the tracklets of ``st`` seen in the last ``max_gap`` frames, or
    new ones; ``st`` is updated in place. ``refit(t)``: tracklet t's new fit (the online
    tracker); by default the tracklets assigned or started in the frame are refitted to all
    their detections together, from their running sums. Tracklets in ``always`` are
    candidates however long unseen; ``candidates``: the tracklets to consider, default all.
    Returns the tracklet of each detection."""
    if candidates is None and not always:
        act = np.flatnonzero(st.ok[: st.n] & (st.last[: st.n] >= f - s.max_gap))
    else:
        act = np.array([t for t in (range(st.n) if candidates is None else candidates)
                        if st.ok[t] and (f - st.last[t] <= s.max_gap or t in always)], dtype=int)
    ts = ds = _NONE
    owner = np.full(dets.size, -1)
    if act.size:
        boxes, _ = sc.project(st.X[act], st.P[act], f)
        iou = sc.iou(boxes, dets)
        # IoU ≥ iou_gate > 0: the landmark is visible (invisible ones have empty boxes)
        allowed = (iou >= s.iou_gate) & (st.label[act][:, None] == sc.label[dets])
        if allowed.any():
            rows, cols = _hungarian(1.0 - iou, allowed)
            ts, ds = act[rows], dets[cols]
            owner[cols] = ts
            st.last[ts] = f
            for t, d in zip(ts.tolist(), ds.tolist()):
                st.append(t, d)
    fresh = owner < 0
    new = st.add(dets[fresh], sc.label[dets[fresh]], f) if fresh.any() else ts[:0]
    owner[fresh] = new
    if refit is None:
        st.S[ts] += sc.terms[ds]
        if new.size:
            st.S[new] = sc.terms[dets[fresh]]
            ts = np.concatenate([ts, new])
        st.refit(sc, ts)
    else:
        for t in ts.tolist():
            st.set_fit(t, refit(t))
        for t in new.tolist():
            st.set_fit(t, sc.fit(st.members(t)))
    return owner


def _tracklets(sc: _Scene, s: AssociationSettings, dets_mask=None) -> list:
    """Frame-by-frame tracking: Hungarian on 1 − IoU(predicted box, detection) between the
    tracklets seen in the last ``max_gap`` frames and the frame's detections (same label,
    IoU ≥ ``iou_gate``); a detection that passes no gate starts a new tracklet. Only the
    detections where ``dets_mask`` is True take part (all by default)."""
    st = _Tracking()
    frames = range(sc.F) if dets_mask is None else np.unique(sc.frame[dets_mask]).tolist()
    for f in frames:
        dets = sc.by_frame[f]
        if dets_mask is not None:
            dets = dets[dets_mask[dets]]
        if dets.size:
            _track_frame(sc, s, st, f, dets)
    return [st.members(t).copy() for t in range(st.n)]


# -- stage 2: merging --------------------------------------------------------------------------


def _merge_cost(sc: _Scene, s: AssociationSettings, ga, fa: _Fit, cov_a, gb, fb: _Fit, cov_b):
    """The cost of merging tracks a and b (detections ``ga``, ``gb``; fits and centre
    covariances), or None where a gate forbids it (``_merge``; one pair)."""
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


def _shape_distance(sc: _Scene, ra: np.ndarray, rb: np.ndarray) -> np.ndarray:
    """d_P = ‖Log(P_a^-½ P_b P_a^-½)‖_F (``geometry.spd.distance``) of coarse landmark shapes
    with radii ra, rb (p, 2) (r_h, r_v): upright shapes share their axes, so the eigenvalues
    are (r_h,b/r_h,a)² twice and (r_v,b/r_v,a)², and d_P = 2·√(2 ln²(r_h,b/r_h,a) +
    ln²(r_v,b/r_v,a)); without an up direction, spheres r_h r_v I: d_P = √3 |ln(ρ_b/ρ_a)|."""
    if sc.up is None:
        return np.sqrt(3.0) * np.abs(np.log((rb[:, 0] * rb[:, 1]) / (ra[:, 0] * ra[:, 1])))
    lh, lv = np.log(rb[:, 0] / ra[:, 0]), np.log(rb[:, 1] / ra[:, 1])
    return 2.0 * np.sqrt(2.0 * lh * lh + lv * lv)


def _merge_costs(sc: _Scene, s: AssociationSettings, X, radii, radius, cov, a: np.ndarray, b: np.ndarray):
    """``_merge_cost`` of the pairs (a[i], b[i]) of tracks (centres X, radii (r_h, r_v), mean
    radii, centre covariances) that passed its label, fit and frame gates: (kept (p,),
    costs) for those that pass the shape and centre gates too."""
    keep = np.zeros(a.size, bool)
    if not a.size:
        return keep, np.zeros(0)
    d_spd = _shape_distance(sc, radii[a], radii[b])
    i = np.flatnonzero(~(d_spd > s.spd_gate))
    ai, bi = a[i], b[i]
    tau = s.centre_tolerance * (radius[ai] + radius[bi])
    delta = X[ai] - X[bi]
    M = cov[ai] + cov[bi] + (tau**2)[:, None, None] * np.eye(3)
    d_x = np.sqrt(np.einsum("ni,ni->n", delta, np.linalg.solve(M, delta[..., None])[..., 0]))
    j = ~(d_x > s.centre_gate)
    keep[i[j]] = True
    return keep, d_x[j] / s.centre_gate + d_spd[i[j]] / s.spd_gate


def _merge(sc: _Scene, groups: list, s: AssociationSettings) -> tuple[list, int]:
    """Agglomerative merging of tracks (duplicates: re-entries after a gap, split tracks).

    Two tracks a, b may merge when they have the same label, share no frame, their shapes
    are within ``spd_gate`` in the affine-invariant log-map distance
    d_P = ‖Log(P_a^-½ P_b P_a^-½)‖_F, and their centres within ``centre_gate`` in the
    Mahalanobis distance d_X² = δᵀ(A_a⁻¹ + A_b⁻¹ + τ²I)⁻¹δ, δ = X_a − X_b, A the fits'
    information matrices, τ = ``centre_tolerance``·(r̄_a + r̄_b) (model error and drift).
    Cost d_X/centre_gate + d_P/spd_gate; the cheapest pair merges first (the earliest
    found among equal costs), then the merged track's costs are computed. The pairs and
    their costs are arrays and each track's frames a bit set; a merged track's term sums
    are those of its two (``_Scene.sums``), and d_P of these upright shapes has a closed
    form (``_shape_distance``). Returns (groups, number of merges)."""
    groups = [np.sort(np.asarray(g, dtype=int)) for g in groups]
    N = len(groups)
    cap = max(2 * N - 1, 1)  # every merge adds one track and ends two
    sizes = np.array([g.size for g in groups], dtype=int)
    cat = np.concatenate(groups) if N else np.zeros(0, int)
    S = _grown(sc.sums(cat, sizes), cap)  # the sums of the terms of each track
    fits = sc.fit_sums(S[:N], sizes.astype(float), sc.records(cat), sizes)
    X, radii, radius, ok = (_grown(a, cap) for a in (fits.X, fits.radii, fits.radius, fits.ok))
    cov = np.zeros((cap, 3, 3))
    cov[:N][fits.ok] = np.linalg.inv(fits.info[fits.ok])
    label = np.full(cap, -1)
    label[:N] = [sc.label[g[0]] if g.size else -1 for g in groups]
    # the frames of each track as a bit set: 64 frames per word
    bits = np.zeros((cap, -(-sc.F // 64)), np.uint64)
    fr = sc.frame[cat].astype(np.uint64)
    np.bitwise_or.at(bits, (np.repeat(np.arange(N), sizes), fr >> np.uint64(6)), np.uint64(1) << (fr & np.uint64(63)))
    alive = np.zeros(cap, bool)
    alive[:N] = True
    # the pairs (a < b) past the label, fit and frame gates, in the order a, then b
    first, second = [np.zeros(0, int)], [np.zeros(0, int)]
    for lab in np.unique(label[:N][ok[:N]]):
        ids = np.flatnonzero(ok[:N] & (label[:N] == lab))
        ia, ib = np.nonzero(np.triu(~(bits[ids, None] & bits[None, ids]).any(axis=2), 1))
        first.append(ids[ia])
        second.append(ids[ib])
    pa, pb = np.concatenate(first), np.concatenate(second)
    order = np.lexsort((pb, pa))
    pa, pb = pa[order], pb[order]
    kept, pc = _merge_costs(sc, s, X, radii, radius, cov, pa, pb)
    pa, pb = pa[kept], pb[kept]
    merges = 0
    while pc.size:
        i = int(np.argmin(pc))  # the first of the cheapest
        a, b = int(pa[i]), int(pb[i])
        new = len(groups)
        groups.append(np.sort(np.concatenate([groups[a], groups[b]])))
        S[new] = S[a] + S[b]
        size = np.array([groups[-1].size])
        fit = sc.fit_sums(S[new : new + 1], size.astype(float), sc.records(groups[-1]), size)
        X[new], radii[new], radius[new], ok[new] = fit.X[0], fit.radii[0], fit.radius[0], fit.ok[0]
        label[new] = label[a]
        if ok[new]:
            cov[new] = np.linalg.inv(fit.info[0])
        bits[new] = bits[a] | bits[b]
        alive[a] = alive[b] = False
        alive[new] = True
        merges += 1
        keep = (pa != a) & (pa != b) & (pb != a) & (pb != b)
        pa, pb, pc = pa[keep], pb[keep], pc[keep]
        if ok[new]:
            o = np.flatnonzero(alive[:new] & ok[:new] & (label[:new] == label[new]))
            o = o[~(bits[o] & bits[new]).any(axis=1)]
            kept, c = _merge_costs(sc, s, X, radii, radius, cov, o, np.full(o.size, new))
            pa, pb = np.concatenate([pa, o[kept]]), np.concatenate([pb, np.full(c.size, new)])
            pc = np.concatenate([pc, c])
    return [g for g, al in zip(groups, alive) if al], merges


# -- stage 3: batch re-assignment --------------------------------------------------------------


def _reassign(sc: _Scene, groups: list, s: AssociationSettings) -> list:
    """Every frame's detections against every landmark: Hungarian on 1 − IoU(projected
    box clipped to the image, detection), same label, IoU ≥ ``iou_gate``. The landmark seen
    from frame f is its time-local fit (``_Scene.local_centres``, σ = ``window`` frames), so
    that odometry drift between distant parts of the sequence does not break the boxes.
    A landmark's IoU with its label's detections depends on its detections only: kept in
    ``sc`` for the next rounds. Frames where every detection and every landmark has at most
    one allowed pairing keep those pairs (what the Hungarian would choose) without it.
    Returns the new groups (possibly empty or short: the caller filters them)."""
    fits = sc.fit_groups(groups)
    keep = np.flatnonzero(fits.ok)
    n = sc.frame.size
    if not keep.size or n == 0:
        return []
    L = keep.size
    labs = np.array([sc.label[groups[i][0]] for i in keep])
    rows, cols, vals = [np.zeros(0, int)], [np.zeros(0, int)], [np.zeros(0)]  # the allowed pairs
    for j, i in enumerate(keep.tolist()):
        g = np.asarray(groups[i], dtype=int)
        if ("label", labs[j]) not in sc.cache:
            di = np.flatnonzero(sc.label == labs[j])
            sc.cache["label", labs[j]] = (di,) + tuple(np.unique(sc.frame[di], return_inverse=True))
        di, frames, inv = sc.cache["label", labs[j]]
        key = ("iou", s.window, g.tobytes())
        if key not in sc.cache:  # the IoU with each detection of the label
            X = sc.local_centres(g, fits.one(i, sc.planes), frames, s.window)
            boxes, vis = sc.project(X, fits.P[i], frames)
            sc.cache[key] = np.where(vis[inv], box_iou(boxes[inv], sc.box[di]), 0.0)
        iou = sc.cache[key]
        hit = np.flatnonzero(iou >= s.iou_gate)
        rows.append(di[hit])
        cols.append(np.full(hit.size, j))
        vals.append(iou[hit])
    r, c, v = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
    owner = np.full(n, -1)
    _, pair, twice = np.unique(sc.frame[r] * L + c, return_inverse=True, return_counts=True)  # (frame, landmark)
    clash = (np.bincount(r, minlength=n)[r] > 1) | (twice[pair] > 1)
    hard = np.isin(sc.frame[r], sc.frame[r[clash]])
    owner[r[~hard]] = c[~hard]
    if hard.any():  # per frame, on the IoU of its detections (rows) with every landmark
        if "row" not in sc.cache:
            sc.cache["row"] = np.zeros(n, int)
            for dets in sc.by_frame:
                sc.cache["row"][dets] = np.arange(dets.size)
        at = np.flatnonzero(hard)
        at = at[np.argsort(sc.frame[r[at]], kind="stable")]
        cuts = np.flatnonzero(np.diff(sc.frame[r[at]])) + 1
        for sel in np.split(at, cuts):
            dets = sc.by_frame[sc.frame[r[sel[0]]]]
            iou_f, allowed = np.zeros((dets.size, L)), np.zeros((dets.size, L), bool)
            iou_f[sc.cache["row"][r[sel]], c[sel]] = v[sel]
            allowed[sc.cache["row"][r[sel]], c[sel]] = True
            rr, cc = _hungarian(1.0 - iou_f, allowed)
            owner[dets[rr]] = cc
    order = np.argsort(owner, kind="stable")  # each landmark's detections, ascending
    counts = np.bincount(owner + 1, minlength=L + 1)
    return np.split(order[counts[0]:], np.cumsum(counts[1:-1]))


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
    s = AssociationSettings.of(settings, **overrides)
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
    groups = [g[np.argsort(sc.frame[g], kind="stable")] for g in groups]
    assignment = np.full(sc.frame.size, -1)
    tracks = []
    for k, g in enumerate(groups):
        assignment[g] = k
        tracks.append(Track(k, sc.labels[sc.label[g[0]]], sc.frame[g].copy(), sc.box[g].copy()))
    fits = sc.fit_groups(groups)
    stats.update(
        merges=merges,
        rounds=rounds,
        tracks=len(tracks),
        assigned=int((assignment >= 0).sum()),
        detections=int(sc.frame.size),
        seconds=time.perf_counter() - t0,
    )
    return Association(tracks, assignment, fits.X, fits.P, stats)


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
        s = AssociationSettings.of(settings, **overrides)
        self.settings, self.fit_window = s, int(fit_window)
        self._sc = _Scene.empty(camera, priors, s)
        self._lab: dict = {}
        self._dets, self._frames = _Grow(), _Grow()
        self._state = _Tracking(keep_fits=True)
        self._mapped: dict = {}
        self._alive: set = set()  # tracks seen in the last max_gap frames

    def _sync(self) -> None:
        sc = self._sc
        for name in ("frame", "box", "label", "w_ok", "h_ok", "ray", "origin", "radius0",
                     "terms", "rec", "area"):
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
        self._dets.add(**sc.detection_terms(np.full(len(boxes), f), boxes, idx))
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
        return self._sc.fit(self._state.members(t)[-self.fit_window:])

    def set_landmark(self, t: int, centre, P) -> None:
        """Predict track t's boxes from the ellipsoid (centre, P) from now on."""
        st = self._state
        assert st.fits is not None
        fit = st.fits[t]
        self._mapped[t] = _Fit(np.asarray(centre, float), np.asarray(P, float), fit.radius,
                               fit.info, fit.plane, True)
        st.set_fit(t, self._mapped[t])

    def merge(self, keep: int, drop: int) -> None:
        """Track ``drop``'s detections join ``keep``; ``drop`` is no longer continued."""
        st = self._state
        st.set_members(keep, np.sort(np.concatenate([st.members(keep), st.members(drop)])))
        st.last[keep] = max(st.last[keep], st.last[drop])
        st.set_members(drop, [])
        st.set_fit(drop, _BAD_FIT)
        self._mapped.pop(drop, None)
        if keep not in self._mapped:
            st.set_fit(keep, self._refit(keep))

    def match(self, t: int, candidates) -> int | None:
        """The track among ``candidates`` that track t is a re-entry of (the batch merging's
        gates and cost on the coarse fits of both, ``_merge``), or None."""
        st, sc = self._state, self._sc
        ga = st.members(t)[-self.fit_window:]
        if not ga.size:
            return None
        fa = sc.fit(ga)
        if not fa.ok:
            return None
        cov_a = np.linalg.inv(fa.info)
        best, best_cost = None, np.inf
        for c in candidates:
            gb = st.members(c)[-self.fit_window:]
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
        return self._state.n

    def track(self, t: int) -> tuple[np.ndarray, np.ndarray, str]:
        """(frames, boxes, label) of track t, in frame order."""
        g = self._state.members(t)
        frames = self._dets.view("frame")[g] if g.size else np.zeros(0, int)
        boxes = self._dets.view("box")[g] if g.size else np.zeros((0, 4))
        return frames, boxes, self._sc.labels[self._state.label[t]]

    def size(self, t: int) -> int:
        """The number of detections of track t."""
        return int(self._state.size[t])


def associate(seq: Sequence, settings: AssociationSettings | None = None, **overrides) -> list:
    """Automatic data association: the tracks (see :func:`associate_detailed`)."""
    return associate_detailed(seq, settings, **overrides).tracks


def merge_tracks(tracks, seq: Sequence, settings: AssociationSettings | None = None, **overrides) -> list:
    """Merge duplicate tracks of the same object (the merging step of :func:`associate`):
    same label, no shared frame, log-map shape distance, centre distance and joint
    reprojection within the gates of ``settings``. Returns new tracks numbered by first
    frame; each track's boxes must be detections of ``seq``."""
    s = AssociationSettings.of(settings, **overrides)
    sc = _Scene(seq, s)
    groups, _ = _merge(sc, seq.detection_indices(tracks), s)
    groups = [g[np.argsort(sc.frame[g], kind="stable")] for g in groups if g.size]
    groups.sort(key=lambda g: (sc.frame[g[0]], g[0]))
    return [Track(k, sc.labels[sc.label[g[0]]], sc.frame[g].copy(), sc.box[g].copy())
            for k, g in enumerate(groups)]
