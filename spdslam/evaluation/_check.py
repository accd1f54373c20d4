"""Consistency of a sequence's inputs (``spdslam check``): do the detection boxes agree with
reference objects projected with the poses and the camera?

Reference objects are the ground-truth objects when the sequence has them, else a map's
objects (the reprojection of the map). Each is projected into every frame with the poses
interpolated at the detection's timestamp (camera-to-world, linear in the centre and
spherical-linear in the rotation, only between two poses at most ``max_gap`` s apart), and
each detection is paired with the visible object of its label whose projected box overlaps it
most (IoU ≥ ``min_iou``), one detection per object and frame. Over the pairs:

- 2D IoU, centre offset (detected − projected, px) and size ratio (detected / projected),
  per object and overall (medians);
- the detection rate: frames with a paired box / frames that see the object whole;
- a scan of time offsets δ (poses at t + δ): the δ with the highest median IoU;
- the box convention: the same pairs read as [x, y, w, h], [cx, cy, w, h] or [y1, x1, y2, x2];
- lens distortion, when the measured boxes and the coefficients are given: the pipeline's
  undistorted boxes against the pinhole projection, the measured boxes against the same (no
  correction), and the measured boxes against the box of the distorted projected outline
  (the exact model);
- with ground-truth poses as well as given ones: the statistics with each, and the constant
  rotation between the two in the camera frame (R_given⁻¹ R_gt after aligning the given
  trajectory), which moves every object mapped on the given poses.

Pairs are formed once per pose source at δ = 0 and kept for the convention and distortion
comparisons; the scan forms them again at each δ. Nothing here optimises.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

from ..geometry import (
    Ellipsoid,
    Equidistant,
    box_iou,
    distort_points,
    dual_quadric,
    in_front,
    project_box,
    project_cuboid_box,
    project_dual_quadric,
)
from ..geometry.se3 import from_tum, interpolate_tum
from ._ellipses import conic_ellipses, ellipses_points
from ._metrics import associate_timestamps
from ._report import ground_truth_in_map_frame, to_groundtruth

__all__ = [
    "BOX_CONVENTIONS",
    "CheckReference",
    "check_findings",
    "camera_frame_offset",
    "check_sequence",
    "interpolate_poses",
    "match_detections",
    "pair_detections",
    "reference_of_ground_truth",
]

#: Readings of a stored box b = (b0, b1, b2, b3) as [u_min, v_min, u_max, v_max].
BOX_CONVENTIONS = {
    "x1 y1 x2 y2": lambda b: b,
    "x y w h": lambda b: np.stack([b[:, 0], b[:, 1], b[:, 0] + b[:, 2], b[:, 1] + b[:, 3]], 1),
    "cx cy w h": lambda b: np.stack([b[:, 0] - b[:, 2] / 2, b[:, 1] - b[:, 3] / 2,
                                     b[:, 0] + b[:, 2] / 2, b[:, 1] + b[:, 3] / 2], 1),
    "y1 x1 y2 x2": lambda b: b[:, [1, 0, 3, 2]],
}
#: Time offsets scanned by default (s): the poses at t + δ.
DEFAULT_OFFSETS = np.round(np.arange(-0.2, 0.2001, 0.02), 4)
#: A time offset is reported when it raises the median IoU by more than this.
TIME_OFFSET_GAIN = 0.02
#: A detection pairs with a projected object only above this IoU.
DEFAULT_MIN_IOU = 0.3


@dataclass(frozen=True)
class CheckReference:
    """Objects to project and the poses to project them with: ``ids``, ``labels``,
    ``ellipsoids`` (in the poses' frame), ``poses_tum`` (N, 8) TUM rows with timestamps,
    ``name`` (e.g. "given poses")."""

    name: str
    ids: list
    labels: list
    ellipsoids: list
    poses_tum: np.ndarray


def interpolate_poses(poses_tum, times, max_gap: float) -> tuple[np.ndarray, np.ndarray]:
    """(poses (n, 7) ``tx ty tz qx qy qz qw``, ok (n,)) of the trajectory ``poses_tum`` (N, 8,
    sorted by time) at ``times``: linear in the centre, spherical-linear in the rotation
    between the two poses around each time (``geometry.se3.interpolate_tum``); ``ok`` is False
    where those are more than ``max_gap`` s apart or the time is outside the trajectory (the
    row is then the nearest pose)."""
    P = np.asarray(poses_tum, float)
    t = np.asarray(times, float)
    ts = np.sort(P[:, 0])
    k = np.clip(np.searchsorted(ts, t, side="right") - 1, 0, len(ts) - 1)
    span = ts[np.minimum(k + 1, len(ts) - 1)] - ts[k]
    inside = (t >= ts[0]) & (t <= ts[-1])
    exact = np.isclose(t, ts[k], rtol=0, atol=1e-9)
    ok = inside & (exact | ((span > 0) & (span <= max_gap)))
    return interpolate_tum(P, t), ok


@jax.jit
def _project_all(P, c, poses, camera):
    """Boxes (F, K, 4) of the ellipsoid and of its circumscribed cuboid, and in-front flags
    (F, K), of K ellipsoids (P, c) from F poses."""
    def one(Pk, ck, T):
        e = Ellipsoid(Pk, ck)
        return project_box(e, T, camera), project_cuboid_box(e, T, camera), in_front(e, T, 1e-3)

    over_objects = jax.vmap(one, in_axes=(0, 0, None))
    return jax.vmap(over_objects, in_axes=(None, None, 0))(P, c, poses)


def _project(ref: CheckReference, camera, times, offset: float, max_gap: float):
    """(boxes (n, K, 4), cuboid boxes (n, K, 4), visible (n, K), whole (n, K), poses ok (n,))
    at ``times`` + offset."""
    rows, ok = interpolate_poses(ref.poses_tum, np.asarray(times) + offset, max_gap)
    P = jnp.asarray(np.stack([np.asarray(e.P, float) for e in ref.ellipsoids]))
    c = jnp.asarray(np.stack([np.asarray(e.center, float) for e in ref.ellipsoids]))
    boxes, cuboid, vis = _project_all(P, c, from_tum(rows), camera)
    boxes, vis = np.asarray(boxes), np.asarray(vis) & ok[:, None] & np.all(np.isfinite(np.asarray(boxes)), -1)
    inside = ((boxes[..., 0] >= 0) & (boxes[..., 1] >= 0) & (boxes[..., 2] <= camera.width)
              & (boxes[..., 3] <= camera.height))
    return boxes, np.asarray(cuboid), vis, vis & inside, ok


def match_detections(det_boxes, det_labels, det_slot, proj, visible, obj_labels,
                     min_iou: float = DEFAULT_MIN_IOU):
    """Pairs (detection index, object index, IoU): each detection with the visible object
    of its label whose projected box (``proj`` (S, K, 4) at the detection's slot
    ``det_slot``) overlaps it most, IoU ≥ ``min_iou``; of several detections of one object
    in one slot, the one that overlaps most."""
    det_boxes = np.asarray(det_boxes, float)
    same = np.asarray(det_labels)[:, None] == np.asarray(obj_labels)[None, :]
    iou = box_iou(det_boxes[:, None, :], proj[det_slot])
    iou = np.where(same & visible[det_slot], iou, 0.0)
    k = np.argmax(iou, axis=1) if iou.size else np.zeros(len(det_boxes), int)
    best = iou[np.arange(len(det_boxes)), k] if iou.size else np.zeros(0)
    d = np.flatnonzero(best >= min_iou)
    if d.size == 0:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    # one detection per (slot, object): the best
    order = np.lexsort((-best[d], k[d], det_slot[d]))
    d = d[order]
    key = det_slot[d] * (len(obj_labels) + 1) + k[d]
    first = np.r_[True, key[1:] != key[:-1]]
    d = d[first]
    return d, k[d], best[d]


def _box_stats(det, proj) -> dict:
    """Medians over pairs of boxes (n, 4): IoU, centre offset (det − proj, px), size ratio."""
    det, proj = np.asarray(det, float), np.asarray(proj, float)
    if len(det) == 0:
        return {"pairs": 0, "iou": None, "center_offset_px": None, "size_ratio": None}
    off = (det[:, :2] + det[:, 2:]) / 2 - (proj[:, :2] + proj[:, 2:]) / 2
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = (det[:, 2:] - det[:, :2]) / (proj[:, 2:] - proj[:, :2])
    return {
        "pairs": int(len(det)),
        "iou": float(np.median(box_iou(det, proj))),
        "center_offset_px": np.round(np.median(off, axis=0), 2).tolist(),
        "size_ratio": np.round(np.nanmedian(ratio, axis=0), 3).tolist(),
    }


def _distorted_boxes(ellipsoid_P, centers, poses_rows, camera, distortion, n: int = 64):
    """Boxes (n, 4) of the distorted projected outlines of ellipsoids (P (n,3,3), centres)
    seen from poses (n, 7)."""
    Q = dual_quadric(Ellipsoid(jnp.asarray(ellipsoid_P), jnp.asarray(centers)))
    C = np.asarray(project_dual_quadric(Q, from_tum(poses_rows), camera))
    c, S, ok = conic_ellipses(C)
    pts = distort_points(ellipses_points(c, S, n), camera, distortion)
    out = np.concatenate([pts.min(axis=-2), pts.max(axis=-2)], axis=-1)
    out[~ok] = np.nan
    return out


def _detection_arrays(seq):
    """(timestamps, boxes (D, 4), labels) of the sequence's detections."""
    dets = seq.detections
    times = np.array([d.timestamp for d in dets], dtype=float)
    boxes = np.stack([d.box for d in dets]) if dets else np.zeros((0, 4))
    return times, boxes, np.array([d.label for d in dets])


def pair_detections(seq, ref: CheckReference, offset: float = 0.0,
                    min_iou: float = DEFAULT_MIN_IOU, max_gap: float = 0.1):
    """(detection indices, object indices, IoU) of the sequence's detections paired with the
    reference's objects (``match_detections``) with the poses at each detection's time +
    ``offset``: the association the reference implies (an oracle, with ground-truth
    objects)."""
    times, boxes, labels = _detection_arrays(seq)
    stamps, slot = np.unique(times, return_inverse=True)
    proj, _, vis, _, _ = _project(ref, seq.camera, stamps, offset, max_gap)
    return match_detections(boxes, labels, slot, proj, vis, ref.labels, min_iou)


def _source(seq, ref: CheckReference, offsets, min_iou, max_gap, raw=None, distortion=None) -> dict:
    """The statistics of one reference (objects + poses) against the sequence's boxes."""
    dets = seq.detections
    times, boxes, labels = _detection_arrays(seq)
    # project once per distinct timestamp
    stamps, slot = np.unique(times, return_inverse=True)
    K = len(ref.ellipsoids)

    def pairs_at(offset):
        proj, cuboid, vis, whole, ok = _project(ref, seq.camera, stamps, offset, max_gap)
        d, k, iou = match_detections(boxes, labels, slot, proj, vis, ref.labels, min_iou)
        return proj, cuboid, vis, whole, ok, d, k, iou

    proj, cuboid, vis, whole, ok, d, k, iou = pairs_at(0.0)
    out: dict[str, Any] = {"reference": ref.name, "detections": len(dets),
                           "detections_with_pose": int(ok[slot].sum()) if len(dets) else 0}
    out["overall"] = _box_stats(boxes[d], proj[slot[d], k])
    per = []
    for j in range(K):
        sel = k == j
        row = {"id": ref.ids[j], "label": ref.labels[j], **_box_stats(boxes[d[sel]], proj[slot[d[sel]], j])}
        seen = int(whole[:, j].sum())
        paired_whole = int(np.unique(slot[d[sel]][whole[slot[d[sel]], j]]).size)
        row["cuboid_iou"] = (float(np.median(box_iou(boxes[d[sel]], cuboid[slot[d[sel]], j])))
                             if sel.any() else None)
        row["frames_seen_whole"] = seen
        row["detection_rate"] = paired_whole / seen if seen else None
        per.append(row)
    if any(r["pairs"] == 0 for r in per):  # which labels do detect the unpaired objects?
        anyl = match_detections(boxes, np.zeros(len(dets), int), slot, proj, vis, np.zeros(K, int), min_iou)
        for j, row in enumerate(per):
            if row["pairs"] == 0:
                got, n = np.unique(labels[anyl[0][anyl[1] == j]], return_counts=True)
                row["other_labels"] = {str(a): int(b) for a, b in sorted(zip(got, n), key=lambda x: -x[1])[:3]}
    out["objects"] = per
    scan = []
    for off in offsets:
        if abs(off) < 1e-12:
            scan.append({"offset_s": 0.0, "pairs": int(len(d)), "iou": out["overall"]["iou"]})
            continue
        p2, _, _, _, _, d2, k2, _ = pairs_at(float(off))
        st = _box_stats(boxes[d2], p2[slot[d2], k2])
        scan.append({"offset_s": float(off), "pairs": st["pairs"], "iou": st["iou"]})
    enough = [s for s in scan if s["iou"] is not None and s["pairs"] >= 0.5 * max(len(d), 1)]
    best = max(enough, key=lambda s: s["iou"]) if enough else None
    out["time_offset"] = {"scan": scan, "best_s": None if best is None else best["offset_s"],
                          "best_iou": None if best is None else best["iou"]}
    conv = {}
    for name, read in BOX_CONVENTIONS.items():
        b = read(boxes[d]) if len(d) else np.zeros((0, 4))
        conv[name] = float(np.median(box_iou(b, proj[slot[d], k]))) if len(d) else None
    out["box_convention"] = conv
    if raw is not None and distortion is not None and len(d):
        raw_boxes = np.stack([x.box for x in raw.detections])[d]
        rows, _ = interpolate_poses(ref.poses_tum, times[d], max_gap)
        P = np.stack([np.asarray(ref.ellipsoids[j].P, float) for j in k])
        c = np.stack([np.asarray(ref.ellipsoids[j].center, float) for j in k])
        exact = _distorted_boxes(P, c, rows, seq.camera, distortion)
        good = np.all(np.isfinite(exact), axis=1)
        out["distortion"] = {
            "model": "equidistant" if isinstance(distortion, Equidistant) else "radial-tangential",
            "coefficients": [float(v) for v in distortion],
            "undistorted_vs_pinhole": _box_stats(boxes[d][good], proj[slot[d], k][good])["iou"],
            "measured_vs_pinhole": _box_stats(raw_boxes[good], proj[slot[d], k][good])["iou"],
            "measured_vs_distorted": _box_stats(raw_boxes[good], exact[good])["iou"],
            "pairs": int(good.sum()),
        }
    return out


def reference_of_ground_truth(seq, poses: str = "given") -> CheckReference:
    """The ground-truth objects with the sequence's trajectory (``poses="given"``; the objects
    moved into its frame by ``to_groundtruth``) or with the ground-truth poses ("ground
    truth")."""
    gts = seq.objects_gt
    ids, labels = [int(g.id) for g in gts], [g.label for g in gts]
    if poses == "given":
        T, _ = to_groundtruth(seq)
        cubs, _ = ground_truth_in_map_frame(seq, T)
        rows, name = np.column_stack([seq.timestamps, seq.poses_tum]), "given poses"
    elif poses == "ground truth":
        cubs, rows, name = [g.cuboid for g in gts], np.asarray(seq.groundtruth_tum, float), "ground-truth poses"
    else:
        raise ValueError(f"poses must be 'given' or 'ground truth', got {poses!r}")
    ells = [Ellipsoid.from_axes(c.rotation, c.center, c.half_extents) for c in cubs]
    return CheckReference(name, ids, labels, ells, rows)


def _same_poses(seq) -> bool:
    """Whether the given trajectory is the ground truth's (same centres and rotations at
    the common timestamps, within 1e-6)."""
    gt = np.asarray(seq.groundtruth_tum)
    ia, ib = associate_timestamps(seq.timestamps, gt[:, 0], 1e-6)
    return ia.size == len(seq) and np.allclose(seq.poses_tum[ia, :3], gt[ib, 1:4], atol=1e-6) and \
        np.allclose(np.abs(np.sum(seq.poses_tum[ia, 3:7] * gt[ib, 4:8], 1)), 1.0, atol=1e-6)


def camera_frame_offset(seq) -> dict | None:
    """The rotation between the given and the ground-truth camera orientations in the
    camera frame, R_g⁻¹ R_gt with R_g the given rotation after aligning the given trajectory
    to the ground truth (``to_groundtruth``): its chordal mean (rotation vector, degrees) and
    the spread (RMS angle about the mean, degrees); None without ground-truth poses."""
    T, _ = to_groundtruth(seq)
    if T is None:
        return None
    gt = np.asarray(seq.groundtruth_tum)
    ia, ib = associate_timestamps(seq.timestamps, gt[:, 0], 0.02)
    if ia.size < 3:
        return None
    d = (Rotation.from_matrix(T[:3, :3]) * Rotation.from_quat(seq.poses_tum[ia, 3:7])).inv() \
        * Rotation.from_quat(gt[ib, 4:8])
    mean = d.mean()
    spread = (mean.inv() * d).magnitude()
    return {"rotation_deg": np.round(np.degrees(mean.as_rotvec()), 3).tolist(),
            "angle_deg": float(np.degrees(mean.magnitude())),
            "spread_deg": float(np.degrees(np.sqrt(np.mean(spread**2)))),
            "pairs": int(ia.size)}


def check_sequence(seq, objects=None, poses_tum=None, *, raw=None, distortion=None,
                   offsets=DEFAULT_OFFSETS, min_iou: float = DEFAULT_MIN_IOU,
                   max_gap: float = 0.1) -> dict:
    """The consistency report of a sequence (module docstring) as a JSON-ready dict.

    References: ``objects`` (``MapObject``s in the frame of ``poses_tum``, TUM rows with
    timestamps, default the sequence's trajectory) when given; else the ground-truth objects
    with the given poses (moved into their frame by ``to_groundtruth``) and, when the
    sequence has ground-truth poses, with those too. ``raw``: the sequence with its boxes
    as measured (same detections, in the same order) and ``distortion`` its coefficients
    (k1, k2, p1, p2, k3), for the distortion comparison. Raises ``ValueError`` when there is
    nothing to project (no objects given and no ground-truth objects)."""
    given = np.column_stack([seq.timestamps, seq.poses_tum])
    refs = []
    if objects is not None:
        objects = list(objects)
        if not objects:
            raise ValueError("no objects to project: the map has none")
        poses = given if poses_tum is None else np.asarray(poses_tum, float)
        refs.append(CheckReference("map", [int(o.id) for o in objects], [o.label for o in objects],
                                   [o.ellipsoid for o in objects], poses))
        kind = "mapped objects"
    elif seq.objects_gt:
        refs.append(reference_of_ground_truth(seq, "given"))
        if seq.groundtruth_tum is not None and not _same_poses(seq):
            refs.append(reference_of_ground_truth(seq, "ground truth"))
        kind = "ground-truth objects"
    else:
        raise ValueError("nothing to project: the sequence has no ground-truth objects "
                         "(objects_gt.txt) and no map was given")
    out = {"sequence": seq.name, "objects": kind, "min_iou": float(min_iou),
           "sources": [_source(seq, r, offsets, min_iou, max_gap, raw, distortion) for r in refs]}
    if objects is None and len(refs) > 1:
        off = camera_frame_offset(seq)
        if off is not None:
            out["camera_frame_offset"] = off
    out["findings"] = check_findings(out)
    return out


def check_findings(report: dict) -> list[str]:
    """One line per finding of a ``check_sequence`` report: agreement, time offset, box
    convention, distortion, a systematic image offset, the camera-frame rotation."""
    lines = []
    for s in report["sources"]:
        o = s["overall"]
        name = s["reference"]
        if not o["pairs"]:
            lines.append(f"{name}: no detection overlaps a projected object of its label "
                         f"(IoU ≥ {report['min_iou']}): the boxes, poses or camera disagree entirely")
            continue
        du, dv = o["center_offset_px"]
        lines.append(f"{name}: median IoU {o['iou']:.3f} over {o['pairs']} box pairs, centre offset "
                     f"{du:+.1f} / {dv:+.1f} px, size ratio {o['size_ratio'][0]:.2f} / {o['size_ratio'][1]:.2f}")
        t = s["time_offset"]
        if t["best_s"] is not None and abs(t["best_s"]) > 1e-9 and t["best_iou"] > o["iou"] + TIME_OFFSET_GAIN:
            lines.append(f"{name}: the boxes agree best with the poses {t['best_s']:+.2f} s later "
                         f"(median IoU {t['best_iou']:.3f} against {o['iou']:.3f} at 0): a time offset")
        elif t["best_s"] is not None:
            lines.append(f"{name}: no time offset: the best of the scan, {t['best_s']:+.2f} s, gains "
                         f"{t['best_iou'] - o['iou']:.3f} in median IoU (< {TIME_OFFSET_GAIN})")
        conv = s["box_convention"]
        alt = max((c for c in conv if c != "x1 y1 x2 y2"), key=lambda c: conv[c] or 0.0)
        if (conv[alt] or 0.0) > (conv["x1 y1 x2 y2"] or 0.0):
            lines.append(f"{name}: the boxes fit better read as [{alt}] (IoU {conv[alt]:.3f} against "
                         f"{conv['x1 y1 x2 y2']:.3f}): check the box convention")
        if "distortion" in s:
            dd = s["distortion"]
            agree = dd["undistorted_vs_pinhole"] >= dd["measured_vs_distorted"] - 0.02
            lines.append(f"{name}: lens distortion: undistorted boxes against the pinhole projection "
                         f"{dd['undistorted_vs_pinhole']:.3f}, measured boxes against the distorted "
                         f"projection {dd['measured_vs_distorted']:.3f} (the exact model), measured boxes "
                         f"uncorrected {dd['measured_vs_pinhole']:.3f}: the undistortion "
                         + ("agrees with the lens model" if agree
                            else "loses against the exact model: check the coefficients"))
        if max(abs(du), abs(dv)) > 3.0:
            same = [r for r in s["objects"] if r["pairs"] and max(abs(v) for v in r["center_offset_px"]) > 2.0]
            lines.append(f"{name}: a systematic image offset ({du:+.1f}, {dv:+.1f}) px, {len(same)} of "
                         f"{sum(1 for r in s['objects'] if r['pairs'])} objects beyond 2 px: a camera "
                         "orientation, principal point or object placement bias")
        box_like = [f"{r['label']} ({r['id']}) {r['cuboid_iou']:.3f} against {r['iou']:.3f}" for r in s["objects"]
                    if r["pairs"] and r["cuboid_iou"] > r["iou"] + 0.05]
        if box_like:
            lines.append(f"{name}: the boxes fit the circumscribed cuboid's silhouette better than the "
                         f"ellipsoid's: {', '.join(box_like)} (box-like objects: shape: cuboid in priors.yaml)")
        other = [f"{r['label']} ({r['id']}) is boxed as "
                 + ", ".join(f"{a} ({b})" for a, b in r["other_labels"].items())
                 for r in s["objects"] if r.get("other_labels")]
        if other:
            lines.append(f"{name}: no box of the object's own label, boxes of others: {'; '.join(other)}")
        low = [f"{r['label']} ({r['id']}) {100 * r['detection_rate']:.0f}%" for r in s["objects"]
               if r["detection_rate"] is not None and r["frames_seen_whole"] >= 30 and r["detection_rate"] < 0.1]
        if low:
            lines.append(f"{name}: rarely detected where seen whole: {', '.join(low)}")
    off = report.get("camera_frame_offset")
    if off is not None:
        lines.append(f"the given camera orientations differ from the ground truth's by a constant "
                     f"{off['angle_deg']:.2f}° in the camera frame (rotation vector "
                     f"{', '.join(f'{v:+.2f}' for v in off['rotation_deg'])}°, spread {off['spread_deg']:.2f}°): "
                     "objects mapped on the given poses move by about depth × that angle")
    return lines
