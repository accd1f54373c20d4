"""Online mapping: frames added one at a time, objects mapped as the camera moves.

``OnlineMapper.add_frame`` takes a frame (timestamp, T_wc pose or odometry, detections,
optional measured ellipsoids) in timestamp order. Per frame:

1. the pose's initial value: the input motion since the previous frame applied to that
   frame's current estimate, T̂ᵢ = T̂ᵢ₋₁ (Tᵢ₋₁⁻¹ Tᵢ) (the first frame: its input pose);
2. association: by instance id, or automatically (``frontend.OnlineTracker``: the tracking
   stage of the batch association, one frame at a time);
3. every ``every`` frames (and at the first frame a track could become an object):
   objects are created for the tracks with at least ``min_views`` views that the batch
   initialisation accepts (``initialize_objects`` on the current pose estimates), duplicates
   merged (automatic association: ``overlapping_duplicates``), and the fixed-lag problem
   solved by LM from the current estimates (warm start).

The fixed-lag problem. Free: the poses of the last ``window`` frames and the objects that
have factors not yet marginalised. On a trajectory without a bound on each pose (drifting
odometry) the poses are held at the odometry instead (``hold_poses``; the boxes of a real
detector do not fix a camera better than the odometry over a minute, and the window's free
poses once followed them metres away on a real recording, docs/drift.md) unless
``initial_poses="input"`` frees them; ``finish`` then holds them too. Held there, the loops
the objects close correct them (``loop_closure``, ``_loops.OnlineLoopClosure``: the batch's
verification and pose graph on the frames so far, each time a submap is complete; in the
worker with ``background``): ``current_map`` gives the corrected trajectory and objects, and
``finish`` holds the poses at it. The odometry factors
are ``_odometry.odometry_factors``' (the batch graph's), with the segments of a joined
recording (``add_frame``'s ``new_segment``). Factors: the odometry between consecutive frames of the
window (the first one from the frame before it, whose pose is held fixed; a prior on the
first frame while the window starts there), the box (and measured-ellipsoid) factors not yet
marginalised (their poses fixed when older than the window), each object's own factors
(orientation, plane, shape, size, radius floor) and its ``LandmarkPriorFactor``. After the
solve, the box factors of frames older than the window are marginalised: with their poses
fixed, their Gauss–Newton quadratic in the object (with the object's previous prior) at the
current estimate becomes the object's new prior (mean x̂ ⊞ (−H⁺g), information H). Older
poses keep their last estimate (conditioning, not marginalising, the poses). The work per
frame is bounded by the window, not by the frames seen (docs/online.md measures it).

``finish(final_batch=True)`` runs one batch optimisation of the whole graph (every frame and
view, ``build_graph``) from the online state; ``final_batch=False`` reports the online
estimates as they are. Both give a ``MapResult``, as ``run_sequence`` does; with automatic
association, objects detected in too few of the frames that see them are reported, not
mapped (the batch run's rule, ``MIN_DETECTION_RATE``).
"""

from __future__ import annotations

import dataclasses
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable

import jaxlie
import numpy as np

from ..frontend import AssociationSettings, OnlineTracker, Track
from ..geometry import as_ellipsoid
from ..geometry.se3 import from_tum, to_tum
from ..io import BUILTIN_CLASSES, Detection, Sequence, without_class_table
from ..solver import (
    FixedLagSmoother,
    L,
    LevenbergMarquardt,
    NonlinearFactorGraph,
    Problem,
    X,
    ensure_compilation_cache,
    group_kernels,
    padded_sizes_above,
)
from ._context import SequenceContext, camera_axes_of
from ._graph import (
    box_factors,
    build_graph,
    initial_values,
    mapping_sigmas,
    measurement_factors,
    object_factors,
    with_robust_by_type,
)
from ._intake import AcceptedFrame, BackgroundWorker, FrameIntake
from ._loops import OnlineLoopClosure
from ._methods import Method, robust_kernel
from ._odometry import absolute_sigma, check_trajectory, odometry_factors, walk_covariances
from ._reuse import transform_ellipsoid
from ._run import (
    Optimised,
    as_landmark,
    drop_rarely_detected,
    in_front_views,
    initialize_objects,
    map_result,
    merged_tracks,
    observed_by,
    overlapping_duplicates,
    too_few_views,
)
from ._settings import (
    Associate,
    InitialPoses,
    OnlineSettings,
    RunSettings,
    as_online_settings,
    default_association,
)

__all__ = ["OnlineMapper", "FrameRecord", "OnlineMap", "ReplayedStart", "replay", "replayed_start", "run_online"]

#: ``OnlineSettings``' fields, taken by ``OnlineMapper`` and ``run_online`` as keywords.


@dataclass(frozen=True)
class FrameRecord:
    """What ``add_frame`` did: frame index, timestamp, seconds spent, objects mapped after
    it, factors and free variables of the problem solved (0 if none), LM iterations, and
    ``lag``: seconds from the frame's arrival (the call of ``add_frame``) to the end of the
    first optimisation that used it (nan: none has yet). In the background
    (``OnlineSettings.background``) ``seconds`` is add_frame's own time and the figures of an
    optimisation go to the record of the last frame it used."""

    frame: int
    timestamp: float
    seconds: float
    objects: int
    factors: int
    variables: int
    iterations: int
    lag: float = float("nan")


@dataclass(frozen=True)
class OnlineMap:
    """The map after a frame: ``objects`` {id: (label, Ellipsoid)}, ``poses_tum`` (F, 8)
    rows ``t tx ty tz qx qy qz qw`` (the current estimates), ``covariances`` {id: 9×9} of the
    objects in the last problem solved (in the landmark's chart; objects not in it: none)."""

    objects: dict
    poses_tum: np.ndarray
    covariances: dict = field(default_factory=dict)
    #: the frames (0 … frames − 1) whose detections the map's last optimisation used
    frames: int = 0


