"""Scaling of the joint back end on synthetic rooms: per-iteration time, graph building, memory.

Scenes: ``spdslam.synthetic.make_room_sequence(seed, frames, objects, drift=0.001)`` (a camera loop
around strips of upright objects, boxes of every object in range). Graph: the multi-spd
method's (``spdslam.mapping.build_graph``: pose prior, odometry between factors, inverse box
factors, orientation, support-plane, shape and size factors per object) with the landmarks
started at the ground-truth ellipsoids perturbed (centre + N(0, 5 cm²), radii × 1.1), so the
front end (initialisation) is left out and LM has real work to do.

Each (frames, objects) size runs in a fresh subprocess (so ``ru_maxrss`` is that size's peak
memory) which reports

- ``generate_s``, ``build_s``: scene generation; ``mapping.build_graph`` (a Python loop per
  factor), apart from the solver;
- ``layout_s`` (``solver.Problem``: grouping and stacking the factors), ``pattern_s`` (the
  CSC pattern of H and the slot maps), ``analyze_s`` (CHOLMOD's symbolic analysis), which
  ``LevenbergMarquardt.optimize`` does once per call (its "setup");
- ``compile_s``: a one-iteration warm-up run minus its setup (JAX tracing + XLA compile);
- the cost of one accepted LM iteration (``iteration_ms``), from ``--iterations`` timed
  trials with the tolerances off, as the sum of its parts: per linearisation (the initial
  one included) linearise (the jitted residuals/Jacobians/JᵀJ call) and assemble (sums into
  H and g); per trial damp, factorise (CHOLMOD numeric), backsolve, retract (retract + cost
  at the trial point). (A rejected trial costs no linearisation, so the plain mean over
  trials, ``mean_trial_ms``, depends on how many were accepted.) The growth with frames is
  summarised by the exponent of a least-squares fit iteration_ms ∝ framesᵖ per object
  count (p = 1: linear);
- ``maxrss_mb`` after building the graph and at the end;
- with ``--orderings``: CHOLMOD's symbolic analysis and numeric factorisation of the damped
  H for each fill-reducing ordering (nnz(L), seconds), the natural ordering of the layout
  (poses first, landmarks last: eliminating the poses first), and an estimate of eliminating
  the landmarks first (a Schur complement onto the poses: the non-zeros of the reduced
  camera system from the pose pairs that co-observe a landmark).

``--recompile`` solves sequences of several lengths in one process and counts XLA
compilations for each (shape bucketing: a length in a bucket already compiled should need
none).

    python3 benchmarks/scaling.py --quick                  # 1k frames x 10 objects, 3 iterations
    python3 benchmarks/scaling.py                          # 1k,5k,10k,20k x 10,100,500
    python3 benchmarks/scaling.py --frames 10000 --objects 100 --orderings
    python3 benchmarks/scaling.py --recompile --frames 1000 --objects 10

Writes ``benchmarks/results/scaling.json`` and the log-log plot ``scaling.png`` (time per
iteration and graph building against the number of factors).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

PARTS = ("jacobians", "assemble", "damp", "factorize", "backsolve", "step")
PART_NAMES = {"jacobians": "linearise", "assemble": "assemble", "damp": "damp",
              "factorize": "factorise", "backsolve": "backsolve", "step": "retract"}
ORDERINGS = ("default", "amd", "metis", "nesdis", "colamd", "natural")
#: guard on the non-zeros of L (or of a Schur complement) we are willing to build
MAX_FILL = 1.5e8


def maxrss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def scene(frames: int, objects: int, seed: int):
    """(sequence, tracks, landmarks {id: Ellipsoid}, values, seconds to generate)."""
    import numpy as np

    from spdslam.frontend import tracks_from_instances
    from spdslam.geometry import Ellipsoid
    from spdslam.mapping import SequenceContext
    from spdslam.solver import L, Values, X
    from spdslam.synthetic import make_room_sequence

    t0 = time.perf_counter()
    seq = make_room_sequence(seed, frames, objects, drift=0.001)
    tracks = tracks_from_instances(seq)
    rng = np.random.default_rng(seed + 1)
    lms = {}
    for g in seq.objects_gt:
        c = g.cuboid
        lms[g.id] = Ellipsoid.from_axes(
            np.asarray(c.rotation), np.asarray(c.center) + 0.05 * rng.standard_normal(3),
            1.1 * np.asarray(c.half_extents))
    values = Values()
    for i, T in enumerate(SequenceContext.of(seq).poses):
        values[X(i)] = T
    for k, v in lms.items():
        values[L(k)] = v
    return seq, tracks, lms, values, time.perf_counter() - t0


def orderings(problem, names) -> dict:
    """Analyse + factorise the damped H at the initial values with each CHOLMOD ordering
    (with the solver's default thread settings, ``cholmod_threads()``)."""
    import numpy as np
    import scipy.sparse
    from sksparse import cholmod

    from spdslam.solver._linear import cholmod_threads

    sp = problem.sparse_pattern()
    n = problem.n
    h, *_ = problem.linearize(problem.vars)
    h = h.copy()
    h[sp["diag"]] += 1e-4 * np.clip(h[sp["diag"]], 1e-6, None)
    A = scipy.sparse.csc_matrix((h, sp["indices"], sp["indptr"]), shape=(n, n))
    out = {"n": int(n), "nnz_H_lower": int(sp["nnz"])}
    # tangent coordinates of the landmarks (the non-SE3 types) and of the poses
    is_pose = np.zeros(n, bool)
    for ts, ti, fr in zip(problem.tspecs, problem.tan_idx, problem.free):
        if ts.cls.__name__ == "SE3":
            is_pose[ti[: len(fr)][fr].ravel()] = True
    out["layout_poses_first"] = bool(is_pose[: int(is_pose.sum())].all())
    # fill of natural ordering (poses first): each landmark row fills from its first pose on
    cols = np.repeat(np.arange(n), np.diff(sp["indptr"]))
    rows = sp["indices"]
    lm_rows = ~is_pose[rows] & is_pose[cols]
    first = np.full(n, n)
    np.minimum.at(first, rows[lm_rows], cols[lm_rows])
    npose = int(is_pose.sum())
    est_natural = float(np.sum(np.maximum(npose - first[~is_pose], 0)))
    for name in names:
        rec = {}
        if name == "natural" and est_natural > MAX_FILL:
            rec["skipped"] = f"estimated nnz(L) {est_natural:.3g} > {MAX_FILL:.3g}"
            out[name] = rec
            continue
        for mode in ("supernodal", "simplicial"):
            if mode == "simplicial" and rec["supernodal"]["nnz_L"] > 1e7:
                rec[mode] = dict(skipped="nnz(L) > 1e7: slow column-by-column")
                continue
            t0 = time.perf_counter()
            f = cholmod.analyze(A, mode=mode, ordering_method=name)
            t_an = time.perf_counter() - t0
            times = []
            for _ in range(3):
                t0 = time.perf_counter()
                with cholmod_threads():
                    f.cholesky_inplace(A)
                times.append(time.perf_counter() - t0)
            L = f.L()
            rec[mode] = dict(analyze_s=t_an, factorize_s=min(times), nnz_L=int(L.nnz))
            del L
            if mode == "supernodal":
                x = f(np.ones(n))
                rec["residual"] = float(np.linalg.norm(
                    (A + A.T - scipy.sparse.diags(A.diagonal())) @ x - 1.0))
        out[name] = rec
    out["natural_estimated_nnz_L_landmark_rows"] = est_natural
    # Schur complement onto the poses (landmarks eliminated first): pose pairs that
    # co-observe a landmark become dense 6x6 blocks of the reduced camera system.
    lm_of_row = np.where(~is_pose)[0]
    B = scipy.sparse.csc_matrix(
        (np.ones(int(lm_rows.sum())), (cols[lm_rows], rows[lm_rows])), shape=(n, n))
    B = B[:, lm_of_row][np.where(is_pose)[0], :]
    V = (B[::6, ::9] != 0).astype(np.float64)  # pose x landmark incidence
    per_lm = np.asarray(V.sum(axis=0)).ravel()  # poses observing each landmark
    est_pairs = float(np.sum(per_lm ** 2))
    sch = {"poses_per_landmark_mean": float(per_lm.mean()) if len(per_lm) else 0.0,
           "estimated_nnz_reduced_upper_bound": 36.0 * est_pairs}
    if 36.0 * est_pairs <= MAX_FILL:
        t0 = time.perf_counter()
        S = (V @ V.T).tocsc()
        sch["nnz_reduced"] = 36 * int(S.nnz)
        sch["pattern_s"] = time.perf_counter() - t0
    else:
        sch["skipped"] = "reduced system too large to build"
    out["schur_landmarks_first"] = sch
    return out


def worker(frames: int, objects: int, iterations: int, seed: int, order_names,
           blas_threads: int = 1) -> dict:
    import jax

    from spdslam.mapping import METHODS, build_graph
    from spdslam.solver import LevenbergMarquardt, Problem
    from spdslam.solver._linear import make_linear_solver, resolve_linear_solver

    compiles = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda ev, d, **kw: compiles.append(d)
        if ev == "/jax/core/compile/backend_compile_duration" else None)
    seq, tracks, lms, values, t_gen = scene(frames, objects, seed)
    t0 = time.perf_counter()
    graph = build_graph(seq, tracks, lms, METHODS["multi-spd"])
    t_build = time.perf_counter() - t0
    kinds: dict = {}
    for f in graph:
        kinds[f.kind] = kinds.get(f.kind, 0) + 1
    rss_build = maxrss_mb()

    # set-up parts, measured apart (optimize() repeats them inside its "setup")
    t0 = time.perf_counter()
    problem = Problem(graph, values)
    t_layout = time.perf_counter() - t0
    t0 = time.perf_counter()
    pattern = problem.sparse_pattern()
    t_pattern = time.perf_counter() - t0
    kind = resolve_linear_solver("auto", problem.n)
    t0 = time.perf_counter()
    make_linear_solver(kind, pattern, problem.n)
    t_analyze = time.perf_counter() - t0

    lm_args = dict(relative_tolerance=0.0, absolute_tolerance=0.0, gradient_tolerance=0.0,
                   step_tolerance=0.0, cholmod_blas_threads=blas_threads or None)
    t0 = time.perf_counter()
    warm = LevenbergMarquardt(max_iterations=1, **lm_args).optimize(graph, values)
    t_warm = time.perf_counter() - t0
    n_compiles = len(compiles)
    t0 = time.perf_counter()
    res = LevenbergMarquardt(max_iterations=iterations, **lm_args).optimize(graph, values)
    t_total = time.perf_counter() - t0
    tm = res.timings
    it = max(res.iterations, 1)
    nlin = max(res.linearizations, 1)
    # linearise and assemble per linearisation (the initial one included), the rest per
    # trial: their sum is one accepted LM iteration, whatever the share of rejected trials
    per = {PART_NAMES[k]: 1e3 * tm.get(k, 0.0) / (nlin if k in ("jacobians", "assemble") else it)
           for k in PARTS}
    t_iter = t_total - tm["setup"]
    out = dict(
        frames=frames, objects=objects, seed=seed, blas_threads=blas_threads,
        factors=len(graph), factor_kinds=kinds, n=int(problem.n), nnz_H_lower=int(pattern["nnz"]),
        landmarks=len(lms), linear_solver=res.linear_solver,
        generate_s=t_gen, build_s=t_build, build_us_per_factor=1e6 * t_build / len(graph),
        layout_s=t_layout, pattern_s=t_pattern, analyze_s=t_analyze,
        setup_s=tm["setup"], compile_s=max(0.0, t_warm - warm.timings["setup"]
                                            - sum(r.time for r in warm.history)),
        compiles_warmup=n_compiles, compiles_timed=len(compiles) - n_compiles,
        iterations=res.iterations, linearizations=res.linearizations,
        accepted=int(sum(r.accepted for r in res.history)),
        initial_cost=res.initial_cost, final_cost=res.final_cost,
        iteration_ms=sum(per.values()), mean_trial_ms=1e3 * t_iter / it, breakdown_ms=per,
        maxrss_build_mb=rss_build,
    )
    if order_names:
        out["orderings"] = orderings(problem, order_names)
    out["maxrss_mb"] = maxrss_mb()
    return out


