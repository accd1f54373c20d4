"""Relocalisation from objects on fr2_desk's halves (issue 37; docs/map-reuse.md).

fr2_desk is cut into its two halves. One half is mapped as it is (the map); the other is
re-expressed as a new recording would be: every pose moved by G = S · T₀⁻¹ (T₀ its first
pose, so that trial 0 starts at the identity as a new ORB-SLAM2 run would; S a random
rigid motion for the other trials, seeded; under --sim3 also a random scale in [0.5, 2]),
mapped in that frame, and localised against the map (``experiments.localize_sequence``:
from the objects, then refined with the recording's boxes; both answers are scored).
Both ways (map = half 1, recording = half 2, and the reverse), ``--trials`` transforms each.
``--merge``: instead, the halves merged (``experiments.merge_recordings``; half 2 moved by
the first ``--trials`` transforms) and evaluated against fr2_desk's ground truth beside the
whole sequence's run: mean IoU, and duplicates of a matched ground-truth object; and two
controls with half 2 at its own poses (the whole run's frame, no localisation): the halves
joined as one sequence (the whole run again), and half 2 a segment as a merge makes it (no
odometry across the cut, half 2 held as one body and placed by the objects).
``--floors C:S,…``: instead, trial 0 both ways refined with each pair of floors (centre m,
shape) of the priors that hold the map's objects (``mapping.refine_localization``).
``--online``: instead, each half replayed frame by frame through a ``LocalizingMapper``
holding the other half's map: when it localised, and the final transform's error; with
``--background`` the mapper optimises and tries in its worker thread, and the frames come at
the recording's own times.
``--drift``: instead, fr2_desk's odometry with added drift (each frame step composed with
Exp(n), n ~ N(0, diag(σ_t² I₃, σ_r² I₃)), seeded, at the rates of ``--rates``), mapped with
the per-pose bound off (``trajectory_absolute_sigma: .inf``): ATE and mean IoU of the input
and of the run, for each drift correction of ``--drift-intervals`` (seconds between its knots,
``RunSettings.drift_interval``; 0: none; ``--rates ""``: none of fr2_desk); then the same for
the synthetic demo rooms (seeds 0-2, ``--room-frames`` at 10 Hz, default 120, ``--room-objects``,
default 4, each odometry drift of ``--room-drifts``: σ metres and σ/2 radians per step; with
``--room-association auto`` their instance ids removed) and the intervals of ``--room-intervals``.
Each run without knots once per start of ``--initial-poses`` (``RunSettings.initial_poses``:
``input``, the odometry's poses; ``incremental`` (``auto`` before issue 46), the frames replayed
through the online mapper first).

The answer is compared with the motion capture's relation of the two halves: each half's
input trajectory aligned rigidly to the motion capture (M₁, M₂), so that the recording's
frame maps to the map's by M_map⁻¹ M_rec G⁻¹. Prints a row per trial and a summary, and
writes the figures as JSON with --out.

    python3 benchmarks/relocalise.py [--trials 10] [--sim3 [--refine-scale]]
        [--merge | --drift | --online | --floors C:S,…] [--out FILE]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from spdslam.evaluation import evaluate_run, trajectory_alignment
from spdslam.experiments import localize_sequence, merge_recordings
from spdslam.io import read_sequence
from spdslam.mapping import (
    LocalizationError,
    LocalizingMapper,
    OnlineSettings,
    RunSettings,
    joined_sequence,
    localize_objects,
    moved_sequence,
    refine_localization,
    run_sequence,
    transform_ellipsoid,
)
from spdslam.synthetic import drifted_sequence, make_room_sequence

ROOT = Path(__file__).resolve().parents[1]
FR2 = ROOT / "../shared/data/tum_fr2_desk"


def pose_matrix(row) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(row[3:7]).as_matrix()
    T[:3, 3] = row[:3]
    return T


def transform_of(rec, rng, trial: int, sim3: bool):
    """(G, s) of a trial: the first camera at the origin, then a random S (trial > 0)."""
    T0i = np.linalg.inv(pose_matrix(rec.poses_tum[0]))
    S = np.eye(4)
    if trial:
        S[:3, :3] = Rotation.random(random_state=rng).as_matrix()
        S[:3, 3] = rng.uniform(-3.0, 3.0, 3)
    s = float(np.exp(rng.uniform(np.log(0.5), np.log(2.0)))) if sim3 and trial else 1.0
    # x ↦ s R_S (R₀ᵀ x − R₀ᵀ t₀) + t_S: the first camera at the origin, then S (scaled)
    G = np.eye(4)
    G[:3, :3] = S[:3, :3] @ T0i[:3, :3]
    G[:3, 3] = s * S[:3, :3] @ T0i[:3, 3] + S[:3, 3]
    return G, s


def write_out(a, doc) -> None:
    """``doc`` as JSON to ``--out``, when given."""
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
        print(f"wrote {a.out}")


def error_of(M, map_k: int, rec_k: int, G, s: float, c0):
    """(T, scale) ↦ (rotation error °, translation error m at the point c0 of the recording's
    frame, scale error) against the truth: the recording's frame → its ORB frame (G⁻¹, scale
    1/s) → the map's ORB frame (M_map⁻¹ M_rec)."""
    Rg, tg = G[:3, :3], G[:3, 3]
    Minv = np.linalg.inv(M[map_k]) @ M[rec_k]
    R_true = Minv[:3, :3] @ Rg.T
    t_true = Minv[:3, :3] @ (-Rg.T @ tg / s) + Minv[:3, 3]

    def errors(T_est, s_est):
        R_est, t_est = np.asarray(T_est)[:3, :3], np.asarray(T_est)[:3, 3]
        return (float(np.degrees(Rotation.from_matrix(R_est.T @ R_true).magnitude())),
                float(np.linalg.norm(s_est * R_est @ c0 + t_est - (R_true @ c0 / s + t_true))),
                float(s_est * s - 1.0))

    return errors


