"""The ``spdslam`` typer application, its conventions and the ``info`` command.

A single typer application, :data:`app`. Commands are plain functions registered with
``@app.command()`` in the modules of this package (``_app``: ``info``; ``_simulate``:
``simulate``; ``_check``: ``check``; ``_run``: ``run``, ``localize``, ``merge``; ``_evaluate``:
``evaluate``; ``_import``: ``import``; ``_batch``: ``compare``, ``batch``; ``_demo``: ``demo``,
``view``, ``warmup``; ``_common``: what the sequence commands share).
Conventions:

* bad user input -> :func:`fail` (one line on stderr, exit status 2);
* heavy imports (solver, factors, mapping, io, matplotlib, ...) go *inside* the command
  function, and what the help shows of them comes from ``_help.FACTS``, so that ``spdslam
  --help``, ``spdslam COMMAND --help`` and ``spdslam --version`` import neither JAX nor
  SciPy (tests/test_cli.py checks it);
* rich output goes through :data:`console` (stdout) / :data:`err_console` (stderr).

When a command runs (not when its help is shown), :func:`start` first enables JAX's
persistent compilation cache in ``$SPDSLAM_CACHE_DIR`` (default ``~/.cache/spdslam/jax``) so
that repeated runs skip most of the XLA compilation time: :data:`app` wraps every command it
registers so.
"""

from __future__ import annotations

import contextlib
import functools
import gc
import os
import platform
import sys
from importlib import metadata
from pathlib import Path
from typing import Any, NoReturn

import typer
from rich.console import Console
from rich.table import Table

from .._version import __version__

#: Set by :func:`start`: the cache directory in use, or ``None`` if the cache is off.
_cache_dir_in_use: Path | None = None


def start() -> None:
    """What every command does before its body (its help, given before, does not): import the
    solver (JAX) with the garbage collector paused, then freeze what the imports made out of
    its full passes (``gc.freeze``); keep large freed blocks for reuse
    (``solver.retain_freed_memory``); turn on JAX's persistent compilation cache
    (``solver.enable_compilation_cache``)."""
    global _cache_dir_in_use
    gc.collect()  # the garbage so far (a process that runs commands in turn: a test) is not frozen
    with collector_paused():  # the imports make some 120 000 objects that live as long as the
        from ..solver import enable_compilation_cache, retain_freed_memory  # process: no full
    # collection traverses them while they arrive (four did: 0.25 s), nor after
    # (docs/performance.md, section 8, "The collector in a batch run")

    from ..geometry import native

    try:
        retain_freed_memory()
        native.native_kernels()  # SPDSLAM_KERNELS checked before any work
    except ValueError as e:
        fail(str(e))
    _cache_dir_in_use = enable_compilation_cache()


@contextlib.contextmanager
def collector_paused():
    """Python's garbage collector off within the block, and what exists at its end frozen out
    of its full passes (``gc.freeze``: never traversed again, still freed when unreferenced);
    the collector then as it was before."""
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        gc.freeze()
        if was:
            gc.enable()


class _Typer(typer.Typer):
    """A typer application whose commands call :func:`start` when they run: in the app
    callback it would run (and import JAX) for ``spdslam COMMAND --help`` too, since click
    calls a group's callback before it parses the command's options."""

    def command(self, *args: Any, **kwargs: Any):
        register = super().command(*args, **kwargs)

        def decorator(f):
            @functools.wraps(f)  # typer reads the signature and type hints through __wrapped__
            def started(*a, **k):
                start()
                return f(*a, **k)

            register(started)
            return f

        return decorator


app = _Typer(
    name="spdslam",
    help="Object-level SLAM back end: ellipsoid landmarks on SPD(3) x R^3.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_show_locals=False,
)

console = Console()
err_console = Console(stderr=True)


# --------------------------------------------------------------------------- helpers


def fail(message: str, code: int = 2) -> NoReturn:
    """Report a bad-input error as one line on stderr and exit with ``code`` (default 2).

    Plain ``typer.echo`` rather than rich, so long messages are never wrapped.
    """
    text = " ".join(str(message).split())  # guarantee a single line
    typer.echo(f"spdslam: error: {text}", err=True)
    raise typer.Exit(code)


#: Help of the engine options shared by simulate, compare and batch.
RAY_HELP = ("Run the tasks on Ray (the ray extra), by default on a local Ray instance with "
            "--workers CPUs. Results are those of the run without --ray.")
RAY_ADDRESS_HELP = ("Run the tasks on the Ray cluster at this address (auto, ray://HOST:10001, "
                    "...); implies --ray.")
WORKERS_HELP = "CPUs of the local Ray instance (--ray without --ray-address; default: all cores)."
RETRIES_HELP = "Attempts more for a task that fails or whose worker dies (then it is reported)."


def open_engine(ray: bool, address: str | None, workers: int | None, retries: int):
    """The engine the options ask for (``experiments.make_engine``: in this process without
    --ray), or a one-line error."""
    from ..experiments import make_engine

    if address is not None and not address.strip():
        fail("--ray-address: expected an address (auto, ray://HOST:10001, ...), got an empty string")
    choice = address if address is not None else ("local" if ray else None)
    if workers is not None and choice != "local":
        fail("--workers: sets the CPUs of a local Ray instance: expected --ray without --ray-address")
    try:
        return make_engine(choice, workers, retries)
    except ImportError as e:
        fail(str(e))
    except Exception as e:  # noqa: BLE001 - Ray's errors when a cluster cannot be reached
        where = "a local Ray instance" if choice == "local" else f"the Ray cluster at {choice}"
        fail(f"--ray: cannot start or reach {where}: {type(e).__name__}: {e}")


