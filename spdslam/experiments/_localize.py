"""``spdslam localize``: a new recording mapped in its own frame, then put into a saved map's
frame from the objects alone (``mapping.localize_objects``), with the agreement of its boxes
and the map's projected objects (``evaluation.check_sequence``, as ``spdslam check --map``
measures it); ``spdslam merge``: two recordings registered that way and mapped as one.
docs/map-reuse.md."""

from __future__ import annotations

import numpy as np

from ..evaluation import check_sequence
from ..mapping import (
    LocalizationError,
    confirm_by_boxes,
    joined_sequence,
    localize_objects,
    localized_result,
    moved_sequence,
    refine_localization,
    transform_ellipsoid,
)
from ._batch import map_sequence

__all__ = ["localize_sequence", "merge_recordings"]


def localize_sequence(seq, map_objects, settings, *, sim3: bool = False, tolerance: float = 0.15,
                      refine: bool = True, refine_scale: bool = False, progress=None):
    """(the run of ``seq`` moved into the map's frame (a ``MapResult``), the
    ``mapping.Localization``, localization.json's content). ``refine``: the transform
    found from the objects refined with the recording's boxes (``mapping.refine_localization``;
    the objects' transform is kept in localization.json's ``from_objects``; under Sim(3) the
    scale too only with ``refine_scale``). Raises
    ``mapping.LocalizationError`` when the objects do not fix a unique transform, or the
    recording's boxes contradict it (``mapping.confirm_by_boxes``;
    nothing is written: the caller writes afterwards) and ``ValueError`` when the run itself
    fails."""
    say = progress or (lambda message: None)
    if len(map_objects) < 3:  # before the recording is mapped: nothing could change it
        raise LocalizationError(f"fewer than three usable matches: the map has {len(map_objects)} "
                                f"object{'s' if len(map_objects) != 1 else ''}")
    result, _ = map_sequence(seq, settings, progress=progress)
    say(f"localisation: {len(result.objects)} objects of the recording against {len(map_objects)} of the map")
    loc = localize_objects(result.objects, map_objects, sim3=sim3, tolerance=tolerance)
    first = loc
    if refine:
        say("localisation: refining the transform with the recording's boxes")
        loc = refine_localization(seq, result.objects, map_objects, loc, poses_tum=result.poses_tum,
                                  refine_scale=refine_scale)
    moved = localized_result(result, loc)
    share, predicted = confirm_by_boxes(seq, loc, map_objects, moved.poses_tum[:, 1:])
    doc = loc.as_dict()
    doc["box_agreement"] = {"share": share, "predicted": predicted}
    if refine:
        doc["from_objects"] = {"T_map_sequence": first.T_map_sequence.tolist(), "scale": float(first.scale),
                               "center_rms": first.rms}
    try:
        check = check_sequence(seq, objects=map_objects, poses_tum=moved.poses_tum)
        overall = check["sources"][0]["overall"]
        doc["agreement"] = {"reference": "the map's objects seen from the localised poses",
                            **{k: overall[k] for k in ("pairs", "iou", "center_offset_px", "size_ratio")
                               if k in overall}}
    except (ValueError, KeyError, IndexError) as e:
        doc["agreement"] = {"error": str(e)}
    return moved, loc, doc


def _partner(e, label: str, objects, tolerance: float):
    """The id of the object of ``objects`` [(id, label, Ellipsoid)] of ``label`` whose centre
    is nearest e's, within ``tolerance`` (m); None when there is none."""
    best, dist = None, tolerance
    for oid, lab, other in objects:
        d = float(np.linalg.norm(np.asarray(other.center) - np.asarray(e.center)))
        if lab == label and d <= dist:
            best, dist = oid, d
    return best


def merge_recordings(seq_a, objects_a, seq_b, objects_b, settings, *, sim3: bool = False,
                     tolerance: float = 0.15, refine: bool = True, progress=None):
    """One map of two recordings of one place: B's objects (its own map, B's frame)
    localised against A's (``mapping.localize_objects``, then refined with B's boxes against
    A's objects unless ``refine`` is False), B's sequence moved into A's frame
    and appended to A's (``mapping.joined_sequence``), and the two mapped as one sequence,
    so that an object seen in both is one object estimated from both recordings' boxes.
    Returns (the ``MapResult``, the joined sequence it maps, the ``Localization``,
    merge.json's content: for each object of the merged map, the object of A and of B it
    continues (None where it has none), and the counts). Raises
    ``mapping.LocalizationError`` when B cannot be localised."""
    say = progress or (lambda message: None)
    loc = localize_objects(objects_b, objects_a, sim3=sim3, tolerance=tolerance)
    say(f"merge: {len(loc.matches)} objects of B matched to A's (centre rms {loc.rms:.3f} m)")
    if refine:
        say("merge: refining the transform with B's boxes against A's objects")
        loc = refine_localization(seq_b, objects_b, objects_a, loc)  # B's input poses: B's run is not at hand
    joined = joined_sequence(seq_a, moved_sequence(seq_b, loc.T_map_sequence, loc.scale))
    result, _ = map_sequence(joined, settings, progress=progress)
    in_a = [(o.id, o.label, o.ellipsoid) for o in objects_a]
    in_b = [(o.id, o.label, transform_ellipsoid(o.ellipsoid, loc.T_map_sequence, loc.scale)) for o in objects_b]
    rows = [{"id": int(o.id), "label": o.label,
             "from_a": _partner(o.ellipsoid, o.label, in_a, tolerance),
             "from_b": _partner(o.ellipsoid, o.label, in_b, tolerance)} for o in result.objects]
    used_a = {r["from_a"] for r in rows if r["from_a"] is not None}
    used_b = {r["from_b"] for r in rows if r["from_b"] is not None}
    doc = {
        "objects": rows,
        "in_both": sum(r["from_a"] is not None and r["from_b"] is not None for r in rows),
        "only_a": sum(r["from_a"] is not None and r["from_b"] is None for r in rows),
        "only_b": sum(r["from_a"] is None and r["from_b"] is not None for r in rows),
        "new": sum(r["from_a"] is None and r["from_b"] is None for r in rows),
        "a_not_kept": sorted(int(i) for i, _, _ in in_a if i not in used_a),
        "b_not_kept": sorted(int(i) for i, _, _ in in_b if i not in used_b),
        "localization": loc.as_dict(),
        "frames": {"a": len(seq_a), "b": len(seq_b)},
    }
    return result, joined, loc, doc