def online_study(halves, maps, M, settings, a) -> None:
    """Each half replayed frame by frame through a ``LocalizingMapper`` holding the other
    half's map (trial 0's transform: the recording starts at the identity): the frame at
    which it localised and the error of that first transform, the time its tries took, the
    error of the final transform (``finish``: every object, refined), add_frame's p99."""
    rows = []
    for map_k, rec_k in ((1, 2), (2, 1)):
        rec = halves[rec_k]
        G, s = transform_of(rec, np.random.default_rng(a.seed), 0, False)
        seq = moved_sequence(rec, G, s)
        run = settings
        if a.background:
            run = settings.replace(online=dataclasses.replace(settings.online or OnlineSettings(), background=True))
        mapper = LocalizingMapper(maps[map_k], seq.camera, seq.priors, run)
        by_frame: dict = {}
        for d in seq.detections:
            by_frame.setdefault(d.frame, []).append(d)
        t0 = time.perf_counter()
        for i in range(len(seq)):
            if a.background:  # frames at the recording's own times, as a camera delivers them
                time.sleep(max(0.0, seq.timestamps[i] - seq.timestamps[0] - (time.perf_counter() - t0)))
            mapper.add_frame(seq.timestamps[i], seq.poses_tum[i], detections=by_frame.get(i, ()))
        result = mapper.finish()
        loc = mapper.localization
        row = {"map": map_k, "recording": rec_k, "frames": len(seq), "localized_at": mapper.localized_at,
               "localize_seconds": mapper.localize_seconds, "seconds": time.perf_counter() - t0,
               "objects": len(result.objects), "map_objects": len(maps[map_k])}
        if loc is not None:
            errors = error_of(M, map_k, rec_k, G, s, seq.poses_tum[0, :3])
            rot, trans, _ = errors(loc.T_map_sequence, loc.scale)
            first = mapper.first_localization
            rot0, trans0, _ = errors(first.T_map_sequence, first.scale)
            row.update(rotation_deg=rot, translation_m=trans, matches=len(loc.matches),
                       first={"rotation_deg": rot0, "translation_m": trans0, "matches": len(first.matches)},
                       frame_ms_p99=1e3 * float(np.percentile([r.seconds for r in mapper.records], 99)),
                       frame_ms_max=1e3 * max(r.seconds for r in mapper.records),
                       frames_over_33ms=sum(r.seconds > 0.033 for r in mapper.records))
        rows.append(row)
        print(f"online, map {map_k} ← half {rec_k}: {row}")
    print(json.dumps(rows, indent=1))
    write_out(a, {"online": rows})


