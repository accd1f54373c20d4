"""Levenberg-Marquardt and Gauss-Newton: the optimisers, and the sparse host loop.

``LevenbergMarquardt(params, **overrides)`` and ``GaussNewton(...)`` hold the parameters
and the rule (``_lm``: damping, gain ratio, λ schedules, every stopping rule). One problem:
``optimize(graph, values, fixed)`` runs the host loop below, with the normal equations in a
sparse CSC pattern factorised by CHOLMOD (or scipy, or densely for small problems). Many
problems of one structure: ``optimize_batched(graphs, values_list, fixed)`` or
``batched(graph, values, fixed)`` (a ``BatchedProblem`` for data given as arrays) run the
same rule on every lane of one jitted loop (``_batched``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Hashable, Iterable, Sequence, cast

import numpy as np

from ..geometry import manifold
from ._batched import BatchedProblem, solve_graphs
from ._linear import make_linear_solver, resolve_linear_solver
from ._lm import (
    CONVERGED_REASONS,
    MAX_ITERATIONS,
    REASONS,
    DoglegParams,
    GaussNewtonParams,
    IterationRecord,
    LevenbergMarquardtParams,
    OptimizerParams,
    StepRule,
    damping,
    decide,
    dogleg_step,
    hyper,
    initial_reason,
    model_decrease,
    predicted_decrease,
    resolve_params,
)
from ._marginals import covariance_blocks
from ._problem import Problem
from ._values import Values

__all__ = [
    "OptimizationResult",
    "Optimizer",
    "LevenbergMarquardt",
    "Dogleg",
    "GaussNewton",
]


@dataclass
class OptimizationResult:
    values: Values
    initial_cost: float
    final_cost: float
    iterations: int
    converged: bool
    reason: str
    history: list[IterationRecord] = field(default_factory=list)
    #: accumulated wall time (s): setup (layout, symbolic analysis), linearize (= jacobians,
    #: the jitted call, + assemble, the sums into H and g), damp (H + λD), solve (= factorize
    #: + backsolve), step (retract, regularize and the cost at the trial point).
    timings: dict[str, float] = field(default_factory=dict)
    linear_solver: str = ""
    linearizations: int = 0
    #: the problem, its variables, H and the linear solver at the final values (the last
    #: accepted linearisation): what ``marginal_covariances`` and ``cost_by_kind`` reuse
    _final: tuple | None = field(default=None, repr=False)

    def marginal_covariances(self, keys) -> dict:
        """{key: Σ} at the final values, as ``solver.marginal_covariances(graph, values,
        keys, fixed=…)`` gives them for this run's graph and fixed keys, from the last
        linearisation and the run's factorisation pattern (no new layout or Jacobians)."""
        problem, _, H, solver = cast(tuple, self._final)  # set by the optimisers
        return covariance_blocks(problem, H, True, solver, keys)

    def cost_by_kind(self) -> dict:
        """{factor kind: its part of the final cost}, in the graph's order of kinds
        (``Problem.cost_by_kind`` at the final values)."""
        problem, x, _, _ = cast(tuple, self._final)
        return problem.cost_by_kind(x)

    def __repr__(self) -> str:
        return (
            f"OptimizationResult(cost {self.initial_cost:.6g} -> {self.final_cost:.6g}, "
            f"{self.iterations} iterations, converged={self.converged}, reason={self.reason!r})"
        )


class Optimizer:
    """The parameters and rule of one method; see ``LevenbergMarquardt``, ``GaussNewton``."""

    Params: type = OptimizerParams

    def __init__(self, params: OptimizerParams | None = None, **overrides: Any):
        """``params`` (default ``self.Params()``), with keyword ``overrides`` of its fields;
        params of the other method keep their shared fields."""
        self.params = resolve_params(self.Params, params, overrides)
        self.rule = StepRule.of(self.params)

    def optimize(self, graph: Iterable, values: Any, fixed: Iterable[Hashable] = (),
                 rows: dict | None = None) -> OptimizationResult:
        """Minimise F over the free variables of ``values``; returns a new Values.
        ``rows`` {factor kind or variable class name: n}: pad those groups to at least n rows
        (``Problem``), so that a caller solving a changing graph meets fewer array shapes
        (each new one compiles)."""
        p = self.params
        t0 = time.perf_counter()
        if not isinstance(values, Values):
            values = Values(values)
        problem = Problem(graph, values, fixed, rows=rows)
        kind = resolve_linear_solver(p.linear_solver, problem.n, p.dense_threshold)
        solver = make_linear_solver(kind, problem.sparse_pattern(), problem.n, p.cholmod_mode,
                                    p.cholmod_ordering, p.cholmod_openmp, p.cholmod_blas_threads)
        timings = {"setup": time.perf_counter() - t0}
        res = _run(problem, solver, p, self.rule, timings)
        res.values = problem.to_values(res.values, values)
        return res

    def batched(self, graph: Iterable, values: Any, fixed: Iterable[Hashable] = (),
                optimize: bool | None = None):
        """A ``BatchedProblem``: ``graph``/``values``/``fixed`` one problem of a structure,
        solved with this optimiser for many data sets given as arrays
        (``BatchedProblem.solve``)."""
        return BatchedProblem(graph, values, fixed, optimizer=self, optimize=optimize)

    def optimize_batched(self, graphs: Any, values_list: Sequence[Any],
                         fixed: Iterable[Hashable] = (), batch_size: int | None = None,
                         optimize: bool | None = None):
        """Solve B independent problems of identical structure in one jitted loop (dense
        linear algebra); ``graphs`` one graph per problem or one shared graph,
        ``values_list`` the B initial Values. Returns a ``BatchedResult``."""
        return solve_graphs(self, graphs, values_list, fixed, batch_size, optimize)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.params!r})"


