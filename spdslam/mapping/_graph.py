"""The factor graph of a sequence.

Variables: one pose T_wc per trajectory frame, key ``X(i)``, and one landmark per object,
key ``L(id)``. Factors, in this order:

- odometry: a ``PriorFactor`` on the first pose (σ ``first_pose``) and a
  ``BetweenFactor(X(i), X(i+1))`` with the relative motion T_i⁻¹ T_{i+1} of the input
  trajectory (σ per step: ``odometry_translation`` m, ``odometry_rotation`` rad): the
  trajectory is both the odometry and the initial values;
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

import jaxlie
import numpy as np

from ..factors import (
    AxisOrientationFactor,
    BetweenFactor,
    ClassicOrientationFactor,
    ClassicShapeFactor,
    EllipsoidMeasurementFactor,
    InverseBoxFactor,
    InverseCuboidBoxFactor,
    OrientationFactor,
    PriorFactor,
    RadiusFloorFactor,
    SemiInverseBoxFactor,
    SemiInverseCuboidBoxFactor,
    ShapeFactor,
    SizeFactor,
    SupportPlaneFactor,
    robust_groups,
)
from ..geometry import as_ellipsoid
from ..solver import L, NonlinearFactorGraph, X
from ._context import SequenceContext, as_context, object_shape
from ._methods import (
    DEFAULT_MAPPING_SIGMAS,
    RADIUS_FLOOR,
    ZERO_ALLOWED,
    Method,
    robust_kernel,
)

__all__ = ["build_graph", "mapping_sigmas", "measured_objects", "support_plane"]

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


def mapping_sigmas(seq, sigmas: dict | None = None) -> dict:
    """The sigmas in use: defaults, then the sequence's ``trajectory_sigma`` prior, then
    ``sigmas``; unknown names are an error."""
    s = dict(DEFAULT_MAPPING_SIGMAS)
    priors = as_context(seq).priors
    ts = None if priors is None else getattr(priors, "trajectory_sigma", None)
    if ts is not None:
        s["odometry_translation"], s["odometry_rotation"] = (float(x) for x in ts)
    unknown = sorted(set(sigmas or {}) - set(s))
    if unknown:
        raise ValueError(f"unknown sigma {', '.join(unknown)}; known: {', '.join(sorted(s))}")
    s.update({k: float(v) for k, v in (sigmas or {}).items()})
    bad = [k for k, v in s.items()
           if not (np.isfinite(v) and (v > 0 or (k in ZERO_ALLOWED and v == 0)))]
    if bad:
        raise ValueError(f"sigmas must be finite and positive: {', '.join(bad)}")
    return s


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


def _odometry(ctx: SequenceContext, s: dict) -> list:
    q = ctx.wxyz_xyz
    steps = np.asarray((jaxlie.SE3(q[:-1]).inverse() @ jaxlie.SE3(q[1:])).wxyz_xyz)  # T_i⁻¹ T_{i+1}
    out = [PriorFactor(X(0), ctx.poses[0], sigma=s["first_pose"])]
    odo = np.r_[np.full(3, s["odometry_translation"]), np.full(3, s["odometry_rotation"])]
    out += [BetweenFactor(X(i), X(i + 1), jaxlie.SE3(step), sigma=odo)
            for i, step in enumerate(steps)]
    return out


def _box_factors(ctx: SequenceContext, track, method: Method, box_model: str, s: dict,
                 robust) -> list:
    """The box factor of each of the track's detections (module docstring)."""
    key = L(track.id)
    shape = object_shape(method, ctx.priors, track.label)
    box_factor = BOX_FACTORS[box_model, shape]
    out = []
    for f, b in zip(track.frames, track.boxes):
        sigma = s[box_factor.kind]
        if box_model == "inverse":
            size = np.array([b[2] - b[0], b[3] - b[1]] * 2)
            sigma = sigma + s[box_factor.kind + "_relative"] * size
        out.append(box_factor(X(f), key, b, ctx.camera, sigma=sigma, robust=robust,
                              truncation_margin=method.margin))
    return out


