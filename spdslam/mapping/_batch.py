"""Object SLAM on a sequence in one batch, the paper's Table III pipeline: ``run_sequence``
composes the steps (``_run``), each inside ``step(name)`` (docs/core.md draws them):

    RunSettings                    every setting, checked before any work (``_settings``)
    → keyframes, screening         ``select_keyframes``, ``frontend.screen_detections``
    → the poses (``RunSettings.initial_poses``), on a trajectory without a bound on each pose:
        auto, loops                the objects mapped on the input poses held (``_map``), then
                                   ``close_loops`` (``_loops``): submaps, verified loops, a
                                   pose graph; the objects mapped again on the corrected
                                   poses held. The boxes move the poses only when a
                                   cross-validation between halves of the labels says they
                                   help (``_refine``), then from the corrected poses.
        input                      the joint optimisation from the input poses, each pose as
                                   free as the odometry lets it (the boxes move the poses)
        incremental                ``replayed_start``: the frames through the online mapper
                                   first, the poses the optimisation starts from, its objects
                                   and, with automatic association, its tracks
    → _map: associate_tracks(ctx, …)  RunTracks: tracks and how they were made
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
from dataclasses import dataclass, field
from typing import Any, Callable

import jaxlie
import numpy as np

from ..frontend import estimate_support_planes, screen_detections
from ..geometry import as_ellipsoid
from ..geometry.se3 import from_tum, to_tum
from ..io import Sequence, without_class_table
from ..solver import L, LevenbergMarquardt, Values, X
from ._context import SequenceContext
from ._drift import correct_drift
from ._graph import (
    build_graph,
    initial_values,
    mapping_sigmas,
    trajectory_noise_note,
)
from ._keyframes import parse_keyframes, select_keyframes
from ._loops import HeldMap, close_loops, stretch_objects
from ._methods import Method
from ._odometry import absolute_sigma, check_trajectory, walk_covariances
from ._online import replayed_start
from ._refine import REFINE_MAX_ROUNDS, Refinement, box_cost_per_box, validate_refinement
from ._run import (
    OBJECT_ERRORS,
    MapResult,
    Optimised,
    as_landmark,
    associate_tracks,
    initialize,
    map_result,
    merge_duplicates,
    observed_by,
    overlapping_duplicates,
    planes_note,
    step,
)
from ._settings import InitialPoses, RunSettings, SettingsError, as_settings, default_association

__all__ = ["run_sequence"]

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
    docstring): the drift is taken out by loops, and by the boxes only where the
    cross-validation between halves of the labels accepts it (``_refined``)."""
    held_run = run.replace(hold_trajectory=True, initial_poses=InitialPoses.INPUT)
    say("objects on the input poses, held")
    held = mapper.map(held_run, hold_note="trajectory held at the input poses (no bound on each pose: the boxes "
                                          "do not move the poses; loops closed by the objects do)")
    with step("loop closure"):
        closure = close_loops(ctx, s, lambda stretches: stretch_objects(held.held, stretches), say)
    if closure.verified:
        corrected = dataclasses.replace(mapper.seq, poses_tum=to_tum(jaxlie.SE3(closure.poses)))  # type: ignore[arg-type]
        say("objects on the corrected poses, held")
        mapped = mapper.map(held_run, seq=corrected, hold_note="trajectory held at the poses the loop closure "
                                                               "corrected")
    else:
        corrected, mapped = mapper.seq, held
    checks = [] if closure.check is None else [closure.check.as_dict()]
    rounds: list = []
    refined = None
    for _ in range(REFINE_MAX_ROUNDS):  # again from the refined poses, until the halves refuse
        refinement, got, more = _refined(mapper, corrected, ctx, s, run, say, len(rounds) + 1)
        rounds.append(refinement)
        checks += more
        if got is None:
            break
        refined = got
        corrected = dataclasses.replace(corrected, poses_tum=np.asarray(got.result.poses_tum)[:, 1:])
    trajectory = {"start": "loops", "loop_closure": closure.as_dict(),
                  "refinement": [rf.as_dict() for rf in rounds], "checks": checks}
    return dataclasses.replace((refined or mapped).opened_by(closure.notes() + [rf.note() for rf in rounds]),
                               trajectory=trajectory)


