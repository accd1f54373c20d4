"""Another system's saved map (issue 49; docs/map-reuse.md, "From another system's map"):
GOReloc's published fr2_desk map (an Osmap: 47 objects of YOLOv8x-seg and ORB-SLAM2, 198
keyframes) read by ``io.load_map``, scored against fr2_desk's ground truth as ``spdslam
evaluate`` scores it, beside spdslam's own map of the recording, and used as the map that
fr2_desk, moved by random rigid motions, is localised against (``spdslam localize --map``).

Scores: ``evaluation.evaluate_run`` (what ``spdslam evaluate`` writes) with the map aligned to
the ground truth by its keyframes' times; with ``--camera-poses`` (GOReloc writes every
frame's pose beside its map, ``camera_poses_*_tum.txt``) a second row aligned by those
(``spdslam evaluate --trajectory``). Localisation: fr2_desk's recording moved by G (trial 0:
its first camera at the origin, as a new run's would be; then a random rotation and a shift
of up to 3 m), ``experiments.localize_sequence`` (what ``spdslam localize`` runs), against
the truth: the moved recording's trajectory aligned to the map's keyframes over their common
times. Errors: the rotation between the two transforms, and the distance between where each
puts the recording's mean camera centre.

The map is not part of this repository: clone https://github.com/yutongwangBIT/GOReloc and
give its ``Saved_Maps/fr2_desk_all/map_fr2_desk_all.yaml``::

    python3 benchmarks/peer_maps.py --map GORELOC/Saved_Maps/fr2_desk_all/map_fr2_desk_all.yaml \\
        --camera-poses GORELOC/Saved_Maps/fr2_desk_all/camera_poses_fr2_desk_all_tum.txt \\
        --trials 3 --out benchmarks/results/peer_maps.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from spdslam.evaluation import evaluate_run, trajectory_alignment
from spdslam.experiments import association_record, localize_sequence
from spdslam.geometry.se3 import from_tum, to_matrix
from spdslam.io import load_map, read_sequence, read_tum
from spdslam.mapping import LocalizationError, RunSettings, moved_sequence, run_sequence

ROOT = Path(__file__).resolve().parents[1]
FR2 = ROOT / "../shared/data/tum_fr2_desk"


def _motion(seq, rng, trial: int) -> np.ndarray:
    """G of a trial: the first camera to the origin, then (trial > 0) a random rigid motion."""
    G = np.linalg.inv(to_matrix(from_tum(seq.poses_tum[0])))
    if trial:
        S = np.eye(4)
        S[:3, :3] = Rotation.random(random_state=rng).as_matrix()
        S[:3, 3] = rng.uniform(-3.0, 3.0, 3)
        G = S @ G
    return G


def _summary(metrics: dict) -> dict:
    s = metrics["summary"]
    return {"mean_iou": s["mean_iou"], "matched": s["matched"], "ground_truth_objects": s["ground_truth_objects"],
            "mean_orientation_deg": s["mean_orientation_deg"], "mean_center_error": s["mean_center_error"],
            "objects": s["objects"], "ate": metrics.get("ate")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--map", type=Path, required=True, help="the peer map (GOReloc's map_fr2_desk_all.yaml)")
    ap.add_argument("--camera-poses", type=Path, default=None,
                    help="a TUM file of the map's camera poses to align by as well")
    ap.add_argument("--sequence", type=Path, default=FR2)
    ap.add_argument("--trials", type=int, default=3, help="rigid motions to localise fr2_desk under")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()
    peer = load_map(a.map)
    seq = read_sequence(a.sequence)
    settings = RunSettings.of("multi-spd")
    doc: dict = {"map": str(a.map), "objects": len(peer.objects), "keyframes": len(peer.trajectory), "scores": {}}
    doc["scores"]["peer, aligned by its keyframes"] = _summary(evaluate_run(peer.document, peer.objects, None,
                                                                            peer.trajectory, seq))
    if a.camera_poses is not None:
        poses = read_tum(a.camera_poses, str(a.camera_poses))
        doc["scores"]["peer, aligned by its camera poses"] = _summary(
            evaluate_run(peer.document, peer.objects, None, poses, seq))
    t0 = time.perf_counter()
    own = run_sequence(seq, settings)
    own_doc = dict(own.as_dict(), association=association_record(own))
    doc["scores"]["spdslam run (default)"] = _summary(evaluate_run(own_doc, own.objects, None, own.poses_tum, seq))
    doc["own_seconds"] = time.perf_counter() - t0
    print("| map | mean IoU | matched | orientation error (°) | centre error (m) | objects | ATE of the poses "
          "aligned by (mm) |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for name, s in doc["scores"].items():
        ate = s["ate"] or {}
        e = ate.get("map") or ate.get("optimized")
        shown = f"{1e3 * e['rmse']:.1f} ({e['pairs']} poses)" if e else "–"
        print(f"| {name} | {s['mean_iou']:.3f} | {s['matched']}/{s['ground_truth_objects']} | "
              f"{s['mean_orientation_deg']:.1f} | {s['mean_center_error']:.3f} | {s['objects']} | {shown} |")
    rng = np.random.default_rng(a.seed)
    rows = []
    for trial in range(a.trials):
        G = _motion(seq, rng, trial)
        moved = moved_sequence(seq, G)
        truth = trajectory_alignment(np.c_[moved.timestamps, moved.poses_tum], peer.trajectory)
        c0 = moved.poses_tum[:, :3].mean(axis=0)
        t0 = time.perf_counter()
        row = {"trial": trial, "G": G.tolist(), "truth": truth.tolist()}
        try:
            _, loc, _ = localize_sequence(moved, peer.objects, settings)
        except LocalizationError as e:
            row.update(localised=False, reason=str(e), seconds=time.perf_counter() - t0)
            print(f"trial {trial}: refused: {e}")
            rows.append(row)
            continue
        T = np.asarray(loc.T_map_sequence)
        rot = float(np.degrees(Rotation.from_matrix(T[:3, :3].T @ truth[:3, :3]).magnitude()))
        shift = float(np.linalg.norm(T[:3, :3] @ c0 + T[:3, 3] - (truth[:3, :3] @ c0 + truth[:3, 3])))
        row.update(localised=True, rotation_error_deg=rot, translation_error_m=shift, matches=len(loc.matches),
                   runner_up=loc.runner_up, seconds=time.perf_counter() - t0)
        rows.append(row)
        print(f"trial {trial}: localised from {len(loc.matches)} objects (rival {loc.runner_up}): "
              f"{rot:.2f}° and {100 * shift:.1f} cm from the keyframes' alignment ({row['seconds']:.1f} s)")
    doc["localisation"] = rows
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
        print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
