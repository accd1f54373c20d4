"""The factor graph of a sequence.

Variables: one pose T_wc per trajectory frame, key ``X(i)``, and one landmark per object,
key ``L(id)``. Factors, in this order:

- odometry: a ``PriorFactor`` on the first pose (σ ``first_pose``), a
  ``BetweenFactor(X(i), X(i+1))`` with the relative motion T_i⁻¹ T_{i+1} of the input
  trajectory (σ per step: ``odometry_translation`` m, ``odometry_rotation`` rad) and a
  ``PriorFactor`` on every other pose at its input value (σ ``absolute_translation``,
  ``absolute_rotation``; none when both are infinite): the trajectory is the odometry, its
  global accuracy and the initial values (``_noise``; the factors are
  ``_odometry.odometry_factors``, which the online mapper and the loop closure use too);
- per object, per detection, a box factor (inverse or semi-inverse) of the object's
  silhouette model, its ellipsoid or (box-like classes, ``Method.object_shape``) its
  circumscribed cuboid; inverse boxes have σ = ``inverse_box`` + ``inverse_box_relative`` ×
  the box's width (u edges) or height (v edges); box edges within ``Method.truncation_margin``
  px of the image border carry no bound;
- per object, when the method uses them and the priors allow: orientation against ``up``
  (improved (Log P m) × m, per axis for cuboid objects; classic: the landmark's third
  axis parallel to ``up``; classic-nearest: the initial axis nearest ``up``), the support
  plane it stands on (the priors' plane nearest to it, or its estimated plane), the shape
  (sorted ratios, or classic: in the landmark's axis order) and size priors of its class, and the
  floor on its smallest radius (``Method.radius_floor``);
- per measured ellipsoid of an object: an ``EllipsoidMeasurementFactor``.

Robust kernels: ``Method.robust`` on the box and measured-ellipsoid factors, then
``Method.robust_by_type`` per factor group.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import jaxlie
import numpy as np

from ..factors import (
    AxisOrientationFactor,
    ClassicOrientationFactor,
    ClassicShapeFactor,
    EllipsoidMeasurementFactor,
    InverseBoxFactor,
    InverseCuboidBoxFactor,
    OrientationFactor,
    RadiusFloorFactor,
    SemiInverseBoxFactor,
    SemiInverseCuboidBoxFactor,
    ShapeFactor,
    SizeFactor,
    SupportPlaneFactor,
    robust_groups,
)
from ..geometry import as_ellipsoid
from ..solver import L, NonlinearFactorGraph, Values, X
from ._context import SequenceContext, as_context, object_shape
from ._methods import (
    DEFAULT_MAPPING_SIGMAS,
    INF_ALLOWED,
    RADIUS_FLOOR,
    ZERO_ALLOWED,
    Method,
    robust_kernel,
)
from ._noise import estimate_step_sigma
from ._odometry import odometry_factors

__all__ = ["OBJECT_FACTORS", "ObjectFactorRule", "ObjectInputs", "box_factors", "initial_values",
           "build_graph", "mapping_sigmas", "measured_objects", "measurement_factors",
           "object_factors", "support_plane", "trajectory_noise_note", "with_robust_by_type"]

#: Cauchy threshold (whitened units) of the shape and size factors of a built-in class
#: prior (``io.BUILTIN_CLASSES``): typical of a class, not certain for an object, and wrong
#: for a misclassified one (fr3_cabinet's cabinet is detected as a suitcase), whose boxes
#: then outweigh it. docs/sequences.md measures it against plain factors.
BUILTIN_PRIOR_CAUCHY = 1.0

#: The box factor of each (box model, silhouette model).
BOX_FACTORS = {
    ("inverse", "ellipsoid"): InverseBoxFactor,
    ("inverse", "cuboid"): InverseCuboidBoxFactor,
    ("semi", "ellipsoid"): SemiInverseBoxFactor,
    ("semi", "cuboid"): SemiInverseCuboidBoxFactor,
}


STEP_SIGMAS = ("odometry_translation", "odometry_rotation")
ABSOLUTE_SIGMAS = ("absolute_translation", "absolute_rotation")


def mapping_sigmas(seq, sigmas: dict | None = None, sources: dict | None = None) -> dict:
    """The sigmas in use: the table's (``DEFAULT_MAPPING_SIGMAS``); for the trajectory, the
    sequence's ``trajectory_sigma`` and ``trajectory_absolute_sigma`` priors, else σ_step
    estimated from the trajectory's jitter (``_noise``); then ``sigmas``. Unknown names are
    an error; the absolute sigmas may be infinite (no prior). ``sources``, when given, is
    filled with where each trajectory sigma came from."""
    s = dict(DEFAULT_MAPPING_SIGMAS)
    ctx = as_context(seq)
    src = dict.fromkeys(STEP_SIGMAS + ABSOLUTE_SIGMAS, "default")
    priors = ctx.priors
    ts = None if priors is None else getattr(priors, "trajectory_sigma", None)
    ta = None if priors is None else getattr(priors, "trajectory_absolute_sigma", None)
    if ts is not None:
        s["odometry_translation"], s["odometry_rotation"] = (float(x) for x in ts)
        src.update(dict.fromkeys(STEP_SIGMAS, "priors.yaml"))
    else:
        est = estimate_step_sigma(ctx.seq.timestamps, ctx.seq.poses_tum)
        if est is not None:
            s["odometry_translation"], s["odometry_rotation"] = est
            src.update(dict.fromkeys(STEP_SIGMAS, "estimated from the trajectory's jitter"))
    if ta is not None:
        s["absolute_translation"], s["absolute_rotation"] = (float(x) for x in ta)
        src.update(dict.fromkeys(ABSOLUTE_SIGMAS, "priors.yaml"))
    unknown = sorted(set(sigmas or {}) - set(s))
    if unknown:
        raise ValueError(f"unknown sigma {', '.join(unknown)}; known: {', '.join(sorted(s))}")
    s.update({k: float(v) for k, v in (sigmas or {}).items()})
    src.update({k: "--sigma" for k in (sigmas or {}) if k in src})
    bad = [k for k, v in s.items()
           if not ((np.isfinite(v) or (k in INF_ALLOWED and v == np.inf))
                   and (v > 0 or (k in ZERO_ALLOWED and v == 0)))]
    if bad:
        raise ValueError(f"sigmas must be finite and positive: {', '.join(bad)}")
    if sources is not None:
        sources.update(src)
    return s


def trajectory_noise_note(seq, sigmas: dict | None = None) -> str:
    """One line: the trajectory's noise model in use and where it came from."""
    src: dict = {}
    s = mapping_sigmas(seq, sigmas, src)
    step = (f"each frame step within {1e3 * s['odometry_translation']:.3g} mm and "
            f"{1e3 * s['odometry_rotation']:.3g} mrad ({src['odometry_translation']})")
    if np.isinf(s["absolute_translation"]) and np.isinf(s["absolute_rotation"]):
        pose = "no bound on each pose (a drifting odometry)"
    else:
        pose = (f"each pose within {1e3 * s['absolute_translation']:.3g} mm and "
                f"{1e3 * s['absolute_rotation']:.3g} mrad of the input ({src['absolute_translation']})")
    return f"trajectory noise: {step}; {pose}"


