"""How well an automatic association grouped the detections, against the instance ids a
sequence carries (a synthetic generator's, or an annotation's): ``association_scores``."""

from __future__ import annotations

import numpy as np

from ..io import Sequence

__all__ = ["association_scores"]


def association_scores(tracks, seq: Sequence) -> dict:
    """Precision and recall of ``tracks`` against the sequence's instance ids.

    Each track maps to the ground-truth instance (id ≥ 0) holding the majority of its
    detections (ties: the smaller id; a track of false detections only maps to none), and
    each instance keeps at most one track: the one with the most of its detections (ties:
    the earlier track); the other tracks map to none. A detection is *correct* when its
    track maps to the detection's own instance. Then

        precision = correct / detections in tracks,
        recall    = correct / detections with instance ≥ 0,

    so false detections (instance < 0) in a track count against precision only. An empty
    denominator gives 1.0 (nothing claimed, nothing to find). Tracks are matched to the
    detections by (frame, box); a box that is no detection of ``seq`` raises ``ValueError``,
    and so does a sequence without instance ids.

    Returns {precision, recall, correct, assigned, true_detections, false_assigned,
    tracks, instances, matched_instances, mapping {track id: instance or None}}.
    """
    inst = np.array([-1 if d.instance is None else d.instance for d in seq.detections], dtype=int)
    if any(d.instance is None for d in seq.detections):
        raise ValueError("association scores need the instance ids of the detections")
    idx = seq.detection_indices(tracks)
    best: dict = {}  # instance -> (count, -order, track order)
    target: list[int | None] = []
    m: int | None  # an instance id
    for k, g in enumerate(idx):
        ids, counts = np.unique(inst[g][inst[g] >= 0], return_counts=True)
        if ids.size == 0:
            target.append(None)
            continue
        m = int(ids[np.argmax(counts)])  # np.unique sorts: argmax takes the smaller id on ties
        target.append(m)
        c = int(counts.max())
        if m not in best or c > best[m][0]:
            best[m] = (c, k)
    mapping = {}
    correct = 0
    for k, (tr, g) in enumerate(zip(tracks, idx)):
        m = target[k]
        if m is not None and best[m][1] != k:
            m = None
        mapping[int(tr.id)] = m
        if m is not None:
            correct += int(np.sum(inst[g] == m))
    assigned = int(sum(g.size for g in idx))
    n_true = int(np.sum(inst >= 0))
    false_assigned = int(sum(np.sum(inst[g] < 0) for g in idx))
    return {
        "precision": correct / assigned if assigned else 1.0,
        "recall": correct / n_true if n_true else 1.0,
        "correct": correct,
        "assigned": assigned,
        "true_detections": n_true,
        "false_assigned": false_assigned,
        "tracks": len(tracks),
        "instances": int(np.unique(inst[inst >= 0]).size),
        "matched_instances": len(best),
        "mapping": mapping,
    }