def recompile_worker(frames: int, objects: int, seed: int) -> dict:
    """Solve sequences of several lengths in one process; count XLA compiles for each."""
    import jax

    from spdslam.mapping import METHODS, build_graph
    from spdslam.solver import LevenbergMarquardt, Problem
    from spdslam.solver._problem import bucket

    events = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda ev, d, **kw: events.append(d)
        if ev == "/jax/core/compile/backend_compile_duration" else None)
    rows = []
    for scale in (1.0, 1.03, 1.1, 1.3, 1.0):
        F = int(round(frames * scale))
        seq, tracks, lms, values, _ = scene(F, objects, seed)
        graph = build_graph(seq, tracks, lms, METHODS["multi-spd"])
        p = Problem(graph, values)
        shapes = sorted(int(ix[0].shape[0]) for ix in p.gidx)
        n0 = len(events)
        t0 = time.perf_counter()
        LevenbergMarquardt(max_iterations=2).optimize(graph, values)
        rows.append(dict(frames=F, factors=len(graph), padded_group_sizes=shapes,
                         group_sizes=sorted(p.group_nf), pose_bucket=bucket(F),
                         compiles=len(events) - n0, compile_s=sum(events[n0:]),
                         solve_s=time.perf_counter() - t0))
    return dict(frames=frames, objects=objects, runs=rows)


