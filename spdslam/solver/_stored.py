"""Compiled programs kept on disk between processes (docs/performance.md, "Compilation").

JAX's persistent compilation cache (``_cache``) saves XLA's compilation, but every new
process still traces and lowers each program, and for the solver's linearisations (forward-
mode Jacobians, vmapped and chunked) that is most of a warm run's first optimisation. A
*stored* program skips both: its executable is compiled once, serialised under a key of
everything that decides it, and loaded by later processes:

    key = H(the source of spdslam's geometry, factors, solver and the front end's
            initialisation, the jax, jaxlib and jaxlie versions, backend, device, CPU
            flags, the program's name and static
            description, its arguments' shapes and dtypes)

Only programs made of the code of those packages are stored (a residual defined elsewhere is
traced as usual, since its code is not in the key); an edit elsewhere (the association,
mapping, io, the command line) keeps the stored programs. The executable is compiled
without the persistent cache: an executable that JAX's persistent cache served cannot be serialised
(it lacks its machine code; a later process that ran it would fail). A build therefore
compiles with an option that does nothing on its backend (``_mark``: a GPU flag on the CPU)
but gives it its own cache key, with the cache's writes held off, so that the cache neither
serves nor keeps it; should the cache serve it all the same (``jax.monitoring``'s cache-hit
event during the compile), it is used in this process and not stored. Before an executable
is loaded the LAPACK kernels it may call are registered (JAX does so only when it lowers a
program that uses them; a loaded executable calling them unregistered crashes the
process). A stored executable that fails to load or to run is deleted and the program
traced as usual; one whose first run did not end (a marker file left beside it by a
process that is gone) is deleted too. The store lives in ``cache_dir()/programs``, one
compressed file per program (nothing else removes them: ``rm -r`` the folder to clear it);
``SPDSLAM_CACHE_DIR=off`` turns it off with the cache.
"""

from __future__ import annotations

import hashlib
import os
import pickle
import platform
import tempfile
import threading
import zlib
from pathlib import Path
from typing import Any, Callable

import jax
import numpy as np

from ._cache import CACHE_ENV, CACHE_OFF, cache_dir

__all__ = ["StoredProgram", "stored_jit", "own_code", "store_dir"]

_LOCK = threading.Lock()
_ENV: list = []  # the environment's part of every key, computed once


def store_dir() -> Path | None:
    """The directory of stored programs, or None when the cache is off."""
    if os.environ.get(CACHE_ENV, "").strip().lower() in CACHE_OFF:
        return None
    return cache_dir() / "programs"


#: The modules whose code stored programs may be made of (their source is in every key).
MODULES = ("geometry", "factors", "solver", "frontend._initialization")


def _environment() -> str:
    """The source of ``MODULES``, the versions, backend, device and CPU flags, hashed."""
    if not _ENV:
        h = hashlib.sha256()
        root = Path(__file__).resolve().parents[1]
        files = [root / (name.replace(".", "/") + ".py") for name in MODULES if "." in name]
        files += [p for name in MODULES if "." not in name for p in (root / name).rglob("*.py")]
        for path in sorted(files):
            h.update(str(path.relative_to(root)).encode())
            h.update(path.read_bytes())
        dev = jax.devices()[0]
        from importlib.metadata import version

        h.update(repr((jax.__version__, getattr(jax.lib, "__version__", ""), version("jaxlie"), jax.default_backend(),
                       dev.device_kind, getattr(dev.client, "platform_version", ""), platform.machine(),
                       bool(jax.config.jax_enable_x64))).encode())  # type: ignore[attr-defined]
        try:  # the CPU's instruction sets (an executable may use any of them)
            with open("/proc/cpuinfo", encoding="utf-8") as f:
                h.update(next((ln for ln in f if ln.startswith("flags")), "").encode())
        except OSError:
            pass
        _ENV.append(h.hexdigest())
    return _ENV[0]


def own_code(*fns) -> bool:
    """Whether every function or class in ``fns`` (None allowed) is defined at module level
    in ``MODULES``, without captured variables: code that the key's source hash covers."""
    for fn in fns:
        if fn is None:
            continue
        mod = getattr(fn, "__module__", "") or ""
        qual = getattr(fn, "__qualname__", "") or ""
        ours = any(mod == f"spdslam.{m}" or mod.startswith(f"spdslam.{m}.") for m in MODULES)
        if (not ours or "<locals>" in qual or "<lambda>" in qual
                or getattr(fn, "__closure__", None)):
            return False
    return True


def _signature(args) -> tuple:
    leaves, td = jax.tree.flatten(args)
    return td, tuple((np.shape(a), str(a.dtype if hasattr(a, "dtype") else np.result_type(a))) for a in leaves)


def _mark() -> dict:
    """A compiler option without effect on this backend (module docstring)."""
    if jax.default_backend() == "cpu":
        return {"xla_gpu_enable_triton_gemm": False}
    return {"xla_cpu_enable_fast_math": False}


