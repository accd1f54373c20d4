"""Object SLAM on a sequence, the paper's Table III pipeline, as one pass of typed stages:

    SequenceContext.of(seq)        the trajectory as SE(3), up, planes, class priors (once)
    → associate_tracks(ctx, …)     Association: tracks and how they were made
    → initialize(ctx, tracks, …)   Initialization: initial ellipsoids, the views that see
                                   them, failures and notes
    → build_graph(ctx, …)          the factor graph (``_graph``), with Values
    → solve                        LM, per box-model stage
    → MapResult                    objects, trajectory, solver figures

Evaluation against ground truth and writing the outputs are the caller's
(``spdslam.evaluation.write_run``): the map never depends on ground truth (with automatic
association, the instance ids, when a sequence has them, only score it).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Callable

import jax
import numpy as np

from ..frontend import (
    InitializationError,
    Track,
    association_scores,
    multi_initialize,
    svd_initialize,
    tracks_from_instances,
)
from ..frontend import associate as auto_associate
from ..geometry import Ellipsoid, EllipsoidFull, EllipsoidRTS, as_ellipsoid, in_front
from ..geometry.se3 import to_tum
from ..io import MapObject, Sequence
from ..solver import L, LevenbergMarquardt, Values, X
from ._context import SequenceContext, as_context, object_shape
from ._graph import build_graph, measured_objects, support_plane
from ._methods import METHODS, Method

__all__ = [
    "ASSOCIATIONS",
    "Association",
    "Initialization",
    "MapResult",
    "associate_tracks",
    "initialize",
    "initialize_objects",
    "initialize_from_measurements",
    "run_sequence",
]

ASSOCIATIONS = ("instances", "auto")


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
        """The content of map.json."""
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


# --- association ------------------------------------------------------------------------------


@dataclass(frozen=True)
class Association:
    """The tracks of a run and the record of how they were made: {"mode": "instances" |
    "auto" | "given"}, with automatic association's scores against the ids when they exist."""

    tracks: list
    record: dict


def associate_tracks(ctx, tracks=None, associate: str | None = None) -> Association:
    """``tracks`` when given; else ``associate="instances"`` (group by the instance ids),
    ``"auto"`` (``frontend.associate``, which ignores the ids), or None: the ids when every
    detection has one, automatic otherwise."""
    seq = as_context(ctx).seq
    if tracks is not None:
        return Association(list(tracks), {"mode": "given"})
    if associate not in (None, *ASSOCIATIONS):
        raise ValueError(f"associate must be one of {', '.join(ASSOCIATIONS)}, got {associate!r}")
    has_ids = bool(seq.detections) and all(d.instance is not None for d in seq.detections)
    if associate is None:
        associate = "instances" if has_ids or not seq.detections else "auto"
    if associate == "instances":
        return Association(tracks_from_instances(seq), {"mode": "instances"})
    found = auto_associate(seq)
    record = {"mode": "auto"}
    if has_ids:
        record.update(association_scores(found, seq))
        record.pop("mapping", None)
    return Association(found, record)


# --- initialisation ---------------------------------------------------------------------------


@dataclass
class Initialization:
    """The front end's result: ``tracks`` (the views that see their initial ellipsoid, and
    objects seen only as measured ellipsoids), ``ellipsoids`` {id: initial Ellipsoid},
    ``measured`` {id: measured ellipsoids}, ``failed`` {id: reason}, ``notes``."""

    tracks: list
    ellipsoids: dict
    measured: dict
    failed: dict
    notes: list


def initialize_objects(ctx, tracks, method: Method, min_views: int = 3):
    """Initial ellipsoids from the boxes: ({id: Ellipsoid}, failures {id: reason}, notes).

    An object with fewer than ``min_views`` views is a failure; so is one the initialiser
    cannot fit (``InitializationError``).
    """
    ctx = as_context(ctx)
    priors = ctx.priors
    init, failed, notes = {}, {}, []
    use_multi = method.initialization == "multi"
    if use_multi and ctx.up is None:
        notes.append("no up direction or support plane in the priors: Quadric-SVD initialisation")
        use_multi = False
    planes = ctx.support_planes()
    for tr in tracks:
        Ts = [ctx.poses[i] for i in tr.frames]
        if len(tr.frames) < min_views:
            failed[tr.id] = f"{len(tr.frames)} views, needs at least {min_views}"
            continue
        try:
            if use_multi:
                plane = None
                if planes:
                    plane = planes[0]
                    if len(planes) > 1:
                        plane = support_plane(priors, svd_initialize(
                            tr.boxes, Ts, ctx.camera, truncation_margin=method.margin))
                cp = ctx.class_prior(tr.label)
                e = multi_initialize(
                    tr.boxes, Ts, ctx.camera, ctx.up, plane,
                    None if cp is None else cp.radii, 0.2 if cp is None else max(cp.sigma, 0.05),
                    shape=object_shape(method, priors, tr.label),
                    truncation_margin=method.margin,
                )
            else:
                e = svd_initialize(tr.boxes, Ts, ctx.camera, truncation_margin=method.margin)
        except InitializationError as err:
            failed[tr.id] = str(err)
            continue
        why = degenerate(e, min_radius=0.0, min_ratio=SINGULAR_RATIO)
        if why:  # not a point of SPD(3) the solver can start from (a flat start is one)
            failed[tr.id] = f"the initial ellipsoid is singular ({why}): the boxes do not fix its extent"
            continue
        init[tr.id] = e
    return init, failed, notes


