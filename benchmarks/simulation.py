"""Simulation-study throughput: the full grid, cold compile vs warm persistent compilation cache.

The grid is ``spdslam.experiments.run_study`` (what ``spdslam simulate`` runs): viewing range (60°,
120°) × noise (L, M, H) × box model (inv, semi) × parameterisation (F, S, O), ``--trials``
scenes per (range, noise) cell: 6 structures × 6 cells × 24 trials = 864 batched solves by
default. Each pass runs in a fresh Python process:

- ``cold``: JAX's persistent compilation cache enabled (as the CLI does) in a new, empty
  directory, so every program is traced and compiled by XLA (and written to the cache);
- ``warm``: a second process on the same directory: XLA executables are read from the cache
  (tracing and lowering still run).

Per pass: ``process_s`` (interpreter start, imports and the grid: what a user waits for),
``wall_s`` (run_study's own wall time: scenes, solves incl. compile, evaluation),
``compile_s`` (tracing + compile of the six batched programs), ``solve_loops_s`` (the batched
LM loops alone), problem-iterations and ``us_per_problem_iteration`` = solve_loops_s /
Σ iterations (compile excluded; the amortised figure including compile is also given).

    python3 benchmarks/simulation.py --quick        # 2 trials per cell
    python3 benchmarks/simulation.py                # 24 trials per cell (864 solves)
    python3 benchmarks/simulation.py --trials 1000
    python3 benchmarks/simulation.py --optimize yes # XLA-optimised loops (more compile time)

Writes ``benchmarks/results/simulation.json``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))


OPTIMIZE = {"auto": None, "yes": True, "no": False}


def one_pass(trials: int, cache: str | None, optimize: str = "auto") -> dict:
    t0 = time.perf_counter()
    import jax

    from spdslam.cli import enable_compilation_cache
    from spdslam.experiments import StudyConfig, run_study

    used = enable_compilation_cache(Path(cache)) if cache else None
    t_import = time.perf_counter() - t0
    res = run_study(StudyConfig(trials=trials, optimize=OPTIMIZE[optimize]))
    tm = res.timings
    n = int(tm["problem_iterations"])
    return dict(
        trials=trials, optimize=optimize, solves=len(res.rows), cache=str(used) if used else None,
        backend=jax.default_backend(), import_s=t_import, wall_s=tm["wall"],
        compile_s=tm["compile"], solve_loops_s=tm["solve_loops"], scenes_s=tm["scenes"],
        evaluate_s=tm["evaluate"], problem_iterations=n,
        us_per_problem_iteration=tm["us_per_problem_iteration"],
        us_per_problem_iteration_with_compile=1e6 * (tm["solve_loops"] + tm["compile"]) / max(n, 1),
        structures=tm.get("structures", {}),
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=24, help="trials per (range, noise) cell")
    ap.add_argument("--quick", action="store_true", help="2 trials per cell")
    ap.add_argument("--cache-dir", default=None,
                    help="compilation cache directory (default: a new temporary one, removed after)")
    ap.add_argument("--optimize", choices=list(OPTIMIZE), default="auto",
                    help="XLA optimisation of the batched programs (auto: the solver's rule "
                         "by work, which leaves this grid unoptimised)")
    ap.add_argument("--out", default=str(HERE / "results" / "simulation.json"))
    ap.add_argument("--pass", dest="one", nargs=3, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        trials, cache, optimize = int(args.one[0]), args.one[1], args.one[2]
        print(json.dumps(one_pass(trials, None if cache == "-" else cache, optimize)))
        return 0
    trials = 2 if args.quick else args.trials

    passes = {}
    with tempfile.TemporaryDirectory(prefix="spdslam-jax-cache-") as tmp:
        cache = args.cache_dir or tmp
        if args.cache_dir and any(Path(cache).iterdir() if Path(cache).exists() else []):
            print(f"warning: {cache} is not empty, the 'cold' pass may hit the cache")
        for name in ("cold", "warm"):
            t0 = time.perf_counter()
            p = subprocess.run([sys.executable, __file__, "--pass", str(trials), cache,
                                args.optimize],
                               capture_output=True, text=True)
            process_s = time.perf_counter() - t0
            lines = [ln for ln in p.stdout.splitlines() if ln.startswith("{")]
            if p.returncode != 0 or not lines:
                print(f"{name} pass failed (exit {p.returncode}): {p.stderr[-800:]}")
                return 1
            r = json.loads(lines[-1])
            r["process_s"] = process_s
            passes[name] = r
            print(f"{name:4s}: {r['solves']} solves, process {process_s:6.2f} s, run_study wall "
                  f"{r['wall_s']:6.2f} s (compile {r['compile_s']:5.2f} s, LM loops "
                  f"{r['solve_loops_s']:5.2f} s, scenes {r['scenes_s']:.2f} s, evaluation "
                  f"{r['evaluate_s']:.2f} s); {r['problem_iterations']} problem-iterations: "
                  f"{r['us_per_problem_iteration']:.1f} us each in the loops, "
                  f"{r['us_per_problem_iteration_with_compile']:.1f} us with compile", flush=True)
    from scaling import environment

    out = dict(environment=environment(), trials_per_cell=trials, optimize=args.optimize,
               passes=passes)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=2))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
