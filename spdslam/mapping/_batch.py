"""Object SLAM on a sequence in one batch, the paper's Table III pipeline: ``run_sequence``
composes the steps (``_run``), each inside ``step(name)`` (docs/core.md draws them):

    RunSettings                    every setting, checked before any work (``_settings``)
    → keyframes, screening         ``select_keyframes``, ``frontend.screen_detections``
    → associate_tracks(ctx, …)     Association: tracks and how they were made
    → replayed_start(seq, …)       a drifting trajectory (``RunSettings.initial_poses``): the
                                   frames through the online mapper first (``_online``), the
                                   poses the optimisation starts from, its objects, and with
                                   automatic association its tracks, made on those poses
    → initialize(ctx, …)           Initialization: initial ellipsoids, the views that see
                                   them, failures and notes
    → correct_drift                knots fitted to the boxes (``drift_interval``)
    → build_graph(ctx, …)          the factor graph (``_graph``), with Values
    → optimisation                 LM per box-model stage, accumulated in ``Optimised``
    → duplicates                   ``overlapping_duplicates`` (automatic association)
    → map_result                   uncertainty, each object's quality, ``MapResult``

A failure confined to one object moves it to ``failed`` (``OBJECT_ERRORS``); one of the
whole problem is a ``MappingError`` naming the step.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import jaxlie
import numpy as np

from ..frontend import estimate_support_planes, screen_detections
from ..geometry import as_ellipsoid
from ..geometry.se3 import to_tum
from ..io import Sequence, without_class_table
from ..solver import L, LevenbergMarquardt, Values, X
from ._context import SequenceContext, as_context
from ._drift import correct_drift
from ._graph import absolute_sigma, build_graph, mapping_sigmas, trajectory_noise_note
from ._keyframes import parse_keyframes, select_keyframes
from ._methods import Method
from ._online import replayed_start
from ._run import (
    OBJECT_ERRORS,
    MapResult,
    Optimised,
    as_landmark,
    associate_tracks,
    initialize,
    map_result,
    merge_duplicates,
    overlapping_duplicates,
    planes_note,
    step,
)
from ._settings import REPLAY_MIN_SPREAD, RunSettings, SettingsError, as_settings, default_association

__all__ = ["odometry_spread", "run_sequence"]


def odometry_spread(ctx, sigmas: dict | None = None) -> tuple[float, float] | None:
    """The odometry's random walk over the recording (a ``Sequence`` or its context),
    √(F − 1) (σ_t, σ_r) (m, rad) with the run's step σ (``mapping_sigmas``), on a trajectory
    without a bound on each pose; None with one."""
    ctx = as_context(ctx)
    s = mapping_sigmas(ctx, sigmas)
    if absolute_sigma(s) is not None:
        return None
    n = np.sqrt(max(len(ctx.seq) - 1, 1))
    return float(n * s["odometry_translation"]), float(n * s["odometry_rotation"])


def spread_drifts(spread: tuple[float, float]) -> bool:
    """Whether an odometry with this walk over the recording may have drifted enough for a
    replay to pay (``REPLAY_MIN_SPREAD``)."""
    return spread[0] > REPLAY_MIN_SPREAD[0] or spread[1] > REPLAY_MIN_SPREAD[1]


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

    The steps (``step``): keyframes (``select_keyframes``; the result's trajectory has those
    frames only), screening (``frontend.screen_detections``, unless ``screen=False`` or
    ``tracks`` are given), association (``associate_tracks``: ``tracks`` when given, else
    by instance ids or automatically), on a drifting trajectory the frames replayed through
    the online mapper (``RunSettings.initial_poses``, ``replayed_start``: the poses the
    optimisation starts from, its objects, and with automatic association its tracks, made
    on those poses), initialisation (``initialize``), the graph
    (``build_graph``) and its optimisation per box-model stage, support planes estimated
    from the optimised objects (``support_planes="optimised"``, then optimised again),
    duplicates merged (automatic association: ``overlapping_duplicates``, then optimised
    again), and the result (``map_result``: uncertainty and each object's quality). A
    failure confined to one object moves it to ``failed``; one of the whole problem is a
    ``MappingError`` naming the step. ``progress(message)`` is called at each step and after
    each LM iteration. A method's ``robust="auto"`` is resolved by the association
    (``Method.resolved``)."""
    say = progress or (lambda message: None)
    run = as_settings(method, settings)
    if run.online is not None:
        raise SettingsError("online", "run_sequence maps in one batch; an online run is run_online's")
    if not run.class_table:
        seq = without_class_table(seq)
    method, keyframes, support_planes = run.method, run.keyframes, run.support_planes
    sigmas, min_views, hold_trajectory = dict(run.sigma), run.min_views, run.hold_trajectory
    associate = None if run.associate is None else str(run.associate)
    max_iterations, tolerance, screen = run.max_iterations, run.tolerance, run.screen
    if parse_keyframes(keyframes) != "all":
        if tracks is not None:
            raise ValueError("keyframes other than 'all' need the run's own association (tracks index frames)")
        with step("keyframes"):
            kept = select_keyframes(seq.poses_tum, keyframes)
        say(f"keyframes ({keyframes}): {kept.size} of {len(seq)} frames")
        seq = seq.subset(kept)
    screened = None
    if screen and tracks is None:
        with step("screening"):
            screened = screen_detections(seq, method.margin)
        seq = screened.sequence
        say(screened.summary())
    with step("association"):
        ctx = SequenceContext.of(seq)
        mode = "given" if tracks is not None else str(associate or default_association(seq))
    method = method.resolved(mode == "auto")
    spread = odometry_spread(ctx, sigmas)
    replay = run.starts_incremental(spread is not None and spread_drifts(spread))
    start, fallback = None, None

    def replay_from(given):
        """The replay's start (``replayed_start``), or None and a note when it failed on numbers."""
        say(f"incremental initialisation: {len(seq)} frames through the online mapper")
        with step("incremental initialisation"):
            try:
                return replayed_start(seq, given, run.replace(method=method), say), None
            except OBJECT_ERRORS as e:  # the replay is a better start, never a reason to fail the run
                why = (f"incremental initialisation failed ({type(e).__name__}: {e}): the optimisation "
                       "starts from the input poses")
                say(why)
                return None, why

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
        front.notes.insert(0, "trajectory held at the input poses" if hold_trajectory
                           else trajectory_noise_note(ctx, sigmas))
        if start is not None:
            replayed = {k: v for k, v in start.landmarks.items() if k in front.ellipsoids}
            front.ellipsoids.update({k: as_ellipsoid(v) for k, v in replayed.items()})
            moved = np.linalg.norm(start.poses[:, 4:] - ctx.wxyz_xyz[:, 4:], axis=1)
            front.notes.insert(1, f"incremental initialisation (the frames replayed through the online "
                               f"mapper first): cameras moved by {1e3 * np.median(moved):.4g} mm median, "
                               f"{1e3 * np.max(moved):.4g} mm most; {len(replayed)} of "
                               f"{len(front.ellipsoids)} objects from the replay")
    if fallback is not None:
        front.notes.insert(1, fallback)
    elif (start is None and spread is not None and spread_drifts(spread) and run.initial_poses == "auto"
          and not hold_trajectory and run.drift_interval == 0 and association.tracks):
        front.notes.insert(1, f"started from the input poses, though the odometry may have drifted over the "
                           f"recording (√(F − 1) σ_step: {1e3 * spread[0]:.3g} mm, {np.degrees(spread[1]):.3g}°): "
                           f"{method.name} does not map online (initial_poses)")
    if screened is not None and screened.counts():
        front.notes.insert(1, screened.summary())
    say(front.notes[0])
    say(f"initialisation: {len(front.ellipsoids)} objects, {len(front.failed)} not initialised")

    landmarks = {k: as_landmark(e, method) for k, e in front.ellipsoids.items()}
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
        if drift is not None:
            seq = dataclasses.replace(seq, poses_tum=drift.poses_tum)
            ctx = SequenceContext.of(seq)
            sigmas = {**sigmas, "absolute_translation": float(drift.bound[0]),
                      "absolute_rotation": float(drift.bound[3])}
            landmarks.update(drift.landmarks)
            front.notes.append(drift.note())
            say(front.notes[-1])
    values = Values()
    for i, T in enumerate(ctx.poses if start is None else [jaxlie.SE3(p) for p in start.poses]):  # type: ignore[arg-type]
        values[X(i)] = T
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
                                planes, odometry=not hold_trajectory, reuse=made)
        say(f"optimisation ({what}): {len(solve.values)} variables, {len(graph)} factors")
        with step(f"optimisation ({what})"):
            solve.add(graph, optimizer.optimize(graph, solve.values, fixed=fixed))
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

    say("uncertainty: marginal covariances of the objects")
    walk = not hold_trajectory and absolute_sigma(mapping_sigmas(ctx, sigmas)) is None
    with step("result"):
        return map_result(method, solve, labels, front.ellipsoids, seq.timestamps, front.failed,
                          front.notes, association.record, priors=ctx.priors, given_poses=walk)
