"""Linear solvers for the damped normal equations (H + λD) δ = −g.

H is given as the data of its lower triangle in a fixed CSC pattern (``Problem.sparse_pattern``).

- ``cholmod``: CHOLMOD (scikit-sparse) supernodal Cholesky; the symbolic analysis (fill-reducing
  ordering) is done once per structure, each solve refactors numerically in place.
- ``scipy``:   SuperLU on the full symmetric matrix (fallback when scikit-sparse is missing).
- ``dense``:   LAPACK Cholesky of the dense matrix (small problems).

``solve`` returns None when the matrix is not positive definite (or the solve fails).
"""

from __future__ import annotations

import warnings

import numpy as np
import scipy.linalg
import scipy.sparse
import scipy.sparse.linalg

try:  # pragma: no cover - availability depends on the environment
    from sksparse import cholmod as _cholmod
except Exception:  # noqa: BLE001
    _cholmod = None

__all__ = ["HAVE_CHOLMOD", "make_linear_solver", "DENSE_THRESHOLD"]

HAVE_CHOLMOD = _cholmod is not None
#: ``linear_solver="auto"`` uses the dense solver below this many tangent dimensions.
DENSE_THRESHOLD = 500


class DenseSolver:
    name = "dense"

    def __init__(self, pattern, n):
        self.n = n
        self.rows, self.cols = pattern["rows"], pattern["cols"]

    def solve(self, data, rhs):
        H = np.zeros((self.n, self.n))
        H[self.rows, self.cols] = data
        H[self.cols, self.rows] = data
        try:
            c = scipy.linalg.cho_factor(H, lower=True, check_finite=False)
        except (np.linalg.LinAlgError, ValueError):
            return None
        x = scipy.linalg.cho_solve(c, rhs, check_finite=False)
        return x if np.all(np.isfinite(x)) else None


class ScipySolver:
    name = "scipy"

    def __init__(self, pattern, n):
        self.n = n
        self.pattern = pattern
        self.diag = pattern["diag"]

    def solve(self, data, rhs):
        p = self.pattern
        L = scipy.sparse.csc_matrix((data, p["indices"], p["indptr"]), shape=(self.n, self.n))
        A = (L + L.T - scipy.sparse.diags(data[self.diag])).tocsc()
        try:
            x = scipy.sparse.linalg.splu(A).solve(rhs)
        except RuntimeError:
            return None
        return x if np.all(np.isfinite(x)) else None


class CholmodSolver:
    name = "cholmod"

    def __init__(self, pattern, n):
        if _cholmod is None:
            raise ImportError("linear_solver='cholmod' needs scikit-sparse (sksparse.cholmod)")
        self.n = n
        self.A = scipy.sparse.csc_matrix(
            (np.ones(pattern["nnz"]), pattern["indices"], pattern["indptr"]), shape=(n, n)
        )
        self.A.has_sorted_indices = True
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            self.factor = _cholmod.analyze(self.A, mode="supernodal")

    def solve(self, data, rhs):
        self.A.data = np.ascontiguousarray(data, dtype=np.float64)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("error", _cholmod.CholmodWarning)
                self.factor.cholesky_inplace(self.A)
                x = self.factor(rhs)
        except (_cholmod.CholmodError, _cholmod.CholmodWarning):
            return None
        return x if np.all(np.isfinite(x)) else None


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


def make_linear_solver(kind: str, pattern, n: int):
    return {"dense": DenseSolver, "scipy": ScipySolver, "cholmod": CholmodSolver}[kind](
        pattern, n
    )
