"""Detections that cannot be a box of an object, left out before association, each with its
reason (``report.md`` lists the counts):

- ``duplicate``: a box whose IoU with a higher-scored box of the same frame exceeds
  ``DUPLICATE_IOU``, whatever the labels: a detector's second box on one object (a can boxed
  as both cup and bottle), which association would otherwise map as a second object;
- ``truncated``: every edge within the truncation margin of the image border (nothing of the
  object's outline is measured);
- ``aspect``: a width / height ratio no view of an object of its class can give. An
  ellipsoid with semi-axes a ≥ b ≥ c seen from anywhere has a silhouette whose box ratio lies
  in [c/a, a/c] (exactly so in orthographic projection; perspective changes it by the
  object's size over its depth, a few per cent here); with the class prior's uncertainty the
  box is refused outside [c/a, a/c] widened by ``ASPECT_MARGIN``.

The screen needs labels, boxes and the camera; nothing here uses poses or ground truth.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from ..geometry import box_iou
from ..io import Sequence, class_prior

__all__ = ["ASPECT_MARGIN", "DUPLICATE_IOU", "SCREEN_REASONS", "Screening", "screen_detections",
           "screen_frame", "screen_summary"]

#: Two boxes of one frame with IoU above this are one object boxed twice.
DUPLICATE_IOU = 0.7
#: The factor by which the class's possible box ratios [c/a, a/c] are widened.
ASPECT_MARGIN = 1.5
SCREEN_REASONS = {
    "duplicate": f"IoU > {DUPLICATE_IOU} with a higher-scored box of the frame (one object boxed twice)",
    "truncated": "every edge at the image border (truncated on all sides)",
    "aspect": "a width/height ratio no view of an object of its class gives",
}


@dataclass
class Screening:
    """The kept sequence, and {reason: [(detection index in the input, text)]} of the
    detections left out."""

    sequence: Sequence
    dropped: dict = field(default_factory=dict)

    def counts(self) -> dict:
        return {k: len(v) for k, v in self.dropped.items() if v}

    def summary(self) -> str:
        """One line: how many boxes were left out, by reason, with one example each."""
        return screen_summary(self.dropped, sum(self.counts().values()) + len(self.sequence.detections))


def screen_summary(dropped: dict, total: int) -> str:
    """One line of {reason: [(index, text)]} out of ``total`` detections."""
    c = {k: len(v) for k, v in dropped.items() if v}
    if not c:
        return "no detection left out by the screen"
    parts = [f"{n} {k} ({SCREEN_REASONS[k]}; e.g. {dropped[k][0][1]})" for k, n in c.items()]
    return f"{sum(c.values())} of {total} detections left out: " + "; ".join(parts)


def screen_frame(dets: list, camera, priors, truncation_margin: float | None = 5.0) -> list:
    """(reason, text) or None for each of one frame's detections (the module docstring's
    rules; duplicates greedily by decreasing score)."""
    out: list = [None] * len(dets)
    if not dets:
        return out
    boxes = np.stack([d.box for d in dets])
    order = np.argsort(-np.array([d.score for d in dets]), kind="stable")
    ranked = boxes[order]
    iou = box_iou(ranked[:, None], ranked[None]) if len(dets) > 1 else np.zeros((1, 1))  # pairwise
    kept: list = []
    for j, i in enumerate(order):
        hit = [m for m in kept if iou[j, m] > DUPLICATE_IOU]
        if hit:
            other = dets[order[hit[0]]]
            out[i] = ("duplicate", f"a {dets[i].label} box at frame {dets[i].frame} under a "
                                   f"{other.label} box (IoU {iou[j, hit[0]]:.2f})")
        else:
            kept.append(j)
    w, h = boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]
    for i, d in enumerate(dets):
        if out[i] is not None:
            continue
        b = boxes[i]
        if truncation_margin is not None:
            m = float(truncation_margin)
            if b[0] <= m and b[1] <= m and b[2] >= camera.width - m and b[3] >= camera.height - m:
                out[i] = ("truncated", f"a {d.label} box at frame {d.frame}")
                continue
        cp = class_prior(priors, d.label)
        if cp is None or not (w[i] > 0 and h[i] > 0):
            continue
        r = np.sort(np.asarray(cp.radii, float))
        lo, hi = r[0] / r[2] / ASPECT_MARGIN, r[2] / r[0] * ASPECT_MARGIN
        ratio = w[i] / h[i]
        if not lo <= ratio <= hi:
            out[i] = ("aspect", f"a {d.label} box {w[i]:.0f}×{h[i]:.0f} px at frame {d.frame} "
                                f"(ratio {ratio:.2f} outside {lo:.2f}–{hi:.2f})")
    return out


def screen_detections(seq: Sequence, truncation_margin: float | None = 5.0) -> Screening:
    """The sequence without the detections the module docstring describes (instance ids
    kept: a known false detection stays for manual association to leave out)."""
    dets = seq.detections
    drop: dict = {}
    gone = np.zeros(len(dets), bool)
    by_frame: dict = {}
    for i, d in enumerate(dets):
        by_frame.setdefault(d.frame, []).append(i)
    for idx in by_frame.values():
        for i, why in zip(idx, screen_frame([dets[i] for i in idx], seq.camera, seq.priors,
                                            truncation_margin)):
            if why is not None:
                gone[i] = True
                drop.setdefault(why[0], []).append((i, why[1]))
    drop = {k: sorted(drop[k]) for k in SCREEN_REASONS if k in drop}
    kept = [d for d, g in zip(dets, gone) if not g]
    return Screening(dataclasses.replace(seq, detections=kept), drop)