#: An ellipsoid is degenerate when its smallest radius is below this (m) …
MIN_RADIUS = 1e-3
#: … or below this fraction of its largest.
MIN_RADIUS_RATIO = 1e-3


#: An initial ellipsoid whose smallest radius is below this fraction of its largest is
#: numerically singular: the solver does not start from it.
SINGULAR_RATIO = 1e-6


def degenerate(e, min_radius: float = MIN_RADIUS, min_ratio: float = MIN_RADIUS_RATIO) -> str:
    """Why the ellipsoid ``e`` is degenerate ("" if it is not): a non-finite value, or a
    smallest radius below ``min_radius`` (m) or ``min_ratio`` of the largest."""
    P, c = np.asarray(e.P, float), np.asarray(e.center, float)
    if not (np.all(np.isfinite(P)) and np.all(np.isfinite(c))):
        return "non-finite values"
    r = np.sqrt(np.clip(np.linalg.eigvalsh(0.5 * (P + P.T)), 0.0, None))
    if r[0] < min_radius or r[0] < min_ratio * r[2]:
        return f"radii {r[0]:.3g}, {r[1]:.3g}, {r[2]:.3g} m"
    return ""


def initialize_from_measurements(ctx, measurements) -> Ellipsoid:
    """The mean of measured ellipsoids taken to the world frame of the trajectory:

        P_w = R_wc P_c R_wcᵀ,  t_w = R_wc t_c + t_wc   (per measurement),
        t = mean t_w,  P = Exp(mean Log P_w)   (log-Euclidean mean).
    """
    ctx = as_context(ctx)
    T = np.asarray(ctx.trajectory([m.frame for m in measurements]).as_matrix())
    R, tw = T[:, :3, :3], T[:, :3, 3]
    Pc = np.stack([m.P for m in measurements])
    Pw = R @ Pc @ np.swapaxes(R, 1, 2)
    w, V = np.linalg.eigh(0.5 * (Pw + np.swapaxes(Pw, 1, 2)))
    Lm = np.mean((V * np.log(w)[:, None, :]) @ np.swapaxes(V, 1, 2), axis=0)
    w, V = np.linalg.eigh(0.5 * (Lm + Lm.T))
    center = np.mean(np.einsum("nij,nj->ni", R, np.stack([m.center for m in measurements])) + tw, axis=0)
    return Ellipsoid(np.asarray((V * np.exp(w)) @ V.T), center)


_visible = jax.jit(jax.vmap(lambda e, T: in_front(e, T, 1e-3), in_axes=(None, 0)))


def _drop_invisible(ctx: SequenceContext, tracks, init, notes, min_views, keep=()):
    """Remove views where the initial ellipsoid is not in front of the camera; objects in
    ``keep`` (measured ones) stay even with fewer than ``min_views`` views left."""
    kept, failed = [], {}
    for tr in tracks:
        if tr.id not in init:
            kept.append(tr)
            continue
        ok = np.asarray(_visible(init[tr.id], ctx.trajectory(tr.frames)))
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


def initialize(ctx, association: Association, method: Method, min_views: int = 3
               ) -> Initialization:
    """The front end of a run: initial ellipsoids from the boxes, or from an object's
    measured ellipsoids when its boxes do not give one (manual association only), then the
    views that see each initial ellipsoid wholly in front (others are dropped, with a note;
    an object left with fewer than ``min_views`` views is a failure)."""
    ctx = as_context(ctx)
    seq = ctx.seq
    init, failed, notes = initialize_objects(ctx, association.tracks, method, min_views)
    measured = measured_objects(ctx)
    auto = association.record["mode"] == "auto"
    if auto and seq.ellipsoids:
        # automatic track ids are not instance ids: measurements cannot be attached by id
        notes.append(f"{len(seq.ellipsoids)} measured ellipsoids left out: they are associated "
                     "by instance id only, and the boxes were associated automatically")
        measured = {}
    for k, ms in measured.items():
        if k not in init:
            init[k] = initialize_from_measurements(ctx, ms)
            why = f" (boxes: {failed.pop(k)})" if k in failed else ""
            notes.append(f"object {k}: initialised from its {len(ms)} measured ellipsoids{why}")
    unassigned = len(seq.ellipsoids or ()) - sum(map(len, measured.values()))
    if unassigned and not auto:
        notes.append(f"{unassigned} measured ellipsoids without an instance id >= 0 left out")
    tracks, more_failed = _drop_invisible(ctx, association.tracks, init, notes, min_views,
                                          keep=measured)
    failed.update(more_failed)
    for k in more_failed:
        init.pop(k, None)
    with_boxes = {tr.id for tr in tracks}
    for k, ms in sorted(measured.items()):  # objects seen only as measured ellipsoids
        if k not in with_boxes:
            labels = [m.label for m in ms]
            label = max(sorted(set(labels)), key=labels.count)
            tracks.append(Track(k, label, np.zeros(0, dtype=int), np.zeros((0, 4))))
    return Initialization(tracks, init, measured, failed, notes)


