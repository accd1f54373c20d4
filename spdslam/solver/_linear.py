"""Linear solvers for the damped normal equations (H + λD) δ = −g.

H is given as the data of its lower triangle in a fixed CSC pattern (``Problem.sparse_pattern``).

- ``cholmod``: CHOLMOD (scikit-sparse) Cholesky; the symbolic analysis (fill-reducing
  ordering) is done once per structure, each solve refactors numerically in place. ``mode``
  "supernodal" (BLAS on dense supernodes), "simplicial" (column by column) or "auto"
  (CHOLMOD's choice by flops per non-zero); ``ordering`` one of CHOLMOD's: "default" (AMD,
  METIS also tried when AMD's fill is high), "amd", "metis", "nesdis", "colamd", "natural"
  (the layout's order: variable types by first appearance), "best".
- ``scipy``:   SuperLU on the full symmetric matrix (fallback when scikit-sparse is missing).
- ``dense``:   LAPACK Cholesky of the dense matrix (small problems).

``solve`` returns None when the matrix is not positive definite (or the solve fails).
"""

from __future__ import annotations

import time
import warnings

import numpy as np
import scipy.linalg
import scipy.sparse
import scipy.sparse.linalg

try:  # pragma: no cover - availability depends on the environment
    from sksparse import cholmod as _cholmod
except Exception:  # noqa: BLE001
    _cholmod = None

__all__ = ["HAVE_CHOLMOD", "make_linear_solver", "DENSE_THRESHOLD", "CHOLMOD_MODES",
           "CHOLMOD_ORDERINGS"]

CHOLMOD_MODES = ("supernodal", "simplicial", "auto")
CHOLMOD_ORDERINGS = ("default", "amd", "metis", "nesdis", "colamd", "natural", "best")

HAVE_CHOLMOD = _cholmod is not None
#: ``linear_solver="auto"`` uses the dense solver below this many tangent dimensions.
DENSE_THRESHOLD = 500


class _Solver:
    name = ""

    def __init__(self):
        #: accumulated seconds: "factorize" (incl. assembly of the matrix) and "backsolve"
        self.timings = {"factorize": 0.0, "backsolve": 0.0}

    def solve(self, data, rhs):
        """x with A x = rhs, A the symmetric matrix whose lower triangle is ``data``;
        None if A is not positive definite (or the solve fails)."""
        t0 = time.perf_counter()
        f = self._factorize(data)
        t1 = time.perf_counter()
        self.timings["factorize"] += t1 - t0
        if f is None:
            return None
        x = self._backsolve(f, rhs)
        self.timings["backsolve"] += time.perf_counter() - t1
        return x if x is not None and np.all(np.isfinite(x)) else None


class DenseSolver(_Solver):
    name = "dense"

    def __init__(self, pattern, n):
        super().__init__()
        self.n = n
        self.rows, self.cols = pattern["rows"], pattern["cols"]

    def _factorize(self, data):
        H = np.zeros((self.n, self.n))
        H[self.rows, self.cols] = data
        H[self.cols, self.rows] = data
        try:
            return scipy.linalg.cho_factor(H, lower=True, check_finite=False)
        except (np.linalg.LinAlgError, ValueError):
            return None

    def _backsolve(self, c, rhs):
        return scipy.linalg.cho_solve(c, rhs, check_finite=False)


class ScipySolver(_Solver):
    name = "scipy"

    def __init__(self, pattern, n):
        super().__init__()
        self.n = n
        self.pattern = pattern
        self.diag = pattern["diag"]

    def _factorize(self, data):
        p = self.pattern
        L = scipy.sparse.csc_matrix((data, p["indices"], p["indptr"]), shape=(self.n, self.n))
        A = (L + L.T - scipy.sparse.diags(data[self.diag])).tocsc()
        try:
            return scipy.sparse.linalg.splu(A)
        except RuntimeError:
            return None

    def _backsolve(self, lu, rhs):
        return lu.solve(rhs)


class CholmodSolver(_Solver):
    name = "cholmod"

    def __init__(self, pattern, n, mode: str = "supernodal", ordering: str = "default"):
        super().__init__()
        if _cholmod is None:
            raise ImportError("linear_solver='cholmod' needs scikit-sparse (sksparse.cholmod)")
        check_cholmod_options(mode, ordering)
        self.n = n
        self.A = scipy.sparse.csc_matrix(
            (np.ones(pattern["nnz"]), pattern["indices"], pattern["indptr"]), shape=(n, n)
        )
        self.A.has_sorted_indices = True
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            self.factor = _cholmod.analyze(self.A, mode=mode, ordering_method=ordering)

    def _factorize(self, data):
        self.A.data = np.ascontiguousarray(data, dtype=np.float64)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("error", _cholmod.CholmodWarning)
                self.factor.cholesky_inplace(self.A)
        except (_cholmod.CholmodError, _cholmod.CholmodWarning):
            return None
        return self.factor

    def _backsolve(self, factor, rhs):
        try:
            return factor(rhs)
        except (_cholmod.CholmodError, _cholmod.CholmodWarning):
            return None


def check_cholmod_options(mode: str, ordering: str) -> None:
    if mode not in CHOLMOD_MODES:
        raise ValueError(f"cholmod_mode must be one of {', '.join(CHOLMOD_MODES)}, got {mode!r}")
    if ordering not in CHOLMOD_ORDERINGS:
        raise ValueError(
            f"cholmod_ordering must be one of {', '.join(CHOLMOD_ORDERINGS)}, got {ordering!r}"
        )


def resolve_linear_solver(kind: str, n: int, dense_threshold: int = DENSE_THRESHOLD) -> str:
    if kind == "auto":
        if n < dense_threshold:
            return "dense"
        return "cholmod" if HAVE_CHOLMOD else "scipy"
    if kind not in ("cholmod", "scipy", "dense"):
        raise ValueError(
            f"linear_solver must be 'auto', 'cholmod', 'scipy' or 'dense', got {kind!r}"
        )
    if kind == "cholmod" and not HAVE_CHOLMOD:
        raise ImportError("linear_solver='cholmod' needs scikit-sparse (sksparse.cholmod)")
    return kind


def make_linear_solver(kind: str, pattern, n: int, cholmod_mode: str = "supernodal",
                       cholmod_ordering: str = "default"):
    """The solver ``kind`` for the CSC ``pattern``; the CHOLMOD options apply to "cholmod"."""
    if kind == "cholmod":
        return CholmodSolver(pattern, n, cholmod_mode, cholmod_ordering)
    return {"dense": DenseSolver, "scipy": ScipySolver}[kind](pattern, n)
