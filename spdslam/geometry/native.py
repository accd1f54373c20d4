"""The compiled kernels (``_kernels.c``): loaded with ctypes, or None.

A namespace (``geometry.native``). ``_kernels.c`` is built with the package where a C
compiler is there (``setup.py``: an optional extension; docs/install.md); it holds the inverse
box factor's and the pose factors' linearisations, a group's whitening, the per-factor JᵀJ and
its sum into H, and the association's medians, each the NumPy code it replaces written per row
(docs/performance.md, section 8, "The box factor compiled"). ``native_kernels()`` gives the
library, or None where it was not built or where ``SPDSLAM_KERNELS=numpy``; the callers then
take their NumPy code. ``compiled_kernels(False)`` turns them off within a block (the tests and
benchmarks that compare the two).
"""

from __future__ import annotations

import contextlib
import ctypes
import importlib.machinery
import importlib.util
import os
from typing import Iterator

import numpy as np

__all__ = ["KERNELS_ENV", "compiled_kernels", "native_kernels", "box_linearize", "gram_upper", "gram_scatter",
           "scatter_add", "pose_prior", "pose_between", "whiten", "segment_medians"]

#: ``numpy``: never use the compiled kernels; ``compiled`` (or unset): use them where built
KERNELS_ENV = "SPDSLAM_KERNELS"

_LIB: list = []  # [the library or None], loaded once
_ENABLED = [True]

_F = ctypes.POINTER(ctypes.c_double)
_I = ctypes.POINTER(ctypes.c_int64)
_U8 = ctypes.POINTER(ctypes.c_uint8)
_N = ctypes.c_int64


def _load():
    """The built ``_kernels`` extension (its file: the Python module it defines is empty) as a
    ctypes library, or None."""
    try:
        spec = importlib.util.find_spec(__name__.rpartition(".")[0] + "._kernels")
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.origin or not spec.origin.endswith(tuple(importlib.machinery.EXTENSION_SUFFIXES)):
        return None
    try:
        lib = ctypes.CDLL(spec.origin)
        lib.box_linearize.argtypes = [_N, _F, _F, _F, _F, _F, _F, _F, _F, _N, _F, _F, _I, _N, ctypes.c_double,
                                      _F, _U8, _F]
        lib.gram_upper.argtypes = [_N, _N, _N, _F, _F, _F, _F]
        lib.scatter_add.argtypes = [_N, _I, _F, _F]
        lib.gram_scatter.argtypes = [_N, _N, _N, _F, _F, _I, _I, _F, _F]
        lib.pose_prior.argtypes = [_N, _F, _F, _F, _F]
        lib.pose_between.argtypes = [_N, _F, _F, _F, _F, _F]
        lib.whiten.argtypes = [_N, _N, _N, _F, _F, _F, _F, _F, _U8, _F]
        lib.segment_medians.argtypes = [_N, _F, _I, _F, _F]
    except (OSError, AttributeError):
        return None
    for f in (lib.box_linearize, lib.gram_upper, lib.scatter_add, lib.gram_scatter, lib.pose_prior, lib.pose_between,
              lib.whiten, lib.segment_medians):
        f.restype = None
    return lib


def _setting() -> str:
    value = os.environ.get(KERNELS_ENV, "").strip().lower()
    if value not in ("", "compiled", "numpy"):
        raise ValueError(f"{KERNELS_ENV} must be 'compiled' or 'numpy', got {value!r}")
    return value or "compiled"


def native_kernels():
    """The compiled kernels (a ``ctypes.CDLL``), or None: not built, turned off by
    ``SPDSLAM_KERNELS=numpy`` (``ValueError`` for another value) or by ``compiled_kernels``."""
    if not _ENABLED[0] or _setting() == "numpy":
        return None
    if not _LIB:
        _LIB.append(_load())
    return _LIB[0]


@contextlib.contextmanager
def compiled_kernels(enabled: bool) -> Iterator[None]:
    """Within the block, the compiled kernels are used where built (True, the default) or
    not at all (False: every caller takes its NumPy code)."""
    before = _ENABLED[0]
    _ENABLED[0] = bool(enabled)
    try:
        yield
    finally:
        _ENABLED[0] = before