def run_sub(argv, timeout) -> dict:
    cmd = [sys.executable, str(Path(__file__).resolve())] + argv
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"error": f"timed out after {timeout} s"}
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("{")]
    if p.returncode != 0 or not lines:
        return {"error": f"exit {p.returncode}: {p.stderr.strip()[-400:]}"}
    return json.loads(lines[-1])


def plot(rows, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(11, 4.2))
    for O in sorted({r["objects"] for r in rows}):
        rs = sorted((r for r in rows if r["objects"] == O), key=lambda r: r["factors"])
        x = [r["factors"] for r in rs]
        ax[0].loglog(x, [r["iteration_ms"] / 1e3 for r in rs], "o-", label=f"{O} objects: iteration")
        ax[0].loglog(x, [r["breakdown_ms"]["factorise"] / 1e3 for r in rs], "s--", alpha=0.6,
                     label=f"{O} objects: factorise")
        ax[0].loglog(x, [r["breakdown_ms"]["linearise"] / 1e3 for r in rs], "^:", alpha=0.6,
                     label=f"{O} objects: linearise")
        ax[1].loglog(x, [r["build_s"] for r in rs], "o-", label=f"{O} objects: build_graph")
        ax[1].loglog(x, [r["setup_s"] for r in rs], "s--", label=f"{O} objects: solver setup")
    allx = sorted(r["factors"] for r in rows)
    if len(allx) > 1:
        for a in ax:
            lo, hi = a.get_ylim()
            ref = [allx[0], allx[-1]]
            y0 = (lo * hi) ** 0.5 / (allx[-1] / allx[0]) ** 0.5
            a.loglog(ref, [y0, y0 * allx[-1] / allx[0]], "k-", lw=0.6, label="slope 1")
    ax[0].set(xlabel="factors", ylabel="seconds per LM iteration", title="LM iteration")
    ax[1].set(xlabel="factors", ylabel="seconds", title="graph building and solver set-up")
    for a in ax:
        a.grid(True, which="both", alpha=0.3)
        a.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def frames_exponents(rows) -> dict:
    """{objects: p} with iteration_ms ∝ framesᵖ fitted in log-log (sizes without errors)."""
    import numpy as np

    out = {}
    for O in sorted({r["objects"] for r in rows}):
        rs = [r for r in rows if r["objects"] == O and "error" not in r]
        if len({r["frames"] for r in rs}) >= 2:
            x = np.log([r["frames"] for r in rs])
            y = np.log([r["iteration_ms"] for r in rs])
            out[str(O)] = float(np.polyfit(x, y, 1)[0])
    return out


