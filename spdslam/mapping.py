"""Object SLAM on a sequence: initialise every object, then optimise camera poses and objects
jointly (the paper's Table III pipeline).

Variables: one pose T_wc per trajectory frame, key ``("pose", i)``, and one landmark per
object (detections grouped by their ``instance`` id), key ``("object", id)``.

Factors:

- odometry: ``BetweenFactor(i, i+1)`` with the relative motion T_i⁻¹ T_{i+1} of the input
  trajectory (σ per step: ``odometry_translation`` m, ``odometry_rotation`` rad), and a
  ``PriorFactor`` on the first pose (σ ``first_pose``): the trajectory is both the odometry
  and the initial values;
- per detection: a box factor (inverse, semi-inverse, or semi-inverse to convergence then
  inverse from there);
- per object, when the method uses them and the priors allow: orientation against ``up``
  (improved (Log P m) × m, or classic: the initial axis nearest ``up`` kept parallel to it),
  support plane (the plane the initial object stands nearest to), and shape and size priors
  of its class.

Methods (:data:`METHODS`) mirror Table III: ``quadric-slam`` (Quadric-SVD initialisation,
inverse boxes, Rot-Trans-Scale), ``multi-rts`` (multi-constraint initialisation, every
constraint in its classic form, RTS) and ``multi-spd`` (the paper's: SPD(3), improved
orientation, sorted shape prior; inverse boxes, because semi-inverse-then-inverse ended in
worse local minima on the demo rooms, see docs/sequences.md). Each field of a method can be
overridden.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import jax
import jaxlie
import numpy as np

from .association import Track, tracks_from_instances
from .camera import in_front
from .ellipsoid import Ellipsoid, EllipsoidFull, EllipsoidRTS, as_ellipsoid
from .factors import (
    DEFAULT_SIGMAS,
    BetweenFactor,
    Cauchy,
    ClassicOrientationFactor,
    Huber,
    InverseBoxFactor,
    OrientationFactor,
    PriorFactor,
    SemiInverseBoxFactor,
    ShapeFactor,
    SizeFactor,
    SupportPlaneFactor,
)
from .initialization import InitializationError, multi_initialize, svd_initialize
from .se3 import from_tum, to_tum
from .sequence import Sequence
from .solver import LevenbergMarquardt, NonlinearFactorGraph, Values

__all__ = [
    "DEFAULT_MAPPING_SIGMAS",
    "METHODS",
    "MapObject",
    "MapResult",
    "Method",
    "Track",
    "build_graph",
    "initialize_objects",
    "mapping_sigmas",
    "object_key",
    "pose_key",
    "run_sequence",
    "tracks_from_instances",
    "trajectory_poses",
]

PARAMETERIZATIONS = ("spd", "rts", "full")
BOX_MODELS = ("inverse", "semi", "semi-then-inverse")
INITIALIZATIONS = ("svd", "multi")
ORIENTATIONS = ("improved", "classic", "none")
ROBUST_KERNELS = ("none", "huber", "cauchy")

#: Default standard deviations: the factor defaults plus odometry and the first-pose prior.
DEFAULT_MAPPING_SIGMAS = {
    **DEFAULT_SIGMAS,
    # A detector's box error grows with the box (and so does the misfit of an ellipsoid to
    # a box-shaped object): per edge σ = inverse_box + inverse_box_relative · box size.
    "inverse_box": 2.0,  # px
    "inverse_box_relative": 0.05,  # of the box width (u edges) or height (v edges)
    # Scene knowledge is held nearly hard: upright objects standing on their plane.
    "orientation": 0.005,  # per component of (Log P m) × m
    "classic_orientation": 0.005,  # per component of ±n × m (≈ rad)
    "support_plane": 0.001,  # m²
    # Accuracy of the input trajectory (visual-odometry keyframes) unless the sequence's
    # priors.yaml states its own (``trajectory_sigma``).
    "odometry_translation": 0.005,  # m per frame step
    "odometry_rotation": 0.003,  # rad per frame step
    "first_pose": 1e-4,  # m and rad
}


@dataclass(frozen=True)
class Method:
    """One back end: parameterisation, initialisation, box model and which constraints."""

    name: str
    parameterization: str = "spd"
    initialization: str = "multi"
    box_model: str = "inverse"
    orientation: str = "improved"
    support_plane: bool = True
    shape: bool = True
    size: bool = True
    robust: str = "none"
    robust_k: float = 1.0

    def __post_init__(self):
        for name, allowed in (
            ("parameterization", PARAMETERIZATIONS),
            ("initialization", INITIALIZATIONS),
            ("box_model", BOX_MODELS),
            ("orientation", ORIENTATIONS),
            ("robust", ROBUST_KERNELS),
        ):
            if getattr(self, name) not in allowed:
                raise ValueError(
                    f"{name} must be one of {', '.join(allowed)}, got {getattr(self, name)!r}"
                )
        if self.orientation == "classic" and self.parameterization != "rts":
            raise ValueError("the classic orientation constraint needs the rts parameterization")
        if not self.robust_k > 0:
            raise ValueError(f"robust_k must be > 0, got {self.robust_k}")

    def replace(self, **overrides) -> Method:
        return dataclasses.replace(self, **{k: v for k, v in overrides.items() if v is not None})


METHODS = {
    "quadric-slam": Method(
        "quadric-slam", "rts", "svd", "inverse", "none", False, False, False
    ),
    "multi-rts": Method("multi-rts", "rts", "multi", "inverse", "classic", True, True, True),
    "multi-spd": Method("multi-spd", "spd", "multi", "inverse", "improved", True, True, True),
}


def pose_key(i: int):
    return ("pose", int(i))


def object_key(i: int):
    return ("object", int(i))


@dataclass(frozen=True)
class MapObject:
    """An object of the map: id, label and ellipsoid (P, t)."""

    id: int
    label: str
    ellipsoid: Ellipsoid

    def as_dict(self) -> dict:
        R, s = (np.asarray(a) for a in self.ellipsoid.axes())
        return {
            "id": int(self.id),
            "label": self.label,
            "center": np.asarray(self.ellipsoid.center).tolist(),
            "rotation": R.tolist(),
            "radii": s.tolist(),
            "P": np.asarray(self.ellipsoid.P).tolist(),
        }


@dataclass
class MapResult:
    """The output of :func:`run_sequence`: front-end (initial) and optimised objects, the
    optimised poses (TUM rows with timestamps), solver figures, and objects left out."""

    method: Method
    objects: list
    initial_objects: list
    poses_tum: np.ndarray
    iterations: int
    initial_cost: float
    final_cost: float
    converged: bool
    reason: str
    failed: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)

    def as_dict(self) -> dict:
        return {
            "method": self.method.name,
            "parameterization": self.method.parameterization,
            "iterations": int(self.iterations),
            "final_cost": float(self.final_cost),
            "initial_cost": float(self.initial_cost),
            "converged": bool(self.converged),
            "reason": self.reason,
            "settings": dataclasses.asdict(self.method),
            "objects": [o.as_dict() for o in self.objects],
            "failed": {str(k): v for k, v in self.failed.items()},
            "notes": list(self.notes),
        }


def _support_plane(priors, e: Ellipsoid):
    """The support plane nearest to the bottom of the initial ellipsoid (or None)."""
    if priors is None or not priors.support_planes:
        return None
    best, dist = None, np.inf
    for p in priors.support_planes:
        p = np.asarray(p, float) / np.linalg.norm(p[:3])
        d = abs(p[:3] @ np.asarray(e.center) + p[3]) - np.sqrt(p[:3] @ np.asarray(e.P) @ p[:3])
        if abs(d) < dist:
            best, dist = p, abs(d)
    return best


def _up(priors):
    """The up direction: ``priors.up``, else the first support plane's normal, else None."""
    if priors is None:
        return None
    if priors.up is not None:
        return np.asarray(priors.up)
    return np.asarray(priors.support_planes[0][:3]) if priors.support_planes else None


