"""Many independent problems of identical structure, solved at once.

``solve_batched(graphs, values_list)`` lays out each problem (``Problem``), checks that they
share one structure (same variable types and free/fixed pattern, same factor groups with the
same key layout and data shapes; the data and initial values may differ), stacks their data
and values along a new leading axis, and runs the whole LM (or GN) loop in JAX: a
``lax.while_loop`` with a per-problem stop flag, vmapped over the batch and jitted once per
structure. Each iteration assembles the dense H = JᵀJ, solves (H + λD)δ = −g by Cholesky and
relinearises at the trial point; the rules (damping, gain ratio, Nielsen update, stopping) are
those of ``LevenbergMarquardt`` / ``GaussNewton`` (see ``_optimizers``), so the results match a
loop of unbatched dense solves up to round-off.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Any, Hashable, Iterable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ._optimizers import (
    CONVERGED_REASONS,
    GaussNewtonParams,
    LevenbergMarquardtParams,
    OptimizerParams,
)
from ._problem import Problem, _retract_all, _violates, split_delta
from ._values import Values

__all__ = ["solve_batched", "BatchedResult", "REASONS"]

#: Reason codes of the batched loop (index → ``OptimizationResult.reason`` string).
REASONS = (
    "",
    "absolute",
    "relative",
    "gradient",
    "step",
    "max_iterations",
    "lambda_max",
    "cost_increase",
    "linear_solver",
)
_ABS, _REL, _GRAD, _STEP, _MAXIT, _LMAX, _CINC, _LINS = range(1, 9)


@dataclass
class BatchedResult:
    """Per-problem results of ``solve_batched`` (leading axis: problem b).

    History arrays have one column per iteration (``max_iterations`` columns), padded with
    NaN (False for ``accepted``) after a problem stopped: ``cost`` after the iteration,
    ``trial_cost`` at its trial point, ``step_norm`` ‖δ‖₂, ``lambda_`` the damping used.
    """

    values: list[Values]
    initial_cost: np.ndarray
    final_cost: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    reason: list[str]
    cost_history: np.ndarray
    trial_cost_history: np.ndarray
    step_norm_history: np.ndarray
    lambda_history: np.ndarray
    accepted_history: np.ndarray
    timings: dict[str, float] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.values)


def _single_solve(kern, n, gn, max_iter, vars_, gdata, gidx, gcols, tan_idx, free, pad, hyper):
    """The LM/GN loop of one problem, in JAX (vmapped by the caller)."""
    (rel_tol, abs_tol, grad_tol, step_tol, dmin, dmax, lam0, lam_min, lam_max) = (
        hyper[i] for i in range(9)
    )

    def lin(x):
        return kern.linearize_dense_fn(x, gdata, gidx, gcols, n)

    H, g, cost, valid, finite = lin(vars_)
    finite = finite & jnp.isfinite(cost)
    reason0 = jnp.where(
        cost <= abs_tol, _ABS, jnp.where(jnp.max(jnp.abs(g), initial=0.0) <= grad_tol, _GRAD, 0)
    )
    nanrow = jnp.full(max_iter, jnp.nan)
    hist = (nanrow, nanrow, nanrow, nanrow, jnp.zeros(max_iter, bool))
    state = (0, vars_, H, g, cost, valid, lam0, 2.0, reason0, hist)

    def cond(s):
        it, *_, reason, _ = s
        return (reason == 0) & (it < max_iter)

    def body(s):
        it, x, H, g, cost, valid, lam, nu, reason, hist = s
        D = jnp.clip(jnp.diagonal(H), dmin, dmax)
        A = H + jnp.diag(lam * D + pad)
        L = jnp.linalg.cholesky(A)
        delta = -jax.scipy.linalg.cho_solve((L, True), g)
        solved = jnp.all(jnp.isfinite(delta))
        delta = jnp.where(solved, delta, 0.0)
        step_norm = jnp.linalg.norm(delta)
        pred = 0.5 * jnp.dot(delta, lam * D * delta - g)
        x1 = _retract_all(kern.tspecs, x, split_delta(delta, tan_idx), free)
        H1, g1, c1, valid1, fin1 = lin(x1)
        ok = solved & jnp.isfinite(c1) & fin1 & ~_violates(valid, valid1)
        accepted = ok & (c1 < cost)
        gain = jnp.where(ok & (pred > 0), (cost - c1) / jnp.where(pred > 0, pred, 1.0), -jnp.inf)
        if gn:
            lam_new, nu_new = lam, nu
            fail = jnp.where(solved, _CINC, _LINS)
        else:
            shrink = jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3)
            lam_new = jnp.where(accepted, jnp.maximum(lam_min, lam * shrink), lam * nu)
            nu_new = jnp.where(accepted, 2.0, 2.0 * nu)
            fail = jnp.where(lam_new > lam_max, _LMAX, 0)
        r_acc = jnp.where(
            c1 <= abs_tol, _ABS,
            jnp.where(cost - c1 <= rel_tol * cost, _REL,
                      jnp.where(jnp.max(jnp.abs(g1), initial=0.0) <= grad_tol, _GRAD,
                                jnp.where(step_norm <= step_tol, _STEP, 0))))
        small = ok & (jnp.abs(cost - c1) <= rel_tol * cost) & (pred <= rel_tol * cost)
        r_rej = jnp.where(solved & (step_norm <= step_tol), _STEP, jnp.where(small, _REL, fail))
        reason = jnp.where(accepted, r_acc, r_rej)

        def pick(a, b):
            return jnp.where(accepted, a, b)

        x = jax.tree.map(pick, x1, x)
        H, g, valid = pick(H1, H), pick(g1, g), jax.tree.map(pick, valid1, valid)
        cost = pick(c1, cost)
        hc, ht, hs, hl, ha = hist
        hist = (
            hc.at[it].set(cost),
            ht.at[it].set(jnp.where(solved, c1, jnp.inf)),
            hs.at[it].set(jnp.where(solved, step_norm, jnp.nan)),
            hl.at[it].set(lam),
            ha.at[it].set(accepted),
        )
        return (it + 1, x, H, g, cost, valid, lam_new, nu_new, reason, hist)

    it, x, _, _, cost_f, _, _, _, reason, hist = jax.lax.while_loop(cond, body, state)
    reason = jnp.where(reason == 0, _MAXIT, reason)
    return x, cost, cost_f, it, reason, finite, hist


_SOLVERS: dict[Any, Any] = {}


def _batched_fn(kern, n: int, gn: bool, max_iter: int):
    key = (id(kern), n, gn, max_iter)
    fn = _SOLVERS.get(key)
    if fn is None:

        def single(vars_, gdata, gidx, gcols, tan_idx, free, pad, hyper):
            return _single_solve(kern, n, gn, max_iter, vars_, gdata, gidx, gcols, tan_idx,
                                 free, pad, hyper)

        fn = jax.jit(jax.vmap(single, in_axes=(0, 0, None, None, None, None, None, None)))
        _SOLVERS[key] = (kern, fn)  # keep kern alive so that id(kern) stays unique
        return fn
    return fn[1]


def _same_structure(a: Problem, b: Problem, i: int) -> None:
    def fail(what):
        raise ValueError(f"problem {i} has a different structure from problem 0: {what}")

    if a.tspecs != b.tspecs:
        fail("variable types")
    if a.nv != b.nv:
        fail("number of variables")
    if any(not np.array_equal(x, y) for x, y in zip(a.free, b.free)) or a.n != b.n:
        fail("free/fixed variables")
    if a.gspecs != b.gspecs:
        fail("factor kinds")
    for ga, gb, da, db in zip(a.group_cols, b.group_cols, a.gdata, b.gdata):
        if ga.shape != gb.shape or not np.array_equal(ga, gb):
            fail("key layout of the factors")
        sa = [np.shape(x) for x in jax.tree.leaves(da)]
        sb = [np.shape(x) for x in jax.tree.leaves(db)]
        if sa != sb:
            fail("shapes of the factor data")


def solve_batched(
    graphs: Any,
    values_list: Sequence[Any],
    params: OptimizerParams | None = None,
    fixed: Iterable[Hashable] = (),
    method: str = "lm",
    **overrides: Any,
) -> BatchedResult:
    """Solve B independent problems of identical structure with one vmapped, jitted LM loop.

    ``graphs``: one graph per problem (a sequence), or a single graph shared by all;
    ``values_list``: the B initial Values; ``fixed``: keys held fixed in every problem;
    ``method``: "lm" (``LevenbergMarquardtParams``) or "gn" (``GaussNewtonParams``);
    keyword overrides replace fields of ``params``. The linear solver is always dense.
    """
    t0 = time.perf_counter()
    if method not in ("lm", "gn"):
        raise ValueError(f"method must be 'lm' or 'gn', got {method!r}")
    gn = method == "gn"
    if params is None:
        params = GaussNewtonParams() if gn else LevenbergMarquardtParams()
    if overrides:
        params = dataclasses.replace(params, **overrides)
    values_list = [v if isinstance(v, Values) else Values(v) for v in values_list]
    if not values_list:
        raise ValueError("solve_batched needs at least one problem")
    if isinstance(graphs, (list, tuple)):
        if len(graphs) != len(values_list):
            raise ValueError(f"{len(graphs)} graphs but {len(values_list)} Values")
    else:
        graphs = [graphs] * len(values_list)
    fixed = list(fixed)
    problems = [Problem(g, v, fixed) for g, v in zip(graphs, values_list)]
    p0 = problems[0]
    for i, p in enumerate(problems[1:], start=1):
        _same_structure(p0, p, i)

    def stack(*trees):
        return jax.tree.map(lambda *xs: jnp.stack(xs), *trees)

    vars_b = stack(*[p.vars for p in problems])
    gdata_b = stack(*[p.gdata for p in problems])
    lam0 = params.ridge if gn else params.lambda_initial
    lam_min = params.ridge if gn else params.lambda_min
    lam_max = np.inf if gn else params.lambda_max
    hyper = jnp.asarray(
        [params.relative_tolerance, params.absolute_tolerance, params.gradient_tolerance,
         params.step_tolerance, params.min_diagonal, params.max_diagonal, lam0, lam_min,
         lam_max], dtype=float,
    )
    max_iter = int(params.max_iterations)
    fn = _batched_fn(p0.kernels, p0.n_pad, gn, max_iter)
    t1 = time.perf_counter()
    out = fn(vars_b, gdata_b, p0.gidx, p0.dense_cols(), p0.tan_idx_pad, p0.free_j,
             p0.pad_diagonal(), hyper)
    out = jax.block_until_ready(out)
    t2 = time.perf_counter()
    x, cost0, cost_f, its, reason, finite, hist = out
    finite = np.asarray(finite)
    if not finite.all():
        b = int(np.flatnonzero(~finite)[0])
        problems[b].diagnose(when=f"at the initial values of problem {b}")
        raise ValueError(
            f"problem {b}: the cost or its gradient is not finite at the initial values")
    reasons = [REASONS[int(r)] for r in np.asarray(reason)]
    hc, ht, hs, hl, ha = (np.asarray(a) for a in hist)
    its = np.asarray(its)
    hl = np.where(np.arange(max_iter)[None, :] < its[:, None], hl, np.nan)
    leaves_np = jax.tree.map(np.asarray, x)
    values_out = [
        problems[b].to_values(jax.tree.map(lambda a, b=b: a[b], leaves_np), values_list[b])
        for b in range(len(problems))
    ]
    return BatchedResult(
        values=values_out,
        initial_cost=np.asarray(cost0),
        final_cost=np.asarray(cost_f),
        iterations=its,
        converged=np.array([r in CONVERGED_REASONS for r in reasons]),
        reason=reasons,
        cost_history=hc,
        trial_cost_history=ht,
        step_norm_history=hs,
        lambda_history=hl,
        accepted_history=ha,
        timings={"setup": t1 - t0, "solve": t2 - t1, "output": time.perf_counter() - t2},
    )
