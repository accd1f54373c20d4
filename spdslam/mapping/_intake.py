"""What the online mapper takes from its caller before anything is mapped: each frame
checked and screened (``FrameIntake``), and the worker thread that takes the checked frames
in and optimises when the mapper runs in the background (``BackgroundWorker``).

``FrameIntake.accept`` refuses, in one line naming the frame, a timestamp that is not finite
or not after the last one, a frame with both or neither of a pose and an odometry step (the
first frame needs a pose), a pose that is not finite, a detection that is not a
``Detection`` or (label, box[, score[, instance]]) or whose box is not x1 < x2, y1 < y2, a
measured ellipsoid that is not an ``EllipsoidDetection``, and, with association by instance
ids, a detection without one; it then drops the detections the batch run's screen drops
(``frontend.screen_frame``), counting them for ``summary``.
"""

from __future__ import annotations

import dataclasses
import threading
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable, Iterable

import jaxlie
import numpy as np

from ..frontend import screen_frame, screen_summary
from ..geometry.se3 import as_pose, from_tum
from ..io import Detection, EllipsoidDetection

__all__ = ["AcceptedFrame", "FrameIntake", "BackgroundWorker"]


@dataclass(frozen=True)
class AcceptedFrame:
    """A frame accepted by ``FrameIntake``, not yet taken into the mapper's state."""

    index: int
    timestamp: float
    pose: np.ndarray  # input T_wc, jaxlie wxyz_xyz
    detections: list
    ellipsoids: list
    new_segment: bool = False


def as_detection(d, frame: int, timestamp: float) -> Detection:
    """A ``Detection`` of this frame from a Detection or (label, box[, score[, instance]])."""
    if isinstance(d, Detection):
        return dataclasses.replace(d, frame=frame, timestamp=timestamp)
    try:
        if isinstance(d, str) or not 2 <= len(d) <= 4 or not isinstance(d[0], str):
            raise ValueError
        label, box, *rest = d
        score = float(rest[0]) if rest else 1.0
        instance = None if len(rest) < 2 or rest[1] is None else int(rest[1])
        return Detection(frame, timestamp, box, label, score, instance)
    except (TypeError, ValueError):
        raise ValueError(f"frame {frame}: a detection must be a Detection or (label, box "
                         f"[x1, y1, x2, y2][, score[, instance]]), got {d!r}") from None


def as_se3(p) -> jaxlie.SE3:
    """T_wc from a ``jaxlie.SE3``, a TUM row tx ty tz qx qy qz qw or a 4×4 matrix."""
    if isinstance(p, jaxlie.SE3):
        return p
    a = np.asarray(p, float)
    if a.shape == (7,):
        return from_tum(a)
    return as_pose(a)