class _FreshCompile:
    """The compiles in its ``with`` block are not written to JAX's persistent cache, and
    ``served`` says whether the cache served one (one block at a time: the counter is
    global)."""

    hits = 0
    _listening = False

    @classmethod
    def _listen(cls, event: str, **kwargs) -> None:
        if event == "/jax/compilation_cache/cache_hits":
            cls.hits += 1

    def __enter__(self):
        _LOCK.acquire()
        if not _FreshCompile._listening:
            jax.monitoring.register_event_listener(_FreshCompile._listen)
            _FreshCompile._listening = True
        self.before = _FreshCompile.hits
        self.was = jax.config.jax_persistent_cache_min_compile_time_secs  # type: ignore[attr-defined]
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 1e12)
        return self

    def __exit__(self, *exc):
        jax.config.update("jax_persistent_cache_min_compile_time_secs", self.was)
        self.served = _FreshCompile.hits > self.before
        _LOCK.release()


class StoredProgram:
    """``jax.jit(fn)`` whose executables are stored on disk under ``key`` (module
    docstring); ``key`` None: plain ``jax.jit``. Call it as the jitted function."""

    def __init__(self, fn: Callable, key: str | None):
        self.jitted = jax.jit(fn, keep_unused=True)  # a stored executable takes every argument
        self.__name__ = self.__qualname__ = getattr(fn, "__name__", "program")
        self.key = key
        self._executables: dict = {}
        self._checked: set = set()

    def __call__(self, *args):
        folder = None if self.key is None else store_dir()
        if folder is None:
            return self.jitted(*args)
        sig = _signature(args)
        ex = self._executables.get(sig)
        if ex is None:
            ex = self._executables[sig] = self._load_or_build(folder, sig, args)
        if ex is False:
            return self.jitted(*args)
        if sig in self._checked:
            return ex(*args)
        path = self._path(folder, sig)
        marker = path.with_suffix(f".{os.getpid()}.trying")
        try:  # a stored executable's first call is checked to its end
            marker.touch()
            out = jax.block_until_ready(ex(*args))
        except Exception:  # noqa: BLE001 - a bad stored program is replaced by tracing
            self._executables[sig] = False
            path.unlink(missing_ok=True)
            return self.jitted(*args)
        finally:
            marker.unlink(missing_ok=True)
        self._checked.add(sig)
        return out

    def _path(self, folder: Path, sig) -> Path:
        digest = hashlib.sha256(repr((_environment(), self.key, sig)).encode()).hexdigest()
        return folder / f"{digest}.bin"

    def _load_or_build(self, folder: Path, sig, args) -> Any:
        from jax.experimental import serialize_executable as se

        path = self._path(folder, sig)
        if _crashed(path):  # its first run in another process never ended
            path.unlink(missing_ok=True)
        if path.is_file():
            try:
                _register_kernels()
                payload, in_tree, out_tree = pickle.loads(zlib.decompress(path.read_bytes()))
                return se.deserialize_and_load(payload, in_tree, out_tree)
            except Exception:  # noqa: BLE001 - unreadable: rebuilt below
                path.unlink(missing_ok=True)
        try:
            with _FreshCompile() as cache:
                compiled = self.jitted.lower(*args).compile(_mark())
            if cache.served:  # not serialisable: used here only
                self._checked.add(sig)
                return compiled
            data = zlib.compress(pickle.dumps(se.serialize(compiled)), 1)  # about a quarter the size
        except Exception:  # noqa: BLE001 - not serialisable here: the plain jit serves
            return False
        try:
            folder.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=folder, suffix=".tmp")
            with os.fdopen(fd, "wb") as f:
                f.write(data)
            os.replace(tmp, path)
        except OSError:
            pass
        self._checked.add(sig)  # compiled here: nothing to check
        return compiled


def _crashed(path: Path) -> bool:
    """Whether a process that ran ``path``'s executable for the first time ended in it: a
    marker ``NAME.PID.trying`` of a process that no longer runs (removed here). A process
    still running it (another one mapping now) is no sign of a crash."""
    crashed = False
    for marker in path.parent.glob(path.stem + ".*.trying"):
        try:
            os.kill(int(marker.suffixes[-2][1:]), 0)
        except (ValueError, IndexError, ProcessLookupError):
            crashed = True
            marker.unlink(missing_ok=True)
        except OSError:  # alive, another user's
            pass
    return crashed


def _register_kernels() -> None:
    """Register jaxlib's LAPACK kernels, which a loaded executable may call."""
    if not _REGISTERED:
        from jaxlib import lapack

        lapack.prepare_lapack_call("getrf_ffi", np.dtype("float64"))
        _REGISTERED.append(True)


_REGISTERED: list = []


def stored_jit(fn: Callable, key: str | None) -> StoredProgram:
    """A ``StoredProgram`` of ``fn`` under ``key`` (None: not stored)."""
    return StoredProgram(fn, key)
