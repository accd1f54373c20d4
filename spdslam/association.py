"""Data association: grouping a sequence's detections into tracks, one per object.

Manual association (:func:`tracks_from_instances`) groups detections by their ``instance``
id. A negative instance id marks a detection known to be false (clutter, e.g. injected by
the demo generator): it belongs to no object and manual association leaves it out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .sequence import Sequence

__all__ = ["Track", "tracks_from_instances"]


@dataclass(frozen=True)
class Track:
    """The detections of one object: its id, label, frame indices and boxes (k, 4)."""

    id: int
    label: str
    frames: np.ndarray
    boxes: np.ndarray


def tracks_from_instances(seq: Sequence) -> list:
    """Group detections by their ``instance`` id (manual association); negative ids
    (known false detections) are left out."""
    missing = [d for d in seq.detections if d.instance is None]
    if missing:
        raise ValueError(
            f"{len(missing)} of {len(seq.detections)} detections have no instance id; "
            "manual association needs the instance column (or use automatic association)"
        )
    groups: dict = {}
    for d in seq.detections:
        if d.instance >= 0:
            groups.setdefault(d.instance, []).append(d)
    tracks = []
    for k in sorted(groups):
        ds = sorted(groups[k], key=lambda d: d.frame)
        labels = sorted({d.label for d in ds})
        label = max(labels, key=lambda lab: sum(d.label == lab for d in ds))
        tracks.append(
            Track(int(k), label, np.array([d.frame for d in ds]), np.array([d.box for d in ds]))
        )
    return tracks
