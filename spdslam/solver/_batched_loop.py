"""The batched solver's lane loop: one ``lax.while_loop`` per structure (and batching
pattern, lane count, ``max_iterations``, step rule), and the batched cost.

Each loop step works on L *lanes*, each holding one problem: a lane solves its damped
system (H + λD)δ = −g (dense Cholesky), retracts to the trial point and relinearises there;
the one linearisation gives the trial cost, its validity and, if the step is accepted, the
next H and g. A lane whose problem stops is refilled with the next problem of the queue (its
first step is then the initial linearisation), so the work follows Σ(iterations + 1) / L
rather than B · max(iterations). The decisions (damping, gain ratio, λ schedules, stopping)
are ``_lm.decide``, the same function the sparse host loop (``_sparse``) calls. With a
``callback`` or ``verbose``, each loop step hands the records of the lanes in flight to the
host (``jax.experimental.io_callback``), which may stop their problems.
"""

from __future__ import annotations

import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import io_callback

from ..geometry import manifold
from ._batched_layout import BatchedKernel
from ._compile import JITTED_PROGRAMS
from ._linearize import violates
from ._lm import (
    CALLBACK,
    HYPER,
    MAX_ITERATIONS,
    REASONS,
    IterationRecord,
    StepRule,
    damping,
    decide,
    dogleg_step,
    hyper,
    initial_reason,
    model_decrease,
    predicted_decrease,
)

__all__ = ["HISTORY", "NONFINITE", "RESULT", "HistoryColumns", "Reporter", "ResultColumns",
           "cost_fn", "hyper_array", "solver_fn"]

#: The stopping reason of a problem whose cost or gradient is not finite at its initial
#: values (a code past ``_lm.REASONS``: ``BatchedProblem.solve`` raises on it).
NONFINITE = len(REASONS)

# lane status
_ACTIVE, _LOADING, _IDLE = 0, 1, 2


def _step(H, g, lam, rule, h, blocks):
    """The trial step and its model decrease, (δ, solved, L): LM/GN δ from (H + λD)δ = −g,
    D from ``_lm.damping``; dogleg (λ = Δ) the dogleg point of the GN step
    (H + ridge·D)δ = −g. Cholesky of the lower triangle, as the unbatched dense solver."""
    D = damping(jnp.diagonal(H), rule, h, jnp, blocks)
    A = H + jnp.diag((h["ridge"] if rule.dogleg else lam) * D)
    # lower Cholesky factor and two triangular solves, through the lax primitives: less to
    # trace than jnp.linalg
    L = jax.lax.linalg.cholesky(A, symmetrize_input=False)
    y = jax.lax.linalg.triangular_solve(L, g[:, None], left_side=True, lower=True)
    delta = -jax.lax.linalg.triangular_solve(L, y, left_side=True, lower=True,
                                             transpose_a=True)[:, 0]
    solved = jnp.all(jnp.isfinite(delta))
    delta = jnp.where(solved, delta, 0.0)
    if rule.dogleg:
        delta = dogleg_step(delta, g, H @ g, lam, jnp)
        return delta, solved, model_decrease(delta, g, H @ delta, jnp)
    return delta, solved, predicted_decrease(delta, D, g, lam, jnp)


def _where(c, a, b):
    """Per-lane select on pytrees whose leaves have a leading lane axis."""
    return jax.tree.map(
        lambda x, y: jnp.where(c.reshape(c.shape + (1,) * (x.ndim - 1)), x, y), a, b)


def _take(tree, axes, pid):
    """Rows ``pid`` of the batched parts of ``tree``; ``axes`` is a prefix of ``tree``
    with 0 (batched) or None (shared) at its leaves."""
    return jax.tree.map(
        lambda ax, sub: sub if ax is None else jax.tree.map(lambda a: a[pid], sub),
        axes, tree, is_leaf=lambda x: x is None)


def solver_fn(kern: BatchedKernel, sig, axes, lanes: int, max_iter: int, rule, report: bool):
    """(cache key, the jitted lane loop) of a structure (``sig``), batching pattern
    (``axes``), lane count, ``max_iterations``, step rule and ``report``, jitted once and
    kept in ``_compile.JITTED_PROGRAMS``."""
    key = ("solve", sig, axes, lanes, max_iter, rule, report)
    fn = JITTED_PROGRAMS.get(key)
    if fn is None:
        fn = JITTED_PROGRAMS[key] = jax.jit(_make_solver(kern, axes, lanes, max_iter, rule, report))
    return key, fn


def cost_fn(kern: BatchedKernel, sig, axes):
    """(cache key, the jitted batched cost F(x) of each problem) of a structure (``sig``) and
    batching pattern (``axes``), jitted once and kept in ``_compile.JITTED_PROGRAMS``."""
    key = ("cost", sig, axes)
    fn = JITTED_PROGRAMS.get(key)
    if fn is None:
        fix_ax, data_ax = axes

        def batched_cost(xf, xfix, gdata):
            return jax.vmap(lambda a, b, c: kern.cost(a, b, c)[0],
                            in_axes=(0, fix_ax, data_ax))(xf, xfix, gdata)

        fn = JITTED_PROGRAMS[key] = jax.jit(batched_cost)
    return key, fn


