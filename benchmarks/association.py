"""Automatic data association: wall time per sequence and per frame.

    python3 benchmarks/association.py [--seeds 0,1,2,3,4] [--fr3 PATH] [--fr2 PATH]
        [--extra SEQ ...] [--repeats 3] [--json out.json]

Times ``spdslam.frontend.associate_detailed`` (best of ``--repeats`` runs) on the demo rooms
with truncated frames and 10 % false detections (``make_room_sequence(seed, truncation=True,
outliers=0.1)``), on fr3_cabinet (when ``../shared`` has it) and on any further sequence
folders given with ``--extra``. Prints frames, detections, tracks, seconds and ms per frame;
``--json`` also records each detection's track (``assignment``), so two versions of the code
can be checked to associate alike (``PYTHONPATH=<an older checkout> python3
benchmarks/association.py`` times the version before the subpackages too).

fr2_desk (``--fr2``, when ``../shared`` has it; ``--fr2 ''`` skips it) is timed as a run
associates it: after the screening of ``run_sequence`` (``screen_detections`` with the
multi-spd method's truncation margin), with the seconds of each stage of the best run too
(tracklets, merging, re-assignment and, within it, the time-local centres).
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


def stages(name: str, seq, repeats: int) -> dict:
    """``bench`` with the seconds of each stage of the best run (the stage functions of
    ``spdslam.frontend._association`` wrapped with timers for the runs)."""
    from spdslam.frontend import _association as assoc

    spent: dict = {}
    wrapped = [(assoc, "_tracklets"), (assoc, "_merge"), (assoc, "_reassign"), (assoc._Scene, "local_centres")]
    originals = [getattr(owner, attr) for owner, attr in wrapped]

    def timed(fn, key):
        def run(*args, **kwargs):
            t = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                spent[key] = spent.get(key, 0.0) + time.perf_counter() - t
        return run

    for (owner, attr), fn in zip(wrapped, originals):
        setattr(owner, attr, timed(fn, attr.lstrip("_")))
    best: tuple = (float("inf"), {})
    try:
        for _ in range(repeats):
            spent.clear()
            t = time.perf_counter()
            a = associate_detailed(seq)
            best = min(best, (time.perf_counter() - t, dict(spent)), key=lambda b: b[0])
    finally:
        for (owner, attr), fn in zip(wrapped, originals):
            setattr(owner, attr, fn)
    row = {"name": name, "frames": len(seq), "detections": len(seq.detections), "tracks": len(a.tracks),
           "seconds": best[0], "ms_per_frame": 1e3 * best[0] / len(seq), "stages": best[1],
           "assignment": a.assignment.tolist()}
    print(f"{name}: {row['frames']} frames, {row['detections']} detections, {row['tracks']} tracks, "
          f"{best[0]:.3f} s, {row['ms_per_frame']:.2f} ms per frame; stages "
          + ", ".join(f"{k} {v:.3f} s" for k, v in best[1].items()))
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="0,1,2,3,4")
    ap.add_argument("--fr3", default=str(ROOT / ".." / "shared" / "data" / "tum_fr3_cabinet"))
    ap.add_argument("--fr2", default=str(ROOT / ".." / "shared" / "data" / "tum_fr2_desk"))
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
    if a.fr2 and Path(a.fr2).is_dir():
        try:
            from spdslam.frontend import screen_detections
            from spdslam.mapping import METHODS
        except ImportError:  # a version before the screening: all detections, no stages
            rows.append(bench("tum_fr2_desk", read_sequence(a.fr2), a.repeats))
        else:
            fr2 = screen_detections(read_sequence(a.fr2), METHODS["multi-spd"].margin).sequence
            rows.append(stages("tum_fr2_desk (screened)", fr2, a.repeats))
    elif a.fr2:
        print(f"(fr2_desk not found at {a.fr2}: skipped)")
    for folder in a.extra:
        rows.append(bench(Path(folder).name, read_sequence(folder), a.repeats))
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
