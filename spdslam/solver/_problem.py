"""A factor graph laid out for vectorised linearisation.

Layout (built once per call to the optimiser, in ``Problem.__init__``):

- variables of one registered type are stacked into one pytree whose leaves have a leading
  axis (one row per variable);
- factors whose residual function, variable types, data layout (tree structure, shapes,
  dtypes), noise-model shape, robust kernel and ``valid`` function agree form a *group*:
  their ``args`` and W are stacked, and each key position gets an integer array of row
  indices into its type's stack;
- the tangent vector δ ∈ Rⁿ concatenates the tangent coordinates of the free variables
  (fixed variables and variables no factor touches have none);
- H = JᵀJ is stored as the lower triangle of a symmetric CSC matrix whose pattern, and the
  slot of every per-factor contribution in it, are computed here once.

Linearisation of a group is one vmapped computation: for each factor,

    r̃(δ) = W r(x₁ ⊞ δ₁, …, x_k ⊞ δ_k, args),   J = ∂r̃/∂δ |_{δ=0} = ∂r̃/∂x · ∂(x ⊞ δ)/∂δ|₀,

the pushforwards ∂(x ⊞ δ)/∂δ|₀ computed once per variable and gathered per factor like the
variables (``_linearize``; types with non-float leaves are differentiated per factor with
``jax.jacfwd`` instead),

with a robust kernel applied by IRLS: s = ‖r̃‖², r̃ ← √ρ'(s) r̃, J ← √ρ'(s) J. Each group is
one jitted call (its per-factor JᵀJ and Jᵀr̃ are scattered into their slots on the host),
except a group whose factor type has a closed form (``factors.closed_form``): it computes the
same terms in NumPy (``_closed_form``), with nothing to compile.

Compilation. A group's jitted functions are cached on its static description (residual
function, variable types, data tree structure, kernel) and take its factors' variables
gathered on the host, so that JAX compiles one program per group and padded count: a
problem whose set of groups changes (the fixed-lag window of online mapping, where kinds of
factors come and go) reuses each group's programs. To keep
the number of shapes small, the counts of variables per type and of factors per group are
padded up to a ``bucket`` (2ᵏ·{1, 1.25, 1.5, 1.75}): pad variables repeat row 0 and are held
fixed, pad factors repeat factor 0 with zero weight and scatter into a discarded slot (H and
g are summed on the host, so n and nnz are not part of the compiled shapes). A graph that
grows by a few factors therefore usually reuses the compiled code. The per-factor terms
(whitening, robust weighting, validity) are ``_linearize``'s, shared with the batched solver.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Any, Callable, Hashable, Iterable

import jax
import jax.numpy as jnp
import numpy as np

from ..factors import CustomFactor, FactorBatch, RobustKernel, closed_form
from ..geometry import manifold, native
from ._closed_form import ClosedFormGroup, closed_form_of, closed_forms_enabled
from ._linearize import (
    differentiable,
    finish,
    jvp_jacobian,
    pushforward,
    retract_rows,
    tangent_directions,
    whitened,
)
from ._pattern import csc_pattern
from ._stored import own_code, stored_jit

__all__ = ["Problem", "bucket", "CHUNK"]

#: Factors are linearised in chunks of about CHUNK // D factors (lax.map over vmapped
#: chunks), so that the intermediates of forward-mode differentiation stay in cache on CPU.
CHUNK = 256


def bucket(x: int, minimum: int = 8) -> int:
    """The smallest of 2ᵏ·{1, 1.25, 1.5, 1.75} that is ≥ max(x, minimum)."""
    x = max(int(x), minimum)
    k = max(int(np.floor(np.log2(x))) - 2, 0)
    step = 1 << k
    return -(-x // step) * step


@dataclass(frozen=True)
class _TypeSpec:
    """Static description of one variable type: class, tree structure, tangent dim."""

    cls: type
    treedef: Any
    dim: int


@dataclass(frozen=True)
class _GroupSpec:
    """Static description of one factor group (hashable: part of the kernels' cache key)."""

    residual: Callable
    var_types: tuple[int, ...]
    dims: tuple[int, ...]
    args_treedef: Any
    has_sqrt_info: bool
    robust: RobustKernel | None
    valid: Callable | None

    @property
    def D(self) -> int:
        return sum(self.dims)


class _GroupBuild:
    """One group's factors as they are laid out: single factors row by row (``fids``,
    ``idx``, ``args``, ``W``, ``kinds``), batches and flushed runs of singles as arrays
    (``chunks``: factor ids, variable rows, stacked leaves, stacked W, kind runs)."""

    __slots__ = ("sig", "fids", "idx", "args", "W", "kinds", "first", "chunks")

    def __init__(self, sig, first) -> None:
        self.sig, self.first = sig, first
        self.fids: list[int] = []
        self.idx: list[list[int]] = []
        self.args: list[list[np.ndarray]] = []
        self.W: list[Any] = []
        self.kinds: list[str] = []
        self.chunks: list[tuple] = []

    def _flush(self) -> None:
        if not self.fids:
            return
        n, nl = len(self.fids), len(self.sig[3])
        self.chunks.append((
            np.asarray(self.fids), np.asarray(self.idx, np.int32).reshape(n, -1),
            [np.stack([a[j] for a in self.args]) for j in range(nl)],
            np.stack(self.W) if self.sig[4] is not None else None,
            [(k, 1) for k in self.kinds]))
        self.fids, self.idx, self.args, self.W, self.kinds = [], [], [], [], []

    def add_batch(self, fids, idx, leaves, W, kind) -> None:
        self._flush()
        self.chunks.append((fids, idx, leaves, W, [(kind, len(fids))]))

    def arrays(self):
        """(factor ids, variable rows (nf, k), stacked leaves, stacked W or None, kind runs)."""
        self._flush()
        cat = lambda xs: xs[0] if len(xs) == 1 else np.concatenate(xs)  # noqa: E731
        c = self.chunks
        leaves = [cat([np.asarray(ch[2][j]) for ch in c]) for j in range(len(self.sig[3]))]
        W = cat([np.asarray(ch[3]) for ch in c]) if self.sig[4] is not None else None
        return (cat([ch[0] for ch in c]), cat([ch[1] for ch in c]), leaves, W,
                [run for ch in c for run in ch[4]])


class _FactorList:
    """The factors of a problem by global index, batches unpacked only where asked."""

    def __init__(self, entries: list) -> None:
        self.entries = entries
        sizes = [len(e) if isinstance(e, FactorBatch) else 1 for e in entries]
        self.starts = np.concatenate([[0], np.cumsum(sizes, dtype=np.int64)])

    def __len__(self) -> int:
        return int(self.starts[-1])

    def __getitem__(self, i: int):
        if not 0 <= i < len(self):
            raise IndexError(i)
        e = int(np.searchsorted(self.starts, i, side="right")) - 1
        entry = self.entries[e]
        return entry[i - int(self.starts[e])] if isinstance(entry, FactorBatch) else entry

    def __iter__(self):
        for e in self.entries:
            if isinstance(e, FactorBatch):
                yield from e
            else:
                yield e


def _describe(f, fi) -> str:
    """"factor #i (BetweenFactor, keys …)": the type's class name, a custom factor's kind."""
    name = f.kind if isinstance(f, CustomFactor) else type(f).__name__
    return f"factor #{fi} ({name}, keys {tuple(f.keys)!r})"


#: Residual dimension by group signature and variable layouts (``_residual_dim``).
_RESIDUAL_DIM: dict[Any, int] = {}


def _residual_dim(f0, gb: _GroupBuild, values: list, layouts: list) -> int:
    """The residual dimension of group ``gb``: its closed form's residual of the first factor
    ``f0`` (NumPy), else ``jax.eval_shape`` of it; once per signature and variable layouts."""
    key = (gb.sig[0], gb.sig[2], gb.sig[3], tuple(layouts))
    m = _RESIDUAL_DIM.get(key)
    if m is None:
        cf = closed_form(f0.residual, f0.valid, tuple(layout[0] for layout in layouts))
        try:
            if cf is not None and closed_forms_enabled():  # the closed form of one row: no tracing
                leaves, treedef, _ = f0.flat_args()
                rows = [jax.tree.map(lambda a: np.asarray(a)[None], v) for v in values]
                with np.errstate(all="ignore"):
                    r = cf.linearize(rows, [None] * len(rows), treedef.unflatten([a[None] for a in leaves]), False)[0]
                m = int(np.prod(np.shape(r)[1:]))
            else:
                out = jax.eval_shape(f0.residual, *values, *f0.args)
                m = int(np.prod(out.shape)) if hasattr(out, "shape") else 1
        except Exception as e:
            raise ValueError(f"{_describe(f0, gb.first)}: residual failed: {e}") from e
        if len(_RESIDUAL_DIM) > 4096:  # ad-hoc residuals (closures) must not pile up
            _RESIDUAL_DIM.clear()
        _RESIDUAL_DIM[key] = m
    return m


def _on_device(a) -> jax.Array:
    """``a`` as a JAX array: a host array is transferred (``jax.device_put``; ``jnp.asarray``
    would run, and with an empty cache compile, a program per shape), a JAX array kept."""
    return a if isinstance(a, jax.Array) else jax.device_put(np.asarray(a))


def _pad_rows(a: np.ndarray, total: int) -> np.ndarray:
    """Append copies of row 0 up to ``total`` rows."""
    if len(a) == total:
        return a
    return np.concatenate([a, np.repeat(a[:1], total - len(a), axis=0)])


# ------------------------------------------------------------------------------------------
# Kernels: pure functions of stacked arrays, cached on the static structure.
# ------------------------------------------------------------------------------------------


def _group_map(spec: _GroupSpec, tspecs, xs, Ts, mask, data, mode: str):
    """Per-factor terms of one group, mapped over its factors in chunks; ``xs``: per key
    position, the variables of each factor (gathered on the host, ``_Kernels``); ``Ts``: their
    pushforwards, gathered alike (None: J by ``jax.jacfwd`` through the retractions).

    mode "cost":   (½ρ(s) (nf,), valid, finite)
    mode "sparse": (JᵀJ upper triangle (nf, D(D+1)/2), Jᵀr (nf, D), ½ρ(s), valid, finite)
    mode "terms":  (r (nf, m), J (nf, m, D), ½ρ(s), valid, finite)

    r and J are whitened and IRLS-weighted: r ← √ρ'(s) W r, J ← √ρ'(s) W ∂r/∂δ, s = ‖W r‖².
    ½ρ(s) is zero on pad rows. ``valid`` is None when the group has no validity function.
    """
    leaves, W = data
    args = jax.tree.unflatten(spec.args_treedef, leaves)
    ops = [manifold.ops(tspecs[t].cls) for t in spec.var_types]
    offs = np.concatenate([[0], np.cumsum(spec.dims)]).tolist()
    D = spec.D
    iu, ju = np.triu_indices(D)

    def one(item):
        xs_i, Ts_i, args_i, W_i, mask_i = item
        if mode == "cost":
            r = whitened(spec.residual, W_i, xs_i, args_i)
            J = None
        elif Ts_i is not None:
            def res(*ys):
                return whitened(spec.residual, W_i, ys, args_i)

            r, J = jvp_jacobian(res, tuple(xs_i), tangent_directions(Ts_i, spec.dims))
        else:

            def fun(d):
                ys = [
                    op.retract(x, d[offs[p] : offs[p + 1]])
                    for p, (op, x) in enumerate(zip(ops, xs_i))
                ]
                r = whitened(spec.residual, W_i, ys, args_i)
                return r, r

            J, r = jax.jacfwd(fun, has_aux=True)(jnp.zeros(D))
        r, J, half_rho, valid, finite = finish(spec, r, J, xs_i, args_i)
        half_rho = jnp.where(mask_i, half_rho, 0.0)
        if mode == "cost":
            return half_rho, valid, finite
        if mode == "terms":
            return r, J, half_rho, valid, finite
        return (J.T @ J)[iu, ju], J.T @ r, half_rho, valid, finite

    nf = mask.shape[0]
    batch = _chunk(nf, D)
    if batch >= nf:
        return jax.vmap(one)((xs, Ts, args, W, mask))
    return jax.lax.map(one, (xs, Ts, args, W, mask), batch_size=batch)


def _chunk(nf: int, D: int) -> int:
    """Chunk size: the largest power of two ≤ CHUNK/D dividing nf (nf is a bucket size,
    so this leaves no remainder), or nf itself when nf ≤ CHUNK/D."""
    target = max(1, CHUNK // max(D, 1))
    if nf <= target:
        return nf
    b = 1
    while b * 2 <= target and nf % (b * 2) == 0:
        b *= 2
    return b


def split_delta(delta, tan_idx):
    """Per-type (rows, dim) blocks of δ (NumPy); ``tan_idx`` rows of non-free variables
    point past the end of δ and get zeros."""
    dext = np.concatenate([delta, np.zeros(1, delta.dtype)])
    return tuple(dext[ti] for ti in tan_idx)


class _GroupKernels:
    """The jitted functions of one factor group, on its factors' variables gathered on the
    host: its compiled shapes are its own padded count only, whatever else is in the
    problem (``_Kernels``)."""

    def __init__(self, spec: _GroupSpec, tspecs: tuple[_TypeSpec, ...]):
        stored = _stored_key(spec, tspecs)

        def program(mode, n_out):
            def cost(xs, m, d):
                return _group_map(spec, tspecs, xs, None, m, d, mode)[:n_out]

            def linearization(xs, Ts, m, d):
                return _group_map(spec, tspecs, xs, Ts, m, d, mode)[:n_out]

            f: Callable = cost if mode == "cost" else linearization

            # named after the residual, as JAX's compile log and profiles show it
            f.__name__ = f.__qualname__ = f"{getattr(spec.residual, '__name__', 'residual')}_{mode}"
            return stored_jit(f, None if stored is None else f"group {mode} {n_out} {CHUNK} {stored}")

        self.cost, self.sparse, self.terms = program("cost", 2), program("sparse", 5), program("terms", 5)
        #: padded sizes called so far, and the first rows of the first call's inputs
        #: (``compile_sizes``)
        self.sizes: set[int] = set()
        self.example: tuple | None = None
        self.example_T = None

    def note(self, xs, Ts, mask, data) -> None:
        self.sizes.add(int(mask.shape[0]))
        # row 0 is all that padding repeats: keep a few rows only
        head = lambda a: np.array(np.asarray(a)[:_EXAMPLE_ROWS])  # noqa: E731
        if self.example is None:
            self.example = (jax.tree.map(head, xs), None, jax.tree.map(head, data))
        if self.example_T is None and Ts is not None:
            self.example_T = jax.tree.map(head, Ts)

    def compile_sizes(self, sizes) -> int:
        """Compile the cost and linearisation programs for each padded factor count in
        ``sizes`` (by calling them on the first call's inputs, row 0 repeated): the in-process
        cache holds them afterwards, and the persistent cache when it is on. Returns the
        number of sizes compiled."""
        if self.example is None:
            return 0
        xs, _, data = self.example
        done = 0
        for n in sorted(set(int(k) for k in sizes) - self.sizes):
            grow = lambda a, n=n: _pad_rows(np.asarray(a)[:n], n)  # noqa: E731
            x, m, d = jax.tree.map(grow, xs), np.zeros(n, bool), jax.tree.map(grow, data)
            T = None if self.example_T is None else jax.tree.map(grow, self.example_T)
            jax.block_until_ready((self.cost(x, m, d), self.sparse(x, T, m, d)))
            self.sizes.add(n)
            done += 1
        return done


def _name(fn) -> str:
    return f"{getattr(fn, '__module__', '')}.{getattr(fn, '__qualname__', repr(fn))}"


def _jaxlie(cls) -> bool:
    """A jaxlie type (its version is in every stored program's key)."""
    return _name(cls).startswith("jaxlie.")


def _stored_key(spec: _GroupSpec, tspecs) -> str | None:
    """The description of a group's programs for the store (``_stored``), or None when
    they are not all code the store's key covers (``own_code``: a user's residual, kernel
    or variable type is traced as usual)."""
    kernel = type(spec.robust) if spec.robust is not None else None
    if not own_code(spec.residual, spec.valid, kernel, *(ts.cls for ts in tspecs if not _jaxlie(ts.cls))):
        return None
    types = [(_name(ts.cls), str(ts.treedef), ts.dim) for ts in tspecs]
    return repr((_name(spec.residual), spec.var_types, spec.dims, str(spec.args_treedef), spec.has_sqrt_info,
                 repr(spec.robust), None if spec.valid is None else _name(spec.valid), types))


def group_kernels() -> list:
    """Every factor group's kernels built in this process (``_GroupKernels``)."""
    return list(_GROUP_KERNELS.values())


#: Rows of a group's first inputs kept for ``_GroupKernels.compile_sizes``.
_EXAMPLE_ROWS = 8
#: Group kernels by their static description.
_GROUP_KERNELS: dict[Any, _GroupKernels] = {}
#: Retractions by variable type.
_RETRACT: dict[_TypeSpec, Callable] = {}
#: Pushforwards of the tangent basis by variable type.
_PUSHFORWARD: dict[_TypeSpec, Callable] = {}


def _retract_kernel(ts: _TypeSpec):
    """The jitted x ⊞ δ of one variable type (rows where ``free``; others unchanged)."""
    k = _RETRACT.get(ts)
    if k is None:
        def retract(x, d, fr):
            y = retract_rows(ts.cls, x, d)
            return jax.tree.map(lambda a, b: jnp.where(fr.reshape((-1,) + (1,) * (a.ndim - 1)), a, b), y, x)

        name = _name(ts.cls)
        key = f"retract {name} {ts.treedef} {ts.dim}" if _jaxlie(ts.cls) or own_code(ts.cls) else None
        k = _RETRACT[ts] = stored_jit(retract, key)
    return k


def _host_retraction(ts: _TypeSpec):
    """x ⊞ δ of one variable type by its registered NumPy retraction (rows where ``free``;
    others unchanged), as JAX arrays like ``_retract_kernel``'s."""
    host = manifold.ops(ts.cls).host_retract

    def retract(x, d, fr):
        xh = jax.tree.map(np.asarray, x)
        y = host(xh, np.asarray(d, dtype=float))
        keep = np.asarray(fr)
        return jax.tree.map(lambda a, b: _on_device(np.where(keep.reshape((-1,) + (1,) * (a.ndim - 1)), a, b)),
                            y, xh)

    return retract


def _pushforward_kernel(ts: _TypeSpec):
    """The jitted ∂(x ⊞ δ)/∂δ|₀ of every row of one variable type (``_linearize.pushforward``)."""
    k = _PUSHFORWARD.get(ts)
    if k is None:
        def push(x):
            return pushforward(ts.cls, x)

        name = _name(ts.cls)
        key = f"pushforward {name} {ts.treedef} {ts.dim}" if _jaxlie(ts.cls) or own_code(ts.cls) else None
        k = _PUSHFORWARD[ts] = stored_jit(push, key)
    return k


def _host(vars_):
    """Per variable type: (its leaves as NumPy arrays, its tree structure)."""
    out = []
    for v in vars_:
        leaves, td = jax.tree.flatten(v)
        out.append(([np.asarray(a) for a in leaves], td))
    return out


class _Kernels:
    """The compiled functions of one static structure: one program per factor group and
    padded count, one retraction per variable type and padded rows. Each group's variables
    are gathered on the host (NumPy), so that a group's programs do not depend on the other
    groups or on the number of variables: a problem whose set of groups or variables
    changes (online mapping's window) reuses them, and the programs a run compiles are
    bounded by the groups' padded sizes (``bucket``), not by their combinations. Costs and
    validity are reduced on the host too."""

    def __init__(self, tspecs: tuple[_TypeSpec, ...], gspecs: tuple[_GroupSpec, ...]):
        self.tspecs, self.gspecs = tspecs, gspecs
        self.groups: list[Any] = []
        needs_push = [False] * len(tspecs)  # a type's pushforward is computed when read
        for spec in gspecs:
            cf = closed_form_of(spec, tspecs)
            if cf is not None:
                self.groups.append(ClosedFormGroup(spec, cf))
                for t, read in zip(spec.var_types, cf.pushforwards):
                    needs_push[t] |= read
                continue
            for t in spec.var_types:
                needs_push[t] = True
            used = tuple(dict.fromkeys(spec.var_types))  # the types, in order of first use
            local = replace(spec, var_types=tuple(used.index(t) for t in spec.var_types))
            key = (local, tuple(tspecs[t] for t in used))
            gk = _GROUP_KERNELS.get(key)
            if gk is None:
                gk = _GROUP_KERNELS[key] = _GroupKernels(*key)
            self.groups.append(gk)
        host = closed_forms_enabled()
        self.retract = [_host_retraction(ts) if host and manifold.ops(ts.cls).host_retract is not None
                        else _retract_kernel(ts) for ts in tspecs]
        self.pushforward = [None if not need else manifold.ops(ts.cls).host_pushforward
                            if host and manifold.ops(ts.cls).host_pushforward is not None
                            else _pushforward_kernel(ts) for ts, need in zip(tspecs, needs_push)]

    def _pushforwards(self, vars_):
        """Per type: the pushforwards of its rows, on the host like ``_host``'s variables
        (None for a type with non-float leaves, or whose pushforward no group reads)."""
        return [_host([push(x)])[0] if push is not None and differentiable(x) else None
                for push, x in zip(self.pushforward, vars_)]

    def _inputs(self, k, vars_host, gidx, data, push_host=None):
        """(variables of each key position of group k's factors, their pushforwards (None
        without ``push_host`` or when a position's type has none), pad mask, data)."""
        idx, mask = gidx
        var_types = self.gspecs[k].var_types
        gather = lambda host, p, t: host[t][1].unflatten([a[idx[:, p]] for a in host[t][0]])  # noqa: E731
        xs = [gather(vars_host, p, t) for p, t in enumerate(var_types)]
        Ts = None
        if push_host is not None and isinstance(self.groups[k], ClosedFormGroup):  # (rows, index): ClosedForm
            Ts = [None if push_host[t] is None else (push_host[t][1].unflatten(push_host[t][0]), idx[:, p])
                  for p, t in enumerate(var_types)]
        elif push_host is not None and all(push_host[t] is not None for t in var_types):
            Ts = [gather(push_host, p, t) for p, t in enumerate(var_types)]
        self.groups[k].note(xs, Ts, mask, data)
        return xs, Ts, mask, data

    def _cost_inputs(self, k, vars_host, gidx, data):
        xs, _, mask, data = self._inputs(k, vars_host, gidx, data)
        return xs, mask, data

    def evaluate(self, vars_, gdata, gidx):
        """(F = Σ ½ρ, validity per group)."""
        vh = _host(vars_)
        out = [gk.cost(*self._cost_inputs(k, vh, ix, d))
               for k, (gk, d, ix) in enumerate(zip(self.groups, gdata, gidx))]
        cost = float(sum(np.sum(np.asarray(hr)) for hr, _ in out))
        return cost, tuple(None if v is None else np.asarray(v) for _, v in out)

    def linearize_into(self, vars_, gdata, gidx, hslots, gslots, h: np.ndarray, g: np.ndarray):
        """Each group's per-factor JᵀJ upper triangles and Jᵀr added into ``h`` and ``g`` at
        their slots (``Problem.sparse_pattern``); (F, validity per group, all finite). With the
        compiled kernels (``geometry.native``) a closed-form group's are summed from its J and
        r in one pass, without the per-factor JᵀJ, and the others' scattered in C; without
        them, summed with ``np.bincount``."""
        lib = native.native_kernels()
        vh, th = _host(vars_), self._pushforwards(vars_)
        cost, valids, finite = 0.0, [], True
        for k, (gk, d, ix) in enumerate(zip(self.groups, gdata, gidx)):
            inputs = self._inputs(k, vh, ix, d, th)
            if lib is not None and isinstance(gk, ClosedFormGroup):
                r, J, hr, v, fin = gk.terms(*inputs)
                native.gram_scatter(lib, J, r, hslots[k], gslots[k], h, g)
            else:
                hc, gc, hr, v, fin = gk.sparse(*inputs)
                hc, gc = np.asarray(hc), np.asarray(gc)
                if lib is not None:
                    native.scatter_add(lib, hslots[k], hc, h)
                    native.scatter_add(lib, gslots[k], gc, g)
                else:
                    h += np.bincount(hslots[k], weights=hc.ravel(), minlength=len(h))
                    g += np.bincount(gslots[k], weights=gc.ravel(), minlength=len(g))
            cost += float(np.sum(np.asarray(hr)))
            valids.append(None if v is None else np.asarray(v))
            finite = finite and bool(np.all(np.asarray(fin)))
        return cost, tuple(valids), finite

    def step(self, vars_, deltas, free, gdata, gidx, valid_cur):
        """(x ⊞ δ, its cost, whether a factor valid at x is invalid there)."""
        new = tuple(r(x, d, fr) for r, x, d, fr in zip(self.retract, vars_, deltas, free))
        cost, valid_new = self.evaluate(new, gdata, gidx)
        bad = any(bool(np.any(np.asarray(vc) & ~vn)) for vc, vn in zip(valid_cur, valid_new)
                  if vc is not None)
        return new, cost, bad

    def group_terms(self, k, vars_, data, gidx):
        r, J, _, _, fin = self.groups[k].terms(
            *self._inputs(k, _host(vars_), gidx, data, self._pushforwards(vars_)))
        return r, J, fin


_KERNELS: dict[Any, _Kernels] = {}


def kernels(tspecs, gspecs) -> _Kernels:
    """The (cached) kernels of a static structure (with the closed forms on or off)."""
    key = (tspecs, gspecs, closed_forms_enabled())
    k = _KERNELS.get(key)
    if k is None:
        k = _KERNELS[key] = _Kernels(tspecs, gspecs)
    return k


# ------------------------------------------------------------------------------------------
# The problem layout
# ------------------------------------------------------------------------------------------


class Problem:
    """A factor graph with values, laid out for the solver (see the module docstring).

    ``fixed`` keys keep their values and have no tangent coordinates; so do keys that are
    in ``values`` but touched by no factor (they are left out of the problem). ``rows``
    {factor kind or variable class name: n}: pad those groups and types to at least n rows
    (the ``bucket`` minimum; 8 otherwise).

    Attributes used by the optimisers: ``n`` (tangent dimension); ``vars`` (per type,
    stacked and padded); ``linearize``, ``step``, ``cost``, ``to_values``.
    """

    def __init__(self, graph: Iterable, values: Any, fixed: Iterable[Hashable] = (),
                 check_free: bool = True, rows: dict | None = None):
        entries = graph.entries() if hasattr(graph, "entries") else list(graph)
        rows = rows or {}
        self.factors = factors = _FactorList(entries)
        fixed = set(fixed)
        for k in fixed:
            if k not in values:
                raise ValueError(f"fixed key {k!r} has no value")
        key_slot: dict[Hashable, tuple[int, int]] = {}
        type_index: dict[type, int] = {}
        t_cls: list[type] = []
        t_treedef: list[Any] = []
        t_shapes: list[Any] = []
        t_keys: list[list[Hashable]] = []
        t_leaves: list[list[list[Any]]] = []
        groups: dict[Any, _GroupBuild] = {}

        def slot(k, fi):
            """(type index, row) of key k, registered at its first use (by factor #fi)."""
            s = key_slot.get(k)
            if s is not None:
                return s
            if k not in values:
                f = factors[fi]
                raise ValueError(f"{_describe(f, fi)} refers to key {k!r}, which has no value")
            v = values[k]
            cls = type(v)
            ti = type_index.get(cls)
            leaves, treedef = jax.tree.flatten(v)
            if ti is None:
                try:
                    manifold.ops(cls)
                except TypeError as e:
                    raise TypeError(f"value for key {k!r}: {e}") from None
                ti = type_index[cls] = len(t_cls)
                t_cls.append(cls)
                t_treedef.append(treedef)
                t_shapes.append([np.shape(x) for x in leaves])
                t_keys.append([])
                t_leaves.append([])
            elif treedef != t_treedef[ti] or [np.shape(x) for x in leaves] != t_shapes[ti]:
                raise ValueError(
                    f"value for key {k!r} ({cls.__name__}) has a different layout "
                    f"from other {cls.__name__} values"
                )
            s = key_slot[k] = (ti, len(t_keys[ti]))
            t_keys[ti].append(k)
            t_leaves[ti].append(leaves)
            return s

        def add_one(f, fi):
            slots = [slot(k, fi) for k in f.keys]
            if len(set(f.keys)) != len(f.keys):
                raise ValueError(f"{_describe(f, fi)} uses a key more than once")
            leaves, treedef, shapes = f.flat_args()
            W = f.sqrt_info
            sig = (f.residual, tuple([s[0] for s in slots]), treedef, shapes,
                   None if W is None else W.shape, f.robust, f.valid)
            gb = groups.get(sig)
            if gb is None:
                gb = groups[sig] = _GroupBuild(sig, fi)
            gb.fids.append(fi)
            gb.idx.append([s[1] for s in slots])
            gb.args.append(leaves)
            gb.W.append(W)
            gb.kinds.append(f.kind)

        def add_batch(b: FactorBatch, fi: int) -> bool:
            """Lay out a batch's factors (#fi onwards) as arrays; False when they do not form
            one group (a key column of mixed types): then they go one by one."""
            n, k = len(b), len(b.key_columns)
            flat = [key for row in zip(*b.key_columns) for key in row]  # factor by factor
            for j, key in enumerate(flat):
                if key not in key_slot:
                    slot(key, fi + j // k)
            sl = np.array([key_slot[key] for key in flat], np.int64).reshape(n, k, 2)
            types = sl[:, :, 0]
            if np.any(types != types[:1]):
                return False
            rows_ = sl[:, :, 1]
            for a in range(k):
                for c in range(a + 1, k):
                    same = np.flatnonzero((types[:, a] == types[:, c]) & (rows_[:, a] == rows_[:, c]))
                    if same.size:
                        j = int(same[0])
                        raise ValueError(f"{_describe(b[j], fi + j)} uses a key more than once")
            W = b.sqrt_info
            sig = (b.residual, tuple(int(t) for t in types[0]), b.treedef, b.shapes,
                   None if W is None else W.shape[1:], b.robust, b.valid)
            gb = groups.get(sig)
            if gb is None:
                gb = groups[sig] = _GroupBuild(sig, fi)
            gb.add_batch(np.arange(fi, fi + n), rows_.astype(np.int32), b.leaves, W, b.kind)
            return True

        for e, entry in enumerate(entries):
            fi = int(factors.starts[e])
            if not isinstance(entry, FactorBatch):
                add_one(entry, fi)
            elif len(entry) and not add_batch(entry, fi):
                for j, f in enumerate(entry):
                    add_one(f, fi + j)

        # --- variable types ------------------------------------------------------------
        self.tspecs = tuple(
            _TypeSpec(c, td, manifold.tangent_dim(c)) for c, td in zip(t_cls, t_treedef)
        )
        self.type_keys = t_keys
        self.nv = [len(keys) for keys in t_keys]
        nv_pad = [bucket(nv, rows.get(c.__name__, 8)) for nv, c in zip(self.nv, t_cls)]
        self.vars = tuple(
            jax.tree.unflatten(
                td,
                [_on_device(_pad_rows(np.stack([np.asarray(lv[j]) for lv in leaves]), npad))
                 for j in range(td.num_leaves)],
            )
            for td, leaves, npad in zip(t_treedef, t_leaves, nv_pad)
        )
        self.free = [np.array([k not in fixed for k in keys], bool) for keys in t_keys]
        offsets = []
        n = 0
        for ts, fr in zip(self.tspecs, self.free):
            off = np.full(len(fr), -1, np.int64)
            off[fr] = n + ts.dim * np.arange(int(fr.sum()))
            n += ts.dim * int(fr.sum())
            offsets.append(off)
        self.offsets = offsets
        self.n = n
        if check_free and n == 0:
            raise ValueError(
                "the graph has no free variables (every key it touches is fixed)"
                if factors else "the graph has no factors"
            )
        # tangent index of each coordinate of each (padded) variable row; rows without
        # tangent coordinates point past the end of δ ∈ Rⁿ
        self.tan_idx, free_j = [], []
        for ts, off, npad in zip(self.tspecs, offsets, nv_pad):
            off = np.concatenate([off, np.full(npad - len(off), -1)])
            tan = off[:, None] + np.arange(ts.dim)
            self.tan_idx.append(np.where(off[:, None] >= 0, tan, n))
            free_j.append(_on_device(off >= 0))
        self.free_j = tuple(free_j)

        # --- factor groups -------------------------------------------------------------
        gspecs, gdata, gidx = [], [], []
        self.group_fids, self.group_cols, self.group_nf = [], [], []
        #: per group, its factors' kinds as runs [(kind, count), …] in its factors' order
        self.group_kinds: list[list[tuple[str, int]]] = []
        for gb in groups.values():
            f0 = factors[gb.first]
            m = _residual_dim(f0, gb, [values[k] for k in f0.keys],
                              [(t_cls[t], t_treedef[t], tuple(t_shapes[t])) for t in gb.sig[1]])
            if f0.dim is not None and m != f0.dim:
                raise ValueError(
                    f"{_describe(f0, gb.first)}: the residual has dimension {m}, but "
                    f"{type(f0).__name__} declares dim = {f0.dim}"
                )
            if gb.sig[4] is not None and gb.sig[4] != (m, m):
                raise ValueError(
                    f"{_describe(f0, gb.first)}: sqrt_info has shape {gb.sig[4]}, "
                    f"but the residual has dimension {m}"
                )
            var_types = gb.sig[1]
            spec = _GroupSpec(
                residual=f0.residual,
                var_types=var_types,
                dims=tuple(self.tspecs[t].dim for t in var_types),
                args_treedef=gb.sig[2],
                has_sqrt_info=gb.sig[4] is not None,
                robust=f0.robust,
                valid=f0.valid,
            )
            fids, idx, stacked, W, kinds = gb.arrays()
            nf = len(fids)
            nf_pad = bucket(nf, rows.get(f0.kind, 8))
            leaves = [_on_device(_pad_rows(a, nf_pad)) for a in stacked]
            W = _on_device(_pad_rows(W, nf_pad)) if spec.has_sqrt_info else None
            mask = np.arange(nf_pad) < nf
            # global tangent index of each local coordinate, -1 where fixed
            cols = []
            for p, t in enumerate(var_types):
                off = offsets[t][idx[:, p]]
                c = off[:, None] + np.arange(self.tspecs[t].dim)
                cols.append(np.where(off[:, None] >= 0, c, -1))
            G = np.concatenate(cols, axis=1)
            gspecs.append(spec)
            gdata.append((leaves, W))
            gidx.append((_pad_rows(idx, nf_pad), _on_device(mask)))
            self.group_fids.append(fids)
            self.group_kinds.append(kinds)
            self.group_cols.append(G)
            self.group_nf.append(nf)
        self.gspecs = tuple(gspecs)
        self.gdata = tuple(gdata)
        self.gidx = tuple(gidx)
        self.kernels = kernels(self.tspecs, self.gspecs)
        self._sparse: dict | None = None

    # --- index maps --------------------------------------------------------------------
    def _pad_index(self, a: np.ndarray, k: int, trash: int) -> np.ndarray:
        """Pad a per-factor index array of group k to its padded length with ``trash``."""
        nf_pad = self.gidx[k][0].shape[0]
        out = np.full((nf_pad,) + a.shape[1:], trash, dtype=np.int64)
        out[: len(a)] = a
        return out

    def sparse_pattern(self) -> dict:
        """The lower-triangular CSC pattern of H and the slot of every contribution
        (``_pattern.csc_pattern``: from the variables' blocks, no sort of the entries).

        nnz; indptr, indices (CSC, int32); rows, cols (of each stored entry); diag (slot of
        each diagonal entry); hslots (per group, flat (nf_pad·D(D+1)/2,): slot of each
        upper-triangle entry of each factor's JᵀJ, nnz where discarded); gslots (per group,
        flat (nf_pad·D,): tangent index of each coordinate, n where discarded).
        """
        if self._sparse is None:
            n = self.n
            offsets = np.concatenate([off[off >= 0] for off in self.offsets] + [np.zeros(0, np.int64)])
            dims = np.concatenate([np.full(int((off >= 0).sum()), ts.dim, np.int64)
                                   for off, ts in zip(self.offsets, self.tspecs)] + [np.zeros(0, np.int64)])
            groups = []
            for k, (G, spec) in enumerate(zip(self.group_cols, self.gspecs)):
                starts = np.concatenate([[0], np.cumsum(spec.dims)[:-1]]).astype(int)
                groups.append((G[:, starts].astype(np.int64), np.asarray(spec.dims), self.gidx[k][0].shape[0]))
            self._sparse = csc_pattern(n, offsets, dims, groups)
            self._sparse["gslots"] = tuple(
                self._pad_index(np.where(G >= 0, G, n), k, n).ravel()
                for k, G in enumerate(self.group_cols)
            )
        return self._sparse

    # --- evaluation --------------------------------------------------------------------
    def cost(self, vars_=None) -> float:
        """F(x) = Σ ½ρ(‖W r‖²)."""
        vars_ = self.vars if vars_ is None else vars_
        c, _ = self.kernels.evaluate(vars_, self.gdata, self.gidx)
        return float(c)

    def cost_by_kind(self, vars_=None) -> dict:
        """{factor kind: Σ ½ρ(‖W r‖²) over the factors of that kind}, in the order the kinds
        first appear among the factors. A group holds one kind unless two kinds share a
        residual function; a one-kind group's padded per-factor costs are summed as ``cost``
        sums them, so that kind's figure is, to the bit, the cost of a problem of its factors
        alone (a shared group's kinds are masked sums: equal up to round-off)."""
        vars_ = self.vars if vars_ is None else vars_
        vh = _host(vars_)
        K = self.kernels
        out: dict = {e.kind: 0 for e in self.factors.entries}
        for k, (gk, d, ix) in enumerate(zip(K.groups, self.gdata, self.gidx)):
            hr = np.asarray(gk.cost(*K._cost_inputs(k, vh, ix, d))[0])
            runs = self.group_kinds[k]
            if len({kind for kind, _ in runs}) == 1:
                out[runs[0][0]] = out[runs[0][0]] + np.sum(hr)
                continue
            kinds = [kind for kind, n in runs for _ in range(n)]
            padded = np.array(kinds + [None] * (len(hr) - len(kinds)), dtype=object)
            for kind in dict.fromkeys(padded[: self.group_nf[k]]):
                out[kind] = out[kind] + np.sum(np.where(padded == kind, hr, 0.0))
        return {kind: float(c) for kind, c in out.items()}

    def linearize(self, vars_, timings: dict | None = None):
        """(H: lower CSC data (nnz,), g = Jᵀr (n,), cost, validity per group, whether all
        residuals and Jacobians are finite). H and g are numpy arrays, summed on the host from
        the per-factor JᵀJ and Jᵀr (``_Kernels.linearize_into``: so compiled code depends on
        the counts of factors and variables only, not on n or nnz). ``timings`` accumulates
        seconds spent in "jacobians" (the terms and their sums into H and g) and "assemble"
        (the sparsity pattern, built by the first call)."""
        t0 = time.perf_counter()
        sp = self.sparse_pattern()
        t1 = time.perf_counter()
        h = np.zeros(sp["nnz"] + 1)  # the last entries: the slots of discarded terms
        g = np.zeros(self.n + 1)
        cost, valids, finite = self.kernels.linearize_into(vars_, self.gdata, self.gidx, sp["hslots"],
                                                           sp["gslots"], h, g)
        if timings is not None:
            timings["jacobians"] = timings.get("jacobians", 0.0) + time.perf_counter() - t1
            timings["assemble"] = timings.get("assemble", 0.0) + t1 - t0
        return h[:-1], g[:-1], float(cost), valids, bool(finite)

    def step(self, vars_, delta, valid_cur):
        """(regularize(x ⊞ δ), its cost, whether a factor valid before is now invalid)."""
        deltas = split_delta(np.asarray(delta, dtype=float), self.tan_idx)
        return self.kernels.step(vars_, deltas, self.free_j, self.gdata, self.gidx, valid_cur)

    def group_terms(self, k: int, vars_=None):
        """Group k: whitened residuals (nf, m), Jacobians (nf, m, D), finiteness (nf,)."""
        vars_ = self.vars if vars_ is None else vars_
        r, J, fin = self.kernels.group_terms(k, vars_, self.gdata[k], self.gidx[k])
        nf = self.group_nf[k]
        return r[:nf], J[:nf], fin[:nf]

    def diagnose(self, vars_=None, when: str = "at the initial values") -> None:
        """Raise ``ValueError`` naming the first factor with a non-finite residual or
        Jacobian; return quietly if there is none."""
        for k in range(len(self.gspecs)):
            r, J, fin = self.group_terms(k, vars_)
            fin = np.asarray(fin)
            if not fin.all():
                j = int(np.flatnonzero(~fin)[0])
                fi = int(self.group_fids[k][j])
                what = "residual" if not np.all(np.isfinite(np.asarray(r[j]))) else "Jacobian"
                raise ValueError(
                    f"{_describe(self.factors[fi], fi)} has a non-finite {what} {when} "
                    f"({int((~fin).sum())} of {len(fin)} factors of this kind)"
                )

    # --- results -----------------------------------------------------------------------
    def to_values(self, vars_, base: Any):
        """A copy of ``base`` (a Values) with this problem's variables set from ``vars_``."""
        out = base.copy()
        for ts, keys, x in zip(self.tspecs, self.type_keys, vars_):
            # read-only NumPy rows of the (immutable) results: no transfer per variable
            leaves = [np.asarray(a) for a in jax.tree.leaves(x)]
            unflatten = ts.treedef.unflatten
            for i, k in enumerate(keys):
                out._data[k] = unflatten([a[i] for a in leaves])
        return out
