"""The demo room seen through a fisheye lens (issue 38; docs/formats.md).

The demo room (``make_room_sequence(seed)``, the generator of ``spdslam demo``) is written
twice as a detector's output folder (YOLO label files, a ROS ``camera_info``, a TUM
``rgb.txt``, the room's trajectory): once with its pinhole boxes, once with the boxes a camera
with the same intrinsics and an equidistant (fisheye) lens would measure: the bounding box of
each object's projected outline pushed through the lens (``geometry.distort_points``), plus
the room's own box noise (its noisy box minus the exact one). Each folder is read as
``spdslam run`` reads it (the fisheye boxes undistorted, ``geometry.undistort_boxes``) and
mapped with automatic association; both maps are evaluated against the room's ground truth.

    python3 benchmarks/fisheye_room.py [--seeds 0,1,2] [--out FILE]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from conftest import write_detector_folder  # noqa: E402  (the tests' writer of the layout)

from spdslam import Ellipsoid, project_box  # noqa: E402
from spdslam.evaluation import conic_ellipses, ellipses_points, evaluate_run  # noqa: E402
from spdslam.geometry import (  # noqa: E402
    Equidistant,
    distort_points,
    dual_quadric,  # noqa: E402
    project_dual_quadric,
)
from spdslam.geometry.se3 import from_tum  # noqa: E402
from spdslam.io import read_sequence  # noqa: E402
from spdslam.mapping import run_sequence  # noqa: E402
from spdslam.synthetic import make_room_sequence  # noqa: E402

#: The lens: equidistant, θ_d = θ (1 + k1θ² + k2θ⁴ + k3θ⁶ + k4θ⁸).
LENS = Equidistant(-0.05, 0.01, -0.002, 0.0003)


def fisheye_boxes(seq, lens: Equidistant, n: int = 128) -> np.ndarray:
    """The boxes (D, 4) a fisheye camera would measure for the room's detections: the bounding
    box of the distorted outline of the object (from the ground-truth pose), plus the room's
    box noise. False detections (instance < 0) keep their pinhole box, distorted as a box."""
    gt = {o.id: Ellipsoid.from_axes(o.cuboid.rotation, o.cuboid.center, o.cuboid.half_extents)
          for o in seq.objects_gt}
    rows = np.asarray(seq.groundtruth_tum)[:, 1:]
    out = []
    for d in seq.detections:
        T = from_tum(rows[d.frame]) if len(rows) == len(seq) else None
        if d.instance is None or d.instance < 0 or d.instance not in gt or T is None:
            pts = distort_points(np.array([[d.box[0], d.box[1]], [d.box[2], d.box[1]],
                                           [d.box[0], d.box[3]], [d.box[2], d.box[3]]]), seq.camera, lens)
            out.append(np.r_[pts.min(axis=0), pts.max(axis=0)])
            continue
        e = gt[d.instance]
        exact = np.asarray(project_box(e, T, seq.camera))
        c, S, ok = conic_ellipses(np.asarray(project_dual_quadric(dual_quadric(e), T, seq.camera)))
        pts = distort_points(ellipses_points(c, S, n), seq.camera, lens)
        out.append(np.r_[pts.min(axis=0), pts.max(axis=0)] + (np.asarray(d.box) - exact))
    return np.clip(np.array(out), 0.0, [seq.camera.width, seq.camera.height] * 2)


def mapped(folder: Path, seq) -> dict:
    read = read_sequence(folder)
    read = dataclasses.replace(read, objects_gt=seq.objects_gt, groundtruth_tum=seq.groundtruth_tum)
    t0 = time.perf_counter()
    r = run_sequence(read, "multi-spd", associate="auto", initial_poses="input")  # as spdslam demo maps
    m = evaluate_run(r.as_dict(), r.objects, r.initial_objects, r.poses_tum, read)
    return {"objects": len(r.objects), "mean_iou": m["summary"]["mean_iou"], "matched": m["summary"]["matched"],
            "seconds": time.perf_counter() - t0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="0,1,2", help="demo room seeds, comma-separated")
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in (int(s) for s in a.seeds.split(",")):
            seq = make_room_sequence(seed)
            pin = write_detector_folder(seq, Path(tmp) / f"pinhole{seed}")
            fish = write_detector_folder(seq, Path(tmp) / f"fisheye{seed}", dist=LENS, boxes=fisheye_boxes(seq, LENS))
            row = {"seed": seed, "pinhole": mapped(pin, seq), "fisheye": mapped(fish, seq)}
            row["difference"] = row["fisheye"]["mean_iou"] - row["pinhole"]["mean_iou"]
            rows.append(row)
            print(f"room {seed}: mean IoU pinhole {row['pinhole']['mean_iou']:.3f}, fisheye "
                  f"{row['fisheye']['mean_iou']:.3f} ({row['difference']:+.3f}); objects "
                  f"{row['pinhole']['objects']} / {row['fisheye']['objects']}")
    out = {"lens": list(LENS), "rooms": rows,
           "max_abs_difference": float(max(abs(r["difference"]) for r in rows))}
    print(json.dumps(out, indent=1))
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(out, indent=1) + "\n", encoding="utf-8")
        print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