def _pack(tree):
    """Leaves with a leading axis (L, ...) → one (L, K) matrix (and back with ``_unpack``)."""
    leaves = jax.tree.leaves(tree)
    L = leaves[0].shape[0]
    return jnp.concatenate([a.reshape(L, -1) for a in leaves], axis=1)


def _unpack(mat, like):
    leaves, td = jax.tree.flatten(like)
    out, o = [], 0
    for a in leaves:
        k = int(np.prod(a.shape[1:], dtype=int))
        out.append(mat[:, o : o + k].reshape((mat.shape[0],) + a.shape[1:]))
        o += k
    return jax.tree.unflatten(td, out)


class HistoryColumns(NamedTuple):
    """Column indices of the packed history (B, max_iterations, 6), one row per problem and
    iteration (NaN past its last): the cost after the iteration (the trial cost if the step
    was accepted, else the previous cost), the trial cost (inf when the damped system could
    not be solved), the step norm ‖δ‖ (NaN then), the λ of the step (dogleg: the trust
    radius Δ), 1.0 if the step was accepted else 0.0, and the gain ratio."""

    COST: int = 0
    TRIAL: int = 1
    STEP: int = 2
    LAMBDA: int = 3
    ACC: int = 4
    GAIN: int = 5


class ResultColumns(NamedTuple):
    """Column indices of the packed per-problem results (B, 4): the initial cost, the final
    cost, the iterations taken and the stopping reason (a code of ``_lm.REASONS``, or
    ``NONFINITE``)."""

    COST0: int = 0
    COST: int = 1
    ITS: int = 2
    REASON: int = 3


#: The history's columns: ``hist[:, :, HISTORY.COST]``.
HISTORY = HistoryColumns()
#: The results' columns: ``res[:, RESULT.REASON]``.
RESULT = ResultColumns()
#: Columns of the per-lane records handed to the host callback.
_REPORT = ("problem", "iteration", "cost", "trial_cost", "step_norm", "lambda", "gain", "accepted")


class Reporter:
    """The host side of ``callback``/``verbose`` in the batched loop. The compiled program
    calls ``_report``, which forwards to the reporter of the solve in progress (so a cached
    program serves every callback)."""

    current: "Reporter | None" = None

    def __init__(self, params, rule: StepRule):
        self.callback, self.verbose = params.callback, params.verbose
        self.radius = rule.dogleg  # the records' damping is the dogleg's Δ
        self.last = time.perf_counter()

    def __call__(self, rows, active):
        now = time.perf_counter()
        dt, self.last = now - self.last, now
        stop = np.zeros(len(active), bool)
        for lane in np.flatnonzero(active):
            p, it, cost, trial, step, lam, gain, acc = rows[lane]
            rec = IterationRecord(int(it), float(cost), float(trial), float(step), float(lam),
                                  float(gain), bool(acc), dt, int(p), self.radius)
            if self.verbose:
                print(rec.line())
            if self.callback is not None and self.callback(rec):
                stop[lane] = True
        return stop


def _report(rows, active):
    rep = Reporter.current
    return np.zeros(len(active), bool) if rep is None else rep(np.asarray(rows), np.asarray(active))


