"""spdslam vs gtsam Levenberg-Marquardt on gtsam's sphere2500 pose graph, in one process.

Same problem for both: gtsam's reading of ``sphere2500.txt`` (2500 poses, 4949 relative-pose
edges), a prior on pose 0 at the identity with σ = 1e-6, initial values from the odometry
chain, LM to a relative cost decrease of 1e-10. Costs are reported in gtsam's convention,
F = Σ ½‖W r‖², and both solutions are evaluated by gtsam's ``graph.error``.

Timing. gtsam: ``LevenbergMarquardtOptimizer(...).optimize()``; its "iteration" is one
linearisation followed by as many λ trials as it needs. spdslam: a warm-up run first compiles
the JAX kernels (reported separately as compile time); the timed run then counts setup (layout,
CHOLMOD symbolic analysis) apart from the iterations. spdslam's iteration is one trial (one
damped solve). gtsam's λ trials are counted exactly in a second, untimed run that prints
them. Times are compared three ways: per iteration in gtsam's unit (one linearisation with
its trials; spdslam: per accepted step), per λ trial (one factorisation or elimination), and
total time of the iterations. The breakdown splits spdslam's time into the jitted Jacobians,
assembly of H and g, damping, CHOLMOD factorisation, back-substitution, and the trial step
(retract + regularize + cost).

    python3 benchmarks/sphere2500.py [--out benchmarks/results/sphere2500.json] [--max-iterations 1000]
    python3 benchmarks/sphere2500.py --gtsam-schedule     # spdslam LM with gtsam's default λ rule
    python3 benchmarks/sphere2500.py --cholmod-mode simplicial --cholmod-ordering metis
    python3 benchmarks/sphere2500.py --cholmod-openmp --blas-threads 0   # CHOLMOD's own threads
    python3 benchmarks/sphere2500.py --quick              # 5 iterations each (smoke run)
    python3 benchmarks/sphere2500.py --optimizer dogleg   # spdslam's dogleg; gtsam's LM and dogleg

spdslam's LM options: ``--lambda-initial``, ``--lambda-schedule nielsen|fixed``,
``--lambda-factor``, ``--damping``; ``--gtsam-schedule`` sets gtsam's defaults
(λ₀ = 1e-5, ÷/×10, D = I). ``--cholmod-mode``, ``--cholmod-ordering``: CHOLMOD's
factorisation and fill-reducing ordering.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # run from a checkout

import spdslam  # noqa: E402
from spdslam.io import pose_graph_factors, read_g2o  # noqa: E402
import dataclasses  # noqa: E402

from spdslam.solver import Dogleg, LevenbergMarquardt, OptimizerParams, default_sparse_solver  # noqa: E402

#: The options every optimiser takes (the λ options are LM's).
_SHARED = {f.name for f in dataclasses.fields(OptimizerParams)}

PRIOR_SIGMA = 1e-6
RELATIVE_TOLERANCE = 1e-10


def cholmod_blas() -> str:
    """The BLAS library the process has loaded (CHOLMOD's supernodal kernels use it)."""
    try:
        maps = Path("/proc/self/maps").read_text().splitlines()
    except OSError:
        return "unknown"
    libs = {os.path.realpath(line.split()[-1]) for line in maps
            if line.split()[-1].startswith("/")}
    names = ("libblas", "libopenblas", "libmkl", "libblis", "libsatlas", "libtatlas")
    libs = sorted(x for x in libs if os.path.basename(x).startswith(names))
    out = ", ".join(libs) or "none found"
    if any("/blas/libblas" in x for x in libs):
        out += " (reference BLAS: slow supernodal CHOLMOD; see benchmarks/README.md)"
    return out


def gtsam_version(gtsam) -> str:
    v = getattr(gtsam, "__version__", None)
    if v is None:
        try:
            from importlib.metadata import version
            v = version("gtsam")
        except Exception:  # noqa: BLE001 - metadata missing (a source build)
            v = "unknown"
    return v


def count_gtsam_trials(gtsam, graph, init, params) -> int:
    """gtsam's λ trials (eliminations) in its LM run: the lines "trying lambda" it prints at
    verbosityLM TRYLAMBDA (C++ stdout, captured at the file-descriptor level)."""
    import tempfile

    params.setVerbosityLM("TRYLAMBDA")
    sys.stdout.flush()
    saved = os.dup(1)
    with tempfile.TemporaryFile(mode="w+b") as tmp:
        os.dup2(tmp.fileno(), 1)
        try:
            gtsam.LevenbergMarquardtOptimizer(graph, init, params).optimize()
        finally:
            os.dup2(saved, 1)
            os.close(saved)
            params.setVerbosityLM("SILENT")
        tmp.seek(0)
        return tmp.read().decode(errors="replace").count("trying lambda")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "sphere2500.json"))
    ap.add_argument("--max-iterations", type=int, default=1000)
    ap.add_argument("--linear-solver", default=default_sparse_solver(),
                    help="cholmod, cvxopt or scipy (default: the one \"auto\" picks)")
    ap.add_argument("--lambda-initial", type=float, default=None)
    ap.add_argument("--lambda-schedule", choices=["nielsen", "fixed"], default=None)
    ap.add_argument("--lambda-factor", type=float, default=None)
    ap.add_argument("--optimizer", choices=["lm", "dogleg"], default="lm",
                    help="spdslam's optimiser: Levenberg-Marquardt (default) or Powell's dogleg")
    ap.add_argument("--damping", choices=["isotropic", "marquardt", "identity"], default=None,
                    help="LM's damping matrix D (default: the solver's, isotropic)")
    ap.add_argument("--gtsam-schedule", action="store_true",
                    help="gtsam's default LM rule: lambda 1e-5, /10 and x10, D = I")
    ap.add_argument("--cholmod-mode", default="supernodal")
    ap.add_argument("--cholmod-ordering", default="default")
    ap.add_argument("--cholmod-openmp", action="store_true",
                    help="let CHOLMOD fork its OpenMP team per supernode (default: one thread)")
    ap.add_argument("--blas-threads", type=int, default=1,
                    help="OpenBLAS threads in CHOLMOD's factorisation (0: leave unchanged)")
    ap.add_argument("--quick", action="store_true", help="5 iterations each (smoke run)")
    args = ap.parse_args()
    if args.quick:
        args.max_iterations = 5
    lm_opts = dict(linear_solver=args.linear_solver, cholmod_mode=args.cholmod_mode,
                   cholmod_ordering=args.cholmod_ordering, cholmod_openmp=args.cholmod_openmp,
                   cholmod_blas_threads=args.blas_threads or None)
    if args.gtsam_schedule:
        lm_opts.update(lambda_initial=1e-5, lambda_schedule="fixed", lambda_factor=10.0,
                       damping="identity")
    for k in ("lambda_initial", "lambda_schedule", "lambda_factor"):
        if getattr(args, k) is not None:
            lm_opts[k] = getattr(args, k)
    if args.damping is not None:
        lm_opts["damping"] = args.damping

    import gtsam

    path = gtsam.findExampleDataFile("sphere2500.txt")
    t0 = time.perf_counter()
    pg = read_g2o(path)
    graph, values = pose_graph_factors(pg, prior_sigma=PRIOR_SIGMA)
    t_read = time.perf_counter() - t0

    g, _ = gtsam.readG2o(path, True)
    prior_noise = gtsam.noiseModel.Isotropic.Sigma(6, PRIOR_SIGMA)
    g.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(), prior_noise))

    def to_gtsam(vals):
        out = gtsam.Values()
        for k, T in vals.items():
            out.insert(k, gtsam.Pose3(np.asarray(T.as_matrix())))
        return out

    init = to_gtsam(values)
    initial_cost = g.error(init)

    # ---- gtsam ---------------------------------------------------------------------------
    def stopping(params):
        """The stopping rule both optimisers share: relative decrease, iteration cap."""
        params.setRelativeErrorTol(RELATIVE_TOLERANCE)
        params.setAbsoluteErrorTol(0.0)
        params.setMaxIterations(args.max_iterations)
        return params

    params = stopping(gtsam.LevenbergMarquardtParams())
    t0 = time.perf_counter()
    opt = gtsam.LevenbergMarquardtOptimizer(g, init, params)
    ref = opt.optimize()
    t_gtsam = time.perf_counter() - t0
    it_gtsam = int(opt.iterations())
    gt = dict(
        iterations=it_gtsam,
        final_cost=g.error(ref),
        total_s=t_gtsam,
        per_iteration_ms=1e3 * t_gtsam / max(it_gtsam, 1),
    )
    # one linearisation and one elimination at the initial values, for reference
    t0 = time.perf_counter()
    gfg = g.linearize(init)
    gt["linearize_ms"] = 1e3 * (time.perf_counter() - t0)
    t0 = time.perf_counter()
    gfg.optimize()
    gt["eliminate_and_solve_ms"] = 1e3 * (time.perf_counter() - t0)
    # gtsam's iteration = one linearisation + its λ trials (each an elimination); count the
    # trials exactly in a second, untimed run that prints each one
    gt["lambda_trials"] = count_gtsam_trials(gtsam, g, init, params)
    if gt["lambda_trials"] < it_gtsam:  # this gtsam prints no "trying lambda" lines
        print(f"warning: counted {gt['lambda_trials']} gtsam λ trials in {it_gtsam} "
              "iterations; taking one trial per iteration (gtsam's per-trial time is then an "
              "upper bound)")
        gt["lambda_trials"] = it_gtsam
    gt["per_trial_ms"] = 1e3 * t_gtsam / max(gt["lambda_trials"], 1)
    gt_dogleg = None
    if args.optimizer == "dogleg":  # like for like: gtsam's Powell's dogleg on the same graph
        t0 = time.perf_counter()
        dopt = gtsam.DoglegOptimizer(g, init, stopping(gtsam.DoglegParams()))
        dref = dopt.optimize()
        gt_dogleg = dict(iterations=int(dopt.iterations()), final_cost=g.error(dref),
                         total_s=time.perf_counter() - t0)

    # ---- spdslam ---------------------------------------------------------------------------
    if args.optimizer == "dogleg":
        Opt = Dogleg
        lm_opts = {k: v for k, v in lm_opts.items() if k in _SHARED}
    else:
        Opt = LevenbergMarquardt
    lm = Opt(relative_tolerance=RELATIVE_TOLERANCE, max_iterations=args.max_iterations, **lm_opts)
    t0 = time.perf_counter()
    Opt(max_iterations=2, **lm_opts).optimize(graph, values)
    t_warm = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = lm.optimize(graph, values)
    t_total = time.perf_counter() - t0
    tm = res.timings
    t_iter = t_total - tm["setup"]
    n_lin = res.linearizations
    sp = dict(
        iterations=res.iterations,
        linearizations=n_lin,
        accepted=int(sum(r.accepted for r in res.history)),
        reason=res.reason,
        final_cost=res.final_cost,
        final_cost_gtsam=g.error(to_gtsam(res.values)),
        total_s=t_total,
        warmup_s=t_warm,
        setup_s=tm["setup"],
        iterations_s=t_iter,
        per_iteration_ms=1e3 * t_iter / max(res.iterations, 1),
        per_linearization_ms=1e3 * t_iter / max(n_lin - 1, 1),
        linear_solver=res.linear_solver,
        options=lm_opts,
        breakdown_ms_per_iteration={
            k: 1e3 * tm[k] / max(res.iterations, 1)
            for k in ("jacobians", "assemble", "damp", "factorize", "backsolve", "step")
        },
    )
    sp["breakdown_ms_per_iteration"]["other"] = sp["per_iteration_ms"] - sum(
        sp["breakdown_ms_per_iteration"].values())
    # compile time: the warm-up run minus what the same work costs once compiled
    sp["compile_s_estimate"] = max(
        0.0, t_warm - tm["setup"] - 2 * sp["per_iteration_ms"] / 1e3)

    # ---- report --------------------------------------------------------------------------
    # per trial: one damped solve (spdslam's iteration; a gtsam λ trial); per iteration in
    # gtsam's unit: one linearisation and its trials (spdslam: per accepted step)
    ratio_trial = sp["per_iteration_ms"] / gt["per_trial_ms"]
    ratio_lin = sp["per_linearization_ms"] / gt["per_iteration_ms"]
    ratio_total = sp["iterations_s"] / gt["total_s"]
    rows = [
        ("iterations (linearisations)", f"{gt['iterations']}", f"{n_lin - 1} accepted steps"),
        ("λ trials (factorisations)", f"{gt['lambda_trials']}", f"{sp['iterations']}"),
        ("final cost (gtsam error)", f"{gt['final_cost']:.8f}", f"{sp['final_cost_gtsam']:.8f}"),
        ("per iteration [ms]", f"{gt['per_iteration_ms']:.1f}",
         f"{sp['per_linearization_ms']:.1f} per accepted step"),
        ("per λ trial [ms]", f"{gt['per_trial_ms']:.1f}", f"{sp['per_iteration_ms']:.1f}"),
        ("total [s]", f"{gt['total_s']:.2f}",
         f"{sp['total_s']:.2f} (setup {sp['setup_s']:.2f}, iterations {sp['iterations_s']:.2f})"),
        ("JAX compile [s]", "-",
         f"{sp['compile_s_estimate']:.2f} (warm-up run of 2 iterations: {sp['warmup_s']:.2f})"),
    ]
    w = max(len(r[0]) for r in rows)
    print(f"sphere2500: {len(pg.poses)} poses, {len(pg.edges)} edges; "
          f"initial cost {initial_cost:.6g}")
    print(f"{'':{w}}  {'gtsam':>14}  spdslam ({sp['linear_solver']})")
    for name, a, b in rows:
        print(f"{name:{w}}  {a:>14}  {b}")
    print(f"ratio spdslam/gtsam: {ratio_lin:.2f}x per iteration (linearisation), "
          f"{ratio_trial:.2f}x per λ trial, {ratio_total:.2f}x total (iterations)")
    print(f"gtsam reference: linearize {gt['linearize_ms']:.1f} ms, "
          f"eliminate+solve {gt['eliminate_and_solve_ms']:.1f} ms")
    print("spdslam breakdown per iteration [ms]: " + ", ".join(
        f"{k} {v:.1f}" for k, v in sp["breakdown_ms_per_iteration"].items()))
    blas = cholmod_blas()
    print(f"BLAS loaded (used by CHOLMOD): {blas}")
    rel = abs(sp["final_cost_gtsam"] - gt["final_cost"]) / gt["final_cost"]
    print(f"relative difference of final costs: {rel:.2e}")
    if gt_dogleg is not None:
        gt_dogleg["ratio_total"] = sp["iterations_s"] / gt_dogleg["total_s"]
        gt_dogleg["relative_cost_difference"] = (
            abs(sp["final_cost_gtsam"] - gt_dogleg["final_cost"]) / gt_dogleg["final_cost"])
        print(f"gtsam's dogleg: {gt_dogleg['iterations']} iterations, final cost "
              f"{gt_dogleg['final_cost']:.8f}, {gt_dogleg['total_s']:.2f} s; spdslam's dogleg "
              f"{gt_dogleg['ratio_total']:.2f}x of it (final costs differ by "
              f"{gt_dogleg['relative_cost_difference']:.2e})")

    out = dict(
        problem=dict(file=path, poses=len(pg.poses), edges=len(pg.edges), prior_sigma=PRIOR_SIGMA,
                     relative_tolerance=RELATIVE_TOLERANCE, initial_cost=initial_cost,
                     read_and_build_s=t_read),
        gtsam=gt,
        gtsam_dogleg=gt_dogleg,
        spdslam=sp,
        ratio_per_iteration=ratio_lin,
        ratio_per_trial=ratio_trial,
        ratio_total=ratio_total,
        relative_cost_difference=rel,
        environment=dict(python=sys.version.split()[0], platform=platform.platform(),
                         cpus=os.cpu_count(), blas=blas, spdslam=spdslam.__version__,
                         gtsam=gtsam_version(gtsam)),
    )
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=2))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
