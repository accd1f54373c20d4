"""Linear solvers for the damped normal equations (H + λD) δ = −g.

H is given as the data of its lower triangle in a fixed CSC pattern (``Problem.sparse_pattern``).

- ``cholmod``: CHOLMOD (scikit-sparse) Cholesky; the symbolic analysis (fill-reducing
  ordering) is done once per structure, each solve refactors numerically in place. ``mode``
  "supernodal" (BLAS on dense supernodes), "simplicial" (column by column) or "auto"
  (CHOLMOD's choice by flops per non-zero); ``ordering`` one of CHOLMOD's: "default" (AMD,
  METIS also tried when AMD's fill is high), "amd", "metis", "nesdis", "colamd", "natural"
  (the layout's order: variable types by first appearance), "best". ``openmp`` and
  ``blas_threads``: threads of CHOLMOD's OpenMP regions and of its BLAS (``cholmod_threads``;
  default one each).
- ``cvxopt``:  the CHOLMOD that cvxopt's wheels bundle (a plain ``pip install`` dependency):
  the same supernodal Cholesky, symbolic analysis once per structure, values written into
  the fixed pattern each time; supernodal mode and the orderings "default"/"amd" (AMD) and
  "natural" only, no thread options (its BLAS is serial). The fallback when scikit-sparse is missing.
- ``scipy``:   SuperLU on the full symmetric matrix (last resort: neither is importable).
- ``dense``:   LAPACK Cholesky of the dense matrix (small problems).

``solve`` returns None when the matrix is not positive definite (or the solve fails).
"""

from __future__ import annotations

import contextlib
import ctypes
import os
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

try:  # pragma: no cover - a default dependency, but its wheel may be missing on a platform
    import cvxopt as _cvxopt
    from cvxopt import cholmod as _cvx_cholmod
except Exception:  # noqa: BLE001
    _cvxopt = _cvx_cholmod = None

__all__ = ["HAVE_CHOLMOD", "HAVE_CVXOPT", "SPARSE_SOLVERS", "make_linear_solver", "DENSE_THRESHOLD", "CHOLMOD_MODES",
           "CHOLMOD_ORDERINGS", "CVXOPT_ORDERINGS", "cholmod_threads", "default_sparse_solver", "HAVE_OPENMP_CONTROL",
           "HAVE_BLAS_CONTROL"]

CHOLMOD_MODES = ("supernodal", "simplicial", "auto")
CHOLMOD_ORDERINGS = ("default", "amd", "metis", "nesdis", "colamd", "natural", "best")

HAVE_CHOLMOD = _cholmod is not None
HAVE_CVXOPT = _cvx_cholmod is not None
#: sparse solvers in the order ``linear_solver="auto"`` tries them
SPARSE_SOLVERS = ("cholmod", "cvxopt", "scipy")
#: the orderings the cvxopt solver can apply (its CHOLMOD is built without METIS)
CVXOPT_ORDERINGS = ("default", "amd", "natural")


def _loaded_library(names, symbols):
    """The first of the shared libraries ``names`` that this process has already loaded and
    that exports ``symbols`` (each ``(name, restype, argtypes)``), else None; loads nothing."""
    if _cholmod is None or not hasattr(os, "RTLD_NOLOAD"):
        return None
    for name in names:
        try:
            lib = ctypes.CDLL(name, mode=os.RTLD_NOLOAD)
            for sym, restype, argtypes in symbols:
                f = getattr(lib, sym)
                f.restype, f.argtypes = restype, argtypes
        except (OSError, AttributeError):
            continue
        return lib
    return None


# GNU OpenMP and OpenBLAS as linked by CHOLMOD (Debian: libcholmod3 -> libgomp, libblas.so.3
# -> OpenBLAS); numpy's own OpenBLAS exports prefixed names and is not touched.
_gomp = _loaded_library(["libgomp.so.1"], [("omp_get_max_active_levels", ctypes.c_int, []),
                                           ("omp_set_max_active_levels", None, [ctypes.c_int])])
_openblas = _loaded_library(["libblas.so.3", "libopenblas.so.0"],
                            [("openblas_get_num_threads", ctypes.c_int, []),
                             ("openblas_set_num_threads", None, [ctypes.c_int])])
#: whether ``cholmod_threads`` can act on OpenMP / on the BLAS
HAVE_OPENMP_CONTROL = _gomp is not None
HAVE_BLAS_CONTROL = _openblas is not None


