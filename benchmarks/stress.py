"""Stress run of the simulation study (issue 15): many trials per cell, then every output
file scanned for NaN and Infinity, and the collapsed estimates counted.

    python3 benchmarks/stress.py [--trials 100000] [--noise H] [--out results/stress]
        [--params F,S,O] [--models inv,semi] [--angles 60,120] [--protocol paper]

Runs one (range, noise) cell at a time and writes its files (trials.csv, table.md,
summary.json, convergence.png) under ``--out``/RANGE-NOISE as ``spdslam simulate`` does, and prints per file the number of NaN / Infinity
tokens (the target: 0 everywhere; strict JSON cannot hold them at all) and, per cell, the
trials, the collapsed estimates (smallest radius below ``COLLAPSED_RATIO`` of the largest)
and the empty orientation fields (estimates without finite axes).
"""

from __future__ import annotations

import argparse
import csv
import json
import re
import time
from pathlib import Path

from spdslam.experiments import COLLAPSED_RATIO, StudyConfig, run_study, write_outputs

_BAD = re.compile(r"(?i)(?<![a-z])(nan|[+-]?inf(inity)?)(?![a-z])")


def bad_tokens(path: Path) -> int:
    """NaN / Infinity tokens in a text file (the words, as Python and JSON write them)."""
    return len(_BAD.findall(path.read_text(encoding="utf-8")))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trials", type=int, default=100_000)
    ap.add_argument("--noise", default="H")
    ap.add_argument("--params", default="F,S,O")
    ap.add_argument("--models", default="inv,semi")
    ap.add_argument("--angles", default="60,120")
    ap.add_argument("--out", default="results/stress")
    ap.add_argument("--protocol", default="paper", help="the scenes' protocol (synthetic.PROTOCOLS)")
    a = ap.parse_args()
    cells: dict = {}
    t = time.perf_counter()
    # One (range, noise) cell per study: the study keeps a record per solve, and 10⁵ trials
    # of several cells at once do not fit in this machine's memory (docs/simulation.md).
    for angle in (float(x) for x in a.angles.split(",")):
        for noise in a.noise.split(","):
            cfg = StudyConfig(trials=a.trials, noise=(noise,), params=tuple(a.params.split(",")),
                              models=tuple(a.models.split(",")), angles=(angle,), protocol=a.protocol)
            t_cell = time.perf_counter()
            result = run_study(cfg)
            out = Path(a.out) / f"{angle:g}-{noise}"
            write_outputs(result, out)
            n_solves = len(result.rows)
            del result
            print(f"{a.trials} trials, range {angle:g}°, noise {noise}: {n_solves} solves in "
                  f"{time.perf_counter() - t_cell:.1f} s -> {out}", flush=True)
            for name in ("trials.csv", "table.md", "summary.json"):
                print(f"  {name}: {bad_tokens(out / name)} NaN/Infinity tokens", flush=True)
            json.loads((out / "summary.json").read_text(),
                       parse_constant=lambda c: (_ for _ in ()).throw(ValueError(c)))
            with open(out / "trials.csv", newline="") as f:
                for r in csv.DictReader(f):
                    key = (r["angle"], r["noise"], r["model"], r["param"])
                    c = cells.setdefault(key, [0, 0, 0])
                    c[0] += 1
                    c[1] += float(r["min_radius_ratio"] or 0.0) < COLLAPSED_RATIO
                    c[2] += r["orientation_error_deg"] == ""
    print(f"all cells: {time.perf_counter() - t:.1f} s")
    print("| range | noise | model | param | trials | collapsed | no orientation |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for (ang, n, m, p), (k, col, no) in sorted(cells.items()):
        print(f"| {ang} | {n} | {m} | {p} | {k} | {col} | {no} |")


if __name__ == "__main__":
    main()