def _ptr(a: np.ndarray, kind=_F):
    return a.ctypes.data_as(kind)


def _f64(a) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float64)


def box_linearize(lib, q, P, t, obs, camera, keep, directions, index, min_depth: float):
    """The inverse box factor of n (pose, ellipsoid) rows by the compiled kernel: (r (n, 4),
    J (n, 4, 6 + Q) or None, valid (n,)). ``q`` (n, 7) wxyz_xyz T_wc; ``P`` (n, 3, 3); ``t``
    (n, 3); ``obs`` (n, 4); ``camera``: (fx, fy, cx, cy), each a scalar or (n,); ``keep`` (n,
    4) or None; ``directions`` (L, 12, Q) (``factors._closed_form._directions``) and
    ``index`` (n,) each row's landmark, or None for the residual only."""
    q, P, t, obs = _f64(q), _f64(P), _f64(t), _f64(obs)
    n = len(q)
    cams = [np.asarray(c, dtype=np.float64) for c in camera]
    per_row = any(c.ndim > 0 and c.size > 1 for c in cams)
    cams = [_f64(np.broadcast_to(c, (n,))) if per_row else _f64(c.reshape(1)) for c in cams]
    r = np.empty((n, 4))
    valid = np.empty(n, np.uint8)
    keep = None if keep is None else _f64(keep)
    keep_p = None if keep is None else _ptr(keep)
    if directions is None:
        J, d_p, i_p, Q = None, None, None, 0
    else:
        directions = _f64(directions)
        index = np.ascontiguousarray(index, dtype=np.int64)
        if index.shape != (n,) or (n and not 0 <= int(index.min()) <= int(index.max()) < len(directions)):
            raise ValueError("box_linearize needs one landmark index per row, each among the directions' landmarks")
        Q = directions.shape[2]
        J = np.empty((n, 4, 6 + Q))
        d_p, i_p = _ptr(directions), _ptr(index, _I)
    lib.box_linearize(n, _ptr(q), _ptr(P), _ptr(t), _ptr(obs), *(_ptr(c) for c in cams), 1 if per_row else 0,
                      keep_p, d_p, i_p, Q, float(min_depth), _ptr(r), _ptr(valid, _U8),
                      None if J is None else _ptr(J))
    return r, J, valid.astype(bool)


