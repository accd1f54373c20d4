"""Real recordings mapped without an up direction: the unoriented start against Quadric-SVD
alone (docs/performance.md, "Starts without an up direction").

Without an up direction or support plane in the priors the multi-constraint fit has no
frame, and each object starts from Quadric-SVD, or (the default since issue 48's eighth stop)
from a sphere on its boxes' rays where Quadric-SVD is flat or fits the boxes worse
(``frontend.unoriented_initialize``). Each recording is read, its up direction and support
planes removed (the office recording has none to remove), and mapped twice in this process by
``run_sequence``: by default, and with ``initialization="svd"`` (Quadric-SVD for every object,
the start before). Every row: LM iterations, seconds of ``run_sequence``, objects mapped and
failed, the thinnest object (smallest radius over largest), and with ground-truth objects the
evaluation's mean IoU, matched IoU and orientation error (``write_run``'s metrics).

    python3 benchmarks/unoriented.py --out benchmarks/results/unoriented.json
    python3 benchmarks/unoriented.py --recordings office
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from spdslam.experiments import write_run
from spdslam.io import read_sequence
from spdslam.mapping import run_sequence

ROOT = Path(__file__).resolve().parents[1]
RECORDINGS = {"fr2": ROOT / "../shared/data/tum_fr2_desk", "fr3": ROOT / "../shared/data/tum_fr3_cabinet",
              "office": ROOT / "../shared/data/tum_fr3_long_office"}
STARTS = {"default": {}, "svd": {"initialization": "svd"}}


def row(seq, start: str) -> dict:
    t0 = time.perf_counter()
    result = run_sequence(seq, **STARTS[start])
    seconds = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as tmp:
        metrics = write_run(tmp, seq, result, overlay=False)
    radii = [np.sort(np.asarray(o.ellipsoid.radii, float)) for o in result.objects]
    summary = metrics.get("summary", {})
    return {"start": start, "iterations": int(result.iterations), "seconds": round(seconds, 2),
            "objects": len(result.objects), "failed": len(result.failed),
            "thinnest_ratio": round(float(min(r[0] / r[2] for r in radii)), 4) if radii else None,
            **{k: summary[k] for k in ("mean_iou", "mean_iou_matched", "mean_orientation_deg", "matched")
               if k in summary}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--recordings", default="fr2,fr3,office", help="comma-separated: fr2, fr3, office")
    ap.add_argument("--out", type=Path, help="write the rows as JSON")
    a = ap.parse_args()
    rows = []
    for name in [n for n in a.recordings.split(",") if n]:
        seq = read_sequence(RECORDINGS[name])
        if seq.priors is not None:
            seq = dataclasses.replace(seq, priors=seq.priors.replace(up=None, support_planes=[]))
        for start in STARTS:
            r = {"recording": name, **row(seq, start)}
            rows.append(r)
            print(" ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in r.items()), flush=True)
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