def trajectory_poses(seq: Sequence) -> list:
    """The trajectory as one ``jaxlie.SE3`` per frame (one batched conversion, then views)."""
    rows = np.asarray(from_tum(np.asarray(seq.poses_tum)).wxyz_xyz)
    return [jaxlie.SE3(r) for r in rows]


def _class_prior(priors, label):
    if priors is None:
        return None
    return priors.classes.get(label)


def initialize_objects(seq: Sequence, tracks, method: Method, min_views: int = 3, poses=None):
    """Front end: (initial ellipsoids {id: Ellipsoid}, failures {id: reason}, notes).

    Views where the initial ellipsoid is not wholly in front of the camera are dropped from
    that object's factors (reported in the notes); an object left with fewer than
    ``min_views`` views is a failure.
    """
    priors = seq.priors
    up = _up(priors)
    init, failed, notes = {}, {}, []
    use_multi = method.initialization == "multi"
    if use_multi and up is None:
        notes.append("no up direction or support plane in the priors: Quadric-SVD initialisation")
        use_multi = False
    poses = trajectory_poses(seq) if poses is None else poses
    for tr in tracks:
        Ts = [poses[i] for i in tr.frames]
        if len(tr.frames) < min_views:
            failed[tr.id] = f"{len(tr.frames)} views, needs at least {min_views}"
            continue
        try:
            if use_multi:
                plane = None
                if priors is not None and priors.support_planes:
                    plane = priors.support_planes[0]
                    if len(priors.support_planes) > 1:
                        plane = _support_plane(priors, svd_initialize(tr.boxes, Ts, seq.camera))
                cp = _class_prior(priors, tr.label)
                e = multi_initialize(
                    tr.boxes, Ts, seq.camera, up, plane,
                    None if cp is None else cp.radii, 0.2 if cp is None else max(cp.sigma, 0.05),
                )
            else:
                e = svd_initialize(tr.boxes, Ts, seq.camera)
        except InitializationError as err:
            failed[tr.id] = str(err)
            continue
        init[tr.id] = e
    return init, failed, notes