@contextlib.contextmanager
def cholmod_threads(openmp: bool = False, blas: int | None = 1):
    """Thread use of CHOLMOD calls made inside this block; restored on exit. Both settings
    are the libraries' process-wide ones (GNU OpenMP's max-active-levels is a global in
    GCC 12), so other OpenMP or OpenBLAS work running in other threads meanwhile sees them.

    - ``openmp=False``: OpenMP's max-active-levels is set to 0, so parallel regions run on
      one thread. CHOLMOD 3 (SuiteSparse 5, Debian 12) opens a region with a compiled-in team
      (``num_threads(4)``, which OMP_NUM_THREADS cannot lower) around the small scatter loop
      of every supernode's update, and the fork/join costs more than the loop.
    - ``blas``: OpenBLAS threads for the dense supernode kernels (None: unchanged). Its
      workers wait by spinning, and so do JAX's between the jitted calls of an LM iteration,
      so on few cores the two pools take turns on the same cores.

    Each part is a no-op when CHOLMOD is not linked against GNU OpenMP / OpenBLAS.
    ``benchmarks/sphere2500.py --cholmod-openmp --blas-threads N`` measures the choices.
    """
    levels = threads = None
    if not openmp and _gomp is not None:
        levels = _gomp.omp_get_max_active_levels()
        _gomp.omp_set_max_active_levels(0)
    if blas is not None and _openblas is not None:
        threads = _openblas.openblas_get_num_threads()
        _openblas.openblas_set_num_threads(int(blas))
    try:
        yield
    finally:
        if threads is not None:
            _openblas.openblas_set_num_threads(threads)
        if levels is not None:
            _gomp.omp_set_max_active_levels(levels)


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

    def __init__(self, pattern, n, mode: str = "supernodal", ordering: str = "default",
                 openmp: bool = False, blas_threads: int | None = 1):
        super().__init__()
        if blas_threads is not None and int(blas_threads) < 1:
            raise ValueError(f"cholmod_blas_threads must be >= 1 or None, got {blas_threads!r}")
        self._threads = lambda: cholmod_threads(openmp, blas_threads)
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
            with warnings.catch_warnings(), self._threads():
                warnings.simplefilter("error", _cholmod.CholmodWarning)
                self.factor.cholesky_inplace(self.A)
        except (_cholmod.CholmodError, _cholmod.CholmodWarning):
            return None
        return self.factor

    def _backsolve(self, factor, rhs):
        try:
            with self._threads():
                return factor(rhs)
        except (_cholmod.CholmodError, _cholmod.CholmodWarning):
            return None


class CvxoptSolver(_Solver):
    """CHOLMOD through cvxopt: ``cholmod.symbolic`` once, ``cholmod.numeric`` per solve on a
    ``spmatrix`` whose values are replaced in place (``A.V = …``, same pattern). Its storage
    order is read once (values 0, 1, … written and read back), so the pattern need not be
    sorted. Supernodal LLᵀ only: cvxopt's simplicial mode is an LDLᵀ that accepts D ≤ 0, so
    it could not tell that H is not positive definite."""

    name = "cvxopt"

    def __init__(self, pattern, n, mode: str = "supernodal", ordering: str = "default"):
        super().__init__()
        if _cvx_cholmod is None:
            raise ImportError("linear_solver='cvxopt' needs cvxopt (pip install cvxopt)")
        check_cholmod_options(mode, ordering)
        if mode != "supernodal":
            raise ValueError(
                f"cholmod_mode {mode!r} needs scikit-sparse; the cvxopt solver factorises "
                "supernodally only (its simplicial LDLᵀ does not detect an indefinite H)"
            )
        if ordering not in CVXOPT_ORDERINGS:
            raise ValueError(
                f"cholmod_ordering {ordering!r} needs scikit-sparse; the cvxopt solver takes "
                f"{', '.join(CVXOPT_ORDERINGS)}"
            )
        self.n = n
        indptr = np.asarray(pattern["indptr"], dtype=np.int64)
        rows = np.asarray(pattern["indices"], dtype=np.int64)
        cols = np.repeat(np.arange(n, dtype=np.int64), np.diff(indptr))
        nnz = rows.size
        self.A = _cvxopt.spmatrix(_cvxopt.matrix(np.arange(nnz, dtype=np.float64)),
                                  _cvxopt.matrix(rows), _cvxopt.matrix(cols), (n, n))
        order = np.asarray(self.A.V, dtype=np.float64).ravel().astype(np.int64)
        self._order = None if np.array_equal(order, np.arange(nnz)) else order
        perm = {} if ordering != "natural" else {"p": _cvxopt.matrix(np.arange(n, dtype=np.int64))}
        with self._options():
            self.factor = _cvx_cholmod.symbolic(self.A, uplo="L", **perm)

    @contextlib.contextmanager
    def _options(self):
        """cvxopt's ``cholmod.options`` is module-global: set for the call, then restored."""
        opts = _cvx_cholmod.options
        saved = dict(opts)
        opts["supernodal"] = 2
        try:
            yield
        finally:
            opts.clear()
            opts.update(saved)

    def _factorize(self, data):
        data = np.ascontiguousarray(data, dtype=np.float64)
        self.A.V = _cvxopt.matrix(data if self._order is None else data[self._order])
        try:
            with self._options():
                _cvx_cholmod.numeric(self.A, self.factor)
        except (ArithmeticError, ValueError):
            return None
        return self.factor

    def _backsolve(self, factor, rhs):
        rhs = np.asarray(rhs, dtype=np.float64)
        B = _cvxopt.matrix(rhs.reshape(self.n, -1))
        try:
            _cvx_cholmod.solve(factor, B)
        except (ArithmeticError, ValueError):
            return None
        return np.asarray(B).reshape(rhs.shape)


