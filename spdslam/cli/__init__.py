"""The ``spdslam`` command: ``info``, ``simulate``, ``run``, ``localize``, ``merge``, ``check``,
``evaluate``, ``import``, ``export``, ``compare``, ``batch``, ``demo``, ``view``, ``warmup``. The top
layer: it may import every other package."""

import importlib
from typing import TYPE_CHECKING

from ._app import app as app
from ._app import fail as fail

# The commands, registered in the order the help lists them.
for _module in ("_check", "_simulate", "_run", "_evaluate", "_import", "_export", "_batch", "_demo"):
    importlib.import_module(f"{__name__}.{_module}")

from ._demo import DEMO_MARKER as DEMO_MARKER  # noqa: E402  (after the registration)

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
