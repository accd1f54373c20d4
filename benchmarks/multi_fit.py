"""The multi-constraint starts in NumPy (docs/performance.md, "The multi-constraint starts
without a compiler"): the fits a batch run of a recording makes (captured from
``spdslam run``'s initialisation), timed as one batch (the default), as one batch with no
member stopped early (``STEP_FLOOR`` 0), and one object at a time; each start's fitted P
against the no-early-stop batch.

    python3 benchmarks/multi_fit.py [--sequence ../shared/data/tum_fr2_desk] [--repeats 3] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np

import spdslam.frontend._initialization as init_mod
from spdslam.frontend import _multi_fit
from spdslam.io import read_sequence
from spdslam.mapping import run_sequence


def captured_problems(path: str) -> tuple[list, object]:
    """The problems and camera of the batch run's first multi-constraint fit."""
    got: list = []
    real = init_mod.fit_multi

    def capture(problems, camera):
        if not got:
            got.append((list(problems), camera))
        return real(problems, camera)

    init_mod.fit_multi = capture
    try:
        run_sequence(read_sequence(path), "multi-spd")
    finally:
        init_mod.fit_multi = real
    return got[0]


def timed(fn, repeats: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sequence", default="../shared/data/tum_fr2_desk")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path)
    a = ap.parse_args()
    problems, camera = captured_problems(a.sequence)
    floor = _multi_fit.STEP_FLOOR
    batch_s, batch = timed(lambda: _multi_fit.fit_multi(problems, camera), a.repeats)
    _multi_fit.STEP_FLOOR = 0.0
    try:
        full_s, full = timed(lambda: _multi_fit.fit_multi(problems, camera), a.repeats)
    finally:
        _multi_fit.STEP_FLOOR = floor
    one_s, _ = timed(lambda: [_multi_fit.fit_multi([p], camera) for p in problems], a.repeats)
    rel = max(float(np.max(np.abs(b[1] - f[1])) / np.max(np.abs(f[1]))) for b, f in zip(batch, full))
    doc = {"sequence": a.sequence, "objects": len(problems), "starts": int(sum(len(p.starts) for p in problems)),
           "batch_s": batch_s, "batch_no_early_stop_s": full_s, "one_at_a_time_s": one_s,
           "per_object_ms": 1e3 * one_s / len(problems), "start_P_rel_vs_no_early_stop": rel, "repeats": a.repeats}
    print(f"{doc['objects']} objects, {doc['starts']} starts: one batch {batch_s:.3f} s; no member stopped early "
          f"{full_s:.3f} s; one object at a time {one_s:.3f} s ({doc['per_object_ms']:.1f} ms each); each start's P "
          f"against the batch without early stops: {rel:.2g} relative")
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(doc, indent=1))
        print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
