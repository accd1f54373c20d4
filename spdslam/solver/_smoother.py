"""A fixed-lag smoother beside the batch optimisers, as GTSAM's ``BatchFixedLagSmoother``
sits beside its ``LevenbergMarquardtOptimizer``: it owns the factors that are waiting to
leave the window and the priors they leave behind, and ``update`` decides what leaves.

Time is the frame index: the pose ``X(i)`` is frame i's. ``add(key, [(i, factor)])`` keeps a
variable's measurement factors (an object's views, each with its frame) until they leave the
window. ``update(now, factors, extra, values_of, accept, hold)``: the window is the last ``lag`` of
the ``now`` frames (``start = max(0, now − lag)``); the graph is ``factors`` (the caller's
factors of this update, e.g. the odometry of the window), then, for each variable with kept
factors (``active``, by key), its kept factors, ``extra(key)`` (factors made afresh, e.g. its
shape and orientation) and its prior; poses before ``start`` are held (conditioned, not
marginalised), and so is ``X(start − 1)`` (the odometry's anchor), and every pose with
``hold``. It is solved by LM (``optimize``) from ``values_of(keys)`` and the solution handed
to ``accept`` (the caller keeps the estimates); then the kept factors of frames before
``start`` leave: with the poses held, their Gauss–Newton quadratic in the variable (with its
previous prior), linearised at ``values_of`` (the solution), becomes the variable's new prior
(``marginalize``, ``prior_from``: a ``LandmarkPriorFactor``, mean x̂ ⊞ (−H⁺g), information
H; the variables are landmarks) — exact marginals, since such a variable shares no factor
with another once the poses are held.

Each factor kind and variable type is padded to a grid of row counts (``padded_size``: 8, 12,
16, 24, 32, 48, … at or above the count, never below the smoother's ``floor`` for that kind)
so that a kind compiles at most two programs per doubling of its count, and pads at most a
third of its rows.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import Callable, Hashable

import numpy as np
import scipy.sparse

from ..factors import LandmarkPriorFactor
from ._graph import NonlinearFactorGraph
from ._keys import X
from ._optimizers import LevenbergMarquardt, OptimizationResult
from ._problem import Problem
from ._values import Values

__all__ = ["FixedLagSmoother", "SmootherUpdate", "padded_size", "padded_sizes_above"]


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
class SmootherUpdate:
    """What ``FixedLagSmoother.update`` did: the window's first frame, the factors and free
    variables of the problem it solved (0 when none), LM's iterations, the solved values of
    the window's variables (None when nothing was solved), and the variables whose leaving
    factors could not be summarised (non-finite: dropped, no prior)."""

    start: int
    factors: int = 0
    variables: int = 0
    iterations: int = 0
    values: Values | None = None
    dropped: list = field(default_factory=list)


class FixedLagSmoother:
    """The window solve and the marginalisation of a fixed-lag problem (module docstring):
    ``optimizer`` (LM), ``floor(name)`` the fewest rows a factor kind or variable type
    (``type(value).__name__``) is padded to, ``lag`` the frames whose poses are free,
    ``prepare(factors)`` applied to each problem's factors before it is solved (robust
    kernels by type; default none). ``last``: (graph, values, fixed) of the last problem
    solved (its marginal covariances)."""

    def __init__(self, optimizer: LevenbergMarquardt, floor: Callable[[str], int], lag: int = 1,
                 prepare: Callable[[list], list] | None = None):
        self.optimizer, self.floor, self.lag = optimizer, floor, int(lag)
        self.prepare = prepare or (lambda factors: factors)
        self._kept: dict = {}  # key -> [(frame, factor)] not yet marginalised
        #: {key: LandmarkPriorFactor}: what the factors that left the window say of each variable
        self.priors: dict = {}
        self.last: tuple | None = None

    def add(self, key: Hashable, stamped) -> None:
        """Keep ``stamped`` [(frame, factor)], factors of the variable ``key`` (and of held
        poses), until their frame leaves the window."""
        stamped = list(stamped)
        if stamped:
            self._kept.setdefault(key, []).extend(stamped)

    def has_kept(self, key: Hashable) -> bool:
        """Whether ``key`` has factors in the window (it is free in the next update)."""
        return bool(self._kept.get(key))

    def kept(self, key: Hashable) -> list:
        """[(frame, factor)] of ``key`` still in the window."""
        return list(self._kept.get(key, []))

    def active(self) -> list:
        """The variables with factors in the window, by key."""
        return sorted((k for k, v in self._kept.items() if v), key=_order)

    def merge(self, keep: Hashable, drop: Hashable) -> None:
        """Variable ``drop`` is ``keep``: its kept factors move to ``keep`` (re-keyed), its
        prior goes."""
        moved = [(f, fac.replace(keys=[keep if k == drop else k for k in fac.keys]))
                 for f, fac in self._kept.pop(drop, [])]
        self.add(keep, moved)
        self.priors.pop(drop, None)

    def update(self, now: int, factors: list, extra: Callable[[Hashable], list],
               values_of: Callable[[set], Values], accept: Callable[[Values], None],
               hold: bool = False) -> SmootherUpdate:
        """Solve the window of the first ``now`` frames from ``values_of(keys)``, hand the
        solution to ``accept`` (the caller's estimates), and marginalise what leaves the
        window, linearised at ``values_of`` again (module docstring)."""
        start = max(0, int(now) - self.lag)
        factors = list(factors)
        for key in self.active():
            factors += [fac for _, fac in self._kept[key]] + list(extra(key))
            factors += [self.priors[key]] if key in self.priors else []
        factors = self.prepare(factors)
        if not factors:  # nothing to solve (poses held, no variable with new factors)
            return SmootherUpdate(start, dropped=self._marginalise(start, values_of))
        graph = NonlinearFactorGraph(factors)
        keys = {key for f in factors for key in f.keys}
        fixed = [key for key in keys if _is_pose(key) and (key.index < start or hold)]
        if start > 0:
            fixed.append(X(start - 1))
        fixed = sorted(set(fixed) & keys, key=lambda k: k.index)
        res = self.optimize(graph, values_of(keys), fixed)
        accept(res.values)
        self.last = (graph, res.values, fixed)
        return SmootherUpdate(start, len(factors), len(keys) - len(fixed), res.iterations, res.values,
                              self._marginalise(start, values_of))

    def _marginalise(self, start: int, values_of: Callable[[set], Values]) -> list:
        old = {}
        for key in self.active():
            items = [v for v in self._kept[key] if v[0] < start]
            if items:
                old[key] = items
        if not old:
            return []
        factors: list = []
        for key, items in old.items():
            factors += [fac for _, fac in items] + ([self.priors[key]] if key in self.priors else [])
        factors = self.prepare(factors)
        values = values_of({key for f in factors for key in f.keys})
        poses = [key for key in values if _is_pose(key)]
        blocks, finite = self.marginalize(factors, values, poses, list(old))
        dropped = []
        for key in old:
            prior = FixedLagSmoother.prior_from(*blocks[key]) if finite else None
            if prior is None:
                dropped.append(key)
            else:
                self.priors[key] = LandmarkPriorFactor(key, values[key], prior[0], sqrt_info=prior[1])
            self._kept[key] = [v for v in self._kept[key] if v[0] >= start]
        return dropped

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


def _is_pose(key) -> bool:
    return getattr(key, "chr", None) == "x"


def _order(key):
    return (getattr(key, "chr", ""), getattr(key, "index", 0))