def measured_objects(seq) -> dict:
    """The measured ellipsoids of each object, {instance: [EllipsoidDetection]} (manual
    association: instance ids ≥ 0; measurements without one belong to no object)."""
    out: dict = {}
    for m in as_context(seq).seq.ellipsoids or ():
        if m.instance is not None and m.instance >= 0:
            out.setdefault(m.instance, []).append(m)
    return out


def support_plane(priors, e):
    """The support plane nearest to the bottom of the ellipsoid ``e`` (or None)."""
    if priors is None or not priors.support_planes:
        return None
    best, dist = None, np.inf
    for p in priors.support_planes:
        p = np.asarray(p, float) / np.linalg.norm(p[:3])
        d = abs(p[:3] @ np.asarray(e.center) + p[3]) - np.sqrt(p[:3] @ np.asarray(e.P) @ p[:3])
        if abs(d) < dist:
            best, dist = p, abs(d)
    return best


@dataclass(frozen=True)
class ObjectInputs:
    """What an object's own factors are made from: the run's context, the object's track,
    key ``L(id)`` and landmark value, the method, its silhouette model ("ellipsoid" or
    "cuboid"), the sigmas in use and the estimated support planes (None: the priors')."""

    ctx: SequenceContext
    track: Any
    key: Any
    landmark: Any
    method: Method
    shape: str
    sigmas: dict
    planes: Any = None

    @property
    def class_prior(self):
        """The ``ClassPrior`` of the object's label (priors.yaml's, else the built-in table's)."""
        return self.ctx.class_prior(self.track.label)