def gram_upper(lib, J, r):
    """(H (n, D(D+1)/2) the upper triangles of each JᵀJ, row-major; g (n, D) = Jᵀr) of J (n, m,
    D) and r (n, m) by the compiled kernel."""
    J, r = _f64(J), _f64(r)
    n, m, D = J.shape
    H = np.empty((n, D * (D + 1) // 2))
    g = np.empty((n, D))
    lib.gram_upper(n, m, D, _ptr(J), _ptr(r), _ptr(H), _ptr(g))
    return H, g


def scatter_add(lib, slots, values, out: np.ndarray) -> None:
    """``out[slots[i]] += values[i]`` for every i, in order, by the compiled kernel (``out``
    float64 C-contiguous, written in place; every slot < ``out.size``, unchecked)."""
    slots = np.ascontiguousarray(slots, dtype=np.int64).reshape(-1)
    values = _f64(values).reshape(-1)
    if slots.size != values.size or not (out.dtype == np.float64 and out.flags.c_contiguous):
        raise ValueError("scatter_add needs as many slots as values and a C-contiguous float64 output")
    lib.scatter_add(slots.size, _ptr(slots, _I), _ptr(values), _ptr(out))


def gram_scatter(lib, J, r, hslots, gslots, h: np.ndarray, g: np.ndarray) -> None:
    """``gram_upper`` of J (n, m, D) and r (n, m) added into ``h`` at ``hslots`` (n·D(D+1)/2,)
    and into ``g`` at ``gslots`` (n·D,) (``scatter_add``), in one pass by the compiled kernel."""
    J, r = _f64(J), _f64(r)
    n, m, D = J.shape
    hslots = np.ascontiguousarray(hslots, dtype=np.int64).reshape(-1)
    gslots = np.ascontiguousarray(gslots, dtype=np.int64).reshape(-1)
    if (r.shape != (n, m) or hslots.size != n * (D * (D + 1) // 2) or gslots.size != n * D
            or not all(a.dtype == np.float64 and a.flags.c_contiguous for a in (h, g))):
        raise ValueError("gram_scatter needs r (n, m), a slot per JᵀJ entry and Jᵀr entry, C-contiguous float64 sums")
    lib.gram_scatter(n, m, D, _ptr(J), _ptr(r), _ptr(hslots, _I), _ptr(gslots, _I), _ptr(h), _ptr(g))


def pose_prior(lib, T, prior, jacobian: bool = True):
    """The pose prior of n rows (wxyz_xyz (n, 7) each) by the compiled kernel: (r = Log(T̄⁻¹ T)
    (n, 6), J = J_r⁻¹(r) (n, 6, 6) or None)."""
    T, prior = _f64(T), _f64(prior)
    n = len(T)
    r = np.empty((n, 6))
    J = np.empty((n, 6, 6)) if jacobian else None
    lib.pose_prior(n, _ptr(T), _ptr(prior), _ptr(r), None if J is None else _ptr(J))
    return r, J


def pose_between(lib, T1, T2, T12, jacobian: bool = True):
    """The pose between factor of n rows by the compiled kernel: (r = Log(T̄₁₂⁻¹ T₁⁻¹ T₂) (n, 6),
    J = [−J_r⁻¹(r) Ad(D⁻¹), J_r⁻¹(r)] (n, 6, 12) or None)."""
    T1, T2, T12 = _f64(T1), _f64(T2), _f64(T12)
    n = len(T1)
    r = np.empty((n, 6))
    J = np.empty((n, 6, 12)) if jacobian else None
    lib.pose_between(n, _ptr(T1), _ptr(T2), _ptr(T12), _ptr(r), None if J is None else _ptr(J))
    return r, J


def whiten(lib, W, r, J):
    """(W r (n, m), W J (n, m, D) or None, finite (n,): W r and W J all finite, s = ‖W r‖² (n,))
    of r (n, m), J (n, m, D) or None and W (n, m, m) or None (no whitening) by the compiled
    kernel."""
    r = _f64(r)
    n, m = r.shape
    W = None if W is None else _f64(W)
    J = None if J is None else _f64(J)
    if (W is not None and W.shape != (n, m, m)) or (J is not None and J.shape[:2] != (n, m)):
        raise ValueError("whiten needs W (n, m, m) and J (n, m, D) for r (n, m)")
    D = 0 if J is None else J.shape[2]
    r_out = np.empty((n, m))
    J_out = None if J is None else np.empty((n, m, D))
    finite = np.empty(n, np.uint8)
    s = np.empty(n)
    lib.whiten(n, m, D, None if W is None else _ptr(W), _ptr(r), None if J is None else _ptr(J), _ptr(r_out),
               None if J_out is None else _ptr(J_out), _ptr(finite, _U8), _ptr(s))
    return r_out, J_out, finite.astype(bool), s


def segment_medians(lib, v, counts) -> np.ndarray:
    """The median (``np.median``'s) of each of the consecutive segments of the finite values
    ``v`` (sizes ``counts`` (k,)), 0.0 for an empty one, by the compiled kernel (selection,
    not a sort)."""
    v = _f64(v).reshape(-1)
    counts = np.ascontiguousarray(counts, dtype=np.int64).reshape(-1)
    if int(counts.sum()) != v.size or (counts.size and counts.min() < 0) or not np.isfinite(v).all():
        raise ValueError("segment_medians needs finite values, as many as the counts say")
    med = np.empty(counts.size)
    buf = np.empty(max(int(counts.max()), 1) if counts.size else 1)
    lib.segment_medians(counts.size, _ptr(v), _ptr(counts, _I), _ptr(buf), _ptr(med))
    return med