def _landmark(e: Ellipsoid, method: Method):
    if method.parameterization == "spd":
        return e
    if method.parameterization == "full":
        return EllipsoidFull.from_ellipsoid(e)
    R, s = (np.asarray(a) for a in e.axes())
    return EllipsoidRTS.from_axes(R, np.asarray(e.center), s)


def _robust(method: Method):
    if method.robust == "huber":
        return Huber(method.robust_k)
    if method.robust == "cauchy":
        return Cauchy(method.robust_k)
    return None


def build_graph(seq: Sequence, tracks, landmarks: dict, method: Method, box_model: str,
                sigmas: dict | None = None):
    """The factor graph of a sequence for the given landmarks {id: landmark value}."""
    s = mapping_sigmas(seq, sigmas)
    batched = from_tum(np.asarray(seq.poses_tum))
    q = batched.wxyz_xyz
    steps = np.asarray((jaxlie.SE3(q[:-1]).inverse() @ jaxlie.SE3(q[1:])).wxyz_xyz)  # T_i⁻¹ T_{i+1}
    graph = NonlinearFactorGraph()
    first = jaxlie.SE3(np.asarray(batched.wxyz_xyz[0]))
    graph.add(PriorFactor(pose_key(0), first, sigma=s["first_pose"]))
    odo = np.r_[np.full(3, s["odometry_translation"]), np.full(3, s["odometry_rotation"])]
    for i, step in enumerate(steps):
        graph.add(BetweenFactor(pose_key(i), pose_key(i + 1), jaxlie.SE3(step), sigma=odo))
    robust = _robust(method)
    box_factor = InverseBoxFactor if box_model == "inverse" else SemiInverseBoxFactor
    priors = seq.priors
    up = _up(priors)
    for tr in tracks:
        if tr.id not in landmarks:
            continue
        key = object_key(tr.id)
        lm = landmarks[tr.id]
        for f, b in zip(tr.frames, tr.boxes):
            if box_model == "inverse":
                size = np.array([b[2] - b[0], b[3] - b[1]] * 2)
                box_sigma = s["inverse_box"] + s["inverse_box_relative"] * size
            else:
                box_sigma = s["semi_inverse_box"]
            graph.add(box_factor(pose_key(f), key, b, seq.camera, sigma=box_sigma, robust=robust))
        if up is not None and method.orientation == "improved":
            graph.add(OrientationFactor(key, up, sigma=s["orientation"]))
        elif up is not None and method.orientation == "classic":
            R = np.asarray(lm.rotation.as_matrix())
            axis = int(np.argmax(np.abs(R.T @ np.asarray(up))))
            graph.add(ClassicOrientationFactor(key, up, axis, sigma=s["classic_orientation"]))
        if method.support_plane:
            plane = _support_plane(priors, as_ellipsoid(lm))
            if plane is not None:
                graph.add(SupportPlaneFactor(key, plane, sigma=s["support_plane"]))
        cp = _class_prior(priors, tr.label)
        if cp is not None and method.shape:
            graph.add(ShapeFactor(key, cp.radii, sigma=s["shape"]))
        if cp is not None and method.size:
            graph.add(SizeFactor(key, cp.radii, sigma=s["size"]))
    return graph