@dataclass(frozen=True)
class ObjectFactorRule:
    """One kind of an object's own factors in a run (``OBJECT_FACTORS``): ``uses(method)``
    says whether a method adds them, ``make(ObjectInputs)`` makes them for one object (none
    when the priors do not allow), reading the sigmas named in ``sigmas``."""

    name: str
    uses: Callable[[Method], bool]
    make: Callable[[ObjectInputs], list]
    sigmas: tuple = ()


def _orientation(o: ObjectInputs) -> list:
    """Against ``up``: improved (Log P m) × m (per axis for cuboid objects), classic (the
    landmark's third axis ∥ up) or classic-nearest (the initial axis nearest up)."""
    up, s, form = o.ctx.up, o.sigmas, o.method.orientation
    if up is None:
        return []
    if form == "improved":
        if o.shape == "cuboid":
            return [AxisOrientationFactor(o.key, up, sigma=s["axis_orientation"])]
        return [OrientationFactor(o.key, up, sigma=s["orientation"])]
    axis = 2 if form == "classic" else \
        int(np.argmax(np.abs(np.asarray(o.landmark.orientation.as_matrix()).T @ up)))
    return [ClassicOrientationFactor(o.key, up, axis, sigma=s["classic_orientation"])]


def _support_plane(o: ObjectInputs) -> list:
    """On the priors' plane nearest to the object, or on its estimated plane."""
    plane = (support_plane(o.ctx.priors, as_ellipsoid(o.landmark)) if o.planes is None
             else o.planes.plane_of(o.track.id))
    return [] if plane is None else [SupportPlaneFactor(o.key, plane, sigma=o.sigmas["support_plane"])]


def _prior_kernel(o: ObjectInputs):
    """The Cauchy kernel of a built-in class prior's factors (``BUILTIN_PRIOR_CAUCHY``), None
    for a prior priors.yaml states."""
    stated = o.ctx.priors is not None and o.track.label in o.ctx.priors.classes
    return robust_kernel("cauchy", BUILTIN_PRIOR_CAUCHY) \
        if o.method.robust_builtin_priors and not stated else None


def _shape(o: ObjectInputs) -> list:
    """The class's shape: sorted ratios, or classic (in the landmark's axis order)."""
    cp = o.class_prior
    if cp is None:
        return []
    if o.method.shape_form == "classic":
        return [ClassicShapeFactor(o.key, cp.radii, sigma=o.sigmas["classic_shape"], robust=_prior_kernel(o))]
    return [ShapeFactor(o.key, cp.radii, sigma=o.sigmas["shape"], robust=_prior_kernel(o))]


def _size(o: ObjectInputs) -> list:
    cp = o.class_prior
    return [] if cp is None else [SizeFactor(o.key, cp.radii, sigma=o.sigmas["size"], robust=_prior_kernel(o))]


