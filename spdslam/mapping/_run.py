"""The steps of a batch run (``_batch.run_sequence`` composes them, each inside
``step(name)``; docs/core.md draws them) and the result they make: association
(``associate_tracks``), initialisation (``initialize``), duplicates
(``overlapping_duplicates``, ``merge_duplicates``), and ``map_result`` (uncertainty, each
object's quality, ``MapResult``); the online mapper (``_online``) uses them too.

A failure confined to one object moves it to ``failed`` (``OBJECT_ERRORS``); one of the
whole problem is a ``MappingError`` naming the step. Evaluation against ground truth and
writing the outputs are the caller's (``spdslam.experiments.write_run``): the map never
depends on ground truth (with automatic association, the instance ids, when a sequence has
them, only score it).
"""

from __future__ import annotations

import contextlib
import dataclasses
from dataclasses import dataclass, field
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..factors import eigenvalue_steps
from ..frontend import (
    InitializationError,
    MultiFit,
    SupportPlanes,
    Track,
    estimate_support_planes,
    multi_initialize_batch,
    svd_initialize,
    tracks_from_instances,
    unoriented_initialize,
)
from ..frontend import associate as auto_associate
from ..geometry import (
    Ellipsoid,
    EllipsoidFull,
    EllipsoidRTS,
    as_ellipsoid,
    in_front,
    manifold,
    project_box,
)
from ..geometry.matfun import eigh
from ..geometry.se3 import to_tum
from ..io import MapObject, class_prior, map_document
from ..solver import L, NonlinearFactorGraph, Values, X, marginal_covariances
from ._context import SequenceContext, as_context, object_shape
from ._graph import measured_objects, support_plane
from ._methods import Method
from ._settings import Associate, PlaneSource, default_association

__all__ = [
    "ASSOCIATIONS",
    "OBJECT_ERRORS",
    "RunTracks",
    "Initialization",
    "MapResult",
    "MappingError",
    "Optimised",
    "associate_tracks",
    "cost_by_factor",
    "implausibly_flat",
    "initialize",
    "initialize_objects",
    "initialize_from_measurements",
    "map_result",
    "merge_duplicates",
    "merged_tracks",
    "merged_track",
    "in_front_views",
    "too_few_views",
    "nesting_depths",
    "object_quality",
    "planes_note",
    "overlapping_duplicates",
    "step",
]

ASSOCIATIONS = tuple(a.value for a in Associate)
#: Where support planes come from: the priors only; else estimated from the initial
#: objects; else estimated from the objects optimised without planes (then optimised again).
SUPPORT_PLANES = tuple(p.value for p in PlaneSource)

#: The errors that a step confines to one object (a singular or non-finite matrix, an
#: initialiser that cannot fit): the object is moved to ``failed`` with the step and the
#: reason, and the run goes on. Anything else, or any error of a step over the whole problem,
#: ends the run as a :class:`MappingError` naming the step.
OBJECT_ERRORS = (ValueError, ArithmeticError)


class MappingError(ValueError):
    """A step of the run failed for the whole problem: ``"<step>: <reason>"``; ``step`` names
    it (keyframes, screening, association, initialisation, graph, optimisation, support
    planes, duplicates, uncertainty, result)."""

    def __init__(self, step: str, reason: str):
        super().__init__(f"{step}: {reason}")
        self.step = step


@contextlib.contextmanager
def step(name: str):
    """Run a step of the pipeline over the whole problem: an error in it (other than a
    ``MappingError`` of an inner step) becomes ``MappingError(name, …)``."""
    try:
        yield
    except MappingError:
        raise
    except Exception as e:  # noqa: BLE001 - re-raised, naming the step
        raise MappingError(name, str(e) or type(e).__name__) from e


@dataclass(kw_only=True)
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
    #: how detections were grouped: {"mode": "instances" | "auto" | "given"}; an automatic
    #: association's precision and recall against the instance ids, where they exist, are the
    #: evaluation's (``evaluation.association_scores`` of ``associated``, added to map.json
    #: by ``experiments.write_run``)
    association: dict = field(default_factory=lambda: {"mode": "instances"})
    #: an automatic association's (tracks, the sequence they group the detections of), else ()
    associated: tuple = field(default=(), repr=False, compare=False)
    #: the final cost of each factor kind, {kind: ½ Σ ρ(‖W r‖²)}: which constraint the
    #: optimum pays for
    costs: dict = field(default_factory=dict)
    #: a trajectory without a bound on each pose: where its poses came from ("start"), the
    #: box errors' correlation, the loop closure (``LoopClosure.as_dict``) and each check
    #: against the odometry (``TrajectoryCheck.as_dict``); empty with a bound
    trajectory: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        """The content of map.json (``io.map_document``)."""
        return map_document(
            method=self.method.name, parameterization=self.method.parameterization,
            iterations=self.iterations, final_cost=self.final_cost,
            initial_cost=self.initial_cost, converged=self.converged, reason=self.reason,
            settings=dataclasses.asdict(self.method), objects=self.objects, failed=self.failed,
            notes=self.notes, association=self.association, cost_by_factor=self.costs,
            trajectory=self.trajectory)


