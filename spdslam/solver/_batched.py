"""Many independent problems of identical structure, solved at once.

``BatchedProblem(graph, values, fixed, optimizer)`` (or ``optimizer.batched(...)``) lays out
one *template* problem: the structure (variable types, which variables are free, factor
kinds and the keys each factor touches). ``.solve(factor_args, values)`` then runs B
problems of that structure whose measurement data and initial values are given as arrays
with a leading batch axis B: no per-problem Python work. ``optimizer.optimize_batched(graphs,
values_list)`` takes a list of graphs instead; it checks that they share one structure,
stacks them and runs the same code.

The LM (or GN) loop runs in JAX, one ``lax.while_loop`` compiled once per structure (and
batching pattern, lane count, ``max_iterations``, B, step rule and ``optimize``). Each loop
step works on L *lanes* (``batch_size``, default 16), each holding one problem: a lane
solves its damped system (H + λD)δ = −g (dense Cholesky), retracts to the trial point and
relinearises there; the one linearisation gives the trial cost, its validity and, if the
step is accepted, the next H and g. A lane whose problem stops is refilled with the next
problem of the queue (its first step is then the initial linearisation), so the work
follows Σ(iterations + 1) / L rather than B · max(iterations). The decisions (damping, gain
ratio, λ schedules, stopping) are ``_lm.decide``, the same function the host loop calls, so
the results match a loop of unbatched dense solves up to round-off. (On badly conditioned
problems that stop on the relative tolerance after many small steps, round-off alone can
change the iteration at which they stop: the order of floating-point operations differs
between the unbatched solver, different lane counts and ``optimize`` settings.) With a
``callback`` or ``verbose``, each loop step hands the records of the lanes in flight to
the host (``jax.experimental.io_callback``), which may stop their problems.

Compilation. On CPU the program is compiled without XLA's newer fusion emitters and, with
``optimize=False``, without LLVM optimisation: a shorter compile for slower loops (the
figures are in docs/performance.md). ``optimize=None`` (default) chooses by the size of the
batch (``AUTO_OPTIMIZE_WORK``). ``BatchedProblem.cost`` runs the solver's program (stopping
every problem at its initial linearisation) when one is built for the same input layout,
so evaluating costs costs no compilation.

Layout (``_Layout``). Variables of one type are split into a *free* stack (the loop state)
and a *fixed* stack (plain data: never retracted, never differentiated). Factors of one
group (same residual, variable types, data layout, ...; see ``_problem``) are split further
by which of their key positions are free, so that every sub-group has a static free/fixed
pattern. A factor is linearised as

    J = ∂r(x ⊞ δ)/∂δ = ∂r/∂x · ∂(x ⊞ δ)/∂δ|₀,

the pushforward ∂(x ⊞ δ)/∂δ|₀ of the basis vectors being computed once per free variable
(not once per factor) and pushed through the residual with ``jax.jvp``. A key position that
every factor of a sub-group shares (one landmark seen by all cameras) is not broadcast: the
residual is vmapped over the factors with that argument unbatched. H = JᵀJ and g = Jᵀr are
formed from the dense (rows × n) Jacobian for small n (one matmul), else by scattering the
per-factor JᵀJ blocks.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable, Hashable, Iterable, Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import io_callback

from ..geometry import manifold
from ._linearize import finish, retract_rows, violates, whitened
from ._lm import (
    CALLBACK,
    CONVERGED_REASONS,
    HYPER,
    MAX_ITERATIONS,
    REASONS,
    IterationRecord,
    damping,
    decide,
    dogleg_step,
    hyper,
    initial_reason,
    model_decrease,
    predicted_decrease,
)
from ._optimizers import LevenbergMarquardt, Optimizer
from ._problem import Problem
from ._values import Values

__all__ = ["BatchedProblem", "BatchedResult", "solve_graphs"]

_NONFINITE = len(REASONS)  # internal: cost or gradient not finite at the initial values

# lane status
_ACTIVE, _LOADING, _IDLE = 0, 1, 2

#: Default number of lanes (problems in flight at once), see ``BatchedProblem.solve``.
DEFAULT_LANES = 16
#: XLA options of the batched programs on CPU: without the newer fusion emitters, which
#: lengthen the compile of these small-array programs and do not speed them up.
COMPILER_OPTIONS: dict[str, Any] = {"xla_cpu_use_fusion_emitters": False}
#: Added when a program is compiled for speed of compilation rather than of execution
#: (``optimize=False``): no LLVM optimisation.
FAST_COMPILE_OPTIONS: dict[str, Any] = {"xla_backend_optimization_level": 0}
#: ``optimize=None`` (auto) optimises the compiled code when B · max_iterations exceeds
#: this: the work at which the longer compile pays for itself (docs/performance.md).
AUTO_OPTIMIZE_WORK = 100_000

#: H and g come from the dense Jacobian (rows × n) when n ≤ this, else from scattered
#: per-factor JᵀJ blocks.
DENSE_JACOBIAN_MAX_N = 48


# ------------------------------------------------------------------------------------------
# Results
# ------------------------------------------------------------------------------------------


@dataclass
class BatchedResult:
    """Per-problem results of a batched solve (leading axis: problem b).

    ``values_batched[key]``: the final value of every variable the graph touches, as one
    pytree of the key's type with a leading axis B (numpy leaves): free variables as
    solved, fixed ones as given. ``values``: the same as a list of B ``Values`` (built on
    first access; for ``optimize_batched`` each is a copy of the problem's input Values).

    History arrays have one column per iteration (``max_iterations`` columns), padded with
    NaN (False for ``accepted``) after a problem stopped: ``cost`` after the iteration,
    ``trial_cost`` at its trial point, ``step_norm`` ‖δ‖₂, ``lambda_`` the damping used,
    ``gain`` the gain ratio; ``history(b)`` gives problem b's as ``IterationRecord``s.
    ``timings`` (s): setup (input layout), trace (tracing and lowering to XLA) and compile
    (XLA compilation; both zero when the program was already built), solve (running the
    loop), output; ``steps`` is the number of loop steps the lanes ran.
    """

    values_batched: dict
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
    gain_history: np.ndarray
    timings: dict[str, float] = field(default_factory=dict)
    steps: int = 0
    _make_values: Callable[[], list] | None = field(default=None, repr=False)
    _values: list | None = field(default=None, repr=False)

    @property
    def values(self) -> list[Values]:
        """The final values of each problem, one ``Values`` per problem."""
        if self._values is None:
            self._values = self._make_values() if self._make_values is not None else []
        return self._values

    def __len__(self) -> int:
        return len(self.initial_cost)

    def history(self, b: int) -> list[IterationRecord]:
        """The iterations of problem ``b`` (``time`` is not recorded per problem: NaN)."""
        return [
            IterationRecord(k + 1, float(self.cost_history[b, k]),
                            float(self.trial_cost_history[b, k]),
                            float(self.step_norm_history[b, k]),
                            float(self.lambda_history[b, k]), float(self.gain_history[b, k]),
                            bool(self.accepted_history[b, k]), float("nan"), b)
            for k in range(int(self.iterations[b]))
        ]

    def __repr__(self) -> str:
        return (f"BatchedResult({len(self)} problems, {int(np.sum(self.converged))} "
                f"converged, median {np.median(self.iterations) if len(self) else 0:g} "
                f"iterations, {self.steps} loop steps)")


# ------------------------------------------------------------------------------------------
# Static layout
# ------------------------------------------------------------------------------------------


def _pos_mode(idx: np.ndarray, nrows: int):
    """How a key position picks its rows from a stack: ("one", i) when every factor uses
    row i, ("all",) when factor j uses row j of all nrows rows, else ("take", indices)."""
    idx = np.asarray(idx)
    if len(idx) and np.all(idx == idx[0]):
        return ("one", int(idx[0]))
    if len(idx) == nrows and np.array_equal(idx, np.arange(nrows)):
        return ("all",)
    return ("take", tuple(int(i) for i in idx))


@dataclass(frozen=True)
class _Sub:
    """A sub-group: factors of one group with one free/fixed pattern (static, hashable)."""

    spec: Any  # _GroupSpec
    pattern: tuple[bool, ...]  # per key position: free?
    modes: tuple  # per key position: _pos_mode into the free or fixed stack of its type
    cols: tuple  # (nf, D) global tangent columns of the free positions, as nested tuples
    nf: int

    @property
    def free_pos(self) -> tuple[int, ...]:
        return tuple(p for p, f in enumerate(self.pattern) if f)

    @property
    def D(self) -> int:
        return sum(self.spec.dims[p] for p in self.free_pos)


class _Layout:
    """Template layout: which rows are free, the sub-groups, tangent offsets."""

    def __init__(self, p: Problem):
        self.problem = p
        self.tspecs = p.tspecs
        self.type_keys = [list(k) for k in p.type_keys]
        free = [np.asarray(f, bool) for f in p.free]
        self.free_rows = [np.flatnonzero(f) for f in free]
        self.fixed_rows = [np.flatnonzero(~f) for f in free]
        self.nfree = tuple(len(r) for r in self.free_rows)
        self.nfixed = tuple(len(r) for r in self.fixed_rows)
        self.local = []  # per type: row -> index in its free or fixed stack
        for f in free:
            loc = np.zeros(len(f), np.int64)
            loc[f] = np.arange(int(f.sum()))
            loc[~f] = np.arange(int((~f).sum()))
            self.local.append(loc)
        off, n = [], 0
        for ts, nf in zip(self.tspecs, self.nfree):
            off.append(n)
            n += ts.dim * nf
        self.offsets = tuple(off)
        self.n = n
        # key -> (type, free?, local index)
        self.key_slot: dict[Hashable, tuple[int, bool, int]] = {}
        for t, keys in enumerate(self.type_keys):
            for r, k in enumerate(keys):
                self.key_slot[k] = (t, bool(free[t][r]), int(self.local[t][r]))

        subs, sub_fids, sub_sel = [], [], []
        for k, spec in enumerate(p.gspecs):
            nf = p.group_nf[k]
            rows = np.asarray(p.gidx[k][0])[:nf]
            pat = np.stack([free[t][rows[:, q]] for q, t in enumerate(spec.var_types)], axis=1)
            _, first, inv = np.unique(pat, axis=0, return_index=True, return_inverse=True)
            inv = np.asarray(inv).reshape(-1)
            for u in np.argsort(first):
                sel = np.flatnonzero(inv == u)
                pattern = tuple(bool(b) for b in pat[sel[0]])
                modes, cols = [], []
                for q, t in enumerate(spec.var_types):
                    loc = self.local[t][rows[sel, q]]
                    nrows = self.nfree[t] if pattern[q] else self.nfixed[t]
                    modes.append(_pos_mode(loc, nrows))
                    if pattern[q]:
                        d = self.tspecs[t].dim
                        cols.append(self.offsets[t] + loc[:, None] * d + np.arange(d))
                G = np.concatenate(cols, axis=1) if cols else np.zeros((len(sel), 0), np.int64)
                subs.append(_Sub(spec, pattern, tuple(modes),
                                 tuple(tuple(int(c) for c in row) for row in G), len(sel)))
                sub_fids.append(np.asarray(p.group_fids[k])[sel])
                sub_sel.append((k, sel))
        self.subs = tuple(subs)
        self.sub_fids = sub_fids
        self.sub_sel = sub_sel
        self.signature = (self.tspecs, self.nfree, self.nfixed, self.subs, self.n)


# ------------------------------------------------------------------------------------------
# Kernels: per-problem functions of the laid-out arrays (vmapped by the drivers)
# ------------------------------------------------------------------------------------------


def _pick(tree, mode):
    """Rows of a stacked pytree for a key position, and whether they are batched over the
    factors (False for mode "one": one shared row)."""
    if mode[0] == "one":
        return jax.tree.map(lambda a: a[mode[1]], tree), False
    if mode[0] == "all":
        return tree, True
    idx = np.asarray(mode[1], np.int32)
    return jax.tree.map(lambda a: a[idx], tree), True


def _pushforward(ts, x):
    """∂(x ⊞ δ)/∂δ at δ = 0 for every row of a stacked pytree x: leaves (rows, dim, ...)."""
    op = manifold.ops(ts.cls)
    eye = jnp.eye(ts.dim)
    zero = jnp.zeros(ts.dim)

    def one(xi):
        f = lambda d: op.retract(xi, d)  # noqa: E731
        return jax.vmap(lambda e: jax.jvp(f, (zero,), (e,))[1])(eye)

    return jax.vmap(one)(x)


class _Kernel:
    """The per-problem functions of one static structure (unjitted; traced by drivers)."""

    def __init__(self, layout: _Layout):
        self.tspecs = layout.tspecs
        self.nfree, self.nfixed = layout.nfree, layout.nfixed
        self.subs = layout.subs
        self.offsets = layout.offsets
        self.n = layout.n
        self.dense_jacobian = self.n <= DENSE_JACOBIAN_MAX_N

    # --- one sub-group -------------------------------------------------------------
    def _sub_terms(self, s: _Sub, xf, Tf, xfix, data, jac: bool):
        spec = s.spec
        leaves, W = data
        args = jax.tree.unflatten(spec.args_treedef, leaves)
        xs, xs_ax, tans = [], [], []
        for q, t in enumerate(spec.var_types):
            if s.pattern[q]:
                x, ax = _pick(xf[t], s.modes[q])
                if jac:
                    tans.append(_pick(Tf[t], s.modes[q])[0])
            else:
                x, ax = _pick(xfix[t], s.modes[q])
            xs.append(x)
            xs_ax.append(0 if ax else None)
        free_pos = s.free_pos
        dims = [spec.dims[p] for p in free_pos]
        D = sum(dims)

        def one(xs_i, tans_i, args_i, W_i):
            def res(*fv):
                vals = list(xs_i)
                for p, v in zip(free_pos, fv):
                    vals[p] = v
                return whitened(spec.residual, W_i, vals, args_i)

            if jac and D > 0:
                dirs, o = [], 0
                for T, d in zip(tans_i, dims):
                    if len(dims) > 1:
                        T = jax.tree.map(
                            lambda a, o=o, d=d: jnp.concatenate(
                                [jnp.zeros((o,) + a.shape[1:], a.dtype), a,
                                 jnp.zeros((D - o - d,) + a.shape[1:], a.dtype)]), T)
                    dirs.append(T)
                    o += d
                primals = tuple(xs_i[p] for p in free_pos)
                r, Jt = jax.vmap(lambda *t: jax.jvp(res, primals, t), out_axes=(None, 0))(*dirs)
                J = Jt.T
            else:
                r, J = res(*[xs_i[p] for p in free_pos]), None
            return finish(spec, r, J, xs_i, args_i)

        tan_ax = [xs_ax[p] for p in free_pos] if jac else []
        if any(a == 0 for a in xs_ax) or leaves or W is not None:
            return jax.vmap(one, in_axes=(xs_ax, tan_ax, 0, None if W is None else 0))(
                xs, tans, args, W)
        # every factor of the sub-group is the same function of the same variables
        out = one(xs, tans, args, W)
        return jax.tree.map(lambda a: jnp.broadcast_to(a, (s.nf,) + a.shape), out)

    def _pushforwards(self, xf):
        return tuple(
            _pushforward(ts, x) if nf else None
            for ts, x, nf in zip(self.tspecs, xf, self.nfree)
        )

    # --- whole problem -------------------------------------------------------------
    def cost(self, xf, xfix, gdata):
        """(F, validity per sub-group, all residuals finite)."""
        cost, valids, finite = jnp.zeros(()), [], jnp.ones((), bool)
        for s, d in zip(self.subs, gdata):
            _, _, hr, v, fin = self._sub_terms(s, xf, None, xfix, d, jac=False)
            cost, finite = cost + jnp.sum(hr), finite & jnp.all(fin)
            valids.append(v)
        return cost, tuple(valids), finite

    def linearize(self, xf, xfix, gdata):
        """(H (n, n), g (n,), F, validity per sub-group, residuals and Jacobians finite)."""
        n = self.n
        Tf = self._pushforwards(xf)
        cost, valids, finite = jnp.zeros(()), [], jnp.ones((), bool)
        rows, rvec = [], []
        H = jnp.zeros((n, n))
        g = jnp.zeros(n)
        for s, d in zip(self.subs, gdata):
            r, J, hr, v, fin = self._sub_terms(s, xf, Tf, xfix, d, jac=True)
            cost, finite = cost + jnp.sum(hr), finite & jnp.all(fin)
            valids.append(v)
            if s.D == 0:
                continue
            cols = np.asarray(s.cols, np.int64)  # (nf, D)
            if self.dense_jacobian:
                if s.D == n and np.all(cols == np.arange(n)):
                    Jn = J  # (nf, m, n) already in global order
                else:
                    S = np.zeros((s.nf, s.D, n))
                    S[np.arange(s.nf)[:, None], np.arange(s.D)[None, :], cols] = 1.0
                    Jn = jnp.einsum("fmd,fdn->fmn", J, S)
                rows.append(Jn.reshape(-1, n))
                rvec.append(r.reshape(-1))
            else:
                JtJ = jnp.einsum("fmi,fmj->fij", J, J)
                Jtr = jnp.einsum("fmi,fm->fi", J, r)
                H = H.at[cols[:, :, None], cols[:, None, :]].add(JtJ)
                g = g.at[cols].add(Jtr)
        if rows:
            Jall = jnp.concatenate(rows) if len(rows) > 1 else rows[0]
            rall = jnp.concatenate(rvec) if len(rvec) > 1 else rvec[0]
            H = H + Jall.T @ Jall
            g = g + Jall.T @ rall
        return H, g, cost, tuple(valids), finite

    def retract(self, xf, delta):
        """regularize(x ⊞ δ) for every free variable (δ ∈ Rⁿ in the layout's order)."""
        out = []
        for ts, x, nf, o in zip(self.tspecs, xf, self.nfree, self.offsets):
            if not nf:
                out.append(None)
                continue
            d = delta[o : o + nf * ts.dim].reshape(nf, ts.dim)
            out.append(retract_rows(ts.cls, x, d))
        return tuple(out)


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


# ------------------------------------------------------------------------------------------
# Drivers: the lane loop and the batched cost, jitted per structure
# ------------------------------------------------------------------------------------------


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


_CACHE: dict[Any, Any] = {}
_EXECUTABLES: dict[Any, Any] = {}
#: solver programs by (structure, batching pattern, input shapes), reused by ``cost``
_BUILT: dict[Any, Any] = {}


def clear_caches() -> None:
    """Drop every compiled solver program: the sparse solver's kernels per structure, the
    batched solver's programs and executables, and JAX's own caches (``jax.clear_caches``).

    Each new graph structure compiles programs that are kept for reuse; a process that maps
    many different structures (a sweep over sequences, a test suite) can call this between
    them, so that their machine code is released (XLA maps each compiled program into
    memory, and a process may hold only ``vm.max_map_count`` mappings)."""
    from . import _problem

    _problem._KERNELS.clear()
    _problem._GROUP_KERNELS.clear()
    _problem._RETRACT.clear()
    _CACHE.clear()
    _EXECUTABLES.clear()
    _BUILT.clear()
    jax.clear_caches()


def _shapes(tree):
    leaves, td = jax.tree.flatten(tree)
    return td, tuple((np.shape(a), a.dtype if hasattr(a, "dtype") else np.result_type(a))
                     for a in leaves)


def _jit(f):
    return jax.jit(f)


def _executable(key, fn, args, timings: dict | None = None, optimize: bool = True):
    """The explicitly lowered and compiled executable of the jitted ``fn`` for ``args``
    (cached on ``key``, ``optimize`` and the argument shapes), recording "trace" (tracing
    and lowering) and "compile" (XLA) seconds in ``timings`` when it is built."""
    sig = (key, optimize, _shapes(args))
    ex = _EXECUTABLES.get(sig)
    if ex is None:
        t0 = time.perf_counter()
        low = fn.lower(*args)
        t1 = time.perf_counter()
        opts = {}
        if jax.default_backend() == "cpu":
            opts = dict(COMPILER_OPTIONS, **({} if optimize else FAST_COMPILE_OPTIONS))
        ex = _EXECUTABLES[sig] = low.compile(opts) if opts else low.compile()
        if timings is not None:
            timings["trace"] = t1 - t0
            timings["compile"] = time.perf_counter() - t1
    elif timings is not None:
        timings["trace"] = timings["compile"] = 0.0
    return ex


def _call(key, fn, args, timings: dict | None = None, optimize: bool = True):
    """Call the jitted ``fn`` through its compiled executable (``_executable``)."""
    return _executable(key, fn, args, timings, optimize)(*args)


def _solver_fn(kern: _Kernel, sig, axes, lanes: int, max_iter: int, rule, report: bool):
    key = ("solve", sig, axes, lanes, max_iter, rule, report)
    fn = _CACHE.get(key)
    if fn is None:
        fn = _CACHE[key] = _jit(_make_solver(kern, axes, lanes, max_iter, rule, report))
    return key, fn


def _cost_fn(kern: _Kernel, sig, axes):
    key = ("cost", sig, axes)
    fn = _CACHE.get(key)
    if fn is None:
        fix_ax, data_ax = axes

        def batched_cost(xf, xfix, gdata):
            return jax.vmap(lambda a, b, c: kern.cost(a, b, c)[0],
                            in_axes=(0, fix_ax, data_ax))(xf, xfix, gdata)

        fn = _CACHE[key] = _jit(batched_cost)
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


#: Columns of the packed history (B, max_iterations, 6).
_H_COST, _H_TRIAL, _H_STEP, _H_LAMBDA, _H_ACC, _H_GAIN = range(6)
#: Columns of the packed per-problem results (B, 4).
_R_COST0, _R_COST, _R_ITS, _R_REASON = range(4)
#: Columns of the per-lane records handed to the host callback.
_REPORT = ("problem", "iteration", "cost", "trial_cost", "step_norm", "lambda", "gain", "accepted")


class _Reporter:
    """The host side of ``callback``/``verbose`` in the batched loop. The compiled program
    calls ``_report``, which forwards to the reporter of the solve in progress (so a cached
    program serves every callback)."""

    current: "_Reporter | None" = None

    def __init__(self, params):
        self.callback, self.verbose = params.callback, params.verbose
        self.last = time.perf_counter()

    def __call__(self, rows, active):
        now = time.perf_counter()
        dt, self.last = now - self.last, now
        stop = np.zeros(len(active), bool)
        for lane in np.flatnonzero(active):
            p, it, cost, trial, step, lam, gain, acc = rows[lane]
            rec = IterationRecord(int(it), float(cost), float(trial), float(step), float(lam),
                                  float(gain), bool(acc), dt, int(p))
            if self.verbose:
                print(rec.line())
            if self.callback is not None and self.callback(rec):
                stop[lane] = True
        return stop


def _report(rows, active):
    rep = _Reporter.current
    return np.zeros(len(active), bool) if rep is None else rep(np.asarray(rows), np.asarray(active))


def _make_solver(kern: _Kernel, axes, lanes: int, max_iter: int, rule, report: bool):
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
            r_0 = jnp.where(~fin0, _NONFINITE, initial_reason(c1, gmax1, h, jnp))
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
            res = st["res"].at[jnp.where(got, pid, B), _R_COST0].set(c1, mode="drop")
            pd = jnp.where(done, pid, B)
            fin = jnp.stack([cost_n, it_n.astype(float),
                             jnp.where(reason == 0, MAX_ITERATIONS, reason).astype(float)], axis=1)
            new["res"] = res.at[pd, _R_COST:].set(fin, mode="drop")
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


# ------------------------------------------------------------------------------------------
# The template-plus-arrays API
# ------------------------------------------------------------------------------------------


def _hyper(params) -> np.ndarray:
    """The numbers of the rule as one array, in ``_lm.HYPER`` order."""
    h = hyper(params)
    return np.asarray([h[k] for k in HYPER], dtype=float)


class _Batch:
    """Inputs of one batched call, laid out: free values (B, nfree, ...) per type, fixed
    values and sub-group data (batched (B, ...) or shared) and their batching axes."""

    __slots__ = ("B", "x0", "xfix", "gdata", "axes", "given_args", "given_values")


class BatchedProblem:
    """A template problem (the structure) for solving many problems with array data.

    ``graph``, ``values``, ``fixed``: one problem of the structure; every problem solved
    with it has the same factors (kinds and keys), the same variables and the same fixed
    keys; measurement data and values may differ and are given as arrays to ``solve``
    and ``cost``. ``optimizer``: a ``LevenbergMarquardt`` (default) or ``GaussNewton`` with
    its parameters (``optimizer.batched(graph, values, fixed)`` is the same). ``optimize``:
    compile for run time (True) or for compile time (False); None chooses by
    B · max_iterations (see the module docstring). The linear solver is always dense
    (Cholesky).

    Example (one landmark seen from V fixed cameras, B scenes)::

        bp = LevenbergMarquardt().batched(graph0, values0, fixed=[X(i) for i in range(V)])
        res = bp.solve({i: (boxes[:, i], camera) for i in range(V)},
                       {L(0): Ellipsoid(P, t), **{X(i): SE3(wxyz_xyz[:, i]) ...}})
        res.values_batched[L(0)]         # Ellipsoid with P (B, 3, 3), center (B, 3)
        bp.cost(same_args, truth_values) # (B,)
    """

    def __init__(self, graph: Iterable, values: Any, fixed: Iterable[Hashable] = (),
                 optimizer: Optimizer | None = None, optimize: bool | None = None):
        self._set_optimizer(optimizer)
        self.optimize = optimize
        if not isinstance(values, Values):
            values = Values(values)
        self.template_values = values
        self.fixed = list(fixed)
        self.factors = list(graph)
        self._init_from_problem(Problem(self.factors, values, self.fixed))

    def _set_optimizer(self, optimizer: Optimizer | None):
        self.optimizer = LevenbergMarquardt() if optimizer is None else optimizer
        if not isinstance(self.optimizer, Optimizer):
            raise TypeError(f"optimizer must be a LevenbergMarquardt or GaussNewton, got "
                            f"{type(self.optimizer).__name__}")
        self.params, self.rule = self.optimizer.params, self.optimizer.rule

    def _init_from_problem(self, problem: Problem):
        self.layout = lay = _Layout(problem)
        self._kernel = _Kernel(lay)
        p = problem
        # template arrays (numpy): per type free / fixed stacks, per sub-group data
        self._tvars = [jax.tree.map(np.asarray, v) for v in p.vars]
        self._targs = []  # per factor: (treedef, [np leaves])
        for f in self.factors:
            leaves, td = jax.tree.flatten(f.args)
            self._targs.append((td, [np.asarray(a) for a in leaves]))
        self._tW = []
        for (k, sel) in lay.sub_sel:
            W = p.gdata[k][1]
            self._tW.append(None if W is None else jnp.asarray(np.asarray(W)[sel]))
        self._tvalue = {}
        for t, keys in enumerate(lay.type_keys):
            for r, key in enumerate(keys):
                self._tvalue[key] = jax.tree.map(lambda a, r=r: a[r], self._tvars[t])

    @property
    def n(self) -> int:
        """Tangent dimension of one problem."""
        return self.layout.n

    @property
    def keys(self) -> list:
        """The variables of the problem (keys touched by the graph), free and fixed."""
        return list(self.layout.key_slot)

    # --- input handling ------------------------------------------------------------
    def _norm_factor_args(self, factor_args, B_hint):
        """{factor index: [(leaf, batched?)]} for the given factors; updates B."""
        nfac = len(self.factors)
        if factor_args is None:
            items = {}
        elif isinstance(factor_args, Mapping):
            items = dict(factor_args)
            for i in items:
                if not isinstance(i, (int, np.integer)) or not 0 <= i < nfac:
                    raise ValueError(
                        f"factor_args: key {i!r} is not a factor index in [0, {nfac})")
        else:
            factor_args = list(factor_args)
            if len(factor_args) != nfac:
                raise ValueError(f"factor_args has {len(factor_args)} entries but the graph "
                                 f"has {nfac} factors")
            items = {i: a for i, a in enumerate(factor_args) if a is not None}
        B = B_hint
        out = {}
        for i, args in items.items():
            if args is None:
                continue
            i = int(i)
            td, tleaves = self._targs[i]
            if not isinstance(args, tuple):
                args = tuple(args) if isinstance(args, list) else (args,)
            leaves, atd = jax.tree.flatten(args)
            if atd != td:
                raise ValueError(f"factor_args[{i}]: structure {atd} does not match the "
                                 f"template factor's args {td}")
            norm = []
            for j, (a, ta) in enumerate(zip(leaves, tleaves)):
                a = np.asarray(a, dtype=ta.dtype)
                if a.shape == ta.shape:
                    norm.append((a, False))
                elif a.ndim == ta.ndim + 1 and a.shape[1:] == ta.shape:
                    if B is not None and a.shape[0] != B[0]:
                        raise ValueError(
                            f"factor_args[{i}] leaf {j}: batch size {a.shape[0]}, but "
                            f"{B[1]} has batch size {B[0]}")
                    B = B or (a.shape[0], f"factor_args[{i}]")
                    norm.append((a, True))
                else:
                    raise ValueError(
                        f"factor_args[{i}] leaf {j}: shape {a.shape}, expected {ta.shape} "
                        f"(shared) or (B,) + {ta.shape} (batched)")
            out[i] = norm
        return out, B

    def _norm_values(self, values, B_hint):
        """{key: ([leaves], batched?)}; updates B."""
        if values is None:
            return {}, B_hint
        if not isinstance(values, Mapping):
            raise TypeError("values must be a mapping key -> batched value")
        B = B_hint
        out = {}
        for key, v in values.items():
            if key not in self.layout.key_slot:
                raise ValueError(f"values: key {key!r} is not a variable of the template "
                                 "problem (no factor uses it)")
            tv = self._tvalue[key]
            if type(v) is not type(tv):
                raise TypeError(f"values[{key!r}]: expected {type(tv).__name__}, got "
                                f"{type(v).__name__}")
            leaves, td = jax.tree.flatten(v)
            tleaves = jax.tree.leaves(tv)
            if td != jax.tree.structure(tv):
                raise ValueError(f"values[{key!r}]: pytree structure does not match the "
                                 "template value")
            shapes = [np.shape(a) for a in leaves]
            tshapes = [np.shape(a) for a in tleaves]
            if shapes == tshapes:
                out[key] = ([np.asarray(a, dtype=t.dtype) for a, t in zip(leaves, tleaves)],
                            False)
                continue
            if not all(len(s) == len(ts) + 1 and s[1:] == ts for s, ts in zip(shapes, tshapes)):
                raise ValueError(
                    f"values[{key!r}]: leaf shapes {shapes}, expected {tshapes} (shared) or "
                    f"each with a leading batch axis B")
            bs = {s[0] for s in shapes}
            if len(bs) != 1:
                raise ValueError(f"values[{key!r}]: leaves have different batch sizes {bs}")
            b = bs.pop()
            if B is not None and b != B[0]:
                raise ValueError(f"values[{key!r}]: batch size {b}, but {B[1]} has batch "
                                 f"size {B[0]}")
            B = B or (b, f"values[{key!r}]")
            out[key] = ([np.asarray(a, dtype=t.dtype) for a, t in zip(leaves, tleaves)], True)
        return out, B

    def _prepare(self, factor_args, values) -> _Batch:
        lay = self.layout
        fa, B = self._norm_factor_args(factor_args, None)
        vals, B = self._norm_values(values, B)
        if B is None:
            raise ValueError("nothing is batched: give factor_args or values with a leading "
                             "batch axis B")
        B = B[0]
        if B < 1:
            raise ValueError("the batch is empty (B = 0)")
        out = _Batch()
        out.B = B
        out.given_args, out.given_values = fa, vals

        def stack_keys(t, rows, force_batched):
            keys = [lay.type_keys[t][r] for r in rows]
            td = self.layout.tspecs[t].treedef
            tl = [jax.tree.leaves(self._tvalue[k]) for k in keys]
            batched = force_batched or any(vals.get(k, (None, False))[1] for k in keys)
            leaves = []
            for j in range(td.num_leaves):
                parts = []
                for k, tk in zip(keys, tl):
                    if k in vals:
                        a, bt = vals[k][0][j], vals[k][1]
                    else:
                        a, bt = tk[j], False
                    if batched and not bt:
                        a = np.broadcast_to(a, (B,) + a.shape)
                    parts.append(a)
                leaves.append(jnp.asarray(np.stack(parts, axis=1 if batched else 0)))
            return jax.tree.unflatten(td, leaves), batched

        x0, xfix, fix_ax = [], [], []
        for t in range(len(lay.tspecs)):
            if lay.nfree[t]:
                x0.append(stack_keys(t, lay.free_rows[t], True)[0])
            else:
                x0.append(None)
            if lay.nfixed[t]:
                v, b = stack_keys(t, lay.fixed_rows[t], False)
                xfix.append(v)
                fix_ax.append(0 if b else None)
            else:
                xfix.append(None)
                fix_ax.append(None)
        gdata, data_ax = [], []
        for s, fids, W in zip(lay.subs, lay.sub_fids, self._tW):
            nleaf = len(self._targs[int(fids[0])][1])
            leaves, lax_ = [], []
            for j in range(nleaf):
                parts = [fa[int(f)][j] if int(f) in fa else (self._targs[int(f)][1][j], False)
                         for f in fids]
                batched = any(bt for _, bt in parts)
                if batched:
                    arrs = [a if bt else np.broadcast_to(a, (B,) + a.shape) for a, bt in parts]
                    leaves.append(jnp.asarray(np.stack(arrs, axis=1)))
                else:
                    leaves.append(jnp.asarray(np.stack([a for a, _ in parts])))
                lax_.append(0 if batched else None)
            gdata.append((tuple(leaves), W))
            data_ax.append((tuple(lax_), None))
        out.x0, out.xfix, out.gdata = tuple(x0), tuple(xfix), tuple(gdata)
        out.axes = (tuple(fix_ax), tuple(data_ax))
        return out

    # --- public --------------------------------------------------------------------
    def cost(self, factor_args=None, values=None) -> np.ndarray:
        """F = Σ ½ρ(‖W r‖²) of each problem at ``values`` (B,): same inputs as ``solve``.

        When ``solve`` has already built its program for inputs of the same shapes and
        batching pattern, that program is reused (with a stopping rule that ends every
        problem at its initial linearisation), so no new compilation is needed.
        """
        b = self._prepare(factor_args, values)
        axes = _hashable_axes(b.axes)
        built = _BUILT.get((self.layout.signature, axes, _shapes((b.x0, b.xfix, b.gdata))))
        if built is not None:
            key, fn, lanes, max_iter, optimize = built
            hyper_arr = _hyper(self.params)
            hyper_arr[HYPER.index("absolute_tolerance")] = np.inf  # every problem stops when loaded
            res0 = np.full((b.B, 4), np.nan)
            hist0 = np.full((b.B, max_iter, 6), np.nan)
            out = _call(key, fn, (b.x0, b.xfix, b.gdata, hyper_arr, res0, hist0),
                        optimize=optimize)
            return np.asarray(out[1])[:, _R_COST0]
        key, fn = _cost_fn(self._kernel, self.layout.signature, axes)
        return np.asarray(_call(key, fn, (b.x0, b.xfix, b.gdata), optimize=False))

    def solve(self, factor_args=None, values=None, batch_size: int | None = None
              ) -> BatchedResult:
        """Solve B problems of the template's structure.

        ``factor_args``: per factor of the template graph (a sequence aligned with it, or a
        dict {factor index: args}), None to use the template factor's args, or its args
        tuple where every leaf has either the template leaf's shape (shared by all
        problems) or a leading batch axis B. Factors of one kind are stacked into their
        group's layout here (array ops, no loop over problems). ``values``: {key: value},
        each value a pytree of the key's type whose leaves have a leading axis B (or the
        template's shapes, shared); missing keys take the template value. B is the batch
        size of the batched inputs (all must agree). ``batch_size``: lanes, the number of
        problems in flight at once (default min(B, DEFAULT_LANES)); a lane whose problem
        stops takes the next one.

        Raises ``ValueError`` naming the problem and factor if some problem's cost or
        gradient is not finite at its initial values.
        """
        t0 = time.perf_counter()
        b = self._prepare(factor_args, values)
        res = self._run(b, batch_size, t0)
        return res

    def compile(self, factor_args=None, values=None, batch_size: int | None = None) -> dict:
        """Trace and compile the solver for these inputs (as ``solve`` takes them) without
        running it; a later ``solve`` of inputs of the same shapes reuses the program.
        Returns {"trace": s, "compile": s} (zeros when it was already built). Safe to call
        from several threads for different problems: XLA compiles them in parallel."""
        b = self._prepare(factor_args, values)
        key, fn, args, optimize, _ = self._plan(b, batch_size)
        timings: dict = {}
        _executable(key, fn, args, timings, optimize)
        return timings

    def _plan(self, b: _Batch, batch_size):
        """(key, jitted solver, its arguments, optimize, report) for the batch ``b``."""
        p = self.params
        max_iter = int(p.max_iterations)
        lanes = int(batch_size) if batch_size is not None else DEFAULT_LANES
        if lanes < 1:
            raise ValueError(f"batch_size must be ≥ 1, got {batch_size}")
        lanes = min(lanes, b.B)
        report = p.callback is not None or bool(p.verbose)
        key, fn = _solver_fn(self._kernel, self.layout.signature, _hashable_axes(b.axes),
                             lanes, max_iter, self.rule, report)
        optimize = self.optimize
        if optimize is None:
            optimize = b.B * max_iter > AUTO_OPTIMIZE_WORK
        if not report:
            _BUILT.setdefault((self.layout.signature, _hashable_axes(b.axes),
                               _shapes((b.x0, b.xfix, b.gdata))),
                              (key, fn, lanes, max_iter, optimize))
        res0 = np.full((b.B, 4), np.nan)
        hist0 = np.full((b.B, max_iter, 6), np.nan)
        return key, fn, (b.x0, b.xfix, b.gdata, _hyper(p), res0, hist0), optimize, report

    def _run(self, b: _Batch, batch_size, t0, make_values=None) -> BatchedResult:
        p = self.params
        key, fn, args, optimize, report = self._plan(b, batch_size)
        t1 = time.perf_counter()
        timings = {"setup": t1 - t0}
        _Reporter.current = _Reporter(p) if report else None
        try:
            xout, res, hist, steps = _call(key, fn, args, timings, optimize)
            xout, res, hist = jax.tree.map(np.asarray, (xout, res, hist))
        finally:
            _Reporter.current = None
        t2 = time.perf_counter()
        timings["solve"] = t2 - t1 - timings["trace"] - timings["compile"]
        reason_codes = res[:, _R_REASON].astype(int)
        bad = np.flatnonzero(reason_codes == _NONFINITE)
        if len(bad):
            self._diagnose(b, int(bad[0]))
            raise ValueError(f"problem {int(bad[0])}: the cost or its gradient is not finite "
                             "at the initial values")
        reasons = [REASONS[int(r)] for r in reason_codes]
        its = res[:, _R_ITS].astype(int)
        vb = self._values_batched(b, xout)
        if make_values is None:
            def make_values():
                return self._values_list(vb, b.B)
        return BatchedResult(
            values_batched=vb,
            initial_cost=res[:, _R_COST0].copy(),
            final_cost=res[:, _R_COST].copy(),
            iterations=its,
            converged=np.array([r in CONVERGED_REASONS for r in reasons]),
            reason=reasons,
            cost_history=hist[:, :, _H_COST].copy(),
            trial_cost_history=hist[:, :, _H_TRIAL].copy(),
            step_norm_history=hist[:, :, _H_STEP].copy(),
            lambda_history=hist[:, :, _H_LAMBDA].copy(),
            accepted_history=hist[:, :, _H_ACC] == 1.0,
            gain_history=hist[:, :, _H_GAIN].copy(),
            timings=dict(timings, output=time.perf_counter() - t2),
            steps=int(steps),
            _make_values=make_values,
        )

    # --- outputs -------------------------------------------------------------------
    def _values_batched(self, b: _Batch, xout) -> dict:
        lay = self.layout
        vb = {}
        for key, (t, free, i) in lay.key_slot.items():
            if free:
                vb[key] = jax.tree.map(lambda a, i=i: np.asarray(a[:, i]), xout[t])
            elif b.axes[0][t] == 0:
                vb[key] = jax.tree.map(lambda a, i=i: np.asarray(a)[:, i], b.xfix[t])
            else:
                vb[key] = jax.tree.map(
                    lambda a, i=i: np.broadcast_to(np.asarray(a)[i], (b.B,) + a.shape[1:]),
                    b.xfix[t])
        return vb

    def _values_list(self, vb: dict, B: int) -> list:
        host = {k: (jax.tree.structure(v), jax.tree.leaves(v)) for k, v in vb.items()}
        out = []
        for i in range(B):
            v = self.template_values.copy()
            for k, (td, leaves) in host.items():
                v._data[k] = jax.tree.unflatten(td, [jnp.asarray(a[i]) for a in leaves])
            out.append(v)
        return out

    def _problem_values(self, b: _Batch, i: int) -> Values:
        """The input Values of problem i (for diagnostics)."""
        v = self.template_values.copy()
        for key, (leaves, batched) in b.given_values.items():
            td = jax.tree.structure(self._tvalue[key])
            v._data[key] = jax.tree.unflatten(td, [a[i] if batched else a for a in leaves])
        return v

    def _problem_graph(self, b: _Batch, i: int) -> list:
        """The factors of problem i (for diagnostics)."""
        out = []
        for fi, f in enumerate(self.factors):
            if fi in b.given_args:
                td = self._targs[fi][0]
                leaves = [a[i] if bt else a for a, bt in b.given_args[fi]]
                f = f.replace(args=jax.tree.unflatten(td, leaves))
            out.append(f)
        return out

    def _diagnose(self, b: _Batch, i: int) -> None:
        Problem(self._problem_graph(b, i), self._problem_values(b, i), self.fixed).diagnose(
            when=f"at the initial values of problem {i}")


def _hashable_axes(axes):
    """The batching pattern as a hashable static key (nested tuples of 0 / None)."""
    if isinstance(axes, (list, tuple)):
        return tuple(_hashable_axes(a) for a in axes)
    return axes


# ------------------------------------------------------------------------------------------
# The list-of-graphs API
# ------------------------------------------------------------------------------------------


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


def solve_graphs(
    optimizer: Optimizer,
    graphs: Any,
    values_list: Sequence[Any],
    fixed: Iterable[Hashable] = (),
    batch_size: int | None = None,
    optimize: bool | None = None,
) -> BatchedResult:
    """Solve B independent problems of identical structure with one jitted loop of
    ``optimizer`` (``Optimizer.optimize_batched``).

    ``graphs``: one graph per problem (a sequence), or a single graph shared by all;
    ``values_list``: the B initial Values; ``fixed``: keys held fixed in every problem;
    ``batch_size``: lanes (see ``BatchedProblem.solve``). The linear solver is always
    dense. Problems may use different keys as long as the structure is the same (variables
    are matched by their position in the layout of problem 0). For many problems,
    ``BatchedProblem`` avoids the per-problem layout work done here.
    """
    t0 = time.perf_counter()
    values_list = [v if isinstance(v, Values) else Values(v) for v in values_list]
    if not values_list:
        raise ValueError("optimize_batched needs at least one problem")
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
    bp = BatchedProblem.__new__(BatchedProblem)
    bp._set_optimizer(optimizer)
    bp.optimize = optimize
    bp.template_values = values_list[0]
    bp.fixed = fixed
    bp.factors = list(p0.factors)
    bp._init_from_problem(p0)
    lay = bp.layout
    B = len(problems)

    # stack the laid-out arrays of every problem (rows matched by layout position)
    def stack(trees):
        return jax.tree.map(lambda *xs: jnp.asarray(np.stack([np.asarray(x) for x in xs])),
                            *trees)

    b = _Batch()
    b.B = B
    b.given_args, b.given_values = {}, {}
    x0, xfix, fix_ax = [], [], []
    for t in range(len(lay.tspecs)):
        rows_f, rows_x = lay.free_rows[t], lay.fixed_rows[t]
        x0.append(stack([jax.tree.map(lambda a: np.asarray(a)[rows_f], p.vars[t])
                         for p in problems]) if len(rows_f) else None)
        if len(rows_x):
            v = stack([jax.tree.map(lambda a: np.asarray(a)[rows_x], p.vars[t])
                       for p in problems])
            xfix.append(v)
            fix_ax.append(0)
        else:
            xfix.append(None)
            fix_ax.append(None)
    gdata, data_ax = [], []
    for (k, sel), W in zip(lay.sub_sel, bp._tW):
        leaves = [jnp.asarray(np.stack([np.asarray(p.gdata[k][0][j])[sel] for p in problems]))
                  for j in range(len(p0.gdata[k][0]))]
        gdata.append((tuple(leaves), W))
        data_ax.append(((0,) * len(leaves), None))
    b.x0, b.xfix, b.gdata = tuple(x0), tuple(xfix), tuple(gdata)
    b.axes = (tuple(fix_ax), tuple(data_ax))

    def make_values():
        vals = []
        xs = res.values_batched
        for i, p in enumerate(problems):
            v = values_list[i].copy()
            for t, keys in enumerate(p.type_keys):
                for r, key in enumerate(keys):
                    k0 = lay.type_keys[t][r]
                    v._data[key] = jax.tree.map(lambda a: jnp.asarray(a[i]), xs[k0])
            vals.append(v)
        return vals

    res = bp._run(b, batch_size, t0, make_values)
    return res
