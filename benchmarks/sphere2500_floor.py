"""What an LM run on sphere2500 cannot go below: the parts of a λ trial, each timed alone.

Issue 28 asked for sphere2500 at half of gtsam's total time by fixing the largest costs of an
LM iteration. This measures the two largest, on the same graph as ``sphere2500.py``:

1. the CHOLMOD factorisation of H + λD (supernodal; each fill-reducing ordering, one and two
   BLAS threads), with the back-substitution;
2. the between-factor Jacobians (the sparse kernel of 4949 ``BetweenFactor``s, padded to
   5120) three ways: forward mode through each factor's retraction (the solver's way), reverse
   mode, and pushforwards of the retraction pushed through the residual with ``jax.jvp``
   (the batched solver's way), at the solver's chunk size and as one vmap.

With ``--results`` (``sphere2500.py``'s JSON, default ``results/sphere2500.json``) it adds the
floor: spdslam's λ trials × (best factorisation + back-substitution), against gtsam's total.

    python3 benchmarks/sphere2500_floor.py [--repeats 30] [--results benchmarks/results/sphere2500.json] [--quick]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # run from a checkout

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

import spdslam  # noqa: E402,F401  (float64)
from spdslam.io import pose_graph_factors, read_g2o  # noqa: E402
from spdslam.solver import Problem  # noqa: E402
from spdslam.solver._problem import _host  # noqa: E402  (the gather the solver does)
from spdslam.solver._linear import make_linear_solver  # noqa: E402
from spdslam.solver import _problem  # noqa: E402


def median_ms(f, repeats: int) -> float:
    jax.block_until_ready(f())
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(f())
        ts.append(time.perf_counter() - t)
    return 1e3 * float(np.median(ts))


def factorisations(problem: Problem, repeats: int) -> dict:
    sp = problem.sparse_pattern()
    H, g, *_ = problem.linearize(problem.vars)
    H = H.copy()
    H[sp["diag"]] += 1e-4 * np.maximum(H[sp["diag"]], 1e-6)
    out = {}
    for ordering in ("default", "amd", "metis", "nesdis"):
        for threads in (1, 2):
            try:
                s = make_linear_solver("cholmod", sp, problem.n, cholmod_ordering=ordering,
                                       cholmod_blas_threads=threads)
            except Exception as e:  # noqa: BLE001 - an ordering this CHOLMOD lacks
                out[f"{ordering}, {threads} BLAS"] = f"unavailable: {e}"
                continue
            out[f"{ordering}, {threads} BLAS"] = median_ms(lambda s=s: s.solve(H, -g), repeats)
    return out


def jacobian_modes(problem: Problem, repeats: int) -> dict:
    """The between group's sparse terms (JᵀJ upper triangle, Jᵀr) three ways."""
    K = problem.kernels
    k = next(i for i, gk in enumerate(K.groups) if gk.sparse.__name__.startswith("pose_between"))
    vh = _host(problem.vars)
    xs, mask, data = K._inputs(k, vh, problem.gidx[k], problem.gdata[k])
    (T1, T2), (leaves, W) = xs, data
    Z = jax.tree.unflatten(K.gspecs[k].args_treedef, leaves)[0]
    residual = K.gspecs[k].residual
    iu, ju = np.triu_indices(12)

    def terms(J, r):
        return (J.T @ J)[iu, ju], J.T @ r

    def fwd_or_rev(jac):
        def one(t1, t2, z, w):
            def f(d):
                r = w @ residual(t1 @ type(t1).exp(d[:6]), t2 @ type(t2).exp(d[6:]), z)
                return r, r
            J, r = jac(f, has_aux=True)(jnp.zeros(12))
            return terms(J, r)
        return one

    def pushforward(t1, t2, z, w):
        def pf(t):
            f = lambda d: (t @ type(t).exp(d)).parameters()  # noqa: E731
            return jax.vmap(lambda e: jax.jvp(f, (jnp.zeros(6),), (e,))[1])(jnp.eye(6))
        g = lambda a, b: w @ residual(type(t1)(a), type(t2)(b), z)  # noqa: E731
        a, b = t1.parameters(), t2.parameters()
        za, zb = jnp.zeros_like(a), jnp.zeros_like(b)
        J1 = jax.vmap(lambda v: jax.jvp(g, (a, b), (v, zb))[1])(pf(t1))
        J2 = jax.vmap(lambda v: jax.jvp(g, (a, b), (za, v))[1])(pf(t2))
        return terms(jnp.concatenate([J1.T, J2.T], axis=1), g(a, b))

    chunk = _problem._chunk(int(mask.shape[0]), 12)
    args = (T1, T2, Z, W)
    out = {"factors (padded)": int(mask.shape[0]), "solver's chunk": chunk}
    for name, one in (("forward (solver)", fwd_or_rev(jax.jacfwd)),
                      ("reverse", fwd_or_rev(jax.jacrev)), ("pushforward + jvp", pushforward)):
        for label, f in ((f"chunk {chunk}", jax.jit(lambda *a, one=one: jax.lax.map(
                              lambda x: one(*x), a, batch_size=chunk))),
                         ("one vmap", jax.jit(jax.vmap(one)))):
            out[f"{name}, {label}"] = median_ms(lambda f=f: f(*args), max(5, repeats // 3))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--quick", action="store_true", help="3 repeats (smoke run)")
    ap.add_argument("--results", type=Path, default=Path(__file__).parent / "results" / "sphere2500.json")
    args = ap.parse_args()
    if args.quick:
        args.repeats = 3
    import gtsam

    graph, values = pose_graph_factors(read_g2o(gtsam.findExampleDataFile("sphere2500.txt")),
                                       prior_sigma=1e-6)
    problem = Problem(graph, values)
    print(f"sphere2500: n = {problem.n}, {len(graph)} factors")
    fac = factorisations(problem, args.repeats)
    print("CHOLMOD factorise + back-substitute (median ms):")
    for k, v in fac.items():
        print(f"  {k}: {v if isinstance(v, str) else f'{v:.1f}'}")
    jac = jacobian_modes(problem, args.repeats)
    print("between-factor sparse terms (median ms):")
    for k, v in jac.items():
        print(f"  {k}: {v if isinstance(v, int) else f'{v:.1f}'}")
    if args.results.is_file():
        r = json.loads(args.results.read_text())
        trials, total = r["spdslam"]["iterations"], r["gtsam"]["total_s"]
        best = min(v for v in fac.values() if not isinstance(v, str))
        floor = trials * best / 1e3
        print(f"floor: {trials} λ trials × {best:.1f} ms = {floor:.2f} s = {floor / total:.2f}× "
              f"gtsam's {total:.2f} s ({args.results.name}), before any Jacobian or step")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