class FrameIntake:
    """The checks and the screen of the frames an online mapper is given (module docstring),
    in the caller's thread. ``camera``, ``priors``, ``margin``: the screen's (``screen``:
    whether to screen); ``by_instances``: association by instance ids."""

    def __init__(self, camera, priors, margin: float | None, screen: bool, by_instances: bool):
        self.camera, self.priors, self.margin = camera, priors, margin
        self.screen, self.by_instances = screen, by_instances
        self.count = 0  # frames accepted
        self.screened: dict = {}  # reason -> [(detection number, text)], as the batch run's screen
        self.detections = 0  # detections given, screened or not
        self._last_time: float | None = None
        self._last_input: Any = None  # jaxlie wxyz_xyz of the last frame accepted

    def accept(self, timestamp, pose, odometry, detections: Iterable, ellipsoids: Iterable,
               new_segment: bool = False) -> AcceptedFrame:
        """The frame checked and screened (module docstring); ``new_segment`` needs a pose
        and a frame before it."""
        f = self.count
        if new_segment and (pose is None or not f):
            raise ValueError(f"frame {f}: a new segment needs a pose and a frame before it")
        t = float(timestamp)
        if not np.isfinite(t):
            raise ValueError(f"frame {f}: the timestamp must be finite, got {timestamp!r}")
        if self._last_time is not None and t <= self._last_time:
            what = "duplicates" if t == self._last_time else "is before"
            raise ValueError(f"frame {f}: timestamp {t:.6f} {what} the last frame's "
                             f"({self._last_time:.6f}); frames must come in increasing time")
        wxyz = self._input_pose(f, pose, odometry)
        dets = self._detections(f, t, detections)
        ellipsoids = list(ellipsoids)
        for m in ellipsoids:
            if not isinstance(m, EllipsoidDetection):
                raise ValueError(f"frame {f}: measured ellipsoids must be EllipsoidDetection, got {m!r}")
        meas = [dataclasses.replace(m, frame=f, timestamp=t) for m in ellipsoids]
        if self.screen:  # the batch run's screen (frontend.screen_detections), frame by frame
            whys = screen_frame(dets, self.camera, self.priors, self.margin)
            for j, why in enumerate(whys):
                if why is not None:
                    self.screened.setdefault(why[0], []).append((self.detections + j, why[1]))
            self.detections += len(dets)
            dets = [d for d, why in zip(dets, whys) if why is None]
        self.count, self._last_time, self._last_input = f + 1, t, wxyz
        return AcceptedFrame(f, t, wxyz, dets, meas, bool(new_segment))

    def _input_pose(self, f: int, pose, odometry) -> np.ndarray:
        """The frame's input T_wc (jaxlie wxyz_xyz): ``pose``, or ``odometry`` after the last."""
        if (pose is None) == (odometry is None):
            raise ValueError(f"frame {f}: give a pose or an odometry step, not "
                             f"{'both' if pose is not None else 'neither'}")
        if pose is None and self._last_input is None:
            raise ValueError("the first frame needs a pose (odometry is relative to the previous frame)")
        T_in = as_se3(odometry if pose is None else pose)
        if pose is None:
            T_in = jaxlie.SE3(self._last_input) @ T_in
        wxyz = np.asarray(T_in.wxyz_xyz, float)
        if not np.all(np.isfinite(wxyz)):
            raise ValueError(f"frame {f}: the pose is not finite")
        return wxyz

    def _detections(self, f: int, t: float, detections: Iterable) -> list:
        dets = [as_detection(d, f, t) for d in detections]
        for i, d in enumerate(dets):
            b = d.box
            if not (np.all(np.isfinite(b)) and b[2] > b[0] and b[3] > b[1]):
                raise ValueError(f"frame {f}: detection {i} has an invalid box {b.tolist()} "
                                 "(expected finite x1 < x2, y1 < y2)")
        if self.by_instances:
            missing = [d for d in dets if d.instance is None]
            if missing:
                raise ValueError(f"frame {f}: {len(missing)} detections without an instance id "
                                 "(association by instance ids needs one on every detection)")
        return dets

    def summary(self) -> str | None:
        """The screen's note (``frontend.screen_summary``), None when it dropped nothing."""
        return screen_summary(self.screened, self.detections) if self.screened else None


class BackgroundWorker:
    """The worker thread of a mapper in the background: ``take(frame, record)`` takes the
    frame in (``ingest(frame)``: whether an optimisation is due) when the worker is idle,
    else queues it, and calls ``record()`` (the frame's record) under the same lock; a due
    optimisation starts the worker, which runs ``optimise()``, takes in every frame queued
    meanwhile, in order, and optimises again (once, on the latest window) if one of them made
    an optimisation due, else stops. An error in the worker is raised by the next
    ``raise_error`` (``take`` and ``wait`` call it)."""

    def __init__(self, ingest: Callable[[AcceptedFrame], bool], optimise: Callable[[], Any]):
        self.ingest, self.optimise = ingest, optimise
        self._lock = threading.Lock()
        self._queue: deque = deque()  # frames accepted while the worker was busy
        self._busy = False
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    @property
    def busy(self) -> bool:
        """Whether the worker is optimising or taking frames in."""
        return self._busy

    @property
    def queued(self) -> int:
        """Frames waiting for the worker."""
        return len(self._queue)

    def take(self, frame: AcceptedFrame, record: Callable[[], Any]) -> Any:
        with self._lock:
            due = False
            if self._busy:
                self._queue.append(frame)
            else:
                due = self.ingest(frame)
            rec = record()
            if due:
                self._busy = True
                self._thread = threading.Thread(target=self._work, name="spdslam-online", daemon=True)
                self._thread.start()
        return rec

    def _work(self) -> None:
        try:
            while True:
                self.optimise()
                due = False
                while True:
                    with self._lock:
                        if not self._queue:
                            if not due:
                                self._busy = False
                                return
                            break
                        frame = self._queue.popleft()
                    due = self.ingest(frame) or due
        except BaseException as e:  # noqa: BLE001 - handed to the caller's thread
            with self._lock:
                self._error = e
                self._queue.clear()
                self._busy = False

    def raise_error(self) -> None:
        """Raise the error the worker met, once."""
        if self._error is not None:
            e, self._error = self._error, None
            raise e

    def wait(self) -> None:
        """Block until the worker has taken in every frame and run the optimisations they
        were due; raise an error it met."""
        while True:
            with self._lock:
                thread = self._thread if self._busy else None
            if thread is None:
                break
            thread.join()
        self.raise_error()