def _refined(mapper: "_Mapper", seq: Sequence, ctx: SequenceContext, s: dict, run: RunSettings, say,
             round_: int = 1) -> tuple[Refinement, "_Mapped | None", list]:
    """The poses of ``seq`` (the input's, the loops' corrected, or the last round's refined)
    refined by the boxes when the cross-validation between halves of the labels accepts it
    (``_refine``): the joint optimisation with every box from them, checked against the
    odometry's walk from the input (``ctx``); None when refused, with the checks made
    (``TrajectoryCheck.as_dict``)."""
    if mapper.tracks is not None:
        return Refinement(reason="the tracks were given: the halves of the labels need the run's association",
                          round=round_), None, []
    quiet = dataclasses.replace(mapper, progress=None, verbose=False)
    free_run = run.replace(initial_poses=InitialPoses.INPUT)
    held_run = run.replace(hold_trajectory=True, initial_poses=InitialPoses.INPUT)

    def part(half, poses=None) -> Sequence:
        moved = seq if poses is None else dataclasses.replace(seq, poses_tum=poses)
        return dataclasses.replace(moved, detections=[d for d in moved.detections if d.label in half])

    def refine(half):
        try:
            result = quiet.map(free_run, seq=part(half)).result
        except OBJECT_ERRORS as e:  # a half that cannot be mapped (a MappingError too) refutes nothing
            return f"mapping them alone failed: {e}"
        refused = [c for c in result.trajectory.get("checks", []) if not c["accepted"]]
        if refused:
            return f"they would move a camera {refused[-1]['worst_sigma']:.3g}σ of the odometry's walk"
        return np.asarray(result.poses_tum)[:, 1:]

    def held_cost(half, poses) -> float:
        try:
            return box_cost_per_box(quiet.map(held_run, seq=part(half, poses)).result)
        except OBJECT_ERRORS:
            return float("nan")

    say(f"pose refinement, round {round_}: the boxes' refinement cross-validated between two halves of the labels")
    with step("pose refinement"):
        refinement = dataclasses.replace(validate_refinement([d.label for d in seq.detections], refine, held_cost),
                                         round=round_)
    say(refinement.note())
    if not refinement.accepted:
        return refinement, None, []
    try:
        joint = mapper.map(free_run, seq=seq)
    except OBJECT_ERRORS as e:
        return dataclasses.replace(refinement, accepted=False, reason=f"the joint optimisation with every box "
                                   f"failed: {e}"), None, []
    checks = list(joint.result.trajectory.get("checks", []))
    if any(not c["accepted"] for c in checks):
        return dataclasses.replace(refinement, accepted=False, reason="the joint optimisation with every box "
                                   "moved a camera beyond the odometry's walk"), None, checks
    q = ctx.wxyz_xyz
    final = np.asarray(from_tum(np.asarray(joint.result.poses_tum)[:, 1:]).wxyz_xyz)
    check = check_trajectory("pose refinement", q, final, walk_covariances(q, s, ctx.seq.segments))
    checks.append(check.as_dict())
    if not check.accepted:
        return dataclasses.replace(refinement, accepted=False, reason="the refined trajectory departs from the "
                                   "input beyond the odometry's walk"), None, checks
    return refinement, joint, checks


@dataclass(frozen=True)
class _Mapped:
    """A batch mapping's result, what the loop closure reads of it (``HeldMap``) and how many
    of its notes open the run (the screening's and the trajectory's)."""

    result: MapResult
    held: HeldMap
    opening: int

    def opened_by(self, notes: list) -> MapResult:
        """The result with ``notes`` said right after its opening notes."""
        kept = list(self.result.notes)
        return dataclasses.replace(self.result, notes=kept[: self.opening] + list(notes) + kept[self.opening:])


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