def _radius_floor(o: ObjectInputs) -> list:
    """A floor on the smallest radius: a quarter of the class's smallest, at least
    ``RADIUS_FLOOR``."""
    cp = o.class_prior
    floor = RADIUS_FLOOR if cp is None else max(RADIUS_FLOOR, 0.25 * float(np.min(cp.radii)))
    return [RadiusFloorFactor(o.key, floor, sigma=o.sigmas["radius_floor"])]


#: An object's own factors, in the graph's order: a new kind reaches ``spdslam run`` through
#: its factor class and one entry here (docs/extending.md).
OBJECT_FACTORS: dict[str, ObjectFactorRule] = {r.name: r for r in (
    ObjectFactorRule("orientation", lambda m: m.orientation != "none", _orientation,
                     ("orientation", "axis_orientation", "classic_orientation")),
    ObjectFactorRule("support_plane", lambda m: m.support_plane, _support_plane, ("support_plane",)),
    ObjectFactorRule("shape", lambda m: m.shape, _shape, ("shape", "classic_shape")),
    ObjectFactorRule("size", lambda m: m.size, _size, ("size",)),
    ObjectFactorRule("radius_floor", lambda m: m.radius_floor, _radius_floor, ("radius_floor",)),
)}


#: ``box_factors`` makes up to this many boxes one by one, more as one ``FactorBatch``.
FEW_BOXES = 4


def inverse_box_sigma(boxes, s: dict, kind: str = "inverse_box") -> np.ndarray:
    """σ (n, 4) of the edges of n boxes (n, 4) under an inverse box model's noise ``kind``:
    s[kind] px plus s[kind + "_relative"] of the box's width (u edges) or height (v edges)."""
    boxes = np.asarray(boxes, dtype=float).reshape(-1, 4)
    size = np.c_[boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]][:, [0, 1, 0, 1]]
    return np.broadcast_to(np.asarray(s[kind], dtype=float), (len(boxes), 4)) + s[kind + "_relative"] * size


def box_factors(ctx: SequenceContext, track, method: Method, box_model: str, s: dict,
                 robust) -> list:
    """The box factor of each of the track's detections (module docstring)."""
    shape = object_shape(method, ctx.priors, track.label)
    box_factor = BOX_FACTORS[box_model, shape]
    boxes = np.asarray(track.boxes, dtype=float).reshape(-1, 4)
    sigma = inverse_box_sigma(boxes, s, box_factor.kind) if box_model == "inverse" \
        else np.broadcast_to(np.asarray(s[box_factor.kind], dtype=float), (len(boxes), 4))
    if len(boxes) <= FEW_BOXES:  # the online mapper's new views: plain factors are quicker to make
        return [box_factor(X(f), L(track.id), b, ctx.camera, sigma=sg, robust=robust,
                           truncation_margin=method.margin) for f, b, sg in zip(track.frames, boxes, sigma)]
    return [box_factor.many([X(f) for f in track.frames], L(track.id), boxes, ctx.camera, sigma=sigma,
                            robust=robust, truncation_margin=method.margin)]


def object_factors(ctx: SequenceContext, track, landmark, method: Method, s: dict, planes=None,
                   boxes: bool = True) -> list:
    """The box factors of the track (``boxes``; ``method.box_model``, "inverse" or "semi";
    made once per track object and settings in a context, ``SequenceContext.box_factors``)
    and the object's own factors (``OBJECT_FACTORS``)."""
    shape = object_shape(method, ctx.priors, track.label)
    out = _box_factors_once(ctx, track, method, s, shape) if boxes else []
    obj = ObjectInputs(ctx, track, L(track.id), landmark, method, shape, s, planes)
    for rule in OBJECT_FACTORS.values():
        if rule.uses(method):
            out += rule.make(obj)
    return out