# --- association ------------------------------------------------------------------------------


@dataclass(frozen=True)
class RunTracks:
    """The tracks of a run and the record of how they were made: {"mode": "instances" |
    "auto" | "given"} (``associated_on``: what poses an automatic association used)."""

    tracks: list
    record: dict


def associate_tracks(ctx, tracks=None, associate: str | None = None, found=None) -> RunTracks:
    """``tracks`` when given; else ``associate="instances"`` (group by the instance ids),
    ``"auto"`` (``frontend.associate``, which ignores the ids; ``found``: tracks an automatic
    association already made, the replay's online tracker's, recorded as
    ``associated_on: incremental poses``), or None: the ids when every detection has one,
    automatic otherwise."""
    seq = as_context(ctx).seq
    if tracks is not None:
        return RunTracks(list(tracks), {"mode": "given"})
    if associate not in (None, *ASSOCIATIONS):
        raise ValueError(f"associate must be one of {', '.join(ASSOCIATIONS)}, got {associate!r}")
    if associate is None:
        associate = str(default_association(seq))
    if associate == "instances":
        return RunTracks(tracks_from_instances(seq), {"mode": "instances"})
    record = {"mode": "auto"}
    if found is None:
        found = auto_associate(seq)
    else:
        record["associated_on"] = "incremental poses"
    return RunTracks(list(found), record)


# --- initialisation ---------------------------------------------------------------------------


@dataclass
class Initialization:
    """The front end's result: ``tracks`` (the views that see their initial ellipsoid, and
    objects seen only as measured ellipsoids), ``ellipsoids`` {id: initial Ellipsoid},
    ``measured`` {id: measured ellipsoids}, ``failed`` {id: reason}, ``notes``, and the
    support ``planes`` estimated from the initial objects (None: the priors' planes, or
    none, are used)."""

    tracks: list
    ellipsoids: dict
    measured: dict
    failed: dict
    notes: list
    planes: SupportPlanes | None = None


def too_few_views(views: int, min_views: int) -> str:
    """Why an object of ``views`` views is not mapped when it needs ``min_views``: the batch
    run's and the online mapper's one gate."""
    return f"{views} views, needs at least {min_views}"


def initialize_objects(ctx, tracks, method: Method, min_views: int = 3,
                       planes: SupportPlanes | None = None):
    """Initial ellipsoids from the boxes: ({id: Ellipsoid}, failures {id: reason}, notes).

    An object with fewer than ``min_views`` views is a failure; so is one the initialiser
    cannot fit (``InitializationError``). The multi-constraint initialisation rests an
    object on its plane of ``planes`` when given, else on the priors' plane nearest to it.
    """
    ctx = as_context(ctx)
    priors = ctx.priors
    init, failed, notes = {}, {}, []
    use_multi = method.initialization == "multi"
    unoriented = use_multi and ctx.up is None  # the multi-constraint fit has no frame
    use_multi = use_multi and not unoriented
    spheres = 0
    prior_planes = ctx.support_planes()
    fitted: dict = {}
    multi: list = []  # (id, (boxes, poses, plane, fit)): fitted together (``multi_initialize_batch``)
    for tr in tracks:
        Ts = [ctx.poses[i] for i in tr.frames]
        if len(tr.frames) < min_views:
            fitted[tr.id] = InitializationError(too_few_views(len(tr.frames), min_views))
            continue
        try:
            if use_multi:
                plane = None
                if planes is not None:
                    plane = planes.plane_of(tr.id)
                elif prior_planes:
                    plane = prior_planes[0]
                    if len(prior_planes) > 1:
                        plane = support_plane(priors, svd_initialize(
                            tr.boxes, Ts, ctx.camera, truncation_margin=method.margin))
                cp = ctx.class_prior(tr.label)
                fit = MultiFit(None if cp is None else cp.radii, 0.2 if cp is None else max(cp.sigma, 0.05),
                               object_shape(method, priors, tr.label), method.margin)
                multi.append((tr.id, (tr.boxes, Ts, plane, fit)))
            elif unoriented:
                fitted[tr.id], start = unoriented_initialize(tr.boxes, Ts, ctx.camera, truncation_margin=method.margin,
                                                             min_ratio=MIN_PLAUSIBLE_RATIO)
                spheres += start == "sphere"
            else:
                fitted[tr.id] = svd_initialize(tr.boxes, Ts, ctx.camera, truncation_margin=method.margin)
        except OBJECT_ERRORS as err:
            fitted[tr.id] = err
    if unoriented:
        notes.append("no up direction or support plane in the priors: Quadric-SVD initialisation, "
                     f"a sphere on the boxes' rays where it is flat or fits the boxes worse ({spheres} objects)")
    if multi:
        got = multi_initialize_batch([m for _, m in multi], ctx.camera, ctx.up)
        fitted.update(zip([i for i, _ in multi], got))
    for tr in tracks:  # in the tracks' order, failures too
        e = fitted[tr.id]
        if isinstance(e, InitializationError):
            failed[tr.id] = str(e)
            continue
        if isinstance(e, Exception):  # a singular or non-finite fit: this object only
            failed[tr.id] = f"initialisation: {type(e).__name__}: {e}"
            continue
        why = degenerate(e, min_radius=0.0, min_ratio=SINGULAR_RATIO)
        if why:  # not a point of SPD(3) the solver can start from (a flat start is one)
            failed[tr.id] = f"the initial ellipsoid is singular ({why}): the boxes do not fix its extent"
            continue
        init[tr.id] = e
    return init, failed, notes


