"""Objects against drift (issue 46; docs/drift.md): real recordings with drift added, and the
long synthetic rooms, mapped by default.

Real recordings: fr2_desk (ORB-SLAM2's poses, real YOLOv5 boxes without ids) and the office
recording (../shared/data/tum_fr3_long_office: motion-capture poses, real YOLO boxes
without ids, a camera that comes back to its start), each made a drifting odometry
(``synthetic.drifted_sequence``: every frame step composed with Exp(ε), ε ~ N(0, σ_t² I₃, σ_r²
I₃), no bound on each pose) at the rates of ``--rates`` (σ_t m : σ_r degrees per frame) and
the seeds of ``--seeds``, and mapped by default (``spdslam run``'s settings; with
``--online`` also replayed through the online mapper, in line). Every row: the input's ATE
and the run's, their ratio, the start the run chose, the box errors' correlation, the loops
found (candidate revisits), verified and rejected, the objects, and the seconds. With
``--compare input`` each real recording is also mapped with ``--initial-poses input`` (the
boxes move each pose), beside it.

Synthetic rooms: ``make_room_sequence`` (``--room-frames``, ``--room-objects``, ``--room-drift``
m per step and half that in rad), seeds of ``--room-seeds``, with the detector's failures of
``--room-failures`` (outliers, missed, truncation: ``outliers=0.1, missed=0.1,
truncation=True``) and without instance ids.

    python3 benchmarks/drift.py [--recordings fr2,office] [--rates 0.0005:0.025,0.001:0.05,0.003:0.15]
        [--seeds 0,1,2] [--online] [--compare input] [--rooms/--no-rooms] [--out FILE]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from spdslam.evaluation import absolute_trajectory_error
from spdslam.io import read_sequence
from spdslam.mapping import RunSettings, run_online, run_sequence
from spdslam.synthetic import drifted_sequence, make_room_sequence

ROOT = Path(__file__).resolve().parents[1]
RECORDINGS = {"fr2": ROOT / "../shared/data/tum_fr2_desk", "office": ROOT / "../shared/data/tum_fr3_long_office"}


def ate_mm(rows, seq) -> float:
    rows = np.asarray(rows, float)
    if rows.shape[1] == 7:
        rows = np.c_[seq.timestamps, rows]
    return 1e3 * absolute_trajectory_error(rows, seq.groundtruth_tum)["rmse"]


def loops_of(result) -> dict:
    """Loops found (candidates), verified and rejected, from the run's ``trajectory`` record."""
    lc = (result.trajectory or {}).get("loop_closure") or {"loops": []}
    status = [lp["status"] for lp in lc["loops"]]
    return {"loops_found": len(status), "loops_verified": status.count("verified"),
            "loops_rejected": status.count("rejected")}


def row_of(seq, result, seconds: float, **more) -> dict:
    a_in, a_out = ate_mm(seq.poses_tum, seq), ate_mm(result.poses_tum, seq)
    t = result.trajectory or {}
    return {**more, "ate_input_mm": a_in, "ate_mm": a_out, "ratio": a_out / a_in, "start": t.get("start"),
            "box_correlation": t.get("box_correlation"), **loops_of(result), "objects": len(result.objects),
            "seconds": seconds}


def show(r: dict) -> None:
    what = " ".join(f"{k} {r[k]}" for k in ("recording", "room", "rate", "seed", "mode") if k in r)
    loops = f"loops {r['loops_found']}/{r['loops_verified']}/{r['loops_rejected']}"
    print(f"{what}: ATE {r['ate_input_mm']:.1f} → {r['ate_mm']:.1f} mm ({r['ratio']:.2f}×), start {r['start']}, "
          f"{loops} (found/verified/rejected), {r['objects']} objects, {r['seconds']:.1f} s", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--recordings", default="fr2,office", help="of fr2, office, comma-separated ('': none)")
    ap.add_argument("--rates", default="0.0005:0.025,0.001:0.05,0.003:0.15",
                    help="σ_t:σ_r per frame step (m:degrees), comma-separated")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--online", action="store_true", help="each drifted recording also through the online mapper")
    ap.add_argument("--compare", default="", help="'input': each drifted recording also with --initial-poses input")
    ap.add_argument("--rooms", action=argparse.BooleanOptionalAction, default=True)
    ap.add_argument("--room-frames", type=int, default=400)
    ap.add_argument("--room-objects", type=int, default=24)
    ap.add_argument("--room-drift", default="0.005,0.01,0.02", help="m per step (and half in rad), comma-separated")
    ap.add_argument("--room-seeds", default="0,1,2")
    ap.add_argument("--room-failures", action=argparse.BooleanOptionalAction, default=True,
                    help="outliers 0.1, missed 0.1 and truncation")
    ap.add_argument("--out", type=Path)
    a = ap.parse_args()
    settings = RunSettings.of("multi-spd")
    rows, rooms = [], []
    for name in (x for x in a.recordings.split(",") if x):
        base = read_sequence(RECORDINGS[name])
        for rate in (x for x in a.rates.split(",") if x):
            st, sr_deg = (float(x) for x in rate.split(":"))
            for seed in (int(x) for x in a.seeds.split(",") if x):
                seq = drifted_sequence(base, st, np.radians(sr_deg), seed)
                modes = ["default", *(["input"] if a.compare == "input" else []), *(["online"] if a.online else [])]
                for mode in modes:
                    t0 = time.perf_counter()
                    if mode == "online":
                        result, _ = run_online(seq, settings)
                    else:
                        result = run_sequence(seq, settings if mode == "default"
                                              else settings.replace(initial_poses="input"))
                    r = row_of(seq, result, time.perf_counter() - t0, recording=name, rate=rate, seed=seed,
                               mode=mode)
                    rows.append(r)
                    show(r)
    failures = dict(outliers=0.1, missed=0.1, truncation=True) if a.room_failures else {}
    for drift in (float(x) for x in a.room_drift.split(",") if x and a.rooms):
        for seed in (int(x) for x in a.room_seeds.split(",") if x):
            room = make_room_sequence(seed, frames=a.room_frames, objects=a.room_objects, drift=drift, **failures)
            room = dataclasses.replace(room, detections=[dataclasses.replace(d, instance=None)
                                                         for d in room.detections])
            t0 = time.perf_counter()
            result = run_sequence(room, settings)
            r = row_of(room, result, time.perf_counter() - t0, room=f"{a.room_objects} objects, {a.room_frames} frames",
                       rate=drift, seed=seed, mode="default")
            rooms.append(r)
            show(r)
    worst = max([r["ratio"] for r in rows + rooms] or [float("nan")])
    print(f"worst ratio to the input's ATE: {worst:.3f}")
    doc = {"recordings": rows, "rooms": rooms, "worst_ratio": worst}
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
        print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
