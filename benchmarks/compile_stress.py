"""Can the batched solver's compilation hang? Many compilations in threads, as ``run_study``
does (every structure of the grid compiled two at a time in a thread pool), with the
production compile options, round after round with every cache dropped in between
(``solver.clear_caches``), so that each round compiles again.

A watchdog (``faulthandler.dump_traceback_later``) prints every thread's stack and ends the
process when a round takes longer than ``--stall`` seconds: a hang shows as a non-zero exit
with the stacks, not as a process that never ends.

    python3 benchmarks/compile_stress.py [--rounds 30] [--optimize no|yes|both] [--stall 300]
"""

from __future__ import annotations

import argparse
import faulthandler
import json
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))  # run from a checkout


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rounds", type=int, default=30)
    ap.add_argument("--optimize", choices=["no", "yes", "both"], default="both")
    ap.add_argument("--stall", type=float, default=300.0, help="Seconds after which a round counts as hung.")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()

    from spdslam.experiments import StudyConfig, run_study
    from spdslam.solver import clear_caches

    modes = {"no": [False], "yes": [True], "both": [False, True]}[args.optimize]
    out = {"rounds": [], "stall_s": args.stall}
    for r in range(args.rounds):
        for opt in modes:
            clear_caches()
            faulthandler.dump_traceback_later(args.stall, exit=True)
            t0 = time.perf_counter()
            res = run_study(StudyConfig(trials=2, max_iters=20, optimize=opt, seed=r))
            seconds = time.perf_counter() - t0
            faulthandler.cancel_dump_traceback_later()
            out["rounds"].append({"round": r, "optimize": opt, "seconds": seconds,
                                  "compile_s": res.timings.get("compile"), "solves": len(res)})
            print(f"round {r} optimize={opt}: {seconds:.1f} s (compile {res.timings.get('compile', 0):.1f} s), "
                  f"{len(res)} solves", flush=True)
    n = len(out["rounds"])
    print(f"{n} rounds of 6 structures compiled in 2 threads: no round over {args.stall:g} s "
          f"(longest {max(x['seconds'] for x in out['rounds']):.1f} s)")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
