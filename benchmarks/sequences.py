"""Table III on the demo rooms, fr3_cabinet and fr2_desk: every method, one table.

    python3 benchmarks/sequences.py [--seeds 0,1,2,3,4] [--fr3 ../shared/data/tum_fr3_cabinet]
        [--fr2 ../shared/data/tum_fr2_desk] [--json out.json]

Prints, per sequence, the front-end (initialisation) and back-end mean IoU (over all
ground-truth objects), orientation error and centre error of quadric-slam, multi-rts and
multi-spd, with the run time, and the mean over the demo seeds; fr2_desk with its
ORB-SLAM2 odometry (as the paper) and with the ground-truth poses, automatic association,
beside the paper's fr2_desk row. The metrics are those of ``spdslam run``
(``evaluation.evaluate_run``: objects compared in the ground truth's frame). The demo rooms
are ``make_room_sequence(seed)`` (default arguments). ``--seeds ''`` or a missing folder
skips a part. ``--no-align`` compares the objects as mapped (the evaluation before
``to_groundtruth``; meaningful where the trajectory is in the ground truth's frame: the demo
rooms, fr3_cabinet).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from spdslam.evaluation import FRONT_END_NAMES, evaluate_run
from spdslam.io import import_oaslam, read_sequence
from spdslam.mapping import METHODS, run_sequence
from spdslam.synthetic import make_room_sequence

#: The paper's Table III, fr2_desk (12 ground-truth objects): mean IoU, orientation error (°).
PAPER_FR2 = {"quadric-slam": (0.172, 30.8), "multi-rts": (0.334, 8.7), "multi-spd": (0.345, 7.3)}


ALIGN = True


def run_all(seq, **kw) -> list:
    rows, fronts = [], {}
    for name in METHODS:
        t = time.perf_counter()
        # the rooms' boxes move their drifting poses, as spdslam demo maps (a no-op on fr3_cabinet)
        r = run_sequence(seq, name, initial_poses="input", **kw)
        dt = time.perf_counter() - t
        m = evaluate_run(r.as_dict(), r.objects, r.initial_objects, r.poses_tum, seq, align=ALIGN)
        init = r.method.initialization
        if init not in fronts:
            fronts[init] = m["front_end"]["summary"]
        # each ground-truth object's IoU (0 where it is missed), for paired comparisons
        gt_iou = {str(g.id): 0.0 for g in seq.objects_gt}
        gt_iou.update({str(o["gt_id"]): o["iou"] for o in m["objects"] if o["gt_id"] is not None})
        rows.append({"stage": "back end", "method": name, **m["summary"], "iterations": r.iterations,
                     "seconds": dt, "objects_mapped": len(r.objects), "failed": len(r.failed),
                     "gt_iou": gt_iou, "ate": (m.get("ate") or {}).get("optimized")})
    front = [{"stage": "front end", "method": FRONT_END_NAMES[k], **v} for k, v in fronts.items()]
    return front + rows


def show(title: str, rows: list, paper: dict | None = None) -> None:
    print(f"\n{title}")
    print("| stage | method | mean IoU | orientation (°) | centre (m) | matched | time (s) |"
          + (" paper IoU / ° |" if paper else ""))
    print("| --- | --- | --- | --- | --- | --- | --- |" + (" --- |" if paper else ""))
    for r in rows:
        extra = f" {paper[r['method']][0]:.3f} / {paper[r['method']][1]:.1f} |" \
            if paper and r["method"] in paper else (" |" if paper else "")
        secs = f"{r['seconds']:.1f}" if "seconds" in r else ""
        print(f"| {r['stage']} | {r['method']} | {r['mean_iou']:.3f} | "
              f"{r['mean_orientation_deg']:.2f} | {r['mean_center_error']:.3f} | "
              f"{r['matched']}/{r['ground_truth_objects']} | {secs} |{extra}")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", default="0,1,2,3,4")
    ap.add_argument("--fr3", default=str(Path(__file__).resolve().parents[1] / "../shared/data/tum_fr3_cabinet"))
    ap.add_argument("--fr2", default=str(Path(__file__).resolve().parents[1] / "../shared/data/tum_fr2_desk"))
    ap.add_argument("--json", default=None)
    ap.add_argument("--no-align", action="store_true",
                    help="compare the objects as mapped, without aligning the trajectory to the ground truth")
    a = ap.parse_args()
    global ALIGN
    ALIGN = not a.no_align
    out = {}
    seeds = [int(s) for s in a.seeds.split(",") if s.strip()]
    demo = []
    for seed in seeds:
        rows = run_all(make_room_sequence(seed))
        show(f"demo room, seed {seed}", rows)
        demo.append(rows)
        out[f"demo_{seed}"] = rows
    if demo:
        mean = [
            {**demo[0][i], **{k: float(np.mean([d[i][k] for d in demo]))
                              for k in ("mean_iou", "mean_orientation_deg", "mean_center_error")}}
            for i in range(len(demo[0]))
        ]
        for i, row in enumerate(mean):  # every room's objects, keyed by room and object
            if "gt_iou" in row:
                row["gt_iou"] = {f"{seed}/{k}": v for seed, d in zip(seeds, demo) for k, v in d[i]["gt_iou"].items()}
        show(f"demo rooms, mean over seeds {seeds}", mean)
        out["demo_mean"] = mean
    fr3 = Path(a.fr3)
    if fr3.is_dir():
        rows = run_all(read_sequence(fr3))
        show("tum_fr3_cabinet", rows)
        out["fr3_cabinet"] = rows
    else:
        print(f"\n(fr3_cabinet not found at {fr3}: skipped)")
    fr2 = Path(a.fr2)
    if fr2.is_dir():
        for trajectory in ("odometry", "groundtruth"):
            rows = run_all(import_oaslam(fr2, trajectory=trajectory), associate="auto")
            show(f"tum_fr2_desk, {trajectory} poses, automatic association", rows, PAPER_FR2)
            out[f"fr2_desk_{trajectory}"] = rows
    else:
        print(f"\n(fr2_desk not found at {fr2}: skipped)")
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