#: An object is poorly observed when the marginal standard deviation of its centre along
#: some direction exceeds this (m; given the cameras where the trajectory has no bound on
#: each pose: ``map_result``) …
MAX_CENTER_SIGMA = 0.1
#: … or that of one of its log-radii exceeds this (log 2: the radius is not known to within
#: a factor of 2).
MAX_LOG_RADIUS_SIGMA = float(np.log(2.0))


#: The upper triangle of P in map.json's covariance order: xx, xy, xz, yy, yz, zz.
_UPPER = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))


def _summary(lm, delta):
    """(centre, log radii, smallest first, P's upper triangle ``_UPPER``) of the landmark
    ``lm`` ⊞ δ."""
    e = as_ellipsoid(manifold.retract(lm, delta))
    w, _ = eigh(e.P)
    return jnp.concatenate([e.center, 0.5 * jnp.log(jnp.maximum(w, 1e-300)), e.P[_UPPER]])


@jax.jit
def _summary_jacobian(lm):
    """∂(centre, log radii, P's upper triangle)/∂δ at δ = 0, in the landmark's chart
    (forward mode)."""
    return jax.jacfwd(lambda d: _summary(lm, d))(jnp.zeros(manifold.tangent_dim(lm)))


def _summary_jacobians(landmarks: list) -> np.ndarray:
    """``_summary_jacobian`` of Ellipsoids in NumPy, stacked (n, 12, 9): the centre's rows
    [0 | I], the log radii's ½ dwᵢ/wᵢ (``factors.eigenvalue_steps``, its rule at tied radii),
    P's upper triangle from the chart's pushforward P^½ Eₖ P^½ (``manifold``'s
    ``host_pushforward``)."""
    stacked = Ellipsoid(np.stack([np.asarray(e.P, float) for e in landmarks]),
                        np.stack([np.asarray(e.center, float) for e in landmarks]))
    w, dw = eigenvalue_steps(stacked)
    push = manifold.ops(Ellipsoid).host_pushforward
    assert push is not None  # Ellipsoid registers one (geometry's _ellipsoid)
    dP = np.asarray(push(stacked).P)  # (n, 9, 3, 3)
    J = np.zeros((len(w), 12, 9))
    J[:, 0:3, 6:9] = np.eye(3)
    with np.errstate(invalid="ignore"):  # a landmark not finite: NaN rows, as the program's
        J[:, 3:6, 0:6] = 0.5 * np.swapaxes(dw, 1, 2) / np.maximum(w, 1e-300)[:, :, None]
    J[:, 6:12, :] = np.swapaxes(dP[:, :, _UPPER[0], _UPPER[1]], 1, 2)
    return J


