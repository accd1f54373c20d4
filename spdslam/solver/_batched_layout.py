"""The batched solver's problem layout: a template problem split into free and fixed
stacks and sub-groups of static pattern, and the per-problem functions (cost,
linearisation, retraction) of that layout, unjitted (``_batched_loop`` vmaps and jits them).

Variables of one type are split into a *free* stack (the loop state) and a *fixed* stack
(plain data: never retracted, never differentiated). Factors of one group (same residual,
variable types, data layout, ...; see ``_problem``) are split further by which of their key
positions are free, so that every sub-group has a static free/fixed pattern. A factor is
linearised as

    J = ∂r(x ⊞ δ)/∂δ = ∂r/∂x · ∂(x ⊞ δ)/∂δ|₀,

the pushforward ∂(x ⊞ δ)/∂δ|₀ of the basis vectors being computed once per free variable
(not once per factor) and pushed through the residual with ``jax.jvp`` (``_linearize``). A key position that
every factor of a sub-group shares (one landmark seen by all cameras) is not broadcast: the
residual is vmapped over the factors with that argument unbatched. H = JᵀJ and g = Jᵀr are
formed from the dense (rows × n) Jacobian for small n (one matmul), else by scattering the
per-factor JᵀJ blocks.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Hashable

import jax
import jax.numpy as jnp
import numpy as np

from ._linearize import finish, jvp_jacobian, pushforward, retract_rows, tangent_directions, whitened
from ._problem import Problem

__all__ = ["DENSE_JACOBIAN_MAX_N", "BatchedKernel", "BatchedLayout"]

#: H and g come from the dense Jacobian (rows × n) when n ≤ this, else from scattered
#: per-factor JᵀJ blocks.
DENSE_JACOBIAN_MAX_N = 48


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


class BatchedLayout:
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


class BatchedKernel:
    """The per-problem functions of one static structure (unjitted; traced by drivers)."""

    def __init__(self, layout: BatchedLayout):
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
                primals = tuple(xs_i[p] for p in free_pos)
                r, J = jvp_jacobian(res, primals, tangent_directions(tans_i, dims))
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
            pushforward(ts.cls, x) if nf else None
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