def environment() -> dict:
    import jax
    import numpy as np
    import scipy

    import spdslam

    cpu = "unknown"
    try:
        for ln in Path("/proc/cpuinfo").read_text().splitlines():
            if ln.startswith("model name"):
                cpu = ln.split(":", 1)[1].strip()
                break
        mem = Path("/proc/meminfo").read_text().splitlines()[0].split()[1]
        mem_gb = int(mem) / 1024**2
    except OSError:
        mem_gb = None
    return dict(python=sys.version.split()[0], platform=platform.platform(), cpu=cpu,
                cpus=os.cpu_count(), memory_gb=mem_gb, jax=jax.__version__,
                backend=jax.default_backend(), numpy=np.__version__, scipy=scipy.__version__,
                spdslam=spdslam.__version__)


def ints(s: str) -> list[int]:
    return [int(x) for x in s.split(",") if x]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=ints, default=[1000, 5000, 10000, 20000])
    ap.add_argument("--objects", type=ints, default=[10, 100, 500])
    ap.add_argument("--iterations", type=int, default=5, help="timed LM iterations per size")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--blas-threads", type=int, default=1,
                    help="OpenBLAS threads in CHOLMOD's factorisation (the solver's default 1; "
                         "0: leave the library's own setting)")
    ap.add_argument("--orderings", nargs="?", const=",".join(ORDERINGS), default="",
                    help="also compare CHOLMOD orderings (default list: %(const)s)")
    ap.add_argument("--recompile", action="store_true",
                    help="only count compilations for sequences of several lengths")
    ap.add_argument("--timeout", type=int, default=1200, help="seconds per size")
    ap.add_argument("--quick", action="store_true", help="1k frames x 10 objects, 3 iterations")
    ap.add_argument("--out", default=str(HERE / "results" / "scaling.json"))
    ap.add_argument("--plot", default=None, help="PNG path (default: next to --out)")
    ap.add_argument("--worker", nargs=2, type=int, help=argparse.SUPPRESS)
    ap.add_argument("--recompile-worker", nargs=2, type=int, help=argparse.SUPPRESS)
    args = ap.parse_args()
    order_names = [x for x in args.orderings.split(",") if x]

    if args.worker:
        import spdslam  # noqa: F401 - enables float64
        print(json.dumps(worker(*args.worker, args.iterations, args.seed, order_names,
                                args.blas_threads)))
        return 0
    if args.recompile_worker:
        import spdslam  # noqa: F401 - enables float64
        print(json.dumps(recompile_worker(*args.recompile_worker, args.seed)))
        return 0
    if args.quick:
        args.frames, args.objects, args.iterations = [1000], [10], 3

    out_path = Path(args.out)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    result = dict(environment=environment(), args={k: v for k, v in vars(args).items()
                                                   if not k.endswith("worker")})
    if args.recompile:
        rows = []
        for F in args.frames:
            for O in args.objects:
                r = run_sub(["--recompile-worker", str(F), str(O), "--seed", str(args.seed)],
                            args.timeout)
                rows.append(r)
                if "error" in r:
                    print(f"{F} x {O}: {r['error']}")
                    continue
                print(f"{F} frames x {O} objects: one process, sequences solved in turn")
                for x in r["runs"]:
                    print(f"  {x['frames']:6d} frames, {x['factors']:7d} factors, padded group "
                          f"sizes {x['padded_group_sizes']}: {x['compiles']} compilations "
                          f"({x['compile_s']:.2f} s), solve {x['solve_s']:.2f} s")
        result["recompile"] = rows
        out_path = out_path.with_name(out_path.stem + "_recompile.json")
        out_path.write_text(json.dumps(result, indent=2))
        print(f"wrote {out_path}")
        return 0

    rows = []
    head = (f"{'frames':>6} {'obj':>4} {'factors':>8} {'n':>7} {'build':>6} {'setup':>6} "
            f"{'compile':>7} {'iter':>7} " + " ".join(f"{PART_NAMES[k]:>9}" for k in PARTS)
            + f" {'RSS MB':>7}")
    print("times in s, iteration (one accepted: linearise + assemble per linearisation, the "
          "rest per trial) and its parts in ms; RSS = peak resident memory of the size's process")
    print(head)
    for F in args.frames:
        for O in args.objects:
            argv = ["--worker", str(F), str(O), "--iterations", str(args.iterations),
                    "--blas-threads", str(args.blas_threads),
                    "--seed", str(args.seed)]
            if order_names:
                argv += ["--orderings", ",".join(order_names)]
            r = run_sub(argv, args.timeout)
            if "error" in r:
                print(f"{F:6d} {O:4d}  {r['error']}", flush=True)
                rows.append(dict(frames=F, objects=O, **r))
                continue
            rows.append(r)
            b = r["breakdown_ms"]
            print(f"{F:6d} {O:4d} {r['factors']:8d} {r['n']:7d} {r['build_s']:6.2f} "
                  f"{r['setup_s']:6.2f} {r['compile_s']:7.2f} {r['iteration_ms']:7.1f} "
                  + " ".join(f"{b[PART_NAMES[k]]:9.1f}" for k in PARTS)
                  + f" {r['maxrss_mb']:7.0f}", flush=True)
            if "orderings" in r:
                o = r["orderings"]
                for name in order_names:
                    rec = o[name]
                    if "skipped" in rec:
                        print(f"      ordering {name:8s} skipped: {rec['skipped']}")
                        continue
                    s, q = rec["supernodal"], rec["simplicial"]
                    simp = (f"{1e3 * q['factorize_s']:8.1f} ms" if "factorize_s" in q
                            else "skipped")
                    print(f"      ordering {name:8s} nnz(L) {s['nnz_L']:>11d}  analyze "
                          f"{s['analyze_s']:6.3f} s  factorise supernodal "
                          f"{1e3 * s['factorize_s']:8.1f} ms, simplicial {simp}")
                sch = o["schur_landmarks_first"]
                print(f"      landmarks first (Schur onto poses): reduced system nnz "
                      f"{sch.get('nnz_reduced', sch['estimated_nnz_reduced_upper_bound']):.3g}"
                      f" (vs nnz(L) {o['default']['supernodal']['nnz_L'] if 'supernodal' in o.get('default', {}) else '-'}"
                      f" with CHOLMOD's default ordering)")
    result["sizes"] = rows
    result["frames_exponent"] = frames_exponents(rows)
    for O, p in result["frames_exponent"].items():
        print(f"{O} objects: iteration time ∝ frames^{p:.2f} (least squares over "
              f"{len([r for r in rows if r['objects'] == int(O) and 'error' not in r])} sizes)")
    out_path.write_text(json.dumps(result, indent=2))
    good = [r for r in rows if "error" not in r]
    if good:
        png = Path(args.plot) if args.plot else out_path.with_suffix(".png")
        plot(good, png)
        print(f"wrote {out_path} and {png}")
    else:
        print(f"wrote {out_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
