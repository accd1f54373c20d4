"""Metrics and tables of a sequence run (``spdslam run`` / ``evaluate``); the folder is
``experiments.write_run``'s.

Per object (matched to the ground truth by id when every estimated id is a ground-truth id,
else by a Hungarian assignment on 3D IoU among objects of the same label):

- IoU between the circumscribed oriented cuboid of the estimate and the ground-truth cuboid
  (exact convex-polytope intersection, ``evaluation.cuboid_iou``);
- orientation error: the smallest rotation aligning the estimate's axes with the ground
  truth's, whatever their order and sign (``evaluation.orientation_error_deg``);
- centre error (m).

Per sequence: the mean IoU over the ground-truth objects (an object the method did not
map counts 0; the headline), the mean over the matched ones, the mean orientation and
centre errors over the matched ones (and the orientation error over the matched objects
whose ground truth has a clear orientation: three distinct half-extents), and the trajectory ATE
(RMSE after SE(3) alignment)
when ground-truth poses exist.

The frame: the map stays in its trajectory's frame. With ground-truth poses the objects
are compared in the ground truth's frame, moved by ``to_groundtruth`` (4×4), the rigid
motion that best maps the estimated (optimised) trajectory's camera centres onto the
ground truth's over timestamps within 0.02 s (``geometry.align_rigid``, as the ATE and
evo's ``--align``): the map is judged with the trajectory it was estimated with.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import Cuboid, Ellipsoid
from ..io import PEER_MODE, MapObject
from ._metrics import (
    absolute_trajectory_error,
    cuboid_iou,
    orientation_error_deg,
    trajectory_alignment,
)

__all__ = [
    "FRONT_END_NAMES",
    "ObjectMetrics",
    "evaluate_objects",
    "evaluate_run",
    "match_objects",
    "moved",
    "report_markdown",
    "table_iii",
    "to_groundtruth",
]


@dataclass(frozen=True)
class ObjectMetrics:
    id: int
    label: str
    gt_id: int | None
    iou: float
    orientation_deg: float
    center_error: float

    def as_dict(self) -> dict:
        return {
            "id": int(self.id), "label": self.label, "gt_id": self.gt_id,
            "iou": float(self.iou), "orientation_deg": float(self.orientation_deg),
            "center_error": float(self.center_error),
        }


def match_objects(objects, gt_objects, by_id: bool = True) -> dict:
    """{estimated id: ground-truth id}: by id when ``by_id`` and every id is a ground-truth
    id (manual association), else a Hungarian assignment on IoU (same labels only)."""
    gt_ids = {int(g.id) for g in gt_objects}
    if by_id and objects and all(int(o.id) in gt_ids for o in objects):
        return {int(o.id): int(o.id) for o in objects}
    from scipy.optimize import linear_sum_assignment

    iou = np.zeros((len(objects), len(gt_objects)))
    for i, o in enumerate(objects):
        c = Cuboid.from_ellipsoid(o.ellipsoid)
        for j, g in enumerate(gt_objects):
            if o.label == g.label:
                iou[i, j] = cuboid_iou(c, g.cuboid)
    rows, cols = linear_sum_assignment(-iou)
    return {int(objects[i].id): int(gt_objects[j].id) for i, j in zip(rows, cols) if iou[i, j] > 0}


def evaluate_objects(objects, gt_objects, by_id: bool = True) -> tuple[list, dict]:
    """(per-object metrics, summary) of a list of objects with ``id, label, ellipsoid``;
    ``by_id=False`` when the ids are not instance ids (automatic association)."""
    match = match_objects(objects, gt_objects, by_id)
    gts = {int(g.id): g for g in gt_objects}
    rows = []
    for o in objects:
        gid = match.get(int(o.id))
        g = None if gid is None else gts.get(gid)
        if g is None:
            rows.append(ObjectMetrics(o.id, o.label, None, 0.0, float("nan"), float("nan")))
            continue
        c = Cuboid.from_ellipsoid(o.ellipsoid)
        rows.append(ObjectMetrics(
            o.id, o.label, int(g.id), cuboid_iou(c, g.cuboid),
            orientation_error_deg(c.rotation, g.cuboid.rotation),
            float(np.linalg.norm(c.center - g.cuboid.center)),
        ))
    matched = [r for r in rows if r.gt_id is not None]
    oriented = [r for r in matched if clearly_oriented(gts[r.gt_id].cuboid.half_extents)]  # type: ignore[index]
    n_gt = len(gt_objects)
    summary = {
        "objects": len(objects),
        "ground_truth_objects": n_gt,
        "matched": len(matched),
        "precision": len(matched) / len(objects) if objects else float("nan"),
        "recall": len(matched) / n_gt if n_gt else float("nan"),
        "duplicates": count_duplicates(objects, gt_objects, match),
        "mean_iou": float(sum(r.iou for r in matched) / n_gt) if n_gt else float("nan"),
        "mean_iou_matched": float(np.mean([r.iou for r in matched])) if matched else float("nan"),
        "mean_orientation_deg": float(np.mean([r.orientation_deg for r in matched])) if matched else float("nan"),
        "mean_center_error": float(np.mean([r.center_error for r in matched])) if matched else float("nan"),
        "oriented_matched": len(oriented),
        "mean_orientation_deg_oriented": float(np.mean([r.orientation_deg for r in oriented]))
        if oriented else float("nan"),
    }
    return rows, summary


def count_duplicates(objects, gt_objects, match: dict) -> int:
    """The number of unmatched objects that overlap (cuboid IoU > 0) a ground-truth object
    of their label which another object is matched to: a second map object of one real
    object, as a split track leaves it."""
    taken = set(match.values())
    n = 0
    for o in objects:
        if int(o.id) in match:
            continue
        c = Cuboid.from_ellipsoid(o.ellipsoid)
        if any(int(g.id) in taken and g.label == o.label and cuboid_iou(c, g.cuboid) > 0
               for g in gt_objects):
            n += 1
    return n


#: A ground-truth object has a clear orientation when every two of its half-extents differ
#: by more than this fraction of the larger: otherwise a rotation about its symmetry axis
#: is undefined and the orientation error measures noise.
CLEAR_ORIENTATION = 0.1


def clearly_oriented(half_extents) -> bool:
    """Whether the three half-extents are pairwise distinct (``CLEAR_ORIENTATION``)."""
    h = np.sort(np.asarray(half_extents, float))
    return bool(np.all(np.diff(h) > CLEAR_ORIENTATION * h[1:]))


def to_groundtruth(seq, poses_tum=None) -> tuple[np.ndarray | None, str]:
    """(4×4 rigid motion from the trajectory's frame to the ground truth's, or None; why
    not): the alignment of the module docstring for the estimated trajectory ``poses_tum``
    (TUM rows with timestamps; default the sequence's own), the ATE's
    (``trajectory_alignment``); None without ground-truth poses or when they do not fix it
    (fewer than 3 common timestamps, collinear centres)."""
    if seq.groundtruth_tum is None:
        return None, "no ground-truth poses"
    est = np.column_stack([seq.timestamps, seq.poses_tum]) if poses_tum is None else poses_tum
    try:
        return trajectory_alignment(np.asarray(est, float), seq.groundtruth_tum), ""
    except ValueError as e:
        return None, str(e)


def moved(objects, T):
    """``MapObject``s moved by the rigid motion T (4×4): P ← R P Rᵀ, t ← R t + p."""
    if T is None:
        return list(objects)
    R, p = T[:3, :3], T[:3, 3]
    return [MapObject(o.id, o.label, Ellipsoid(R @ np.asarray(o.ellipsoid.P) @ R.T,
                                               R @ np.asarray(o.ellipsoid.center) + p),
                      getattr(o, "uncertainty", None))
            for o in objects]


#: map.json's association modes whose object ids are track ids, not instance ids (a batch
#: run's automatic association, an online run's).
AUTOMATIC_MODES = ("auto", "online-auto")


def evaluate_run(map_dict: dict, objects, initial_objects, poses_tum, seq,
                 align: bool = True) -> dict:
    """Metrics of a run against the sequence's ground truth (what exists of it), the
    objects compared in the ground truth's frame (``to_groundtruth``; ``align=False``
    compares them as mapped, for sequences whose trajectory is in that frame already)."""
    out = {"sequence": seq.name, "method": map_dict["method"]}
    association = map_dict.get("association")
    if not isinstance(association, dict):  # maps written before automatic association
        association = {"mode": "instances"}
    peer = association.get("mode") == PEER_MODE  # another system's map: its keyframes' ATE only
    T, why = (None, "")
    if align and poses_tum is None:
        why = "the map has no trajectory"
    elif align:
        T, why = to_groundtruth(seq, poses_tum)
    if T is not None:
        out["to_groundtruth"] = T.tolist()
    elif seq.groundtruth_tum is not None and align:
        out["not_aligned"] = why
    objects = moved(objects, T)
    initial_objects = None if initial_objects is None else moved(initial_objects, T)
    # automatic track ids, another system's ids: not instance ids
    by_id = association.get("mode") not in AUTOMATIC_MODES and not peer
    if "precision" in association:
        out["association"] = {k: association[k] for k in ("precision", "recall", "tracks", "instances")
                              if k in association}
    if seq.objects_gt:
        rows, summary = evaluate_objects(objects, seq.objects_gt, by_id)
        out["objects"] = [r.as_dict() for r in rows]
        out["summary"] = summary
        if initial_objects is not None:
            rows0, summary0 = evaluate_objects(initial_objects, seq.objects_gt, by_id)
            out["front_end"] = {"objects": [r.as_dict() for r in rows0], "summary": summary0}
    if seq.groundtruth_tum is not None and poses_tum is not None:
        traj_in = np.column_stack([seq.timestamps, seq.poses_tum])
        out["ate"], ate_failures = {}, {}
        pairs = (("map", np.asarray(poses_tum)),) if peer else \
            (("input", traj_in), ("optimized", np.asarray(poses_tum)))
        for key, traj in pairs:
            try:
                out["ate"][key] = absolute_trajectory_error(traj, seq.groundtruth_tum)
            except ValueError as e:  # too few common poses, a path that fixes no alignment
                out["ate"][key], ate_failures[key] = None, str(e)
        if ate_failures:
            out["ate"]["not_computed"] = ate_failures
    return out


FRONT_END_NAMES = {"svd": "Quadric-SVD", "multi": "Quadric-Multi"}


def table_iii(rows) -> str:
    """A Markdown table like the paper's Table III from ``(stage, method, summary)`` rows."""
    lines = [
        "| stage | method | mean IoU | orientation error (°) | centre error (m) | objects |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for stage, name, s in rows:
        lines.append(
            f"| {stage} | {name} | {shown(s['mean_iou'])} | {shown(s['mean_orientation_deg'], '.2f')} | "
            f"{shown(s['mean_center_error'])} | {s['matched']}/{s['ground_truth_objects']} |"
        )
    return "\n".join(lines) + "\n"


def shown(v, spec: str = ".3f", unit: str = "") -> str:
    """``v`` formatted, or "not computed" when it is None or not finite."""
    if v is None or not np.isfinite(v):
        return "not computed"
    return f"{v:{spec}}{unit}"


def ate_line(ate: dict) -> str:
    """One line of the input and optimised ATE RMSE, each "not computed: reason" when so."""
    why = ate.get("not_computed", {})
    if "map" in ate or "map" in why:  # another system's map: its keyframes' or the given poses' (``evaluate_run``)
        a = ate.get("map")
        return (f"ATE RMSE of the map's poses: {1e3 * a['rmse']:.2f} mm ({a['pairs']} poses)." if a else
                f"ATE RMSE of the map's poses: not computed ({why.get('map', 'no ground truth')}).")

    def one(key):
        a = ate.get(key)
        return f"{1e3 * a['rmse']:.2f} mm" if a else f"not computed ({why.get(key, 'no ground truth')})"

    opt = ate.get("optimized")
    pairs = f" ({opt['pairs']} poses)" if opt else ""
    return f"ATE RMSE: input {one('input')}, optimised {one('optimized')}{pairs}."


def report_markdown(metrics: dict, map_dict: dict) -> str:
    lines = [f"# {map_dict['method']} on {metrics['sequence']}", ""]
    if "format" in map_dict:  # another system's map (``io.peer_document``)
        lines.append(f"A map read from {map_dict['source']} ({map_dict['format']}): {len(map_dict['objects'])} "
                     f"objects, {map_dict['keyframes']} keyframes. Its object ids are its own: objects are "
                     "matched to the ground truth by label and overlap.")
    else:
        lines.append(
            f"Parameterisation {map_dict['parameterization']}, {map_dict['iterations']} iterations "
            f"({map_dict.get('reason', '')}), final cost {map_dict['final_cost']:.6g}."
        )
    lines.append("")
    if "summary" in metrics:
        rows = []
        if "front_end" in metrics:
            init = map_dict.get("settings", {}).get("initialization", "")
            rows.append(("front end", FRONT_END_NAMES.get(init, init), metrics["front_end"]["summary"]))
        rows.append(("back end", map_dict["method"], metrics["summary"]))
        s = metrics["summary"]
        if "mean_iou_matched" in s:
            lines += [f"Mean IoU over all {s['ground_truth_objects']} ground-truth objects (a missed one "
                      f"counts 0): {shown(s['mean_iou'])}; over the {s['matched']} matched: "
                      f"{shown(s['mean_iou_matched'])}. Orientation error over the "
                      f"{s.get('oriented_matched', 0)} matched objects with a clear orientation "
                      "(three distinct half-extents): "
                      f"{shown(s.get('mean_orientation_deg_oriented'), '.2f', '°')}.", ""]
        if "precision" in s:
            lines += [f"Objects: {s['objects']} mapped for {s['ground_truth_objects']} in the ground "
                      f"truth; precision {shown(s['precision'])} (matched / mapped; objects the ground "
                      f"truth does not list count as false), recall {shown(s['recall'])} (matched / "
                      f"ground truth), {s['duplicates']} duplicates (an unmatched object overlapping "
                      "a matched ground-truth object of its class).", ""]
        if "to_groundtruth" in metrics:
            lines += ["Objects compared in the ground truth's frame, after aligning the optimised "
                      "trajectory to it (`to_groundtruth` in map.json).", ""]
        lines += [table_iii(rows), "## Objects", "",
                  "| id | label | IoU | orientation error (°) | centre error (m) |",
                  "| --- | --- | --- | --- | --- |"]
        for r in metrics["objects"]:
            lines.append(f"| {r['id']} | {r['label']} | {shown(r['iou'])} | "
                         f"{shown(r['orientation_deg'], '.2f').replace('not computed', '–')} | "
                         f"{shown(r['center_error']).replace('not computed', '–')} |")
        lines.append("")
    else:
        lines += ["No object ground truth (objects_gt.txt): no object metrics.", ""]
    if "association" in metrics:
        a = metrics["association"]
        lines += ["## Data association", "",
                  f"Automatic: {a['tracks']} tracks for {a['instances']} instances, precision "
                  f"{shown(a['precision'])}, recall {shown(a['recall'])} (against the instance ids).", ""]
    if "ate" in metrics:
        lines += ["## Trajectory", "", ate_line(metrics["ate"]), ""]
        a = metrics["ate"]
        if a.get("input") and a.get("optimized") and a["optimized"]["rmse"] > a["input"]["rmse"]:
            lines += [f"**The optimisation made the trajectory worse** (ATE {1e3 * a['input']['rmse']:.2f} → "
                      f"{1e3 * a['optimized']['rmse']:.2f} mm): the boxes moved the poses beyond the input's "
                      "accuracy; see the trajectory noise note below and docs/sequences.md.", ""]
    lines += trajectory_section(map_dict.get("trajectory") or {})
    costs = map_dict.get("cost_by_factor") or {}
    if costs:
        total = sum(costs.values()) or 1.0
        lines += ["## Cost at the optimum, by factor", "", "| factor | cost | share |", "| --- | --- | --- |"]
        lines += [f"| {k} | {v:.6g} | {100 * v / total:.1f} % |" for k, v in costs.items()]
        lines.append("")
    if "not_aligned" in metrics:
        lines += [f"Objects compared as mapped, not in the ground truth's frame: the alignment "
                  f"was not computed ({metrics['not_aligned']}).", ""]
    failed = map_dict.get("failed") or {}
    if failed:
        lines += ["## Objects not mapped", ""] + [f"- {k}: {v}" for k, v in failed.items()] + [""]
    for n in map_dict.get("notes") or []:
        lines.append(f"- note: {n}")
    return "\n".join(lines).rstrip() + "\n"


def trajectory_section(t: dict) -> list:
    """report.md's lines on a trajectory without a bound on each pose (map.json's
    ``trajectory``): where the poses came from, each check against the odometry, the loops."""
    if not t:
        return []
    rounds = t.get("refinement") or []
    done = sum(rf["accepted"] for rf in rounds)
    refined = f", then refined by the boxes ({done} round{'s' * (done > 1)})" if done else ""
    lines = ["## Drift", "", f"The trajectory has no bound on each pose; its poses: {t.get('start', 'input')}{refined} "
                             "(docs/drift.md)."]
    for c in t.get("checks") or []:
        verdict = "accepted" if c["accepted"] else "**refused** (the poses it started from were kept)"
        lines.append(f"- {c['step']}: moved the cameras by {1e3 * c['moved_median_m']:.3g} mm median, "
                     f"{1e3 * c['moved_max_m']:.3g} mm most, at most {c['worst_sigma']:.3g}σ of the odometry's "
                     f"walk (limit {c['limit_sigma']:g}σ): {verdict}.")
    lc = t.get("loop_closure")
    if lc:
        loops = lc.get("loops") or []
        n = {k: sum(lp["status"] == k for lp in loops) for k in ("verified", "rejected", "not verified")}
        lines += ["", f"Loop closure: {len(lc.get('submaps', []))} submaps, {len(loops)} candidate revisits, "
                      f"{n['verified']} verified and used, {n['rejected']} rejected in the pose graph, "
                      f"{n['not verified']} not verified."]
        if loops:
            lines += ["", "| frames | later frames | status | objects matched | box agreement | why |",
                      "| --- | --- | --- | --- | --- | --- |"]
            for lp in loops:
                agree = " / ".join(f"{100 * a:.0f} %" for a in lp.get("box_agreement") or [])
                lines.append(f"| {lp['earlier_frames'][0]}–{lp['earlier_frames'][1]} | {lp['later_frames'][0]}–"
                             f"{lp['later_frames'][1]} | {lp['status']} | {lp['matches']} | {agree or '–'} | "
                             f"{lp.get('reason') or '–'} |")
    if rounds:
        lines += ["", f"Poses refined by the boxes, cross-validated between two halves of the labels: each half's "
                      f"box cost on the poses the other half refined, as a share of it on the poses given (the "
                      f"limit {100 * rounds[0]['limit']:.0f} %), round by round from the poses the last one refined:",
                  ""]
        for rf in rounds:
            halves = " and ".join("{" + ", ".join(h) + "}" for h in rf.get("halves") or [])
            ratios = " and ".join(f"{100 * r:.0f} %" for r in rf.get("ratios") or [])
            lines.append(f"- round {rf['round']}: halves {halves or '–'}, {ratios or '–'}: "
                         + ("**accepted**." if rf["accepted"] else f"not accepted ({rf['reason']})."))
    return lines + [""]


def ground_truth_in_map_frame(seq, T):
    """(ground-truth cuboids, ground-truth TUM rows) moved into the map's frame by T⁻¹
    (``to_groundtruth``; unchanged when T is None)."""
    cuboids = [g.cuboid for g in seq.objects_gt] if seq.objects_gt else None
    traj = seq.groundtruth_tum
    if T is None:
        return cuboids, traj
    from scipy.spatial.transform import Rotation

    R, p = T[:3, :3].T, -T[:3, :3].T @ T[:3, 3]
    if cuboids is not None:
        cuboids = [Cuboid(R @ c.center + p, R @ c.rotation, c.half_extents) for c in cuboids]
    if traj is not None:
        traj = np.array(traj, dtype=float)
        traj[:, 1:4] = traj[:, 1:4] @ R.T + p
        traj[:, 4:8] = (Rotation.from_matrix(R) * Rotation.from_quat(traj[:, 4:8])).as_quat()
    return cuboids, traj
