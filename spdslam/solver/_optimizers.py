"""Levenberg-Marquardt and Gauss-Newton on the product manifold of the variables.

Cost F(x) = Σᵢ ½ ρᵢ(‖Wᵢ rᵢ(x)‖²). At x the solver linearises (IRLS for robust kernels),
H = JᵀJ, g = Jᵀr, and solves the damped normal equations

    (H + λ D) δ = −g,    D = diag(clip(diag H, min_diagonal, max_diagonal))

(Marquardt's scaling, as in Ceres: the damping is invariant to the units of each coordinate,
and the clip keeps it positive on coordinates that no residual sees, e.g. the scale of a
Full quadric). The candidate is x' = regularize(x ⊞ δ).

LM (Nielsen's rule, ``lambda_schedule="nielsen"``, the default). The gain ratio
ρ = (F(x) − F(x')) / L, with the model decrease L = −gᵀδ − ½δᵀHδ = ½ δᵀ(λDδ − g) > 0. The step
is accepted iff F(x') < F(x) (ρ > 0), F(x') is finite, and no factor that is valid at x is
invalid at x'. On acceptance λ ← max(λ_min, λ·max(1/3, 1 − (2ρ − 1)³)), ν ← 2; on rejection
λ ← λν, ν ← 2ν. ``lambda_schedule="fixed"`` is gtsam's default rule instead:
λ ← max(λ_min, λ/f) on acceptance, λ ← λf on rejection (f = ``lambda_factor``, 10).
``diagonal_damping=False`` damps with D = I (gtsam's default) instead of Marquardt's diag H.

GN: λ is a fixed tiny ridge (``ridge``, relative to D) so that Cholesky survives singular
directions. Every step that lowers the cost is taken; the first that does not (cost increase,
invalid factor, non-finite cost) ends the run, keeping the values before it: reason
"relative" when the change was within the relative tolerance, else "cost_increase".

An iteration is one solve of the damped system and one trial step (accepted or not), as in
Ceres. Stopping reasons (``OptimizationResult.reason``):

- "absolute":       F(x) ≤ absolute_tolerance;
- "relative":       an accepted step lowered F by ≤ relative_tolerance·F, or a rejected step
                    changed F and had a model decrease both ≤ relative_tolerance·F;
- "gradient":       ‖g‖∞ ≤ gradient_tolerance;
- "step":           ‖δ‖₂ ≤ step_tolerance;
- "max_iterations": the iteration budget ran out;
- "lambda_max":     LM: λ grew beyond lambda_max without an acceptable step;
- "cost_increase":  GN: a step raised the cost (see above);
- "linear_solver":  GN: the ridged system could not be factorised;
- "callback":       the callback returned True.

``converged`` is True for the first four.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Hashable, Iterable

import numpy as np

from ._linear import (
    DENSE_THRESHOLD,
    check_cholmod_options,
    make_linear_solver,
    resolve_linear_solver,
)
from ._problem import Problem
from ._values import Values

__all__ = [
    "OptimizerParams",
    "LevenbergMarquardtParams",
    "GaussNewtonParams",
    "IterationRecord",
    "OptimizationResult",
    "LevenbergMarquardt",
    "GaussNewton",
    "CONVERGED_REASONS",
]

CONVERGED_REASONS = ("absolute", "relative", "gradient", "step")


@dataclass
class OptimizerParams:
    """Stopping rules and linear solver, shared by LM and GN.

    max_iterations:     budget of iterations (damped solves + trial steps).
    relative_tolerance: stop when an accepted step lowers F by ≤ this·F.
    absolute_tolerance: stop when F ≤ this.
    gradient_tolerance: stop when ‖Jᵀr‖∞ ≤ this.
    step_tolerance:     stop when ‖δ‖₂ ≤ this.
    min_diagonal, max_diagonal: clip of diag H in the damping matrix D.
    linear_solver:      "auto" (dense below ``dense_threshold`` tangent dims, else CHOLMOD if
                        scikit-sparse is importable, else scipy), "cholmod", "scipy", "dense".
    cholmod_mode, cholmod_ordering: CHOLMOD's factorisation ("supernodal", "simplicial",
                        "auto") and fill-reducing ordering ("default", "amd", "metis", …);
                        see ``_linear``.
    cholmod_openmp, cholmod_blas_threads: threads of CHOLMOD's OpenMP regions (False: one)
                        and of its OpenBLAS (None: unchanged) during factorisations and
                        solves; see ``_linear.cholmod_threads``.
    verbose:            print one line per iteration.
    callback:           ``callback(record)`` after each iteration; returning True stops.
    """

    max_iterations: int = 100
    relative_tolerance: float = 1e-6
    absolute_tolerance: float = 1e-12
    gradient_tolerance: float = 1e-10
    step_tolerance: float = 1e-10
    min_diagonal: float = 1e-6
    max_diagonal: float = 1e32
    linear_solver: str = "auto"
    dense_threshold: int = DENSE_THRESHOLD
    cholmod_mode: str = "supernodal"
    cholmod_ordering: str = "default"
    cholmod_openmp: bool = False
    cholmod_blas_threads: int | None = 1
    verbose: bool = False
    callback: Callable[["IterationRecord"], Any] | None = None


@dataclass
class LevenbergMarquardtParams(OptimizerParams):
    """LM damping: λ starts at ``lambda_initial``, stays ≥ ``lambda_min``, and the run stops
    (reason "lambda_max") when rejections push it above ``lambda_max``. ``lambda_schedule``:
    "nielsen" (gain-ratio rule) or "fixed" (÷/× ``lambda_factor``, gtsam's default);
    ``diagonal_damping``: D = clip(diag H) (Marquardt) or D = I (False, gtsam's default)."""

    lambda_initial: float = 1e-4
    lambda_min: float = 1e-10
    lambda_max: float = 1e10
    lambda_schedule: str = "nielsen"
    lambda_factor: float = 10.0
    diagonal_damping: bool = True


@dataclass
class GaussNewtonParams(OptimizerParams):
    """GN: ``ridge`` is the fixed relative damping λ in (H + λD)δ = −g."""

    ridge: float = 1e-9


@dataclass
class IterationRecord:
    """One iteration: the trial at damping ``lambda_`` with step norm ‖δ‖₂.

    cost:       F after the iteration (the trial's cost if accepted, else unchanged);
    trial_cost: F at the trial point (inf if the system could not be solved);
    gain_ratio: ρ = actual / predicted decrease;
    time:       wall-clock seconds of this iteration (incl. relinearisation if accepted).
    """

    iteration: int
    cost: float
    trial_cost: float
    step_norm: float
    lambda_: float
    gain_ratio: float
    accepted: bool
    time: float


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

    def __repr__(self) -> str:
        return (
            f"OptimizationResult(cost {self.initial_cost:.6g} -> {self.final_cost:.6g}, "
            f"{self.iterations} iterations, converged={self.converged}, reason={self.reason!r})"
        )


class _Optimizer:
    _gn = False
    Params = OptimizerParams

    def __init__(self, params: OptimizerParams | None = None, **overrides: Any):
        """``params`` (default ``self.Params()``), with keyword ``overrides`` of its fields;
        params of the other method keep their shared fields."""
        if params is None:
            params = self.Params()
        elif not isinstance(params, self.Params):
            shared = {f.name: getattr(params, f.name) for f in dataclasses.fields(OptimizerParams)}
            params = self.Params(**shared)
        self.params = dataclasses.replace(params, **overrides) if overrides else params

    def optimize(self, graph: Iterable, values: Any, fixed: Iterable[Hashable] = ()
                 ) -> OptimizationResult:
        """Minimise F over the free variables of ``values``; returns a new Values."""
        p = self.params
        if getattr(p, "lambda_schedule", "nielsen") not in ("nielsen", "fixed"):
            raise ValueError(
                f"lambda_schedule must be 'nielsen' or 'fixed', got {p.lambda_schedule!r}"
            )
        if not getattr(p, "lambda_factor", 10.0) > 1:
            raise ValueError(f"lambda_factor must be > 1, got {p.lambda_factor!r}")
        check_cholmod_options(p.cholmod_mode, p.cholmod_ordering)
        t0 = time.perf_counter()
        if not isinstance(values, Values):
            values = Values(values)
        problem = Problem(graph, values, fixed)
        kind = resolve_linear_solver(self.params.linear_solver, problem.n,
                                     self.params.dense_threshold)
        solver = make_linear_solver(kind, problem.sparse_pattern(), problem.n,
                                    self.params.cholmod_mode, self.params.cholmod_ordering,
                                    self.params.cholmod_openmp,
                                    self.params.cholmod_blas_threads)
        timings = {"setup": time.perf_counter() - t0}
        res = _run(problem, solver, self.params, self._gn, timings)
        res.values = problem.to_values(res.values, values)
        return res


class LevenbergMarquardt(_Optimizer):
    """Levenberg-Marquardt with Marquardt scaling and Nielsen's λ update (module docstring)."""

    Params = LevenbergMarquardtParams


class GaussNewton(_Optimizer):
    """Gauss-Newton with a tiny fixed ridge; stops at the first non-decreasing step."""

    Params = GaussNewtonParams
    _gn = True


def _run(problem: Problem, solver, p, gn: bool, timings: dict) -> OptimizationResult:
    tick = time.perf_counter
    timings.update(linearize=0.0, jacobians=0.0, assemble=0.0, damp=0.0, solve=0.0, step=0.0)
    diag = problem.sparse_pattern()["diag"]

    def linearize(x):
        t = tick()
        h, g, c, valid, finite = problem.linearize(x, timings)
        timings["linearize"] += tick() - t
        return h, g, c, valid, finite and np.isfinite(c)

    x = problem.vars
    h, g, cost, valid, finite = linearize(x)
    if not finite:
        problem.diagnose(x)
        raise ValueError("the cost or its gradient is not finite at the initial values")
    initial_cost = cost
    lam = p.ridge if gn else p.lambda_initial
    nu = 2.0
    fixed_schedule = not gn and p.lambda_schedule == "fixed"
    identity_damping = not gn and not p.diagonal_damping
    history: list[IterationRecord] = []
    reason = None
    nlin = 1
    if cost <= p.absolute_tolerance:
        reason = "absolute"
    elif np.max(np.abs(g), initial=0.0) <= p.gradient_tolerance:
        reason = "gradient"
    it = 0
    while reason is None:
        if it >= p.max_iterations:
            reason = "max_iterations"
            break
        it += 1
        t_it = tick()
        D = np.ones(len(diag)) if identity_damping else np.clip(h[diag], p.min_diagonal,
                                                                  p.max_diagonal)
        hd = h.copy()
        hd[diag] += lam * D
        t = tick()
        timings["damp"] += t - t_it
        delta = solver.solve(hd, -g)
        timings["solve"] += tick() - t
        t = tick()
        if delta is None:
            rec = IterationRecord(it, cost, np.inf, np.nan, lam, -np.inf, False, 0.0)
            accepted, ok, trial_cost, pred, step_norm = False, False, np.inf, np.nan, np.nan
        else:
            step_norm = float(np.linalg.norm(delta))
            pred = 0.5 * float(delta @ (lam * D * delta - g))
            x_new, c_new, violates = problem.step(x, delta, valid)
            trial_cost = float(c_new)
            timings["step"] += tick() - t
            ok = np.isfinite(trial_cost) and not bool(violates)
            accepted = ok and trial_cost < cost
            gain = (cost - trial_cost) / pred if (ok and pred > 0) else -np.inf
            rec = IterationRecord(it, cost, trial_cost, step_norm, lam, gain, accepted, 0.0)
        if accepted:
            lin = linearize(x_new)
            nlin += 1
            if not lin[4]:  # non-finite Jacobian at the trial point: reject it
                accepted = rec.accepted = False
                ok = False
        if accepted:
            decrease, old = cost - trial_cost, cost
            x, cost = x_new, trial_cost
            rec.cost = cost
            if fixed_schedule:
                lam = max(p.lambda_min, lam / p.lambda_factor)
            elif not gn:
                shrink = max(1.0 / 3.0, 1.0 - (2.0 * rec.gain_ratio - 1.0) ** 3)
                lam = max(p.lambda_min, lam * shrink)
                nu = 2.0
            h, g, _, valid, _ = lin
            if cost <= p.absolute_tolerance:
                reason = "absolute"
            elif decrease <= p.relative_tolerance * old:
                reason = "relative"
            elif np.max(np.abs(g), initial=0.0) <= p.gradient_tolerance:
                reason = "gradient"
            elif step_norm <= p.step_tolerance:
                reason = "step"
        else:
            small = (
                ok
                and abs(cost - trial_cost) <= p.relative_tolerance * cost
                and pred <= p.relative_tolerance * cost
            )
            if delta is not None and step_norm <= p.step_tolerance:
                reason = "step"
            elif small:
                reason = "relative"
            elif gn:
                reason = "linear_solver" if delta is None else "cost_increase"
            elif fixed_schedule:
                lam *= p.lambda_factor
                if lam > p.lambda_max:
                    reason = "lambda_max"
            else:
                lam *= nu
                nu *= 2.0
                if lam > p.lambda_max:
                    reason = "lambda_max"
        rec.time = tick() - t_it
        history.append(rec)
        if p.verbose:
            print(
                f"iter {it:4d}  cost {rec.cost:.10e}  trial {rec.trial_cost:.4e}  "
                f"|step| {rec.step_norm:.3e}  lambda {rec.lambda_:.2e}  "
                f"rho {rec.gain_ratio:.3g}  {'accept' if accepted else 'reject'}  "
                f"{1e3 * rec.time:.1f} ms"
            )
        if p.callback is not None and p.callback(rec) and reason is None:
            reason = "callback"
    timings.update(solver.timings)
    return OptimizationResult(
        values=x,
        initial_cost=initial_cost,
        final_cost=cost,
        iterations=it,
        converged=reason in CONVERGED_REASONS,
        reason=reason,
        history=history,
        timings=timings,
        linear_solver=solver.name,
        linearizations=nlin,
    )