# --- the run ----------------------------------------------------------------------------------


def _landmark(e: Ellipsoid, method: Method):
    if method.parameterization == "spd":
        return e
    if method.parameterization == "full":
        return EllipsoidFull.from_ellipsoid(e)
    R, s = (np.asarray(a) for a in e.axes())
    return EllipsoidRTS.from_axes(R, np.asarray(e.center), s)


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
    progress: Callable[[str], Any] | None = None,
    **overrides,
) -> MapResult:
    """Initialise and jointly optimise a sequence with a named method (or a :class:`Method`);
    ``overrides`` replace fields of the method (e.g. ``parameterization="rts"``).

    Data association: ``tracks`` when given; else ``associate="instances"`` (group by the
    instance ids), ``"auto"`` (:func:`spdslam.frontend.associate`, which ignores the ids),
    or None: the ids when every detection has one, automatic otherwise. With automatic
    association the result records precision and recall against the ids where they exist.
    ``progress(message)`` is called at each stage and after each LM iteration.
    """
    say = progress or (lambda message: None)
    if isinstance(method, str):
        if method not in METHODS:
            raise ValueError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
        method = METHODS[method]
    method = method.replace(**overrides)
    ctx = SequenceContext.of(seq)
    say(f"association: {len(seq.detections)} detections in {len(seq)} frames")
    association = associate_tracks(ctx, tracks, associate)
    say(f"association: {len(association.tracks)} tracks ({association.record.get('mode', 'given')})")
    front = initialize(ctx, association, method, min_views)
    say(f"initialisation: {len(front.ellipsoids)} objects, {len(front.failed)} not initialised")

    landmarks = {k: _landmark(e, method) for k, e in front.ellipsoids.items()}
    values = Values()
    for i, T in enumerate(ctx.poses):
        values[X(i)] = T
    for k, lm in landmarks.items():
        values[L(k)] = lm
    stages = ["semi", "inverse"] if method.box_model == "semi-then-inverse" else [method.box_model]

    def each_iteration(rec):
        say(f"LM iteration {rec.iteration}: cost {rec.cost:.6g} "
            f"({'accepted' if rec.accepted else 'rejected'}, λ {rec.lambda_:.2g})")

    optimizer = LevenbergMarquardt(max_iterations=max_iterations, verbose=verbose,
                                   callback=each_iteration if progress else None)
    total_it, first_cost, res = 0, None, None
    for stage in stages:
        graph = build_graph(ctx, front.tracks, landmarks, method, stage, sigmas, front.measured)
        say(f"optimisation ({stage} boxes): {len(values)} variables, {len(graph)} factors")
        res = optimizer.optimize(graph, values)
        values = res.values
        total_it += res.iterations
        first_cost = res.initial_cost if first_cost is None else first_cost
        landmarks = {k: values[L(k)] for k in landmarks}

    labels = {tr.id: tr.label for tr in front.tracks}
    objects = [MapObject(k, labels[k], as_ellipsoid(values[L(k)])) for k in sorted(landmarks)]
    initial = [MapObject(k, labels[k], front.ellipsoids[k]) for k in sorted(front.ellipsoids)]
    rows = np.stack([to_tum(values[X(i)]) for i in range(len(seq))])
    poses_out = np.c_[np.asarray(seq.timestamps), rows]
    failed = dict(front.failed)
    kept = []
    for o in objects:  # reported, not mapped: an object whose extent the data do not fix
        why = degenerate(o.ellipsoid)
        if why:
            failed[o.id] = f"degenerate after the optimisation ({why}): the boxes do not fix its extent"
        else:
            kept.append(o)
    return MapResult(
        method, kept, initial, poses_out, total_it, first_cost, res.final_cost,
        res.converged, res.reason, failed, front.notes, association.record,
    )
