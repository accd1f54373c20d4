"""Objects against drift (issue 46; docs/drift.md): real recordings with drift added, and the
long synthetic rooms, mapped by default.

Real recordings: fr2_desk (ORB-SLAM2's poses, real YOLOv5 boxes without ids) and the office
recording (../shared/data/tum_fr3_long_office: motion-capture poses, real YOLO boxes
without ids, a camera that comes back to its start), each made a drifting odometry
(``synthetic.drifted_sequence``: every frame step composed with Exp(ε), ε ~ N(0, σ_t² I₃, σ_r²
I₃), no bound on each pose) at the rates of ``--rates`` (σ_t m : σ_r degrees per frame) and
the seeds of ``--seeds``, and mapped by default (``spdslam run``'s settings; with
``--online`` also replayed through the online mapper, in line, and with ``--background``
also with its optimisations and loop closure in the worker thread; ``--realtime``: each frame
added when its time has come, as a camera delivers it, else as fast as the mapper takes
them, when the worker runs one optimisation for all the frames that queued meanwhile). Every
row: the input's ATE and the run's, their ratio, the start the run chose, the box errors' correlation, the loops
found (candidate revisits), verified and rejected, the objects, and the seconds; an online
row also ``add_frame``'s time per frame (median, p99, most: the caller's wait; in line the
loop closure's tries run after it, ``loop_closure_seconds`` in all). With
``--compare input`` each real recording is also mapped with ``--initial-poses input`` (the
boxes move each pose), beside it.

``--localize``: instead, the issue's relocalisation of a drifting recording's last quarter
against its first (the office recording at the rates and seeds above): each quarter mapped
by default (its poses held near its input), then ``spdslam localize``'s steps
(``experiments.localize_sequence``); the transform, when not refused, compared with the drift
between the two quarters (the correction between their middle frames, from the motion
capture): rotation error, and translation error at the last quarter's middle camera.

Synthetic rooms: ``make_room_sequence`` (``--room-frames``, ``--room-objects``, ``--room-drift``
m per step and half that in rad), seeds of ``--room-seeds``, with the detector's failures of
``--room-failures`` (outliers, missed, truncation: ``outliers=0.1, missed=0.1,
truncation=True``) and without instance ids; with ``--room-bias PX`` each object's boxes are
shifted by one offset (σ PX per coordinate, drawn per object) in every view: a detector's bias,
shared over an object's views, as real boxes have it (the refinement by the boxes must not
follow it). ``--start-jitter EPS`` multiplies every multi-constraint start θ by 1 + EPS (the
front end's ``_multi_starts``): how far a row moves under a change of round-off's size.

    python3 benchmarks/drift.py [--recordings fr2,office] [--rates 0.0005:0.025,0.001:0.05,0.003:0.15]
        [--seeds 0,1,2] [--online] [--background] [--realtime] [--compare input] [--rooms/--no-rooms]
        [--submap-seconds 5] [--localize] [--room-bias PX] [--start-jitter EPS] [--out FILE]
        [--against EARLIER.json]

``--submap-seconds 2.5,5,10``: every recording row again with the loop closure's submaps of
each length (``LOOP_SUBMAP_SECONDS``), the rows then named by it: how the loops' registration
error and the drift they measure change with the submap's size (each row's loop errors,
medians, printed).

``--against`` compares each row with the same row of an earlier ``--out`` (a refactoring
must leave them equal to 1e-9).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from spdslam.evaluation import absolute_trajectory_error
from spdslam.experiments import localize_sequence
from spdslam.geometry.se3 import from_tum
from spdslam.io import read_sequence
from spdslam.mapping import LocalizationError, OnlineSettings, RunSettings, run_online, run_sequence
from spdslam.mapping import _loops as loops
from spdslam.synthetic import drifted_sequence, make_room_sequence

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_SUBMAP = loops.LOOP_SUBMAP_SECONDS
#: An input ATE below this (mm) is the ground truth itself.
EXACT_MM = 1e-3
RECORDINGS = {"fr2": ROOT / "../shared/data/tum_fr2_desk", "office": ROOT / "../shared/data/tum_fr3_long_office"}


def matrices(rows) -> np.ndarray:
    """(F, 4, 4) T_wc of TUM rows ``tx ty tz qx qy qz qw``."""
    return np.asarray(from_tum(rows).as_matrix())


def ate_mm(rows, seq) -> float:
    rows = np.asarray(rows, float)
    if rows.shape[1] == 7:
        rows = np.c_[seq.timestamps, rows]
    return 1e3 * absolute_trajectory_error(rows, seq.groundtruth_tum)["rmse"]


def loops_of(result) -> dict:
    """Loops found (candidates), verified and rejected, from the run's ``trajectory`` record,
    and each candidate's frames, status and reason."""
    lc = (result.trajectory or {}).get("loop_closure") or {"loops": []}
    status = [lp["status"] for lp in lc["loops"]]
    return {"loops_found": len(status), "loops_verified": status.count("verified"),
            "loops_rejected": status.count("rejected"),
            "loops": [{k: lp[k] for k in ("frames", "status", "reason")} for lp in lc["loops"]]}


