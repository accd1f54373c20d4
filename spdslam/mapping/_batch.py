"""Object SLAM on a sequence in one batch, the paper's Table III pipeline: ``run_sequence``
composes the steps (``_run``), each inside ``step(name)`` (docs/core.md draws them):

    RunSettings                    every setting, checked before any work (``_settings``)
    → keyframes, screening         ``select_keyframes``, ``frontend.screen_detections``
    → the poses (``RunSettings.initial_poses``), on a trajectory without a bound on each pose:
        auto, loops                the objects mapped on the input poses held (``_map``), then
                                   ``close_loops`` (``_loops``): submaps, verified loops, a
                                   pose graph; the objects mapped again on the corrected
                                   poses held. The boxes do not move the poses.
        input                      the joint optimisation from the input poses, each pose as
                                   free as the odometry lets it (the boxes move the poses)
        incremental                ``replayed_start``: the frames through the online mapper
                                   first, the poses the optimisation starts from, its objects
                                   and, with automatic association, its tracks
    → _map: associate_tracks(ctx, …)  Association: tracks and how they were made
          → initialize(ctx, …)     Initialization: initial ellipsoids, the views that see
                                   them, failures and notes
          → correct_drift          knots fitted to the boxes (``drift_interval``)
          → build_graph(ctx, …)    the factor graph (``_graph``), with Values
          → optimisation           LM per box-model stage, accumulated in ``Optimised``
          → duplicates             ``overlapping_duplicates`` (automatic association)
          → map_result             uncertainty, each object's quality, ``MapResult``

Every trajectory a step proposes on a trajectory without a bound on each pose (a replay, a
drift correction, a loop closure, the joint optimisation) is checked against the odometry's
walk (``check_trajectory``): one that departs further than the odometry can have drifted is
refused, the step keeps the poses it started from, and the notes and map.json's
``trajectory`` say so.

A failure confined to one object moves it to ``failed`` (``OBJECT_ERRORS``); one of the
whole problem is a ``MappingError`` naming the step.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Callable

import jaxlie
import numpy as np

from ..frontend import Track, estimate_support_planes, screen_detections
from ..geometry import as_ellipsoid
from ..geometry.se3 import to_tum
from ..io import MapObject, Sequence, without_class_table
from ..solver import L, LevenbergMarquardt, NonlinearFactorGraph, Values, X
from ._context import SequenceContext
from ._drift import correct_drift
from ._graph import build_graph, mapping_sigmas, object_factors, trajectory_noise_note, with_robust_by_type
from ._keyframes import parse_keyframes, select_keyframes
from ._loops import close_loops
from ._methods import Method, robust_kernel
from ._odometry import absolute_sigma, check_trajectory, walk_covariances
from ._online import replayed_start
from ._run import (
    OBJECT_ERRORS,
    MapResult,
    Optimised,
    as_landmark,
    associate_tracks,
    degenerate,
    initialize,
    map_result,
    merge_duplicates,
    object_uncertainty,
    overlapping_duplicates,
    planes_note,
    step,
)
from ._settings import InitialPoses, RunSettings, SettingsError, as_settings, default_association

__all__ = ["run_sequence", "stretch_objects"]

def run_sequence(
    seq: Sequence,
    method: str | Method | RunSettings = "multi-spd",
    *,
    tracks=None,
    verbose: bool = False,
    progress: Callable[[str], Any] | None = None,
    **settings,
) -> MapResult:
    """Initialise and jointly optimise a sequence in one batch. ``method``: the run's
    :class:`RunSettings`, or a name of ``METHODS`` (or a :class:`Method`) with ``settings``,
    the keywords of ``RunSettings.of`` (its fields, and ``Method`` fields as overrides, e.g.
    ``parameterization="rts"``); all are checked before any work starts.

    The steps (``step``; module docstring): keyframes (``select_keyframes``; the result's
    trajectory has those frames only), screening (``frontend.screen_detections``, unless
    ``screen=False`` or ``tracks`` are given), where the poses come from on a drifting
    trajectory (``RunSettings.initial_poses``: loops closed between submaps, a replay
    through the online mapper, or the input), association (``associate_tracks``: ``tracks``
    when given, else by instance ids or automatically), initialisation (``initialize``), the
    graph (``build_graph``) and its optimisation per box-model stage, support planes
    estimated from the optimised objects (``support_planes="optimised"``, then optimised
    again), duplicates merged (automatic association: ``overlapping_duplicates``, then
    optimised again), and the result (``map_result``: uncertainty and each object's
    quality). A failure confined to one object moves it to ``failed``; one of the whole
    problem is a ``MappingError`` naming the step. ``progress(message)`` is called at each
    step and after each LM iteration. A method's ``robust="auto"`` is resolved by the
    association (``Method.resolved``)."""
    say = progress or (lambda message: None)
    run = as_settings(method, settings)
    if run.online is not None:
        raise SettingsError("online", "run_sequence maps in one batch; an online run is run_online's")
    if not run.class_table:
        seq = without_class_table(seq)
    if parse_keyframes(run.keyframes) != "all":
        if tracks is not None:
            raise ValueError("keyframes other than 'all' need the run's own association (tracks index frames)")
        with step("keyframes"):
            kept = select_keyframes(seq.poses_tum, run.keyframes)
        say(f"keyframes ({run.keyframes}): {kept.size} of {len(seq)} frames")
        seq = seq.subset(kept)
    screened = None
    if run.screen and tracks is None:
        with step("screening"):
            screened = screen_detections(seq, run.method.margin)
        seq = screened.sequence
        say(screened.summary())
    first = [] if screened is None or not screened.counts() else [screened.summary()]
    ctx = SequenceContext.of(seq)
    with step("association"):
        s = mapping_sigmas(ctx, dict(run.sigma))
    start = run.start(absolute_sigma(s) is None)
    mapper = _Mapper(seq, tracks, verbose, progress, first)
    if start == InitialPoses.INPUT or start == InitialPoses.INCREMENTAL:
        return mapper.map(run).result
    return _drifting(mapper, ctx, s, run, say)


def _drifting(mapper: "_Mapper", ctx: SequenceContext, s: dict, run: RunSettings, say) -> MapResult:
    """A trajectory without a bound on each pose, ``initial_poses`` auto or loops (module
    docstring): the boxes do not move the poses; the drift is taken out by loops only."""
    held_run = run.replace(hold_trajectory=True, initial_poses=InitialPoses.INPUT)
    say("objects on the input poses, held")
    held = mapper.map(held_run, hold_note="trajectory held at the input poses (no bound on each pose: the boxes "
                                          "do not move the poses; loops closed by the objects do)")
    with step("loop closure"):
        closure = close_loops(ctx, s, lambda stretches: stretch_objects(held, stretches), say)
    if closure.verified:
        corrected = dataclasses.replace(mapper.seq, poses_tum=to_tum(jaxlie.SE3(closure.poses)))  # type: ignore[arg-type]
        say("objects on the corrected poses, held")
        result = mapper.map(held_run, seq=corrected, hold_note="trajectory held at the poses the loop closure "
                                                               "corrected").result
    else:
        result = held.result
    notes = list(result.notes)
    at = len(mapper.first_notes) + 1  # after the screening's and the trajectory's notes
    notes[at:at] = closure.notes()
    trajectory = {"start": "loops", "loop_closure": closure.as_dict(),
                  "checks": [] if closure.check is None else [closure.check.as_dict()]}
    return dataclasses.replace(result, notes=notes, trajectory=trajectory)


def stretch_objects(mapped: "_Mapped", stretches: list) -> list:
    """The objects of each stretch (first, last frame) of a run mapped with its poses held
    (``mapped``), each from that stretch's boxes alone (``MapObject`` s with the track's id
    and their marginal uncertainty; a stretch's object needs ``min_views`` of its boxes
    there; degenerate ones are left out): every stretch's objects in one optimisation with
    the poses held, each started from the run's estimate of it."""
    ctx, method, s = mapped.ctx, mapped.method, mapped.sigmas
    robust = robust_kernel(method.robust, method.robust_k)
    stage = "inverse" if method.box_model == "semi-then-inverse" else method.box_model
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
            factors += object_factors(ctx, part, mapped.landmarks[tr.id], method, stage, s, robust, mapped.planes)
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