def check_cholmod_options(mode: str, ordering: str) -> None:
    if mode not in CHOLMOD_MODES:
        raise ValueError(f"cholmod_mode must be one of {', '.join(CHOLMOD_MODES)}, got {mode!r}")
    if ordering not in CHOLMOD_ORDERINGS:
        raise ValueError(
            f"cholmod_ordering must be one of {', '.join(CHOLMOD_ORDERINGS)}, got {ordering!r}"
        )


def resolve_linear_solver(kind: str, n: int, dense_threshold: int = DENSE_THRESHOLD) -> str:
    """The solver that ``kind`` means here: "auto" is dense below ``dense_threshold`` tangent
    dimensions, else the first importable of ``SPARSE_SOLVERS``."""
    if kind == "auto":
        if n < dense_threshold:
            return "dense"
        kind = default_sparse_solver()
        if kind == "scipy":
            warnings.warn("neither scikit-sparse nor cvxopt imports: the sparse normal equations "
                          "are solved by scipy's SuperLU, 8-20x slower (pip install cvxopt)",
                          RuntimeWarning, stacklevel=2)
        return kind
    if kind not in SPARSE_SOLVERS + ("dense",):
        raise ValueError(
            f"linear_solver must be 'auto', 'cholmod', 'cvxopt', 'scipy' or 'dense', got {kind!r}"
        )
    if kind == "cholmod" and not HAVE_CHOLMOD:
        raise ImportError("linear_solver='cholmod' needs scikit-sparse (sksparse.cholmod)")
    if kind == "cvxopt" and not HAVE_CVXOPT:
        raise ImportError("linear_solver='cvxopt' needs cvxopt (pip install cvxopt)")
    return kind


def default_sparse_solver() -> str:
    """The sparse solver "auto" uses: CHOLMOD through scikit-sparse, else through cvxopt,
    else scipy's SuperLU."""
    if HAVE_CHOLMOD:
        return "cholmod"
    return "cvxopt" if HAVE_CVXOPT else "scipy"


def make_linear_solver(kind: str, pattern, n: int, cholmod_mode: str = "supernodal",
                       cholmod_ordering: str = "default", cholmod_openmp: bool = False,
                       cholmod_blas_threads: int | None = 1):
    """The solver ``kind`` for the CSC ``pattern``; the CHOLMOD options apply to "cholmod",
    mode "supernodal" and the orderings "default", "amd", "natural" also to "cvxopt"."""
    if kind == "cholmod":
        return CholmodSolver(pattern, n, cholmod_mode, cholmod_ordering, cholmod_openmp,
                             cholmod_blas_threads)
    if kind == "cvxopt":
        return CvxoptSolver(pattern, n, cholmod_mode, cholmod_ordering)
    return {"dense": DenseSolver, "scipy": ScipySolver}[kind](pattern, n)
