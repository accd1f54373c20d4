"""Batched single-object solves: compile and run time of ``BatchedProblem`` per structure.

The six structures of the simulation study: landmark parameterisation (Ellipsoid = SPD,
EllipsoidRTS, EllipsoidFull) × box factor (inverse, semi-inverse), each a batch of B scenes
from ``spdslam.synthetic.make_scenes`` (10 fixed camera poses, 1 landmark, 10 box factors).

    python3 benchmarks/batched.py                      # B = 144, writes results/batched.json
    python3 benchmarks/batched.py --batch 32 --lanes 16 --out my.json

Per structure: trace (tracing + lowering) and compile (XLA) seconds of the batched program
(cold: each structure is a new program; no persistent compilation cache), solve seconds of
the first run and the best of ``--repeat`` further runs, µs per problem-iteration (best
solve seconds / Σ iterations over the problems), iterations (median, max), loop steps, and
the first call of ``cost`` (at the ground truth; includes building its program). "wall" is
everything for the structure in the cold pass: template, input layout, solve, cost.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

T_START = time.perf_counter()

import jax  # noqa: E402
import jaxlie  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

import spdslam  # noqa: E402
from spdslam import Ellipsoid, EllipsoidFull, EllipsoidRTS  # noqa: E402
from spdslam.factors import InverseBoxFactor, SemiInverseBoxFactor  # noqa: E402
from spdslam.solver import L, LevenbergMarquardt, NonlinearFactorGraph, Values, X  # noqa: E402
from spdslam.synthetic import make_scenes  # noqa: E402

LANDMARKS = {
    "Ellipsoid": (Ellipsoid, None),
    "EllipsoidRTS": (EllipsoidRTS, EllipsoidRTS.from_ellipsoid),
    "EllipsoidFull": (EllipsoidFull, EllipsoidFull.from_ellipsoid),
}
BOXES = {"inverse": InverseBoxFactor, "semi_inverse": SemiInverseBoxFactor}


def structure(scenes, landmark: str, box: str, max_iterations: int, optimize=None, **params):
    """(BatchedProblem, factor_args, initial values, truth values) of one structure."""
    _, conv = LANDMARKS[landmark]
    factor = BOXES[box]
    views = scenes.boxes.shape[1]
    if conv is None:
        init, truth = scenes.initial, scenes.truth
    else:
        cv = jax.jit(jax.vmap(conv))
        init, truth = cv(scenes.initial), cv(scenes.truth)
    init = jax.tree.map(np.asarray, init)
    truth = jax.tree.map(np.asarray, truth)
    poses = np.asarray(scenes.poses.wxyz_xyz)
    boxes = np.asarray(scenes.boxes)
    graph, values = NonlinearFactorGraph(), Values()
    for i in range(views):
        values[X(i)] = jaxlie.SE3(poses[0, i])
        graph.add(factor(X(i), L(0), boxes[0, i], scenes.camera))
    values[L(0)] = jax.tree.map(lambda a: a[0], init)
    bp = LevenbergMarquardt(max_iterations=max_iterations, **params).batched(
        graph, values, fixed=[X(i) for i in range(views)], optimize=optimize)
    factor_args = {i: (boxes[:, i], scenes.camera) for i in range(views)}
    pose_values = {X(i): jaxlie.SE3(poses[:, i]) for i in range(views)}
    return bp, factor_args, {**pose_values, L(0): init}, {**pose_values, L(0): truth}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--batch", type=int, default=144, help="problems per structure (B)")
    ap.add_argument("--lanes", type=int, default=None,
                    help="problems in flight at once (default: the solver's)")
    ap.add_argument("--max-iterations", type=int, default=100)
    ap.add_argument("--lambda-initial", type=float, default=None,
                    help="LM's initial damping (default: the solver's)")
    ap.add_argument("--noise", default="M", choices=["L", "M", "H"])
    ap.add_argument("--angle", type=float, default=60.0, help="angle range of the views (deg)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--optimize", choices=["auto", "yes", "no"], default="auto",
                    help="optimise the compiled code (default: the solver's choice by size)")
    ap.add_argument("--repeat", type=int, default=3, help="warm solves timed per structure")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(os.path.abspath(__file__)),
                                                  "results", "batched.json"))
    ap.add_argument("--quick", action="store_true", help="B = 16, one warm solve (smoke run)")
    args = ap.parse_args()
    if args.quick:
        args.batch, args.repeat = 16, 1
    optimize = {"auto": None, "yes": True, "no": False}[args.optimize]
    params = {} if args.lambda_initial is None else {"lambda_initial": args.lambda_initial}

    t0 = time.perf_counter()
    scenes = make_scenes(args.seed, args.batch, args.noise, args.angle)
    t_scenes = time.perf_counter() - t0
    print(f"jax {jax.__version__} on {jax.default_backend()}, {os.cpu_count()} CPUs; "
          f"B = {args.batch}, lanes = {args.lanes or 'default'}, "
          f"max_iterations = {args.max_iterations}, optimize = {args.optimize}; import {t0 - T_START:.2f} s, "
          f"scenes {t_scenes:.2f} s")
    head = (f"{'structure':<30} {'trace':>6} {'compile':>7} {'solve1':>7} {'solve':>7} "
            f"{'us/it':>6} {'med it':>6} {'max it':>6} {'steps':>5} {'conv':>5} {'cost()':>6} "
            f"{'wall':>6}")
    print(head)
    print("-" * len(head))
    rows = []
    t_all = time.perf_counter()
    for landmark in LANDMARKS:
        for box in BOXES:
            tw = time.perf_counter()
            bp, fa, init, truth = structure(scenes, landmark, box, args.max_iterations,
                                            optimize, **params)
            r = bp.solve(fa, init, batch_size=args.lanes)
            tc = time.perf_counter()
            cost_truth = bp.cost(fa, truth)
            t_cost = time.perf_counter() - tc
            wall = time.perf_counter() - tw
            warm = []
            for _ in range(args.repeat):
                warm.append(bp.solve(fa, init, batch_size=args.lanes).timings["solve"])
            its = r.iterations
            best = min(warm) if warm else r.timings["solve"]
            row = dict(
                landmark=landmark, box=box, batch=args.batch, lanes=args.lanes,
                trace_s=r.timings["trace"], compile_s=r.timings["compile"],
                solve_first_s=r.timings["solve"], solve_s=best,
                us_per_iteration=1e6 * best / max(int(its.sum()), 1),
                iterations_total=int(its.sum()), iterations_median=float(np.median(its)),
                iterations_max=int(its.max()), steps=r.steps,
                converged=float(np.mean(r.converged)),
                cost_first_s=t_cost, wall_s=wall,
                final_cost_median=float(np.median(r.final_cost)),
                truth_cost_median=float(np.median(cost_truth)),
            )
            rows.append(row)
            name = f"{landmark} / {box}"
            print(f"{name:<30} {row['trace_s']:6.2f} {row['compile_s']:7.2f} "
                  f"{row['solve_first_s']:7.3f} {best:7.3f} {row['us_per_iteration']:6.1f} "
                  f"{row['iterations_median']:6.1f} {row['iterations_max']:6d} "
                  f"{row['steps']:5d} {row['converged']:5.2f} {t_cost:6.2f} {wall:6.2f}",
                  flush=True)
    total = {k: sum(r[k] for r in rows) for k in
             ("trace_s", "compile_s", "solve_first_s", "solve_s", "cost_first_s", "wall_s",
              "iterations_total")}
    total["us_per_iteration"] = 1e6 * total["solve_s"] / max(total["iterations_total"], 1)
    print("-" * len(head))
    print(f"{'total':<30} {total['trace_s']:6.2f} {total['compile_s']:7.2f} "
          f"{total['solve_first_s']:7.3f} {total['solve_s']:7.3f} "
          f"{total['us_per_iteration']:6.1f} {'':>6} {'':>6} {'':>5} {'':>5} "
          f"{total['cost_first_s']:6.2f} {total['wall_s']:6.2f}")
    print(f"cold pass over the {len(rows)} structures ({len(rows) * args.batch} solves): "
          f"{sum(r['wall_s'] for r in rows):.2f} s; from process start: "
          f"{t_all - T_START + sum(r['wall_s'] for r in rows):.2f} s")
    out = dict(
        jax=jax.__version__, spdslam=spdslam.__version__, backend=jax.default_backend(),
        cpus=os.cpu_count(), machine=platform.machine(), args=vars(args),
        import_s=t0 - T_START, scenes_s=t_scenes, structures=rows, total=total,
    )
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(out, f, indent=2)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