def object_uncertainty(graph, values, ids, fixed=(), result=None) -> dict:
    """{id: {"center_sigma": [3] (m, along the world axes), "center_sigma_max" (m, along
    the worst direction), "log_radius_sigma": [3] (of the sorted radii, smallest first),
    "covariance": 9×9 of (centre (m), P's xx, xy, xz, yy, yz, zz (m²))}} from the marginal
    covariance Σ of each landmark L(id) at ``values`` (``solver.marginal_covariances``),
    propagated as J Σ Jᵀ with J the Jacobian of (centre, log sorted radii, P's upper
    triangle) in the landmark's chart. An object whose block is not determined gets
    ``inf`` (and covariance None). ``fixed`` keys are held (the poses of a held trajectory).
    ``result``: the optimisation of ``graph`` (with ``fixed``) that ended at ``values``,
    whose last linearisation gives the covariances (``OptimizationResult.marginal_covariances``)."""
    keys = [L(k) for k in ids]
    if _reusable(result, values):
        cov = result.marginal_covariances(keys)
    else:
        cov = marginal_covariances(graph, values, keys, fixed=fixed)
    out = {}
    inf = [float("inf")] * 3
    spd_ids = [k for k in ids if type(values[L(k)]) is Ellipsoid]  # in NumPy; the others' by JAX
    host = dict(zip(spd_ids, _summary_jacobians([values[L(k)] for k in spd_ids]))) if spd_ids else {}
    for k in ids:
        lm, S = values[L(k)], cov[L(k)]
        J = (host[k] if k in host else np.asarray(_summary_jacobian(lm))) if np.all(np.isfinite(S)) else None
        if J is None or not np.all(np.isfinite(J)):  # not determined, or no chart there
            out[k] = {"center_sigma": inf, "center_sigma_max": float("inf"), "log_radius_sigma": inf,
                      "covariance": None}
            continue
        C = J @ S @ J.T
        Cc = C[:3, :3]
        amb = np.r_[0:3, 6:12]  # centre and P's upper triangle
        out[k] = {
            "center_sigma": np.sqrt(np.maximum(np.diag(Cc), 0.0)).tolist(),
            "center_sigma_max": float(np.sqrt(max(np.linalg.eigvalsh(Cc)[-1], 0.0))),
            "log_radius_sigma": np.sqrt(np.maximum(np.diag(C)[3:6], 0.0)).tolist(),
            "covariance": (0.5 * (C[np.ix_(amb, amb)] + C[np.ix_(amb, amb)].T)).tolist(),
        }
    return out


def mapped_uncertainty(graph, values, ids, fixed=(), result=None) -> dict:
    """``object_uncertainty`` of the objects that are not degenerate (``degenerate``), from
    the graph without the degenerate ones and their factors: a degenerate object (reported,
    not mapped) can make the joint information singular, which would leave every object's
    marginal undetermined. ``result``: the optimisation that ended at ``values`` (reused
    when no object is degenerate)."""
    flat = {L(k) for k in ids if degenerate(as_ellipsoid(values[L(k)]))}
    if not flat:
        return object_uncertainty(graph, values, ids, fixed, result)
    return object_uncertainty(
        NonlinearFactorGraph([f for f in graph if not flat.intersection(f.keys)]),
        Values({k: values[k] for k in values if k not in flat}),
        [k for k in ids if L(k) not in flat], fixed)


def poorly_observed(u: dict | None) -> str:
    """Why an object's uncertainty (``object_uncertainty``) makes it poorly observed, or ""."""
    if not u:
        return ""
    why = []
    if not u["center_sigma_max"] <= MAX_CENTER_SIGMA:
        why.append(f"centre σ {u['center_sigma_max']:.3g} m > {MAX_CENTER_SIGMA} m")
    worst = max(u["log_radius_sigma"])
    if not worst <= MAX_LOG_RADIUS_SIGMA:
        factor = np.exp(min(worst, 700.0))  # e^700 ≈ 1e304: no overflow warning for inf
        why.append(f"a radius known only to a factor {factor:.3g} > 2" if worst < 700
                   else "a radius not determined")
    return "; ".join(why)


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


#: An object is implausibly flat when its smallest radius is below this (m) …
MIN_PLAUSIBLE_RADIUS = 3e-3
#: … or below this fraction of its largest, unless its class prior is itself that flat
#: (``implausibly_flat``).
MIN_PLAUSIBLE_RATIO = 0.03