def loop_errors(seq, result) -> list:
    """Each candidate loop that reached a transform: its status, the drift it should measure
    (the true correction between its two frames, from the ground truth) and its error against
    it (rotation °, translation mm at the later frame's camera)."""
    lc = (result.trajectory or {}).get("loop_closure") or {"loops": []}
    gt = np.asarray(seq.groundtruth_tum, float)
    idx = np.clip(np.searchsorted(gt[:, 0], seq.timestamps), 0, len(gt) - 1)
    prev = np.clip(idx - 1, 0, len(gt) - 1)
    idx = np.where(np.abs(gt[prev, 0] - seq.timestamps) < np.abs(gt[idx, 0] - seq.timestamps), prev, idx)
    ok = np.abs(gt[idx, 0] - seq.timestamps) < 0.02
    truth, given = matrices(gt[idx, 1:]), matrices(seq.poses_tum)
    C = truth @ np.linalg.inv(given)  # truth = C · input (up to the ground truth's own frame)
    out = []
    for lp in lc["loops"]:
        if "T_earlier_later" not in lp:
            continue
        a, b = lp["frames"]
        if not (ok[a] and ok[b]):
            continue
        T, G = np.asarray(lp["T_earlier_later"]), np.linalg.inv(C[a]) @ C[b]
        p = given[b][:3, 3]
        E = np.linalg.inv(G) @ T
        sd = np.sqrt(np.diag(np.asarray(lp["covariance"]))) if "covariance" in lp else np.full(6, np.nan)
        out.append({"frames": [a, b], "status": lp["status"],
                    "drift_deg": float(np.degrees(Rotation.from_matrix(G[:3, :3]).magnitude())),
                    "drift_mm": 1e3 * float(np.linalg.norm(G[:3, :3] @ p + G[:3, 3] - p)),
                    "error_deg": float(np.degrees(Rotation.from_matrix(E[:3, :3]).magnitude())),
                    "error_mm": 1e3 * float(np.linalg.norm(T[:3, :3] @ p + T[:3, 3] - (G[:3, :3] @ p + G[:3, 3]))),
                    "sigma_deg": float(np.degrees(np.max(sd[3:])))})
    return out


def row_of(seq, result, seconds: float, **more) -> dict:
    a_in, a_out = ate_mm(seq.poses_tum, seq), ate_mm(result.poses_tum, seq)
    t = result.trajectory or {}
    return {**more, "ate_input_mm": a_in, "ate_mm": a_out, "ratio": a_out / a_in, "start": t.get("start"),
            **loops_of(result), "objects": len(result.objects), "seconds": seconds,
            "checks": t.get("checks", []), "refinement": refinement_of(t), "loop_errors": loop_errors(seq, result)}


def refinement_of(t: dict) -> list | None:
    """The cross-validated refinement by the boxes, round by round (map.json's
    ``trajectory.refinement``): accepted, the two halves' ratios, why not."""
    f = t.get("refinement")
    return None if f is None else [{k: rf[k] for k in ("round", "accepted", "ratios", "reason")} for rf in f]