class LevenbergMarquardt(Optimizer):
    """Levenberg-Marquardt with damping in the metric and Nielsen's λ update (``_lm``)."""

    Params = LevenbergMarquardtParams


class Dogleg(Optimizer):
    """Powell's dogleg in a trust region of the tangent metric (``_lm``)."""

    Params = DoglegParams


class GaussNewton(Optimizer):
    """Gauss-Newton with a tiny fixed ridge; stops at the first non-decreasing step."""

    Params = GaussNewtonParams


def _sym_matvec(sp: dict, h: np.ndarray, x: np.ndarray) -> np.ndarray:
    """H x for H stored as its lower triangle in the CSC pattern ``sp`` (data ``h``)."""
    rows, cols = sp["rows"], sp["cols"]
    n = len(x)
    y = np.bincount(rows, weights=h * x[cols], minlength=n)
    y += np.bincount(cols, weights=h * x[rows], minlength=n)
    return y - h[sp["diag"]] * x


def _run(problem: Problem, solver, p, rule: StepRule, timings: dict) -> OptimizationResult:
    tick = time.perf_counter
    timings.update(linearize=0.0, jacobians=0.0, assemble=0.0, damp=0.0, solve=0.0, step=0.0)
    sp = problem.sparse_pattern()
    diag = sp["diag"]
    blocks = tuple((int(f.sum()), manifold.ops(ts.cls).blocks)
                   for ts, f in zip(problem.tspecs, problem.free))
    h = hyper(p)

    def linearize(x):
        t = tick()
        H, g, c, valid, finite = problem.linearize(x, timings)
        timings["linearize"] += tick() - t
        return H, g, c, valid, finite and np.isfinite(c)

    x = problem.vars
    H, g, cost, valid, finite = linearize(x)
    if not finite:
        problem.diagnose(x)
        raise ValueError("the cost or its gradient is not finite at the initial values")
    initial_cost = cost
    lam, nu = h["lambda_initial"], 2.0
    d_gn = Hg = None  # dogleg: the GN step at the current linearisation
    history: list[IterationRecord] = []
    nlin = 1
    reason = int(initial_reason(cost, np.max(np.abs(g), initial=0.0), h, np))
    it = 0
    while not reason:
        if it >= p.max_iterations:
            reason = MAX_ITERATIONS
            break
        it += 1
        t_it = tick()
        if rule.dogleg:
            if d_gn is None:  # once per linearisation: the GN step and the Cauchy data
                hd = H.copy()
                hd[diag] += h["ridge"] * damping(H[diag], rule, h, np, blocks)
                t = tick()
                timings["damp"] += t - t_it
                d_gn = solver.solve(hd, -g)
                Hg = _sym_matvec(sp, H, g)
            else:
                t = tick()
            delta = None if d_gn is None or not np.all(np.isfinite(d_gn)) else \
                dogleg_step(d_gn, g, Hg, lam, np)
        else:
            D = damping(H[diag], rule, h, np, blocks)
            hd = H.copy()
            hd[diag] += lam * D
            t = tick()
            timings["damp"] += t - t_it
            delta = solver.solve(hd, -g)
        timings["solve"] += tick() - t
        t = tick()
        solved = delta is not None
        trial_cost, step_norm, pred, lin = np.inf, np.nan, np.nan, None
        usable = False
        if delta is not None:  # solved
            step_norm = float(np.linalg.norm(delta))
            pred = float(model_decrease(delta, g, _sym_matvec(sp, H, delta), np) if rule.dogleg
                         else predicted_decrease(delta, D, g, lam, np))
            x_new, c_new, violated = problem.step(x, delta, valid)
            trial_cost = float(c_new)
            timings["step"] += tick() - t
            usable = bool(np.isfinite(trial_cost) and not bool(violated))
            if usable and trial_cost < cost:
                lin = linearize(x_new)  # the next H, g if accepted; its finiteness decides
                nlin += 1
                usable = bool(lin[4])
        gmax = np.max(np.abs(lin[1]), initial=0.0) if lin is not None else np.inf
        accepted, gain, lam_new, nu_new, code = decide(
            rule, h, cost, trial_cost, np.bool_(usable), np.bool_(solved), pred, step_norm,
            gmax, lam, nu, np)
        accepted = bool(accepted)
        rec = IterationRecord(it, trial_cost if accepted else cost, trial_cost, step_norm, lam,
                              float(gain), accepted, 0.0, radius=rule.dogleg)
        if accepted:
            x, cost = x_new, trial_cost
            H, g, _, valid, _ = cast(tuple, lin)  # accepted: the trial was linearised
            d_gn = None
        lam, nu, reason = float(lam_new), float(nu_new), int(code)
        rec.time = tick() - t_it
        history.append(rec)
        if p.verbose:
            print(rec.line())
        if p.callback is not None and p.callback(rec) and not reason:
            reason = REASONS.index("callback")
    timings.update(solver.timings)
    return OptimizationResult(
        values=x,  # type: ignore[arg-type]  # the variables: optimize() makes them Values
        initial_cost=initial_cost,
        final_cost=cost,
        iterations=it,
        converged=REASONS[reason] in CONVERGED_REASONS,
        reason=REASONS[reason],
        history=history,
        timings=timings,
        linear_solver=solver.name,
        linearizations=nlin,
        _final=(problem, x, H, solver),
    )