class _Poses:
    """The current pose estimates as a growing (F, 7) array of jaxlie parameters, indexable
    as ``SequenceContext.poses`` is (``poses[i]`` a ``jaxlie.SE3``)."""

    def __init__(self):
        self._a = np.zeros((256, 7))
        self.n = 0

    def append(self, wxyz_xyz) -> None:
        if self.n == len(self._a):
            self._a = np.concatenate([self._a, np.zeros_like(self._a)])
        self._a[self.n] = wxyz_xyz
        self.n += 1

    @property
    def array(self) -> np.ndarray:
        return self._a[: self.n]

    def __getitem__(self, i) -> jaxlie.SE3:
        return jaxlie.SE3(self._a[: self.n][i])

    def __len__(self) -> int:
        return self.n


class _Detections:
    """The detections taken in, kept as columns (timestamp, box, score as floats; frame and
    instance as integers; the labels as strings) instead of objects: a long run takes in
    hundreds of thousands, and each object the garbage collector tracks lengthens every full
    pass (docs/online.md, "Pauses of the garbage collector"). ``list()`` gives them back as
    ``Detection`` s equal to the bit to those taken in; one of a subclass of ``Detection``, or
    with an instance id beyond 64 bits, is kept as it is."""

    _INT64 = np.iinfo(np.int64)

    def __init__(self):
        self._x = np.zeros((256, 6))  # timestamp, x1, y1, x2, y2, score
        self._k = np.zeros((256, 2), np.int64)  # frame, instance
        self._none = np.zeros(256, bool)  # no instance id
        self._labels: list = []
        self._kept: dict = {}  # index -> a detection kept as given
        self.n = 0

    def extend(self, dets) -> None:
        while self.n + len(dets) > len(self._x):
            grown = (np.concatenate([a, np.zeros_like(a)]) for a in (self._x, self._k, self._none))
            self._x, self._k, self._none = grown
        for i, d in enumerate(dets, self.n):
            self._x[i, 0], self._x[i, 1:5], self._x[i, 5] = d.timestamp, d.box, d.score
            self._none[i] = d.instance is None
            if type(d) is not Detection or not (d.instance is None or self._INT64.min <= d.instance <= self._INT64.max):
                self._kept[i] = d
                continue
            self._k[i] = d.frame, (0 if d.instance is None else d.instance)
        self._labels += [d.label for d in dets]
        self.n += len(dets)

    def list(self) -> list:
        x, k, none = self._x[: self.n], self._k[: self.n].tolist(), self._none[: self.n].tolist()
        return [self._kept[i] if i in self._kept else
                Detection(k[i][0], float(x[i, 0]), x[i, 1:5], label, float(x[i, 5]), None if none[i] else k[i][1])
                for i, label in enumerate(self._labels)]

    def __len__(self) -> int:
        return self.n