def recording_rows(a, settings, seconds: float) -> list:
    """The rows of the real recordings (module docstring) with submaps of ``seconds``."""
    loops.LOOP_SUBMAP_SECONDS = seconds  # the study's knob: the module's constant, read when a run cuts
    more = {} if seconds == DEFAULT_SUBMAP else {"submap_seconds": seconds}
    rows = []
    for name in (x for x in a.recordings.split(",") if x):
        base = read_sequence(RECORDINGS[name])
        for rate in (x for x in a.rates.split(",") if x):
            st, sr_deg = (float(x) for x in rate.split(":"))
            for seed in (int(x) for x in a.seeds.split(",") if x):
                seq = drifted_sequence(base, st, np.radians(sr_deg), seed)
                modes = ["default", *(["input"] if a.compare == "input" else []), *(["online"] if a.online else []),
                         *(["online-background"] if a.background else [])]
                for mode in modes:
                    t0 = time.perf_counter()
                    records = None
                    if mode.startswith("online"):
                        result, records = run_online(seq, settings.replace(
                            online=OnlineSettings(background=mode == "online-background", realtime=a.realtime)))
                    else:
                        result = run_sequence(seq, settings if mode == "default"
                                              else settings.replace(initial_poses="input"))
                    r = row_of(seq, result, time.perf_counter() - t0, recording=name, rate=rate, seed=seed,
                               mode=mode, **more, **frame_times(records, result))
                    rows.append(r)
                    show(r)
    loops.LOOP_SUBMAP_SECONDS = DEFAULT_SUBMAP
    return rows


def frame_times(records, result) -> dict:
    """An online run's ``add_frame`` times (ms: median, p99, most) and its loop closure's
    tries and seconds; {} for a batch run."""
    if records is None:
        return {}
    ms = 1e3 * np.array([rec.seconds for rec in records])
    online = ((result.trajectory or {}).get("loop_closure") or {}).get("online", {})
    return {"frame_ms": {"p50": float(np.median(ms)), "p99": float(np.percentile(ms, 99)), "max": float(ms.max())},
            "loop_closure_tries": online.get("tries"), "loop_closure_seconds": online.get("seconds")}


def show(r: dict) -> None:
    what = " ".join(f"{k} {r[k]}" for k in ("recording", "room", "rate", "seed", "mode", "submap_seconds", "bias_px")
                    if k in r)
    loops = f"loops {r['loops_found']}/{r['loops_verified']}/{r['loops_rejected']}"
    refused = [c["step"] for c in r["checks"] if not c["accepted"]]
    print(f"{what}: ATE {r['ate_input_mm']:.1f} → {r['ate_mm']:.1f} mm ({r['ratio']:.2f}×), start {r['start']}, "
          f"{loops} (found/verified/rejected), {r['objects']} objects, {r['seconds']:.1f} s"
          + (f"; refused by the check against the odometry: {', '.join(refused)}" if refused else "")
          + refinement_figures(r)
          + (online_figures(r) if "frame_ms" in r else "") + error_figures(r), flush=True)


def refinement_figures(r: dict) -> str:
    f = r.get("refinement")
    if not f:
        return ""
    rounds = ", ".join(f"{'accepted' if rf['accepted'] else 'refused'} {'/'.join(f'{x:.2f}' for x in rf['ratios']) or '–'}"
                       for rf in f)
    return f"; the boxes' refinement in {sum(rf['accepted'] for rf in f)} rounds ({rounds})"


def error_figures(r: dict) -> str:
    """The loops' median drift to measure and median error (rotation), verified or not."""
    e = r.get("loop_errors") or []
    if not e:
        return ""
    med = {k: float(np.median([x[k] for x in e])) for k in ("drift_deg", "error_deg", "drift_mm", "error_mm")}
    return (f"; {len(e)} loops measure a drift of {med['drift_deg']:.1f}° ({med['drift_mm']:.0f} mm) to "
            f"{med['error_deg']:.1f}° ({med['error_mm']:.0f} mm), medians")


def online_figures(r: dict) -> str:
    return (f"; add_frame p99 {r['frame_ms']['p99']:.1f} ms, most {r['frame_ms']['max']:.0f} ms, loop closure "
            f"{r['loop_closure_seconds'] or 0:.1f} s in {r['loop_closure_tries'] or 0} tries")


