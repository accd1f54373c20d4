"""Marginal covariances at a solution (GTSAM's ``Marginals``).

With H = JᵀJ the Gauss–Newton Hessian of the whitened residuals at ``values`` (robust
weights included), the marginal covariance of a variable is the block of H⁻¹ on its
tangent coordinates: Σ_k = E_kᵀ H⁻¹ E_k, in the variable's own chart (x ⊞ δ). All
requested blocks come from one factorisation and one multi-column solve.
"""

from __future__ import annotations

from typing import Any, Hashable, Iterable

import numpy as np

from ._linear import make_linear_solver, resolve_linear_solver
from ._problem import Problem

__all__ = ["marginal_covariances", "covariance_blocks"]


def marginal_covariances(graph: Iterable, values: Any, keys: Iterable[Hashable],
                         linear_solver: str = "auto", fixed: Iterable[Hashable] = ()) -> dict:
    """{key: Σ (d × d)} for each of ``keys`` (module docstring); a key whose block is not
    determined (H singular) gets a matrix of ``inf``. ``ValueError`` for a key that is not
    a free variable of the graph. ``fixed`` keys are held (conditioned on), as in
    ``optimize``."""
    problem = Problem(graph, values, fixed)
    keys = list(keys)
    _columns(problem, keys)  # every key free, before the linearisation
    if not keys:
        return {}
    H, _, _, _, finite = problem.linearize(problem.vars)
    kind = resolve_linear_solver(linear_solver, problem.n)
    solver = make_linear_solver(kind, problem.sparse_pattern(), problem.n)
    return covariance_blocks(problem, H, finite, solver, keys)


def _columns(problem: Problem, keys: list) -> list:
    """The tangent columns of each key (``ValueError`` for a key that is not free)."""
    where = {}
    for ti, tkeys in enumerate(problem.type_keys):
        for j, k in enumerate(tkeys):
            where[k] = (ti, j)
    cols = []
    for k in keys:
        if k not in where or problem.offsets[where[k][0]][where[k][1]] < 0:
            raise ValueError(f"key {k!r} is not a free variable of the graph")
        ti, j = where[k]
        off = int(problem.offsets[ti][j])
        cols.append(np.arange(off, off + problem.tspecs[ti].dim))
    return cols


def covariance_blocks(problem: Problem, H, finite: bool, solver, keys) -> dict:
    """{key: Σ} from H (lower CSC data of ``problem``'s pattern) at a solution: one
    factorisation of H by ``solver`` (made for that pattern) and one multi-column solve
    (``marginal_covariances``; the optimisers' results reuse their last linearisation)."""
    keys = list(keys)
    cols = _columns(problem, keys)
    out: dict = {}
    if not keys:
        return out
    idx = np.concatenate(cols)
    E = np.zeros((problem.n, idx.size))
    E[idx, np.arange(idx.size)] = 1.0
    X = solver.solve(H, E) if finite else None  # None: H not positive definite
    start = 0
    for k, c in zip(keys, cols):
        d = c.size
        if X is None:
            out[k] = np.full((d, d), np.inf)
        else:
            block = np.asarray(X[c, start:start + d])
            out[k] = 0.5 * (block + block.T)
        start += d
    return out
