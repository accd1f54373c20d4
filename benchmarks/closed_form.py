"""The inverse box factor's closed form against its JAX program: one linearisation and one
cost evaluation of a problem of box factors only, with ``solver.closed_forms`` on and off, in
one process (docs/performance.md, section 8).

The problem has the shape of fr2_desk's box group: ``--poses`` camera poses, each seeing
``--per-pose`` of ``--objects`` SPD landmarks (inverse box model, Cauchy kernel, σ 2 px,
truncation margin 5 px); the first pose is held. Each mode is run once to load or compile its
programs (the closed form first: its first linearisation also compiles the two variable
types' pushforwards, which both modes use), then ``--repeats`` times; medians are printed.
The two linearisations' H and g are compared.

``--retain`` first calls ``solver.retain_freed_memory`` (as the ``spdslam`` command does when
a command starts): freed blocks are reused instead of being handed back and faulted in again.

The closed form is measured twice where the compiled kernels are built (``geometry.native``):
with them (the default) and with its NumPy code (``native.compiled_kernels(False)``).

    python3 benchmarks/closed_form.py [--poses 2200] [--per-pose 10] [--objects 20] [--repeats 7] [--retain]
                                      [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # run from a checkout

from spdslam.factors import Cauchy, InverseBoxFactor  # noqa: E402
from spdslam.geometry import Camera, Ellipsoid, look_at, native, project_box  # noqa: E402
from spdslam.solver import L, NonlinearFactorGraph, Problem, Values, X, closed_forms, retain_freed_memory  # noqa: E402


def problem_parts(poses: int, per_pose: int, objects: int, seed: int = 0):
    """(graph, values): objects on a 4 m × 3 m floor, cameras 1.5–3 m from an object looking
    near it, each box the projection plus 2 px of noise."""
    rng = np.random.default_rng(seed)
    cam = Camera(fx=520.0, fy=520.0, cx=320.0, cy=240.0, width=640.0, height=480.0)
    values = Values()
    centres = np.c_[rng.uniform(-2, 2, objects), rng.uniform(-1.5, 1.5, objects), rng.uniform(0.2, 1.0, objects)]
    lms = []
    for j in range(objects):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        lm = Ellipsoid.from_axes(q, centres[j], rng.uniform(0.05, 0.3, 3))
        lms.append(lm)
        values.insert(L(j), lm)
    pose_keys, lm_keys, boxes = [], [], []
    for i in range(poses):
        j0 = i % objects
        direction = rng.normal(size=3)
        direction[2] = abs(direction[2]) + 0.3
        eye = centres[j0] + rng.uniform(4.0, 6.0) * direction / np.linalg.norm(direction)
        T = look_at(eye, centres[j0] + rng.normal(scale=0.05, size=3))
        values.insert(X(i), T)
        for j in rng.choice(objects, size=min(per_pose, objects), replace=False):
            pose_keys.append(X(i))
            lm_keys.append(L(int(j)))
            boxes.append(np.asarray(project_box(lms[j], T, cam)) + rng.normal(scale=2.0, size=4))
    graph = NonlinearFactorGraph()
    boxes_a = np.asarray(boxes)
    boxes_a = np.c_[np.minimum(boxes_a[:, 0], boxes_a[:, 2]), np.minimum(boxes_a[:, 1], boxes_a[:, 3]),
                    np.maximum(boxes_a[:, 0], boxes_a[:, 2]), np.maximum(boxes_a[:, 1], boxes_a[:, 3])]
    graph.add(InverseBoxFactor.many(pose_keys, lm_keys, boxes_a, cam, sigma=2.0, robust=Cauchy(1.0),
                                    truncation_margin=5.0))
    return graph, values


def measure(graph, values, on: bool, repeats: int) -> dict:
    """Seconds of the first and the later linearisations and cost evaluations, and (H, g)."""
    with closed_forms(on):
        problem = Problem(graph, values, fixed=[X(0)])
    t0 = time.perf_counter()
    H, g, *_ = problem.linearize(problem.vars)
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    problem.cost()
    first_cost = time.perf_counter() - t0
    lin, cost = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        problem.linearize(problem.vars)
        lin.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        problem.cost()
        cost.append(time.perf_counter() - t0)
    return dict(first_linearisation=first, first_cost=first_cost, linearisation=statistics.median(lin),
                cost=statistics.median(cost), H=H, g=g)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--poses", type=int, default=2200)
    ap.add_argument("--per-pose", type=int, default=10)
    ap.add_argument("--objects", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--quick", action="store_true", help="200 poses, 3 repeats")
    ap.add_argument("--retain", action="store_true", help="solver.retain_freed_memory() first, as the command")
    ap.add_argument("--out", type=Path)
    a = ap.parse_args()
    if a.quick:
        a.poses, a.repeats = 200, 3
    retained = retain_freed_memory() if a.retain else False
    graph, values = problem_parts(a.poses, a.per_pose, a.objects)
    n = len(graph.entries()[0])
    res = {}
    if native.native_kernels() is not None:
        res["closed form (compiled)"] = measure(graph, values, True, a.repeats)
    with native.compiled_kernels(False):
        res["closed form (NumPy)"] = measure(graph, values, True, a.repeats)
    res["JAX"] = measure(graph, values, False, a.repeats)
    print(f"{n} inverse box factors, {a.poses} poses, {a.objects} objects; medians of {a.repeats}; "
          f"freed memory {'retained' if retained else 'handed back (glibc defaults)'}")
    modes = list(res)
    print("| | " + " | ".join(modes) + " | ratios to JAX |\n|" + " --- |" * (len(modes) + 2))
    for key in ("first_linearisation", "linearisation", "first_cost", "cost"):
        ms = " | ".join(f"{1e3 * res[m][key]:.1f}" for m in modes)
        ratios = ", ".join(f"{res[m][key] / res['JAX'][key]:.2f}×" for m in modes[:-1])
        print(f"| {key.replace('_', ' ')} (ms) | {ms} | {ratios} |")
    Hj, gj = res["JAX"]["H"], res["JAX"]["g"]
    diffs = {}
    for m in modes[:-1]:
        diffs[m] = (float(np.max(np.abs(res[m]["H"] - Hj)) / np.max(np.abs(Hj))),
                    float(np.max(np.abs(res[m]["g"] - gj)) / np.max(np.abs(gj))))
        print(f"H and g, {m} against JAX: largest difference {diffs[m][0]:.1e} and {diffs[m][1]:.1e} of their "
              "largest entries")
    if a.out:
        out = {mode: {k: v for k, v in r.items() if k not in ("H", "g")} for mode, r in res.items()}
        out.update(factors=n, poses=a.poses, objects=a.objects, repeats=a.repeats, retained=retained,
                   differences_to_jax={m: {"H": d[0], "g": d[1]} for m, d in diffs.items()})
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(out, indent=2))
        print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