def implausibly_flat(e, prior=None) -> str:
    """Why the ellipsoid ``e`` is thinner than any object of its class ("" if it is not):
    its smallest radius below ``MIN_PLAUSIBLE_RADIUS`` or below ``MIN_PLAUSIBLE_RATIO`` of its
    largest. A class prior (``ClassPrior``, semi-axes a ≥ b ≥ c) that is flatter allows half
    of its own c and c/a: a sheet of paper may be thinner than 3 mm."""
    P = np.asarray(e.P, float)
    r = np.sqrt(np.clip(np.linalg.eigvalsh(0.5 * (P + P.T)), 0.0, None))
    min_r, min_ratio = MIN_PLAUSIBLE_RADIUS, MIN_PLAUSIBLE_RATIO
    if prior is not None:
        c = np.sort(np.asarray(prior.radii, float))
        min_r, min_ratio = min(min_r, 0.5 * c[0]), min(min_ratio, 0.5 * c[0] / c[2])
    if r[0] < min_r or r[0] < min_ratio * r[2]:
        return (f"flat (radii {r[2]:.3g}, {r[1]:.3g}, {r[0]:.3g} m: the smallest below "
                f"{1e3 * min_r:.3g} mm or {min_ratio:.3g} of the largest), thinner than any object "
                "of its class: the boxes do not fix its thickness")
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


def _numpy_ellipsoid(e) -> Ellipsoid:
    return Ellipsoid(np.asarray(e.P, dtype=float), np.asarray(e.center, dtype=float))


def wholly_in_front(e, pose) -> np.ndarray:
    """Whether the ellipsoid ``e`` lies wholly in front (depth > 1 mm) of each camera of
    ``pose`` (R_wc (n, 3, 3), centres (n, 3)); NumPy, so that no program is compiled per
    track length."""
    return np.asarray(in_front(_numpy_ellipsoid(e), pose, 1e-3))

#: A track is spurious when its object, seen whole (in front, its box inside the image) in
#: at least ``MIN_SEEN_FRAMES`` frames, is detected in fewer than this fraction of them: a
#: detector's recall on a real, unoccluded object is far higher (a duplicate of another
#: track, a recurring misclassification, a hallucinated box).
MIN_DETECTION_RATE = 0.1
MIN_SEEN_FRAMES = 30


def detection_rate(ctx, track, e) -> tuple[int, int]:
    """(views of the track, frames of the sequence that see the ellipsoid ``e`` whole)."""
    ctx = as_context(ctx)
    cam = ctx.camera
    pose = ctx.camera_axes
    ok = wholly_in_front(e, pose)
    with np.errstate(divide="ignore", invalid="ignore"):  # boxes of views where it is not in front
        b = np.asarray(project_box(_numpy_ellipsoid(e), pose, cam))
    whole = ok & (b[:, 0] >= 0) & (b[:, 1] >= 0) & (b[:, 2] <= cam.width) & (b[:, 3] <= cam.height)
    return len(track.frames), int(whole.sum())


def drop_rarely_detected(ctx, tracks, init, keep=()):
    """Tracks whose object is detected in too few of the frames that see it
    (``MIN_DETECTION_RATE``): {id: reason}."""
    failed = {}
    for tr in tracks:
        if tr.id not in init or tr.id in keep:
            continue
        views, seen = detection_rate(ctx, tr, init[tr.id])
        if seen >= MIN_SEEN_FRAMES and views < MIN_DETECTION_RATE * seen:
            failed[tr.id] = (f"detected in {views} of the {seen} frames that see it whole "
                             f"({100 * views / seen:.1f}% < {100 * MIN_DETECTION_RATE:.0f}%): "
                             "a spurious or duplicate track")
    return failed


def _drop_invisible(ctx: SequenceContext, tracks, init, notes, min_views, keep=()):
    """Remove views where the initial ellipsoid is not in front of the camera; objects in
    ``keep`` (measured ones) stay even with fewer than ``min_views`` views left."""
    kept, failed = [], {}
    for tr in tracks:
        if tr.id not in init:
            kept.append(tr)
            continue
        R, C = ctx.camera_axes
        ok, note = in_front_views(init[tr.id], (R[tr.frames], C[tr.frames]), tr.id)
        if note:
            notes.append(note)
        if ok.sum() < min_views and tr.id not in keep:
            failed[tr.id] = f"only {int(ok.sum())} views see the initial ellipsoid in front"
            continue
        kept.append(Track(tr.id, tr.label, tr.frames[ok], tr.boxes[ok]))
    return kept, failed