def _make_solver(kern: BatchedKernel, axes, lanes: int, max_iter: int, rule, report: bool):
    """The lane loop. Inputs: x0 (per type, (B, nfree, ...)), fixed values and sub-group
    data (batched or shared, ``axes``), the numbers of the rule (``_lm.HYPER``), and the
    output buffers (filled on the host): results (B, 4) and history (B, max_iter, 6), NaN.
    ``rule`` (``_lm.StepRule``) is static; ``report`` compiles the host callback in."""
    fix_ax, data_ax = axes
    n = kern.n
    lin_l = jax.vmap(kern.linearize, in_axes=(0, fix_ax, data_ax))
    retract_l = jax.vmap(kern.retract)
    valid_shapes = [None if s.spec.valid is None else (s.nf,) for s in kern.subs]

    def run(x0, xfix, gdata, hyper_arr, res0, hist0):
        h = {k: hyper_arr[i] for i, k in enumerate(HYPER)}
        B = jax.tree.leaves(x0)[0].shape[0]
        L = min(lanes, B)
        blocks = tuple((nf, manifold.ops(ts.cls).blocks) for ts, nf in zip(kern.tspecs, kern.nfree))
        step_l = jax.vmap(lambda H, g, lam: _step(H, g, lam, rule, h, blocks))

        # initial state: lanes 0..L-1 load problems 0..L-1
        pid = jnp.arange(L, dtype=jnp.int32)
        x = jax.tree.map(lambda a: a[:L], x0)
        valid = tuple(None if s is None else jnp.zeros((L,) + s, bool) for s in valid_shapes)
        zL = jnp.zeros(L)
        state = dict(
            x=x, H=jnp.zeros((L, n, n)), g=jnp.zeros((L, n)), cost=zL, valid=valid,
            lam=zL, nu=zL, it=jnp.zeros(L, jnp.int32),
            status=jnp.full(L, _LOADING, jnp.int32), pid=pid,
            nxt=jnp.asarray(L, jnp.int32), steps=jnp.zeros((), jnp.int32),
            xout=jnp.zeros((B, _pack(x).shape[1])), res=res0, hist=hist0,
        )

        def cond(st):
            return jnp.any(st["status"] != _IDLE)

        def body(st):
            x, H, g, cost, valid = st["x"], st["H"], st["g"], st["cost"], st["valid"]
            lam, nu, it, status, pid = st["lam"], st["nu"], st["it"], st["status"], st["pid"]
            active = status == _ACTIVE
            got = status == _LOADING
            # trial step of the active lanes; the loading lanes evaluate their x0 instead
            delta, solved, pred = step_l(H, g, lam)
            x1 = retract_l(x, delta)
            xe = _where(got, jax.tree.map(lambda a: a[pid], x0), x1)
            H1, g1, c1, valid1, fin1 = lin_l(xe, _take(xfix, fix_ax, pid),
                                            _take(gdata, data_ax, pid))

            step_norm = jnp.sqrt(jnp.sum(delta * delta, axis=-1))
            usable = solved & jnp.isfinite(c1) & fin1 & ~violates(valid, valid1, axis=-1)
            gmax1 = jnp.max(jnp.abs(g1), axis=-1, initial=0.0)
            acc, gain, lam_u, nu_u, r_step = decide(rule, h, cost, c1, usable, solved, pred,
                                                    step_norm, gmax1, lam, nu, jnp)
            accepted = active & acc
            # loading lanes: their initial linearisation
            fin0 = fin1 & jnp.isfinite(c1)
            r_0 = jnp.where(~fin0, NONFINITE, initial_reason(c1, gmax1, h, jnp))
            reason = jnp.where(got, r_0, jnp.where(active, r_step, 0))

            take_new = got | accepted
            new = dict(st)
            new["x"] = _where(take_new, xe, x)
            new["H"] = _where(take_new, H1, H)
            new["g"] = _where(take_new, g1, g)
            new["valid"] = _where(take_new, valid1, valid)
            cost_n = new["cost"] = jnp.where(take_new, c1, cost)
            new["lam"] = jnp.where(got, h["lambda_initial"], jnp.where(active, lam_u, lam))
            new["nu"] = jnp.where(got, 2.0, jnp.where(active, nu_u, nu))
            it_n = new["it"] = jnp.where(got, 0, jnp.where(active, it + 1, it)).astype(jnp.int32)
            trial = jnp.where(solved, c1, jnp.inf)
            step = jnp.where(solved, step_norm, jnp.nan)
            if report:
                rows = jnp.stack([pid.astype(float), it_n.astype(float), cost_n, trial, step, lam,
                                  gain, accepted.astype(float)], axis=1)
                stop = io_callback(_report, jax.ShapeDtypeStruct((L,), jnp.bool_), rows, active)
                reason = jnp.where(active & stop & (reason == 0), CALLBACK, reason)
            done = (got | active) & ((reason != 0) | (it_n >= max_iter))

            # history of the active lanes at (problem, iteration)
            if max_iter > 0:
                rows = jnp.stack([cost_n, trial, step, lam, accepted.astype(float), gain], axis=1)
                new["hist"] = st["hist"].at[jnp.where(active, pid, B),
                                            jnp.minimum(it, max_iter - 1)].set(rows, mode="drop")
            # results: initial cost when loaded, the rest when done
            res = st["res"].at[jnp.where(got, pid, B), RESULT.COST0].set(c1, mode="drop")
            pd = jnp.where(done, pid, B)
            fin = jnp.stack([cost_n, it_n.astype(float),
                             jnp.where(reason == 0, MAX_ITERATIONS, reason).astype(float)], axis=1)
            new["res"] = res.at[pd, RESULT.COST:].set(fin, mode="drop")
            new["xout"] = st["xout"].at[pd].set(_pack(new["x"]), mode="drop")
            # refill the lanes that finished with the next problems of the queue
            status = jnp.where(got, _ACTIVE, status)
            cand = st["nxt"] + jnp.cumsum(done, dtype=jnp.int32) - 1
            refill = done & (cand < B)
            new["pid"] = jnp.where(refill, cand, pid)
            new["status"] = jnp.where(refill, _LOADING, jnp.where(done, _IDLE, status))
            new["nxt"] = st["nxt"] + jnp.sum(refill, dtype=jnp.int32)
            new["steps"] = st["steps"] + 1
            return new

        st = jax.lax.while_loop(cond, body, state)
        xout = _unpack(st["xout"], x0)
        return xout, st["res"], st["hist"], st["steps"]

    return run



def hyper_array(params) -> np.ndarray:
    """The numbers of the rule as one array, in ``_lm.HYPER`` order."""
    h = hyper(params)
    return np.asarray([h[k] for k in HYPER], dtype=float)