def _box_factors_once(ctx: SequenceContext, track, method: Method, s: dict, shape: str) -> list:
    """``box_factors``, taken from the context's store when an earlier build made them for
    the same track object and settings (factors are immutable; a rebuild after merging two
    tracks remakes only the merged one's)."""
    robust = robust_kernel(method.robust, method.robust_k)
    memo = (id(track), method.box_model, robust, method.margin, shape, tuple(sorted(s.items())))
    try:
        hit = ctx.box_factors.get(memo)
    except TypeError:  # a setting that cannot be a key: build afresh, keep nothing
        return box_factors(ctx, track, method, method.box_model, s, robust)
    if hit is not None and hit[0] is track:
        return list(hit[1])
    out = box_factors(ctx, track, method, method.box_model, s, robust)
    ctx.box_factors[memo] = (track, tuple(out))  # the track kept alive, so that its id stays its own
    return out


def measurement_factors(ctx, measured: dict, landmarks: dict, s: dict, robust) -> list:
    sigma = np.r_[np.full(6, s["ellipsoid_shape"]), np.full(3, s["ellipsoid_center"])]
    return [
        EllipsoidMeasurementFactor(X(m.frame), L(k), (m.rotation, m.radii), m.center,
                                   sigma=sigma, robust=robust)
        for k, ms in measured.items() if k in landmarks for m in ms
    ]


def with_robust_by_type(factors: list, method: Method) -> list:
    """The factors with ``method.robust_by_type``'s kernels on those of the chosen groups."""
    if not method.robust_by_type:
        return factors
    groups = robust_groups()
    by_kind = {}
    for group, name, k in method.robust_by_type:
        for kind in groups[group]:
            by_kind[kind] = robust_kernel(name, k)
    return [f.with_robust(by_kind[f.kind]) if f.kind in by_kind else f for f in factors]


def initial_values(poses, landmarks: dict, keys=None) -> Values:
    """The ``Values`` an optimisation starts from: each of ``keys`` (default X(i) of every
    pose, then L(k) of every landmark, in order), X(i) the pose ``poses[i]`` (a
    ``jaxlie.SE3`` or its wxyz_xyz row), L(k) the landmark value ``landmarks[k]``."""
    if keys is None:
        keys = [X(i) for i in range(len(poses))] + [L(k) for k in landmarks]
    values = Values()
    for key in keys:
        if key.chr == "l":
            values[key] = landmarks[key.index]
        else:
            T = poses[key.index]
            values[key] = T if isinstance(T, jaxlie.SE3) else jaxlie.SE3(np.asarray(T))  # type: ignore[arg-type]
    return values


def build_graph(seq, tracks, landmarks: dict, method: Method, sigmas: dict | None = None,
                measured: dict | None = None, planes=None, odometry: bool = True) -> NonlinearFactorGraph:
    """The factor graph of a sequence (a ``Sequence`` or a ``SequenceContext``) for the
    landmarks {id: landmark value} of the tracks, with ``method.box_model``, "inverse" or
    "semi" (module docstring; "semi-then-inverse" is two graphs, one per stage:
    ``method.replace(box_model=stage)``); ``measured`` the measured ellipsoids per object id
    (default: by instance id); ``planes`` the estimated ``frontend.SupportPlanes`` (each
    object on its own plane, or on none) instead of the priors' planes; ``odometry=False``
    leaves out the trajectory's factors (poses held fixed by the caller). A track's box
    factors are made once per ``SequenceContext``: the builds of one run on one context
    share them."""
    if method.box_model not in ("inverse", "semi"):
        raise ValueError(f"build_graph: box model {method.box_model!r} is one graph per stage: build each "
                         "with method.replace(box_model='semi') or 'inverse'")
    ctx = as_context(seq)
    s = mapping_sigmas(ctx, sigmas)
    factors = odometry_factors(ctx.wxyz_xyz, ctx.seq.segments, s) if odometry else []
    for tr in tracks:
        if tr.id in landmarks:
            factors += object_factors(ctx, tr, landmarks[tr.id], method, s, planes)
    measured = measured_objects(ctx) if measured is None else measured
    factors += measurement_factors(ctx, measured, landmarks, s, robust_kernel(method.robust, method.robust_k))
    return NonlinearFactorGraph(with_robust_by_type(factors, method))