def floors_study(halves, maps, M, settings, a) -> None:
    """Trial 0 both ways, the objects' transform refined with the map's objects held by
    priors with the floors of ``--floors`` (centre m : shape), one row per floor pair."""
    rows = []
    for map_k, rec_k in ((1, 2), (2, 1)):
        rec = halves[rec_k]
        G, s = transform_of(rec, np.random.default_rng(a.seed), 0, False)
        seq = moved_sequence(rec, G, s)
        result = run_sequence(seq, settings)
        loc = localize_objects(result.objects, maps[map_k])
        errors = error_of(M, map_k, rec_k, G, s, seq.poses_tum[0, :3])
        rot, trans, _ = errors(loc.T_map_sequence, loc.scale)
        rows.append({"map": map_k, "recording": rec_k, "floors": None, "rotation_deg": rot, "translation_m": trans})
        print(f"map {map_k} ← half {rec_k}, the objects alone: {rot:.2f}°, {100 * trans:.1f} cm")
        for item in a.floors.split(","):
            fc, fs = (float(x) for x in item.split(":"))
            ref = refine_localization(seq, result.objects, maps[map_k], loc, poses_tum=result.poses_tum,
                                      floors=(fc, fs))
            rot, trans, _ = errors(ref.T_map_sequence, ref.scale)
            rows.append({"map": map_k, "recording": rec_k, "floors": [fc, fs], "rotation_deg": rot,
                         "translation_m": trans, "note": ref.notes[-1]})
            print(f"map {map_k} ← half {rec_k}, floors {fc} m : {fs}: {rot:.2f}°, {100 * trans:.1f} cm; "
                  f"{ref.notes[-1]}")
    write_out(a, {"floors": rows})


def summary_of(seq, result) -> dict:
    m = evaluate_run(result.as_dict(), result.objects, result.initial_objects, result.poses_tum, seq)
    s = m["summary"]
    return {"objects": len(result.objects), "mean_iou": s["mean_iou"], "matched": s["matched"],
            "duplicates": s["duplicates"], "ate_mm": 1e3 * m["ate"]["optimized"]["rmse"] if "ate" in m else None,
            "ate_input_mm": 1e3 * m["ate"]["input"]["rmse"] if "ate" in m else None}


def drift_settings(settings, intervals: str, starts: str):
    """(knot interval, initial poses, settings) of each run of the drift study: every interval
    with ``input``; ``auto`` and ``incremental`` without knots only (with knots auto starts from
    the input poses, and incremental is refused)."""
    out = []
    for interval in (float(x) for x in intervals.split(",")):
        for start in (x for x in starts.split(",") if x):
            if interval == 0 or start == "input":
                out.append((interval, start, settings.replace(drift_interval=interval, initial_poses=start)))
    return out


def drift_study(fr2, settings, a) -> None:
    rows = []
    for item in (x for x in a.rates.split(",") if x):
        st, sr = (float(x) for x in item.split(":"))
        seq = drifted_sequence(fr2, st, sr, a.seed)
        for interval, start, run in drift_settings(settings, a.drift_intervals, a.initial_poses):
            t0 = time.perf_counter()
            r = run_sequence(seq, run)
            row = {"sigma_t": st, "sigma_r": sr, "drift_interval": interval, "initial_poses": start,
                   **summary_of(seq, r), "seconds": time.perf_counter() - t0}
            rows.append(row)
            print(f"drift {st} m, {sr} rad per frame, knots {interval:g} s apart, start {start}: {row}")
    rooms = []
    for drift in (float(x) for x in a.room_drifts.split(",") if x):
        for seed in range(3):
            room = make_room_sequence(seed, frames=a.room_frames, objects=a.room_objects, drift=drift)
            base = settings
            if a.room_association == "auto":  # the detections without their instance ids
                room = dataclasses.replace(room, detections=[dataclasses.replace(d, instance=None)
                                                             for d in room.detections])
                base = settings.replace(associate="auto")
            for interval, start, run in drift_settings(base, a.room_intervals, a.initial_poses):
                t0 = time.perf_counter()
                r = run_sequence(room, run)
                m = summary_of(room, r)
                row = {"seed": seed, "drift": drift, "drift_interval": interval, "initial_poses": start,
                       "ate_input_mm": m["ate_input_mm"], "ate_mm": m["ate_mm"], "mean_iou": m["mean_iou"],
                       "duplicates": m["duplicates"], "objects": m["objects"], "objects_gt": len(room.objects_gt),
                       "association": a.room_association, "seconds": time.perf_counter() - t0}
                rooms.append(row)
                print(f"room {seed}, drift {drift} per step, knots {interval:g} s apart, start {start}: {row}")
    print(json.dumps({"drift": rows, "rooms": rooms}, indent=1))
    write_out(a, {"drift": rows, "rooms": rooms})