@dataclass
class _Pass:
    """One mapping pass (``_map``): the sequence, settings and what each stage leaves for
    the next, in the order the stages set it."""

    seq: Sequence
    run: RunSettings
    method: Method
    ctx: SequenceContext
    mode: str  # the association: given, instances or auto
    say: Callable[[str], Any]
    sigmas: dict  # the run's sigma overrides (a drift correction's bound added)
    in_use: dict  # mapping_sigmas of the sequence as given
    walk: Any  # walk_covariances on a free trajectory without a bound on each pose, else None
    checks: list = field(default_factory=list)  # check_trajectory of each proposed trajectory
    start: Any = None  # replayed_start's answer (initial_poses incremental)
    fallback: str | None = None  # why the replay's start was not used
    association: Any = None
    front: Any = None  # Initialization
    landmarks: dict = field(default_factory=dict)
    drift: Any = None  # DriftCorrection
    start_poses: Any = None  # (F, 7) where the optimisation starts the poses
    solve: Any = None  # Optimised
    optimizer: Any = None
    planes: Any = None
    labels: dict = field(default_factory=dict)  # the front end's objects {id: label}, merged or not
    opening: int = 0  # how many notes open the run (the screening's, the trajectory's)

    @property
    def box_stages(self) -> list:
        return ["semi", "inverse"] if self.method.box_model == "semi-then-inverse" else [self.method.box_model]

    def note(self, text: str) -> None:
        """A note after the initialisation's, said as it is made."""
        self.front.notes.append(text)
        self.say(text)


def _map(seq: Sequence, run: RunSettings, tracks, verbose: bool, progress, first_notes: list,
         hold_note: str | None = None) -> _Mapped:
    """One mapping pass over ``seq`` with ``run``: named stages over one ``_Pass``."""
    p = _open(seq, run, tracks, progress)
    _associate(p, tracks)
    _initialise(p, first_notes, hold_note)
    _correct_drift(p)
    _start_solve(p, verbose, progress)
    for stage in p.box_stages:
        _optimise(p, stage, f"{stage} boxes")
    _estimate_planes(p)
    _merge_duplicates(p)
    _check_joint(p)
    return _result(p)


def _open(seq: Sequence, run: RunSettings, tracks, progress) -> _Pass:
    say = progress or (lambda message: None)
    with step("association"):
        ctx = SequenceContext.of(seq)
        mode = "given" if tracks is not None else str(run.associate or default_association(seq))
    in_use = mapping_sigmas(ctx, dict(run.sigma))
    free = absolute_sigma(in_use) is None and not run.hold_trajectory
    walk = walk_covariances(ctx.wxyz_xyz, in_use, seq.segments) if free else None
    return _Pass(seq, run, run.method.resolved(mode == "auto"), ctx, mode, say, dict(run.sigma), in_use, walk)


def _replay(p: _Pass, given) -> None:
    """The replay's start (``replayed_start``), or a note (``fallback``) when it failed on
    numbers or moved the poses further than the odometry can have drifted."""
    p.say(f"incremental initialisation: {len(p.seq)} frames through the online mapper")
    with step("incremental initialisation"):
        try:
            got = replayed_start(p.seq, given, p.run.replace(method=p.method), p.say)
        except OBJECT_ERRORS as e:  # the replay is a better start, never a reason to fail the run
            p.fallback = (f"incremental initialisation failed ({type(e).__name__}: {e}): the optimisation "
                          "starts from the input poses")
            p.say(p.fallback)
            return
    if p.walk is not None:
        check = check_trajectory("incremental initialisation", p.ctx.wxyz_xyz, got.poses, p.walk)
        p.checks.append(check)
        if not check.accepted:
            p.fallback = check.note()
            p.say(p.fallback)
            return
    p.start = got


def _associate(p: _Pass, tracks) -> None:
    """The tracks (``associate_tracks``); with ``initial_poses`` incremental the replay,
    before the association when it is automatic (the online tracker's tracks, made on the
    corrected poses), else after it, on its tracks."""
    replay = p.run.initial_poses == InitialPoses.INCREMENTAL
    if replay and p.mode == "auto" and p.seq.detections:
        _replay(p, None)
    with step("association"):
        p.say(f"association: {len(p.seq.detections)} detections in {len(p.seq)} frames")
        associate = None if p.run.associate is None else str(p.run.associate)
        p.association = associate_tracks(p.ctx, tracks, associate, found=None if p.start is None else p.start.tracks)
    p.say(f"association: {len(p.association.tracks)} tracks ({p.association.record.get('mode', 'given')})")
    if replay and p.mode != "auto" and p.association.tracks:
        _replay(p, p.association.tracks)


