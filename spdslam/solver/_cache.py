"""JAX's persistent compilation cache, as spdslam turns it on (the CLI and ``OnlineMapper``).

The cache stores each compiled XLA program on disk under a key that JAX computes from the
program itself (its StableHLO), the compile options, the jax and jaxlib versions and the
backend; a changed spdslam (a different program), a new JAX or another machine's backend
therefore never load a stale entry: it misses and compiles. Tracing and lowering still run in
each process; what the cache saves is XLA's compilation (docs/performance.md, "Compilation").
It lives in ``solver``, the lowest layer that compiles; ``spdslam.solver`` exports it.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["CACHE_ENV", "CACHE_MIN_COMPILE_SECS", "CACHE_OFF", "DEFAULT_CACHE_DIR", "cache_dir",
           "enable_compilation_cache", "ensure_compilation_cache"]

#: Environment variable naming the JAX compilation-cache directory; ``off`` turns it off.
CACHE_ENV = "SPDSLAM_CACHE_DIR"
#: Values of :data:`CACHE_ENV` that turn the persistent cache off.
CACHE_OFF = ("off", "0", "none", "false")
#: Default JAX compilation-cache directory.
DEFAULT_CACHE_DIR = Path("~/.cache/spdslam/jax")
#: Only compilations that took at least this long are written to the persistent cache: all of
#: them, since loading a small one (~1 ms) is still cheaper than compiling it (5–40 ms).
CACHE_MIN_COMPILE_SECS = 0.0


def cache_dir() -> Path:
    """The configured JAX compilation-cache directory (not necessarily existing)."""
    raw = os.environ.get(CACHE_ENV) or str(DEFAULT_CACHE_DIR)
    return Path(raw).expanduser()


def enable_compilation_cache(path: Path | None = None) -> Path | None:
    """Turn on JAX's persistent compilation cache in ``path`` (default :func:`cache_dir`).

    Returns the directory used, or ``None`` when it is turned off (``SPDSLAM_CACHE_DIR=off``)
    or could not be created or configured; never raises.
    """
    if path is None:
        if os.environ.get(CACHE_ENV, "").strip().lower() in CACHE_OFF:
            return None
        path = cache_dir()
    path = Path(path).expanduser()
    try:
        path.mkdir(parents=True, exist_ok=True)
        if not os.access(path, os.W_OK):
            return None
    except OSError:
        return None
    try:
        import jax

        jax.config.update("jax_compilation_cache_dir", str(path))
        jax.config.update("jax_persistent_cache_min_compile_time_secs", CACHE_MIN_COMPILE_SECS)
    except Exception:  # noqa: BLE001 - the cache is an optimisation, never fatal
        return None
    return path


def ensure_compilation_cache() -> Path | None:
    """The cache directory JAX already uses (set by the caller or an earlier call), else
    :func:`enable_compilation_cache`'s default: a library entry point turns the cache on
    without overriding a directory its caller chose."""
    try:
        import jax

        current = jax.config.jax_compilation_cache_dir  # type: ignore[attr-defined]  # a dynamic option
    except Exception:  # noqa: BLE001
        return None
    return Path(current) if current else enable_compilation_cache()
