"""fr2_desk under the choices docs/sequences.md discusses: one table, one process.

    python3 benchmarks/fr2_variants.py [--fr2 ../shared/data/tum_fr2_desk] [--fr3 ...]

multi-spd with the ORB-SLAM2 odometry and automatic association, as ``spdslam run``
evaluates it (``evaluation.evaluate_run``), for: the defaults; no built-in class table; the
table's factors without their Cauchy kernel; support planes estimated from the initial or
the optimised objects; every 3rd frame and motion keyframes; tighter odometry; and the
defaults evaluated after aligning the *input* trajectory instead of the optimised one.
Then fr3_cabinet's cuboid model with and without the kernel (its cabinet is detected as a
suitcase). Prints mean IoU over the 7 objects, per-object IoU, ATE and run time.

``--halves`` runs multi-spd on each half of the frames instead (the real-sequences check:
no degenerate or implausibly flat object, no failure, the trajectory no worse than its input)
and prints what each maps and reports, with the ATE of the input and of the optimised
trajectory.

``--offsets`` prints instead what limits the thin objects: the constant rotation between
ORB-SLAM2's camera orientations and the motion capture's (mean rotation vector in the
camera frame over the frames within 0.02 s), and, for the defaults, each matched object's
vertical offset from its ground truth (along the ground truth's +z).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from spdslam.evaluation import evaluate_run
from spdslam.io import read_sequence, without_class_table
from spdslam.mapping import run_sequence

ROOT = Path(__file__).resolve().parents[1]


def _row(name, seq, r, dt, poses=None):
    m = evaluate_run(r.as_dict(), r.objects, r.initial_objects,
                     r.poses_tum if poses is None else poses, seq)
    s = m["summary"]
    gt = {int(g.id): g.label for g in seq.objects_gt}
    per = ", ".join(f"{gt[o['gt_id']]} {o['iou']:.2f}" for o in m["objects"] if o["gt_id"] is not None)
    ate = m["ate"]["optimized"]["rmse"] if "ate" in m else float("nan")
    print(f"| {name} | {s['mean_iou']:.3f} | {per} | {len(r.objects)} | {ate:.4f} | {dt:.1f} |", flush=True)


def halves(seq) -> None:
    import numpy as np

    from spdslam.mapping._run import degenerate, implausibly_flat

    n = len(seq)
    for name, idx in (("first half", np.arange(n // 2)), ("second half", np.arange(n // 2, n))):
        part = seq.subset(idx)
        t = time.perf_counter()
        r = run_sequence(part, "multi-spd", associate="auto")
        dt = time.perf_counter() - t
        m = evaluate_run(r.as_dict(), r.objects, r.initial_objects, r.poses_tum, part)
        bad = [o.id for o in r.objects if degenerate(o.ellipsoid) or implausibly_flat(o.ellipsoid)]
        flat = sum("flat" in why for why in r.failed.values())
        finite = all(np.all(np.isfinite(np.asarray(o.ellipsoid.P))) for o in r.objects)
        ate = m["ate"]
        print(f"{name}: {len(part)} frames, {len(part.detections)} boxes, {len(r.objects)} objects, "
              f"{len(r.failed)} not mapped ({flat} flat), degenerate or flat mapped {len(bad)}, "
              f"finite {finite}, mean IoU {m['summary']['mean_iou']:.3f} ({m['summary']['matched']}/7), "
              f"ATE input {1e3 * ate['input']['rmse']:.2f} mm, optimised {1e3 * ate['optimized']['rmse']:.2f} mm "
              f"({ate['optimized']['pairs']} poses), {dt:.1f} s")


def offsets(seq) -> None:
    import numpy as np
    from scipy.spatial.transform import Rotation

    from spdslam.evaluation import associate_timestamps, moved, to_groundtruth

    gt = np.asarray(seq.groundtruth_tum)
    ia, ib = associate_timestamps(np.asarray(seq.timestamps), gt[:, 0], 0.02)
    T, _ = to_groundtruth(seq)
    Rw = Rotation.from_matrix(T[:3, :3])
    odo = Rw * Rotation.from_quat(np.asarray(seq.poses_tum)[ia, 3:7])  # in the mocap frame
    d = (odo.inv() * Rotation.from_quat(gt[ib, 4:8])).as_rotvec()
    print(f"ORB-SLAM2 vs motion capture, camera frame, {len(ia)} frames: mean rotation vector "
          f"{np.round(np.degrees(d.mean(0)), 2).tolist()}° (norm {np.degrees(np.linalg.norm(d.mean(0))):.2f}°), "
          f"spread {np.round(np.degrees(d.std(0)), 2).tolist()}°")
    r = run_sequence(seq, "multi-spd", associate="auto")
    m = evaluate_run(r.as_dict(), r.objects, r.initial_objects, r.poses_tum, seq)
    objs = {o.id: o for o in moved(r.objects, np.asarray(m["to_groundtruth"]))}
    gts = {int(g.id): g for g in seq.objects_gt}
    for row in m["objects"]:
        if row["gt_id"] is None:
            continue
        g, o = gts[row["gt_id"]], objs[row["id"]]
        dz = float(np.asarray(o.ellipsoid.center)[2] - g.cuboid.center[2])
        print(f"{g.label}: IoU {row['iou']:.2f}, centre {dz * 100:+.1f} cm vertically from the ground truth's")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--fr2", default=str(ROOT / "../shared/data/tum_fr2_desk"))
    ap.add_argument("--fr3", default=str(ROOT / "../shared/data/tum_fr3_cabinet"))
    ap.add_argument("--offsets", action="store_true")
    ap.add_argument("--halves", action="store_true")
    a = ap.parse_args()
    seq = read_sequence(a.fr2)
    if a.halves:
        halves(seq)
        return
    if a.offsets:
        offsets(seq)
        return
    no_table = without_class_table(seq)
    variants = [
        ("defaults", seq, {}),
        ("no class table", no_table, {}),
        ("class table without its kernel", seq, {"robust_builtin_priors": False}),
        ("support planes from the initial objects", seq, {"support_planes": "initial"}),
        ("support planes from the optimised objects", seq, {"support_planes": "optimised"}),
        ("every 3rd frame", seq, {"keyframes": 3}),
        ("motion keyframes (5 cm / 5°)", seq, {"keyframes": "motion"}),
        ("odometry σ 1e-4 m, 1e-4 rad", seq,
         {"sigmas": {"odometry_translation": 1e-4, "odometry_rotation": 1e-4}}),
    ]
    print("| fr2_desk, multi-spd | mean IoU (7) | matched | objects | ATE (m) | time (s) |")
    print("| --- | --- | --- | --- | --- | --- |")
    for name, s, kw in variants:
        t = time.perf_counter()
        r = run_sequence(s, "multi-spd", associate="auto", **kw)
        dt = time.perf_counter() - t
        _row(name, s, r, dt)
        if name == "defaults":
            import numpy as np

            inp = np.column_stack([seq.timestamps, seq.poses_tum])
            _row("defaults, evaluated by aligning the input trajectory", seq, r, dt, poses=inp)
    fr3 = Path(a.fr3)
    if fr3.is_dir():
        s = read_sequence(fr3)
        print("\n| fr3_cabinet, multi-spd, cuboid model | IoU | orientation (°) |")
        print("| --- | --- | --- |")
        for name, kw in (("defaults", {}), ("class table without its kernel", {"robust_builtin_priors": False})):
            r = run_sequence(s, "multi-spd", object_shape="cuboid", **kw)
            m = evaluate_run(r.as_dict(), r.objects, r.initial_objects, r.poses_tum, s)["summary"]
            print(f"| {name} | {m['mean_iou']:.3f} | {m['mean_orientation_deg']:.2f} |")


if __name__ == "__main__":
    main()