def initialize(ctx, association: RunTracks, method: Method, min_views: int = 3,
               support_planes: str = "priors") -> Initialization:
    """The front end of a run: initial ellipsoids from the boxes, or from an object's
    measured ellipsoids when its boxes do not give one (manual association only), then the
    views that see each initial ellipsoid wholly in front (others are dropped, with a note;
    an object left with fewer than ``min_views`` views is a failure)."""
    ctx = as_context(ctx)
    seq = ctx.seq
    init, failed, notes = initialize_objects(ctx, association.tracks, method, min_views)
    unknown = sorted({tr.label for tr in association.tracks if ctx.class_prior(tr.label) is None})
    if unknown:  # said once per run, whatever the format that read them
        notes.append(f"labels without a class prior, mapped without a size or shape prior: {', '.join(unknown)}")
    measured = measured_objects(ctx)
    rare = drop_rarely_detected(ctx, association.tracks, init, keep=measured)
    failed.update(rare)
    for k in rare:
        init.pop(k)
    planes = None
    if (support_planes == "initial" and method.support_plane and method.initialization == "multi"
            and ctx.up is not None and not ctx.support_planes() and init):
        planes = estimate_support_planes(init, ctx.up)
        if len(planes.planes):
            notes.append(planes_note(planes, ctx.up, "initial"))
            rested = [tr for tr in association.tracks if tr.id in planes.assignment and tr.id in init]
            again, _, _ = initialize_objects(ctx, rested, method, min_views, planes)
            init.update(again)  # an object that no longer fits keeps its first start
        else:
            planes = None
    auto = association.record["mode"] == "auto"
    if auto and seq.ellipsoids:
        # automatic track ids are not instance ids: measurements cannot be attached by id
        notes.append(f"{len(seq.ellipsoids)} measured ellipsoids left out: they are associated "
                     "by instance id only, and the boxes were associated automatically")
        measured = {}
    for k, ms in measured.items():
        if k not in init:
            try:
                e = initialize_from_measurements(ctx, ms)
                bad = degenerate(e, min_radius=0.0, min_ratio=SINGULAR_RATIO)
            except OBJECT_ERRORS as err:
                bad = f"{type(err).__name__}: {err}"
            if bad:
                failed[k] = f"initialisation from its {len(ms)} measured ellipsoids: {bad}"
                continue
            init[k] = e
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
    return Initialization(tracks, init, measured, failed, notes, planes)


def nesting_depths(ellipsoids) -> np.ndarray:
    """D[i, j] = max(dᵀ P_i⁻¹ d, dᵀ P_j⁻¹ d) with d = t_j − t_i, for a list of ellipsoids
    (P, t): below 1 when each centre lies inside the other ellipsoid. ``inf`` on the
    diagonal and in the row and column of an ellipsoid whose P is not finite or not
    positive definite (a collapsed object nests in nothing and nothing nests in it)."""
    n = len(ellipsoids)
    D = np.full((n, n), np.inf)
    if n < 2:
        return D
    P = np.stack([np.asarray(e.P, float) for e in ellipsoids])
    C = np.stack([np.asarray(e.center, float) for e in ellipsoids])
    ok = np.all(np.isfinite(P), axis=(1, 2)) & np.all(np.isfinite(C), axis=1)
    w = np.zeros((n, 3))
    w[ok] = np.linalg.eigvalsh(0.5 * (P[ok] + np.swapaxes(P[ok], 1, 2)))
    ok &= w[:, 0] > np.finfo(float).eps * np.abs(w[:, 2])
    i = np.flatnonzero(ok)
    if i.size < 2:
        return D
    Pinv = np.linalg.inv(P[i])
    d = C[i][None, :, :] - C[i][:, None, :]  # d[a, b] = t_b − t_a
    into_a = np.einsum("abj,ajk,abk->ab", d, Pinv, d)  # b's centre in a
    sub = np.maximum(into_a, into_a.T)
    np.fill_diagonal(sub, np.inf)
    D[np.ix_(i, i)] = sub
    return D


def overlapping_duplicates(ellipsoids: dict, labels: dict, views: dict, among=None) -> list:
    """Pairs (kept, merged) of objects that are one object mapped twice: the same label
    (``labels`` {id: label}) and each centre inside the other's ellipsoid (``nesting_depths``
    < 1). Each object is in at most one pair; the most deeply nested pair first; the object
    with more views (``views`` {id: count}; the smaller id on a tie) is kept. ``among``: only
    pairs with one of these objects (the online mapper's window). A collapsed object (P
    singular or not finite) is in no pair. The batch run and the online mapper both merge by
    this rule."""
    ids = sorted(k for k in ellipsoids if k in labels)
    D = nesting_depths([ellipsoids[k] for k in ids])
    lab = np.array([str(labels[k]) for k in ids])
    near = np.triu((D < 1.0) & (lab[:, None] == lab[None, :]), 1)
    if among is not None:
        window = set(among)
        mine = np.array([k in window for k in ids], dtype=bool)
        near &= mine[:, None] | mine[None, :]
    pairs = sorted((float(D[i, j]), ids[i], ids[j]) for i, j in zip(*np.nonzero(near)))
    out, used = [], set()
    for _, a, b in pairs:
        if a in used or b in used:
            continue
        used |= {a, b}
        out.append((a, b) if views[a] >= views[b] else (b, a))
    return out