def _initialise(p: _Pass, first_notes: list, hold_note: str | None) -> None:
    """The objects' first estimates (``initialize``; the replay's where it made them) and
    the notes that open the run's: the screening's, the trajectory's, the replay's."""
    start = p.start
    with step("initialisation"):
        ctx = p.ctx if start is None else SequenceContext.of(dataclasses.replace(p.seq, poses_tum=to_tum(
            jaxlie.SE3(start.poses))))  # type: ignore[arg-type]
        front = initialize(ctx, p.association, p.method, p.run.min_views, p.run.support_planes)
        notes = list(first_notes)
        notes.append((hold_note or "trajectory held at the input poses") if p.run.hold_trajectory
                     else trajectory_noise_note(p.ctx, p.sigmas))
        if start is not None:
            replayed = {k: v for k, v in start.landmarks.items() if k in front.ellipsoids}
            front.ellipsoids.update({k: as_ellipsoid(v) for k, v in replayed.items()})
            moved = np.linalg.norm(start.poses[:, 4:] - p.ctx.wxyz_xyz[:, 4:], axis=1)
            notes.append(f"incremental initialisation (the frames replayed through the online mapper first): "
                         f"cameras moved by {1e3 * np.median(moved):.4g} mm median, {1e3 * np.max(moved):.4g} mm "
                         f"most; {len(replayed)} of {len(front.ellipsoids)} objects from the replay")
        if p.fallback is not None:
            notes.append(p.fallback)
        p.front = dataclasses.replace(front, notes=notes + front.notes)
    p.opening = len(first_notes) + 1
    p.say(p.front.notes[len(first_notes)])
    p.say(f"initialisation: {len(p.front.ellipsoids)} objects, {len(p.front.failed)} not initialised")
    p.landmarks = {k: as_landmark(e, p.method) for k, e in p.front.ellipsoids.items()}


def _correct_drift(p: _Pass) -> None:
    """Knots fitted to the boxes (``drift_interval``) on a trajectory without a bound on
    each pose; the corrected trajectory, checked against the walk, replaces the input."""
    if p.run.hold_trajectory or not p.run.drift_interval > 0 or not p.landmarks:
        return
    drift = None
    with step("drift correction"):
        s = mapping_sigmas(p.ctx, p.sigmas)
        if np.isinf(s["absolute_translation"]) and np.isinf(s["absolute_rotation"]):
            p.say(f"drift correction: knots about {p.run.drift_interval:g} s apart")
            lm = LevenbergMarquardt(max_iterations=p.run.max_iterations, relative_tolerance=p.run.tolerance)
            drift = correct_drift(p.ctx, p.front.tracks, p.landmarks, p.method, s, p.run.drift_interval,
                                  p.front.planes, lm)
        else:
            p.front.notes.append("no drift correction: the trajectory has a bound on each pose "
                                 "(trajectory_absolute_sigma)")
    if drift is not None and p.walk is not None:
        moved = SequenceContext.of(dataclasses.replace(p.seq, poses_tum=drift.poses_tum)).wxyz_xyz
        check = check_trajectory("drift correction", p.ctx.wxyz_xyz, moved, p.walk)
        p.checks.append(check)
        if not check.accepted:
            p.note(check.note())
            drift = None
    if drift is not None:
        p.seq = dataclasses.replace(p.seq, poses_tum=drift.poses_tum)
        p.ctx = SequenceContext.of(p.seq)
        p.sigmas = {**p.sigmas, "absolute_translation": float(drift.bound[0]),
                    "absolute_rotation": float(drift.bound[3])}
        p.landmarks.update(drift.landmarks)
        p.note(drift.note())
        p.drift = drift


def _start_solve(p: _Pass, verbose: bool, progress) -> None:
    """The values the optimisation starts from, the LM solver and the keys it holds."""
    p.start_poses = p.ctx.wxyz_xyz if p.start is None else p.start.poses
    values = initial_values(p.start_poses, p.landmarks)

    def each_iteration(rec):
        p.say(f"LM iteration {rec.iteration}: cost {rec.cost:.6g} "
              f"({'accepted' if rec.accepted else 'rejected'}, {'Δ' if rec.radius else 'λ'} {rec.damping:.2g})")

    p.optimizer = LevenbergMarquardt(max_iterations=p.run.max_iterations, verbose=verbose,
                                     relative_tolerance=p.run.tolerance,
                                     callback=each_iteration if progress else None)
    fixed = [X(i) for i in range(len(p.ctx.poses))] if p.run.hold_trajectory else []
    p.solve = Optimised(values=values, fixed=fixed)
    p.planes = p.front.planes