def check_output(out: Path, inputs=(), option: str = "--out") -> None:
    """Refuse, before anything is read or written, an output folder that is one of the
    ``inputs``, lies inside one or contains one (``--overwrite`` would delete it), or that
    cannot be written: the nearest existing folder above it (and above its parent, where
    atomic writes make their temporary folder) must let a folder be made (probed, then
    removed)."""
    import tempfile

    def resolved(p: Path, what: str) -> Path:
        try:
            return Path(os.path.abspath(p)).resolve()
        except (RuntimeError, OSError):  # Python 3.11 raises RuntimeError on a link loop
            fail(f"{what}: {p}: expected a path, got a symbolic-link loop")

    o = resolved(out, option)
    for src in inputs:
        s = resolved(src, str(src))
        if o == s:
            fail(f"{option}: {out} is the input {src}: expected an output folder apart from it")
        if s in o.parents:
            fail(f"{option}: {out} lies inside the input {src}: expected an output folder apart from it")
        if o in s.parents:
            fail(f"{option}: {out} contains the input {src}: expected an output folder apart from it")
    for start in {o, o.parent}:
        anc = start
        while not os.path.lexists(anc) and anc != anc.parent:
            anc = anc.parent
        if not anc.is_dir():
            fail(f"{option}: {out}: expected a path under a folder, got {anc}, which is not a folder")
        try:
            os.rmdir(tempfile.mkdtemp(prefix=".spdslam-probe-", dir=anc))
        except OSError as e:
            fail(f"{option}: cannot write {out}: {anc} does not let a folder be made ({e.strerror or e})")


def cholmod_available() -> bool:
    """Whether scikit-sparse's CHOLMOD bindings import."""
    try:
        import sksparse.cholmod  # noqa: F401
    except Exception:  # noqa: BLE001 - ImportError or a broken shared library
        return False
    return True


def kernels_name() -> str:
    """Which code linearises the box factors (``geometry.native``): the compiled kernels or
    NumPy, and why NumPy."""
    from ..geometry import native

    if native.native_kernels() is not None:
        return "compiled (geometry/_kernels.c)"
    if os.environ.get(native.KERNELS_ENV, "").strip().lower() == "numpy":
        return f"off ({native.KERNELS_ENV}=numpy): NumPy"
    return "not built (no C compiler at install): NumPy"


def sparse_solver_name() -> str:
    """Human-readable name of the sparse linear solver the optimiser will use (as the
    solver itself decides: ``spdslam.solver.default_sparse_solver``)."""
    from ..solver import default_sparse_solver

    return {
        "cholmod": f"cholmod: CHOLMOD (scikit-sparse {_dist_version('scikit-sparse')})",
        "cvxopt": f"cvxopt: CHOLMOD bundled with cvxopt {_dist_version('cvxopt')}"
                  " (install scikit-sparse for thread and METIS options)",
        "scipy": "scipy: SuperLU (slow: neither scikit-sparse nor cvxopt imports)",
    }[default_sparse_solver()]


def _dist_version(name: str) -> str:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return "not installed"


def _version_callback(value: bool) -> None:
    if value:
        typer.echo(__version__)
        raise typer.Exit(0)


# --------------------------------------------------------------------------- app callback


@app.callback()
def main(
    version: bool = typer.Option(
        False,
        "--version",
        "-V",
        help="Print the spdslam version and exit.",
        callback=_version_callback,
        is_eager=True,
    ),
) -> None:
    """Object-level SLAM back end: ellipsoid landmarks on SPD(3) x R^3."""


# --------------------------------------------------------------------------- commands


@app.command()
def info() -> None:
    """Print versions, the sparse solver in use and the JAX backend."""
    import jax

    import spdslam  # noqa: F401 - enables float64 as a side effect

    versions = Table(title="spdslam environment", show_header=True, header_style="bold")
    versions.add_column("component")
    versions.add_column("value")
    versions.add_row("python", f"{platform.python_version()} ({sys.executable})")
    versions.add_row("spdslam", __version__)
    for dist in ("jax", "jaxlib", "jaxlie", "numpy", "scipy", "cvxopt", "ray"):
        versions.add_row(dist, _dist_version(dist))
    has_cholmod = cholmod_available()
    versions.add_row(
        "cholmod",
        f"available (scikit-sparse {_dist_version('scikit-sparse')})"
        if has_cholmod
        else "not available",
    )
    versions.add_row("sparse solver", sparse_solver_name())
    versions.add_row("compiled kernels", kernels_name())
    try:
        backend = jax.default_backend()
        devices = ", ".join(str(d) for d in jax.devices())
    except Exception as exc:  # noqa: BLE001
        backend, devices = "unavailable", f"error: {exc}"
    versions.add_row("jax backend", backend)
    versions.add_row("jax devices", devices)
    x64 = jax.config.jax_enable_x64  # type: ignore[attr-defined]  # JAX's options are dynamic
    versions.add_row("float64 (jax_enable_x64)", "enabled" if x64 else "DISABLED")
    versions.add_row(
        "compilation cache",
        str(_cache_dir_in_use) if _cache_dir_in_use is not None else "off",
    )
    console.print(versions)