def in_front_views(e, axes, k) -> tuple[np.ndarray, str | None]:
    """Which views see the initial ellipsoid ``e`` of object ``k`` wholly in front (cameras
    ``axes``: (R_wc, centres)), and the note that says how many do not (None: all do): the
    views a batch run and the online mapper keep."""
    ok = wholly_in_front(e, axes)
    if ok.all():
        return ok, None
    return ok, (f"object {k}: {int((~ok).sum())} of {ok.size} views dropped (the initial ellipsoid is not "
                "wholly in front of the camera there)")


def merged_track(keep: Track, drop: Track) -> Track:
    """``keep``'s boxes and ``drop``'s boxes in the frames where ``keep`` has none."""
    extra = ~np.isin(drop.frames, keep.frames)
    frames = np.concatenate([keep.frames, drop.frames[extra]])
    boxes = np.concatenate([keep.boxes, drop.boxes[extra]])
    order = np.argsort(frames, kind="stable")
    return Track(keep.id, keep.label, frames[order], boxes[order])


def merged_tracks(tracks: list, landmarks: dict, pairs) -> tuple[list, list]:
    """(``tracks`` with each pair's joined (``merged_track``), a note per pair); the merged
    object is dropped from ``landmarks`` (in place)."""
    by_id = {tr.id: tr for tr in tracks}
    gone = {drop for _, drop in pairs}
    for keep, drop in pairs:
        by_id[keep] = merged_track(by_id[keep], by_id[drop])
        landmarks.pop(drop)
    notes = [f"objects {keep} and {drop} ({by_id[keep].label}) are one object: after the optimisation "
             f"each centre lay inside the other ellipsoid; {drop}'s boxes joined to {keep}" for keep, drop in pairs]
    return [by_id[tr.id] for tr in tracks if tr.id not in gone], notes


def merge_duplicates(front: Initialization, landmarks: dict, pairs) -> Initialization:
    """``front`` with each pair's tracks joined and the merged object dropped from
    ``landmarks`` (in place; ``merged_tracks``); a note per pair."""
    tracks, notes = merged_tracks(front.tracks, landmarks, pairs)
    return dataclasses.replace(front, tracks=tracks, notes=front.notes + notes)


def planes_note(planes: SupportPlanes, up, source: str) -> str:
    counts = np.bincount(list(planes.assignment.values()), minlength=len(planes.planes))
    tilt = np.degrees(np.arccos(np.clip(planes.planes[0, :3] @ np.asarray(up), -1.0, 1.0)))
    each = ", ".join(f"height {-p[3]:.3f} m ({n} objects)" for p, n in zip(planes.planes, counts))
    return (f"support planes estimated from the {source} objects: {each}; the first one's "
            f"normal is {tilt:.2f}° from up")


# --- the run ----------------------------------------------------------------------------------


def as_landmark(e: Ellipsoid, method: Method):
    if method.parameterization == "spd":
        return e
    if method.parameterization == "full":
        return EllipsoidFull.from_ellipsoid(e)
    R, s = (np.asarray(a) for a in e.axes())
    return EllipsoidRTS.from_axes(R, np.asarray(e.center), s)


@dataclass
class Optimised:
    """A run's optimisations so far: the last graph and its result (``OptimizationResult``,
    or anything with ``final_cost``, ``converged`` and ``reason``), the values it ended at,
    the LM iterations of all of them, the cost before the first, and the keys held fixed."""

    values: Any
    graph: Any = None
    result: Any = None
    iterations: int = 0
    initial_cost: float | None = None
    fixed: list = field(default_factory=list)

    def add(self, graph, result) -> None:
        """One more optimisation of ``graph``, which ended with ``result``."""
        self.graph, self.result, self.values = graph, result, result.values
        self.iterations += result.iterations
        if self.initial_cost is None:
            self.initial_cost = result.initial_cost


def recording_names(seq) -> list:
    """The names of the recordings a sequence holds: its own, or for a sequence joined from
    several (``Sequence.segments``) the parts of its name joined by "+" (``joined_sequence``),
    else "NAME (k)"."""
    n = len(seq.segments) + 1
    parts = seq.name.split("+")
    if n == 1:
        return [seq.name]
    return parts if len(parts) == n else [f"{seq.name} ({k + 1})" for k in range(n)]


