"""Where independent tasks run: in this process (:class:`LocalEngine`) or on a Ray cluster
(:class:`RayEngine`, the ``ray`` extra).

An engine maps a module-level function over a list of task arguments and returns one
:class:`TaskOutcome` per task, in the tasks' order, whatever order they finished in. A task
that raises, or whose worker dies, is tried again up to ``retries`` times; if every attempt
fails its outcome carries the last error (one line) and the others are unaffected: nothing
is dropped silently. Results do not depend on the engine: a task computes the same thing
wherever it runs (the callers' tests check it).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from typing import Any, Callable, Sequence

__all__ = ["RAY_MISSING", "LocalEngine", "RayEngine", "TaskOutcome", "error_line", "make_engine"]

#: The message when Ray is asked for and not installed.
RAY_MISSING = 'Ray is not installed: pip install -e ".[ray]" (or pip install ray)'


@dataclass(frozen=True)
class TaskOutcome:
    """What became of one task: its ``value``, or the ``error`` of its last attempt
    (``"<ExceptionType>: <message>"`` on one line); ``attempts`` made and the ``seconds``
    the last one took where it ran (the worker's clock, queueing excluded)."""

    index: int
    value: Any = None
    error: str | None = None
    attempts: int = 1
    seconds: float = 0.0
    #: Where the last attempt ran: "local", or the Ray worker's "host:pid".
    where: str = "local"

    @property
    def ok(self) -> bool:
        return self.error is None


def error_line(e: BaseException) -> str:
    """An exception as one line, ``"<Type>: <message>"`` (whitespace runs collapsed; an
    empty message reads "(no message)"): a failed task's or job's error."""
    text = " ".join(str(e).split()) or "(no message)"
    return f"{type(e).__name__}: {text}"


def _attempt(fn: Callable, args: tuple) -> tuple:
    """Run ``fn(*args)`` and report rather than raise: ("ok", value, seconds, where) or
    ("error", message, seconds, where). Runs in the worker."""
    import socket

    where = f"{socket.gethostname()}:{os.getpid()}"
    t0 = time.perf_counter()
    try:
        value = fn(*args)
    except Exception as e:  # noqa: BLE001 - reported to the driver, which decides
        return "error", error_line(e), time.perf_counter() - t0, where
    return "ok", value, time.perf_counter() - t0, where


class _Engine:
    """What every engine has: ``close()`` and use as a context manager."""

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class LocalEngine(_Engine):
    """Tasks one after another in this process."""

    name = "local"

    def __init__(self, retries: int = 0):
        if retries < 0:
            raise ValueError(f"retries must be ≥ 0, got {retries}")
        self.retries = retries
        self.workers = 1

    def map(self, fn: Callable, tasks: Sequence[tuple],
            progress: Callable[[int, int], None] | None = None,
            on_outcome: Callable[[TaskOutcome], None] | None = None) -> list[TaskOutcome]:
        """``fn(*task)`` for every task; ``on_outcome(outcome)`` and ``progress(done, total)``
        after each."""
        out = []
        for i, args in enumerate(tasks):
            for attempt in range(1, self.retries + 2):
                status, value, seconds, _ = _attempt(fn, tuple(args))
                if status == "ok":
                    out.append(TaskOutcome(i, value, None, attempt, seconds))
                    break
            else:
                out.append(TaskOutcome(i, None, value, attempt, seconds))
            if on_outcome:
                on_outcome(out[-1])
            if progress:
                progress(i + 1, len(tasks))
        return out


class RayEngine(_Engine):
    """Tasks on Ray: the cluster at ``address`` (``"auto"``, ``"ray://host:10001"``, …), or,
    without one, a Ray instance started here with ``workers`` CPUs (default: this
    machine's cores) and stopped by :meth:`close`. Each task takes one CPU; a worker process
    runs many tasks, so a program it compiled once serves all its later tasks of the same
    shape. A local instance's workers share this process's JAX compilation cache (when one
    is enabled)."""

    name = "ray"

    def __init__(self, address: str | None = None, workers: int | None = None, retries: int = 1):
        try:
            import ray
        except ImportError:
            raise ImportError(RAY_MISSING) from None
        if retries < 0:
            raise ValueError(f"retries must be ≥ 0, got {retries}")
        if workers is not None and workers < 1:
            raise ValueError(f"workers must be ≥ 1, got {workers}")
        if address is not None and workers is not None:
            raise ValueError("workers sets the size of a local Ray instance: not with an address")
        if address is not None:
            _check_reachable(address)
        self.retries = retries
        self.address = address
        self._ray = ray
        if ray.is_initialized():
            self._owned = False
        elif address is None:
            env = {**_compilation_cache_env(), **_thread_env(local=True)}
            _quiet_init(ray, num_cpus=workers or (os.cpu_count() or 1), include_dashboard=False,
                        log_to_driver=False, logging_level="ERROR",
                        runtime_env={"env_vars": env} if env else None)
            self._owned = True
        else:
            env = _thread_env(local=False)
            _quiet_init(ray, address=address, log_to_driver=False, logging_level="ERROR",
                        runtime_env={"env_vars": env} if env else None)
            self._owned = True
        self.workers = max(1, int(ray.cluster_resources().get("CPU", 1)))
        self._remote = ray.remote(num_cpus=1, max_retries=0)(_attempt)

    def map(self, fn: Callable, tasks: Sequence[tuple],
            progress: Callable[[int, int], None] | None = None,
            on_outcome: Callable[[TaskOutcome], None] | None = None) -> list[TaskOutcome]:
        """``fn(*task)`` for every task on the cluster; ``on_outcome(outcome)`` (in this
        process) and ``progress(done, total)`` as tasks end. ``fn`` must be importable by the
        workers (a module-level function)."""
        ray = self._ray
        fn_ref = ray.put(fn)
        pending = {}  # object ref -> (task index, attempt)
        for i, args in enumerate(tasks):
            pending[self._remote.remote(fn_ref, tuple(args))] = (i, 1)
        out: dict[int, TaskOutcome] = {}
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            ref = ready[0]
            i, attempt = pending.pop(ref)
            try:
                status, value, seconds, where = ray.get(ref)
            except Exception as e:  # noqa: BLE001 - the worker died, the task was cancelled, …
                status, value, seconds, where = "error", error_line(e), 0.0, "ray"
            if status == "error" and attempt <= self.retries:
                pending[self._remote.remote(fn_ref, tuple(tasks[i]))] = (i, attempt + 1)
                continue
            out[i] = TaskOutcome(i, value if status == "ok" else None,
                                 value if status == "error" else None, attempt, seconds, where)
            if on_outcome:
                on_outcome(out[i])
            if progress:
                progress(len(out), len(tasks))
        return [out[i] for i in range(len(tasks))]

    def close(self) -> None:
        """Stop the Ray instance this engine started (a cluster keeps running)."""
        if self._owned and self._ray.is_initialized():
            self._ray.shutdown()
        self._owned = False


def _check_reachable(address: str, timeout: float = 5.0) -> None:
    """``ConnectionError`` (one line) when the HOST:PORT of ``address`` ("HOST:PORT" or
    "ray://HOST:PORT"; "auto" is left to Ray) does not accept a TCP connection within
    ``timeout`` seconds: Ray itself would retry for minutes."""
    import socket

    if address == "auto":
        return
    hostport = address.split("://", 1)[1] if "://" in address else address
    host, sep, port = hostport.rpartition(":")
    if not sep or not host or not port.isdigit():
        raise ValueError(f"expected auto, HOST:PORT or ray://HOST:PORT, got {address!r}")
    try:
        socket.create_connection((host, int(port)), timeout=timeout).close()
    except OSError as e:
        raise ConnectionError(f"nothing answers at {host}:{port} ({e.strerror or e}) within "
                              f"{timeout:g} s") from None


def _quiet_init(ray, **kwargs) -> None:
    """``ray.init`` without JAX's warning about ``os.fork``: Ray starts its processes with
    fork + exec (subprocess), which runs no JAX code in the child."""
    import warnings

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)
        ray.init(**kwargs)


