"""Sparse Cholesky libraries side by side on spdslam's normal equations, in one run.

Two problems: gtsam's sphere2500 pose graph (15 000 tangent dimensions) and the
10k-frame x 100-object room of ``benchmarks/scaling.py`` (60 900).

1. Factorisation: H at the initial values, damped as LM's first trial (H + λ·clip(diag H),
   λ = 1e-4), given to each library in a fresh process of its own (a library that crashes
   is reported, not fatal): analysis (symbolic, fill-reducing ordering) once, then
   ``--repeats`` numeric factorisations with new values (H scaled by 1 + 10⁻³k) — the
   median is reported — one back-substitution, and the relative residual ‖Ax − b‖/‖b‖.
   "reuse" says whether the library can refactorise on a stored analysis. Libraries:
   spdslam's own solvers ("cholmod": scikit-sparse, "cvxopt": the CHOLMOD in cvxopt's
   wheels, "scipy": SuperLU), CHOLMOD's simplicial mode, and, when installed, qdldl,
   cholespy and pypardiso (MKL).
2. LM: ``LevenbergMarquardt`` with each of spdslam's sparse solvers on the same problem in
   this process: a compile run first, then ``--rounds`` rounds in which each solver runs
   ``--iterations`` trials with every tolerance 0 (the fastest round of each is kept); per
   trial: the whole iteration and its factorisation, and the ratio to "cholmod".

    python3 benchmarks/linear_solvers.py [--out benchmarks/results/linear_solvers.json]
    python3 benchmarks/linear_solvers.py --problems sphere2500 --iterations 3 --repeats 3
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))  # run from a checkout
sys.path.insert(0, str(HERE))

LAMBDA = 1e-4
LIBRARIES = ("cholmod", "cholmod-simplicial", "cvxopt", "scipy", "qdldl", "cholespy", "pardiso")
#: the libraries spdslam's LM can use (``linear_solver=``)
LM_SOLVERS = ("cholmod", "cvxopt", "scipy")
PROBLEMS = ("sphere2500", "room10k")


def make_problem(name: str):
    """(graph, values) of the named problem."""
    if name == "sphere2500":
        import gtsam

        from spdslam.io import pose_graph_factors, read_g2o

        pg = read_g2o(gtsam.findExampleDataFile("sphere2500.txt"))
        return pose_graph_factors(pg, prior_sigma=1e-6)
    if name == "room10k":
        import scaling

        from spdslam.mapping import METHODS, build_graph

        seq, tracks, lms, values, _ = scaling.scene(10000, 100, 0)
        return build_graph(seq, tracks, lms, METHODS["multi-spd"]), values
    raise ValueError(f"unknown problem {name!r}; expected one of {', '.join(PROBLEMS)}")


def damped_system(problem) -> dict:
    """The lower triangle of H + λ·clip(diag H) at the initial values, and its CSC pattern."""
    sp = problem.sparse_pattern()
    h, *_ = problem.linearize(problem.vars)
    h = np.array(h, dtype=np.float64)
    d = sp["diag"]
    h[d] += LAMBDA * np.clip(h[d], 1e-6, None)
    return dict(data=h, indices=np.asarray(sp["indices"]), indptr=np.asarray(sp["indptr"]),
                diag=np.asarray(d), n=int(problem.n))


# ------------------------------------------------------------------ one library, one process


def _adapter(lib: str, z: dict):
    """(analyse(), factor(data) -> f, solve(f, b) -> x, reuse) for library ``lib``."""
    import scipy.sparse as sps

    n = z["n"]
    pattern = dict(indices=z["indices"], indptr=z["indptr"], diag=z["diag"],
                   nnz=z["data"].size)

    def lower(data):
        return sps.csc_matrix((data, z["indices"], z["indptr"]), shape=(n, n))

    def upper(data):  # the same values as the upper triangle (CSR of Lᵀ = CSC of L)
        return sps.csr_matrix((data, z["indices"], z["indptr"]), shape=(n, n))

    if lib in ("cholmod", "cholmod-simplicial", "cvxopt", "scipy"):
        from spdslam.solver._linear import make_linear_solver

        kind = "cholmod" if lib.startswith("cholmod") else lib
        mode = "simplicial" if lib == "cholmod-simplicial" else "supernodal"
        st = {}

        def analyse():
            st["s"] = make_linear_solver(kind, pattern, n, cholmod_mode=mode)

        def factor(data):
            return st["s"]._factorize(data)

        return analyse, factor, lambda f, b: st["s"]._backsolve(f, b), lib != "scipy"
    if lib == "qdldl":
        import qdldl

        st = {}

        def analyse():  # qdldl's constructor analyses and factorises
            st["s"] = qdldl.Solver(upper(z["data"]).tocsc())

        def factor(data):
            st["s"].update(upper(data).tocsc())
            return st["s"]

        return analyse, factor, lambda f, b: f.solve(b), True
    if lib == "cholespy":
        import cholespy

        def factor(data):  # no separate analysis: every matrix is analysed anew
            A = lower(data)
            A = (A + A.T - sps.diags(A.diagonal())).tocsc()
            return cholespy.CholeskySolverD(n, A.indptr.astype(np.int32),
                                            A.indices.astype(np.int32), A.data,
                                            cholespy.MatrixType.CSC)

        def solve(f, b):
            x = np.zeros_like(b)
            f.solve(b, x)
            return x

        return (lambda: None), factor, solve, False
    if lib == "pardiso":
        import pypardiso

        s = pypardiso.PyPardisoSolver(mtype=2)  # real symmetric positive definite

        st = {}

        def call(phase, data, b):
            s.set_phase(phase)
            return s._call_pardiso(upper(data), b)

        def analyse():
            call(11, z["data"], np.zeros(n))

        def factor(data):
            st["data"] = data
            call(22, data, np.zeros(n))
            return s

        def solve(f, b):
            return call(33, st["data"], b).ravel()

        return analyse, factor, solve, True
    raise ValueError(f"unknown library {lib!r}")


def library_worker(lib: str, path: str, repeats: int) -> dict:
    import scipy.sparse as sps

    with np.load(path) as f:
        z = {k: f[k] for k in f.files}
    z["n"] = int(z["n"])
    try:
        analyse, factor, solve, reuse = _adapter(lib, z)
    except ImportError as e:
        return dict(skipped=f"not installed ({e.name or e})")
    t0 = time.perf_counter()
    analyse()
    t_an = time.perf_counter() - t0
    times = []
    for k in range(repeats):
        data = z["data"] * (1.0 + 1e-3 * k)
        t0 = time.perf_counter()
        f = factor(data)
        times.append(time.perf_counter() - t0)
    if f is None:
        return dict(skipped="factorisation failed")
    b = np.random.default_rng(0).standard_normal(z["n"])
    t0 = time.perf_counter()
    x = solve(f, b)
    t_solve = time.perf_counter() - t0
    L = sps.csc_matrix((data, z["indices"], z["indptr"]), shape=(z["n"],) * 2)
    A = L + L.T - sps.diags(L.diagonal())
    return dict(analyse_ms=1e3 * t_an, factorise_ms=1e3 * statistics.median(times),
                factorise_all_ms=[1e3 * t for t in times], solve_ms=1e3 * t_solve,
                residual=float(np.linalg.norm(A @ x - b) / np.linalg.norm(b)), reuse=reuse)


def run_library(lib: str, path: str, repeats: int, timeout: int) -> dict:
    cmd = [sys.executable, __file__, "--library-worker", lib, path, str(repeats)]
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return dict(skipped=f"over {timeout} s")
    if p.returncode != 0:
        tail = (p.stderr.strip().splitlines() or [""])[-1]
        return dict(skipped=f"crashed (exit {p.returncode}) {tail}".strip())
    return json.loads(p.stdout.strip().splitlines()[-1])


# ------------------------------------------------------------------ LM per iteration


def lm_times(graph, values, solvers, iterations: int, rounds: int) -> dict:
    from spdslam.solver import HAVE_CHOLMOD, HAVE_CVXOPT, LevenbergMarquardt

    have = {"cholmod": HAVE_CHOLMOD, "cvxopt": HAVE_CVXOPT, "scipy": True}
    opts = dict(relative_tolerance=0.0, absolute_tolerance=0.0, gradient_tolerance=0.0,
                step_tolerance=0.0)
    first = next((s for s in solvers if have[s]), "scipy")
    LevenbergMarquardt(max_iterations=1, linear_solver=first, **opts).optimize(graph, values)
    out = {}
    for _ in range(rounds):  # the solvers in turn, each round; the fastest round is kept
        for s in solvers:
            if not have[s]:
                out[s] = dict(skipped="not installed")
                continue
            t0 = time.perf_counter()
            res = LevenbergMarquardt(max_iterations=iterations, linear_solver=s,
                                     **opts).optimize(graph, values)
            total = time.perf_counter() - t0
            it = max(res.iterations, 1)
            tm = res.timings
            r = dict(iterations=res.iterations, final_cost=float(res.final_cost),
                     iteration_ms=1e3 * (total - tm["setup"]) / it,
                     factorise_ms=1e3 * tm["factorize"] / it, setup_ms=1e3 * tm["setup"],
                     linear_solver=res.linear_solver)
            if s not in out or r["iteration_ms"] < out[s]["iteration_ms"]:
                out[s] = r
    ref = out.get("cholmod", {}).get("iteration_ms")
    for s, r in out.items():
        if ref and "iteration_ms" in r:
            r["iteration_vs_cholmod"] = r["iteration_ms"] / ref
            r["factorise_vs_cholmod"] = r["factorise_ms"] / out["cholmod"]["factorise_ms"]
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--problems", default=",".join(PROBLEMS))
    ap.add_argument("--libraries", default=",".join(LIBRARIES))
    ap.add_argument("--lm-solvers", default=",".join(LM_SOLVERS))
    ap.add_argument("--repeats", type=int, default=5, help="numeric factorisations per library")
    ap.add_argument("--iterations", type=int, default=5, help="LM trials per solver")
    ap.add_argument("--rounds", type=int, default=2, help="LM runs per solver (fastest kept)")
    ap.add_argument("--timeout", type=int, default=600, help="seconds per library and problem")
    ap.add_argument("--out", default=str(HERE / "results" / "linear_solvers.json"))
    ap.add_argument("--library-worker", nargs=3, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.library_worker:
        lib, path, repeats = args.library_worker
        print(json.dumps(library_worker(lib, path, int(repeats))))
        return 0

    import spdslam  # noqa: F401 - float64
    from spdslam.solver import Problem

    libs = [x for x in args.libraries.split(",") if x]
    results = {}
    for name in [x for x in args.problems.split(",") if x]:
        print(f"== {name}", flush=True)
        graph, values = make_problem(name)
        problem = Problem(graph, values)
        z = damped_system(problem)
        rec = dict(n=z["n"], nnz_H_lower=int(z["data"].size), factorisation={})
        print(f"n = {z['n']}, nnz(H lower) = {z['data'].size}", flush=True)
        with tempfile.TemporaryDirectory() as tmp:
            path = str(Path(tmp) / "H.npz")
            np.savez(path, **z)
            print(f"{'library':20} {'analyse':>9} {'factorise':>10} {'solve':>8} "
                  f"{'residual':>9} reuse   (ms; factorise: median of {args.repeats})")
            for lib in libs:
                r = run_library(lib, path, args.repeats, args.timeout)
                rec["factorisation"][lib] = r
                if "skipped" in r:
                    print(f"{lib:20} {r['skipped']}", flush=True)
                else:
                    print(f"{lib:20} {r['analyse_ms']:9.1f} {r['factorise_ms']:10.1f} "
                          f"{r['solve_ms']:8.1f} {r['residual']:9.1e} "
                          f"{'yes' if r['reuse'] else 'no'}", flush=True)
        del problem
        solvers = [x for x in args.lm_solvers.split(",") if x]
        if not solvers:
            results[name] = rec
            continue
        rec["lm"] = lm_times(graph, values, solvers, args.iterations, args.rounds)
        print(f"LM, {args.iterations} trials, best of {args.rounds}: {'solver':8} {'iteration':>10} {'factorise':>10} "
              f"{'x cholmod':>9}")
        for s, r in rec["lm"].items():
            if "skipped" in r:
                print(f"{'':20} {s:8} {r['skipped']}")
            else:
                ratio = r.get("iteration_vs_cholmod")
                print(f"{'':20} {s:8} {r['iteration_ms']:10.1f} {r['factorise_ms']:10.1f} "
                      f"{ratio if ratio is not None else float('nan'):9.2f}", flush=True)
        results[name] = rec
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=1) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