def _optimise(p: _Pass, stage: str, what: str) -> None:
    """The graph of the current tracks, landmarks and planes (``build_graph``), optimised;
    the landmarks where it ended."""
    with step("graph"):
        graph = build_graph(p.ctx, p.front.tracks, p.landmarks, p.method.replace(box_model=stage), p.sigmas,
                            p.front.measured, p.planes, odometry=not p.solve.fixed)
    p.say(f"optimisation ({what}): {len(p.solve.values)} variables, {len(graph)} factors")
    with step(f"optimisation ({what})"):
        p.solve.add(graph, p.optimizer.optimize(graph, p.solve.values, fixed=p.solve.fixed))
    p.landmarks = {k: p.solve.values[L(k)] for k in p.landmarks}


def _estimate_planes(p: _Pass) -> None:
    """Support planes estimated from the optimised objects (``support_planes="optimised"``),
    then the objects optimised again on them."""
    if not (p.run.support_planes == "optimised" and p.method.support_plane and p.ctx.up is not None
            and not p.ctx.support_planes() and p.landmarks):
        return
    with step("support planes"):
        estimated = estimate_support_planes({k: as_ellipsoid(v) for k, v in p.landmarks.items()}, p.ctx.up)
    if len(estimated.planes):
        p.planes = estimated
        p.front.notes.append(planes_note(estimated, p.ctx.up, "optimised"))
        _optimise(p, p.box_stages[-1], "with the estimated support planes")


def _merge_duplicates(p: _Pass) -> None:
    """Objects of automatic association that are one object (``overlapping_duplicates``)
    merged, then optimised again; instance ids are trusted as given."""
    p.labels = {tr.id: tr.label for tr in p.front.tracks}
    if p.association.record.get("mode") != "auto":
        return
    with step("duplicates"):
        pairs = overlapping_duplicates({k: as_ellipsoid(v) for k, v in p.landmarks.items()}, p.labels,
                                       {tr.id: len(tr.frames) for tr in p.front.tracks})
        if pairs:
            p.front = merge_duplicates(p.front, p.landmarks, pairs)
            gone = {L(d) for _, d in pairs}
            p.solve.values = Values({k: v for k, v in p.solve.values.items() if k not in gone})
    if pairs:
        _optimise(p, p.box_stages[-1], f"after merging {len(pairs)} duplicate objects")


def _check_joint(p: _Pass) -> None:
    """The poses the joint optimisation moved, against the odometry's walk; refused: the
    objects optimised again with the poses held where it started."""
    if p.walk is None:
        return
    n = len(p.ctx.poses)
    final = np.stack([np.asarray(p.solve.values[X(i)].wxyz_xyz) for i in range(n)])
    check = check_trajectory("the joint optimisation", p.ctx.wxyz_xyz, final, p.walk)
    p.checks.append(check)
    if check.accepted:
        return
    p.note(check.note())
    for i, T in enumerate(p.start_poses):
        p.solve.values[X(i)] = jaxlie.SE3(T)
    p.solve.fixed = [X(i) for i in range(n)]
    _optimise(p, p.box_stages[-1], "with the poses held where it started")


def _result(p: _Pass) -> _Mapped:
    """The ``MapResult`` (``map_result``) and what later steps read of the pass."""
    p.say("uncertainty: marginal covariances of the objects")
    unbounded = absolute_sigma(p.in_use) is None
    given = not p.solve.fixed and unbounded
    with step("result"):
        result = map_result(p.method, p.solve, p.labels, p.front.ellipsoids, p.seq.timestamps, p.front.failed,
                            priors=p.ctx.priors, given_poses=given)
        result = observed_by(result, p.front.tracks, p.seq)
        auto = p.association.record.get("mode") == "auto"
        result = dataclasses.replace(result, notes=list(p.front.notes), association=p.association.record,
                                     associated=(p.association.tracks, p.seq) if auto else ())
    if unbounded:
        start = "held" if p.run.hold_trajectory else ("incremental" if p.start is not None else "input")
        result = dataclasses.replace(result, trajectory={"start": start, "checks": [c.as_dict() for c in p.checks]})
    in_use = mapping_sigmas(p.ctx, p.sigmas) if p.drift is not None else p.in_use  # the corrected graph's
    return _Mapped(result, HeldMap(p.ctx, p.front.tracks, dict(p.landmarks), p.method, in_use, p.planes,
                                   p.run.min_views, p.run.max_iterations), p.opening)
