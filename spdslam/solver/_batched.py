"""Many independent problems of identical structure, solved at once.

``BatchedProblem(graph, values, fixed, optimizer)`` (or ``optimizer.batched(...)``) lays out
one *template* problem: the structure (variable types, which variables are free, factor
kinds and the keys each factor touches). ``.solve(factor_args, values)`` then runs B
problems of that structure whose measurement data and initial values are given as arrays
with a leading batch axis B: no per-problem Python work. ``optimizer.optimize_batched(graphs,
values_list)`` takes a list of graphs instead (``solve_graphs``); it checks that they share
one structure, stacks them and runs the same code.

The parts, in the order they act: the layout of the template (``_batched_layout``), the lane
loop jitted per structure (``_batched_loop``: the LM, GN or dogleg rule of ``_lm``, so the
results match a loop of unbatched dense solves up to round-off), and its compilation
(``_compile``). (On badly conditioned problems that stop on the relative tolerance after
many small steps, round-off alone can change the iteration at which they stop: the order of
floating-point operations differs between the unbatched solver, different lane counts and
``optimize`` settings.) ``optimize=None`` (default) chooses the compile options by the size
of the batch (``AUTO_OPTIMIZE_WORK``). ``BatchedProblem.cost`` runs the solver's program
(stopping every problem at its initial linearisation) when one is built for the same input
layout, so evaluating costs costs no compilation.

The optimiser is any object with the ``params`` (``_lm.OptimizerParams``) and ``rule``
(``_lm.StepRule``) of ``LevenbergMarquardt``, ``GaussNewton`` or ``Dogleg``: this module
shares the rule with the optimisers through ``_lm``, not through them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable, Hashable, Iterable, Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ._batched_layout import BatchedKernel, BatchedLayout
from ._batched_loop import (
    HISTORY,
    NONFINITE,
    RESULT,
    Reporter,
    cost_fn,
    hyper_array,
    solver_fn,
)
from ._compile import (
    AUTO_OPTIMIZE_WORK,
    BUILT_SOLVERS,
    call_compiled,
    compiled_executable,
    shape_signature,
)
from ._graph import NonlinearFactorGraph
from ._lm import (
    CONVERGED_REASONS,
    HYPER,
    REASONS,
    IterationRecord,
    LevenbergMarquardtParams,
    OptimizerParams,
    StepRule,
)
from ._problem import Problem
from ._values import Values

__all__ = ["BatchedProblem", "BatchedResult", "solve_graphs", "DEFAULT_LANES"]

#: Default number of lanes (problems in flight at once), see ``BatchedProblem.solve``.
DEFAULT_LANES = 16


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
    ``trial_cost`` at its trial point, ``step_norm`` ‖δ‖₂, ``lambda`` the damping used (λ, or
    the dogleg's trust-region radius Δ: then ``radius`` is True), ``gain`` the gain ratio;
    ``history(b)`` gives problem b's as ``IterationRecord``s.
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
    radius: bool = False
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
                            bool(self.accepted_history[b, k]), float("nan"), b, self.radius)
            for k in range(int(self.iterations[b]))
        ]

    def __repr__(self) -> str:
        return (f"BatchedResult({len(self)} problems, {int(np.sum(self.converged))} "
                f"converged, median {np.median(self.iterations) if len(self) else 0:g} "
                f"iterations, {self.steps} loop steps)")






class _Batch:
    """Inputs of one batched call, laid out: free values (B, nfree, ...) per type, fixed
    values and sub-group data (batched (B, ...) or shared) and their batching axes."""

    __slots__ = ("B", "x0", "xfix", "gdata", "axes", "given_args", "given_values")
    B: int
    x0: tuple
    xfix: tuple
    gdata: tuple
    axes: tuple
    given_args: dict
    given_values: dict


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
                 optimizer=None, optimize: bool | None = None):
        self._set_optimizer(optimizer)
        self.optimize = optimize
        if not isinstance(values, Values):
            values = Values(values)
        self.template_values = values
        self.fixed = list(fixed)
        self.factors = list(NonlinearFactorGraph(graph))  # batches (FactorBatch) one by one
        self._init_from_problem(Problem(self.factors, values, self.fixed))

    def _set_optimizer(self, optimizer):
        """The optimiser's parameters and rule (default: LevenbergMarquardt's defaults)."""
        self.optimizer = optimizer
        if optimizer is None:
            self.params = LevenbergMarquardtParams()
            self.rule = StepRule.of(self.params)
            return
        params, rule = getattr(optimizer, "params", None), getattr(optimizer, "rule", None)
        if not (isinstance(params, OptimizerParams) and isinstance(rule, StepRule)):
            raise TypeError(f"optimizer must be a LevenbergMarquardt, GaussNewton or Dogleg, "
                            f"got {type(optimizer).__name__}")
        self.params, self.rule = params, rule

    def _init_from_problem(self, problem: Problem):
        self.layout = lay = BatchedLayout(problem)
        self._kernel = BatchedKernel(lay)
        p = problem
        # template arrays (numpy): per type free / fixed stacks, per sub-group data
        self._tvars = [jax.tree.map(np.asarray, v) for v in p.vars]
        self._targs = []  # per factor: (treedef, [np leaves])
        for f in self.factors:
            leaves, td, _ = f.flat_args()
            self._targs.append((td, leaves))
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
        for _sub, fids, W in zip(lay.subs, lay.sub_fids, self._tW):
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
        built = BUILT_SOLVERS.get((self.layout.signature, axes,
                                   shape_signature((b.x0, b.xfix, b.gdata))))
        if built is not None:
            key, fn, lanes, max_iter, optimize = built
            hyper_arr = hyper_array(self.params)
            hyper_arr[HYPER.index("absolute_tolerance")] = np.inf  # every problem stops when loaded
            res0 = np.full((b.B, len(RESULT)), np.nan)
            hist0 = np.full((b.B, max_iter, len(HISTORY)), np.nan)
            out = call_compiled(key, fn, (b.x0, b.xfix, b.gdata, hyper_arr, res0, hist0),
                                optimize=optimize)
            return np.asarray(out[1])[:, RESULT.COST0]
        key, fn = cost_fn(self._kernel, self.layout.signature, axes)
        return np.asarray(call_compiled(key, fn, (b.x0, b.xfix, b.gdata), optimize=False))

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
        compiled_executable(key, fn, args, timings, optimize)
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
        key, fn = solver_fn(self._kernel, self.layout.signature, _hashable_axes(b.axes),
                             lanes, max_iter, self.rule, report)
        optimize = self.optimize
        if optimize is None:
            optimize = b.B * max_iter > AUTO_OPTIMIZE_WORK
        if not report:
            BUILT_SOLVERS.setdefault((self.layout.signature, _hashable_axes(b.axes),
                                      shape_signature((b.x0, b.xfix, b.gdata))),
                                     (key, fn, lanes, max_iter, optimize))
        res0 = np.full((b.B, len(RESULT)), np.nan)
        hist0 = np.full((b.B, max_iter, len(HISTORY)), np.nan)
        return key, fn, (b.x0, b.xfix, b.gdata, hyper_array(p), res0, hist0), optimize, report

    def _run(self, b: _Batch, batch_size, t0, make_values=None) -> BatchedResult:
        p = self.params
        key, fn, args, optimize, report = self._plan(b, batch_size)
        t1 = time.perf_counter()
        timings = {"setup": t1 - t0}
        Reporter.current = Reporter(p, self.rule) if report else None
        try:
            xout, res, hist, steps = call_compiled(key, fn, args, timings, optimize)
            xout, res, hist = jax.tree.map(np.asarray, (xout, res, hist))
        finally:
            Reporter.current = None
        t2 = time.perf_counter()
        timings["solve"] = t2 - t1 - timings["trace"] - timings["compile"]
        reason_codes = res[:, RESULT.REASON].astype(int)
        bad = np.flatnonzero(reason_codes == NONFINITE)
        if len(bad):
            self._diagnose(b, int(bad[0]))
            raise ValueError(f"problem {int(bad[0])}: the cost or its gradient is not finite "
                             "at the initial values")
        reasons = [REASONS[int(r)] for r in reason_codes]
        its = res[:, RESULT.ITS].astype(int)
        vb = self._values_batched(b, xout)
        if make_values is None:
            def make_values():
                return self._values_list(vb, b.B)
        return BatchedResult(
            values_batched=vb,
            initial_cost=res[:, RESULT.COST0].copy(),
            final_cost=res[:, RESULT.COST].copy(),
            iterations=its,
            converged=np.array([r in CONVERGED_REASONS for r in reasons]),
            reason=reasons,
            cost_history=hist[:, :, HISTORY.COST].copy(),
            trial_cost_history=hist[:, :, HISTORY.TRIAL].copy(),
            step_norm_history=hist[:, :, HISTORY.STEP].copy(),
            lambda_history=hist[:, :, HISTORY.LAMBDA].copy(),
            accepted_history=hist[:, :, HISTORY.ACC] == 1.0,
            gain_history=hist[:, :, HISTORY.GAIN].copy(),
            timings=dict(timings, output=time.perf_counter() - t2),
            steps=int(steps),
            radius=self.rule.dogleg,
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
    optimizer,
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
    x0: list = []
    xfix: list = []
    fix_ax: list[int | None] = []
    for t in range(len(lay.tspecs)):
        rows_f, rows_x = lay.free_rows[t], lay.fixed_rows[t]
        x0.append(stack([jax.tree.map(lambda a, rows_f=rows_f: np.asarray(a)[rows_f], p.vars[t])
                         for p in problems]) if len(rows_f) else None)
        if len(rows_x):
            v = stack([jax.tree.map(lambda a, rows_x=rows_x: np.asarray(a)[rows_x], p.vars[t])
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
                    v._data[key] = jax.tree.map(lambda a, i=i: jnp.asarray(a[i]), xs[k0])
            vals.append(v)
        return vals

    res = bp._run(b, batch_size, t0, make_values)
    return res

