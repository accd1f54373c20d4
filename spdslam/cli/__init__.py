"""The ``spdslam`` command: ``info``, ``simulate``, ``run``, ``localize``, ``merge``, ``check``,
``evaluate``, ``import``, ``compare``, ``batch``, ``demo``, ``view``, ``warmup``. The top
layer: it may import every other package."""

from typing import TYPE_CHECKING

from . import _check, _sequences, _simulate  # noqa: F401  (register the commands)
from ._app import app as app
from ._app import fail as fail
from ._sequences import DEMO_MARKER as DEMO_MARKER

#: Names of ``spdslam.solver`` this package lends, imported (with JAX) on first use.
_SOLVER_NAMES = ("CACHE_ENV", "cache_dir", "enable_compilation_cache")

if TYPE_CHECKING:
    from ..solver import CACHE_ENV as CACHE_ENV
    from ..solver import cache_dir as cache_dir
    from ..solver import enable_compilation_cache as enable_compilation_cache


def __getattr__(name: str):
    if name in _SOLVER_NAMES:
        from .. import solver

        return getattr(solver, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


if __name__ == "__main__":  # pragma: no cover
    app()