class OnlineMapper:
    """Incremental object mapping (module docstring).

    ``loop_closure``: on a trajectory without a bound on each pose, with ``initial_poses``
    auto or loops, the loops its objects close (``OnlineLoopClosure``, attached by
    ``watch``); ``current_map`` and ``finish`` give the trajectory and objects it corrected.

    ``camera``, ``priors``: as a ``Sequence``'s. ``method``: the run's ``RunSettings`` (its
    ``online`` the fixed-lag settings, ``OnlineSettings()`` when None), or a name of
    ``METHODS`` (or a ``Method``; SPD or RTS landmarks) with ``settings``: the keywords of
    ``RunSettings.of``, and ``OnlineSettings``' fields (``window``: frames whose poses are
    free; ``every``: frames between optimisations; ``iterations``: LM iterations per
    optimisation) as keywords of their own. ``associate``: "instances" (every detection
    carries its object's id; negative ids are false detections) or "auto" (the default);
    ``min_views``: views before an object is created; ``max_iterations`` and ``tolerance``:
    ``finish``'s batch optimisation. ``compilation_cache``: turn on JAX's persistent
    compilation cache (``SPDSLAM_CACHE_DIR``, as the CLI does) unless the process already
    has one; ``warmup`` compiles before the first frame.

    ``background`` (``OnlineSettings``): the optimisations run in a worker thread. Then
    ``add_frame`` only checks and screens the frame and, when the worker is idle, takes it in
    (pose prediction, association), and returns; the frames that arrive while the worker
    optimises wait in a queue, and the worker takes them all in, in order, before it
    optimises again (once, on the latest window, however many optimisations came due
    meanwhile). ``current_map`` is the map the last optimisation published
    (``OnlineMap.frames`` says which frames it used). While the worker keeps up, the frames
    are taken in and optimised as without it, and the maps are the same; when it falls
    behind it skips the optimisations it missed rather than fall further behind
    (``FrameRecord.lag`` says when each frame reached a map). ``wait`` blocks until the
    worker is idle; ``finish`` waits first. An error in the worker is raised by the next
    ``add_frame``, ``wait`` or ``finish``.

    Python's garbage collector pauses every thread for 0.1–0.5 s in a full pass over a
    process that has imported JAX; a process that maps for long should call ``gc.collect();
    gc.freeze()`` once its long-lived objects exist (``spdslam run`` does;
    docs/online.md, "Pauses of the garbage collector"). The mapper does not: the process is
    its host application's.
    """

    #: whether a mapper of this class closes loops (``loop_closure``)
    closes_loops = True

    def __init__(self, camera, priors=None, method: str | Method | RunSettings = "multi-spd", *,
                 association: AssociationSettings | None = None, name: str = "online",
                 compilation_cache: bool = True, **settings):
        run = as_online_settings(method, settings)
        online = run.online or OnlineSettings()
        run = run.replace(online=online, associate=run.associate or Associate.AUTO)
        self.settings, self.online = run, online
        self._association = association
        if compilation_cache:
            ensure_compilation_cache()
        associate = str(run.associate)
        method = run.method.resolved(associate == "auto")
        sigmas = dict(run.sigma)
        self.method, self.associate = method, associate
        self.window, self.every, self.min_views = online.window, online.every, run.min_views
        self.name = name
        empty = Sequence(name, camera, np.zeros(0), np.zeros((0, 7)), [], priors=priors)
        self._ctx0 = SequenceContext.of(empty)
        self._sigmas = mapping_sigmas(self._ctx0, sigmas)
        #: a trajectory without a bound on each pose: the boxes do not move the poses (they
        #: follow the odometry) unless ``initial_poses="input"`` lets them (module docstring)
        self.hold_poses = absolute_sigma(self._sigmas) is None and run.initial_poses != InitialPoses.INPUT
        self._segments: list = []  # the frames that start a later segment (add_frame's new_segment)
        self._user_sigmas = sigmas
        self._robust = robust_kernel(method.robust, method.robust_k)
        self._smoother = FixedLagSmoother(LevenbergMarquardt(max_iterations=online.iterations), self._floor,
                                          lag=online.window, prepare=lambda fs: with_robust_by_type(fs, method))
        self._tracker = OnlineTracker(camera, priors, association) if associate == "auto" else None
        self._assoc_settings = association or AssociationSettings()
        self._intake = FrameIntake(camera, priors, method.margin, run.screen, associate == "instances")
        self._timestamps: list = []
        self._input = _Poses()  # input poses (jaxlie parameters)
        self._est = _Poses()  # current estimates
        self._detections = _Detections()
        self._ellipsoids: list = []
        self._views: dict = {}  # track id -> [(frame, box)]
        self._labels: dict = {}  # track id -> Counter of its detections' labels
        self._candidates: set = set()  # tracks with new views that are not objects
        self._measured: dict = {}  # track id -> [EllipsoidDetection]
        self.landmarks: dict = {}  # object id -> landmark value
        self._tried: dict = {}  # track id -> views at the last failed initialisation
        self.failed: dict = {}
        self.notes: list = []
        self.records: list = []
        self._initial: dict = {}
        self._merged: dict = {}  # object id -> label, of the objects merged into another
        self._since = 0
        self._arrival: list = []  # perf_counter at each frame's add_frame
        self._used = 0  # frames the last optimisation used (records before it have their lag)
        self.background = online.background
        self._worker = BackgroundWorker(self._ingest, self._optimise_and_publish)
        self._published = OnlineMap({}, np.zeros((0, 8)))
        self._watchers: list = []
        #: on a trajectory whose poses are held at the odometry (``initial_poses`` auto or
        #: loops): the loops the objects close as the frames come (``OnlineLoopClosure``)
        self.loop_closure = OnlineLoopClosure(self) if self.closes_loops and self.hold_poses and \
            run.start(True) == InitialPoses.LOOPS else None
        self._prime()

    def watch(self, due: Callable[[int, int], bool], look: Callable[[dict, int], Any]) -> None:
        """Attach a collaborator that looks at the map as it grows (relocalisation against a
        saved map: ``LocalizingMapper``): ``due(objects, frames)`` says whether to look at a
        map of that many objects over that many frames, ``look(objects, frames)`` gets its
        objects {id: (label, Ellipsoid)}. In the caller's thread after each frame, or in the
        background in the worker's thread on each map it publishes (never holding up a frame)."""
        self._watchers.append((due, look))

    def _notify(self, count: int, frames: int, objects: Callable[[], dict]) -> None:
        for due, look in self._watchers:
            if due(count, frames):
                look(objects(), frames)

    @staticmethod
    def _prime() -> None:
        """Run the pose arithmetic of a frame once (``FrameIntake.accept``, ``_ingest``, ``_associate``):
        JAX compiles its small programs on first use (about 0.1 s in a new process), which
        belongs to the mapper's start, not to its first frames."""
        T = from_tum(np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]))
        wxyz = np.asarray(T.wxyz_xyz, float)
        step = jaxlie.SE3(wxyz).inverse() @ jaxlie.SE3(wxyz)  # type: ignore[arg-type]
        est = jaxlie.SE3(wxyz) @ step  # type: ignore[arg-type]
        np.asarray(est.wxyz_xyz), np.asarray(est.rotation().as_matrix()), np.asarray(est.translation())

    # --- input ------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self._timestamps)

    def warmup(self, sequence: Sequence, progress: Callable[[int, int], Any] | None = None) -> float:
        """Compile (or load from the compilation cache) what a replay needs, before the
        first frame: ``sequence`` (a synthetic room, ``synthetic.make_room_sequence``, or a
        recording of the same kind) is replayed through a mapper of this one's method and
        settings (its priors; the sequence's labels renamed to their classes), then
        discarded (``finish`` is not run); this mapper is unchanged. Programs are kept per
        factor kind and padded size (2ᵏ and 3·2ᵏ⁻¹, ``solver.padded_size``), so those compiled
        here serve any sequence whose fixed-lag problems reach the same sizes; each kind's
        programs are also compiled for the sizes of two more doublings of the largest size the
        replay reached. Returns the seconds it took; ``progress(frame, frames)`` as
        ``replay``'s."""
        t0 = time.perf_counter()
        # this mapper's priors (they decide which factors exist: class size and shape priors,
        # the trajectory's noise model), with the sequence's labels renamed to its classes
        priors = self._ctx0.priors
        classes = [] if priors is None else list(priors.classes) or (
            sorted(BUILTIN_CLASSES) if priors.builtin_classes else [])
        rename = {lab: classes[i % len(classes)] for i, lab in
                  enumerate(sorted({d.label for d in sequence.detections}))} if classes else {}
        twin = OnlineMapper(sequence.camera, priors,
                            self.settings.replace(online=dataclasses.replace(self.online, background=False)),
                            association=self._association, compilation_cache=False)
        by_frame: dict = {}
        for d in sequence.detections:
            by_frame.setdefault(d.frame, []).append(dataclasses.replace(d, label=rename.get(d.label, d.label)))
        replay(sequence, twin, by_frame, {}, progress)
        # each factor kind's programs for the sizes of the next two doublings of its
        # largest, which a longer or busier recording reaches
        for gk in group_kernels():
            if gk.sizes:
                gk.compile_sizes(padded_sizes_above(max(gk.sizes), 4))
        return time.perf_counter() - t0

    def add_frame(self, timestamp: float, pose: Any = None, *, odometry: Any = None,
                  detections: Iterable = (), ellipsoids: Iterable = (), new_segment: bool = False) -> FrameRecord:
        """Add one frame (module docstring) and return what was done. ``pose``: T_wc (a
        ``jaxlie.SE3``, 4×4, or a TUM row tx ty tz qx qy qz qw); or ``odometry``: the motion
        T_{i−1}⁻¹ Tᵢ since the previous frame. ``detections``: ``Detection``s or (label, box
        [x1, y1, x2, y2][, score[, instance]]); ``ellipsoids``: ``EllipsoidDetection``s
        (camera frame, with instance ids). ``new_segment``: the frame starts a later segment of
        a joined recording (``Sequence.segments``): no odometry links it to the frame before,
        and its pose (given, not odometry) is where the segment was placed."""
        t0 = time.perf_counter()
        self._worker.raise_error()
        frame = self._intake.accept(timestamp, pose, odometry, detections, ellipsoids, bool(new_segment))
        self._arrival.append(t0)
        if not self.background:
            due = self._ingest(frame)
            figures = self._update() if due else (0, 0, 0)
            rec = FrameRecord(frame.index, frame.timestamp, time.perf_counter() - t0, len(self.landmarks),
                              *figures)
            self.records.append(rec)
            if due:
                self._publish(len(self), figures)
            self._notify(len(self.landmarks), len(self), self._objects)
            return self.records[-1]

        def record() -> FrameRecord:  # under the worker's lock, as the frame is taken in or queued
            self.records.append(FrameRecord(frame.index, frame.timestamp, time.perf_counter() - t0,
                                            len(self.landmarks), 0, 0, 0))
            return self.records[-1]

        return self._worker.take(frame, record)

    def _ingest(self, frame: AcceptedFrame) -> bool:
        """Take an accepted frame into the state (pose prediction, association, views);
        returns whether an optimisation is due."""
        f, t, wxyz, dets, meas = (frame.index, frame.timestamp, frame.pose, frame.detections,
                                  frame.ellipsoids)
        if frame.new_segment:
            self._segments.append(f)
        if f == 0 or frame.new_segment:
            est = wxyz
        else:
            step = jaxlie.SE3(self._input.array[-1]).inverse() @ jaxlie.SE3(wxyz)  # type: ignore[arg-type]
            est = np.asarray((jaxlie.SE3(self._est.array[-1]) @ step).wxyz_xyz)
        self._timestamps.append(t)
        self._input.append(wxyz)
        self._est.append(est)
        self._detections.extend(dets)
        self._ellipsoids += meas
        self._associate(f, dets)
        for m in meas:
            if m.instance is not None and m.instance >= 0 and self.associate == "instances":
                self._measured.setdefault(m.instance, []).append(m)
                if m.instance in self.landmarks:
                    self._smoother.add(L(m.instance), self._measurement(m.instance, [m]))
        self._since += 1
        ready = any(self._could_start(k) for k in self._candidates)
        if self._since >= self.every or (ready and not self.landmarks):
            self._since = 0
            return True
        return False

    def _optimise_and_publish(self) -> None:
        """The worker's optimisation (``BackgroundWorker``): the window solved, the map published."""
        n = len(self)
        self._publish(n, self._update())

    def _publish(self, n: int, figures) -> None:
        """An optimisation that used frames 0 … n − 1 ended: their records get their lag (and,
        in the background, the last one the optimisation's figures); in the background the
        map is published for ``current_map``."""
        now = time.perf_counter()
        if self.background:
            k = n - 1
            self.records[k] = dataclasses.replace(self.records[k], factors=figures[0],
                                                  variables=figures[1], iterations=figures[2])
            snap = self._snapshot(n)
        for i in range(self._used, n):
            self.records[i] = dataclasses.replace(self.records[i], lag=now - self._arrival[i])
        self._used = n
        if self.background:
            self._notify(len(snap.objects), n, lambda: snap.objects)  # the mapper's own frame
            self._published = self._corrected(snap)

    def wait(self) -> None:
        """Block until the worker (``background``) has taken in every frame added and run
        the optimisations they were due; raise an error it met. Without a worker: nothing."""
        self._worker.wait()

    def _associate(self, f: int, dets: list) -> None:
        if not dets:
            if self._tracker is not None:
                T = jaxlie.SE3(self._est.array[f])
                self._tracker.add_frame(np.asarray(T.rotation().as_matrix()), np.asarray(T.translation()),
                                        np.zeros((0, 4)), [])
            return
        if self._tracker is None:
            ids = [d.instance for d in dets]
        else:
            T = jaxlie.SE3(self._est.array[f])
            ids = list(self._tracker.add_frame(
                np.asarray(T.rotation().as_matrix()), np.asarray(T.translation()),
                np.stack([d.box for d in dets]), [d.label for d in dets]))
        for d, k in zip(dets, ids):
            if k is None or k < 0:
                continue  # a known false detection
            k = int(k)
            self._views.setdefault(k, []).append((f, np.asarray(d.box, float)))
            self._labels.setdefault(k, Counter())[d.label] += 1
            if k not in self.landmarks:
                self._candidates.add(k)
            if k in self.landmarks:
                self._smoother.add(L(k), self._box_factors(k, [(f, np.asarray(d.box, float))]))

    def _label(self, k) -> str:
        counts = self._labels.get(k) or Counter(m.label for m in self._measured.get(k, []))
        return max(sorted(counts), key=counts.__getitem__)

    def _track(self, k, views=None) -> Track:
        views = self._views.get(k, []) if views is None else views
        frames = np.array([v[0] for v in views], dtype=int)
        boxes = np.array([v[1] for v in views], dtype=float).reshape(-1, 4)
        return Track(k, self._label(k), frames, boxes)

    def _could_start(self, k) -> bool:
        n = len(self._views.get(k, ()))
        return n >= self._views_needed() and n >= 1.5 * self._tried.get(k, 0)

    def _views_needed(self) -> int:
        """The views a track needs before it is an object: ``min_views``, and with automatic
        association the detections the batch association keeps a track for."""
        return max(self.min_views, self._assoc_settings.min_detections if self._tracker else 1)

    def _context(self) -> SequenceContext:
        """The context of the frames so far, with the current estimates as the poses."""
        return dataclasses.replace(self._ctx0, wxyz_xyz=self._est.array, poses=self._est)  # type: ignore[arg-type]

    # --- the update ---------------------------------------------------------------------------
    def _reentry(self, k):
        """The object that track k is a re-entry of (after a gap, or a split track), or None."""
        if self._tracker is None or not self.landmarks:
            return None
        return self._tracker.match(k, sorted(self.landmarks))

    def _create_objects(self) -> None:
        """The tracks ready to start an object (``_could_start``), in order of their ids: each
        joins the object it is a re-entry of (``_reentry``), or becomes an object when its
        initial ellipsoid (``initialize_objects``) has ``min_views`` views in front of the
        cameras. The initial ellipsoids of all the tracks that are no re-entry are fitted in
        one batch, as the batch run fits its objects'; a track's re-entry is looked for again
        when an object was made or joined before it."""
        ctx = self._context()
        cands = sorted(k for k in self._candidates if self._could_start(k))
        first = {k: self._reentry(k) for k in cands}
        batch = [self._track(k) for k in cands if first[k] is None]
        init = initialize_objects(ctx, batch, self.method, self.min_views)[0] if batch else {}
        changed = False
        for k in cands:
            j = self._reentry(k) if changed else first[k]
            if j is not None:
                self._join(j, k)
                changed = True
                continue
            tr = self._track(k)
            if first[k] is not None:  # a re-entry before an object was made or joined, no longer
                init.update(initialize_objects(ctx, [tr], self.method, self.min_views)[0])
            if k not in init:
                self._tried[k] = len(tr.frames)
                continue
            e = init[k]
            ok, note = in_front_views(e, camera_axes_of(self._est.array[tr.frames]), k)
            if ok.sum() < self.min_views:
                self._tried[k] = len(tr.frames)
                continue
            self.landmarks[k] = as_landmark(e, self.method)
            changed = True
            self._candidates.discard(k)
            self._initial[k] = e
            self._views[k] = [v for v, good in zip(self._views[k], ok) if good]
            self._smoother.add(L(k), self._box_factors(k, self._views[k]))
            self._smoother.add(L(k), self._measurement(k, self._measured.get(k, [])))
            if note:
                self.notes.append(note)

    def _join(self, keep, drop) -> None:
        """Track ``drop``'s views join object ``keep`` (``drop`` is no object)."""
        if self._tracker is not None:
            self._tracker.merge(keep, drop)
        views = self._views.pop(drop)
        self._views[keep] = sorted(self._views[keep] + views, key=lambda v: v[0])
        self._labels[keep] += self._labels.pop(drop)
        self._candidates.discard(drop)
        self._smoother.add(L(keep), self._box_factors(keep, views))
        self._tried.pop(drop, None)

    def _merge_duplicates(self, active) -> None:
        """Objects of ``active`` that are one object with another (automatic association;
        ``overlapping_duplicates``, the batch run's rule, for the objects of the window
        against all): the one with more views is kept and the other's views join it."""
        if self._tracker is None or len(self.landmarks) < 2:
            return
        ells = {k: as_ellipsoid(v) for k, v in self.landmarks.items()}
        labels = {k: self._label(k) for k in ells}
        for keep, drop in overlapping_duplicates(ells, labels, {k: len(self._views[k]) for k in ells}, active):
            self._merge(keep, drop)

    def _merge(self, keep, drop) -> None:
        """Object ``drop`` is object ``keep``: its views join it, its landmark and prior go."""
        if self._tracker is not None:
            self._tracker.merge(keep, drop)
        self._merged[drop] = self._label(drop)
        self._views[keep] = sorted(self._views[keep] + self._views.pop(drop), key=lambda v: v[0])
        self._labels[keep] += self._labels.pop(drop)
        self._smoother.merge(L(keep), L(drop))
        self.landmarks.pop(drop)
        self.notes.append(f"objects {keep} and {drop} ({self._label(keep)}) are one object: "
                          f"each centre lay inside the other ellipsoid; {drop}'s boxes joined to {keep}")

    def _box_factors(self, k, views) -> list:
        """[(frame, box factor)] of object k's ``views`` [(frame, box)] (made once per view)."""
        if not views:
            return []
        out = NonlinearFactorGraph(box_factors(self._ctx0, self._track(k, views), self.method,
                                               self.method.box_model, self._sigmas, self._robust))
        return [(f, fac) for (f, _), fac in zip(views, out)]  # one factor per view

    def _measurement(self, k, meas) -> list:
        """[(frame, factor)] of object k's measured ellipsoids ``meas``."""
        if not meas:
            return []
        out = measurement_factors(self._ctx0, {k: list(meas)}, {k: self.landmarks[k]},
                                   self._sigmas, self._robust)
        return [(m.frame, fac) for m, fac in zip(meas, out)]

    def _object_factors(self, key) -> list:
        """Object ``key``'s own factors (orientation, plane, shape, size, radius floor), made
        afresh at each update from its current estimate."""
        k = key.index
        return object_factors(self._ctx0, self._track(k, []), self.landmarks[k], self.method, self._sigmas,
                              boxes=False)

    def _update(self) -> tuple[int, int, int]:
        """Create and merge objects, then the smoother's update (``FixedLagSmoother``): the
        window solved, what left it marginalised. Returns (factors, free variables, LM
        iterations)."""
        self._create_objects()
        self._merge_duplicates([k for k in self.landmarks if self._smoother.has_kept(L(k))])
        start = max(0, len(self) - self.window)
        odometry = [] if self.hold_poses else list(NonlinearFactorGraph(
            odometry_factors(self._input.array, self._segments, self._sigmas, start)))
        active = [key.index for key in self._smoother.active()]

        def accept(values) -> None:  # the window's solution becomes the estimates
            for key in values:
                if key.chr == "l":
                    self.landmarks[key.index] = values[key]
                elif key.index >= start:
                    self._est.array[key.index] = np.asarray(values[key].wxyz_xyz)
            if self._tracker is not None:
                for k in active:
                    e = as_ellipsoid(self.landmarks[k])
                    self._tracker.set_landmark(k, np.asarray(e.center), np.asarray(e.P))

        done = self._smoother.update(len(self), odometry, self._object_factors,
                                     lambda keys: initial_values(self._est, self.landmarks, keys), accept,
                                     self.hold_poses)
        for key in done.dropped:
            self.notes.append(f"object {key.index}: the views before frame {done.start} could not be "
                              "summarised (non-finite); they are dropped")
        return done.factors, done.variables, done.iterations

    def _floor(self, name: str) -> int:
        """The fewest rows the smoother pads a factor kind or variable type to: the boxes of a
        full window, the odometry and poses of a window and a batch of frames, 16 else."""
        if "box" in name:
            return 4 * self.window
        return self.window + self.every + 8 if name in ("between", "SE3") else 16

    # --- output ----------------------------------------------------------------------------
    def _snapshot(self, n: int) -> OnlineMap:
        """The map of the current state, frames 0 … n − 1 (covariances: none)."""
        est = self._est.array[:n]
        rows = to_tum(jaxlie.SE3(est)) if len(est) else np.zeros((0, 7))  # type: ignore[arg-type]
        poses = np.c_[np.asarray(self._timestamps[:n]), rows]
        return OnlineMap(self._objects(), poses, frames=n)

    def _corrected(self, snap: OnlineMap) -> OnlineMap:
        """``snap`` with the loop closure's corrections (``OnlineLoopClosure.corrections``):
        each pose T ↦ C T, each object moved by C at the middle of its views (the frames in
        between follow the corrected trajectory); ``snap`` itself before a loop closed."""
        n = snap.frames
        moved = self._correction(n)
        if moved is None:
            return snap
        T, move = moved
        objects = {k: (label, move(k, e)) for k, (label, e) in snap.objects.items()}
        return dataclasses.replace(snap, objects=objects, poses_tum=np.c_[snap.poses_tum[:, 0], to_tum(T)])

    def _correction(self, n: int):
        """The loop closure's correction of the first n frames: (the corrected poses T = C T̂,
        ``move(k, ellipsoid)``: object k's ellipsoid moved by C at the frame in the middle of
        its views); None before a loop closed."""
        C = None if self.loop_closure is None or not n else self.loop_closure.corrections(self._est.array[:n])
        if C is None:
            return None
        T = jaxlie.SE3.from_matrix(C) @ jaxlie.SE3(self._est.array[:n])  # type: ignore[arg-type]

        def move(k, e):
            frames = sorted(f for f, _ in self._views.get(k, ()) if f < n)
            return transform_ellipsoid(e, C[frames[len(frames) // 2] if frames else n - 1])

        return T, move

    def _objects(self) -> dict:
        """The objects now, {id: (label, Ellipsoid)}."""
        return {k: (self._label(k), as_ellipsoid(v)) for k, v in sorted(self.landmarks.items())}

    def current_map(self, covariances: bool = False) -> OnlineMap:
        """The map now (``OnlineMap``; in the background: the last one published, which
        does not wait for the worker); ``covariances``: the objects' marginal covariances in
        the last problem solved (``solver.marginal_covariances``, one factorisation; in the
        background after ``wait``)."""
        if self.background:
            if not covariances:
                return self._published
            self.wait()
        snap = self._corrected(self._snapshot(len(self)))
        objects, poses = snap.objects, snap.poses_tum
        cov: dict = {}
        if covariances and self._smoother.last is not None:
            from ..solver import marginal_covariances

            graph, values, fixed = self._smoother.last
            keys = [key for key in values if key.chr == "l"]
            cov = {key.index: c for key, c in marginal_covariances(graph, values, keys, fixed=fixed).items()}
        return OnlineMap(objects, poses, cov, frames=self._used)

    @property
    def timestamps(self) -> np.ndarray:
        """The frames' timestamps, in the order they came."""
        return np.asarray(self._timestamps, float)

    @property
    def estimates(self) -> np.ndarray:
        """The current pose estimates, (F, 7) jaxlie ``wxyz_xyz`` in the order the frames came."""
        return self._est.array.copy()

    def tracks(self) -> list[Track]:
        """The tracks of the objects seen so far that the batch association would keep (at
        least ``AssociationSettings.min_detections`` views)."""
        need = self._assoc_settings.min_detections
        return [self._track(k) for k in sorted(self._views) if len(self._views[k]) >= need]

    def sequence(self) -> Sequence:
        """The frames so far as a ``Sequence`` (input poses, detections, measured ellipsoids)."""
        rows = np.stack([to_tum(jaxlie.SE3(r)) for r in self._input.array]) if len(self) else np.zeros((0, 7))
        return Sequence(self.name, self._ctx0.camera, np.asarray(self._timestamps), rows,
                        self._detections.list(), priors=self._ctx0.priors,
                        ellipsoids=list(self._ellipsoids) if self._ellipsoids else None,
                        segments=tuple(self._segments))

    def finish(self, final_batch: bool | None = None, max_iterations: int | None = None,
               tolerance: float | None = None, progress=None):
        """The ``MapResult`` of the frames so far (the mapper is not changed): after one batch
        optimisation of every frame and view from the online state (``final_batch``; LM with
        ``max_iterations`` and relative ``tolerance``), or of the online estimates as they are
        (the uncertainty then still comes from the whole graph). None: the settings'
        (``online.final_batch``, ``max_iterations``, ``tolerance``)."""
        self.wait()
        run = self.settings
        final_batch = self.online.final_batch if final_batch is None else final_batch
        max_iterations = run.max_iterations if max_iterations is None else max_iterations
        tolerance = run.tolerance if tolerance is None else tolerance
        say = progress or (lambda message: None)
        if not len(self):
            raise ValueError("no frames were added")
        seq = self.sequence()
        tracks, landmarks, rare = self._final_objects()
        notes = list(self.notes)
        if self.hold_poses:
            notes.append("the poses follow the odometry (no bound on each pose: the boxes do not move them)")
        est = self._est.array
        if self.loop_closure is not None:
            self.loop_closure.look(final=True)  # the submaps left at the end
            notes += self.loop_closure.notes()
            seq, est, landmarks = self._closed(seq, landmarks)
        optimizer = LevenbergMarquardt(max_iterations=max_iterations, relative_tolerance=tolerance)
        solved, trajectory = self._final_solve(seq, tracks, landmarks, notes, optimizer if final_batch else None,
                                               say, est)
        tracks, landmarks, pairs = self._undoubled(solved, tracks, landmarks, notes)
        if pairs:  # solved again without the merged objects (the batch run's rule)
            solved, trajectory = self._final_solve(seq, tracks, landmarks, notes,
                                                   optimizer if final_batch else None, say, est)
        if self.loop_closure is not None:
            check = self.loop_closure.closure.check if self.loop_closure.closure is not None else None
            trajectory = {**trajectory, "start": "loops", "loop_closure": self.loop_closure.as_dict(),
                          "checks": trajectory.get("checks", []) + ([] if check is None else [check.as_dict()])}
        failed, short, need = self._unmapped(rare)
        labels = {**self._merged, **{k: self._label(k) for k in self.landmarks}}
        notes += [f"{short} tentative tracks with fewer than {need} detections discarded"] if short else []
        screened = self._intake.summary()
        notes += [screened] if screened else []
        record = {"mode": "online-" + self.associate}
        unbounded = absolute_sigma(self._sigmas) is None
        result = map_result(self.method, solved, labels, dict(self._initial), seq.timestamps,
                            failed, priors=seq.priors, given_poses=unbounded and not solved.fixed)
        result = observed_by(result, tracks, seq)
        return dataclasses.replace(result, notes=notes, association=record, trajectory=trajectory)

    def _closed(self, seq: Sequence, landmarks: dict) -> tuple[Sequence, np.ndarray, dict]:
        """(sequence, pose estimates, landmarks) of the final batch with the loop closure's
        corrections (``_corrected``): the poses held there are the corrected ones; as they
        are before a loop closed."""
        moved = self._correction(len(self))
        if moved is None:
            return seq, self._est.array, landmarks
        T, move = moved
        objects = {k: as_landmark(move(k, as_ellipsoid(v)), self.method) for k, v in landmarks.items()}
        return dataclasses.replace(seq, poses_tum=to_tum(T)), np.asarray(T.wxyz_xyz), objects

    def _undoubled(self, solved: Optimised, tracks: list, landmarks: dict, notes: list) -> tuple[list, dict, list]:
        """After the loop closure corrected the poses (automatic association): the objects the
        drift doubled (seen again after the odometry drifted, mapped again where the drifted
        poses put them) lie on each other; each such pair (``overlapping_duplicates`` on the
        final batch's objects, as the batch run) joined (``merged_tracks``). (tracks,
        landmarks from the solved values, pairs); unchanged when nothing was corrected."""
        if self.loop_closure is None or self.loop_closure.poses is None or self._tracker is None:
            return tracks, landmarks, []
        ells = {k: as_ellipsoid(solved.values[L(k)]) for k in landmarks}
        pairs = overlapping_duplicates(ells, {tr.id: tr.label for tr in tracks},
                                       {tr.id: len(tr.frames) for tr in tracks})
        if not pairs:
            return tracks, landmarks, []
        kept = {k: solved.values[L(k)] for k in landmarks}
        tracks, said = merged_tracks(tracks, kept, pairs)
        notes += said
        return tracks, kept, pairs

    def _final_objects(self) -> tuple[list, dict, dict]:
        """(tracks, landmarks, dropped) of the final batch: the objects now, less those the
        batch run's rule for spurious automatic tracks drops ({id: why})."""
        landmarks = dict(self.landmarks)
        tracks = [self._track(k) for k in sorted(landmarks)]
        rare = {}
        if self._tracker is not None:  # the batch run's rule for spurious automatic tracks
            rare = drop_rarely_detected(self._context(), tracks,
                                         {k: as_ellipsoid(v) for k, v in landmarks.items()})
            for k in rare:
                landmarks.pop(k)
            tracks = [tr for tr in tracks if tr.id in landmarks]
        return tracks, landmarks, rare

    def _final_solve(self, seq: Sequence, tracks: list, landmarks: dict, notes: list, optimizer, say,
                     est: np.ndarray) -> tuple[Optimised, dict]:
        """The final batch (``optimizer``; None: the online estimates as they are) over every
        frame and view from the pose estimates ``est`` (F, 7), its trajectory checked against
        the odometry's walk (refused: solved again with the poses held); (what was solved,
        map.json's ``trajectory``)."""
        ctx = SequenceContext.of(seq)
        measured = {k: self._measured[k] for k in landmarks if k in self._measured}
        unbounded, hold = absolute_sigma(self._sigmas) is None, self.hold_poses
        fixed = [X(i) for i in range(len(self))] if hold else []
        graph = build_graph(ctx, tracks, landmarks, self.method, self._user_sigmas, measured, odometry=not hold)
        values = initial_values(est, landmarks)
        say(f"{'final batch optimisation' if optimizer is not None else 'online map'}: {len(values)} "
            f"variables, {len(graph)} factors")
        trajectory: dict = {}
        if optimizer is not None:
            res = optimizer.optimize(graph, values, fixed=fixed)
            if unbounded and not hold:  # no further than the odometry can have drifted
                est = np.stack([np.asarray(res.values[X(i)].wxyz_xyz) for i in range(len(self))])
                check = check_trajectory("the final batch", ctx.wxyz_xyz, est,
                                         walk_covariances(ctx.wxyz_xyz, self._sigmas, seq.segments))
                trajectory["checks"] = [check.as_dict()]
                if not check.accepted:
                    notes.append(check.note())
                    fixed = [X(i) for i in range(len(self))]
                    graph = build_graph(ctx, tracks, landmarks, self.method, self._user_sigmas, measured,
                                        odometry=False)
                    res = optimizer.optimize(graph, values, fixed=fixed)
            values = res.values
        else:
            res = _Unchanged(graph, values)  # type: ignore[assignment]  # the figures only
        if unbounded:
            trajectory["start"] = "held" if fixed else "input"
        return Optimised(values=values, graph=graph, result=res, iterations=res.iterations,
                         initial_cost=res.initial_cost, fixed=fixed), trajectory

    def _unmapped(self, rare: dict) -> tuple[dict, int, int]:
        """(failed {id: why}, tentative tracks discarded, the detections a track needs): the
        tracks that are no object, and why."""
        failed = {**self.failed, **rare}
        need = self._views_needed()
        short = 0
        for k in self._views:
            if k in self.landmarks:
                continue
            if len(self._views[k]) < need and self._tracker is not None:
                short += 1  # a tentative track, discarded as the batch association does
            elif len(self._views[k]) < self.min_views:
                failed.setdefault(k, too_few_views(len(self._views[k]), self.min_views))
            else:
                failed.setdefault(k, "not initialised: the boxes do not give an ellipsoid in front of the cameras")
        return failed, short, need


class _Unchanged:
    """The figures of a result without an optimisation (the cost at the given values)."""

    def __init__(self, graph, values):
        c = Problem(graph, values).cost()
        self.initial_cost = self.final_cost = c
        self.iterations, self.converged, self.reason = 0, True, "online estimates (no final batch)"


def run_online(seq: Sequence, method: str | Method | RunSettings = "multi-spd", *,
               progress=None, warmup: Sequence | None = None, **settings):
    """Replay a sequence through an ``OnlineMapper``, frame by frame in timestamp order:
    (``MapResult``, the ``FrameRecord`` of every frame). ``method`` and ``settings`` as
    ``OnlineMapper``'s; ``associate`` None: by instance id when every detection has one,
    else auto (``default_association``); the settings' ``online.final_batch``,
    ``max_iterations`` and ``tolerance`` are ``OnlineMapper.finish``'s. ``warmup``: a
    sequence for ``OnlineMapper.warmup`` before the first frame (as a live mapper would, so
    that the frames' times do not include compilation). ``online.realtime``: each frame is
    added when its time since the first frame has passed, as a camera delivers them (with
    ``online.background``, how a live mapper runs). ``progress(message)`` every 100
    frames."""
    say = progress or (lambda message: None)
    run = as_online_settings(method, settings)
    if not run.class_table:
        seq = without_class_table(seq)
    if run.associate is None:
        run = run.replace(associate=default_association(seq))
    mapper = OnlineMapper(seq.camera, seq.priors, run, name=seq.name)
    if warmup is not None:
        say(f"online: warm-up on {warmup.name} ({len(warmup)} frames)")
        say(f"online: warm-up took {mapper.warmup(warmup):.1f} s")
    by_frame: dict = {}
    for d in seq.detections:
        by_frame.setdefault(d.frame, []).append(d)
    meas: dict = {}
    for m in seq.ellipsoids or ():
        meas.setdefault(m.frame, []).append(m)
    replay(seq, mapper, by_frame, meas, lambda n, total: say(
        f"online: frame {n} of {total}, {mapper.records[-1].objects} objects"), realtime=mapper.online.realtime)
    result = mapper.finish(progress=say)
    return result, list(mapper.records)


def replay(seq: Sequence, mapper: OnlineMapper, detections: dict, ellipsoids: dict, progress=None,
           realtime: bool = False) -> None:
    """Add the frames of ``seq`` to ``mapper`` in timestamp order: each its pose, its
    ``detections[frame]`` and ``ellipsoids[frame]`` (lists, default none), a later segment's
    first frame as a new segment (``Sequence.segments``); ``realtime``: each when its time
    since the first frame has passed. ``progress(n, frames)`` every 100 frames and at the
    last."""
    order = np.argsort(np.asarray(seq.timestamps), kind="stable")
    segments = set(int(k) for k in seq.segments)
    t_first, start = (float(seq.timestamps[order[0]]) if len(order) else 0.0), time.perf_counter()
    for n, i in enumerate(order):
        if realtime:
            time.sleep(max(0.0, start + float(seq.timestamps[i]) - t_first - time.perf_counter()))
        mapper.add_frame(seq.timestamps[i], seq.poses_tum[i], detections=detections.get(int(i), ()),
                         ellipsoids=ellipsoids.get(int(i), ()), new_segment=int(i) in segments)
        if progress is not None and ((n + 1) % 100 == 0 or n + 1 == len(order)):
            progress(n + 1, len(order))


@dataclass(frozen=True)
class ReplayedStart:
    """``replayed_start``'s answer: the poses the replay ended at (F, 7, jaxlie's wxyz_xyz),
    its objects {track id: landmark value}, and its tracks (automatic association: the
    online tracker's, made with the poses as the replay corrected them; else None)."""

    poses: np.ndarray
    landmarks: dict
    tracks: list | None = None


def replayed_start(seq: Sequence, tracks, run: RunSettings, progress=None) -> ReplayedStart:
    """Where a batch run on a drifting trajectory starts (``InitialPoses.INCREMENTAL``): the
    frames of ``seq`` replayed in order through an ``OnlineMapper`` with ``run``'s method,
    sigmas and views, without a final batch. ``tracks``: the batch association's, given to
    the mapper as instance ids (with the measured ellipsoids of those ids); None: the
    detections of ``seq`` associated by the online tracker, which predicts each frame's
    objects from the poses as corrected so far, so an object seen again after the odometry
    drifted is found again where the drifted poses would put a new one. The fixed-lag
    smoother moves each new pose with the objects it sees, so a re-observed object pulls
    the poses back before the next ones are predicted from them: the batch, started there,
    no longer has to bend the whole drift out at once."""
    say = progress or (lambda message: None)
    by_frame: dict = {}
    meas: dict = {}
    if tracks is None:
        for d in seq.detections:
            by_frame.setdefault(d.frame, []).append(d)
    else:
        for tr in tracks:
            for f, b in zip(np.asarray(tr.frames, dtype=int), np.asarray(tr.boxes, dtype=float).reshape(-1, 4)):
                by_frame.setdefault(int(f), []).append((tr.label, b, 1.0, int(tr.id)))
        ids = {int(tr.id) for tr in tracks}
        for m in seq.ellipsoids or ():
            if m.instance is not None and int(m.instance) in ids:
                meas.setdefault(m.frame, []).append(m)
    settings = run.replace(associate=Associate.AUTO if tracks is None else Associate.INSTANCES, screen=False,
                           online=OnlineSettings(final_batch=False), initial_poses="input", drift_interval=0.0,
                           hold_trajectory=False)
    mapper = OnlineMapper(seq.camera, seq.priors, settings, name=seq.name)
    replay(seq, mapper, by_frame, meas, lambda n, total: say(
        f"incremental initialisation: frame {n} of {total}, {len(mapper.landmarks)} objects"))
    mapper.wait()
    order = np.argsort(np.asarray(seq.timestamps), kind="stable")
    poses = np.empty((len(order), 7))
    poses[order] = mapper.estimates
    found = mapper.tracks() if tracks is None else None
    return ReplayedStart(poses, dict(mapper.landmarks), found)
