"""The batched solver's compiled programs: XLA options, caches and explicit compilation.

Programs are jitted per structure (``_batched_loop``) and compiled explicitly for their
argument shapes, so that the trace and XLA compile times can be reported
(``BatchedResult.timings``) and a program can be compiled ahead (``BatchedProblem.compile``).
On CPU the programs are compiled without XLA's newer fusion emitters and, with
``optimize=False``, without LLVM optimisation: a shorter compile for slower loops (the
figures are in docs/performance.md). ``clear_caches`` drops every compiled program of the
solver, the sparse host solver's kernels (``_problem``) included.
"""

from __future__ import annotations

import time
from typing import Any

import jax
import numpy as np

from . import _problem

__all__ = ["clear_caches", "COMPILER_OPTIONS", "FAST_COMPILE_OPTIONS", "AUTO_OPTIMIZE_WORK",
           "JITTED_PROGRAMS", "BUILT_SOLVERS", "shape_signature",
           "compiled_executable", "call_compiled"]

#: XLA options of the batched programs on CPU: without the newer fusion emitters, which
#: lengthen the compile of these small-array programs and do not speed them up.
COMPILER_OPTIONS: dict[str, Any] = {"xla_cpu_use_fusion_emitters": False}
#: Added when a program is compiled for speed of compilation rather than of execution
#: (``optimize=False``): no LLVM optimisation.
FAST_COMPILE_OPTIONS: dict[str, Any] = {"xla_backend_optimization_level": 0}
#: ``optimize=None`` (auto) optimises the compiled code when B · max_iterations exceeds
#: this: the work at which the longer compile pays for itself (docs/performance.md).
AUTO_OPTIMIZE_WORK = 100_000

#: The jitted batched programs (lane loops and costs) by their cache key
#: (``_batched_loop.solver_fn``, ``cost_fn``).
JITTED_PROGRAMS: dict[Any, Any] = {}
_EXECUTABLES: dict[Any, Any] = {}
#: The solver programs built so far, (key, program, lanes, max_iterations, optimize) by
#: (structure, batching pattern, input shapes): ``BatchedProblem.cost`` reuses them.
BUILT_SOLVERS: dict[Any, Any] = {}


def clear_caches() -> None:
    """Drop every compiled solver program: the sparse solver's kernels per structure, the
    batched solver's programs and executables, and JAX's own caches (``jax.clear_caches``).

    Each new graph structure compiles programs that are kept for reuse; a process that maps
    many different structures (a sweep over sequences, a test suite) can call this between
    them, so that their machine code is released (XLA maps each compiled program into
    memory, and a process may hold only ``vm.max_map_count`` mappings)."""
    _problem._KERNELS.clear()
    _problem._GROUP_KERNELS.clear()
    _problem._RETRACT.clear()
    _problem._RESIDUAL_DIM.clear()
    JITTED_PROGRAMS.clear()
    _EXECUTABLES.clear()
    BUILT_SOLVERS.clear()
    jax.clear_caches()


def shape_signature(tree):
    """(tree structure, (shape, dtype) of each leaf) of a pytree of arguments: what a
    compiled executable is specialised to, hashable."""
    leaves, td = jax.tree.flatten(tree)
    return td, tuple((np.shape(a), a.dtype if hasattr(a, "dtype") else np.result_type(a))
                     for a in leaves)


def compiled_executable(key, fn, args, timings: dict | None = None, optimize: bool = True):
    """The explicitly lowered and compiled executable of the jitted ``fn`` for ``args``
    (cached on ``key``, ``optimize`` and the argument shapes), recording "trace" (tracing
    and lowering) and "compile" (XLA) seconds in ``timings`` when it is built."""
    sig = (key, optimize, shape_signature(args))
    ex = _EXECUTABLES.get(sig)
    if ex is None:
        t0 = time.perf_counter()
        low = fn.lower(*args)
        t1 = time.perf_counter()
        opts = {}
        if jax.default_backend() == "cpu":
            opts = dict(COMPILER_OPTIONS, **({} if optimize else FAST_COMPILE_OPTIONS))
        ex = _EXECUTABLES[sig] = low.compile(opts) if opts else low.compile()
        if timings is not None:
            timings["trace"] = t1 - t0
            timings["compile"] = time.perf_counter() - t1
    elif timings is not None:
        timings["trace"] = timings["compile"] = 0.0
    return ex


def call_compiled(key, fn, args, timings: dict | None = None, optimize: bool = True):
    """Call the jitted ``fn`` through its compiled executable (``compiled_executable``)."""
    return compiled_executable(key, fn, args, timings, optimize)(*args)

