"""Stress run of the simulation study (issue 15): many trials per cell, then every output
file scanned for NaN and Infinity, and the collapsed estimates counted.

    python3 benchmarks/stress.py [--trials 100000] [--noise H] [--out results/stress]
        [--params F,S,O] [--models inv,semi] [--angles 60,120]

Writes the study's files (trials.csv, table.md, summary.json, convergence.png) under
``--out`` as ``spdslam simulate`` does, and prints per file the number of NaN / Infinity
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
    a = ap.parse_args()
    cfg = StudyConfig(trials=a.trials, noise=tuple(a.noise.split(",")), params=tuple(a.params.split(",")),
                      models=tuple(a.models.split(",")), angles=tuple(float(x) for x in a.angles.split(",")))
    t = time.perf_counter()
    result = run_study(cfg)
    out = Path(a.out)
    write_outputs(result, out)
    wall = time.perf_counter() - t
    print(f"{a.trials} trials per cell, noise {a.noise}: {len(result.rows)} solves in {wall:.1f} s -> {out}")
    for name in ("trials.csv", "table.md", "summary.json"):
        print(f"  {name}: {bad_tokens(out / name)} NaN/Infinity tokens")
    json.loads((out / "summary.json").read_text(), parse_constant=lambda c: (_ for _ in ()).throw(ValueError(c)))
    cells: dict = {}
    with open(out / "trials.csv", newline="") as f:
        for r in csv.DictReader(f):
            key = (r["angle"], r["noise"], r["model"], r["param"])
            c = cells.setdefault(key, [0, 0, 0])
            c[0] += 1
            c[1] += float(r["min_radius_ratio"] or 0.0) < COLLAPSED_RATIO
            c[2] += r["orientation_error_deg"] == ""
    print("| range | noise | model | param | trials | collapsed | no orientation |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for (ang, n, m, p), (k, col, no) in sorted(cells.items()):
        print(f"| {ang} | {n} | {m} | {p} | {k} | {col} | {no} |")


if __name__ == "__main__":
    main()
