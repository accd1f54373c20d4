"""Simulation throughput here and through Ray: the same grid run locally (one process, no
engine) and on a local Ray instance with 1 and 2 workers, each part in a fresh process
(every program compiled from scratch, no persistent compilation cache).

Per part: the study's wall time (``run_study``: scenes, tasks or solves, evaluation), Ray's
start-up apart, solves per second, the ratio to the local throughput, and whether the trials
(every trials.csv column but ``seconds``) are identical to the local run's. Ray's overhead
per task is measured twice: round trips of an empty task, and in the study as (wall ×
workers − the tasks' own seconds) / tasks, the time a worker spends not computing.

    python3 benchmarks/ray_scaling.py                      # 1000 trials per cell, local, Ray 1 and 2
    python3 benchmarks/ray_scaling.py --trials 24 --quick  # a smoke run
    python3 benchmarks/ray_scaling.py --address ray://HEAD:10001 --parts local,cluster

With ``--address`` the ``cluster`` part runs on that cluster with all its CPUs (start the
cluster first: ``ray start --head`` on one machine, ``ray start --address HEAD:6379`` on the
others, each with spdslam installed at the same version). Writes
``benchmarks/results/ray_scaling.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))


def _noop(i):
    return i


def one_part(part: str, trials: int, address: str | None, rows_path: str) -> dict:
    """One part in this process: "local", "ray:N" (a local instance of N CPUs) or "cluster"."""
    t0 = time.perf_counter()
    import jax

    from spdslam.experiments import StudyConfig, run_study

    cfg = StudyConfig(trials=trials)
    out = {"part": part, "trials": trials, "solves": 0, "backend": jax.default_backend()}
    engine = None
    if part != "local":
        from spdslam.experiments import RayEngine

        t = time.perf_counter()
        engine = RayEngine(address=address) if part == "cluster" else \
            RayEngine(workers=int(part.split(":")[1]))
        out["ray_start_s"] = time.perf_counter() - t
        out["workers"] = engine.workers
        # the round trip of empty tasks, after one wave has started the workers
        engine.map(_noop, [(i,) for i in range(engine.workers)])
        n = 200
        t = time.perf_counter()
        engine.map(_noop, [(i,) for i in range(n)])
        out["empty_task_ms"] = 1e3 * (time.perf_counter() - t) / n
    res = run_study(cfg, engine=engine)
    tm = res.timings
    out.update(solves=len(res.rows), wall_s=tm["wall"], solves_per_s=len(res.rows) / tm["wall"],
               us_per_problem_iteration=tm["us_per_problem_iteration"],
               problem_iterations=int(tm["problem_iterations"]), compile_s=tm["compile"],
               process_s=time.perf_counter() - t0)
    if engine is not None:
        out.update(tasks=tm["tasks"], trials_per_task=tm["trials_per_task"],
                   task_seconds=tm["task_seconds"],
                   idle_per_task_s=(tm["wall"] * engine.workers - tm["task_seconds"]) / tm["tasks"])
        engine.close()
    with open(rows_path, "w") as f:
        json.dump([{k: v for k, v in r.items() if k != "seconds"} for r in res.rows], f)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=1000, help="trials per (range, noise) cell")
    ap.add_argument("--parts", default="local,ray:1,ray:2",
                    help="comma-separated: local, ray:N (a local Ray instance of N CPUs), cluster")
    ap.add_argument("--address", default=None, help="the Ray cluster of the cluster part")
    ap.add_argument("--quick", action="store_true", help="24 trials per cell")
    ap.add_argument("--out", default=str(HERE / "results" / "ray_scaling.json"))
    ap.add_argument("--part", nargs=4, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.part:
        part, trials, address, rows = args.part
        print(json.dumps(one_part(part, int(trials), None if address == "-" else address, rows)))
        return 0
    trials = 24 if args.quick else args.trials
    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    if "cluster" in parts and not args.address:
        ap.error("the cluster part needs --address")
    results, rows = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        for part in parts:
            path = os.path.join(tmp, part.replace(":", "_") + ".json")
            cmd = [sys.executable, __file__, "--part", part, str(trials), args.address or "-", path]
            proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
            if proc.returncode != 0:
                print(proc.stderr[-3000:], file=sys.stderr)
                return proc.returncode
            r = json.loads(proc.stdout.strip().splitlines()[-1])
            rows[part] = json.load(open(path))
            results.append(r)
            print(f"{part:>8}: {r['solves']} solves in {r['wall_s']:.1f} s = {r['solves_per_s']:.0f} "
                  f"solves/s" + (f"; Ray start {r['ray_start_s']:.1f} s, {r['tasks']} tasks of "
                                 f"{r['trials_per_task']}, empty task {r['empty_task_ms']:.2f} ms, "
                                 f"idle per task {r['idle_per_task_s']:.2f} s" if "tasks" in r else ""),
                  flush=True)
    base = next((r for r in results if r["part"] == "local"), None)
    for r in results:
        if base is not None:
            r["throughput_vs_local"] = r["solves_per_s"] / base["solves_per_s"]
            r["identical_to_local"] = rows[r["part"]] == rows["local"]
            print(f"{r['part']:>8}: {r['throughput_vs_local']:.2f}x local, trials identical: "
                  f"{r['identical_to_local']}")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps({
        "machine": {"cores": os.cpu_count(), "python": platform.python_version(),
                    "platform": platform.platform()},
        "command": "python3 benchmarks/ray_scaling.py " + " ".join(sys.argv[1:]),
        "date": time.strftime("%Y-%m-%d"), "parts": results}, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