def observed_by(result: MapResult, tracks, seq) -> MapResult:
    """``result`` with each object's ``observed_by``: ((recording, frames), …), in how many
    frames of each recording of ``seq`` (``recording_names``) its track has a box
    (recordings without one left out)."""
    names = recording_names(seq)
    starts = np.r_[0, np.asarray(seq.segments, int)]
    seen = {}
    for tr in tracks:
        part = np.searchsorted(starts, np.unique(np.asarray(tr.frames, int)), side="right") - 1
        counts = np.bincount(part, minlength=len(names))
        seen[tr.id] = tuple((names[k], int(c)) for k, c in enumerate(counts) if c)
    return dataclasses.replace(result, objects=[dataclasses.replace(o, observed_by=seen.get(o.id))
                                                for o in result.objects])


def map_result(method: Method, solved: Optimised, labels: dict, initial: dict, timestamps,
               failed: dict, priors=None, given_poses: bool = False) -> MapResult:
    """The ``MapResult`` of a run's optimisations ``solved``: the objects L(id) of ``labels``
    {id: label} in its values with their uncertainty (``mapped_uncertainty``), each checked
    (``object_quality``) and those that fail it moved to ``failed``; the poses X(0…) as TUM
    rows with ``timestamps``; ``initial`` {id: Ellipsoid} the front end's objects. The
    caller adds the run's notes and association record.
    ``given_poses`` (a trajectory without a bound on each pose): the check reads each object's
    uncertainty given the cameras (every pose held), as the marginal then holds the
    odometry's random walk since the first pose, which grows with the time from it whatever
    the boxes fix; the objects keep their marginal uncertainty."""
    graph, values, res, fixed = solved.graph, solved.values, solved.result, solved.fixed
    ids = sorted(k for k in labels if L(k) in values)
    with step("uncertainty"):
        spread = mapped_uncertainty(graph, values, ids, fixed, res)
        judged = spread
        if given_poses and ids:
            judged = mapped_uncertainty(graph, values, ids, [X(i) for i in range(len(timestamps))])
    objects = [MapObject(k, labels[k], as_ellipsoid(values[L(k)]), spread.get(k)) for k in ids]
    first = [MapObject(k, labels[k], initial[k]) for k in sorted(initial)]
    rows = np.stack([to_tum(values[X(i)]) for i in range(len(timestamps))])
    poses_out = np.c_[np.asarray(timestamps), rows]
    failed = dict(failed)
    kept = []
    for o in objects:  # reported, not mapped: an object whose extent the data do not fix
        why = object_quality(dataclasses.replace(o, uncertainty=judged.get(o.id)), class_prior(priors, o.label))
        if why:
            failed[o.id] = why
        else:
            kept.append(o)
    return MapResult(
        method=method, objects=kept, initial_objects=first, poses_tum=poses_out,
        iterations=solved.iterations,
        initial_cost=res.final_cost if solved.initial_cost is None else solved.initial_cost,
        final_cost=res.final_cost, converged=res.converged, reason=res.reason, failed=failed,
        costs=cost_by_factor(graph, values, res),
    )


def object_quality(o: MapObject, prior=None) -> str:
    """Why an optimised object is not mapped ("" if it is): degenerate (``degenerate``),
    thinner than any of its class (``implausibly_flat``, with its ``ClassPrior``), or poorly
    observed (``poorly_observed``, from its uncertainty)."""
    try:
        why = degenerate(o.ellipsoid)
        if why:
            return f"degenerate after the optimisation ({why}): the boxes do not fix its extent"
        flat = implausibly_flat(o.ellipsoid, prior)
        if flat:
            return f"poorly observed: {flat}"
        seen = poorly_observed(o.uncertainty)
        return f"poorly observed ({seen})" if seen else ""
    except OBJECT_ERRORS as err:
        return f"quality check: {type(err).__name__}: {err}"


def _reusable(result, values) -> bool:
    """Whether ``result`` is an ``OptimizationResult`` that ended at ``values`` (and so holds
    the problem and last linearisation there)."""
    return getattr(result, "_final", None) is not None and getattr(result, "values", None) is values


def cost_by_factor(graph, values, result=None) -> dict:
    """{factor kind: its part of the cost at ``values``}, in the graph's order of kinds;
    ``result``: the optimisation of ``graph`` that ended at ``values`` (its final problem is
    reused: ``OptimizationResult.cost_by_kind``)."""
    if _reusable(result, values):
        return result.cost_by_kind()
    kinds: dict = {}
    for f in graph:
        kinds.setdefault(f.kind, []).append(f)
    return {k: float(NonlinearFactorGraph(fs).error(values)) for k, fs in kinds.items()}
