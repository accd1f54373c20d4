"""An online mapper that starts from a saved map: localise first, then extend it.

``LocalizingMapper`` is an ``OnlineMapper`` (frames added one at a time, mapped in the
odometry's frame as always) that also holds a saved map's objects. Whenever the online map
has gained an object since the last try (and has at least three), its objects are matched to
the saved map's (``localize_objects``); a transform from at least ``ONLINE_MIN_MATCHES``
objects that the next try (with more objects, or ``CONFIRM_FRAMES`` frames later) confirms
is taken, and later tries that agree with it replace it.
From then on ``current_map`` is the saved map extended: the saved objects as they were, the
recording's objects that match none of them added with new ids, and the poses, all in the
saved map's frame. ``finish`` maps the
recording (``OnlineMapper.finish``), localises again with every object, refines the transform
with the recording's boxes (``refine_localization``) and returns the extended map as a
``MapResult`` in the saved map's frame. An object seen again keeps the saved map's estimate:
re-estimating it from both recordings' boxes needs both recordings (``spdslam merge``).
docs/map-reuse.md.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from ..io import MapObject
from ._online import OnlineMap, OnlineMapper
from ._reuse import (
    Localization,
    LocalizationError,
    localize_objects,
    localized_result,
    refine_localization,
    transform_ellipsoid,
    transform_poses_tum,
)

__all__ = ["LocalizingMapper", "ONLINE_MIN_MATCHES"]

#: The matched objects a ``LocalizingMapper`` needs before it takes a transform (and then
#: only once the next try confirms it): on fr2_desk a transform from the first three objects,
#: three frames in, was 26° and 75° off (docs/map-reuse.md).
ONLINE_MIN_MATCHES = 4
#: Frames after which a transform awaiting confirmation is tried again, even if no object
#: was added meanwhile (the objects' estimates have moved on).
CONFIRM_FRAMES = 10


class LocalizingMapper(OnlineMapper):
    """``OnlineMapper`` that starts from ``map_objects`` (``io.MapObject`` s of a saved map,
    e.g. ``io.read_map(RUN)[1]``): module docstring. ``sim3``: also estimate the recording's
    scale; ``tolerance``: metres within which a matched centre must land
    (``localize_objects``); the other arguments are ``OnlineMapper``'s.

    ``localization`` is None until the objects fix a transform (``reason`` says why not
    yet): one from at least ``min_matches`` matched objects that the next try (when an object
    is added, or ``CONFIRM_FRAMES`` frames later) confirms (puts the recording's objects
    within the tolerance of where it did);
    ``localized_at`` is the frame count then and ``first_localization`` that transform. Each
    later try that agrees replaces ``localization``, and ``finish`` replaces it with one from
    every object, refined. ``localize_seconds`` is the time spent trying: in the caller's
    thread, or in the background (``background=True``) in the worker's, on each map it
    publishes (``localized_at`` then counts the frames that map used)."""

    #: no loop closure: the transform to the saved map is found on the recording's own frame
    #: (a localised run with loops: not built)
    closes_loops = False

    def __init__(self, map_objects, camera, priors=None, method="multi-spd", *, sim3: bool = False,
                 tolerance: float = 0.15, min_matches: int = ONLINE_MIN_MATCHES, **settings):
        super().__init__(camera, priors, method, **settings)
        self.map_objects = list(map_objects)
        if not self.map_objects:
            raise ValueError("a saved map to start from has no objects")
        ids = [int(o.id) for o in self.map_objects]
        if len(set(ids)) != len(ids):
            raise ValueError("the saved map's object ids are not unique")
        self.sim3, self.tolerance = bool(sim3), float(tolerance)
        self.localization: Localization | None = None
        self.localized_at: int | None = None
        self.first_localization: Localization | None = None
        self.reason = "no objects mapped yet"
        self.min_matches = int(min_matches)
        self._candidate: Localization | None = None
        self._candidate_at = 0
        self.localize_seconds = 0.0
        self._tried_with = 0
        self._first_new_id = max(ids) + 1
        self.watch(self._due, self._step)  # in the caller's thread after each frame, or the worker's

    def _due(self, count: int, frames: int) -> bool:
        """Whether to try: at least three objects, and more than at the last try, or a
        transform awaiting confirmation for ``CONFIRM_FRAMES`` frames."""
        waiting = self._candidate is not None and self.localization is None \
            and frames - self._candidate_at >= CONFIRM_FRAMES
        return count >= 3 and (count > self._tried_with or waiting)

    def _step(self, objects: dict, frames: int) -> None:
        """One try with ``objects`` ({id: (label, ellipsoid)}, the recording's frame) after
        ``frames`` frames, and what it decides (class docstring)."""
        mine = self._as_map_objects(objects)
        found = self._try(mine)
        if found is None:
            return
        if self.localization is not None:  # a later transform from more objects, if it agrees
            if self._agree(self.localization, found, mine):
                self.localization = found
        elif len(found.matches) < self.min_matches:
            self.reason = f"{len(found.matches)} objects matched: waiting for {self.min_matches}"
        elif self._candidate is not None and self._agree(self._candidate, found, mine):
            self.localization = self.first_localization = found
            self.localized_at = frames
        else:
            self._candidate, self._candidate_at = found, frames
            self.reason = f"a transform from {len(found.matches)} objects, to be confirmed by the next try"

    @staticmethod
    def _as_map_objects(objects: dict) -> list:
        return [MapObject(int(k), label, e) for k, (label, e) in sorted(objects.items())]

    def _try(self, objects: list) -> Localization | None:
        t0 = time.perf_counter()
        self._tried_with = len(objects)
        try:
            return localize_objects(objects, self.map_objects, sim3=self.sim3, tolerance=self.tolerance)
        except LocalizationError as e:
            self.reason = str(e)
            return None
        finally:
            self.localize_seconds += time.perf_counter() - t0

    def _agree(self, a: Localization, b: Localization, objects: list) -> bool:
        """Whether two transforms put the recording's objects in the same places: median
        displacement of their centres within the tolerance."""
        c = np.array([np.asarray(o.ellipsoid.center, float) for o in objects])
        return bool(np.median(np.linalg.norm(a.apply(c) - b.apply(c), axis=1)) <= self.tolerance)

    def _new_objects(self, objects: list, loc: Localization) -> list:
        """The recording's objects (moved into the map's frame) that are none of the saved
        map's: not matched, and no saved object of their label within the tolerance."""
        matched = {int(a) for a, _ in loc.matches}
        saved = [(o.label, np.asarray(o.ellipsoid.center, float)) for o in self.map_objects]
        out = []
        for o in objects:
            if int(o.id) in matched:
                continue
            e = transform_ellipsoid(o.ellipsoid, loc.T_map_sequence, loc.scale)
            c = np.asarray(e.center, float)
            if any(label == o.label and np.linalg.norm(c - sc) <= self.tolerance for label, sc in saved):
                continue
            out.append(replace(o, id=self._first_new_id + int(o.id), ellipsoid=e))
        return out

    def current_map(self, covariances: bool = False) -> OnlineMap:
        """Before localisation: ``OnlineMapper.current_map`` (the recording's frame). After:
        the saved map extended by the recording's new objects, with the poses, in the saved
        map's frame (ids of new objects: the recording's id plus one more than the saved
        map's largest; covariances: of the new objects, in their chart before the move)."""
        snap = super().current_map(covariances)
        loc = self.localization
        if loc is None:
            return snap
        new = self._new_objects(self._as_map_objects(snap.objects), loc)
        objects = {int(o.id): (o.label, o.ellipsoid) for o in self.map_objects}
        objects.update({int(o.id): (o.label, o.ellipsoid) for o in new})
        poses = transform_poses_tum(snap.poses_tum, loc.T_map_sequence, loc.scale) if len(snap.poses_tum) \
            else snap.poses_tum
        cov = {self._first_new_id + k: c for k, c in snap.covariances.items()
               if self._first_new_id + k in objects}
        return OnlineMap(objects, poses, cov, frames=snap.frames)

    def finish(self, final_batch=None, max_iterations=None, tolerance=None, progress=None):
        """The extended map as a ``MapResult`` in the saved map's frame (module docstring);
        when the objects never fixed a transform, the recording's own ``MapResult`` in its
        frame, with a note that says why (``localization`` stays None)."""
        say = progress or (lambda message: None)
        result = super().finish(final_batch, max_iterations, tolerance, progress)
        found = self._try(result.objects)  # every object: the surest transform there is
        loc = self.localization = found or self.localization
        if loc is None:
            return replace(result, notes=[*result.notes, f"not localised against the saved map: {self.reason}"])
        say(f"localised against the saved map from {len(loc.matches)} objects; refining with the boxes")
        loc = self.localization = refine_localization(self.sequence(), result.objects, self.map_objects, loc,
                                                      poses_tum=result.poses_tum)
        moved = localized_result(result, loc)
        new = self._new_objects(result.objects, loc)
        new_ids = {int(o.id) for o in new}
        first = [replace(o, id=self._first_new_id + int(o.id)) for o in moved.initial_objects
                 if self._first_new_id + int(o.id) in new_ids]
        note = (f"started from a saved map of {len(self.map_objects)} objects: {len(loc.matches)} seen again "
                f"(kept as saved), {len(new)} new")
        return replace(moved, objects=[*self._seen_again(moved.objects, loc), *new],
                       initial_objects=[*self.map_objects, *first], notes=[*moved.notes, note])

    def _seen_again(self, objects: list, loc) -> list:
        """The saved map's objects, each seen again with the recording's ``observed_by``
        added to its own (where the saved map records one); the estimates as saved."""
        again = {int(b): int(a) for a, b in loc.matches}
        recorded = {int(o.id): o.observed_by for o in objects}
        out = []
        for o in self.map_objects:
            extra = recorded.get(again.get(int(o.id), -1))
            if o.observed_by is not None and extra:
                o = replace(o, observed_by=(*o.observed_by, *extra))
            out.append(o)
        return out