def localize_study(a, settings) -> list:
    """The last quarter of each drifted office recording localised against its first (module
    docstring)."""
    base = read_sequence(RECORDINGS["office"])
    rows = []
    for rate in (x for x in a.rates.split(",") if x):
        st, sr_deg = (float(x) for x in rate.split(":"))
        for seed in (int(x) for x in a.seeds.split(",") if x):
            seq = drifted_sequence(base, st, np.radians(sr_deg), seed)
            q = len(seq) // 4
            first, last = np.arange(q), np.arange(len(seq) - q, len(seq))
            C = matrices(base.poses_tum) @ np.linalg.inv(matrices(seq.poses_tum))  # truth = C · input
            mid_a, mid_b = int(first[q // 2]), int(last[q // 2])
            truth = np.linalg.inv(C[mid_a]) @ C[mid_b]  # x_first = truth · x_last, the inputs' frames
            drift_deg = float(np.degrees(Rotation.from_matrix(truth[:3, :3]).magnitude()))
            p = matrices(seq.poses_tum)[mid_b][:3, 3]
            drift_mm = 1e3 * float(np.linalg.norm(truth[:3, :3] @ p + truth[:3, 3] - p))
            t0 = time.perf_counter()
            map_objects = run_sequence(seq.subset(first), settings).objects
            row = {"rate": rate, "seed": seed, "drift_deg": drift_deg, "drift_mm": drift_mm}
            try:
                _, loc, _ = localize_sequence(seq.subset(last), map_objects, settings)
                T = loc.T_map_sequence
                E = np.linalg.inv(truth) @ T
                row.update(status="localised", matches=len(loc.matches), rival=loc.runner_up,
                           rotation_error_deg=float(np.degrees(Rotation.from_matrix(E[:3, :3]).magnitude())),
                           translation_error_mm=1e3 * float(np.linalg.norm(T[:3, :3] @ p + T[:3, 3]
                                                                            - (truth[:3, :3] @ p + truth[:3, 3]))))
            except LocalizationError as e:
                row.update(status="refused", reason=str(e))
            row["seconds"] = time.perf_counter() - t0
            rows.append(row)
            print(f"office {rate} seed {seed}: drift between the quarters {drift_deg:.2f}°, {drift_mm:.0f} mm; "
                  + (f"localised from {row['matches']} objects (rival {row['rival']}): off by "
                     f"{row['rotation_error_deg']:.2f}° and {row['translation_error_mm']:.0f} mm"
                     if row["status"] == "localised" else f"refused: {row['reason']}"), flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--recordings", default="fr2,office", help="of fr2, office, comma-separated ('': none)")
    ap.add_argument("--rates", default="0.0005:0.025,0.001:0.05,0.003:0.15",
                    help="σ_t:σ_r per frame step (m:degrees), comma-separated")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--online", action="store_true", help="each drifted recording also through the online mapper")
    ap.add_argument("--background", action="store_true",
                    help="each drifted recording also through the online mapper with its worker thread")
    ap.add_argument("--submap-seconds", default=str(DEFAULT_SUBMAP),
                    help="the loop closure's submap length (s), comma-separated: each a run of every recording row")
    ap.add_argument("--realtime", action="store_true",
                    help="the online replays at the recording's own rate (as a camera delivers the frames)")
    ap.add_argument("--compare", default="", help="'input': each drifted recording also with --initial-poses input")
    ap.add_argument("--rooms", action=argparse.BooleanOptionalAction, default=True)
    ap.add_argument("--room-frames", type=int, default=400)
    ap.add_argument("--room-objects", type=int, default=24)
    ap.add_argument("--room-drift", default="0.005,0.01,0.02", help="m per step (and half in rad), comma-separated")
    ap.add_argument("--room-seeds", default="0,1,2")
    ap.add_argument("--room-bias", type=float, default=0.0,
                    help="px: each object's boxes shifted by one offset of this σ per coordinate in every view")
    ap.add_argument("--room-failures", action=argparse.BooleanOptionalAction, default=True,
                    help="outliers 0.1, missed 0.1 and truncation")
    ap.add_argument("--start-jitter", type=float, default=0.0,
                    help="multiply each multi-constraint start by 1 + this (round-off's sensitivity)")
    ap.add_argument("--localize", action="store_true", help="instead, the office's last quarter localised against "
                    "its first")
    ap.add_argument("--out", type=Path)
    ap.add_argument("--against", type=Path, help="an earlier --out of this benchmark: each row's ATE against its "
                    "row there (a refactoring's check: the same to 1e-9)")
    a = ap.parse_args()
    settings = RunSettings.of("multi-spd")
    if a.start_jitter:
        jitter_starts(a.start_jitter)
    if a.localize:
        return write_out(a, {"localize": localize_study(a, settings)})
    rooms: list = []
    rows = [r for seconds in (float(x) for x in a.submap_seconds.split(",") if x)
            for r in recording_rows(a, settings, seconds)]
    failures = dict(outliers=0.1, missed=0.1, truncation=True) if a.room_failures else {}
    for drift in (float(x) for x in a.room_drift.split(",") if x and a.rooms):
        for seed in (int(x) for x in a.room_seeds.split(",") if x):
            room = make_room_sequence(seed, frames=a.room_frames, objects=a.room_objects, drift=drift, **failures)
            room = biased(room, a.room_bias, seed)
            t0 = time.perf_counter()
            result = run_sequence(room, settings)
            r = row_of(room, result, time.perf_counter() - t0, room=f"{a.room_objects} objects, {a.room_frames} frames",
                       rate=drift, seed=seed, mode="default", **({"bias_px": a.room_bias} if a.room_bias else {}))
            rooms.append(r)
            show(r)
    # an input at the ground truth (the office's motion capture, undrifted) has an ATE of
    # round-off: its rows are judged by the difference, not the ratio
    exact = [r for r in rows + rooms if r["ate_input_mm"] < EXACT_MM]
    worst = max([r["ratio"] for r in rows + rooms if r not in exact] or [float("nan")])
    print(f"worst ratio to the input's ATE: {worst:.3f}")
    doc = {"recordings": rows, "rooms": rooms, "worst_ratio": worst,
           **({"start_jitter": a.start_jitter} if a.start_jitter else {})}
    if exact:
        doc["worst_difference_mm_at_exact_input"] = max(r["ate_mm"] - r["ate_input_mm"] for r in exact)
        print(f"rows whose input is the ground truth (ATE below {EXACT_MM} mm): {len(exact)}, the run's ATE "
              f"{doc['worst_difference_mm_at_exact_input']:.2g} mm above it at most")
    if a.against:
        doc["against"] = {"file": str(a.against), **compare_rows(rows + rooms, json.loads(a.against.read_text()))}
    write_out(a, doc)


def jitter_starts(eps: float) -> None:
    """Every multi-constraint start θ times 1 + ``eps`` from now on (``--start-jitter``)."""
    import spdslam.frontend._initialization as init_mod

    real = init_mod._multi_starts

    def jittered(*args, **kwargs):
        return [list(np.asarray(s, dtype=float) * (1.0 + eps)) for s in real(*args, **kwargs)]

    init_mod._multi_starts = jittered


def biased(room, px: float, seed: int):
    """The room's detections without instance ids, each object's boxes shifted by one offset
    ~ N(0, px² I₄) (drawn per object, in the order of their ids, from ``seed``) in every view
    (a box the offset would leave less than a pixel wide or high, a sliver at the image's
    border, as it is); the false boxes (instance −1) as they are."""
    rng = np.random.default_rng(seed)
    ids = sorted({d.instance for d in room.detections if d.instance is not None and d.instance >= 0})
    off = {k: rng.normal(0.0, px, 4) for k in ids} if px > 0 else {}

    def shifted(box, k):
        b = box + off.get(k, 0.0)
        return b if b[2] - b[0] >= 1.0 and b[3] - b[1] >= 1.0 else box

    return dataclasses.replace(room, detections=[
        dataclasses.replace(d, box=shifted(d.box, d.instance), instance=None) for d in room.detections])


def compare_rows(rows: list, earlier: dict) -> dict:
    """Each row's ATE and loop counts against the same row (recording or room, rate, seed,
    mode) of an ``earlier`` run of this benchmark; prints and returns the largest relative
    ATE difference, the rows whose counts differ and those the earlier run lacks."""
    def key(r):
        return r.get("recording", r.get("room")), str(r["rate"]), r["seed"], r["mode"], r.get("submap_seconds")

    old = {key(r): r for r in earlier.get("recordings", []) + earlier.get("rooms", [])}
    worst, differ, missing = 0.0, [], []
    for r in rows:
        o = old.get(key(r))
        if o is None:
            missing.append(key(r))
            continue
        worst = max(worst, abs(r["ate_mm"] - o["ate_mm"]) / max(abs(o["ate_mm"]), 1e-12))
        if any(r[f] != o[f] for f in ("loops_found", "loops_verified", "loops_rejected", "objects")):
            differ.append(key(r))
    print(f"against the earlier run: {len(rows) - len(missing)} rows compared, largest relative ATE difference "
          f"{worst:.1e}, {len(differ)} with other loop or object counts, {len(missing)} not in it")
    return {"compared": len(rows) - len(missing), "worst_relative_ate": worst, "counts_differ": differ,
            "missing": missing}


def write_out(a, doc: dict) -> None:
    """``doc`` as JSON to ``--out``, when given."""
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
        print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
