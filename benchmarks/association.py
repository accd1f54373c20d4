"""Automatic data association: wall time per sequence and per frame.

    python3 benchmarks/association.py [--seeds 0,1,2,3,4] [--fr3 PATH] [--extra SEQ ...]
        [--repeats 3] [--json out.json]

Times ``spdslam.frontend.associate_detailed`` (best of ``--repeats`` runs) on the demo rooms
with truncated frames and 10 % false detections (``make_room_sequence(seed, truncation=True,
outliers=0.1)``), on fr3_cabinet (when ``../shared`` has it) and on any further sequence
folders given with ``--extra``. Prints frames, detections, tracks, seconds and ms per frame;
``--json`` also records each detection's track (``assignment``), so two versions of the code
can be checked to associate alike (``PYTHONPATH=<an older checkout> python3
benchmarks/association.py`` times the version before the subpackages too).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

try:
    from spdslam.frontend import associate_detailed
    from spdslam.io import read_sequence
    from spdslam.synthetic import make_room_sequence
except ImportError:  # the flat layout before the subpackages, to time the previous version
    from spdslam.association import associate_detailed
    from spdslam.demo import make_room_sequence
    from spdslam.sequence import read_sequence

ROOT = Path(__file__).resolve().parents[1]


def bench(name: str, seq, repeats: int) -> dict:
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        a = associate_detailed(seq)
        times.append(time.perf_counter() - t)
    best = min(times)
    row = {"name": name, "frames": len(seq), "detections": len(seq.detections),
           "tracks": len(a.tracks), "seconds": best, "ms_per_frame": 1e3 * best / len(seq),
           "assignment": a.assignment.tolist()}
    print(f"{name}: {row['frames']} frames, {row['detections']} detections, {row['tracks']} "
          f"tracks, {best:.3f} s, {row['ms_per_frame']:.2f} ms per frame")
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="0,1,2,3,4")
    ap.add_argument("--fr3", default=str(ROOT / ".." / "shared" / "data" / "tum_fr3_cabinet"))
    ap.add_argument("--extra", nargs="*", default=[], help="more sequence folders")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    rows = []
    for seed in [int(s) for s in a.seeds.split(",") if s.strip()]:
        rows.append(bench(f"demo {seed}, truncated, 10 % outliers",
                          make_room_sequence(seed, truncation=True, outliers=0.1), a.repeats))
    if Path(a.fr3).is_dir():
        rows.append(bench("tum_fr3_cabinet", read_sequence(a.fr3), a.repeats))
    else:
        print(f"(fr3_cabinet not found at {a.fr3}: skipped)")
    for folder in a.extra:
        rows.append(bench(Path(folder).name, read_sequence(folder), a.repeats))
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