@dataclass(frozen=True)
class _Mapped:
    """A batch mapping's result and what later steps read of it: its context, its tracks
    and final landmarks {id: value}, the method, sigmas, estimated planes, ``min_views`` and
    the LM budget."""

    result: MapResult
    ctx: SequenceContext
    tracks: list
    landmarks: dict
    method: Method
    sigmas: dict
    planes: Any
    min_views: int
    max_iterations: int


@dataclass
class _Mapper:
    """The batch mapping of one (screened) sequence (``map``), with the run's given tracks,
    verbosity, progress and the notes that come first (the screening's)."""

    seq: Sequence
    tracks: Any
    verbose: bool
    progress: Callable | None
    first_notes: list

    def map(self, run: RunSettings, seq: Sequence | None = None, hold_note: str | None = None) -> _Mapped:
        """The steps association … result (module docstring) of ``seq`` (default the run's)
        with ``run``'s settings; ``hold_note``: the note of a held trajectory."""
        return _map(self.seq if seq is None else seq, run, self.tracks, self.verbose, self.progress,
                    self.first_notes, hold_note)


def _map(seq: Sequence, run: RunSettings, tracks, verbose: bool, progress, first_notes: list,
         hold_note: str | None = None) -> _Mapped:
    method, support_planes = run.method, run.support_planes
    sigmas, min_views, hold_trajectory = dict(run.sigma), run.min_views, run.hold_trajectory
    associate = None if run.associate is None else str(run.associate)
    max_iterations, tolerance = run.max_iterations, run.tolerance
    say = progress or (lambda message: None)
    with step("association"):
        ctx = SequenceContext.of(seq)
        mode = "given" if tracks is not None else str(associate or default_association(seq))
    method = method.resolved(mode == "auto")
    replay = run.initial_poses == InitialPoses.INCREMENTAL
    in_use = mapping_sigmas(ctx, sigmas)
    unbounded = absolute_sigma(in_use) is None
    walk = walk_covariances(ctx.wxyz_xyz, in_use, seq.segments) if unbounded and not hold_trajectory else None
    checks: list = []
    start, fallback = None, None

    def replay_from(given):
        """The replay's start (``replayed_start``), or None and a note when it failed on numbers
        or moved the poses further than the odometry can have drifted."""
        say(f"incremental initialisation: {len(seq)} frames through the online mapper")
        with step("incremental initialisation"):
            try:
                got = replayed_start(seq, given, run.replace(method=method), say)
            except OBJECT_ERRORS as e:  # the replay is a better start, never a reason to fail the run
                why = (f"incremental initialisation failed ({type(e).__name__}: {e}): the optimisation "
                       "starts from the input poses")
                say(why)
                return None, why
        if walk is not None:
            check = check_trajectory("incremental initialisation", ctx.wxyz_xyz, got.poses, walk)
            checks.append(check)
            if not check.accepted:
                say(check.note())
                return None, check.note()
        return got, None

    if replay and mode == "auto" and seq.detections:  # the online tracker associates on the corrected poses
        start, fallback = replay_from(None)
    with step("association"):
        say(f"association: {len(seq.detections)} detections in {len(seq)} frames")
        association = associate_tracks(ctx, tracks, associate, found=None if start is None else start.tracks)
    say(f"association: {len(association.tracks)} tracks ({association.record.get('mode', 'given')})")
    if replay and mode != "auto" and association.tracks:
        start, fallback = replay_from(association.tracks)
    with step("initialisation"):
        init_ctx = ctx if start is None else SequenceContext.of(dataclasses.replace(seq, poses_tum=to_tum(
            jaxlie.SE3(start.poses))))  # type: ignore[arg-type]
        front = initialize(init_ctx, association, method, min_views, support_planes)
        notes = list(first_notes)
        notes.append((hold_note or "trajectory held at the input poses") if hold_trajectory
                      else trajectory_noise_note(ctx, sigmas))
        if start is not None:
            replayed = {k: v for k, v in start.landmarks.items() if k in front.ellipsoids}
            front.ellipsoids.update({k: as_ellipsoid(v) for k, v in replayed.items()})
            moved = np.linalg.norm(start.poses[:, 4:] - ctx.wxyz_xyz[:, 4:], axis=1)
            notes.append(f"incremental initialisation (the frames replayed through the online mapper first): "
                         f"cameras moved by {1e3 * np.median(moved):.4g} mm median, {1e3 * np.max(moved):.4g} mm "
                         f"most; {len(replayed)} of {len(front.ellipsoids)} objects from the replay")
        if fallback is not None:
            notes.append(fallback)
        front = dataclasses.replace(front, notes=notes + front.notes)
    say(front.notes[len(first_notes)])
    say(f"initialisation: {len(front.ellipsoids)} objects, {len(front.failed)} not initialised")

    landmarks = {k: as_landmark(e, method) for k, e in front.ellipsoids.items()}
    drift = None
    if not hold_trajectory and run.drift_interval > 0 and landmarks:
        with step("drift correction"):
            s = mapping_sigmas(ctx, sigmas)
            drift = None
            if np.isinf(s["absolute_translation"]) and np.isinf(s["absolute_rotation"]):
                say(f"drift correction: knots about {run.drift_interval:g} s apart")
                drift = correct_drift(ctx, front.tracks, landmarks, method, s, run.drift_interval, front.planes,
                                      max_iterations, tolerance)
            else:
                front.notes.append("no drift correction: the trajectory has a bound on each pose "
                                   "(trajectory_absolute_sigma)")
        if drift is not None and walk is not None:
            check = check_trajectory("drift correction", ctx.wxyz_xyz,
                                     SequenceContext.of(dataclasses.replace(seq, poses_tum=drift.poses_tum)).wxyz_xyz,
                                     walk)
            checks.append(check)
            if not check.accepted:
                front.notes.append(check.note())
                say(front.notes[-1])
                drift = None
        if drift is not None:
            seq = dataclasses.replace(seq, poses_tum=drift.poses_tum)
            ctx = SequenceContext.of(seq)
            sigmas = {**sigmas, "absolute_translation": float(drift.bound[0]),
                      "absolute_rotation": float(drift.bound[3])}
            landmarks.update(drift.landmarks)
            front.notes.append(drift.note())
            say(front.notes[-1])
    values = Values()
    start_poses = ctx.wxyz_xyz if start is None else start.poses
    for i, T in enumerate(start_poses):
        values[X(i)] = jaxlie.SE3(T)
    for k, lm in landmarks.items():
        values[L(k)] = lm
    stages = ["semi", "inverse"] if method.box_model == "semi-then-inverse" else [method.box_model]

    def each_iteration(rec):
        say(f"LM iteration {rec.iteration}: cost {rec.cost:.6g} "
            f"({'accepted' if rec.accepted else 'rejected'}, {'Δ' if rec.radius else 'λ'} {rec.damping:.2g})")

    optimizer = LevenbergMarquardt(max_iterations=max_iterations, verbose=verbose,
                                   relative_tolerance=tolerance,
                                   callback=each_iteration if progress else None)
    fixed = [X(i) for i in range(len(ctx.poses))] if hold_trajectory else []
    solve = Optimised(values=values, fixed=fixed)
    planes = front.planes
    made: dict = {}  # box factors per track, across this run's graphs (build_graph's reuse)

    def optimise(stage: str, what: str) -> dict:
        """The graph of the current tracks, landmarks and planes, optimised: the landmarks."""
        with step("graph"):
            graph = build_graph(ctx, front.tracks, landmarks, method, stage, sigmas, front.measured,
                                planes, odometry=not solve.fixed, reuse=made)
        say(f"optimisation ({what}): {len(solve.values)} variables, {len(graph)} factors")
        with step(f"optimisation ({what})"):
            solve.add(graph, optimizer.optimize(graph, solve.values, fixed=solve.fixed))
        return {k: solve.values[L(k)] for k in landmarks}

    for stage in stages:
        landmarks = optimise(stage, f"{stage} boxes")
    if (support_planes == "optimised" and method.support_plane and ctx.up is not None
            and not ctx.support_planes() and landmarks):
        with step("support planes"):
            estimated = estimate_support_planes({k: as_ellipsoid(v) for k, v in landmarks.items()}, ctx.up)
        if len(estimated.planes):
            planes = estimated
            front.notes.append(planes_note(planes, ctx.up, "optimised"))
            landmarks = optimise(stages[-1], "with the estimated support planes")

    labels = {tr.id: tr.label for tr in front.tracks}  # the front end's objects, merged or not
    if association.record.get("mode") == "auto":  # instance ids are trusted as given
        with step("duplicates"):
            pairs = overlapping_duplicates({k: as_ellipsoid(v) for k, v in landmarks.items()},
                                           front.tracks)
            if pairs:
                front = merge_duplicates(front, landmarks, pairs)
                gone = {L(d) for _, d in pairs}
                solve.values = Values({k: v for k, v in solve.values.items() if k not in gone})
        if pairs:
            landmarks = optimise(stages[-1], f"after merging {len(pairs)} duplicate objects")

    if walk is not None:  # the joint optimisation moved the poses: no further than the odometry allows
        final = np.stack([np.asarray(solve.values[X(i)].wxyz_xyz) for i in range(len(ctx.poses))])
        check = check_trajectory("the joint optimisation", ctx.wxyz_xyz, final, walk)
        checks.append(check)
        if not check.accepted:
            front.notes.append(check.note())
            say(front.notes[-1])
            for i, T in enumerate(start_poses):
                solve.values[X(i)] = jaxlie.SE3(T)
            solve.fixed = [X(i) for i in range(len(ctx.poses))]
            landmarks = optimise(stages[-1], "with the poses held where it started")

    say("uncertainty: marginal covariances of the objects")
    given = not solve.fixed and unbounded
    with step("result"):
        result = map_result(method, solve, labels, front.ellipsoids, seq.timestamps, front.failed,
                            front.notes, association.record, priors=ctx.priors, given_poses=given)
    if unbounded:
        start_name = "held" if hold_trajectory else ("incremental" if start is not None else "input")
        result = dataclasses.replace(result, trajectory={"start": start_name, "checks": [c.as_dict() for c in checks]})
    if drift is not None:  # the sigmas of the corrected trajectory's graph
        in_use = mapping_sigmas(ctx, sigmas)
    return _Mapped(result, ctx, front.tracks, {k: solve.values[L(k)] for k in landmarks}, method,
                   in_use, planes, min_views, max_iterations)