def _object_factors(ctx: SequenceContext, track, landmark, method: Method, box_model: str,
                    s: dict, robust, planes=None, boxes: bool = True) -> list:
    """The box factors of the track (``boxes``) and the object's own factors."""
    key = L(track.id)
    priors = ctx.priors
    shape = object_shape(method, priors, track.label)
    out = _box_factors(ctx, track, method, box_model, s, robust) if boxes else []
    up = ctx.up
    if up is not None and method.orientation == "improved":
        if shape == "cuboid":
            out.append(AxisOrientationFactor(key, up, sigma=s["axis_orientation"]))
        else:
            out.append(OrientationFactor(key, up, sigma=s["orientation"]))
    elif up is not None and method.orientation == "classic":  # the landmark's third axis
        out.append(ClassicOrientationFactor(key, up, 2, sigma=s["classic_orientation"]))
    elif up is not None and method.orientation == "classic-nearest":
        axis = int(np.argmax(np.abs(np.asarray(landmark.orientation.as_matrix()).T @ up)))
        out.append(ClassicOrientationFactor(key, up, axis, sigma=s["classic_orientation"]))
    if method.support_plane:
        plane = (support_plane(priors, as_ellipsoid(landmark)) if planes is None
                 else planes.plane_of(track.id))
        if plane is not None:
            out.append(SupportPlaneFactor(key, plane, sigma=s["support_plane"]))
    cp = ctx.class_prior(track.label)
    if cp is not None and (method.shape or method.size):
        stated = ctx.priors is not None and track.label in ctx.priors.classes
        kernel = robust_kernel("cauchy", BUILTIN_PRIOR_CAUCHY) \
            if method.robust_builtin_priors and not stated else None
        if method.shape and method.shape_form == "classic":
            out.append(ClassicShapeFactor(key, cp.radii, sigma=s["classic_shape"], robust=kernel))
        elif method.shape:
            out.append(ShapeFactor(key, cp.radii, sigma=s["shape"], robust=kernel))
        if method.size:
            out.append(SizeFactor(key, cp.radii, sigma=s["size"], robust=kernel))
    if method.radius_floor:
        floor = RADIUS_FLOOR if cp is None else max(RADIUS_FLOOR, 0.25 * float(np.min(cp.radii)))
        out.append(RadiusFloorFactor(key, floor, sigma=s["radius_floor"]))
    return out


def _measurement_factors(ctx, measured: dict, landmarks: dict, s: dict, robust) -> list:
    sigma = np.r_[np.full(6, s["ellipsoid_shape"]), np.full(3, s["ellipsoid_center"])]
    return [
        EllipsoidMeasurementFactor(X(m.frame), L(k), (m.rotation, m.radii), m.center,
                                   sigma=sigma, robust=robust)
        for k, ms in measured.items() if k in landmarks for m in ms
    ]


def _with_robust_by_type(factors: list, method: Method) -> list:
    """The factors with ``method.robust_by_type``'s kernels on those of the chosen groups."""
    if not method.robust_by_type:
        return factors
    groups = robust_groups()
    by_kind = {}
    for group, name, k in method.robust_by_type:
        for kind in groups[group]:
            by_kind[kind] = robust_kernel(name, k)
    return [f.with_robust(by_kind[f.kind]) if f.kind in by_kind else f for f in factors]


def build_graph(seq, tracks, landmarks: dict, method: Method, box_model: str,
                sigmas: dict | None = None, measured: dict | None = None,
                planes=None) -> NonlinearFactorGraph:
    """The factor graph of a sequence (a ``Sequence`` or a ``SequenceContext``) for the
    landmarks {id: landmark value} of the tracks, with the "inverse" or "semi" box model
    (module docstring); ``measured`` the measured ellipsoids per object id (default: by
    instance id); ``planes`` the estimated ``frontend.SupportPlanes`` (each object on its
    own plane, or on none) instead of the priors' planes."""
    ctx = as_context(seq)
    s = mapping_sigmas(ctx, sigmas)
    robust = robust_kernel(method.robust, method.robust_k)
    factors = _odometry(ctx, s)
    for tr in tracks:
        if tr.id in landmarks:
            factors += _object_factors(ctx, tr, landmarks[tr.id], method, box_model, s, robust,
                                       planes)
    measured = measured_objects(ctx) if measured is None else measured
    factors += _measurement_factors(ctx, measured, landmarks, s, robust)
    return NonlinearFactorGraph(_with_robust_by_type(factors, method))
