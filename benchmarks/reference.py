"""Our LM against an independent reference on the simulation study's trials.

The reference (``spdslam.experiments.reference_solve``) solves every trial of the grid again
with SciPy's trust-region reflective least squares (``least_squares(method="trf")``, at most
``--max-nfev`` residual evaluations, central-difference Jacobian) on the same residuals, over
global charts (O: P = P₀^½ Exp(ξ) P₀^½; S: (so(3), t, s); F: the 10 entries of Q*), with the
study's success rule for both. Per (cell, model, param) it prints both success rates, the
trials where only one succeeds, median iterations and evaluations, and the collapse rates.

    python3 benchmarks/reference.py --quick                 # 8 trials, H only
    python3 benchmarks/reference.py --trials 1000           # the full grid (≈ 10 min, 2 cores)
    python3 benchmarks/reference.py --trials 1000 --noise H --params S,O
    python3 benchmarks/reference.py --trials 1000 --protocol v1   # the protocol until issue 16

Writes ``benchmarks/results/reference.json`` and ``reference.md``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=60)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--params", default="F,S,O")
    ap.add_argument("--models", default="inv,semi")
    ap.add_argument("--angles", default="60,120")
    ap.add_argument("--noise", default="L,M,H")
    ap.add_argument("--max-iters", type=int, default=None,
                    help="our LM's budget (default: the study's)")
    ap.add_argument("--max-nfev", type=int, default=100, help="TRF's budget of evaluations")
    ap.add_argument("--workers", type=int, default=None, help="TRF processes (default ≤ 2)")
    ap.add_argument("--protocol", default="paper", help="the scenes' protocol (synthetic.PROTOCOLS)")
    ap.add_argument("--quick", action="store_true", help="8 trials at H")
    ap.add_argument("--out", default=str(HERE / "results" / "reference.json"))
    args = ap.parse_args()
    if args.quick:
        args.trials, args.noise = 8, "H"

    from spdslam.experiments import StudyConfig, compare_with_reference, reference_table

    cfg = StudyConfig(trials=args.trials, seed=args.seed, params=tuple(args.params.split(",")),
                      models=tuple(args.models.split(",")),
                      angles=tuple(float(a) for a in args.angles.split(",")),
                      noise=tuple(args.noise.split(",")), protocol=args.protocol,
                      **({} if args.max_iters is None else {"max_iters": args.max_iters}))
    t0 = time.perf_counter()
    out = compare_with_reference(cfg, args.max_nfev, args.workers,
                                 progress=lambda s: print(f"  reference {s} done", flush=True))
    wall = time.perf_counter() - t0
    table = reference_table(out["cells"])
    print(table)
    print(f"ours: {out['result'].timings['wall']:.1f} s; all: {wall:.1f} s")
    path = Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"config": vars(args), "cells": out["cells"],
                                "ours_wall_s": out["result"].timings["wall"], "wall_s": wall},
                               indent=1))
    path.with_suffix(".md").write_text(table)
    print(f"wrote {path} and {path.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
