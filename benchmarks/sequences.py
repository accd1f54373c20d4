"""Table III on the demo rooms and on fr3_cabinet: every method, one table.

    python3 benchmarks/sequences.py [--seeds 0,1,2,3,4] [--fr3 ../shared/data/tum_fr3_cabinet]
        [--json out.json]

Prints, per sequence, the front-end (initialisation) and back-end mean IoU, orientation
error and centre error of quadric-slam, multi-rts and multi-spd, and the mean over the
demo seeds. The demo rooms are ``make_room_sequence(seed)`` (default arguments).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from spdslam.evaluation import FRONT_END_NAMES, evaluate_objects
from spdslam.io import read_sequence
from spdslam.mapping import METHODS, run_sequence
from spdslam.synthetic import make_room_sequence


def run_all(seq) -> list:
    rows, fronts = [], {}
    for name in METHODS:
        t = time.perf_counter()
        r = run_sequence(seq, name)
        dt = time.perf_counter() - t
        init = r.method.initialization
        if init not in fronts:
            fronts[init] = evaluate_objects(r.initial_objects, seq.objects_gt)[1]
        s = evaluate_objects(r.objects, seq.objects_gt)[1]
        rows.append({"stage": "back end", "method": name, **s, "iterations": r.iterations, "seconds": dt})
    front = [{"stage": "front end", "method": FRONT_END_NAMES[k], **v} for k, v in fronts.items()]
    return front + rows


def show(title: str, rows: list) -> None:
    print(f"\n{title}")
    print("| stage | method | mean IoU | orientation (°) | centre (m) |")
    print("| --- | --- | --- | --- | --- |")
    for r in rows:
        print(f"| {r['stage']} | {r['method']} | {r['mean_iou']:.3f} | "
              f"{r['mean_orientation_deg']:.2f} | {r['mean_center_error']:.3f} |")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", default="0,1,2,3,4")
    ap.add_argument("--fr3", default=str(Path(__file__).resolve().parents[1] / "../shared/data/tum_fr3_cabinet"))
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
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
        show(f"demo rooms, mean over seeds {seeds}", mean)
        out["demo_mean"] = mean
    fr3 = Path(a.fr3)
    if fr3.is_dir():
        rows = run_all(read_sequence(fr3))
        show("tum_fr3_cabinet", rows)
        out["fr3_cabinet"] = rows
    else:
        print(f"\n(fr3_cabinet not found at {fr3}: skipped)")
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
