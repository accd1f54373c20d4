"""``spdslam localize``: a new recording mapped in its own frame, then put into a saved map's
frame from the objects alone (``mapping.localize_objects``), with the agreement of its boxes
and the map's projected objects (``evaluation.check_sequence``, as ``spdslam check --map``
measures it). docs/map-reuse.md."""

from __future__ import annotations

from ..evaluation import check_sequence
from ..mapping import LocalizationError, localize_objects, localized_result
from ._batch import map_sequence

__all__ = ["localize_sequence"]


def localize_sequence(seq, map_objects, settings, *, sim3: bool = False, tolerance: float = 0.15,
                      progress=None):
    """(the run of ``seq`` moved into the map's frame (a ``MapResult``), the
    ``mapping.Localization``, localization.json's content). Raises
    ``mapping.LocalizationError`` when the objects do not fix a unique transform (nothing is
    written: the caller writes afterwards) and ``ValueError`` when the run itself fails."""
    say = progress or (lambda message: None)
    if len(map_objects) < 3:  # before the recording is mapped: nothing could change it
        raise LocalizationError(f"fewer than three usable matches: the map has {len(map_objects)} "
                                f"object{'s' if len(map_objects) != 1 else ''}")
    result, _ = map_sequence(seq, settings, progress=progress)
    say(f"localisation: {len(result.objects)} objects of the recording against {len(map_objects)} of the map")
    loc = localize_objects(result.objects, map_objects, sim3=sim3, tolerance=tolerance)
    moved = localized_result(result, loc)
    doc = loc.as_dict()
    try:
        check = check_sequence(seq, objects=map_objects, poses_tum=moved.poses_tum)
        overall = check["sources"][0]["overall"]
        doc["agreement"] = {"reference": "the map's objects seen from the localised poses",
                            **{k: overall[k] for k in ("pairs", "iou", "center_offset_px", "size_ratio")
                               if k in overall}}
    except (ValueError, KeyError, IndexError) as e:
        doc["agreement"] = {"error": str(e)}
    return moved, loc, doc
