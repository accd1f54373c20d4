"""A fixed-lag smoother: the window solve and the marginalisation of an online mapper, beside
the batch optimisers (GTSAM's ``BatchFixedLagSmoother`` beside its ``LevenbergMarquardtOptimizer``).

``FixedLagSmoother.optimize(graph, values, fixed)`` solves the window's graph with its LM,
holding the keys outside the window, each factor kind and variable type padded to a grid of
row counts (``padded_size``: 8, 12, 16, 24, 32, 48, … at or above the count, never below the
smoother's floor for that kind) so that a kind compiles at most two programs per doubling of
its count, and pads at most a third of its rows. ``marginalize(factors, values, fixed,
keys)`` turns the factors that leave the window into one Gaussian prior on each of ``keys``,
the ``fixed`` keys held: linearised at ``values``, the quadratic ½δᵀHδ + gᵀδ of the key's
block of the Hessian is the prior ½‖W(δ − o)‖² (WᵀW = H, o = −H⁺g) up to a constant
(``prior_from``). The blocks are exact marginals when the keys share no factor (each object's
views with the poses held): what the online mapper marginalises.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.sparse

from ._graph import NonlinearFactorGraph
from ._optimizers import LevenbergMarquardt, OptimizationResult
from ._problem import Problem

__all__ = ["FixedLagSmoother", "padded_size", "padded_sizes_above"]


def padded_size(n: int) -> int:
    """The smallest of 2ᵏ and 3·2ᵏ⁻¹ (k ≥ 3: 8, 12, 16, 24, 32, 48, …) that is ≥ max(n, 8)."""
    n = max(int(n), 8)
    p = 1 << int(np.ceil(np.log2(n)))
    return p * 3 // 4 if p >= 16 and p * 3 // 4 >= n else p


def padded_sizes_above(n: int, factor: int) -> list:
    """The sizes of ``padded_size``'s grid above n, up to ``factor``·n."""
    out, k = [], padded_size(n + 1)
    while k <= factor * n:
        out.append(k)
        k = padded_size(k + 1)
    return out


@dataclass(frozen=True)
class FixedLagSmoother:
    """The window solve (``optimizer``, LM) and the marginalisation of a fixed-lag problem
    (module docstring); ``floor(name)``: the fewest rows a factor kind or variable type
    (``type(value).__name__``) is padded to."""

    optimizer: LevenbergMarquardt
    floor: Callable[[str], int]

    def rows(self, factors, values) -> dict:
        """The rows each factor kind and variable type of ``factors`` and ``values`` is padded
        to: ``padded_size`` of its count, at least its floor."""
        counts = Counter(f.kind for f in factors)
        counts.update(type(values[k]).__name__ for k in values)
        return {name: padded_size(max(c, self.floor(name))) for name, c in counts.items()}

    def optimize(self, graph: NonlinearFactorGraph, values, fixed) -> OptimizationResult:
        """The window's graph solved from ``values`` with the ``fixed`` keys held."""
        return self.optimizer.optimize(graph, values, fixed, rows=self.rows(list(graph), values))

    def marginalize(self, factors, values, fixed, keys) -> tuple[dict, bool]:
        """({key: (H, g)} the block of each of ``keys`` in the Hessian and gradient of
        ``factors`` linearised at ``values`` with the ``fixed`` keys held, whether every
        entry was finite); ``prior_from`` makes each a prior."""
        problem = Problem(NonlinearFactorGraph(factors), values, fixed, rows=self.rows(factors, values))
        h, g, _, _, finite = problem.linearize(problem.vars)
        sp = problem.sparse_pattern()
        H = scipy.sparse.csc_matrix((h, sp["indices"], sp["indptr"]), shape=(problem.n, problem.n)).toarray()
        H = H + H.T - np.diag(np.diag(H))
        where = {key: (ti, j) for ti, tkeys in enumerate(problem.type_keys) for j, key in enumerate(tkeys)}
        out = {}
        for key in keys:
            ti, j = where[key]
            o = int(problem.offsets[ti][j])
            d = problem.tspecs[ti].dim
            out[key] = (H[o:o + d, o:o + d], g[o:o + d])
        return out, bool(finite)

    @staticmethod
    def prior_from(H, g):
        """(offset o = −H⁺g, W with WᵀW = H) of the quadratic ½δᵀHδ + gᵀδ, or None."""
        H = 0.5 * (H + H.T)
        if not (np.all(np.isfinite(H)) and np.all(np.isfinite(g))):
            return None
        w, V = np.linalg.eigh(H)
        keep = w > 1e-10 * max(w[-1], 1e-300)
        w = np.where(keep, w, 0.0)
        inv = np.where(keep, 1.0 / np.where(keep, w, 1.0), 0.0)
        return -(V * inv) @ (V.T @ g), np.sqrt(w)[:, None] * V.T