def mapping_sigmas(seq: Sequence, sigmas: dict | None = None) -> dict:
    """The sigmas in use: defaults, then the sequence's ``trajectory_sigma`` prior, then
    ``sigmas``; unknown names are an error."""
    s = dict(DEFAULT_MAPPING_SIGMAS)
    ts = None if seq.priors is None else getattr(seq.priors, "trajectory_sigma", None)
    if ts is not None:
        s["odometry_translation"], s["odometry_rotation"] = (float(x) for x in ts)
    unknown = sorted(set(sigmas or {}) - set(s))
    if unknown:
        raise ValueError(f"unknown sigma {', '.join(unknown)}; known: {', '.join(sorted(s))}")
    s.update({k: float(v) for k, v in (sigmas or {}).items()})
    bad = [k for k, v in s.items() if not (np.isfinite(v) and (v > 0 or k == "inverse_box_relative"))]
    if bad or s["inverse_box_relative"] < 0:
        raise ValueError(f"sigmas must be finite and positive: {', '.join(bad) or 'inverse_box_relative'}")
    return s


def _drop_invisible(seq, tracks, init, notes, min_views):
    """Remove views where the initial ellipsoid is not in front of the camera."""
    poses = from_tum(np.asarray(seq.poses_tum))
    visible = jax.jit(jax.vmap(lambda e, T: in_front(e, T, 1e-3), in_axes=(None, 0)))
    kept, failed = [], {}
    for tr in tracks:
        if tr.id not in init:
            kept.append(tr)
            continue
        e = init[tr.id]
        ok = np.asarray(visible(e, jaxlie.SE3(poses.wxyz_xyz[tr.frames])))
        if not ok.all():
            notes.append(
                f"object {tr.id}: {int((~ok).sum())} of {ok.size} views dropped (the initial "
                "ellipsoid is not wholly in front of the camera there)"
            )
        if ok.sum() < min_views:
            failed[tr.id] = f"only {int(ok.sum())} views see the initial ellipsoid in front"
            continue
        kept.append(Track(tr.id, tr.label, tr.frames[ok], tr.boxes[ok]))
    return kept, failed


def run_sequence(
    seq: Sequence,
    method: str | Method = "multi-spd",
    *,
    tracks=None,
    sigmas: dict | None = None,
    max_iterations: int = 100,
    min_views: int = 3,
    verbose: bool = False,
    **overrides,
) -> MapResult:
    """Initialise and jointly optimise a sequence with a named method (or a :class:`Method`);
    ``overrides`` replace fields of the method (e.g. ``parameterization="rts"``)."""
    if isinstance(method, str):
        if method not in METHODS:
            raise ValueError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
        method = METHODS[method]
    method = method.replace(**overrides)
    if tracks is None:
        tracks = tracks_from_instances(seq)
    poses = trajectory_poses(seq)
    init, failed, notes = initialize_objects(seq, tracks, method, min_views, poses)
    tracks, more_failed = _drop_invisible(seq, tracks, init, notes, min_views)
    failed.update(more_failed)
    for k in more_failed:
        init.pop(k, None)
    landmarks = {k: _landmark(e, method) for k, e in init.items()}
    values = Values()
    for i, T in enumerate(poses):
        values[pose_key(i)] = T
    for k, lm in landmarks.items():
        values[object_key(k)] = lm

    stages = ["semi", "inverse"] if method.box_model == "semi-then-inverse" else [method.box_model]
    total_it, first_cost, res = 0, None, None
    for stage in stages:
        graph = build_graph(seq, tracks, landmarks, method, stage, sigmas)
        res = LevenbergMarquardt(max_iterations=max_iterations, verbose=verbose).optimize(graph, values)
        values = res.values
        total_it += res.iterations
        first_cost = res.initial_cost if first_cost is None else first_cost
        landmarks = {k: values[object_key(k)] for k in landmarks}

    labels = {tr.id: tr.label for tr in tracks}
    objects = [MapObject(k, labels[k], as_ellipsoid(values[object_key(k)])) for k in sorted(landmarks)]
    initial = [MapObject(k, labels[k], init[k]) for k in sorted(init)]
    rows = np.stack([to_tum(values[pose_key(i)]) for i in range(len(seq))])
    poses_out = np.c_[np.asarray(seq.timestamps), rows]
    for o in objects:
        if not (np.all(np.isfinite(np.asarray(o.ellipsoid.P)))
                and np.all(np.isfinite(np.asarray(o.ellipsoid.center)))):
            raise FloatingPointError(f"object {o.id}: the optimiser returned non-finite values")
    return MapResult(
        method, objects, initial, poses_out, total_it, first_cost, res.final_cost,
        res.converged, res.reason, failed, notes,
    )
