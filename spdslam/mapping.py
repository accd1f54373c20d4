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
  inverse from there) of the object's silhouette model, its ellipsoid or (box-like
  classes, ``Method.object_shape``) its circumscribed cuboid; box edges within
  ``Method.truncation_margin`` px of the image border carry no bound (truncated boxes);
- per measured ellipsoid (``seq.ellipsoids``, RGB-D / LiDAR, instance id ≥ 0): an
  ``EllipsoidMeasurementFactor`` (σ ``ellipsoid_shape`` per log-shape component,
  ``ellipsoid_center`` m). An object with measurements whose box initialisation fails (too
  few boxes, or none) starts from the world-frame mean of its measurements;
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

from .association import Track, association_scores, tracks_from_instances
from .association import associate as auto_associate
from .camera import in_front
from .ellipsoid import Ellipsoid, EllipsoidFull, EllipsoidRTS, as_ellipsoid
from .factors import (
    DEFAULT_SIGMAS,
    DEFAULT_TRUNCATION_MARGIN,
    ELLIPSOID_MEASUREMENT_SIGMAS,
    AxisOrientationFactor,
    BetweenFactor,
    Cauchy,
    ClassicOrientationFactor,
    EllipsoidMeasurementFactor,
    Huber,
    InverseBoxFactor,
    InverseCuboidBoxFactor,
    OrientationFactor,
    PriorFactor,
    SemiInverseBoxFactor,
    SemiInverseCuboidBoxFactor,
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
    "initialize_from_measurements",
    "initialize_objects",
    "measured_objects",
    "mapping_sigmas",
    "object_key",
    "object_shape",
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
#: Factor types a robust kernel can be chosen for (``Method.robust_by_type``): their kinds.
ROBUST_FACTOR_TYPES = {
    "box": ("inverse_box", "semi_inverse_box", "inverse_cuboid_box", "semi_inverse_cuboid_box"),
    "ellipsoid": ("ellipsoid_measurement",),
    "odometry": ("BetweenFactor",),
    "orientation": ("orientation", "classic_orientation", "axis_orientation"),
    "support_plane": ("support_plane",),
    "shape": ("shape",),
    "size": ("size",),
}
OBJECT_SHAPE_CHOICES = ("priors", "ellipsoid", "cuboid")

#: Default standard deviations: the factor defaults plus odometry and the first-pose prior.
DEFAULT_MAPPING_SIGMAS = {
    **DEFAULT_SIGMAS,
    # A detector's box error grows with the box (and so does the misfit of an ellipsoid to
    # a box-shaped object): per edge σ = inverse_box + inverse_box_relative · box size.
    "inverse_box": 2.0,  # px
    "inverse_box_relative": 0.05,  # of the box width (u edges) or height (v edges)
    # The same for the cuboid silhouette of box-like objects.
    "inverse_cuboid_box": 2.0,  # px
    "inverse_cuboid_box_relative": 0.05,
    # Scene knowledge is held nearly hard: upright objects standing on their plane.
    "orientation": 0.005,  # per component of (Log P m) × m
    "classic_orientation": 0.005,  # per component of ±n × m (≈ rad)
    "axis_orientation": 0.005,  # per component of (nᵢ × m)(nᵢ·m) (≈ rad), cuboid objects
    "support_plane": 0.001,  # m²
    # Accuracy of the input trajectory (visual-odometry keyframes) unless the sequence's
    # priors.yaml states its own (``trajectory_sigma``).
    "odometry_translation": 0.005,  # m per frame step
    "odometry_rotation": 0.003,  # rad per frame step
    "first_pose": 1e-4,  # m and rad
    # Whole-ellipsoid measurements (ellipsoids.txt): ellipsoid_shape 0.1 per log-shape
    # component (≈ 5 % of a radius), ellipsoid_center 0.05 m.
    **ELLIPSOID_MEASUREMENT_SIGMAS,
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
    #: Kernels per factor type, overriding ``robust`` (which covers box and measured-ellipsoid
    #: factors): ((type, kernel, k), ...) with type a key of ROBUST_FACTOR_TYPES.
    robust_by_type: tuple = ()
    #: Silhouette model of every object ("ellipsoid" or "cuboid"), or "priors": per class,
    #: ``priors.classes[label].shape`` ("ellipsoid" for classes without a prior).
    object_shape: str = "priors"
    #: Box edges within this many px of the image border carry no bound (truncated
    #: detections), in the initialisation and in every box factor; negative: keep all edges.
    truncation_margin: float = DEFAULT_TRUNCATION_MARGIN

    def __post_init__(self):
        for name, allowed in (
            ("parameterization", PARAMETERIZATIONS),
            ("initialization", INITIALIZATIONS),
            ("box_model", BOX_MODELS),
            ("orientation", ORIENTATIONS),
            ("robust", ROBUST_KERNELS),
            ("object_shape", OBJECT_SHAPE_CHOICES),
        ):
            if getattr(self, name) not in allowed:
                raise ValueError(
                    f"{name} must be one of {', '.join(allowed)}, got {getattr(self, name)!r}"
                )
        if self.orientation == "classic" and self.parameterization != "rts":
            raise ValueError("the classic orientation constraint needs the rts parameterization")
        if not self.robust_k > 0:
            raise ValueError(f"robust_k must be > 0, got {self.robust_k}")
        rbt = tuple(tuple(x) for x in self.robust_by_type)
        for item in rbt:
            if (len(item) != 3 or item[0] not in ROBUST_FACTOR_TYPES or item[1] not in ROBUST_KERNELS
                    or not (isinstance(item[2], (int, float)) and item[2] > 0)):
                raise ValueError(
                    f"robust_by_type entries must be (type, kernel, k > 0) with type one of "
                    f"{', '.join(ROBUST_FACTOR_TYPES)} and kernel one of {', '.join(ROBUST_KERNELS)}, "
                    f"got {item!r}"
                )
        object.__setattr__(self, "robust_by_type", tuple((t, n, float(k)) for t, n, k in rbt))
        if not np.isfinite(self.truncation_margin):
            raise ValueError(f"truncation_margin must be finite (px), got {self.truncation_margin}")

    @property
    def margin(self) -> float | None:
        """The truncation margin handed to initialisers and box factors (None: off)."""
        return None if self.truncation_margin < 0 else float(self.truncation_margin)

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
    #: how detections were grouped: {"mode": "instances" | "auto" | "given"}, with automatic
    #: association's precision and recall against the instance ids when they exist
    association: dict = field(default_factory=lambda: {"mode": "instances"})

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
            "association": dict(self.association),
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


def object_shape(method: Method, priors, label) -> str:
    """The silhouette model of an object of class ``label``: the method's, or with
    ``object_shape="priors"`` its class prior's shape ("ellipsoid" without a prior)."""
    if method.object_shape != "priors":
        return method.object_shape
    cp = _class_prior(priors, label)
    return "ellipsoid" if cp is None else getattr(cp, "shape", "ellipsoid")


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
                        plane = _support_plane(priors, svd_initialize(
                            tr.boxes, Ts, seq.camera, truncation_margin=method.margin))
                cp = _class_prior(priors, tr.label)
                e = multi_initialize(
                    tr.boxes, Ts, seq.camera, up, plane,
                    None if cp is None else cp.radii, 0.2 if cp is None else max(cp.sigma, 0.05),
                    shape=object_shape(method, priors, tr.label),
                    truncation_margin=method.margin,
                )
            else:
                e = svd_initialize(tr.boxes, Ts, seq.camera, truncation_margin=method.margin)
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


def _kernel(name: str, k: float):
    return {"huber": Huber, "cauchy": Cauchy}[name](k) if name != "none" else None


def _robust(method: Method):
    return _kernel(method.robust, method.robust_k)


def _with_robust_by_type(graph, method: Method):
    """The graph with ``method.robust_by_type``'s kernels on the factors of those types."""
    if not method.robust_by_type:
        return graph
    by_kind = {}
    for ftype, name, k in method.robust_by_type:
        for kind in ROBUST_FACTOR_TYPES[ftype]:
            by_kind[kind] = _kernel(name, k)
    return NonlinearFactorGraph(
        dataclasses.replace(f, robust=by_kind[f.kind]) if f.kind in by_kind else f for f in graph
    )


def build_graph(seq: Sequence, tracks, landmarks: dict, method: Method, box_model: str,
                sigmas: dict | None = None, measured: dict | None = None):
    """The factor graph of a sequence for the given landmarks {id: landmark value};
    ``measured`` the measured ellipsoids per object id (default: by instance id)."""
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
    priors = seq.priors
    up = _up(priors)
    for tr in tracks:
        if tr.id not in landmarks:
            continue
        key = object_key(tr.id)
        lm = landmarks[tr.id]
        cuboid = object_shape(method, priors, tr.label) == "cuboid"
        if box_model == "inverse":
            box_factor = InverseCuboidBoxFactor if cuboid else InverseBoxFactor
            name = "inverse_cuboid_box" if cuboid else "inverse_box"
        else:
            box_factor = SemiInverseCuboidBoxFactor if cuboid else SemiInverseBoxFactor
            name = "semi_inverse_cuboid_box" if cuboid else "semi_inverse_box"
        for f, b in zip(tr.frames, tr.boxes):
            if box_model == "inverse":
                size = np.array([b[2] - b[0], b[3] - b[1]] * 2)
                box_sigma = s[name] + s[name + "_relative"] * size
            else:
                box_sigma = s[name]
            graph.add(box_factor(pose_key(f), key, b, seq.camera, sigma=box_sigma, robust=robust,
                                 truncation_margin=method.margin))
        if up is not None and method.orientation == "improved":
            if cuboid:
                graph.add(AxisOrientationFactor(key, up, sigma=s["axis_orientation"]))
            else:
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
    for k, ms in (measured_objects(seq) if measured is None else measured).items():
        for m in ms if k in landmarks else ():
            graph.add(EllipsoidMeasurementFactor(
                pose_key(m.frame), object_key(k), (m.rotation, m.radii), m.center,
                sigma_shape=s["ellipsoid_shape"], sigma_center=s["ellipsoid_center"], robust=robust,
            ))
    return _with_robust_by_type(graph, method)


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
    relative = ("inverse_box_relative", "inverse_cuboid_box_relative")  # may be 0
    bad = [k for k, v in s.items() if not (np.isfinite(v) and (v > 0 or (k in relative and v == 0)))]
    if bad:
        raise ValueError(f"sigmas must be finite and positive: {', '.join(bad)}")
    return s


def measured_objects(seq: Sequence) -> dict:
    """The measured ellipsoids of each object, {instance: [EllipsoidDetection]} (manual
    association: instance ids ≥ 0; measurements without one belong to no object)."""
    out: dict = {}
    for m in seq.ellipsoids or ():
        if m.instance is not None and m.instance >= 0:
            out.setdefault(m.instance, []).append(m)
    return out


def initialize_from_measurements(seq: Sequence, measurements) -> Ellipsoid:
    """The mean of measured ellipsoids taken to the world frame of the trajectory:

        P_w = R_wc P_c R_wcᵀ,  t_w = R_wc t_c + t_wc   (per measurement),
        t = mean t_w,  P = Exp(mean Log P_w)   (log-Euclidean mean).
    """
    T = np.asarray(from_tum(np.asarray(seq.poses_tum)).as_matrix())[[m.frame for m in measurements]]
    R, tw = T[:, :3, :3], T[:, :3, 3]
    Pc = np.stack([m.P for m in measurements])
    Pw = R @ Pc @ np.swapaxes(R, 1, 2)
    w, V = np.linalg.eigh(0.5 * (Pw + np.swapaxes(Pw, 1, 2)))
    L = np.mean((V * np.log(w)[:, None, :]) @ np.swapaxes(V, 1, 2), axis=0)
    w, V = np.linalg.eigh(0.5 * (L + L.T))
    center = np.mean(np.einsum("nij,nj->ni", R, np.stack([m.center for m in measurements])) + tw, axis=0)
    return Ellipsoid(np.asarray((V * np.exp(w)) @ V.T), center)


def _drop_invisible(seq, tracks, init, notes, min_views, keep=()):
    """Remove views where the initial ellipsoid is not in front of the camera; objects in
    ``keep`` (measured ones) stay even with fewer than ``min_views`` views left."""
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
        if ok.sum() < min_views and tr.id not in keep:
            failed[tr.id] = f"only {int(ok.sum())} views see the initial ellipsoid in front"
            continue
        kept.append(Track(tr.id, tr.label, tr.frames[ok], tr.boxes[ok]))
    return kept, failed


def run_sequence(
    seq: Sequence,
    method: str | Method = "multi-spd",
    *,
    tracks=None,
    associate: str | None = None,
    sigmas: dict | None = None,
    max_iterations: int = 100,
    min_views: int = 3,
    verbose: bool = False,
    **overrides,
) -> MapResult:
    """Initialise and jointly optimise a sequence with a named method (or a :class:`Method`);
    ``overrides`` replace fields of the method (e.g. ``parameterization="rts"``).

    Data association: ``tracks`` when given; else ``associate="instances"`` (group by the
    instance ids), ``"auto"`` (:func:`spdslam.association.associate`, which ignores the ids),
    or None: the ids when every detection has one, automatic otherwise. With automatic
    association the result records precision and recall against the ids where they exist.
    """
    if isinstance(method, str):
        if method not in METHODS:
            raise ValueError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
        method = METHODS[method]
    method = method.replace(**overrides)
    tracks, association = _tracks(seq, tracks, associate)
    poses = trajectory_poses(seq)
    init, failed, notes = initialize_objects(seq, tracks, method, min_views, poses)
    measured = measured_objects(seq)
    if association["mode"] == "auto" and seq.ellipsoids:
        # automatic track ids are not instance ids: measurements cannot be attached by id
        notes.append(f"{len(seq.ellipsoids)} measured ellipsoids left out: they are associated "
                     "by instance id only, and the boxes were associated automatically")
        measured = {}
    for k, ms in measured.items():
        if k not in init:
            init[k] = initialize_from_measurements(seq, ms)
            why = f" (boxes: {failed.pop(k)})" if k in failed else ""
            notes.append(f"object {k}: initialised from its {len(ms)} measured ellipsoids{why}")
    unassigned = len(seq.ellipsoids or ()) - sum(map(len, measured.values()))
    if unassigned and association["mode"] != "auto":
        notes.append(f"{unassigned} measured ellipsoids without an instance id >= 0 left out")
    tracks, more_failed = _drop_invisible(seq, tracks, init, notes, min_views, keep=measured)
    failed.update(more_failed)
    for k in more_failed:
        init.pop(k, None)
    with_boxes = {tr.id for tr in tracks}
    for k, ms in sorted(measured.items()):  # objects seen only as measured ellipsoids
        if k not in with_boxes:
            labels = [m.label for m in ms]
            label = max(sorted(set(labels)), key=labels.count)
            tracks.append(Track(k, label, np.zeros(0, dtype=int), np.zeros((0, 4))))
    landmarks = {k: _landmark(e, method) for k, e in init.items()}
    values = Values()
    for i, T in enumerate(poses):
        values[pose_key(i)] = T
    for k, lm in landmarks.items():
        values[object_key(k)] = lm

    stages = ["semi", "inverse"] if method.box_model == "semi-then-inverse" else [method.box_model]
    total_it, first_cost, res = 0, None, None
    for stage in stages:
        graph = build_graph(seq, tracks, landmarks, method, stage, sigmas, measured)
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
        res.converged, res.reason, failed, notes, association,
    )


ASSOCIATIONS = ("instances", "auto")


def _tracks(seq: Sequence, tracks, associate: str | None):
    """(tracks, association record) for :func:`run_sequence`."""
    if tracks is not None:
        return list(tracks), {"mode": "given"}
    if associate not in (None, *ASSOCIATIONS):
        raise ValueError(f"associate must be one of {', '.join(ASSOCIATIONS)}, got {associate!r}")
    has_ids = bool(seq.detections) and all(d.instance is not None for d in seq.detections)
    if associate is None:
        associate = "instances" if has_ids or not seq.detections else "auto"
    if associate == "instances":
        return tracks_from_instances(seq), {"mode": "instances"}
    tracks = auto_associate(seq)
    record = {"mode": "auto"}
    if has_ids:
        record.update(association_scores(tracks, seq))
        record.pop("mapping", None)
    return tracks, record