def merge_study(fr2, halves, settings, a) -> None:
    rng = np.random.default_rng(a.seed)
    t0 = time.perf_counter()
    whole = summary_of(fr2, run_sequence(fr2, settings))
    print(f"whole sequence: {whole} ({time.perf_counter() - t0:.1f} s)")
    controls = {}  # half 2 at its own poses (the whole run's frame): which part of the merge costs
    for name, segments in (("one_sequence", False), ("half_2_a_segment", True)):
        joined = joined_sequence(halves[1], halves[2])
        joined = joined if segments else dataclasses.replace(joined, segments=())
        controls[name] = summary_of(joined, run_sequence(joined, settings))
        print(f"halves joined at their own poses, {name.replace('_', ' ')}: {controls[name]}")
    map_a = run_sequence(halves[1], settings).objects
    map_b = run_sequence(halves[2], settings).objects
    rows = []
    for trial in range(a.trials):
        G, s = transform_of(halves[2], rng, trial, a.sim3)
        seq_b = moved_sequence(halves[2], G, s)
        objs_b = [dataclasses.replace(o, ellipsoid=transform_ellipsoid(o.ellipsoid, G, s)) for o in map_b]
        t0 = time.perf_counter()
        result, joined, loc, doc = merge_recordings(halves[1], map_a, seq_b, objs_b, settings, sim3=a.sim3)
        row = {"trial": trial, **summary_of(joined, result), "in_both": doc["in_both"], "only_a": doc["only_a"],
               "only_b": doc["only_b"], "new": doc["new"], "seconds": time.perf_counter() - t0}
        rows.append(row)
        print(f"merge, trial {trial}: {row}")
    out = {"whole": whole, "controls": controls, "merges": rows}
    print(json.dumps(out, indent=1))
    write_out(a, out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sequence", type=Path, default=FR2)
    ap.add_argument("--trials", type=int, default=10, help="transforms per direction")
    ap.add_argument("--sim3", action="store_true", help="random scale in [0.5, 2] too, localised with Sim(3)")
    ap.add_argument("--refine-scale", action="store_true",
                    help="with --sim3: the boxes refine the scale too (by default it stays the objects' layout's)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--merge", action="store_true", help="merge the halves instead (see above)")
    ap.add_argument("--drift", action="store_true", help="drifted odometry instead (see above)")
    ap.add_argument("--floors", default=None,
                    help="centre:shape floor pairs of the priors that hold the map's objects, comma-separated: "
                         "trial 0 refined with each instead")
    ap.add_argument("--online", action="store_true",
                    help="each half replayed through a LocalizingMapper holding the other's map instead")
    ap.add_argument("--background", action="store_true",
                    help="with --online: the mapper in the background (optimisations and tries in its worker), "
                         "the frames given at the recording's own times")
    ap.add_argument("--rates", default="0:0,0.0005:0.00025,0.001:0.0005,0.002:0.001",
                    help="σ_t:σ_r (m:rad per frame) of --drift, comma-separated")
    ap.add_argument("--drift-intervals", default="0,15",
                    help="with --drift: seconds between the knots of the drift correction, comma-separated (0: none)")
    ap.add_argument("--room-drifts", default="0.005,0.01",
                    help="with --drift: the demo rooms' odometry drifts (m per step), comma-separated ('' : none)")
    ap.add_argument("--room-intervals", default="0,1,3,6,12",
                    help="with --drift: the rooms' knot intervals (s), comma-separated")
    ap.add_argument("--room-objects", type=int, default=4, help="with --drift: objects in each room")
    ap.add_argument("--room-frames", type=int, default=120, help="with --drift: frames of each room (10 Hz)")
    ap.add_argument("--room-association", choices=("given", "auto"), default="given",
                    help="with --drift: the rooms' instance ids as given, or removed and the tracks associated")
    ap.add_argument("--initial-poses", default="input,incremental",
                    help="with --drift: RunSettings.initial_poses of each run without knots, comma-separated "
                         "(input: the odometry's poses; incremental: a replay through the online mapper "
                         "first; auto: loops, docs/drift.md); runs with knots start from the input poses")
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()
    fr2 = read_sequence(a.sequence)
    n = len(fr2)
    halves = {1: fr2.subset(np.arange(0, n // 2)), 2: fr2.subset(np.arange(n // 2, n))}
    settings = RunSettings.of("multi-spd")
    if a.merge:
        return merge_study(fr2, halves, settings, a)
    if a.drift:
        return drift_study(fr2, settings, a)
    maps, M = {}, {}
    for k, h in halves.items():
        t0 = time.perf_counter()
        maps[k] = run_sequence(h, settings).objects
        M[k] = trajectory_alignment(np.c_[h.timestamps, h.poses_tum], h.groundtruth_tum)
        print(f"map of half {k}: {len(maps[k])} objects ({time.perf_counter() - t0:.1f} s)")
    if a.online:
        return online_study(halves, maps, M, settings, a)
    if a.floors:
        return floors_study(halves, maps, M, settings, a)
    rng = np.random.default_rng(a.seed)
    rows = []
    for map_k, rec_k in ((1, 2), (2, 1)):
        rec = halves[rec_k]
        for trial in range(a.trials):
            G, s = transform_of(rec, rng, trial, a.sim3)
            seq = moved_sequence(rec, G, s)
            t0 = time.perf_counter()
            row = {"map": map_k, "recording": rec_k, "trial": trial, "scale_applied": s}
            try:
                _, loc, doc = localize_sequence(seq, maps[map_k], settings, sim3=a.sim3, refine_scale=a.refine_scale)
            except LocalizationError as e:
                row.update(localised=False, reason=str(e), seconds=time.perf_counter() - t0)
                rows.append(row)
                print(f"map {map_k} ← half {rec_k}, trial {trial}: refused: {e}")
                continue
            errors = error_of(M, map_k, rec_k, G, s, seq.poses_tum[0, :3])
            rot, trans, scale_err = errors(loc.T_map_sequence, loc.scale)
            row.update(localised=True, rotation_deg=rot, translation_m=trans, scale_error=scale_err,
                       matches=len(loc.matches), runner_up=loc.runner_up, center_rms=loc.rms,
                       agreement_iou=doc.get("agreement", {}).get("iou"), seconds=time.perf_counter() - t0)
            if "from_objects" in doc:  # the transform of the objects alone, before the boxes refined it
                o = doc["from_objects"]
                row["objects_only"] = dict(zip(("rotation_deg", "translation_m", "scale_error"),
                                               errors(o["T_map_sequence"], o["scale"])))
            rows.append(row)
            before = row.get("objects_only")
            print(f"map {map_k} ← half {rec_k}, trial {trial}: {len(loc.matches)} matches (rival "
                  f"{loc.runner_up}), rotation error {rot:.2f}°, translation error {100 * trans:.1f} cm"
                  + (f", scale error {100 * scale_err:+.2f} %" if a.sim3 else "")
                  + (f" (objects alone: {before['rotation_deg']:.2f}°, {100 * before['translation_m']:.1f} cm"
                     + (f", {100 * before['scale_error']:+.2f} %" if a.sim3 else "") + ")" if before else "")
                  + f" ({row['seconds']:.1f} s)")
    ok = [r for r in rows if r["localised"]]
    summary = {"trials": len(rows), "localised": len(ok), "sim3": a.sim3}
    if ok:
        for key in ("rotation_deg", "translation_m", "scale_error"):
            v = np.abs([r[key] for r in ok])
            summary[key] = {"median": float(np.median(v)), "max": float(np.max(v))}
        if all("objects_only" in r for r in ok):
            summary["objects_only"] = {}
            for key in ("rotation_deg", "translation_m", "scale_error"):
                v = np.abs([r["objects_only"][key] for r in ok])
                summary["objects_only"][key] = {"median": float(np.median(v)), "max": float(np.max(v))}
    print(json.dumps(summary, indent=1))
    write_out(a, {"summary": summary, "trials": rows})


if __name__ == "__main__":
    main()