def _thread_env(local: bool) -> dict:
    """``OMP_NUM_THREADS`` for the workers: this process's. Ray sets it to a task's CPUs (1)
    where it is unset, and a thread count changes the order of a BLAS or OpenMP library's sums:
    maps then differ from the run without Ray in the last bits. A local instance's workers
    get this process's value or, where unset, the cores (what those libraries use then); a
    cluster's get this process's value only when it is set."""
    value = os.environ.get("OMP_NUM_THREADS")
    if value is None and local:
        value = str(os.cpu_count() or 1)
    return {} if value is None else {"OMP_NUM_THREADS": value}


def _compilation_cache_env() -> dict:
    """The JAX compilation-cache settings of this process as environment variables, for
    the workers of a local instance (they read them when JAX starts)."""
    import jax

    d = jax.config.jax_compilation_cache_dir  # type: ignore[attr-defined]  # JAX's options are dynamic
    if not d:
        return {}
    return {"JAX_COMPILATION_CACHE_DIR": str(d),
            "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS":
                str(jax.config.jax_persistent_cache_min_compile_time_secs)}  # type: ignore[attr-defined]


def make_engine(ray: str | None, workers: int | None = None, retries: int = 1):
    """The engine of a command line: None → :class:`LocalEngine`; ``"local"`` → a Ray
    instance started here (``workers`` CPUs); anything else → the Ray cluster at that
    address."""
    if ray is None:
        return LocalEngine(retries=retries)
    return RayEngine(None if ray == "local" else ray, workers if ray == "local" else None,
                     retries=retries)
